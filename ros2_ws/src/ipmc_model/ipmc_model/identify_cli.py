"""``ipmc identify`` and ``ipmc evaluate``: identify a model from a record, score it on another.

Records are ``t,u,y`` CSV files (s, V, mm) or rosbag2 folders, read by
``ipmc_driver.dataio.load_record``. Every printed error says whether it is one-step or
free-run; free runs start from the first ``max_lag`` measured samples, which are skipped.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import sys
from pathlib import Path

import numpy as np

from ipmc_driver.dataio import add_allow_implausible, load_record, print_notes, write_atomic
from ipmc_driver.validation import check_output_dir, check_output_file

from .effects import (
    AugmentedInverse,
    AugmentedModel,
    check_rate,
    load_any_model,
    load_augmented,
    save_augmented,
)
from .excitation import input_kind
from .hysteresis import GeneralizedPI, GpiInverse
from .metrics import score
from .narx import PAPER_C, PAPER_SIGMA, InverseNarxModel, NarxModel
from .persistence import check_model_output, save_model
from .play import PrandtlIshlinskii
from .selection import FAMILIES, compare_families, record_limits, unlike_identification
from .tuning import (
    DEFAULT_CYCLES,
    DEFAULT_LAG_STEPS,
    DEFAULT_MAX_EXACT,
    DEFAULT_SOURCES,
    identify_lssvm_narx,
)

#: ``ipmc identify`` defaults for lssvm-narx, measured on the simulated rig (docs/models.md):
#: 6/6 lags with the spacing searched, 4-fold blocked free-run validation, 500 prototypes.
#: The paper's structure is ``--input-lags 3 --output-lags 3 --lag-step 1 --folds 1``.
DEFAULT_LAGS, DEFAULT_FOLDS, DEFAULT_PROTOTYPES = 6, 4, 500
#: Past voltages of the inverse model by default: with u_{l-1} among the regressors the 100 Hz
#: inverse learns u_l ~ u_{l-1} and its free run drifts (about 1 V RMSE on the rig); without
#: voltage feedback (m = 0) it is a nonlinear FIR in the displacement (docs/models.md).
DEFAULT_INVERSE_INPUT_LAGS = 0
#: Lags of a forward model with voltage channels (--input-memory-taus) by default: none, the
#: NFIR in the low-passed voltages that inverts smoothly (docs/control.md, "Feedforward from
#: the forward model").
DEFAULT_CHANNEL_LAGS = 0
#: What an lssvm-narx option not given on the command line is: forward, the ABC-tuned model of
#: the paper; inverse (--inverse), the recipe of docs/control.md (no past voltages, 10
#: displacement lags 20 ms apart, a memory channel at 1 s: the back-relaxation's inverse), which
#: tracks better in hybrid than the ABC-tuned inverse (docs/control.md).
NARX_DEFAULTS = {"tune": "abc", "C": PAPER_C, "sigma": PAPER_SIGMA, "input_lags": DEFAULT_LAGS,
                 "output_lags": DEFAULT_LAGS,
                 "prototypes": DEFAULT_PROTOTYPES, "memory_taus": ()}
NARX_INVERSE_DEFAULTS = {"tune": "none", "C": 1e4, "sigma": 2.0,
                         "input_lags": DEFAULT_INVERSE_INPUT_LAGS,
                         "output_lags": 10, "lag_step": 2, "prototypes": 800,
                         "memory_taus": (1.0,)}
#: A forward model on voltage channels (--input-memory-taus): C and sigma of docs/control.md,
#: whose online inversion tracks better than the ABC-tuned pair (sine 0.0123 vs 0.0150 mm).
NARX_CHANNEL_DEFAULTS = {"tune": "none", "C": 1e6, "sigma": 1.0, "prototypes": 800,
                         "memory_taus": ()}
#: Validation samples scored per block (100 s at 100 Hz).
MAX_VAL_SAMPLES = 10000


def _load(path: str, prog: str, allow_implausible: bool):
    """The record of ``--data``, its plausibility warnings printed."""
    notes: list[str] = []
    rec = load_record(path, allow_implausible=allow_implausible, notes=notes)
    print_notes(prog, notes)
    return rec


def _budget(text: str) -> tuple[int, int]:
    try:
        s, c = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"budget must look like SOURCESxCYCLES (e.g. 10x10, paper 100x100), got {text!r}"
        ) from None
    if s < 2 or c < 1:
        raise argparse.ArgumentTypeError(f"budget needs >= 2 sources and >= 1 cycle: {text!r}")
    return s, c


def _memory_taus(text: str) -> tuple[float, ...]:
    try:
        taus = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"memory taus must be a comma list of time constants in seconds, got {text!r}"
        ) from None
    if not taus or not all(math.isfinite(v) and v > 0 for v in taus):
        raise argparse.ArgumentTypeError(f"memory taus must be positive seconds, got {text!r}")
    return taus


def taus_list(values) -> tuple[float, ...]:
    """--input-memory-taus TAU [TAU ..] (each token parsed by _memory_taus: a comma list);
    () when the option was not given."""
    return tuple(t for v in values or () for t in v)


def add_input_memory_taus(p: argparse.ArgumentParser, help_text: str) -> None:
    """The ``--input-memory-taus TAU [TAU ..]`` option (s) of the commands that take it."""
    p.add_argument("--input-memory-taus", nargs="+", type=_memory_taus, default=None,
                   metavar="TAU", help=help_text)


def _lag_step(text: str):
    if text.strip().lower() == "auto":
        return "auto"
    try:
        steps = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"lag step must be an integer, a comma list of integers or 'auto', got {text!r}"
        ) from None
    if any(s < 1 for s in steps):
        raise argparse.ArgumentTypeError(f"lag steps must be >= 1, got {text!r}")
    return steps[0] if len(steps) == 1 else steps


def _progress(cycle: int, n_cycles: int, best: float, nfev: int) -> None:
    print(f"  ABC cycle {cycle}/{n_cycles}: best validation RMSE {best:.4g} "
          f"({nfev} fits)", file=sys.stderr, flush=True)


def evaluate_model(model, u, y) -> dict:
    """Free-run and one-step metrics of a model on one record.

    For a forward model the target is y (mm); for an inverse model it is u (V). The free run
    starts from the first ``max_lag`` measured samples (skipped in the metrics).

    Returns
    -------
    dict
        ``{"free_run": {...}, "one_step": {...}, "units": "mm" | "V", "samples_skipped": int}``
        plus ``"free_run_output"`` and ``"one_step_output"`` arrays (drop them before JSON).
    """
    if isinstance(model, (PrandtlIshlinskii, GeneralizedPI)):
        y_free = model.simulate(u)
        y_one = y_free  # no output feedback: one-step equals free run
        skip, target, units = 0, y, "mm"
    elif isinstance(model, GpiInverse):
        # the numerical inverse from rest (free run), or from the state the measured
        # voltages leave (one-step)
        skip, target, units = 0, u, "V"
        y_free = model.simulate(y)
        y_one = model.predict(y, u)
    elif isinstance(model, (InverseNarxModel, AugmentedInverse)):
        # an AugmentedInverse (ipmc identify --inverse --effects-from) runs as the feedforward
        # does: its effects' states from rest, fed by the voltages it gives (free run) or by
        # the measured ones (one-step)
        skip = model.max_lag_
        y_free = model.simulate(y, u[:skip])
        y_one = model.predict(y, u)
        target, units = u, "V"
    elif isinstance(model, (NarxModel, AugmentedModel)):
        # an AugmentedModel (ipmc diagnose's model_after) is scored as its baseline is, its
        # effects as blocks around it: a creep starts from rest, a drift at the first sample
        skip = model.max_lag_
        y_free = model.simulate(u, y[:skip])
        y_one = model.predict(u, y)
        target, units = y, "mm"
    else:
        raise ValueError(f"cannot evaluate an object of type {type(model).__name__}")
    if np.all(np.isfinite(y_free)):
        free = score(target, y_free, skip)
    else:
        free = {k: float("inf") for k in ("rmse", "nrmse", "max_abs")}
        free["fit_percent"] = float("-inf")
    return {
        "free_run": free,
        "one_step": score(target, y_one, skip),
        "input_only": y_one is y_free,
        "units": units,
        "samples_skipped": int(skip),
        "free_run_output": y_free,
        "one_step_output": y_one,
    }


def _print_metrics(result: dict, label: str) -> None:
    units = result["units"]
    modes = ("free_run",) if result.get("input_only") else ("free_run", "one_step")
    for mode in modes:
        m = result[mode]
        name = mode.replace("_", "-")
        print(f"{label} {name}: RMSE {m['rmse']:.4f} {units}, NRMSE {m['nrmse']:.4f}, "
              f"fit {m['fit_percent']:.2f} %, max |error| {m['max_abs']:.4f} {units}")
    if result.get("input_only"):
        print("(the model runs on the input alone: its one-step prediction is its free run)")
    elif result["samples_skipped"]:
        print(f"({result['samples_skipped']} initial samples skipped: the model's lags)")


#: A model that explains less than half of its own record's variance in free run (fit % is
#: 100 (1 - |e| / |y - mean y|)) is not one to control with.
POOR_FIT_PERCENT = 50.0


def _warn_poor_training_fit(result: dict) -> None:
    fit = result["free_run"]["fit_percent"]
    if fit < POOR_FIT_PERCENT:
        print(f"warning: the model reproduces its own record at a free-run fit of {fit:.1f} % "
              f"(below {POOR_FIT_PERCENT:g} %): do not use it as a feedforward. For an "
              "inverse this means the forward model cannot be inverted on this record (e.g. "
              "a transport delay the fit took for dynamics); try ipmc diagnose on the record, "
              "then --effects-from its model_after.json", file=sys.stderr)


def _identify_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ipmc identify",
        description="Identify an actuator model from a record. With no --model it tries the "
                    "families (" + ", ".join(FAMILIES) + ") fitted on the first 70 % of the "
                    "record, picks the lowest held-out free-run RMSE on the rest, refits it on "
                    "the whole record and stores the table in the model file.",
    )
    p.add_argument("--data", required=True, help="t,u,y CSV file (s, V, mm) or rosbag2 folder")
    p.add_argument("--model", choices=("gpi", "pi", "lssvm-narx"), default=None,
                   help="force one family: gpi (rate-dependent generalised PI), pi (the "
                        "paper's PI), lssvm-narx (the paper's LSSVM-NARX, ABC-tuned). Default: "
                        "the best of " + ", ".join(FAMILIES) + " on held-out free run; with "
                        "--inverse, gpi (served through its numerical inverse)")
    p.add_argument("--out", required=True,
                   help="model file to write (.json, added if missing; + .npz beside it), "
                        "checked before the fit; the pair is written whole or not at all")
    add_allow_implausible(p)
    p.add_argument("--inverse", action="store_true",
                   help="a feedforward: gpi (default) writes the model served through its "
                        "numerical inverse; lssvm-narx identifies the inverse model "
                        "u = h(y, past u) (Eq. 19)")
    p.add_argument("--effects-from", metavar="MODEL",
                   help="a model with effects (ipmc diagnose's model_after.json): its "
                        "structure, with the delay, dead zone, creep, drift and charging-current "
                        "stages the diagnosis added, refitted on this record; with --inverse "
                        "its feedforward, which undoes them too. The record must be at the "
                        "model's sample rate. An augmented LSSVM-NARX file of earlier versions "
                        "goes with --model lssvm-narx --inverse")
    _add_narx_options(p)
    p.add_argument("--pi-method", choices=("nnls", "pso"), default="nnls",
                   help="pi: thresholds on a grid + NNLS (default, invertible) or PSO (paper)")
    p.add_argument("--operators", type=int, default=10, help="pi: number of play operators")
    p.add_argument("--seed", type=int, default=0)
    return p



def _add_narx_options(p: argparse.ArgumentParser) -> None:
    """The lssvm-narx options of ``ipmc identify`` (unset ones: :data:`NARX_DEFAULTS`, or
    :data:`NARX_INVERSE_DEFAULTS` with --inverse)."""
    p.add_argument("--tune", choices=("abc", "none"), default=None,
                   help="lssvm-narx: tune C and sigma by ABC (default for a forward model) or "
                        "use --C/--sigma (default with --inverse)")
    p.add_argument("--budget", type=_budget, default=(DEFAULT_SOURCES, DEFAULT_CYCLES),
                   help=f"ABC budget SOURCESxCYCLES (default {DEFAULT_SOURCES}x{DEFAULT_CYCLES}"
                        ", about 210 fits; the paper's is 100x100, about 20000)")
    p.add_argument("--objective", choices=("free-run", "one-step"), default="free-run",
                   help="tuning objective: validation RMSE of the free run (default) or of the "
                        "one-step prediction")
    p.add_argument("--C", type=float, default=None,
                   help=f"LSSVM C (default {PAPER_C}; with --inverse "
                        f"{NARX_INVERSE_DEFAULTS['C']:g})")
    p.add_argument("--sigma", type=float, default=None,
                   help=f"LSSVM sigma, standardised units (default {PAPER_SIGMA}; with "
                        f"--inverse {NARX_INVERSE_DEFAULTS['sigma']:g})")
    p.add_argument("--input-lags", type=int, default=None,
                   help=f"m: input lags; with --inverse, past voltages (default {DEFAULT_LAGS}"
                        f", with --inverse {NARX_INVERSE_DEFAULTS['input_lags']}: no voltage "
                        "feedback, so the inverse free run cannot drift; the paper's is 3)")
    p.add_argument("--output-lags", type=int, default=None,
                   help=f"n (default {DEFAULT_LAGS}, with --inverse "
                        f"{NARX_INVERSE_DEFAULTS['output_lags']}, with --input-memory-taus "
                        f"{DEFAULT_CHANNEL_LAGS}; the paper's is 3)")
    p.add_argument("--lag-step", type=_lag_step, default=None,
                   help="spacing of the lags in samples: an integer, a comma list to search "
                        "(e.g. 5,10,20) or 'auto' (searches "
                        f"{','.join(map(str, DEFAULT_LAG_STEPS))}; needs --tune abc). Default: "
                        "auto with --tune abc, 1 with --tune none, "
                        f"{NARX_INVERSE_DEFAULTS['lag_step']} with --inverse")
    p.add_argument("--memory-taus", type=_memory_taus, default=None, metavar="TAU[,TAU..]",
                   help="lssvm-narx --inverse: memory channels, the desired displacement "
                        "low-passed with these time constants (s, comma list, e.g. 1.0); they "
                        "let the inverse undo the IPMC's back-relaxation without a voltage "
                        "recursion (default 1.0 with --inverse; none is the paper's "
                        "structure)")
    add_input_memory_taus(
        p, "lssvm-narx forward: voltage channels, the voltage low-passed with these time "
           "constants (s, e.g. 0.3 0.5), built by the model from the raw voltage and stored in "
           "its file; such a model can be inverted for the feedforward (model_server, ipmc "
           f"track). Input and output lags default to {DEFAULT_CHANNEL_LAGS}; C "
           f"{NARX_CHANNEL_DEFAULTS['C']:g}, sigma {NARX_CHANNEL_DEFAULTS['sigma']:g}, "
           f"{NARX_CHANNEL_DEFAULTS['prototypes']} prototypes (--tune abc tunes C and sigma)")
    p.add_argument("--no-raw-voltage", dest="raw_voltage", action="store_false",
                   help="with --input-memory-taus: the low-passed voltages only, not the "
                        "voltage itself (the structure that inverts smoothly)")
    p.add_argument("--prototypes", type=int, default=None,
                   help=f"lssvm-narx: fixed-size prototypes above --max-exact rows (default "
                        f"{DEFAULT_PROTOTYPES}, with --inverse "
                        f"{NARX_INVERSE_DEFAULTS['prototypes']})")
    p.add_argument("--max-exact", type=int, default=DEFAULT_MAX_EXACT,
                   help=f"lssvm-narx: exact LSSVM up to this many rows (default "
                        f"{DEFAULT_MAX_EXACT})")
    p.add_argument("--max-rows", type=int, default=None,
                   help="lssvm-narx: fit (tuning candidates and final model) on at most this "
                        "many regressor rows, evenly spaced (default all; caps time on long "
                        "records)")
    p.add_argument("--folds", type=int, default=DEFAULT_FOLDS,
                   help="tuning validation: 1 = the last 30 %% of the record; K >= 2 = blocked "
                        f"K-fold cross-validation (K times the fits, less noisy; default "
                        f"{DEFAULT_FOLDS})")


def identify_main(argv: list[str] | None = None) -> int:
    """Entry point of ``ipmc identify``."""
    args = _identify_parser().parse_args(argv)
    try:
        out = check_model_output(args.out)
        rec = _load(args.data, "ipmc identify", args.allow_implausible)
        u, y = rec.u_v, rec.y_mm
        # the kind of input kept with the model: ipmc diagnose --model checks a record against it
        meta = {"data": str(args.data), "samples": int(u.size), "rate_hz": float(rec.rate_hz),
                "input_kind": input_kind(u, float(rec.rate_hz)),
                "input_range_v": [float(u.min()), float(u.max())]}
        if args.effects_from and args.model in ("lssvm-narx", "pi") and not args.inverse:
            raise ValueError("--effects-from with --model lssvm-narx makes a feedforward: add "
                             "--inverse")
        model = _identify(args, rec, u, y, meta)
        meta["record_limits"] = record_limits(u, float(rec.rate_hz))
        for why in meta["record_limits"]:
            print(f"note: this record cannot show how a model generalises: {why}",
                  file=sys.stderr)
        result = evaluate_model(model, u, y)
        meta["training_metrics"] = {k: result[k] for k in ("free_run", "one_step", "units",
                                                           "samples_skipped")}
        if isinstance(model, AugmentedInverse):
            path = save_augmented(model, out, metadata=meta)
        else:
            path = save_model(model, out, metadata=meta)
        _print_metrics(result, "training")
        _warn_poor_training_fit(result)
        print(f"model written to {path}")
    # DataError, ModelFileError, a refused --out and bad inputs are ValueErrors; OSError: the
    # disk refused the write
    except (ValueError, OSError) as exc:
        print(f"ipmc identify: error: {exc}", file=sys.stderr)
        return 1
    return 0


def _identify(args, rec, u, y, meta: dict):
    """The model of the command line's family (or of the comparison, without --model)."""
    dt_s = 1.0 / float(rec.rate_hz)
    if args.effects_from and args.model in (None, "gpi"):
        return _gpi_with_effects(args, u, y, dt_s, meta)
    if args.model is None and args.inverse:
        args.model = "gpi"
    if args.model is None:
        _check_no_family_options(args)
        print(f"comparing {', '.join(FAMILIES)} on held-out free run (fit on the first 70 %)",
              file=sys.stderr, flush=True)
        sel = compare_families(u, y, dt_s, progress=_stage)
        print(sel.table())
        meta["selection"] = sel.as_dict()
        args.model = sel.chosen
        print(f"refitting {sel.chosen} on the whole record", file=sys.stderr, flush=True)
        return _report_family(sel.refit(u, y, dt_s, _stage))
    if args.model == "gpi":
        _check_gpi_args(args)
        print("fitting a GPI model (rate-dependent generalised Prandtl-Ishlinskii)",
              file=sys.stderr, flush=True)
        model = _report_family(FAMILIES["gpi"].fit(u, y, dt_s, _stage))
        return model.inverse() if args.inverse else model
    if args.model == "pi":
        if args.inverse:
            raise ValueError("--inverse is for gpi or lssvm-narx; a PI model is inverted "
                             "analytically (PrandtlIshlinskii.inverse())")
        if args.input_memory_taus is not None or not args.raw_voltage:
            raise ValueError("--input-memory-taus and --no-raw-voltage are for lssvm-narx")
        print(f"fitting a PI model ({args.operators} play operators, {args.pi_method})",
              file=sys.stderr)
        return PrandtlIshlinskii(n_operators=args.operators, method=args.pi_method,
                                 seed=args.seed).fit(u, y)
    if args.input_memory_taus is not None or not args.raw_voltage:
        return _identify_channel_model(args, u, y, dt_s, meta)
    return _identify_narx(args, rec, u, y, meta)


