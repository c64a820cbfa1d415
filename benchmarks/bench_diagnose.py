"""Benchmark of ``ipmc diagnose``: wall time on 30 000 samples, the plant's effects, and the
third-party data (Bouc-Wen, piezo). Prints figures; not part of the pass/fail suite.

    .venv/bin/python benchmarks/bench_diagnose.py [timing|thirdparty|all]
    .venv/bin/python benchmarks/bench_diagnose.py timing committee

``committee`` as a word of ``timing``, ``effects``, ``stale``, ``combos``: every baseline the
benchmark identifies is a committee (``--committee``, session 32).
    .venv/bin/python benchmarks/bench_diagnose.py effects [SEED...] [LABEL_PREFIX...]
    .venv/bin/python benchmarks/bench_diagnose.py creepfit [SEED...]
    .venv/bin/python benchmarks/bench_diagnose.py slowcreep [SEED...]
    .venv/bin/python benchmarks/bench_diagnose.py stale [SEED...] [LABEL_PREFIX...]
    .venv/bin/python benchmarks/bench_diagnose.py combos [SEED...] [LABEL_PREFIX...]
    .venv/bin/python benchmarks/bench_diagnose.py pairs [SEED...]
    .venv/bin/python benchmarks/bench_diagnose.py creepmodel [SEED...]
    .venv/bin/python benchmarks/bench_diagnose.py baseline [SEED...]
    .venv/bin/python benchmarks/bench_diagnose.py blind [SEED...]

``effects``: every case of :data:`CASES` through the CLI, without ``--model`` (seeds 0, 1, 2
by default; they were used to design it).

``stale``: a model fitted on a clean day (the diagnosis's own baseline on 120 s of the mixed
3 V input) given with ``--model`` to the record of a later day (seed + 100) on which the plant
has a dead zone, a saturation, a drift, an asymmetry or a rate dependence (or nothing): what
changed since, fitted around the model (seeds 0, 1 by default; they were used to design it).
``combos``: the same with two changes at once (:data:`COMBO_CHANGES`; seeds 0-3 by default,
used to design the rules for two changes in sessions 28-29).

``pairs``: as ``effects``, with two effects at once in the plant (:data:`PAIR_CASES`; seeds
0-3 by default; seeds 0 and 1 were used to design the creep + drift pair in session 30).

``blind``: ``stale`` and ``effects`` with effect sizes (:data:`BLIND_CHANGES`,
:data:`BLIND_CASES`) and seeds (60 and above) that no rule was designed on: the held-out check
of the rules themselves (session 42). Keep those seeds out of design.

``creepmodel``: a creep around a given model (:data:`CREEP_MODEL_CASES`; seeds 0-3 by
default, used to design the frozen creep in session 34): day 1's baseline given with --model
to a later day's record with input holds, on which the plant creeps (or not).

``baseline``: the diagnosis's own baseline on clean records (3 V ``mixed``, 120 s; the
``effects`` input, 90 s), held-out free-run RMSE as tuned, at the tuning grid's best on the
held-out part (the most any choice from the grid could give), with a 2.4 s window (24 input
lags), and with memory channels (1, 3, 10 s); and the share of its squared error on samples
whose displacement leaves the fit part's range (seeds 0-11 by default). Its error is what a
block fitted around it must not mistake for an effect (docs/diagnose.md, session 32).

``creepfit``: the creep candidate alone (``diagnose(candidates=("creep",))``, full tuning) on
``creep_hold_experiment``'s kind of record (300 s of random 2.5 V steps held 0.5-5 s, 100 Hz),
clean and with creeps of several sizes: fitted tau and gain against the plant's, hold evidence,
held-out gain, accepted, named in the data (seeds 0, 1, 3 by default). ``slowcreep``: the
same on 600 s of steps held 5-40 s at 50 Hz with creeps of 60-120 s (seeds 0-3 by default).

Third-party records are converted to t,u,y CSV in a temporary folder (the CLI reads t,u,y CSV
or a bag; the conversion is done here, not taught to the loader) (Bouc-Wen: u in N,
y in mm; piezo: u in V, y in mm from um); the units are not IPMC ones, the procedure is the same.
"""

from __future__ import annotations

import csv
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from ipmc_driver.dataio import Record, save_csv
from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import random_sine, random_steps
from ipmc_model.diagnose_cli import main as diagnose_main

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RATE = 50.0


