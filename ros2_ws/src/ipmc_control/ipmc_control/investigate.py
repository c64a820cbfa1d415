"""``ipmc investigate``: the residual loop that designs and runs its own deciding experiment.

    ipmc investigate --sim|--rig PORT [--plant-effect NAME ...]
        [--first-input random-sine|steps|mixed] [--budget-min M] [--seed N] --report DIR

Round 1 plays a first excitation, records it and diagnoses the record (``ipmc diagnose``'s
procedure). When the diagnosis leaves an effect undecided for lack of the input that shows it
(creep or drift without input holds, a delay without steps, a dead zone without slow crossings
of 0 V) or accepts one the record cannot pin down (a creep's time constant left open), it
proposes the experiment that decides it; the next round plays that
experiment, records it and diagnoses it; and so on until nothing is undecided, an experiment
left its effects as undecided as before, the next experiment would decide only effects that
an earlier record able to show them decided, or it would overrun the budget of recorded
minutes.

Each new record is diagnosed on its own, from the diagnosis's core model refitted on its fit
part with the blocks of the effects earlier rounds accepted (``known``: fitted on this fit
part, not judged again; the new record was made for other effects and need not show them):
the experiment repeats the probes in its held-out part after an identification input, so
that record alone judges every candidate on the excitation that shows it, whereas blocks
fitted around the earlier record's frozen model would be judged against that model's errors.
Diagnosing all the records together (``ipmc diagnose --data A --data B``;
``residual_diagnoser(together=True)``) fits one core model to every excitation instead. That
joint fit is less biased where the core's misfit of the plant's small loops biases a
parameter fitted with one excitation (a dead zone's width), but its fit rows also carry each
excitation's own misfit, which a drift block can take up, and every round refits every
record (``benchmarks/bench_investigate.py --seeds 0 1 2 3 [--together]`` compares them).

The record comes from a runner: the simulated IPMC in this process (``--in-process``: fast),
the simulated plant in the lock-step ROS graph (``--sim``: ``ipmc bringup --sim --lockstep
--experiment FILE --record BAG``), or the rig through the driver (``--rig PORT``). Ctrl-C stops
the running graph (its last command is 0 V), keeps the records made so far readable and
writes the report of the finished rounds.

Files in DIR: ``summary.json``, ``report.md`` and per round ``round_N/`` with the input
played (``input.csv`` or ``experiment.json``), the record (``record.csv`` or ``bag/``) and the
diagnosis's report (``diagnosis/``: its summary, report, models before and after, and the next
experiment). Progress goes to stderr. No ROS import here: the graph runs as a command.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import subprocess
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from ipmc_model.diagnosis.experiment import ExperimentPart

#: Length of the first excitation (s): the diagnosis's fit part (70 %) then spans 84 s, three
#: time constants of a 12 s creep, the slowest relaxation it can then fit as a rival and size
#: the deciding holds by.
FIRST_SECONDS = 120.0
#: Default budget of recorded minutes for the whole investigation.
BUDGET_MIN = 20.0
#: At most this many rounds (records), whatever the budget.
MAX_ROUNDS = 6
#: The graph's sampling rate (ipmc bringup runs the plant, the driver and the excitation at
#: 100 Hz); the in-process plant may run at another.
GRAPH_RATE_HZ = 100.0
#: Seconds a stopped graph may take to exit after SIGINT before it is killed.
STOP_GRACE_S = 30.0


@dataclass(frozen=True)
class PlannedInput:
    """What one round plays: voltages ``u_v`` (V) at ``rate_hz``, the file that holds them (the
    graph plays it), what it is, its parts and the effects it is designed to decide."""

    u_v: np.ndarray
    rate_hz: float
    path: Path
    label: str
    parts: tuple[ExperimentPart, ...]
    decides: tuple[str, ...] = ()

    @property
    def duration_s(self) -> float:
        return self.u_v.size / self.rate_hz


@dataclass(frozen=True)
class Recorded:
    """A record: time (s), applied voltage (V), tip (mm; NaN where a sample was lost), where
    it was written, the parts of the experiment it played (its probes are where the diagnosis
    judges their effects) and what was lost on the way, if anything."""

    t_s: np.ndarray
    u_v: np.ndarray
    y_mm: np.ndarray
    path: Path
    parts: tuple[ExperimentPart, ...] = ()
    lost: str | None = None

    @property
    def duration_s(self) -> float:
        return float(self.u_v.size * np.median(np.diff(self.t_s)))


@dataclass(frozen=True)
class Verdicts:
    """What the diagnosis of the records so far decided, as the loop uses it."""

    outcomes: dict[str, str]
    reasons: dict[str, str]
    params: dict[str, dict]
    effects_found: tuple[str, ...]
    rmse_before_mm: float
    rmse_after_mm: float
    noise_floor_mm: float
    next_experiment: object | None
    report_dir: Path
    model_before: Path | None = None
    model_after: Path | None = None
    #: The records the diagnosis took (every record so far, or the newest alone).
    records: tuple[str, ...] = ()

    def undecided(self) -> tuple[str, ...]:
        """The effects the next experiment is designed to decide."""
        x = self.next_experiment
        return tuple(x.decides) if x is not None else ()


class Runner(Protocol):
    """Plays an input on a plant or rig and returns the record."""

    rate_hz: float

    def describe(self) -> str: ...

    def record(self, plan: PlannedInput, out_dir: Path) -> Recorded: ...


#: Diagnoses the records made so far (oldest first) into a report folder.
#: (records, report folder, effects earlier rounds accepted) -> the verdicts.
Diagnoser = Callable[[list[Recorded], Path, tuple[str, ...]], Verdicts]
Progress = Callable[[str], None]


@dataclass(frozen=True)
class InvestigationRound:
    """One round: what was undecided before it, what it played, the record, the verdicts."""

    number: int
    undecided: tuple[str, ...]
    played: PlannedInput
    record: Recorded
    verdicts: Verdicts
    wall_s: float

    @property
    def decided(self) -> dict[str, str]:
        """Outcome (accepted / rejected) of each effect this round was played to decide (the
        first round: every effect its record could test)."""
        want = self.undecided or tuple(self.verdicts.outcomes)
        return {n: o for n, o in self.verdicts.outcomes.items()
                if n in want and o != "not testable"}


@dataclass
class Investigation:
    """The whole investigation: its rounds, why it stopped, its budget."""

    runner: str
    budget_s: float
    rounds: list[InvestigationRound] = field(default_factory=list)
    stopped_because: str = ""
    interrupted: bool = False
    error: str = ""
    wall_s: float = 0.0

    @property
    def recorded_s(self) -> float:
        return float(sum(r.record.duration_s for r in self.rounds))

    @property
    def effects_found(self) -> list[str]:
        """Effects whose latest verdict on a record that could test them is 'accepted'."""
        latest: dict[str, str] = {}
        for rnd in self.rounds:
            for name, outcome in rnd.verdicts.outcomes.items():
                if outcome != "not testable":
                    latest[name] = outcome
        return [n for n, o in latest.items() if o == "accepted"]

    @property
    def undecided(self) -> tuple[str, ...]:
        """What the last round left undecided that no earlier record decided."""
        if not self.rounds:
            return ()
        done = settled_before(self.rounds)
        return tuple(n for n in self.rounds[-1].verdicts.undecided() if n not in done)

    @property
    def rmse_before_mm(self) -> float:
        """The first round's starting model on the first record's held-out part."""
        return self.rounds[0].verdicts.rmse_before_mm if self.rounds else float("nan")

    @property
    def rmse_after_mm(self) -> float:
        """The last model (every accepted effect) on the held-out part of the last diagnosis's
        records."""
        return self.rounds[-1].verdicts.rmse_after_mm if self.rounds else float("nan")


# -- inputs ---------------------------------------------------------------------------------
def first_input(kind: str, *, seconds: float, rate_hz: float, amplitude_v: float, seed: int,
                out_dir: Path) -> PlannedInput:
    """The first excitation (``ipmc bringup --excite KIND``'s voltages), written as
    ``out_dir/input.csv`` (t, u)."""
    from .excitation import make_excitation, save_csv

    exc = make_excitation(kind, amplitude_v=amplitude_v, seconds=seconds, rate_hz=rate_hz,
                          seed=seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = save_csv(exc, out_dir / "input.csv")
    why = {"random-sine": "a random sum of sines up to 0.8 Hz: the hysteresis loops of "
                          "tracking, no input holds",
           "steps": "held levels across the range: settling after each step",
           "mixed": "random sines, slow sines and short levels, then input holds at levels "
                    "spanning the range"}[kind]
    part = ExperimentPart(f"first input: {kind}", "", 0.0, exc.duration_s,
                     f"{why}; +-{amplitude_v:g} V")
    return PlannedInput(exc.u_v, exc.rate_hz, path, f"first input: {kind}, "
                        f"{exc.duration_s:.0f} s", (part,))


def experiment_input(experiment, out_dir: Path, after_round: int) -> PlannedInput:
    """The diagnosis's next experiment, written as ``out_dir/experiment.json`` (the format
    ``ipmc bringup --experiment`` plays)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "experiment.json"
    path.write_text(json.dumps(experiment.as_dict()) + "\n")
    parts = tuple(experiment.parts)
    return PlannedInput(np.asarray(experiment.u_v, dtype=float), float(experiment.rate_hz),
                        path, f"the experiment round {after_round} proposed, "
                        f"{experiment.duration_s:.0f} s", parts, tuple(experiment.decides))