def _report_family(model):
    """Print what a GPI fit found; any model is returned as it is."""
    if isinstance(model, GeneralizedPI):
        print(f"GPI: charging tau {model.charge_tau_s_:.3g} s, ion-current limit "
              f"{model.slew_v_per_s_:.3g} V/s, ridge alpha {model.cv_.alpha:.3g} "
              f"({model.cv_.n_folds}-fold blocked free-run CV: {min(model.cv_.rmse):.4f} mm)")
    return model


#: Options that belong to one family: refused without --model, not ignored.
FAMILY_OPTIONS = {"--tune": "tune", "--C": "C", "--sigma": "sigma", "--input-lags": "input_lags",
                  "--output-lags": "output_lags", "--lag-step": "lag_step",
                  "--memory-taus": "memory_taus", "--input-memory-taus": "input_memory_taus",
                  "--prototypes": "prototypes"}


def _gpi_with_effects(args, u, y, dt_s: float, meta: dict):
    """--effects-from a GPI file (ipmc diagnose's model_after.json): its structure, with the
    effects the diagnosis added (delay, dead zone, creep, drift, charging current), refitted
    on this record; with --inverse its feedforward, which undoes them too."""
    src = load_any_model(args.effects_from)
    if isinstance(src, GpiInverse):
        src = src.model
    if not isinstance(src, GeneralizedPI):
        raise ValueError(f"{args.effects_from} is not a GPI model; an augmented LSSVM-NARX "
                         "file is used with --model lssvm-narx --inverse --effects-from")
    if abs(src.dt_s - dt_s) > 0.01 * dt_s:
        raise ValueError(f"{args.effects_from} runs at {1 / src.dt_s:.4g} Hz, the record at "
                         f"{1 / dt_s:.4g} Hz")
    _check_gpi_args(args)
    print(f"refitting the structure of {args.effects_from} on this record: {gpi_stages(src)}",
          file=sys.stderr, flush=True)
    model = GeneralizedPI(**{**src.get_params(), "progress": _stage}).fit(u, y)
    meta["effects_from"] = str(args.effects_from)
    return model.inverse() if args.inverse else model


