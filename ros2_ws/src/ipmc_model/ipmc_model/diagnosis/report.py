"""The diagnosis's files: summary.json, report.md, a figure and the models before and after.
Decides nothing: it writes what :mod:`.search` decided."""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np

from ..persistence import save_model
from .candidates import CANDIDATES, DEAD_ZONE_TOL_V
from .results import Diagnosis, Outcome

METRIC = ("free-run RMSE (mm) on the held-out part of the record (of each record, when "
          "several are diagnosed): its last {held:.0f} %, or the last copies of the probes of "
          "the experiment it played; the model run from the record's start on its input alone")

RULE = ("An effect is accepted when the current model with its block, fitted on the same fit "
        "rows as the current model, has less squared free-run error on the held-out rows "
        "(those within the fit rows' voltage range for the last {settle:g} s; on a record "
        "played from a proposed experiment, an effect with its own probe there is judged on "
        "that probe's rows, the other probes showing other effects): the "
        "Diebold-Mariano test of the loss differential of the errors about their mean over each "
        "record's held-out rows (that offset is one draw per record, however many rows carry "
        "it; HAC variance, Bartlett kernel, bandwidth "
        "covering the differential's own autocorrelation, Harvey-Leybourne-Newbold factor, "
        "one-sided), Holm's weighted step-down at a family-wise {alpha:g} over the round's "
        "testable candidates that the fit rows support (their block lowers the fit rows' "
        "free-run squared error by a likelihood ratio, at the residual's effective sample "
        "size, above chi2 of its parameter count at {alpha:g}), each weighted by its z on the "
        "fit rows, the square root of that ratio (screen and weights are decided without the "
        "held-out rows, so the family-wise error holds), "
        "and a mean gain of at least {share:g} x the noise floor squared ({margin:.3g} mm^2) "
        "both of the errors about their held-out mean (what the test found significant) and "
        "of the errors as they are (the block must not move the level away). "
        "A round accepts the passing candidate with the largest gain and the next refits the "
        "rest around it. A candidate the record cannot test is still fitted as a rival: if it "
        "would gain the most, nothing is accepted and it is reported undecided, with what to "
        "record. A candidate that does not pass but whose block the fit rows support, with a "
        "positive held-out gain, is undecided (not rejected) when the test would pass with "
        "less than {power:.0%} probability at the gain the fit rows show: the held-out rows "
        "are too few to decide it, and its probe is proposed. An accepted effect whose "
        "parameter, re-estimated on every row, lies outside the effect's physical range (a "
        "creep faster than {creep_min:g} s, a dead zone narrower than its scan's resolution, "
        "{dz_tol:g} V) is rejected: its block took up something else.")


def check_report_dir(out_dir) -> Path:
    """The report folder, refused at once if it is a file or cannot be written."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--report {out} is a file; give a folder (it is created if missing)")
    out.mkdir(parents=True, exist_ok=True)
    if not os.access(out, os.W_OK):
        raise ValueError(f"--report {out} cannot be written")
    return out


def _write_atomic(path: Path, text: str) -> None:
    with tempfile.NamedTemporaryFile("w", dir=path.parent, delete=False, suffix=".tmp") as f:
        f.write(text)
    os.replace(f.name, path)


def _finite(x):
    return float(x) if x is not None and math.isfinite(x) else None


def _json_safe(o):
    if isinstance(o, dict):
        return {str(k): _json_safe(v) for k, v in o.items()}
    if isinstance(o, (list, tuple, np.ndarray)):
        return [_json_safe(v) for v in o]
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def summary_of(d: Diagnosis, paths: dict) -> dict:
    c = d.config
    margin = c.material_noise_share * d.noise_floor_mm ** 2
    return _json_safe({
        "effects_found": d.effects_found,
        "rmse_before_mm": _finite(d.rmse_before_mm),
        "rmse_after_mm": _finite(d.rmse_after_mm),
        "noise_floor_mm": d.noise_floor_mm,
        "metric": METRIC.format(held=100 * (1 - c.fit_share)),
        "rule": RULE.format(alpha=c.family_alpha, share=c.material_noise_share, margin=margin,
                            settle=c.settle_s, power=c.min_power, creep_min=c.creep_min_tau_s,
                            dz_tol=DEAD_ZONE_TOL_V),
        "given_model": d.given_model,
        "known_effects": list(d.known),
        "candidates": [r.as_dict() for r in d.candidates],
        "rounds": [{"number": r.number, "rmse_start_mm": r.rmse_start_mm,
                    "accepted": r.accepted, "results": [x.as_dict() for x in r.results]}
                   for r in d.rounds],
        "excitation": d.excitation,
        "records": _records(d),
        "config": c.as_dict(),
        "seconds": d.seconds,
        **paths,
    })


def _records(d: Diagnosis) -> list[dict]:
    """Each record's rows and its held-out RMSE before and after."""
    before, after = d.record_rmse(d.model_before), d.record_rmse(d.model_after)
    return [{"name": s.name, "samples": s.stop - s.start, "fit_samples": s.cut - s.start,
             "rmse_before_mm": before[s.name], "rmse_after_mm": after[s.name]}
            for s in d.segments]