# -- the loop -------------------------------------------------------------------------------
def settled(rounds) -> set[str]:
    """Effects a round judged on a record that could show them (accepted or rejected) and
    did not ask to probe again (an accepted creep whose time constant was left open does)."""
    out = set()
    for rnd in rounds:
        asked = set(rnd.verdicts.undecided())
        out |= {n for n, o in rnd.verdicts.outcomes.items()
                if o in ("accepted", "rejected") and n not in asked}
    return out


def settled_before(rounds) -> set[str]:
    """Effects the last round could not test that an earlier round settled."""
    last = rounds[-1].verdicts.outcomes
    return settled(rounds[:-1]) & {n for n, o in last.items() if o == "not testable"}


def stop_reason(inv: Investigation, max_rounds: int) -> str | None:
    """Why no further round is played, or None if the next experiment is."""
    last = inv.rounds[-1]
    nxt = last.verdicts.next_experiment
    if nxt is None:
        return "nothing undecided: every candidate effect the records can show was judged"
    if set(nxt.decides) <= settled_before(inv.rounds):
        return (f"nothing undecided: {', '.join(nxt.decides)}, which the last record could "
                f"not show, was decided by an earlier record that could")
    if last.undecided and set(last.verdicts.undecided()) >= set(last.undecided):
        return (f"the experiment played to decide {', '.join(last.undecided)} left it "
                "undecided: another such experiment would not decide it")
    if len(inv.rounds) >= max_rounds:
        return f"{max_rounds} rounds played"
    need_s = inv.recorded_s + nxt.duration_s
    if need_s > inv.budget_s:
        return (f"budget: the next experiment ({nxt.duration_s:.0f} s, deciding "
                f"{', '.join(nxt.decides)}) would bring the recorded time to "
                f"{need_s / 60:.1f} min, beyond {inv.budget_s / 60:g} min")
    return None