def plant_record(effects, seconds, seed, rate=RATE, holds=False):
    """0.6 x random sine + random steps (1.5 V, 3-10 s); ``holds``: the sine is off during every
    other step (true input holds, which the creep evidence needs)."""
    _, us = random_sine(seconds, rate, 2.5, (0.05, 1.0), 8, seed=seed + 2)
    _, st = random_steps(seconds, rate, 1.5, (3.0, 10.0), seed=seed + 3)
    if holds:
        us = us * (np.cumsum(np.r_[0, np.diff(st) != 0]) % 2 == 0)
    u = np.clip(0.6 * us + st, -3, 3)
    run = IpmcPlant(effects=effects, seed=seed, dt_s=1 / rate).run(u)
    return Record(run.t_s, u, run.y_mm)


def run_cli(csv_path, out, model=None, extra=()):
    t0 = time.perf_counter()
    code = diagnose_main(["--data", str(csv_path), "--report", str(out), "--seed", "0"]
                         + (["--model", str(model)] if model else []) + list(extra))
    import json

    s = json.loads((Path(out) / "summary.json").read_text()) if code == 0 else {}
    return code, time.perf_counter() - t0, s


def _mixed_run(fx, seconds, seed, amplitude=3.0) -> Record:
    """The plant with effects ``fx`` on the mixed input (``amplitude`` V)."""
    from ipmc_driver.signals import mixed

    _, u = mixed(seconds, RATE, amplitude, band_hz=(0.02, 0.8), seed=seed)
    run = IpmcPlant(effects=fx, seed=seed, dt_s=1 / RATE).run(u)
    return Record(run.t_s, run.u_v, run.y_mm)


def _mixed_record(fx, seconds, seed, path, amplitude=3.0):
    """:func:`_mixed_run`, saved as CSV."""
    return save_csv(_mixed_run(fx, seconds, seed, amplitude), path)


def timing(tmp, committee=False):
    """Must-show 3 on 30 000 samples, both ways: the diagnosis's own baseline, and a given model
    around which two static blocks are fitted, refitted together and halved (the slowest kind
    of record known: session 29). ``committee``: both baselines are committees
    (``--committee``, session 32)."""
    extra = ["--committee"] if committee else []
    if committee:
        print("timing with committee baselines (--committee)")
    rec = plant_record({"creep": {}}, 600.0, seed=0)  # 30 000 samples at 50 Hz
    p = save_csv(rec, Path(tmp) / "long.csv")
    code, sec, s = run_cli(p, Path(tmp) / "long", extra=extra)
    print(f"timing: {len(rec)} samples: exit {code}, wall {sec:.1f} s (limit 300 s); "
          f"found {s.get('effects_found')}, free-run RMSE {s.get('rmse_before_mm')} -> "
          f"{s.get('rmse_after_mm')} mm", flush=True)
    # a clean day's model (120 s of the mixed 3 V input, seed 0), then 600 s of a later day
    # (seed 100) with an asymmetry 0.8 and a 0.3 V dead zone
    _, _, s1 = run_cli(_mixed_record({}, 120.0, 0, Path(tmp) / "day1.csv"), Path(tmp) / "day1",
                       extra=extra)
    p2 = _mixed_record({"asymmetry": {"negative_gain_ratio": 0.8}, "dead_zone": {"width_v": 0.3}},
                       600.0, 100, Path(tmp) / "day2long.csv")
    code, sec, s = run_cli(p2, Path(tmp) / "day2long", model=s1["model_before"])
    acc = [c["evidence"]["describe"] for c in s.get("candidates", []) if c["accepted"]]
    print(f"timing with --model (a clean day's 120 s model; asymmetry 0.8 + dead zone 0.3 V): "
          f"30000 samples: exit {code}, wall {sec:.1f} s (limit 300 s); found "
          f"{s.get('effects_found')} ({'; '.join(acc)}), free-run RMSE "
          f"{s.get('rmse_before_mm')} -> {s.get('rmse_after_mm')} mm", flush=True)


