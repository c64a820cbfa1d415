"""ipmc investigate: the round logic with a stand-in runner and diagnosis (fast), and the loop on
the simulated IPMC in process (a creep hidden by a random sine; a clean plant)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from ipmc_control.excitation import load_excitation
from ipmc_control.investigate import (
    GraphRunner,
    InProcessRunner,
    InvestigationRound,
    PlannedInput,
    Recorded,
    Verdicts,
    first_input,
    investigate,
    main,
    residual_diagnoser,
)
from ipmc_control.investigate_report import write_investigation
from ipmc_model.diagnosis.experiment import Experiment, ExperimentPart

RATE_HZ = 50.0
HISTORY = re.compile(r"\bsessions?\b|\bmust[- ]shows?\b|\bissue \d", re.IGNORECASE)


class StandInRunner:
    """Records the input with a zero tip; counts its runs."""

    rate_hz = RATE_HZ

    def __init__(self, interrupt_on: int | None = None):
        self.played: list[PlannedInput] = []
        self.interrupt_on = interrupt_on

    def describe(self) -> str:
        return "a stand-in plant"

    def record(self, plan: PlannedInput, out_dir: Path) -> Recorded:
        self.played.append(plan)
        if len(self.played) == self.interrupt_on:
            raise KeyboardInterrupt
        out_dir.mkdir(parents=True, exist_ok=True)
        t = np.arange(plan.u_v.size) / plan.rate_hz
        return Recorded(t, plan.u_v, np.zeros_like(t), out_dir / "record.csv")


def creep_experiment(seconds: float = 100.0) -> Experiment:
    n = int(seconds * RATE_HZ)
    u = np.concatenate([np.full(n // 2, 2.0), np.full(n - n // 2, -2.0)])
    part = ExperimentPart("creep probe", "creep", 0.0, seconds, "holds of 36 s")
    return Experiment(RATE_HZ, 0.7, u, (part,))


def stand_in_diagnoser(script: list[tuple[dict, Experiment | None]], together: bool = False):
    """Round k's diagnosis returns script[k] (outcomes, next experiment); the last repeats.
    It says it took every record so far (``together``) or the newest alone."""
    calls = []

    def run(records: list[Recorded], report_dir: Path, known: tuple[str, ...] = ()
            ) -> Verdicts:
        outcomes, nxt = script[min(len(calls), len(script) - 1)]
        calls.append(records)
        run.known.append(known)
        found = tuple(n for n, o in outcomes.items() if o == "accepted")
        return Verdicts(outcomes, {n: f"{n} was {o}" for n, o in outcomes.items()},
                        {n: {"taus_s": [12.0]} for n in found}, found, 0.02,
                        0.01 if found else 0.02, 0.005, nxt, report_dir,
                        records=tuple(str(r.path) for r in records[0 if together else -1:]))

    run.calls, run.known = calls, []
    return run


def _first(tmp_path: Path) -> PlannedInput:
    return first_input("random-sine", seconds=60.0, rate_hz=RATE_HZ, amplitude_v=3.0, seed=1,
                       out_dir=tmp_path / "round_1")


UNDECIDED = ({"creep": "not testable", "delay": "rejected"}, creep_experiment())
DELAY_FOUND = ({"creep": "not testable", "delay": "accepted"}, creep_experiment())
DECIDED = ({"creep": "accepted", "delay": "rejected"}, None)


def test_rounds_play_the_proposed_experiment_until_nothing_is_undecided(tmp_path):
    runner = StandInRunner()
    diagnoser = stand_in_diagnoser([UNDECIDED, DECIDED])
    inv = investigate(runner, _first(tmp_path), diagnoser, tmp_path, budget_s=600.0)
    assert [r.number for r in inv.rounds] == [1, 2]
    # each round diagnoses every record made so far, oldest first
    assert [len(c) for c in diagnoser.calls] == [1, 2]
    assert diagnoser.calls[1][0] is inv.rounds[0].record
    first, second = inv.rounds
    assert first.undecided == () and first.decided == {"delay": "rejected"}
    assert second.undecided == ("creep",) and second.decided == {"creep": "accepted"}
    np.testing.assert_array_equal(runner.played[1].u_v, creep_experiment().u_v)
    played = load_excitation(runner.played[1].path, RATE_HZ)   # what bringup would play
    np.testing.assert_allclose(played.u_v, creep_experiment().u_v, atol=1e-4)
    assert inv.effects_found == ["creep"]
    assert inv.stopped_because.startswith("nothing undecided")
    assert inv.rmse_before_mm == 0.02 and inv.rmse_after_mm == 0.01


def test_summary_and_report_tell_each_round(tmp_path):
    inv = investigate(StandInRunner(), _first(tmp_path), stand_in_diagnoser([UNDECIDED, DECIDED]),
                      tmp_path, budget_s=600.0)
    summary = write_investigation(inv, tmp_path)
    doc = json.loads((tmp_path / "summary.json").read_text())
    assert doc == summary
    assert {"effects_found", "rmse_before_mm", "rmse_after_mm", "rounds"} <= set(doc)
    assert [set(r) >= {"undecided", "experiment", "decided"} for r in doc["rounds"]] == [True] * 2
    assert doc["rounds"][1]["undecided"] == ["creep"]
    assert doc["rounds"][1]["experiment"]["parts"][0]["reason"] == "holds of 36 s"
    assert doc["rounds"][1]["decided"] == {"creep": "accepted"}
    report = (tmp_path / "report.md").read_text()
    assert "## Round 2" in report and "Undecided before it: creep" in report
    assert "holds of 36 s" in report
    assert not HISTORY.search(report + json.dumps(doc))
    assert "Each new record is diagnosed on its own" in report


def test_the_report_says_when_every_record_was_diagnosed_together(tmp_path):
    inv = investigate(StandInRunner(), _first(tmp_path),
                      stand_in_diagnoser([UNDECIDED, DECIDED], together=True), tmp_path,
                      budget_s=600.0)
    write_investigation(inv, tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert "Each round diagnoses every record so far together" in report
    assert "diagnosed on its own" not in report


class LossyRunner(StandInRunner):
    """Loses 42 samples of every record (y NaN, as ``load_record(gaps=True)`` keeps them)."""

    def record(self, plan: PlannedInput, out_dir: Path) -> Recorded:
        rec = super().record(plan, out_dir)
        y = rec.y_mm.copy()
        y[100:142] = np.nan
        return replace(rec, y_mm=y, lost="bag: 42 of ... samples were not measured")


def test_a_round_says_what_its_record_lost(tmp_path):
    said: list[str] = []
    inv = investigate(LossyRunner(), _first(tmp_path), stand_in_diagnoser([DECIDED]), tmp_path,
                      budget_s=600.0, progress=said.append)
    assert any(line.startswith("round 1: bag: 42 of") for line in said)
    doc = write_investigation(inv, tmp_path)
    assert doc["rounds"][0]["samples_lost"] == 42
    assert "Lost on the way: bag: 42 of" in (tmp_path / "report.md").read_text()


def test_the_budget_stops_before_an_experiment_that_would_overrun_it(tmp_path):
    runner = StandInRunner()
    inv = investigate(runner, _first(tmp_path), stand_in_diagnoser([UNDECIDED]), tmp_path,
                      budget_s=120.0)
    assert len(runner.played) == 1
    assert inv.stopped_because.startswith("budget") and inv.undecided == ("creep",)


def test_an_experiment_that_leaves_its_effect_undecided_is_not_repeated(tmp_path):
    runner = StandInRunner()
    inv = investigate(runner, _first(tmp_path), stand_in_diagnoser([UNDECIDED]), tmp_path,
                      budget_s=3600.0)
    assert len(runner.played) == 2
    assert "left it undecided" in inv.stopped_because


def test_an_experiment_for_effects_earlier_records_decided_is_not_played(tmp_path):
    """The creep's experiment cannot show the dead zone round 1 accepted; its probe is not
    worth another round."""
    n = int(40 * RATE_HZ)
    crossing = Experiment(RATE_HZ, 0.7, np.linspace(-0.5, 0.5, n),
                          (ExperimentPart("dead_zone probe", "dead_zone", 0.0, 40.0, "slow"),))
    runner = StandInRunner()
    inv = investigate(runner, _first(tmp_path), stand_in_diagnoser([
        ({"dead_zone": "accepted", "creep": "not testable"}, creep_experiment()),
        ({"dead_zone": "not testable", "creep": "accepted"}, crossing)]), tmp_path,
        budget_s=3600.0)
    assert len(runner.played) == 2
    assert inv.stopped_because.startswith("nothing undecided: dead_zone, which the last")
    assert inv.undecided == ()
    assert sorted(inv.effects_found) == ["creep", "dead_zone"]


def test_an_effect_the_last_record_judged_and_asks_to_pin_down_goes_on(tmp_path):
    """Rejected on round 1's record, accepted on round 2's with its time constant left open:
    the holds that pin it down are played, whatever round 1 said."""
    steps = Experiment(RATE_HZ, 0.7, np.repeat([1.0, -1.0] * 10, int(2 * RATE_HZ)),
                       (ExperimentPart("delay probe", "delay", 0.0, 40.0, "steps"),))
    runner = StandInRunner()
    inv = investigate(runner, _first(tmp_path), stand_in_diagnoser([
        ({"creep": "rejected", "delay": "not testable"}, steps),
        ({"creep": "accepted", "delay": "accepted"}, creep_experiment(200.0)),
        ({"creep": "accepted", "delay": "not testable"}, None)]), tmp_path, budget_s=3600.0)
    assert len(runner.played) == 3 and inv.effects_found == ["creep", "delay"]


def test_ctrl_c_keeps_the_finished_rounds(tmp_path):
    inv = investigate(StandInRunner(interrupt_on=2), _first(tmp_path),
                      stand_in_diagnoser([UNDECIDED, DECIDED]), tmp_path, budget_s=600.0)
    assert inv.interrupted and len(inv.rounds) == 1
    assert inv.stopped_because.startswith("interrupted during round 2")
    assert write_investigation(inv, tmp_path)["rounds"][0]["undecided"] == []


def test_the_graph_runner_plays_the_file_through_bringup(tmp_path):
    plan = _first(tmp_path)
    sim = GraphRunner(None, ["creep"]).argv(plan, tmp_path / "bag")
    assert sim[-8:] == ["--sim", "--lockstep", "--experiment", str(plan.path), "--record",
                        str(tmp_path / "bag"), "--plant-effect", "creep"]
    rig = GraphRunner("/dev/pts/7").argv(plan, tmp_path / "bag")
    assert rig[4:6] == ["--rig", "/dev/pts/7"] and "--plant-effect" not in rig


def test_refusals_name_the_option(tmp_path, capsys):
    assert main(["--rig", "/dev/null", "--plant-effect", "creep", "--report",
                 str(tmp_path / "a")]) == 1
    assert "--plant-effect" in capsys.readouterr().err
    assert main(["--budget-min", "1", "--report", str(tmp_path / "b")]) == 1
    assert "budget" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()


def test_importing_the_core_leaves_rclpy_out():
    code = ("import sys, ipmc_control.investigate, ipmc_control.investigate_report; "
            "assert 'rclpy' not in sys.modules, 'rclpy imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_round_says_what_it_decided():
    v = Verdicts({"creep": "not testable", "delay": "accepted"}, {}, {}, ("delay",), 0.1, 0.1,
                 0.01, None, Path("d"))
    t = np.arange(3.0)
    rnd = InvestigationRound(1, (), PlannedInput(t, 1.0, Path("i"), "x", ()),
                             Recorded(t, t, t, Path("r")), v, 0.0)
    assert rnd.decided == {"delay": "accepted"}


# -- the loop on the simulated IPMC in process (each investigation runs once per module) ------
def _investigate_in_process(tmp_path_factory, *effects: str) -> dict:
    out = tmp_path_factory.mktemp("investigation") / "report"
    argv = ["--sim", "--in-process", "--rate-hz", str(RATE_HZ), "--first-input", "random-sine",
            "--seed", "0", "--report", str(out)]
    for name in effects:
        argv += ["--plant-effect", name]
    with threadpool_limits(1):   # BLAS threads spinning on a shared machine slow fits ~10x
        assert main(argv) == 0
    return json.loads((out / "summary.json").read_text()) | {"dir": out}


@pytest.fixture(scope="module")
def creep_run(tmp_path_factory) -> dict:
    return _investigate_in_process(tmp_path_factory, "creep")


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory) -> dict:
    return _investigate_in_process(tmp_path_factory)


def clean_twin_rmse_mm(round_dir: Path) -> float:
    """Held-out free-run RMSE of the diagnosis's core model on the clean simulated IPMC under
    the voltages of the round's record, split where the experiment it played marks."""
    from ipmc_driver.dataio import load_record
    from ipmc_driver.plant import IpmcPlant
    from ipmc_model.diagnosis.experiment import read_experiment
    from ipmc_model.diagnosis.search import diagnose_records

    u = load_record(round_dir / "record.csv").u_v
    parts = read_experiment(round_dir / "experiment.json")[0]   # played in process: no lag
    run = IpmcPlant(seed=7, dt_s=1.0 / RATE_HZ).run(u)
    return diagnose_records([("clean", run.t_s, u, run.y_mm, parts)],
                            candidates=[]).rmse_before_mm