def play_round(number: int, plan: PlannedInput, undecided: tuple[str, ...], runner: Runner,
               diagnoser: Diagnoser, out_dir: Path, say: Progress,
               earlier: list[Recorded] | None = None, known: tuple[str, ...] = ()
               ) -> InvestigationRound:
    """Play ``plan``, record it and diagnose it with the ``earlier`` records into
    ``out_dir``, the ``known`` effects (earlier rounds') in the model it starts from, except
    those this round was played to decide (``undecided``): they are judged again."""
    t0 = time.monotonic()
    why = f" to decide {', '.join(undecided)}" if undecided else ""
    say(f"round {number}: playing {plan.label}{why} on {runner.describe()} (into {out_dir})")
    rec = runner.record(plan, out_dir)
    rec = replace(rec, parts=placed_parts(plan, rec, say))
    if rec.lost:
        say(f"round {number}: {rec.lost}")
    records = [*(earlier or []), rec]
    say(f"round {number}: recorded {rec.u_v.size} samples ({rec.duration_s:.0f} s) in "
        f"{rec.path}; diagnosing")
    verdicts = diagnoser(records, out_dir / "diagnosis",
                         tuple(k for k in known if k not in undecided))
    rnd = InvestigationRound(number, undecided, plan, rec, verdicts, time.monotonic() - t0)
    found = ", ".join(verdicts.effects_found) or "none"
    left = ", ".join(verdicts.undecided()) or "nothing"
    say(f"round {number}: effects found {found}; undecided {left}; held-out RMSE "
        f"{verdicts.rmse_before_mm:.4f} -> {verdicts.rmse_after_mm:.4f} mm "
        f"({rnd.wall_s:.0f} s)")
    return rnd