# (label, plant effects, record seconds): the effect sizes the diagnosis was developed on and
# the plant defaults (plant_default.yaml) it was not tuned on
CASES = [
    ("none", {}, 90.0),
    ("creep tau 12 s, -0.6 mm/V", {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}}, 90.0),
    ("drift 0.1 /min, 0.3 mm/min", {"drift": {"gain_loss_per_min": 0.1,
                                              "offset_mm_per_min": 0.3}}, 90.0),
    ("drift default 0.03 /min, 0.05 mm/min, 300 s", {"drift": {}}, 300.0),
    ("delay 0.2 s", {"delay": {"delay_s": 0.2}}, 90.0),
    ("delay 0.1 s", {"delay": {"delay_s": 0.1}}, 90.0),
    ("delay default 0.05 s", {"delay": {}}, 90.0),
    ("dead_zone 0.6 V", {"dead_zone": {"width_v": 0.6}}, 90.0),
    ("dead_zone default 0.3 V", {"dead_zone": {}}, 90.0),
    ("saturation 1.5 mm", {"saturation": {"limit_mm": 1.5}}, 90.0),
    ("saturation default 3 mm", {"saturation": {}}, 90.0),
    ("asymmetry default 0.7", {"asymmetry": {}}, 90.0),
    ("rate_dependence default 0.1 mm/(V/s)", {"rate_dependence": {}}, 90.0),
    # input with true holds (the sine off during every other step): creep evidence in time
    ("holds: none", {}, 90.0, True),
    ("holds: creep tau 12 s, -0.6 mm/V, 120 s", {"creep": {"tau_s": 12.0,
                                                           "gain_mm_per_v": -0.6}}, 120.0, True),
    ("holds: creep default tau 20 s, -0.12 mm/V, 300 s", {"creep": {}}, 300.0, True),
]


# two effects at once, without --model: a creep the holds show and a drift, which each hide the
# other (session 30)
PAIR_CASES = [
    ("holds: creep tau 12 s, -0.6 mm/V + drift 0.1 /min, 0.3 mm/min, 120 s",
     {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6},
      "drift": {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}}, 120.0, True),
]