def gpi_stages(m: GeneralizedPI) -> str:
    """The optional stages of a GPI model in words."""
    parts = [f"delay {m.delay_s:g} s" if m.delay_s else "",
             f"dead zone {m.dead_zone_v:.3g} V" if m.dead_zone_v else "",
             f"creep taus {', '.join(f'{t:g}' for t in m.output_taus_s)} s"
             if m.output_taus_s else "",
             "drift" if m.drift else "", "charging-current channel" if m.rate_channel else "",
             "charging-current bending" if m.output_rate else ""]
    return ", ".join(p for p in parts if p) or "no optional stage"


def _check_no_family_options(args) -> None:
    """Without --model the comparison fits each family with its defaults."""
    given = [flag for flag, key in FAMILY_OPTIONS.items() if getattr(args, key) is not None]
    given += ["--no-raw-voltage"] * (not args.raw_voltage)
    given += ["--operators"] * (args.operators != 10)
    given += ["--pi-method"] * (args.pi_method != "nnls")
    if given:
        raise ValueError(f"{', '.join(given)} belong to one model family; name it with "
                         "--model (without --model every family is fitted with its defaults)")


def _stage(text: str) -> None:
    print(f"  {text}", file=sys.stderr, flush=True)


def _check_gpi_args(args) -> None:
    """Options of other families are refused for gpi, not ignored."""
    if args.input_memory_taus is not None or not args.raw_voltage or args.memory_taus:
        raise ValueError("--input-memory-taus, --no-raw-voltage and --memory-taus are for "
                         "lssvm-narx; the GPI model has its relaxation bank built in")