def placed_parts(plan: PlannedInput, rec: Recorded, say: Progress
                 ) -> tuple[ExperimentPart, ...]:
    """The plan's parts where the record played them (a recorder that started first leaves
    samples before them); none, so that every held-out row judges, if it did not play all."""
    from ipmc_model.diagnosis.experiment import played_parts

    if not plan.parts:
        return ()
    try:
        return played_parts(plan.parts, plan.u_v, rec.u_v, 1.0 / plan.rate_hz)
    except ValueError as exc:
        say(f"  {exc}: the record is split at the diagnosis's share, and every held-out "
            f"row judges each effect")
        return ()


def investigate(runner: Runner, first: PlannedInput, diagnoser: Diagnoser, out_dir: Path, *,
                budget_s: float, max_rounds: int = MAX_ROUNDS,
                progress: Progress | None = None) -> Investigation:
    """Run rounds (module doc) from the input ``first`` until nothing is undecided or the
    budget of recorded seconds ``budget_s`` is spent; a KeyboardInterrupt ends the
    investigation after the finished rounds (``interrupted``)."""
    say = progress or (lambda text: None)
    inv = Investigation(runner.describe(), float(budget_s))
    t0 = time.monotonic()
    plan, undecided = first, ()
    try:
        while True:
            n = len(inv.rounds) + 1
            inv.rounds.append(play_round(n, plan, undecided, runner, diagnoser,
                                         out_dir / f"round_{n}", say,
                                         [r.record for r in inv.rounds],
                                         tuple(inv.effects_found)))
            why = stop_reason(inv, max_rounds)
            if why is not None:
                inv.stopped_because = why
                break
            nxt = inv.rounds[-1].verdicts.next_experiment
            plan = experiment_input(nxt, out_dir / f"round_{n + 1}", n)
            undecided = plan.decides
    except KeyboardInterrupt:
        inv.interrupted = True
        inv.stopped_because = (f"interrupted during round {len(inv.rounds) + 1}; the records "
                               "made so far are kept")
    except (RuntimeError, ValueError, OSError) as exc:
        inv.error = f"round {len(inv.rounds) + 1}: {exc}"
        inv.stopped_because = f"error in {inv.error}"
    inv.wall_s = time.monotonic() - t0
    say(f"stopped: {inv.stopped_because}")
    return inv