def effects(tmp, seeds=(0, 1, 2), only=None, cases=CASES, extra=()):
    print("| plant effect (not told) | seconds | seed | found | free-run RMSE before (mm) | "
          "after (mm) | wall (s) | fitted | in the data, not accepted | undecided (holds) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for label, eff, seconds, *holds in cases:
        if only and not label.startswith(only):
            continue
        for seed in seeds:
            stem = f"{label.split()[0].strip(':')}{len(label)}_{seed}"
            p = save_csv(plant_record(eff, seconds, seed, holds=bool(holds and holds[0])),
                         Path(tmp) / f"{stem}.csv")
            code, sec, s = run_cli(p, Path(tmp) / stem, extra=extra)
            fitted = "; ".join(f"{c['effect']}: {c['evidence'].get('describe', '')}"
                               for c in s.get("candidates", []) if c["accepted"])
            named = ", ".join(dict.fromkeys(
                c["effect"] for c in s.get("candidates", [])
                if c["evidence"].get("in_data") and not c["accepted"])) or "none"
            # as Diagnosis.undecided: the latest round's candidate of each effect
            last = {c["effect"]: c for c in s.get("candidates", [])}
            undecided = ", ".join(
                f"{c['effect']} ({c['evidence']['hold_drift']['holds']})" for c in last.values()
                if c["evidence"].get("undecided") and not c["accepted"]) or "none"
            print(f"| {label} | {seconds:.0f} | {seed} | "
                  f"{', '.join(s.get('effects_found', [])) or 'none'} | "
                  f"{s.get('rmse_before_mm', float('nan')):.4f} | "
                  f"{s.get('rmse_after_mm', float('nan')):.4f} | {sec:.0f} | {fitted} | "
                  f"{named} | {undecided} |", flush=True)


CREEP_SIZES = [("clean", {}), ("tau 20 s, -0.12 mm/V (default)", {"creep": {}}),
               ("tau 10 s, -0.08 mm/V", {"creep": {"tau_s": 10.0, "gain_mm_per_v": -0.08}}),
               ("tau 20 s, +0.12 mm/V", {"creep": {"tau_s": 20.0, "gain_mm_per_v": 0.12}}),
               ("tau 40 s, +0.1 mm/V", {"creep": {"tau_s": 40.0, "gain_mm_per_v": 0.1}}),
               ("tau 40 s, -0.12 mm/V", {"creep": {"tau_s": 40.0, "gain_mm_per_v": -0.12}})]


#: creeps of minutes, for records with long holds (``slowcreep``)
SLOW_CREEP_SIZES = [("clean", {}),
                    ("tau 60 s, -0.12 mm/V", {"creep": {"tau_s": 60.0, "gain_mm_per_v": -0.12}}),
                    ("tau 90 s, -0.08 mm/V", {"creep": {"tau_s": 90.0, "gain_mm_per_v": -0.08}}),
                    ("tau 120 s, -0.12 mm/V", {"creep": {"tau_s": 120.0,
                                                         "gain_mm_per_v": -0.12}}),
                    ("tau 60 s, +0.12 mm/V", {"creep": {"tau_s": 60.0, "gain_mm_per_v": 0.12}})]


def creepfit(seeds=(0, 1, 3), seconds=300.0, rate_hz=100.0, hold_s=(0.5, 5.0),
             sizes=CREEP_SIZES):
    from ipmc_model.diagnose import diagnose

    print(f"random 2.5 V steps held {hold_s[0]}-{hold_s[1]} s, {seconds:.0f} s at "
          f"{rate_hz:.0f} Hz; paired: the held-out gain with the other row budgets")
    print("| plant creep | seed | fitted tau (s) | fitted gain (mm/V) | hold beta (95 % lower) "
          "| signature | held-out RMSE (mm) | gain (paired) | accepted | in the data |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for seed in seeds:
        _, u = random_steps(seconds, rate_hz, 2.5, hold_s, seed=seed + 3)
        for label, fx in sizes:
            run = IpmcPlant(effects=fx, seed=seed, dt_s=1.0 / rate_hz).run(u)
            d = diagnose(run.t_s, run.u_v, run.y_mm, seed=seed, candidates=("creep",))
            c = d.candidates[0]
            ev = c.evidence
            nan = float("nan")
            p, hd = ev.get("params", {}), ev.get("hold_drift", {})
            print(f"| {label} | {seed} | {p.get('tau_s', nan):.1f} | "
                  f"{p.get('gain_mm_per_v', nan):+.3f} | "
                  f"{hd.get('beta') or nan:.2f} ({hd.get('lower') or nan:.2f}) | "
                  f"{'yes' if ev.get('significant') else 'no'} | {d.rmse_before_mm:.4f} -> "
                  f"{c.rmse_mm:.4f} | {100 * ev.get('improvement', nan):+.1f} % "
                  f"({', '.join(f'{100 * g:+.1f}' for g in ev.get('paired_improvements', []))})"
                  " | "
                  f"{'yes' if c.accepted else 'no'} | "
                  f"{'yes' if any(x is c for x in d.in_data()) else 'no'} |", flush=True)


STALE_CHANGES = (
    ("none", {}),
    ("dead zone 0.3 V", {"dead_zone": {"width_v": 0.3}}),
    ("dead zone 0.45 V", {"dead_zone": {"width_v": 0.45}}),
    ("saturation 3 mm", {"saturation": {"limit_mm": 3.0}}),
    ("saturation 2.5 mm", {"saturation": {"limit_mm": 2.5}}),
    ("drift 0.1 /min, 0.3 mm/min", {"drift": {"gain_loss_per_min": 0.1,
                                              "offset_mm_per_min": 0.3}}),
    ("asymmetry 0.7", {"asymmetry": {"negative_gain_ratio": 0.7}}),
    ("asymmetry 0.8", {"asymmetry": {"negative_gain_ratio": 0.8}}),
    ("rate 0.1 mm/(V/s)", {"rate_dependence": {"gain_mm_per_v_per_s": 0.1}}),
    ("rate 0.05 mm/(V/s)", {"rate_dependence": {"gain_mm_per_v_per_s": 0.05}}),
)


COMBO_CHANGES = (
    ("asymmetry 0.8 + drift", {"asymmetry": {"negative_gain_ratio": 0.8},
                               "drift": {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}}),
    ("asymmetry 0.8 + dead zone 0.3 V", {"asymmetry": {"negative_gain_ratio": 0.8},
                                         "dead_zone": {"width_v": 0.3}}),
    ("asymmetry 1.25 + drift", {"asymmetry": {"negative_gain_ratio": 1.25},
                                "drift": {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}}),
    ("saturation 3 mm + asymmetry 0.8", {"saturation": {"limit_mm": 3.0},
                                         "asymmetry": {"negative_gain_ratio": 0.8}}),
)


#: ``blind``: effect sizes no rule was designed on, for seeds no rule was designed on (60 and
#: above: keep them so). Around a clean day's model (``stale``) ...
BLIND_CHANGES = (
    ("none", {}),
    ("dead zone 0.38 V", {"dead_zone": {"width_v": 0.38}}),
    ("saturation 2.7 mm", {"saturation": {"limit_mm": 2.7}}),
    ("asymmetry 0.75", {"asymmetry": {"negative_gain_ratio": 0.75}}),
    ("rate 0.12 mm/(V/s)", {"rate_dependence": {"gain_mm_per_v_per_s": 0.12}}),
    ("drift 0.08 /min, 0.25 mm/min", {"drift": {"gain_loss_per_min": 0.08,
                                                "offset_mm_per_min": 0.25}}),
)
#: ... and without a model, on records with input holds (``effects``)
BLIND_CASES = (
    ("holds: none", {}, 120.0, True),
    ("holds: creep tau 15 s, -0.35 mm/V", {"creep": {"tau_s": 15.0, "gain_mm_per_v": -0.35}},
     120.0, True),
    ("holds: delay 0.15 s", {"delay": {"delay_s": 0.15}}, 120.0, True),
    ("holds: drift 0.08 /min, 0.25 mm/min", {"drift": {"gain_loss_per_min": 0.08,
                                                       "offset_mm_per_min": 0.25}}, 120.0, True),
)


def stale(tmp, seeds=(0, 1), amplitude=3.0, only=None, changes=STALE_CHANGES, extra=()):
    """A model from a clean day, given with --model, on a later day's record with a change
    (``only``: labels starting with one of these prefixes; "none" always runs)."""
    print(f"mixed input {amplitude} V, 120 s at 50 Hz; day 1 clean (seed S), day 2 seed S + 100")
    print("| day 2 plant | seed | found | fitted | held-out RMSE before -> after (mm) | wall |")
    print("|---|---|---|---|---|---|")
    for seed in seeds:
        def record(fx, sd, name):
            return _mixed_record(fx, 120.0, sd, Path(tmp) / f"{name}.csv", amplitude)

        _, _, s1 = run_cli(record({}, seed, f"day1_{seed}"), Path(tmp) / f"day1_{seed}",
                           extra=extra)
        for label, fx in changes:
            if only and label != "none" and not label.startswith(only):
                continue
            name = f"day2_{seed}_{label.replace(' ', '_').replace('/', '')}"
            code, sec, s = run_cli(record(fx, seed + 100, name), Path(tmp) / name,
                                   model=s1["model_before"])
            acc = [c["evidence"]["describe"] for c in s.get("candidates", []) if c["accepted"]]
            print(f"| {label} | {seed} | {', '.join(s.get('effects_found', [])) or 'none'} | "
                  f"{'; '.join(acc)} | {s.get('rmse_before_mm', 0):.4f} -> "
                  f"{s.get('rmse_after_mm', 0):.4f} | {sec:.0f} s |", flush=True)


#: ``creepmodel``: (label, day-1 plant, day-2 plant). The plant's default creep (20 s,
#: -0.12 mm/V) and a strong one (12 s, -0.6 mm/V).
CREEP_MODEL_CASES = (
    ("clean -> clean", {}, {}),
    ("clean -> creep 20 s", {}, {"creep": {}}),
    ("clean -> creep 12 s, -0.6", {}, {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}}),
    ("creep 20 s -> same", {"creep": {}}, {"creep": {}}),
    ("creep 12 s, -0.6 -> same", {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}},
     {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}}),
)