def _narx_defaults(args, defaults: dict | None = None) -> None:
    """Fill the lssvm-narx options not given from ``defaults``, by default
    :data:`NARX_INVERSE_DEFAULTS` for an inverse model, else :data:`NARX_DEFAULTS`."""
    if defaults is None:
        defaults = NARX_INVERSE_DEFAULTS if args.inverse else NARX_DEFAULTS
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)


def _identify_narx(args, rec, u, y, meta: dict):
    """The paper's LSSVM-NARX, forward or inverse, tuned by ABC or with --C/--sigma."""
    _narx_defaults(args)
    tune = args.tune == "abc"
    if args.memory_taus and not args.inverse:
        raise ValueError("--memory-taus is for an inverse model: add --inverse")
    fit_u, fit_y, augmented = u, y, None
    if args.effects_from:
        augmented, fit_u, fit_y = _feedforward_space(args, u, y, rec.dt_s, meta)
    if args.lag_step is None:
        args.lag_step = "auto" if tune else 1
    if tune:
        print(f"tuning C, sigma by ABC ({args.budget[0]} sources x {args.budget[1]} "
              f"cycles, {args.objective} objective)", file=sys.stderr, flush=True)
    model, tuning = identify_lssvm_narx(
        fit_u, fit_y,
        C=None if tune else args.C, sigma=None if tune else args.sigma,
        input_lags=args.input_lags, output_lags=args.output_lags,
        lag_step=args.lag_step, inverse=args.inverse, seed=args.seed,
        memory_taus_s=args.memory_taus, dt_s=1.0 / float(rec.rate_hz),
        n_prototypes=args.prototypes, max_exact=args.max_exact,
        max_train_rows=args.max_rows, **_tuning_kwargs(args, tune),
    )
    _report_tuning(args, tuning, meta)
    return AugmentedInverse(augmented, model) if augmented is not None else model