# -- the diagnosis --------------------------------------------------------------------------
def verdicts_of(d, report_dir: Path, paths: dict) -> Verdicts:
    """The loop's view of an :class:`ipmc_model.diagnosis.Diagnosis`."""
    results = d.candidates
    params = {r.name: dict(r.evidence.params) for r in results
              if r.accepted and r.evidence is not None}
    return Verdicts(
        outcomes={r.name: r.outcome.value for r in results},
        reasons={r.name: r.reason for r in results}, params=params,
        effects_found=tuple(d.effects_found), rmse_before_mm=float(d.rmse_before_mm),
        rmse_after_mm=float(d.rmse_after_mm), noise_floor_mm=float(d.noise_floor_mm),
        next_experiment=d.next_experiment, report_dir=report_dir,
        model_before=Path(paths["model_before"]), model_after=Path(paths["model_after"]),
        records=tuple(seg.name for seg in d.segments))


def residual_diagnoser(candidates: list[str] | None = None, progress: Progress | None = None,
                       together: bool = False) -> Diagnoser:
    """The diagnosis of ``ipmc diagnose`` (own core model; ``candidates``: default all) of the
    newest record, starting from the effects earlier rounds accepted, or with ``together`` of
    every record so far at once (every effect judged again); its report written to the
    round's ``diagnosis/`` folder."""
    from ipmc_model.diagnosis.report import write_report
    from ipmc_model.diagnosis.search import diagnose_records

    def run(records: list[Recorded], report_dir: Path, known: tuple[str, ...] = ()
            ) -> Verdicts:
        records = records if together else records[-1:]
        d = diagnose_records([(str(r.path), r.t_s, r.u_v, r.y_mm, r.parts) for r in records],
                             candidates=candidates, known=() if together else known,
                             progress=(lambda text: progress("  " + text)) if progress else None)
        summary = write_report(d, report_dir, data_label=", ".join(str(r.path) for r in records))
        return verdicts_of(d, report_dir, summary)

    return run


# -- runners --------------------------------------------------------------------------------
class InProcessRunner:
    """The simulated IPMC (:class:`ipmc_driver.plant.IpmcPlant`) in this process, from rest
    each round, its sensor noise seeded ``seed`` plus the round; writes ``record.csv``.
    ``plant_params``: the plant's parameters (:func:`ipmc_driver.plant.load_plant_params`'s
    form; None: the shipped calibration)."""

    def __init__(self, effects: list[str], seed: int = 0, rate_hz: float = GRAPH_RATE_HZ,
                 plant_params: dict | None = None):
        self.effects, self.seed, self.rate_hz = list(effects), int(seed), float(rate_hz)
        self.plant_params = plant_params
        self._runs = 0

    def describe(self) -> str:
        fx = ", ".join(self.effects) or "no optional effect"
        own = "" if self.plant_params is None else ", parameters of its own"
        return f"the simulated IPMC in process ({fx}; {self.rate_hz:g} Hz{own})"

    def record(self, plan: PlannedInput, out_dir: Path) -> Recorded:
        from ipmc_driver.dataio import Record, save_csv
        from ipmc_driver.plant import IpmcPlant

        if abs(plan.rate_hz - self.rate_hz) > 1e-6 * self.rate_hz:
            raise ValueError(f"the input is sampled at {plan.rate_hz:g} Hz, the plant at "
                             f"{self.rate_hz:g} Hz")
        plant = IpmcPlant(self.plant_params, effects=self.effects, seed=self.seed + self._runs,
                          dt_s=1.0 / self.rate_hz)
        self._runs += 1
        run = plant.run(plan.u_v)
        path = save_csv(Record(run.t_s, run.u_v, run.y_mm), out_dir / "record.csv")
        return Recorded(run.t_s, run.u_v, run.y_mm, path)


