"""Back into control by the commands a lab runs (issue 6): the feedforward of a diagnosis's
model (``ipmc identify --inverse --effects-from model_after.json``) against the plain inverse,
on the plant with its creep.

    .venv/bin/python scripts/creep_feedforward.py --seeds 4 5 6 7 [--seconds 300]
        [--prototypes 800] [--amplitude 2.5] [--history-voltage clamped applied] [--out DIR]

Per seed: a record of random steps up to 2.5 V (``--amplitude``) held 0.5-5 s on the plant
with its creep (the demo's rig data); ``model_after.json`` holds the plant's own creep (what
the diagnosis finds, tests/test_creep_hold.py) around a small forward NARX; the demo's
inverse recipe identified plain and with ``--effects-from``; then 60 s holds (-3 mm, and
-4 mm at the 3 V limit) in process, inverse alone and hybrid, and a 30 s hybrid sine. Prints,
per run, the whole-run RMSE, the RMSE after 2 s and the mean error over the last 10 s (mm),
for each voltage the feedforward takes as applied (``--history-voltage``: its own limited to
3 V, as ``ipmc track``, or the plant's, PID included, as model_server's default on the rig;
it drives the creep state). docs/diagnose.md, "Control: inverse of baseline + creep", has
the tables (sessions 39 and 40).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from itertools import product
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits


def feedforwards(seed: int, seconds: float, prototypes: int, out: Path,
                 amplitude_v: float = 2.5) -> dict[str, Path]:
    """The plain and the creep-undone feedforward files of one record."""
    from ipmc_control.demo import INVERSE  # the demo's inverse recipe (docs/control.md)
    from ipmc_driver.dataio import Record, save_csv
    from ipmc_driver.plant import IpmcPlant, load_plant_params
    from ipmc_driver.signals import random_steps
    from ipmc_model.effects import AugmentedModel, Effect, save_augmented
    from ipmc_model.identify_cli import identify_main
    from ipmc_model.lssvm import FixedSizeLSSVMRegressor
    from ipmc_model.narx import NarxModel

    out.mkdir(parents=True, exist_ok=True)
    _, u = random_steps(seconds, 100.0, amplitude_v, seed=seed)
    run = IpmcPlant(effects=["creep"], seed=seed).run(u)
    save_csv(Record(run.t_s, run.u_v, run.y_mm), out / "rig.csv")
    base = NarxModel(FixedSizeLSSVMRegressor(C=1e3, sigma=3.0, n_prototypes=200, seed=0),
                     input_lags=12, output_lags=0, lag_step=10).fit(run.u_v, run.y_mm)
    creep = Effect("creep", **load_plant_params()["effects"]["creep"])
    after = save_augmented(AugmentedModel(base, [creep], 0.01), out / "model_after.json")
    # (the last --prototypes wins over the recipe's)
    common = ["--data", str(out / "rig.csv"), *INVERSE, "--prototypes", str(prototypes)]
    files = {"plain": out / "plain.json", "creep": out / "creep.json"}
    if identify_main([*common, "--out", str(files["plain"])]) or identify_main(
            [*common, "--effects-from", str(after), "--out", str(files["creep"])]):
        raise SystemExit("ipmc identify failed")
    return files


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[4, 5, 6, 7])
    p.add_argument("--seconds", type=float, default=300.0, help="record length (default 300)")
    p.add_argument("--prototypes", type=int, default=800, help="the inverse's (default 800)")
    p.add_argument("--amplitude", type=float, default=2.5,
                   help="largest step of the record, V (default 2.5, the demo's)")
    p.add_argument("--history-voltage", nargs="+", default=["clamped"],
                   choices=["clamped", "applied"],
                   help="the voltage the feedforward takes as applied (default clamped)")
    p.add_argument("--out", help="folder for the records and models (default: a temporary one)")
    args = p.parse_args(argv)
    from ipmc_control.experiment import paper_reference, run_tracking
    from ipmc_control.track_cli import load_feedforward
    from ipmc_driver.plant import IpmcPlant

    root = Path(args.out or tempfile.mkdtemp(prefix="creep_ff_"))
    runs = [("constant-reachable", m, 60.0) for m in ("inverse", "hybrid")] + \
           [("constant", m, 60.0) for m in ("inverse", "hybrid")] + [("sine", "hybrid", 30.0)]
    print("seed reference mode: feedforward whole-run RMSE / RMSE after 2 s / mean error "
          "over the last 10 s (mm)")
    with threadpool_limits(1):
        for seed in args.seeds:
            files = feedforwards(seed, args.seconds, args.prototypes, root / f"seed{seed}",
                                 args.amplitude)
            ff = {name: load_feedforward(str(f), "hybrid") for name, f in files.items()}
            for ref, mode, dur in runs:
                cells = []
                for (name, model), hist in product(ff.items(), args.history_voltage):
                    r = run_tracking(paper_reference(ref), dur, mode, inverse=model,
                                     plant=IpmcPlant(effects=["creep"], seed=100),
                                     history_voltage=hist)
                    e, t = r.reference_mm - r.y_mm, r.t_s
                    label = name if len(args.history_voltage) == 1 else f"{name}/{hist}"
                    cells.append(f"{label} {np.sqrt(np.mean(e ** 2)):.4f} / "
                                 f"{np.sqrt(np.mean(e[t >= 2.0] ** 2)):.4f} / "
                                 f"{np.mean(e[t >= dur - 10.0]):+.3f}")
                print(f"{seed} {ref} {mode}: {' | '.join(cells)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
