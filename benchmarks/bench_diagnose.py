"""Benchmark of ``ipmc diagnose``: the acceptance table of the residual diagnosis, and its wall
time on 30 000 samples. Prints figures; not part of the pass/fail suite.

    .venv/bin/python benchmarks/bench_diagnose.py acceptance [--jobs 2] [--seed-offset N]
        [--core-direction-channels N] [--core-map linear|quadratic]
    .venv/bin/python benchmarks/bench_diagnose.py design [--jobs 2]
    .venv/bin/python benchmarks/bench_diagnose.py timing
    .venv/bin/python benchmarks/bench_diagnose.py second [--jobs 2] [--seed-offset N]

Two fixed sets of records, each a list of (plant, record kind, injected effects, given model,
seed): ``design`` (seeds 0-1, the effect sizes the rule and the candidates were developed on)
and ``acceptance`` (seeds 10-12, other sizes; fixed before the rule was judged on it). Both
hold the simulated IPMC and a plant of another structure (``ipmc_model/test/duhem_plant.py``:
Duhem hysteresis, a 0.8 s relaxation, polynomial output; its transport delay and its slow
relaxation are here injected effects, off in the clean twin), records with and without input
holds (240 s at 50 Hz), a given model (a clean day's core model) with what changed on a later
day, and two effects at once.

``second``: the acceptance set's records without input holds and without a given model, each
diagnosed, then the experiment that diagnosis proposes played on the same plant (another
noise seed) and diagnosed with the first record's findings known, as the second round of
``ipmc investigate``: an effect's verdict is its latest on a record that could test it, and
the record is right when the accepted ones are exactly the injected ones (the first round
also as scored below).

Scoring: a record is right when the effects found are exactly the injected ones; a creep or
a drift on a record without holds is right when it is reported not testable for lack of
holds and nothing else is named. The ratio compares the held-out free-run RMSE after the
diagnosis with its clean twin's (same plant, input and seed, no effect): goal <= 1.2.

``--core-direction-channels N``: the diagnosis's core model with direction memory on its N
fastest channels (``DiagnosisConfig.core_direction_channels``; the given model's day too):
the comparison behind its default of none. ``--core-map quadratic``: its output map a
quadratic spline instead of hinges (``DiagnosisConfig.core_map``), the comparison behind that
default.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "ros2_ws/src/ipmc_model/test"))

RATE = 50.0
SECONDS = 240.0


@dataclass(frozen=True)
class Case:
    plant: str        # "ipmc" or "duhem"
    holds: bool       # input holds (the sine off during every other step)
    effects: tuple    # ((name, params), ...) injected
    given: tuple      # effects of the given model's day; None: no given model
    seed: int

    @property
    def names(self) -> list[str]:
        return sorted(n for n, _ in self.effects)

    def label(self) -> str:
        fx = " + ".join(f"{n} {_params(p)}" for n, p in self.effects) or "clean"
        return (f"{self.plant} {'holds' if self.holds else 'moving'} "
                f"{'given ' if self.given is not None else ''}{fx} s{self.seed}")


def _params(p: dict) -> str:
    return ",".join(f"{v:g}" for v in p.values())


def _input(seconds: float, seed: int, holds: bool) -> np.ndarray:
    from ipmc_driver.signals import random_sine, random_steps

    _, us = random_sine(seconds, RATE, 2.5, (0.05, 1.0), 8, seed=seed + 2)
    _, st = random_steps(seconds, RATE, 1.5, (3.0, 10.0), seed=seed + 3)
    if holds:
        us = us * (np.cumsum(np.r_[0, np.diff(st) != 0]) % 2 == 0)
    return np.clip(0.6 * us + st, -3, 3)


def duhem_run(u: np.ndarray, effects: dict, seed: int) -> np.ndarray:
    """The Duhem plant with effects injected: dead zone and delay on its drive, an additive
    slow relaxation (creep) and a gain and offset drift on its output."""
    from duhem_plant import duhem_plant

    from ipmc_model.hysteresis import dead_zone, lowpass_bank

    dt = 1.0 / RATE
    uu = dead_zone(u, effects["dead_zone"]["width_v"]) if "dead_zone" in effects else u
    d = int(round(effects["delay"]["delay_s"] / dt)) if "delay" in effects else 0
    y = duhem_plant(uu, seed=seed, dt_s=dt, delay_samples=d, creep_share=0.0)
    if "creep" in effects:
        c = effects["creep"]
        y = y + c["gain_mm_per_v"] * lowpass_bank(u, (c["tau_s"],), dt)[0][:, 0]
    if "drift" in effects:
        t_min = np.arange(u.size) * dt / 60.0
        dr = effects["drift"]
        y = y * (1.0 - dr["gain_loss_per_min"] * t_min) + dr["offset_mm_per_min"] * t_min
    return y


def record(plant: str, effects: dict, seed: int, holds: bool):
    from ipmc_driver.dataio import Record

    u = _input(SECONDS, seed, holds)
    return Record(np.arange(u.size) / RATE, u, plant_run(plant, effects, seed, u))


def plant_run(plant: str, effects: dict, seed: int, u: np.ndarray) -> np.ndarray:
    """The measured tip (mm) of ``plant`` with ``effects`` under the voltages ``u``."""
    from ipmc_driver.plant import IpmcPlant

    if plant == "ipmc":
        return IpmcPlant(effects=effects, seed=seed, dt_s=1.0 / RATE).run(u).y_mm
    return duhem_run(u, effects, seed)


def _single(plant, seeds, sizes, kinds=(False, True)):
    out = []
    for seed in seeds:
        for holds in kinds:
            out.append(Case(plant, holds, (), None, seed))
            out += [Case(plant, holds, ((n, p),), None, seed) for n, p in sizes]
    return out


def _given(seeds, sizes):
    return [Case("ipmc", False, fx, (), seed) for seed in seeds for fx in [()] + sizes]


DESIGN = (
    _single("ipmc", (0, 1), [("creep", {"tau_s": 12.0, "gain_mm_per_v": -0.6}),
                             ("drift", {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}),
                             ("delay", {"delay_s": 0.2}), ("dead_zone", {"width_v": 0.3}),
                             ("rate_dependence", {"gain_mm_per_v_per_s": 0.1})])
    + _single("duhem", (0,), [("creep", {"tau_s": 20.0, "gain_mm_per_v": -0.3}),
                              ("delay", {"delay_s": 0.08}), ("dead_zone", {"width_v": 0.3}),
                              ("drift", {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3})])
    + _given((0,), [(("asymmetry", {"negative_gain_ratio": 0.7}),),
                    (("saturation", {"limit_mm": 3.0}),), (("dead_zone", {"width_v": 0.3}),)])
)

ACCEPTANCE = (
    _single("ipmc", (10, 11, 12), [
        ("creep", {"tau_s": 20.0, "gain_mm_per_v": -0.3}),
        ("drift", {"gain_loss_per_min": 0.05, "offset_mm_per_min": 0.15}),
        ("delay", {"delay_s": 0.12}), ("dead_zone", {"width_v": 0.25}),
        ("rate_dependence", {"gain_mm_per_v_per_s": 0.15})])
    + _single("duhem", (10, 11), [
        ("creep", {"tau_s": 30.0, "gain_mm_per_v": -0.25}),
        ("drift", {"gain_loss_per_min": 0.06, "offset_mm_per_min": 0.2}),
        ("delay", {"delay_s": 0.1}), ("dead_zone", {"width_v": 0.35})])
    + _given((10, 11), [(("asymmetry", {"negative_gain_ratio": 0.75}),),
                        (("saturation", {"limit_mm": 2.5}),),
                        (("dead_zone", {"width_v": 0.35}),), (("delay", {"delay_s": 0.1}),),
                        (("drift", {"gain_loss_per_min": 0.05, "offset_mm_per_min": 0.15}),)])
    + [Case("ipmc", True, (("creep", {"tau_s": 20.0, "gain_mm_per_v": -0.3}),
                           ("drift", {"gain_loss_per_min": 0.05, "offset_mm_per_min": 0.15})),
            None, s) for s in (10, 11)]
    + [Case("ipmc", False, (("dead_zone", {"width_v": 0.25}), ("delay", {"delay_s": 0.12})),
            None, s) for s in (10, 11)]
)


@dataclass(frozen=True)
class Outcome:
    case: Case
    found: tuple
    right: bool
    rmse_before_mm: float
    rmse_after_mm: float
    noise_mm: float
    seconds: float


#: Effects only input holds can show: without them each is right when reported not
#: testable for lack of holds.
NEED_HOLDS = ("creep", "drift")


def _is_right(case: Case, d) -> bool:
    found = sorted(d.effects_found)
    if found == case.names:
        return True
    if case.holds:
        return False
    untestable = {r.name for r in d.candidates
                  if r.outcome.value == "not testable" and "holds" in r.reason}
    lacking = [n for n in case.names if n in NEED_HOLDS]
    return (bool(lacking) and set(lacking) <= untestable
            and found == [n for n in case.names if n not in NEED_HOLDS])


def run_case(case: Case, config=None) -> Outcome:
    """One record diagnosed (``config``: the diagnosis's, None its default)."""
    from ipmc_model.diagnosis import DiagnosisConfig, diagnose
    from ipmc_model.diagnosis.record import DiagnosisRecord
    from ipmc_model.diagnosis.search import core_model

    config = config or DiagnosisConfig()

    with threadpool_limits(1):
        rec = record(case.plant, dict(case.effects), case.seed, case.holds)
        model = None
        if case.given is not None:  # a clean earlier day, seed + 100, same kind of input
            day1 = record(case.plant, dict(case.given), case.seed + 100, case.holds)
            model = core_model(DiagnosisRecord(day1.t_s, day1.u_v, day1.y_mm, config))
        t0 = time.perf_counter()
        # the cases run side by side, one per core: each diagnosis in its own process
        d = diagnose(rec.t_s, rec.u_v, rec.y_mm, model=model, config=config, jobs=1)
        return Outcome(case, tuple(d.effects_found), _is_right(case, d), d.rmse_before_mm,
                       d.rmse_after_mm, d.noise_floor_mm, time.perf_counter() - t0)


def table(cases, jobs: int, config=None) -> None:
    with ProcessPoolExecutor(jobs) as pool:
        results = list(pool.map(partial(run_case, config=config), cases))
    clean = {(r.case.plant, r.case.holds, r.case.given is not None, r.case.seed):
             r.rmse_after_mm for r in results if not r.case.effects}
    print("| record | found | right | RMSE before / after (mm) | after / clean twin | s |")
    print("|---|---|---|---|---|---|")
    ratios = []
    for r in results:
        c = r.case
        twin = clean.get((c.plant, c.holds, c.given is not None, c.seed))
        ratio = r.rmse_after_mm / twin if twin and c.effects else float("nan")
        ratios.append(ratio)
        print(f"| {c.label()} | {', '.join(r.found) or '-'} | {'yes' if r.right else 'NO'} | "
              f"{r.rmse_before_mm:.4f} / {r.rmse_after_mm:.4f} | {ratio:.2f} | "
              f"{r.seconds:.0f} |", flush=True)
    _totals(results, ratios)


def _totals(results, ratios) -> None:
    def share(rows, label, goal):
        n = len(rows)
        k = sum(r.right for r in rows)
        print(f"{label}: {k} / {n} right ({100 * k / max(n, 1):.0f} %; goal >= {goal} %)")

    single = [r for r in results if len(r.case.effects) == 1]
    share([r for r in single if r.case.given is None], "single effect, no given model", 90)
    share([r for r in single if r.case.given is not None], "single effect, a given model", 95)
    share([r for r in results if not r.case.effects], "clean records: nothing found", 95)
    share([r for r in results if len(r.case.effects) == 2], "two effects at once", 0)
    share([r for r in results if r.case.plant == "duhem" and r.case.effects],
          "of which the Duhem plant (effects)", 90)
    named = [i for i, r in enumerate(results) if r.right and r.case.effects and r.found]
    ok = sum(ratios[i] <= 1.2 for i in named)
    print(f"after the right effect, held-out RMSE within 1.2 x the clean twin's: {ok} / "
          f"{len(named)}")


@dataclass(frozen=True)
class SecondOutcome:
    """A record, the experiment its diagnosis proposed and what the two decided."""

    case: Case
    first: tuple
    first_right: bool
    decides: tuple          # what the experiment was proposed to decide; () if none
    experiment_s: float
    final: tuple            # accepted on the latest record that could test each effect
    right: bool


def latest_accepted(diagnoses) -> tuple:
    """Effects whose latest verdict on a record that could test them is 'accepted'."""
    latest = {}
    for d in diagnoses:
        for res in d.candidates:
            if res.outcome.value != "not testable":
                latest[res.name] = res.outcome.value
    return tuple(sorted(n for n, o in latest.items() if o == "accepted"))


def run_second(case: Case) -> SecondOutcome:
    from ipmc_model.diagnosis import diagnose
    from ipmc_model.diagnosis.search import diagnose_records

    with threadpool_limits(1):
        rec = record(case.plant, dict(case.effects), case.seed, case.holds)
        d1 = diagnose(rec.t_s, rec.u_v, rec.y_mm, jobs=1)
        first = (tuple(d1.effects_found), _is_right(case, d1))
        x = d1.next_experiment
        if x is None:
            final = tuple(sorted(d1.effects_found))
            return SecondOutcome(case, *first, (), 0.0, final, list(final) == case.names)
        # known as ipmc investigate passes them: the found effects the experiment is not for
        known = tuple(n for n in d1.effects_found if n not in x.decides)
        y2 = plant_run(case.plant, dict(case.effects), case.seed + 1000, x.u_v)
        d2 = diagnose_records([("experiment", np.arange(x.u_v.size) / RATE, x.u_v, y2,
                                x.parts)], known=known, jobs=1)
    final = latest_accepted([d1, d2])
    return SecondOutcome(case, *first, tuple(x.decides), x.duration_s, final,
                         list(final) == case.names)


def second(cases, jobs: int) -> None:
    """The moving records of ``cases`` without a given model, over two records (module doc)."""
    cases = [c for c in cases if not c.holds and c.given is None]
    print(f"of which without holds and without a given model: {len(cases)} records")
    print("| record | found on the record | right | experiment: decides, s | found after it "
          "| right |")
    print("|---|---|---|---|---|---|")
    results = []
    with ProcessPoolExecutor(jobs) as pool:
        for r in pool.map(run_second, cases):   # each row as soon as it and those before are
            results.append(r)
            print(f"| {r.case.label()} | {', '.join(r.first) or '-'} | "
                  f"{'yes' if r.first_right else 'NO'} | {', '.join(r.decides) or '-'}, "
                  f"{r.experiment_s:.0f} | {', '.join(r.final) or '-'} | "
                  f"{'yes' if r.right else 'NO'} |", flush=True)
    for label, rows in (("one effect", [r for r in results if len(r.case.effects) == 1]),
                        ("clean", [r for r in results if not r.case.effects]),
                        ("two effects", [r for r in results if len(r.case.effects) == 2])):
        print(f"{label}: right on the record {sum(r.first_right for r in rows)} / {len(rows)}, "
              f"after its experiment {sum(r.right for r in rows)} / {len(rows)}")


def timing() -> None:
    """30 000 samples (600 s at 50 Hz, creep on, input holds), no given model, on the cores
    this process may use (a round's candidates and a profile's refits run side by side):
    goal <= 60 s."""
    from ipmc_driver.plant import IpmcPlant
    from ipmc_model.diagnosis import diagnose

    u = _input(600.0, 0, True)
    run = IpmcPlant(effects={"creep": {}}, seed=0, dt_s=1.0 / RATE).run(u)
    t0 = time.perf_counter()
    d = diagnose(run.t_s, u, run.y_mm)
    from ipmc_model.diagnosis.parallel import cores

    print(f"timing: {u.size} samples, no given model, {cores()} cores: "
          f"{time.perf_counter() - t0:.1f} s "
          f"(goal <= 60 s); found {d.effects_found}, held-out RMSE {d.rmse_before_mm:.4f} -> "
          f"{d.rmse_after_mm:.4f} mm")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("section", choices=("acceptance", "design", "timing", "second"))
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--seed-offset", type=int, default=0,
                   help="shift every seed of the set: fresh records of the same kinds and sizes")
    p.add_argument("--core-direction-channels", type=int, default=0, metavar="N",
                   help="acceptance and design: the diagnosis's core model with direction "
                        "memory on N channels (DiagnosisConfig.core_direction_channels; "
                        "default 0, none)")
    p.add_argument("--core-map", default="linear", metavar="NAME",
                   help="acceptance and design: the core model's output map (linear: hinges, "
                        "the default; quadratic: a quadratic spline)")
    a = p.parse_args()
    for flag, value, default in (("--core-direction-channels", a.core_direction_channels, 0),
                                 ("--core-map", a.core_map, "linear")):
        if value != default and a.section in ("timing", "second"):
            p.error(f"{flag} applies to acceptance and design, not {a.section}")
    if a.section == "timing":
        timing()
        return
    from ipmc_model.diagnosis import DiagnosisConfig

    try:
        config = DiagnosisConfig(core_direction_channels=a.core_direction_channels,
                                 core_map=a.core_map)
    except ValueError as exc:
        p.error(str(exc))
    cases = DESIGN if a.section == "design" else ACCEPTANCE
    cases = [Case(c.plant, c.holds, c.effects, c.given, c.seed + a.seed_offset) for c in cases]
    print(f"{a.section} set: {len(cases)} records")
    if a.section == "second":
        second(cases, a.jobs)
    else:
        table(cases, a.jobs, config)


if __name__ == "__main__":
    main()