@pytest.mark.timeout(240)
def test_creep_hidden_by_a_random_sine_is_named_after_the_proposed_experiment(creep_run):
    first, second = creep_run["rounds"]
    # neither a creep nor a drift shows on a moving input; the creep's holds decide both
    assert first["left_undecided"] == ["creep", "drift"]
    assert "0 input holds" in first["reasons"]["creep"]
    probes = [p for p in second["experiment"]["parts"] if p["effect"] == "creep"]
    assert len(probes) == 2 and all("holds of" in p["reason"] for p in probes)
    assert all(p["effect"] != "drift" for p in second["experiment"]["parts"])
    assert second["undecided"] == ["creep", "drift"] and second["decided"]["creep"] == "accepted"
    assert second["decided"]["drift"] == "rejected"
    assert creep_run["effects_found"] == ["creep"] and creep_run["undecided"] == []
    creep = second["params"]["creep"]   # the plant's creep: 20 s, -0.12 mm per V of charge
    lo, hi = creep["tau_ci_s"]
    assert lo < 20.0 < hi and hi < 60.0
    assert -0.2 < creep["gain_mm_per_v"] < -0.07
    # the error left is the core model's own on this experiment: within 1.2x that of the
    # same input on the clean plant (its core fitted and judged the same way)
    clean = clean_twin_rmse_mm(creep_run["dir"] / "round_2")
    assert second["rmse_after_mm"] < min(1.2 * clean, second["rmse_before_mm"])
    assert (creep_run["dir"] / "round_2" / "record.csv").is_file()
    assert Path(creep_run["model_after"]).is_file()


