"""Benchmark of ``ipmc investigate`` on the simulated IPMC in process: per case, the effects
found, their parameters beside the plant's, the held-out error before and after beside the
clean plant's, the simulated and wall time, and each proposed experiment's length beside what
it decides. Prints figures; not part of the pass/fail suite.

    .venv/bin/python benchmarks/bench_investigate.py [--case creep ...] [--rate-hz 50] [--graph]
    .venv/bin/python benchmarks/bench_investigate.py --case dead_zone --seeds 0 1 2 3 4 5 6 7
    .venv/bin/python benchmarks/bench_investigate.py --twin-of REPORT_DIR
    .venv/bin/python benchmarks/bench_investigate.py --case dead_zone --plant-param hyst_weight=0

``--graph`` runs each round through the lock-step ROS graph (``ipmc bringup --sim --lockstep
--experiment FILE --record BAG``, 100 Hz), as ``ipmc investigate --sim`` does; the default is
the same simulated IPMC in this process, several times faster.

Cases: a creep (tau 20 s) under a random sine (no holds); a transport delay (0.05 s) and a
dead zone (0.3 V) under a smooth random sine (band 0.02-0.3 Hz: few fast components, no steps,
no dwelling near 0 V); and the clean plant under a random sine. The clean plant's figure is the
diagnosis's final held-out error on the clean plant under the last round's input, same seed
(with ``--together``, every round's diagnosis takes every record so far, and the clean plant
under every round's input is diagnosed the same way): the error left when nothing is missing
(goal: the investigation's final error within 1.2 x it); what the diagnosis found there is
printed beside it.

``--seeds`` runs each case on several seeds and closes with how often the found parameters'
95 % intervals held the plant's values: a calibrated interval holds it on about 95 % of
them.

``--plant-param KEY=VALUE`` sets one of the simulated IPMC's parameters (``plant:`` in
ipmc_driver's plant_default.yaml) for the investigation and its clean twin alike: which part
of the plant an estimate's bias comes from (the effects keep their values).

``--twin-of`` takes the report folder of an investigation run elsewhere (through the rig
emulator: ``ipmc investigate --rig PTY --report DIR``) and prints the same comparison: the
clean simulated IPMC under the last round's recorded voltages, diagnosed as that round was.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from threadpoolctl import threadpool_limits

from ipmc_control.investigate import (
    GraphRunner,
    InProcessRunner,
    Investigation,
    PlannedInput,
    first_input,
    investigate,
    residual_diagnoser,
)
from ipmc_control.investigate_report import write_investigation
from ipmc_model.diagnosis.experiment import ExperimentPart
from ipmc_model.diagnosis.search import diagnose_records  # BLAS loaded before the limit

SECONDS = 120.0


@dataclass(frozen=True)
class Case:
    name: str
    effects: tuple[str, ...]
    smooth: bool          # a smooth first input (random sine up to 0.3 Hz)
    plant: str            # the plant's parameter, in words


CASES = {
    "creep": Case("creep", ("creep",), False, "tau 20 s, gain -0.12 mm/V"),
    "delay": Case("delay", ("delay",), True, "delay 0.050 s (its line holds whole samples)"),
    "dead_zone": Case("dead_zone", ("dead_zone",), True, "width 0.300 V"),
    "clean": Case("clean", (), False, "no optional effect"),
}


def smooth_input(rate_hz: float, seed: int, out_dir: Path) -> PlannedInput:
    """A random sine over 0.02-0.3 Hz at +-3 V, written as the round's input.csv."""
    from ipmc_control.excitation import Excitation, save_csv
    from ipmc_driver.signals import random_sine

    u = random_sine(SECONDS, rate_hz, 3.0, band_hz=(0.02, 0.3), seed=seed)[1]
    out_dir.mkdir(parents=True, exist_ok=True)
    path = save_csv(Excitation(u, rate_hz, "smooth"), out_dir / "input.csv")
    part = ExperimentPart("first input: smooth random sine", "", 0.0, SECONDS,
                     "random sum of sines over 0.02-0.3 Hz, +-3 V")
    return PlannedInput(u, rate_hz, path, f"first input: smooth random sine, {SECONDS:g} s",
                        (part,))