def _feedforward_space(args, u, y, dt_s: float, meta: dict):
    """--effects-from: the augmented model, and the record (u V, y mm) as the baseline of its
    feedforward part sees it, for the inverse to be fitted on."""
    model = check_rate(load_augmented(args.effects_from), dt_s)
    part, left = model.feedforward_part()
    for name, why in left.items():
        print(f"{name} left out of the feedforward: {why}", file=sys.stderr)
    if not part.effects:
        raise ValueError(f"{args.effects_from} has no effect a feedforward can undo (effects: "
                         f"{', '.join(model.effect_names) or 'none'}); identify the plain "
                         "inverse without --effects-from")
    print(f"fitting the inverse in the baseline space of {args.effects_from} (effects undone: "
          f"{'; '.join(f'{e.name}: {e.describe()}' for e in part.effects)})", file=sys.stderr,
          flush=True)
    meta["effects_from"] = str(args.effects_from)
    meta["feedforward_effects"] = part.effect_names
    v, z = part.to_baseline_space(u, y)
    return model, v, z


def _identify_channel_model(args, u, y, dt_s: float, meta: dict) -> NarxModel:
    """The forward LSSVM-NARX with voltage channels of --input-memory-taus / --no-raw-voltage."""
    if args.input_memory_taus is None:
        raise ValueError("--no-raw-voltage needs --input-memory-taus (the low-passed voltage "
                         "channels that replace the voltage)")
    taus = taus_list(args.input_memory_taus)
    if args.inverse:
        raise ValueError("--input-memory-taus is for a forward model; an inverse model's "
                         "channels are --memory-taus (the desired displacement low-passed)")
    if args.memory_taus:
        raise ValueError("--memory-taus is for an inverse model: add --inverse")
    _narx_defaults(args, NARX_CHANNEL_DEFAULTS)
    tune = args.tune == "abc"
    lag_step = 1 if args.lag_step is None else args.lag_step
    if not tune and not isinstance(lag_step, int):
        raise ValueError("--lag-step 'auto' or a list needs tuning; give one integer")
    in_lags = DEFAULT_CHANNEL_LAGS if args.input_lags is None else args.input_lags
    out_lags = DEFAULT_CHANNEL_LAGS if args.output_lags is None else args.output_lags
    what = (f"a forward LSSVM-NARX on voltage channels (taus {', '.join(map(str, taus))} s"
            f"{', and the voltage' if args.raw_voltage else ''}; input lags {in_lags}, output "
            f"lags {out_lags}")
    if tune:
        print(f"tuning C, sigma of {what}) by ABC ({args.budget[0]} sources x "
              f"{args.budget[1]} cycles, {args.objective} objective)", file=sys.stderr,
              flush=True)
    else:
        print(f"fitting {what}, C = {args.C:g}, sigma = {args.sigma:g})", file=sys.stderr,
              flush=True)
    model, tuning = identify_lssvm_narx(
        u, y,
        C=None if tune else args.C, sigma=None if tune else args.sigma,
        input_lags=in_lags, output_lags=out_lags, lag_step=lag_step, seed=args.seed,
        dt_s=dt_s, input_memory_taus_s=taus, include_voltage=args.raw_voltage,
        n_prototypes=args.prototypes, max_exact=args.max_exact, max_train_rows=args.max_rows,
        **_tuning_kwargs(args, tune),
    )
    _report_tuning(args, tuning, meta)
    return model