@pytest.mark.timeout(180)
def test_a_clean_plant_stops_with_nothing_found(clean_run):
    assert clean_run["effects_found"] == [] and clean_run["undecided"] == []
    assert len(clean_run["rounds"]) <= 2
    assert clean_run["stopped_because"].startswith("nothing undecided")


def test_help_describes_the_loop(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "--first-input" in text and "--budget-min" in text and "--in-process" in text
    assert not HISTORY.search(text)


def test_the_next_round_starts_from_the_effects_earlier_rounds_accepted(tmp_path):
    # round 1 accepts a delay and cannot test creep; round 2's record is made for creep and
    # its diagnosis starts from a model with the delay in it
    diagnoser = stand_in_diagnoser([DELAY_FOUND, ({"creep": "accepted"}, None)])
    inv = investigate(StandInRunner(), _first(tmp_path), diagnoser, tmp_path, budget_s=600.0)
    assert diagnoser.known == [(), ("delay",)]
    assert sorted(inv.effects_found) == ["creep", "delay"]


def test_an_accepted_effect_a_round_was_played_to_pin_down_is_judged_again(tmp_path):
    # round 1 accepts creep but leaves its time constant open; round 2 is played to decide it,
    # so its diagnosis judges creep again instead of starting from it
    pin_down = ({"creep": "accepted", "delay": "rejected"}, creep_experiment())
    diagnoser = stand_in_diagnoser([pin_down, ({"creep": "rejected"}, None)])
    inv = investigate(StandInRunner(), _first(tmp_path), diagnoser, tmp_path, budget_s=600.0)
    assert inv.rounds[1].undecided == ("creep",)
    assert diagnoser.known == [(), ()]
    assert inv.effects_found == []


def test_the_diagnoser_takes_the_newest_record_or_every_record_together(tmp_path):
    from ipmc_driver.plant import IpmcPlant
    from ipmc_driver.signals import random_sine

    records = []
    for i in range(2):
        u = random_sine(40.0, RATE_HZ, 2.5, band_hz=(0.05, 1.0), seed=i)[1]
        run = IpmcPlant(seed=i, dt_s=1.0 / RATE_HZ).run(u)
        records.append(Recorded(run.t_s, run.u_v, run.y_mm, tmp_path / f"r{i}.csv"))
    for together, names in ((False, [str(records[1].path)]),
                            (True, [str(r.path) for r in records])):
        out = tmp_path / f"together_{together}"
        verdicts = residual_diagnoser(["drift"], together=together)(records, out)
        summary = json.loads((out / "summary.json").read_text())
        assert [r["name"] for r in summary["records"]] == names == list(verdicts.records)
        assert verdicts.rmse_before_mm == pytest.approx(summary["rmse_before_mm"])


def test_the_parts_are_placed_where_the_record_played_them(tmp_path):
    """A record that began before the experiment (a recorder started first) has its probes
    where it played them; one that did not play all of it is judged on every held-out row."""
    from ipmc_control.investigate import placed_parts
    from ipmc_model.diagnosis.experiment import holds

    u = np.concatenate([holds([1.0, -1.0], 2.0, RATE_HZ), holds([0.5, 0.0], 1.0, RATE_HZ)])
    parts = (ExperimentPart("creep probe", "creep", 0.0, 4.0, "holds"),
             ExperimentPart("delay probe", "delay", 4.0, 2.0, "steps"))
    plan = PlannedInput(u, RATE_HZ, tmp_path / "x.json", "experiment", parts, ("creep",))
    lead = np.zeros(int(1.5 * RATE_HZ))
    t = np.arange(lead.size + u.size) / RATE_HZ
    said: list[str] = []
    rec = Recorded(t, np.r_[lead, u], t * 0.0, tmp_path / "r.csv")
    placed = placed_parts(plan, rec, said.append)
    assert [p.start_s for p in placed] == pytest.approx([1.5, 5.5])
    assert said == []
    short = Recorded(t[:100], u[:100], t[:100] * 0.0, tmp_path / "s.csv")
    assert placed_parts(plan, short, said.append) == ()
    assert len(said) == 1 and "shorter than the experiment" in said[0]


def test_the_in_process_runner_plays_a_plant_of_the_parameters_given(tmp_path):
    """Without its hysteresis the simulated IPMC bends otherwise under the same input (by
    more than its sensor's noise), and without sensor noise its record does not depend on
    the noise's seed."""
    from ipmc_driver.plant import load_plant_params

    plan = _first(tmp_path)
    shipped = load_plant_params()
    quiet = {**shipped, "noise_std_mm": 0.0, "resolution_mm": 0.0}
    ys = [InProcessRunner([], seed=seed, rate_hz=RATE_HZ, plant_params=params)
          .record(plan, tmp_path / f"{name}_{seed}").y_mm
          for name, params in (("quiet", quiet), ("no_hysteresis", {**quiet, "hyst_weight": 0.0}))
          for seed in (0, 7)]
    assert np.array_equal(ys[0], ys[1]) and np.array_equal(ys[2], ys[3])
    assert np.sqrt(np.mean((ys[0] - ys[2]) ** 2)) > shipped["noise_std_mm"]
    assert "parameters of its own" in InProcessRunner([], plant_params=quiet).describe()