def describe_params(name: str, p: dict) -> str:
    """An accepted effect's parameters in the plant's terms."""
    if name == "creep":
        (lo, hi), (glo, ghi) = p["tau_ci_s"], p["gain_ci_mm_per_v"]
        return (f"creep tau {p['tau_s']:.1f} s (95 % {lo:.1f}-{hi:.1f}), gain "
                f"{p['gain_mm_per_v']:.4f} mm/V (95 % {glo:.4f} to {ghi:.4f}); the model's "
                f"creep taus {[round(t, 1) for t in p['taus_s']]} s")
    if name == "delay":
        lo, hi = p["delay_ci_s"]
        return f"delay {p['delay_s']:.3f} s (95 % {lo:.3f}-{hi:.3f})"
    if name == "dead_zone":
        lo, hi = p["width_ci_v"]
        return f"dead zone {p['width_v']:.3f} V (95 % {lo:.3f}-{hi:.3f})"
    return f"{name} " + ", ".join(f"{k} {v:.3g}" for k, v in p.items())


#: Each case's parameters and the key of their 95 % interval in the diagnosis's evidence.
INTERVAL_KEYS = {"creep": (("tau_s", "tau_ci_s"), ("gain_mm_per_v", "gain_ci_mm_per_v")),
                 "delay": (("delay_s", "delay_ci_s"),),
                 "dead_zone": (("width_v", "width_ci_v"),)}


def plant_value(effect: str, key: str, rate_hz: float) -> float:
    """The simulated plant's value of an effect's parameter, as it acts at ``rate_hz`` (its
    delay line holds whole samples)."""
    from ipmc_driver.plant import load_plant_params

    value = load_plant_params()["effects"][effect][key]
    return round(value * rate_hz) / rate_hz if key == "delay_s" else value


def interval_checks(inv: Investigation, rate_hz: float
                    ) -> list[tuple[str, str, float, float, float]]:
    """Each accepted effect's parameters, as the latest round that accepted it estimated
    them: (effect, key, the plant's value, 95 % interval's ends)."""
    latest = {name: p for rnd in inv.rounds for name, p in rnd.verdicts.params.items()}
    out = []
    for name, p in latest.items():
        for key, ci in INTERVAL_KEYS.get(name, ()):
            lo, hi = p.get(ci, (float("nan"), float("nan")))
            out.append((name, key, plant_value(name, key, rate_hz), lo, hi))
    return out


def within_intervals(inv: Investigation, rate_hz: float) -> str:
    """Whether each found effect's 95 % intervals hold the plant's values."""
    return "; ".join(f"{key} {true:g} in [{lo:.4g}, {hi:.4g}]: "
                     f"{'yes' if lo <= true <= hi else 'NO'}"
                     for _, key, true, lo, hi in interval_checks(inv, rate_hz)) or "-"


def found_params(inv: Investigation) -> str:
    """Each round's accepted effects and their parameters."""
    out = [f"round {rnd.number}: " + "; ".join(describe_params(n, p)
                                               for n, p in rnd.verdicts.params.items())
           for rnd in inv.rounds if rnd.verdicts.params]
    return " | ".join(out) or "-"


def clean_twin(inv: Investigation, rate_hz: float, seed: int, together: bool,
               plant_params: dict | None = None) -> tuple[float, list[str]]:
    """The clean plant under the last round's input (every round's, ``together``), the same
    seeds, split and judged on the same rows as the investigation's last round: the final
    held-out error and what it found there."""
    first = 0 if together else len(inv.rounds) - 1
    d = clean_diagnosis([(f"round {i + 1}", rnd.played.u_v, seed + i, rnd.played.parts)
                         for i, rnd in enumerate(inv.rounds[first:], start=first)],
                        1.0 / rate_hz, plant_params)
    return d.rmse_after_mm, d.effects_found


def clean_diagnosis(runs, dt_s: float, plant_params: dict | None = None):
    """The clean simulated IPMC (of ``plant_params``; None: the shipped calibration) under
    each run's voltages ``(name, u_v, seed, parts)``, the records diagnosed together."""
    from ipmc_driver.plant import IpmcPlant

    records = []
    for name, u_v, seed, parts in runs:
        run = IpmcPlant(plant_params, effects=(), seed=seed, dt_s=dt_s).run(u_v)
        records.append((name, run.t_s, run.u_v, run.y_mm, parts))
    return diagnose_records(records)


@dataclass(frozen=True)
class CaseResult:
    """One investigated case: the lines that report it, whether it named the plant's effects
    (and nothing else), and whether each parameter's 95 % interval holds the plant's value."""

    lines: list[str]
    right: bool
    covered: tuple[bool, ...]