def creepmodel(tmp, seeds=(0, 1, 2, 3)):
    """Creep around a given model: day 1's baseline given with --model to a later day's record
    of the same kind (seed + 100). Day 1 is 120 s of :func:`plant_record` with input holds;
    its ``model_before`` is given, the baseline without effects whatever the diagnosis found
    there, as the paper's LSSVM-NARX has none. A model fitted on a creeping plant lacks the
    creep too: its 1.2 s window cannot hold one (session 34)."""
    print("120 s at 50 Hz, 0.6 x random sine + 1.5 V steps with input holds; day 1 seed S, "
          "day 2 seed S + 100")
    print("| day 1 -> day 2 plant | seed | found | fitted | held-out RMSE before -> after (mm) "
          "| wall |")
    print("|---|---|---|---|---|---|")
    for seed in seeds:
        day1 = {}  # one day-1 model per day-1 plant
        for label, fx1, fx2 in CREEP_MODEL_CASES:
            name = f"cm_{seed}_{label.replace(' ', '_').replace(',', '')}"
            key = repr(fx1)
            if key not in day1:
                p1 = save_csv(plant_record(fx1, 120.0, seed, holds=True),
                              Path(tmp) / f"{name}_day1.csv")
                day1[key] = run_cli(p1, Path(tmp) / f"{name}_day1")[2]
            s1 = day1[key]
            p2 = save_csv(plant_record(fx2, 120.0, seed + 100, holds=True),
                          Path(tmp) / f"{name}_day2.csv")
            code, sec, s = run_cli(p2, Path(tmp) / f"{name}_day2", model=s1["model_before"])
            acc = [c["evidence"]["describe"] for c in s.get("candidates", []) if c["accepted"]]
            print(f"| {label} | {seed} | {', '.join(s.get('effects_found', [])) or 'none'} | "
                  f"{'; '.join(acc)} | {s.get('rmse_before_mm', 0):.4f} -> "
                  f"{s.get('rmse_after_mm', 0):.4f} | {sec:.0f} s |", flush=True)