def write_report(d: Diagnosis, out_dir, data_label: str = "data") -> dict:
    """Write summary.json, report.md, residual.png and model_before/after.json to
    ``out_dir``; return the summary."""
    out = check_report_dir(out_dir)
    meta = {"data": data_label, "fit_share": d.config.fit_share, "samples": int(d.u_v.size),
            "rate_hz": 1.0 / d.model_before.dt_s,
            "input_range_v": [float(d.u_v.min()), float(d.u_v.max())]}
    p_before = save_model(d.model_before, out / "model_before.json",
                          metadata={**meta, "held_out_free_run_rmse_mm": d.rmse_before_mm})
    p_after = save_model(d.model_after, out / "model_after.json",
                         metadata={**meta, "held_out_free_run_rmse_mm": d.rmse_after_mm,
                                   "effects_found": d.effects_found})
    paths = {"model_before": str(p_before), "model_after": str(p_after)}
    if d.next_experiment is not None:
        experiment = out / "next_experiment.json"
        _write_atomic(experiment, json.dumps(d.next_experiment.as_dict()) + "\n")
        paths["next_experiment"] = str(experiment)
    summary = summary_of(d, paths)
    _write_atomic(out / "summary.json", json.dumps(summary, indent=2, allow_nan=False) + "\n")
    fig = _figure(d, out)
    _write_atomic(out / "report.md", markdown(d, summary, data_label, fig))
    return summary