class GraphRunner:
    """The ROS graph through ``ipmc bringup --experiment FILE --record BAG``: the simulated
    plant in lock-step (``rig_port`` None; faster than real time) or the rig through the driver
    on ``rig_port`` (real time); one bringup per round, its console in ``bringup.log``."""

    rate_hz = GRAPH_RATE_HZ

    def __init__(self, rig_port: str | None = None, effects: list[str] | None = None):
        self.rig_port, self.effects = rig_port, list(effects or [])

    def describe(self) -> str:
        if self.rig_port:
            return f"the rig on {self.rig_port} through the driver"
        fx = ", ".join(self.effects) or "no optional effect"
        return f"the simulated plant in the lock-step graph ({fx})"

    def argv(self, plan: PlannedInput, bag: Path) -> list[str]:
        """The bringup command that plays ``plan`` and records it to ``bag``."""
        cmd = [sys.executable, "-m", "ipmc_driver.cli", "bringup"]
        cmd += ["--rig", self.rig_port] if self.rig_port else ["--sim", "--lockstep"]
        cmd += ["--experiment", str(plan.path), "--record", str(bag)]
        for name in self.effects:
            cmd += ["--plant-effect", name]
        return cmd

    def timeout_s(self, plan: PlannedInput) -> float:
        """Wall seconds the run may take: real time on the rig, a lock-step plant at no less
        than a quarter of it, plus the graph's start and stop."""
        return plan.duration_s * (1.0 if self.rig_port else 4.0) + 120.0

    def record(self, plan: PlannedInput, out_dir: Path) -> Recorded:
        from ipmc_driver.dataio import ImplausibleDataWarning, load_record

        out_dir.mkdir(parents=True, exist_ok=True)
        bag = out_dir / "bag"
        with open(out_dir / "bringup.log", "w") as log:
            proc = subprocess.Popen(self.argv(plan, bag), stdout=log,
                                    stderr=subprocess.STDOUT)
            try:
                code = proc.wait(timeout=self.timeout_s(plan))
            except subprocess.TimeoutExpired:
                stop_process(proc)
                raise RuntimeError(f"ipmc bringup did not finish within "
                                   f"{self.timeout_s(plan):.0f} s; see {log.name}") from None
            except KeyboardInterrupt:
                stop_process(proc)
                raise
        if code != 0:
            hint = "" if self.rig_port else " (--in-process runs the simulated IPMC without ROS)"
            raise RuntimeError(f"ipmc bringup exited with code {code}; see "
                               f"{out_dir / 'bringup.log'}{hint}")
        notes: list[str] = []
        # a loaded machine or a rig's link loses samples: kept as rows not measured
        rec = load_record(bag, gaps=True, notes=notes)
        lost = next((n.rstrip(".") for n in notes if "not measured" in n), None)
        for note in notes:
            if "not measured" not in note:
                warnings.warn(note, ImplausibleDataWarning, stacklevel=2)
        return Recorded(rec.t_s - rec.t_s[0], rec.u_v, rec.y_mm, bag, lost=lost)