#: Baseline variants of ``baseline``: label -> keyword arguments of ``diagnose``.
BASELINE_VARIANTS = (
    ("tuned", {}),
    ("24 lags", {"input_lags": 24}),
    ("memory 1, 3, 10 s", {"memory_taus_s": (1.0, 3.0, 10.0)}),
)


def _baseline_row(t, u, y):
    """Held-out free-run RMSE (mm) of each baseline variant, of their runs' mean, of the
    committee (``diagnose(committee=True)``) and of the tuning grid's best, over the same
    samples; the grid's best (C, sigma); the share of the
    held-out samples beyond the fit part's displacement range, and of the tuned one's squared
    error on them."""
    from ipmc_model.diagnose import TUNING_GRID_C, TUNING_GRID_SIGMA, _held_out, diagnose

    def held(**kw):
        d = diagnose(t, u, y, candidates=(), **kw)
        return d.cut, _held_out(d.model_before, u, y, d.cut)[0], d.model_before.max_lag_

    runs = [held(**kw) for _, kw in BASELINE_VARIANTS]
    com = held(committee=True)
    grid = {(c, s): held(C=c, sigma=s) for c in TUNING_GRID_C for s in TUNING_GRID_SIGMA}
    cut = runs[0][0]
    lag = max(x[2] for x in runs + [com] + list(grid.values()))
    yh = y[cut:][lag:]
    scores = {g: float(np.sqrt(np.mean((yh - v[1][lag:]) ** 2))) for g, v in grid.items()}
    best = min(scores, key=scores.get)
    frees = ([x[1][lag:] for x in runs] + [np.mean([x[1][lag:] for x in runs], axis=0)]
             + [com[1][lag:]])
    res = [float(np.sqrt(np.mean((yh - f) ** 2))) for f in frees] + [scores[best]]
    e = yh - frees[0]
    out = (yh < y[:cut].min()) | (yh > y[:cut].max())
    return res, best, 100 * out.mean(), 100 * np.sum(e[out] ** 2) / np.sum(e ** 2)


def baseline(seeds=tuple(range(12))):
    """The diagnosis's baseline alone (no candidate) on clean records: where its held-out
    error comes from (tuning, window, range), and what the mean of the variants' free runs
    gives. Every RMSE is over the same held-out samples (after the longest variant's lags)."""
    labels = [v[0] for v in BASELINE_VARIANTS]
    print("clean plant, 50 Hz; held-out free-run RMSE (mm) of the baseline alone")
    print(f"| record | seed | {' | '.join(labels)} | mean of the {len(labels)} runs | committee "
          "(12, 18, 24 lags) | grid's best (C, sigma) | beyond the fit range: samples, squared "
          "error |")
    print("|---|---|" + "---|" * (len(labels) + 4))
    totals = np.zeros(len(labels) + 3)
    for kind in ("mixed 3 V, 120 s", "effects input, 90 s"):
        for seed in seeds:
            rec = _mixed_run({}, 120.0, seed) if kind.startswith("mixed") else \
                plant_record({}, 90.0, seed)
            res, best, share, err_share = _baseline_row(rec.t_s, rec.u_v, rec.y_mm)
            totals += res
            print(f"| {kind} | {seed} | {' | '.join(f'{x:.4f}' for x in res[:-1])} | "
                  f"{res[-1]:.4f} ({best[0]:g}, {best[1]:g}) | {share:.1f} %, "
                  f"{err_share:.1f} % |", flush=True)
    print(f"| sum | | {' | '.join(f'{x:.4f}' for x in totals)} | |")


