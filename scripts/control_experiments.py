"""The tracking table of docs/control.md: identification + ``ipmc track`` in process and through
the node graph, every number from the commands printed as they run.

    .venv/bin/python scripts/control_experiments.py [--out-dir DIR] [--no-graph]
        [--seconds S] [--model INVERSE.json] [--forward-model FORWARD.json]
        [--feedforwards inverse-model forward-inversion] [--references REF ..]

1. Training data as in the paper's section 3.4 (random-sine voltage on the simulated IPMC):
   ``ipmc simulate --input random-sine --amplitude 3 --frequency 0.5 --seconds 300 --seed 1``.
2. The inverse model (Eq. 19) with the recipe of docs/control.md (``RECIPE``): ``ipmc identify
   --inverse --tune none ...``.
3. The second feedforward: a forward model on low-passed voltages, inverted online, trained on
   the ``mixed`` input (``ipmc simulate --input mixed ...``, ``ipmc identify
   --input-memory-taus ...``: ``FEEDFORWARD`` in ipmc_control.demo).
4. ``ipmc track`` for every reference x mode x feedforward, in process and with ``--graph``
   (sim_plant in lock-step, model_server, controller, reference and recorder as processes over
   DDS).
5. A markdown table on stdout (and ``DIR/table.md``), with the JSON summaries in ``DIR``.

Every child runs with one BLAS thread (the machine is shared; the solves are small).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ipmc_control.demo import FEEDFORWARD, TRAIN_FEEDFORWARD
from ipmc_control.demo import INVERSE as RECIPE
from ipmc_control.demo import TRAIN_INVERSE as TRAIN

BIN = Path(sys.executable).parent
# (reference, plant effects, label, paper's figures)
EXPERIMENTS = [
    ("sine", [], "(a) sine 2.5 mm @ 1/2pi Hz",
     {"inverse": "0.1152 (sim, Fig. 42)", "hybrid": "0.0244 (sim) / 0.0365 (rig)"}),
    ("random", [], "(b) random sine 0-0.7 Hz, -9..4 mm (paper's range)",
     {"hybrid": "0.0306 (rig)"}),
    ("random-reachable", [], "(b') random sine 0-0.7 Hz, -4..2 mm (reachable)", {}),
    ("constant", ["creep"], "(c) constant -4 mm hold, 60 s, creep on",
     {"hybrid": "0.8756 (rig, +4 mm)"}),
    ("constant-reachable", ["creep"], "(c') constant -3 mm hold, 60 s, creep on", {}),
]
MODES = ("pid", "inverse", "hybrid")
# Which model makes the feedforward: the paper's inverse LSSVM-NARX, or the forward model
# inverted online (docs/control.md); PID rows use neither.
FEEDFORWARDS = ("inverse-model", "forward-inversion")


def run(argv: list[str], env: dict, log) -> None:
    print("$ " + " ".join(argv), file=log, flush=True)
    out = subprocess.run(argv, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed ({out.returncode}):\n{out.stderr[-3000:]}")
    for line in out.stdout.splitlines():
        print("  " + line, file=log, flush=True)
    for line in out.stderr.splitlines():  # e.g. "warning: the controller ran without ..."
        if line.startswith("warning"):
            print("  " + line, file=log, flush=True)


def track(ref: str, mode: str, effects: list[str], model: Path, out_dir: Path, graph: bool,
          seconds: float | None, env: dict, log, tag: str = "") -> dict:
    name = f"{ref}_{mode}{tag}{'_graph' if graph else ''}.json"
    argv = [str(BIN / "ipmc"), "track", "--reference", ref, "--mode", mode,
            "--json", str(out_dir / name)]
    if mode != "pid":
        argv += ["--model", str(model)]
    for e in effects:
        argv += ["--plant-effect", e]
    if graph:
        argv.append("--graph")
    if seconds:
        argv += ["--seconds", str(seconds)]
    for attempt in (1, 2):
        try:
            run(argv, env, log)
            return json.loads((out_dir / name).read_text())
        except RuntimeError as exc:
            # A graph run can fail on a loaded machine (a node missing its SIGINT budget loses
            # the bag): say so, try once more, then leave the cell empty rather than stop.
            print(f"  attempt {attempt} failed: {str(exc).splitlines()[-1]}", file=log)
    return None


def cells(feedforwards) -> list[tuple[str, str]]:
    """(mode, feedforward) pairs in table order; PID once, '-' as its feedforward."""
    return [("pid", "-")] + [(m, f) for f in feedforwards for m in MODES if m != "pid"]


def table(results: dict, graph: bool, feedforwards=FEEDFORWARDS) -> str:
    head = ("| reference | mode | feedforward | RMSE in process (mm) | "
            + ("RMSE graph (mm) | graph vs in process | " if graph else "")
            + "max abs error (mm) | max abs u (V) | paper RMSE (mm) |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for ref, _effects, label, paper in EXPERIMENTS:
        for mode, ff in cells(feedforwards):
            if (ref, mode, ff, False) not in results:
                continue
            a = results[(ref, mode, ff, False)]
            if a is None:
                lines.append(f"| {label} | {mode} | {ff} | failed |")
                continue
            row = f"| {label} | {mode} | {ff} | {a['rmse_mm']:.4f} | "
            if graph:
                b = results.get((ref, mode, ff, True))
                if b is None:
                    row += "- | - | "
                else:
                    rel = (b["rmse_mm"] - a["rmse_mm"]) / a["rmse_mm"]
                    row += f"{b['rmse_mm']:.4f} | {rel:+.1%} | "
            # The paper's figures are for its inverse-model feedforward.
            p = paper.get(mode, "-") if ff in ("-", "inverse-model") else "-"
            row += f"{a['max_abs_mm']:.3f} | {a['u_max_v']:.2f} | {p} |"
            lines.append(row)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", help="where data, model and JSON go (default: a temp dir)")
    parser.add_argument("--no-graph", action="store_true", help="in process only")
    parser.add_argument("--seconds", type=float, help="override every run's duration, s")
    parser.add_argument("--model", help="use this inverse model file instead of identifying")
    parser.add_argument("--forward-model", help="use this forward model with voltage channels "
                        "(for forward-inversion) instead of identifying")
    parser.add_argument("--feedforwards", nargs="+", choices=FEEDFORWARDS,
                        default=list(FEEDFORWARDS), help="which feedforwards (default: both)")
    parser.add_argument("--references", nargs="+", choices=[e[0] for e in EXPERIMENTS],
                        help="only these references (default: all)")
    args = parser.parse_args(argv)
    out_dir = Path(args.out_dir or tempfile.mkdtemp(prefix="ipmc_control_"))
    out_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    log = sys.stderr
    t0 = time.monotonic()
    models = {}
    for ff, given, train, recipe, name in (
            ("inverse-model", args.model, TRAIN, RECIPE, "inverse"),
            ("forward-inversion", args.forward_model, TRAIN_FEEDFORWARD, FEEDFORWARD,
             "forward_ff")):
        if ff not in args.feedforwards:
            continue
        if given:
            models[ff] = Path(given)
            continue
        data, models[ff] = out_dir / f"train_{name}.csv", out_dir / f"{name}.json"
        run([str(BIN / "ipmc"), "simulate", *train, "--out", str(data)], env, log)
        run([str(BIN / "ipmc"), "identify", "--data", str(data), *recipe, "--out",
             str(models[ff])], env, log)
    results = {}
    for graph in (False,) if args.no_graph else (False, True):
        for ref, effects, _label, _paper in EXPERIMENTS:
            if args.references and ref not in args.references:
                continue
            for mode, ff in cells(args.feedforwards):
                model = models.get(ff)
                tag = "" if ff in ("-", "inverse-model") else f"_{ff}"
                results[(ref, mode, ff, graph)] = track(ref, mode, effects, model, out_dir,
                                                        graph, args.seconds, env, log, tag)
    md = table(results, not args.no_graph, args.feedforwards)
    (out_dir / "table.md").write_text(md + "\n")
    print(md)
    print(f"\n{len(results)} runs in {time.monotonic() - t0:.0f} s; files in {out_dir}",
          file=log)
    return 0


if __name__ == "__main__":
    sys.exit(main())