def _tuning_kwargs(args, tune: bool) -> dict:
    """identify_lssvm_narx's ABC options from the command line (none without tuning)."""
    if not tune:
        return {}
    return {"n_sources": args.budget[0], "n_cycles": args.budget[1],
            "objective": args.objective.replace("-", "_"), "progress": _progress,
            "n_folds": args.folds, "max_val_samples": MAX_VAL_SAMPLES}


def _report_tuning(args, tuning, meta: dict) -> None:
    """Print the tuned values and keep them in the model file's metadata."""
    if tuning is None:
        return
    meta["tuning"] = tuning.as_dict()
    print(f"tuned: C = {tuning.C:.6g}, sigma = {tuning.sigma:.6g}, lag step "
          f"{tuning.lag_step} (validation {args.objective} RMSE {tuning.score_mm:.4f}, "
          f"{tuning.nfev} fits, {tuning.seconds:.1f} s)")


def _evaluate_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ipmc evaluate",
                                description="Score a saved model on a record (free-run and "
                                            "one-step).")
    p.add_argument("--model", required=True,
                   help="model file written by ipmc identify, or ipmc diagnose's "
                        "model_before.json / model_after.json (the baseline with the effects "
                        "found: a creep starts from rest, a drift at the record's start)")
    p.add_argument("--data", required=True, help="t,u,y CSV file (s, V, mm) or rosbag2 folder")
    p.add_argument("--plots", metavar="DIR",
                   help="write PNG figures to DIR (a folder, created if missing)")
    p.add_argument("--json", metavar="OUT", help="write the metrics as JSON to OUT (.json)")
    add_allow_implausible(p)
    return p