def _cell(x, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def markdown(d: Diagnosis, s: dict, label: str, figure: str | None) -> str:
    """The report: the record, the rule, each round, what to record next, the thresholds."""
    ex, c = d.excitation, d.config
    rate = 1.0 / d.model_before.dt_s
    base = "the given model (frozen; blocks fitted around it)" if d.given_model else \
        "the core GPI model (charging, back-relaxation, path memory; no delay, no creep)"
    if d.known:
        base += (f", with {', '.join(d.known)} (decided on an earlier record; fitted on these "
                 f"fit rows, not judged again)")
    split = "; ".join(f"{s.name}: {s.stop - s.start} samples, fitted on the first "
                      f"{s.cut - s.start}, judged on the last {s.stop - s.cut}"
                      for s in d.segments)
    joined = (" (joined in this order, each after a rest at 0 V whose output is not measured)"
              if len(d.segments) > 1 else "")
    lines = [f"# Residual diagnosis of `{label}`", "",
             f"At {rate:.4g} Hz{joined}: {split}. Starting model: {base}. Noise floor "
             f"{d.noise_floor_mm:.4f} mm. "
             f"Holds of {c.hold_min_s:g} s or more: {ex['holds_fit']} in the fit part, "
             f"{ex['holds_held']} held out; steps in the fit part: {ex['steps_fit']}. "
             f"Run time {d.seconds:.1f} s.", "",
             f"**Effects found: {', '.join(s['effects_found']) or 'none'}.** Held-out "
             f"free-run RMSE {s['rmse_before_mm']:.4f} mm before, {s['rmse_after_mm']:.4f} mm "
             f"after ({s['rmse_after_mm'] / d.noise_floor_mm:.1f} x the noise floor).", "",
             f"Metric: {s['metric']}.", "", f"Decision rule: {s['rule']}", ""]
    for rnd in d.rounds:
        lines += [f"## Round {rnd.number} (from {rnd.rmse_start_mm:.4f} mm): "
                  f"{'accepted ' + rnd.accepted if rnd.accepted else 'nothing accepted'}", "",
                  "| effect | outcome | RMSE with it (mm) | mean gain (mm^2) | DM p | Holm p | "
                  "parameters |", "|---|---|---|---|---|---|---|"]
        for r in rnd.results:
            ev = r.evidence
            params = "" if ev is None else ", ".join(
                f"{k} {_fmt(v)}" for k, v in ev.params.items())
            lines.append(f"| {r.name} | {r.outcome.value} | "
                         f"{_cell(ev and ev.rmse_candidate_mm, '.4f')} | "
                         f"{_cell(ev and ev.test.mean_gain_mm2, '.3g')} | "
                         f"{_cell(ev and ev.test.p_value, '.2g')} | "
                         f"{_cell(ev and ev.p_holm, '.2g')} | {params} |")
        lines += [""] + [f"- {r.name}: {r.reason}." for r in rnd.results] + [""]
        lines += _decided_by(rnd)
    untestable = [r for r in d.candidates if r.outcome is Outcome.NOT_TESTABLE]
    if untestable:
        lines += ["## Not testable on this record", ""]
        lines += [f"- **{r.name}** ({CANDIDATES[r.name].meaning}): {r.reason}."
                  for r in untestable] + [""]
    if d.next_experiment is not None:
        lines += _experiment_lines(d.next_experiment)
    if figure:
        lines += [f"![held-out residual before and after]({figure})", ""]
    lines += ["## Thresholds", "", "| name | value |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in c.as_dict().items()] + [""]
    lines += [f"Models: `{Path(s['model_before']).name}` (before), "
              f"`{Path(s['model_after']).name}` (after; GPI model files, served by "
              "model_server and inverted by ipmc identify --inverse --effects-from).", ""]
    return "\n".join(lines)


def _decided_by(rnd) -> list[str]:
    """Which record decided the round's accepted effect (when several are diagnosed)."""
    res = next((r for r in rnd.results if r.accepted), None)
    if res is None or res.evidence is None or not res.evidence.records:
        return []
    lines = [f"Which record decided {res.name}:", "",
             "| record | held-out RMSE before (mm) | with it (mm) | mean gain (mm^2) |",
             "|---|---|---|---|"]
    lines += [f"| {r.record} | {r.rmse_current_mm:.4f} | {r.rmse_candidate_mm:.4f} | "
              f"{r.mean_gain_mm2:.3g} |" for r in res.evidence.records]
    return lines + [""]


def _experiment_lines(x) -> list[str]:
    lines = ["## The next experiment", "",
             f"`next_experiment.json` ({x.duration_s:.0f} s at {x.rate_hz:.4g} Hz, |u| <= "
             f"{float(np.max(np.abs(x.u_v))):.2f} V) decides {', '.join(x.decides)}; its last "
             f"{100 * (1 - x.fit_share):.0f} % is the held-out part. Record it and diagnose "
             "that record with `--experiment next_experiment.json` (a bag that `ipmc bringup "
             "--experiment` recorded carries it), so that it is split where its held-out part "
             "starts:", "", "| part | from (s) | length (s) | held out | why |",
             "|---|---|---|---|---|"]
    lines += [f"| {p.name} | {p.start_s:.1f} | {p.duration_s:.1f} | "
              f"{'yes' if p.held_out else '-'} | {p.reason} |" for p in x.parts]
    return lines + [""]


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


def _figure(d: Diagnosis, out: Path) -> str | None:
    """Each record's held-out part (one column each): measured and both models, and both
    residuals."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    y_before, y_after = d.model_before.simulate(d.u_v), d.model_after.simulate(d.u_v)
    n = len(d.segments)
    fig, axes = plt.subplots(2, n, figsize=(9 if n == 1 else 4.5 * n, 5.5), sharex="col",
                             sharey="row", squeeze=False)
    for (a1, a2), s in zip(axes.T, d.segments, strict=True):
        rows = slice(s.cut, s.stop)
        t, y = d.t_s[rows] - d.t_s[s.start], d.y_mm[rows]
        a1.plot(t, y, "k", lw=0.8, label="measured")
        a1.plot(t, y_before[rows], lw=0.8, label="before")
        a1.plot(t, y_after[rows], lw=0.8, label="after")
        a2.plot(t, y - y_before[rows], lw=0.8, label=f"before, RMSE {d.rmse_before_mm:.4f} mm")
        a2.plot(t, y - y_after[rows], lw=0.8, label=f"after, RMSE {d.rmse_after_mm:.4f} mm")
        a2.set_xlabel(f"time in {Path(s.name).name} (s)" if n > 1 else "time (s)")
    axes[0, 0].set_ylabel("tip (mm)")
    axes[1, 0].set_ylabel("residual (mm)")
    axes[0, -1].legend(loc="upper right", fontsize=8)
    axes[1, -1].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "residual.png", dpi=110)
    plt.close(fig)
    return "residual.png"
