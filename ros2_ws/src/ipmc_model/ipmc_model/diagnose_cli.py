"""``ipmc diagnose``: residual -> missing physical effect -> model with it, before and after.

``ipmc diagnose --data FILE.csv|BAG [--data ...] [--experiment FILE] [--model MODEL]
--report DIR [--effects NAME ...]``

Writes ``summary.json``, ``report.md``, ``residual.png`` and the model files before and after
to DIR; progress goes to stderr. See :mod:`ipmc_model.diagnosis` for the procedure.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from .diagnosis import CANDIDATES
from .diagnosis.report import check_report_dir, write_report
from .diagnosis.search import diagnose_records


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ipmc diagnose",
        description="Fit a model on the first 70 % of a record (a record of a proposed "
                    "experiment: up to the last copies of its probes), find the physical "
                    "effects it lacks (creep, drift, delay, dead zone, ...) by their held-out "
                    "free-run gain, and report the error before and after.")
    p.add_argument("--data", required=True, action="append", metavar="FILE",
                   help="t,u,y CSV file (s, V, mm) or rosbag2 folder; give it again for more "
                        "records of the same actuator (an experiment after a first record): "
                        "each is split on its own, the models are fitted on the fit parts of "
                        "all and judged on the held-out parts of all, and the report says "
                        "which record decided what")
    p.add_argument("--experiment", metavar="FILE",
                   help="the next_experiment.json the last --data record played (ipmc bringup "
                        "--experiment): that record is then split where the experiment's "
                        "held-out part starts (the probes' last copies), and each effect with "
                        "a probe there is judged on that probe's rows, the other probes "
                        "showing other effects")
    p.add_argument("--model", help="a GPI model file (ipmc identify's default, or a diagnosis's "
                                   "model_after.json), e.g. from another day: kept as it is, "
                                   "and each effect's block is fitted around it (what changed "
                                   "since); default: the diagnosis's own core model, fitted on "
                                   "the fit part of the data")
    p.add_argument("--report", required=True, metavar="DIR", help="output folder")
    p.add_argument("--effects", nargs="+", metavar="NAME", choices=list(CANDIDATES),
                   help=f"candidate effects to try (default all: {', '.join(CANDIDATES)})")
    p.add_argument("--jobs", type=int, metavar="N",
                   help="worker processes for a round's candidate fits and a profile's refits "
                        "(default: the cores this process may use; the result is the same "
                        "for any N)")
    p.add_argument("--seed", type=int, default=0,
                   help="accepted for scripts written for earlier versions; the diagnosis is "
                        "deterministic")
    from ipmc_driver.dataio import add_allow_implausible

    add_allow_implausible(p)
    return p


def _progress(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _played(path: str, record) -> tuple:
    """The parts of the experiment ``path``, where the record that played it has them."""
    from .diagnosis.experiment import played_parts, read_experiment

    parts, u_v, rate_hz = read_experiment(path)
    name, t_s, u_rec = record[0], record[1], record[2]
    dt_s = float(np.median(np.diff(t_s)))
    if abs(rate_hz * dt_s - 1.0) > 0.01:
        raise ValueError(f"{path} is sampled at {rate_hz:g} Hz but {name} at "
                         f"{1 / dt_s:.4g} Hz: it is not the experiment that record played")
    try:
        return played_parts(parts, u_v, u_rec, dt_s)
    except ValueError as exc:
        raise ValueError(f"{name} did not play all of {path}: {exc}") from None


def experiment_of(data: str, given: str | None) -> str | None:
    """The experiment a record played: ``given`` (``--experiment``), or the copy a bag that
    ``ipmc bringup --experiment`` recorded keeps; None for a record of another input."""
    from .diagnosis.experiment import BAG_EXPERIMENT

    kept = Path(data) / BAG_EXPERIMENT
    return given or (str(kept) if kept.is_file() else None)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ipmc diagnose``; returns the exit code."""
    args = _parser().parse_args(argv)
    try:
        from ipmc_driver.dataio import load_record, print_notes

        from .effects import load_any_model

        check_report_dir(args.report)
        model = load_any_model(args.model) if args.model else None
        records = []
        for path in args.data:
            notes: list[str] = []
            # samples lost on a link are rows not measured: the models run through them
            rec = load_record(path, allow_implausible=args.allow_implausible, notes=notes,
                              gaps=True)
            print_notes("ipmc diagnose", notes)
            _progress(f"{path}: {len(rec)} samples at {rec.rate_hz:.4g} Hz")
            records.append((str(path), rec.t_s, rec.u_v, rec.y_mm))
        for i, rec in enumerate(records):
            given = args.experiment if i == len(records) - 1 else None
            played = experiment_of(args.data[i], given)
            try:
                records[i] = (*rec, _played(played, rec)) if played else rec
            except ValueError as exc:
                if given:
                    raise
                # a bag whose recording stopped early (Ctrl-C): a record of part of it
                _progress(f"{exc}; split at the share, as a record of another input")
                continue
            if played:
                _progress(f"{args.data[i]}: played {played}; split where its held-out part "
                          f"starts")
        d = diagnose_records(records, model=model, candidates=args.effects,
                             progress=_progress, jobs=args.jobs)
        summary = write_report(d, args.report, data_label=", ".join(map(str, args.data)))
    except ValueError as exc:  # DataError, ModelFileError and bad inputs are ValueErrors
        print(f"ipmc diagnose: error: {exc}", file=sys.stderr)
        return 1
    found = ", ".join(summary["effects_found"]) or "none"
    print(f"effects found: {found}; held-out free-run RMSE {summary['rmse_before_mm']:.4f} mm "
          f"before, {summary['rmse_after_mm']:.4f} mm after; report in {args.report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
