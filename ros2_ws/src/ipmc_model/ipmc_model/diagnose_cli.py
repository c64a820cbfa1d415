"""``ipmc diagnose``: residual -> missing physical effect -> augmented model, before and after.

``ipmc diagnose --data FILE.csv|BAG [--model MODEL] --report DIR [--seed N] [--committee]``

Writes ``summary.json``, ``report.md``, figures and the model files before/after to DIR;
progress goes to stderr. See :mod:`ipmc_model.diagnose` for the procedure.
"""

from __future__ import annotations

import argparse
import sys

from .diagnose import diagnose, print_progress, write_report
from .effects import check_rate, load_augmented
from .identify_cli import add_input_memory_taus, taus_list


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ipmc diagnose",
        description="Fit a baseline model, analyse its held-out residual, add the physical "
                    "effect it lacks (creep, drift, delay, ...), report before/after.")
    p.add_argument("--data", required=True, help="t,u,y CSV file (s, V, mm) or rosbag2 folder")
    p.add_argument("--model", help="baseline model file (lssvm-narx from ipmc identify, or a "
                                   "diagnosis's model_before/after), e.g. fitted on another "
                                   "day: kept as it is, and drift, delay, dead zone, asymmetry "
                                   "and saturation are fitted around it (what changed since); "
                                   "identify it on the same kind of input (a model of another "
                                   "kind gets its blocks undecided, not accepted); default: "
                                   "identify one on the first 70 %% of the data")
    p.add_argument("--report", required=True, metavar="DIR", help="output directory")
    p.add_argument("--seed", type=int, default=0, help="seed of tuning and prototypes")
    add_input_memory_taus(
        p, "memory channels for the baseline identified here: the voltage low-passed with "
           "these time constants (s, e.g. 1 3), each one more input channel; they carry the "
           "back-relaxation beyond the baseline's 1.2 s lag window (docs/diagnose.md, "
           "'Memory channels'); default none; not with --model")
    p.add_argument("--committee", action="store_true",
                   help="identify the baseline as the mean of three LSSVM-NARX with 1.2, 1.8 "
                        "and 2.4 s input windows (each tuned on its own): less error on new "
                        "input than one model, about three times the cost (docs/diagnose.md, "
                        "session 32); not with --model or --input-memory-taus")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ipmc diagnose``; returns the exit code."""
    args = _parser().parse_args(argv)
    try:
        from ipmc_driver.dataio import load_record

        rec = load_record(args.data)
        print_progress(f"{args.data}: {len(rec)} samples at {rec.rate_hz:.4g} Hz")
        model = None
        if args.model:
            model = check_rate(load_augmented(args.model, dt_s=rec.dt_s), rec.dt_s)
        d = diagnose(rec.t_s, rec.u_v, rec.y_mm, model=model, seed=args.seed,
                     memory_taus_s=taus_list(args.input_memory_taus),
                     committee=args.committee, progress=print_progress)
        summary = write_report(d, args.report, data_label=str(args.data))
    except ValueError as exc:  # DataError, ModelFileError and bad inputs are ValueErrors
        print(f"ipmc diagnose: error: {exc}", file=sys.stderr)
        return 1
    found = ", ".join(summary["effects_found"]) or "none"
    print(f"effects found: {found}; held-out free-run RMSE {summary['rmse_before_mm']:.4f} mm "
          f"before, {summary['rmse_after_mm']:.4f} mm after; report in {args.report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