def stop_process(proc: subprocess.Popen) -> None:
    """SIGINT (bringup then stops its nodes, the commanders first with 0 V, the recorder
    last), SIGKILL after :data:`STOP_GRACE_S`."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# -- the command ----------------------------------------------------------------------------
def _parser() -> argparse.ArgumentParser:
    from ipmc_driver.plant import EFFECTS

    from .excitation import KINDS

    p = argparse.ArgumentParser(
        prog="ipmc investigate",
        description="The residual loop end to end: play a first excitation, record it, "
                    "diagnose it; while the diagnosis leaves an effect undecided for lack of "
                    "the input that shows it, play the experiment it proposes, record and "
                    "diagnose again, until nothing is undecided or the budget is spent.")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--sim", action="store_true",
                       help="the simulated plant in the lock-step ROS graph (default)")
    where.add_argument("--rig", metavar="PORT", help="the rig through the driver on PORT")
    p.add_argument("--in-process", action="store_true",
                   help="with --sim: the simulated IPMC in this process instead of the graph "
                        "(same plant, no ROS; several times faster)")
    p.add_argument("--plant-effect", action="append", default=[], choices=EFFECTS,
                   metavar="NAME", help=f"simulated plant effect (repeatable): "
                                        f"{', '.join(EFFECTS)}")
    p.add_argument("--first-input", choices=KINDS, default="random-sine",
                   help="the first excitation (default random-sine: no holds, no steps)")
    p.add_argument("--first-seconds", type=float, default=FIRST_SECONDS,
                   help=f"its length, s (default {FIRST_SECONDS:g})")
    p.add_argument("--amplitude-v", type=float, default=3.0,
                   help="its largest |voltage|, V (<= 3, the H-bridge's limit)")
    p.add_argument("--budget-min", type=float, default=BUDGET_MIN,
                   help=f"recorded minutes the investigation may spend (default {BUDGET_MIN:g})")
    p.add_argument("--rate-hz", type=float, default=GRAPH_RATE_HZ,
                   help=f"--in-process: the plant's sampling rate, Hz (the graph runs at "
                        f"{GRAPH_RATE_HZ:g})")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the first excitation and of the simulated sensor noise")
    p.add_argument("--report", required=True, metavar="DIR", help="output folder (new or empty)")
    return p


def runner_from(args: argparse.Namespace) -> Runner:
    """The runner the options ask for; a ValueError in one sentence for ones that clash."""
    if args.rig and (args.plant_effect or args.in_process):
        raise ValueError("--plant-effect and --in-process drive the simulated plant; the rig "
                         "(--rig) has its own physics")
    if args.in_process:
        return InProcessRunner(args.plant_effect, seed=args.seed, rate_hz=args.rate_hz)
    if args.rate_hz != GRAPH_RATE_HZ:
        raise ValueError(f"the graph samples at {GRAPH_RATE_HZ:g} Hz; --rate-hz is for "
                         "--in-process")
    return GraphRunner(args.rig, args.plant_effect)


def _progress(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


@contextlib.contextmanager
def _interruptible():
    """SIGINT and SIGTERM raise KeyboardInterrupt (the loop then stops the graph at 0 V and
    keeps the records), set explicitly: a process started with SIGINT ignored, as a script's
    background job is, would otherwise inherit that and run on. The old handlers come back."""
    sigs = (signal.SIGINT, signal.SIGTERM)
    old = {s: signal.signal(s, signal.default_int_handler) for s in sigs}
    try:
        yield
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ipmc investigate``; returns the exit code (130 after Ctrl-C)."""
    from .investigate_report import check_out_dir, write_investigation

    args = _parser().parse_args(argv)
    try:
        if not 0.0 < args.first_seconds <= 60.0 * args.budget_min:
            raise ValueError(f"the first input ({args.first_seconds:g} s) must fit the budget "
                             f"(--budget-min {args.budget_min:g})")
        runner = runner_from(args)
        out = check_out_dir(args.report)
        first = first_input(args.first_input, seconds=args.first_seconds,
                            rate_hz=runner.rate_hz, amplitude_v=args.amplitude_v,
                            seed=args.seed, out_dir=out / "round_1")
    except ValueError as exc:
        print(f"ipmc investigate: error: {exc}", file=sys.stderr)
        return 1
    with _interruptible():
        inv = investigate(runner, first, residual_diagnoser(progress=_progress), out,
                          budget_s=60.0 * args.budget_min, progress=_progress)
    summary = write_investigation(inv, out)
    if inv.error:
        print(f"ipmc investigate: error in {inv.error}", file=sys.stderr)
        return 1
    found = ", ".join(summary["effects_found"]) or "none"
    rmse = ("" if not inv.rounds else f"; held-out free-run RMSE {inv.rmse_before_mm:.4f} mm "
            f"before, {inv.rmse_after_mm:.4f} mm after")
    print(f"effects found: {found}{rmse}; {len(inv.rounds)} rounds, "
          f"{inv.recorded_s / 60:.1f} min recorded; report in {out}")
    return 130 if inv.interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