def evaluate_main(argv: list[str] | None = None) -> int:
    """Entry point of ``ipmc evaluate``."""
    args = _evaluate_parser().parse_args(argv)
    try:
        if args.json:
            check_output_file(args.json, option="--json", suffixes=(".json",))
        if args.plots:
            check_output_dir(args.plots, option="--plots")
        rec = _load(args.data, "ipmc evaluate", args.allow_implausible)
        model = load_any_model(args.model, rec.dt_s)
        result = evaluate_model(model, rec.u_v, rec.y_mm)
        notes = unlike_identification(getattr(model, "metadata_", {}) or {}, rec.u_v,
                                      float(rec.rate_hz))
    except (ValueError, TypeError) as exc:  # TypeError: a hand-edited metadata value
        print(f"ipmc evaluate: error: {exc}", file=sys.stderr)
        return 1
    for why in notes:
        print(f"note: this record is unlike the identification record: {why}",
              file=sys.stderr)
    _print_metrics(result, "evaluation")
    try:
        if args.json:
            doc = {k: result[k] for k in ("free_run", "one_step", "units", "samples_skipped")}
            doc["unlike_identification"] = notes
            write_atomic({args.json: json.dumps(doc, indent=2) + "\n"})
            print(f"metrics written to {args.json}")
        if args.plots:
            for f in write_plots(model, rec, result, args.plots):
                print(f"figure written to {f}")
    except OSError as exc:
        print(f"ipmc evaluate: error: cannot write the results ({exc})", file=sys.stderr)
        return 1
    return 0