def _convert(src, dst, cols, scale_y, rate=None):
    rows = list(csv.reader(open(src)))[1:]
    a = np.array([[float(r[c]) for c in cols] for r in rows])
    if rate is None:
        t, u, y = a[:, 0], a[:, 1], a[:, 2] * scale_y
    else:
        t = np.arange(len(a)) / rate
        u, y = a[:, 0], a[:, 1] * scale_y
    return save_csv(Record(t, u, y), dst)


def thirdparty(tmp):
    bw = _convert(DATA / "boucwen" / "train_multisine.csv", Path(tmp) / "boucwen.csv",
                  (0, 1), 1000.0, rate=750.0)
    pz = _convert(DATA / "piezo_smarthysteresis" / "hysteresis_v_150_1hz.csv",
                  Path(tmp) / "piezo.csv", (1, 3, 2), 1e-3)
    for label, p in (("boucwen train_multisine (N, mm)", bw), ("piezo 150 V 1 Hz (V, mm)", pz)):
        code, sec, s = run_cli(p, Path(tmp) / Path(p).stem)
        print(f"{label}: exit {code}, wall {sec:.0f} s, found {s.get('effects_found')}, "
              f"free-run RMSE {s.get('rmse_before_mm')} -> {s.get('rmse_after_mm')} mm",
              flush=True)
        for c in s.get("candidates", []):
            print(f"   {c['effect']}: {c['evidence'].get('text', '')}")


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "all"
    committee = "committee" in sys.argv[2:]
    sys.argv = [a for a in sys.argv if a != "committee"]
    extra = ["--committee"] if committee else []
    threadpool_limits(1)  # small solves; the machine is shared
    with tempfile.TemporaryDirectory() as tmp:
        if what in ("timing", "all"):
            timing(tmp, committee=committee)
        if what in ("effects", "all"):
            args = sys.argv[2:] if what == "effects" else []
            effects(tmp, tuple(int(a) for a in args if a.isdigit()) or (0, 1, 2),
                    only=tuple(a for a in args if not a.isdigit()) or None, extra=extra)
        if what in ("thirdparty", "all"):
            thirdparty(tmp)
        if what == "stale":
            args = sys.argv[2:]
            stale(tmp, tuple(int(a) for a in args if a.isdigit()) or (0, 1),
                  only=tuple(a for a in args if not a.isdigit()) or None, extra=extra)
        if what == "blind":
            seeds = tuple(int(a) for a in sys.argv[2:]) or (60, 61)
            stale(tmp, seeds, changes=BLIND_CHANGES, extra=extra)
            effects(tmp, seeds, cases=BLIND_CASES, extra=extra)
        if what == "combos":
            args = sys.argv[2:]
            stale(tmp, tuple(int(a) for a in args if a.isdigit()) or (0, 1, 2, 3),
                  only=tuple(a for a in args if not a.isdigit()) or None, changes=COMBO_CHANGES,
                  extra=extra)
        if what == "pairs":
            effects(tmp, tuple(int(a) for a in sys.argv[2:]) or (0, 1, 2, 3), cases=PAIR_CASES)
        if what == "creepmodel":
            creepmodel(tmp, tuple(int(a) for a in sys.argv[2:]) or (0, 1, 2, 3))
        if what == "baseline":
            baseline(tuple(int(a) for a in sys.argv[2:]) or tuple(range(12)))
        if what == "creepfit":
            creepfit(tuple(int(a) for a in sys.argv[2:]) or (0, 1, 3))
        if what == "slowcreep":
            creepfit(tuple(int(a) for a in sys.argv[2:]) or (0, 1, 2, 3), seconds=600.0,
                     rate_hz=50.0, hold_s=(5.0, 40.0), sizes=SLOW_CREEP_SIZES)