def run_case(case: Case, rate_hz: float, seed: int, out: Path, together: bool = False,
             graph: bool = False, plant_params: dict | None = None) -> CaseResult:
    """Investigate one case (in process, or through the lock-step graph at its rate), on the
    simulated IPMC with ``plant_params`` (None: the shipped calibration; in process only)."""
    runner = (GraphRunner(effects=list(case.effects)) if graph else
              InProcessRunner(list(case.effects), seed=seed, rate_hz=rate_hz,
                              plant_params=plant_params))
    first = (smooth_input(rate_hz, seed, out / "round_1") if case.smooth else
             first_input("random-sine", seconds=SECONDS, rate_hz=rate_hz, amplitude_v=3.0,
                         seed=seed, out_dir=out / "round_1"))
    t0 = time.perf_counter()
    inv = investigate(runner, first, residual_diagnoser(together=together), out,
                      budget_s=20 * 60.0,
                      progress=lambda text: print(f"  [{case.name}] {text}", file=sys.stderr,
                                                  flush=True))
    wall_s = time.perf_counter() - t0
    write_investigation(inv, out)
    clean, clean_found = clean_twin(inv, rate_hz, seed, together, plant_params)
    lines = [f"{case.name}: plant {case.plant}; first input "
             f"{'smooth random sine' if case.smooth else 'random sine'} {SECONDS:g} s; "
             f"{runner.describe()}",
             f"  effects found: {', '.join(inv.effects_found) or 'none'}; "
             f"undecided: {', '.join(inv.undecided) or 'nothing'}; stopped: "
             f"{inv.stopped_because}",
             f"  parameters found: {found_params(inv)}",
             f"  plant's values within the 95 % intervals: {within_intervals(inv, rate_hz)}",
             f"  held-out RMSE before {inv.rmse_before_mm:.4f} mm, after "
             f"{inv.rmse_after_mm:.4f} mm, clean plant {clean:.4f} mm (after / clean "
             f"{inv.rmse_after_mm / clean:.2f}; found on the clean plant: "
             f"{', '.join(clean_found) or 'nothing'})",
             f"  rounds {len(inv.rounds)}, simulated {inv.recorded_s:.0f} s, wall "
             f"{wall_s:.0f} s"]
    for rnd in inv.rounds[1:]:
        probes = [p for p in rnd.played.parts if p.effect]
        probe_s = sum(p.duration_s for p in probes) / 2
        lines.append(f"  round {rnd.number}: experiment {rnd.played.duration_s:.0f} s "
                     f"(probes {probe_s:.0f} s, each played twice) deciding "
                     f"{', '.join(rnd.undecided)}: "
                     + "; ".join(f"{p.name} {p.duration_s:.0f} s: {p.reason}"
                                 for p in probes[:len(probes) // 2])
                     + f" -> {rnd.decided or 'nothing decided'}")
        lines += [f"    {n}: {rnd.verdicts.reasons[n]}" for n in rnd.undecided]
    return CaseResult(lines, sorted(inv.effects_found) == sorted(case.effects),
                      tuple(lo <= true <= hi for name, _, true, lo, hi
                            in interval_checks(inv, rate_hz) if name in case.effects))


def coverage(name: str, seeds: list[int], results: list[CaseResult]) -> str:
    """A case over several seeds: how often it named the plant's effect (and nothing else),
    and there how often the 95 % intervals of its parameters held the plant's values (a
    calibrated interval: about 95 % of them)."""
    right = [s for s, r in zip(seeds, results, strict=True) if r.right]
    checks = [(s, c) for s, r in zip(seeds, results, strict=True) if r.right for c in r.covered]
    held = sum(c for _, c in checks)
    missed = sorted({s for s, c in checks if not c})
    return (f"{name}: effects named on {len(right)} / {len(seeds)} seeds; the plant's values "
            f"within the 95 % intervals {held} / {len(checks)} (seeds missed: "
            f"{', '.join(map(str, missed)) or 'none'})")


def twin_of(report: Path, seed: int) -> list[str]:
    """The clean twin of the investigation in ``report``: the records its last round's
    diagnosis took (every round's, or the last alone), their voltages through the clean
    simulated IPMC (noise seeded ``seed`` plus the round's index, as :func:`clean_twin`),
    diagnosed together with each round's experiment parts."""
    import json

    from ipmc_driver.dataio import load_record
    from ipmc_model.diagnosis.experiment import played_parts, read_experiment

    summary = json.loads((report / "summary.json").read_text())
    rounds = summary["rounds"]
    last = json.loads((Path(rounds[-1]["diagnosis"]) / "summary.json").read_text())
    runs = []
    for i in range(len(rounds) - len(last["records"]), len(rounds)):
        rnd = rounds[i]
        rec = load_record(rnd["record"], gaps=True, notes=[])
        parts = ()
        if any(part["effect"] for part in rnd["experiment"]["parts"]):   # a proposed one
            planned, u_plan, _ = read_experiment(rnd["experiment"]["path"])
            parts = played_parts(planned, u_plan, rec.u_v, rec.dt_s)
        runs.append((f"clean twin of round {i + 1}", rec.u_v, seed + i, parts))
    d = clean_diagnosis(runs, rec.dt_s)
    after = summary["rmse_after_mm"]
    return [f"{report}: found {', '.join(summary['effects_found']) or 'nothing'}; after "
            f"{after:.4f} mm, clean twin {d.rmse_after_mm:.4f} mm (found there: "
            f"{', '.join(d.effects_found) or 'nothing'}): after / clean "
            f"{after / d.rmse_after_mm:.2f}; {summary['recorded_min']:.1f} min recorded, "
            f"{summary['wall_s'] / 60:.1f} min wall, {len(summary['rounds'])} rounds, "
            f"{sum(r.get('samples_lost', 0) for r in summary['rounds'])} samples lost"]


def plant_params_with(settings: list[str], parser: argparse.ArgumentParser) -> dict | None:
    """The shipped plant's parameters with each ``KEY=VALUE`` of ``settings`` set (None when
    there is none); a key the plant does not have, or a value that is not a number, is
    refused naming the keys it has."""
    from ipmc_driver.plant import load_plant_params

    if not settings:
        return None
    params = load_plant_params()
    keys = sorted(k for k in params if k != "effects")
    for item in settings:
        key, _, value = item.partition("=")
        if key not in keys:
            parser.error(f"--plant-param {item}: the simulated IPMC has no parameter {key!r}; "
                         f"it has {', '.join(keys)}")
        try:
            params[key] = float(value)
        except ValueError:
            parser.error(f"--plant-param {item}: {value!r} is not a number")
    return params


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--case", action="append", choices=list(CASES),
                   help="cases to run (default all)")
    p.add_argument("--rate-hz", type=float, default=50.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", type=int, nargs="+", metavar="N",
                   help="run each case on each of these seeds and close with how often the "
                        "intervals held the plant's values (their calibration)")
    p.add_argument("--together", action="store_true",
                   help="each round diagnoses every record so far at once (ipmc diagnose "
                        "--data A --data B), not the newest record alone")
    p.add_argument("--graph", action="store_true",
                   help="through the lock-step ROS graph at its rate (as ipmc investigate "
                        "--sim), not the simulated IPMC in this process")
    p.add_argument("--plant-param", action="append", default=[], metavar="KEY=VALUE",
                   help="set one of the simulated IPMC's parameters (plant: in "
                        "plant_default.yaml), e.g. hyst_weight=0; in process only")
    p.add_argument("--twin-of", type=Path, metavar="REPORT_DIR",
                   help="compare a finished investigation (its report folder) with its clean "
                        "twin instead of running the cases")
    args = p.parse_args()
    plant_params = plant_params_with(args.plant_param, p)
    if args.twin_of:
        if plant_params is not None:
            p.error("--plant-param sets the plant of the investigations run here; --twin-of "
                    "compares one run elsewhere with the shipped plant")
        print("\n".join(twin_of(args.twin_of, args.seed)))
        return 0
    if args.graph:
        if plant_params is not None:
            p.error("--plant-param sets the plant in this process; the graph's plant node "
                    "keeps its own")
        args.rate_hz = GraphRunner.rate_hz
    if plant_params is not None:
        print(f"the simulated IPMC with {', '.join(args.plant_param)} (the shipped calibration "
              f"otherwise), in the investigations and their clean twins", flush=True)
    t0 = time.perf_counter()
    seeds = args.seeds or [args.seed]
    summary = []
    with threadpool_limits(1), tempfile.TemporaryDirectory() as tmp:
        for name in args.case or list(CASES):
            results = []
            for seed in seeds:
                results.append(run_case(CASES[name], args.rate_hz, seed,
                                        Path(tmp) / f"{name}_{seed}", args.together,
                                        args.graph, plant_params))
                print("\n".join(results[-1].lines), flush=True)
            summary.append(coverage(name, seeds, results))
    if len(seeds) > 1:
        print("\n".join(summary))
    print(f"total wall time {time.perf_counter() - t0:.0f} s at {args.rate_hz:g} Hz, "
          f"seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
