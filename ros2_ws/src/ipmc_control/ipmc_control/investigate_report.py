"""The files of ``ipmc investigate``: ``summary.json`` and ``report.md``. Decides nothing: it
writes what :mod:`ipmc_control.investigate` played and what each diagnosis decided."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from ipmc_model.diagnosis.experiment import ExperimentPart

from .investigate import Investigation, InvestigationRound

METRIC = ("free-run RMSE (mm) on a record's held-out part (the first record's last 30 %; an "
          "experiment's record: the last copies of its probes), the model run from the "
          "record's start on its input alone; before: the first round's starting model on "
          "the first record; after: the last round's model (every effect it accepted) on the "
          "last record, whose held-out part repeats the deciding probes")


def check_out_dir(path) -> Path:
    """The report folder: created if missing; refused if it is a file or already holds an
    investigation (records are never written over)."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--report {out} is a file; give a folder (it is created if missing)")
    if (out / "summary.json").exists() or (out / "round_1").exists():
        raise ValueError(f"--report {out} holds an investigation already; give a new folder")
    out.mkdir(parents=True, exist_ok=True)
    if not os.access(out, os.W_OK):
        raise ValueError(f"--report {out} cannot be written")
    return out


def _num(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _json_safe(o):
    """Plain JSON: numpy numbers as Python ones, non-finite numbers as null."""
    if isinstance(o, dict):
        return {str(k): _json_safe(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_json_safe(v) for v in o]
    if hasattr(o, "item") and not isinstance(o, (str, bytes)):
        o = o.item()
    return _num(o) if isinstance(o, float) else o


def _part(p: ExperimentPart) -> dict:
    return {"name": p.name, "effect": p.effect, "start_s": p.start_s,
            "duration_s": p.duration_s, "reason": p.reason, "held_out": p.held_out}


def round_summary(r: InvestigationRound) -> dict:
    """One round as JSON: what was undecided, what was played, what it decided."""
    v, plan = r.verdicts, r.played
    return {
        "number": r.number,
        "undecided": list(r.undecided),
        "experiment": {"label": plan.label, "path": str(plan.path),
                       "duration_s": plan.duration_s, "decides": list(plan.decides),
                       "parts": [_part(p) for p in plan.parts]},
        "decided": r.decided,
        "left_undecided": list(v.undecided()),
        "effects_found": list(v.effects_found),
        "params": v.params,
        "reasons": v.reasons,
        "rmse_before_mm": _num(v.rmse_before_mm),
        "rmse_after_mm": _num(v.rmse_after_mm),
        "noise_floor_mm": _num(v.noise_floor_mm),
        "record": str(r.record.path),
        "recorded_s": r.record.duration_s,
        "samples_lost": int(np.sum(~np.isfinite(r.record.y_mm))),
        "wall_s": r.wall_s,
        "diagnosis": str(v.report_dir),
        "model_before": str(v.model_before) if v.model_before else None,
        "model_after": str(v.model_after) if v.model_after else None,
    }


def summary_of(inv: Investigation) -> dict:
    """The investigation as JSON (``summary.json``)."""
    last = inv.rounds[-1].verdicts if inv.rounds else None
    return {
        "effects_found": inv.effects_found,
        "rmse_before_mm": _num(inv.rmse_before_mm),
        "rmse_after_mm": _num(inv.rmse_after_mm),
        "metric": METRIC,
        "undecided": list(inv.undecided),
        "stopped_because": inv.stopped_because,
        "interrupted": inv.interrupted,
        "error": inv.error or None,
        "runner": inv.runner,
        "budget_min": inv.budget_s / 60.0,
        "recorded_min": inv.recorded_s / 60.0,
        "wall_s": inv.wall_s,
        "model_after": str(last.model_after) if last and last.model_after else None,
        "rounds": [round_summary(r) for r in inv.rounds],
    }


def write_investigation(inv: Investigation, out_dir) -> dict:
    """Write ``summary.json`` and ``report.md`` to ``out_dir``; return the summary."""
    out = Path(out_dir)
    summary = _json_safe(summary_of(inv))
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
    (out / "report.md").write_text(markdown(inv, summary, out))
    return summary


def _rel(path, out: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(out.resolve()))
    except ValueError:
        return str(path)


def _mm(x: float | None) -> str:
    return "-" if x is None else f"{x:.4f}"


def markdown(inv: Investigation, s: dict, out: Path) -> str:
    """The report: the outcome, then each round's question, input, verdicts and files."""
    lines = ["# Investigation", "",
             f"Runner: {inv.runner}. {len(inv.rounds)} round(s), "
             f"{inv.recorded_s / 60:.1f} of {inv.budget_s / 60:g} recorded minutes, "
             f"{inv.wall_s:.0f} s wall time. Stopped: {inv.stopped_because}.", "",
             f"**Effects found: {', '.join(s['effects_found']) or 'none'}.** Held-out free-run "
             f"RMSE {_mm(s['rmse_before_mm'])} mm before, {_mm(s['rmse_after_mm'])} mm after. "
             f"Still undecided: {', '.join(s['undecided']) or 'nothing'}.", "",
             f"Metric: {s['metric']}.", "", _how_diagnosed(inv), ""]
    for r, rs in zip(inv.rounds, s["rounds"], strict=True):
        lines += _round_lines(r, rs, out)
    if s["model_after"]:
        lines += [f"Final model: `{_rel(s['model_after'], out)}` (a GPI model file: "
                  "model_server serves it, ipmc identify --inverse --effects-from inverts it).",
                  ""]
    return "\n".join(lines)


def _how_diagnosed(inv: Investigation) -> str:
    """How the rounds' diagnoses took the records, in one paragraph."""
    probes = ("the experiment plays the probes after an identification input and repeats them "
              "as the held-out part, each copy after a memory wipe (both start from the same "
              "state)")
    if any(len(r.verdicts.records) > 1 for r in inv.rounds):
        return ("Each round diagnoses every record so far together: one core model and each "
                "block fitted on the fit parts of all, each effect judged on the held-out parts "
                f"of all (on an experiment's, on the probe that shows it): {probes}.")
    return ("Each new record is diagnosed on its own, from the core model refitted on its fit "
            f"part: {probes}, so that record alone judges each effect on the input that shows "
            "it.")


def _round_lines(r: InvestigationRound, rs: dict, out: Path) -> list[str]:
    v = r.verdicts
    asked = (f"Undecided before it: {', '.join(r.undecided)}." if r.undecided else
             "Nothing was known before it: every candidate effect was open.")
    lines = [f"## Round {r.number}", "", asked, "",
             f"Played: {r.played.label} (`{_rel(r.played.path, out)}`), recorded "
             f"{r.record.duration_s:.0f} s to `{_rel(r.record.path, out)}` "
             f"({r.wall_s:.0f} s wall time).", "",
             *([f"Lost on the way: {r.record.lost}.", ""] if r.record.lost else []),
             "| part | effect | from (s) | length (s) | why |", "|---|---|---|---|---|"]
    lines += [f"| {p.name} | {p.effect or '-'} | {p.start_s:.1f} | {p.duration_s:.1f} | "
              f"{p.reason} |" for p in r.played.parts]
    decided = ", ".join(f"{n} {o}" for n, o in rs["decided"].items()) or "nothing"
    lines += ["", f"Decided: {decided}. Effects found on this record: "
                  f"{', '.join(v.effects_found) or 'none'}; left undecided: "
                  f"{', '.join(v.undecided()) or 'nothing'}. Held-out RMSE "
                  f"{_mm(rs['rmse_before_mm'])} -> {_mm(rs['rmse_after_mm'])} mm (noise floor "
                  f"{_mm(rs['noise_floor_mm'])} mm).", ""]
    lines += [f"- {n}: {o}; {v.reasons.get(n, '')}." for n, o in v.outcomes.items()]
    lines += ["", f"Diagnosis: `{_rel(v.report_dir, out)}/report.md`; models "
                  f"`{_rel(v.model_before, out) if v.model_before else '-'}` (before), "
                  f"`{_rel(v.model_after, out) if v.model_after else '-'}` (after).", ""]
    return lines