def _save_png(fig, path: Path) -> None:
    """Save a figure as a PNG file, whole or not at all."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    write_atomic({path: buf.getvalue()})


def write_plots(model, rec, result: dict, out_dir) -> list[Path]:
    """Measured vs model, error curve and hysteresis loop as PNG files in ``out_dir``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    t, u, y = rec.t_s, rec.u_v, rec.y_mm
    inverse = isinstance(model, (InverseNarxModel, AugmentedInverse))
    target, unit = (u, "V") if inverse else (y, "mm")
    name = "voltage u" if inverse else "displacement y"
    free, one = result["free_run_output"], result["one_step_output"]
    s = result["samples_skipped"]
    paths = []

    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(t, target, label="measured", lw=1.2)
    ax.plot(t, free, "--", label="model, free-run", lw=1.0)
    ax.plot(t, one, ":", label="model, one-step", lw=1.0)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"{name} ({unit})")
    ax.legend()
    ax.set_title(f"measured vs model (free-run RMSE {result['free_run']['rmse']:.4f} {unit}, "
                 f"one-step {result['one_step']['rmse']:.4f} {unit})")
    fig.tight_layout()
    paths.append(out_dir / "measured_vs_model.png")
    _save_png(fig, paths[-1])
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 3.5))
    ax.plot(t[s:], (target - free)[s:], label="free-run error", lw=1.0)
    ax.plot(t[s:], (target - one)[s:], label="one-step error", lw=1.0)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"measured - model ({unit})")
    ax.legend()
    fig.tight_layout()
    paths.append(out_dir / "error.png")
    _save_png(fig, paths[-1])
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5, 5))
    if inverse:
        ax.plot(y, u, label="measured", lw=1.0)
        ax.plot(y, free, "--", label="inverse model, free-run", lw=1.0)
        ax.set_xlabel("displacement y (mm)")
        ax.set_ylabel("voltage u (V)")
    else:
        ax.plot(u, y, label="measured", lw=1.0)
        ax.plot(u, free, "--", label="model, free-run", lw=1.0)
        ax.set_xlabel("voltage u (V)")
        ax.set_ylabel("displacement y (mm)")
    ax.set_title("hysteresis loop")
    ax.legend()
    fig.tight_layout()
    paths.append(out_dir / "hysteresis.png")
    _save_png(fig, paths[-1])
    plt.close(fig)
    return paths


if __name__ == "__main__":
    sys.exit(identify_main())
