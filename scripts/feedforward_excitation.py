"""Which training input lets one forward-inversion feedforward meet both tracking goals?

    .venv/bin/python scripts/feedforward_excitation.py [--excitations random-sine mixed ...]
                                                       [--seeds 1 2 3 4 5]

For each training input (600 s or less at 100 Hz on the simulated IPMC, 3 V peak) and each
seed: fit the forward model of docs/control.md (LSSVM, C 1e6, sigma 1, 800 prototypes, inputs
the voltage low-passed at 0.3 s and 0.5 s, no output lags), check its free run on two records
it never saw (a 3 V random sine 0-0.7 Hz, seed 5, and a 2.6 V sine at 1/2pi Hz, the voltage
the sine reference needs), then track in process (``run_tracking``, noisy plant, the paper's
PID) in modes inverse and hybrid on two held-out random references (0-0.7 Hz, -4..2 mm, seeds
1, 2) and on the table's test references (random-reachable, sine). Goals: hybrid <= 0.02 mm on
random-reachable, <= 0.025 mm on the sine.

Training inputs (``ipmc_driver.signals``):
- random-sine: 300 s random sine 0.02-0.8 Hz (the previous forward model's data);
- random-sine+steps: that, then 150 s of random levels held 0.5-5 s;
- random-sine+slow: that, then 150 s of random sine 0.02-0.2 Hz;
- random-sine+slow+steps: both parts added (600 s);
- mixed: ``signals.mixed`` / ``ipmc simulate --input mixed`` over 600 s (the same three parts,
  its own seeds): the demo's recipe.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from ipmc_control.experiment import DEFAULT_DURATION_S, paper_reference, run_tracking
from ipmc_control.references import make_reference
from ipmc_driver import signals
from ipmc_driver.plant import IpmcPlant
from ipmc_model.forward_inversion import ForwardInversionFeedforward
from ipmc_model.narx import NarxModel, make_lssvm

DT_S = 0.01
TAUS_S = (0.3, 0.5)
EXCITATIONS = ("random-sine", "random-sine+steps", "random-sine+slow",
               "random-sine+slow+steps", "mixed")


def excitation(name: str, seed: int) -> np.ndarray:
    """Training voltage, V."""
    if name == "mixed":
        return signals.mixed(600, 100, 3.0, (0.02, 0.8), seed=seed)[1]
    parts = [signals.random_sine(300, 100, 3.0, (0.02, 0.8), seed=seed)[1]]
    if "slow" in name:
        parts.append(signals.random_sine(150, 100, 3.0, (0.02, 0.2), seed=seed + 11)[1])
    if "steps" in name:
        parts.append(signals.random_steps(150, 100, 3.0, (0.5, 5.0), seed=seed + 10)[1])
    return np.concatenate(parts)


def plant_record(u_v: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    run = IpmcPlant(seed=seed, dt_s=DT_S).run(u_v)
    return run.u_v, run.y_mm


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--excitations", nargs="+", choices=EXCITATIONS, default=list(EXCITATIONS))
    p.add_argument("--seeds", type=int, nargs="+", default=[1])
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    checks = [plant_record(signals.random_sine(60, 100, 3.0, (0.0, 0.7), seed=5)[1], 5),
              plant_record(signals.sine(2.6, 1 / (2 * np.pi), 25.1, 100)[1], 5)]
    refs = [("held-out 1", make_reference("random", band_hz=[0, 0.7], range_mm=[-4, 2], seed=1),
             60.0),
            ("held-out 2", make_reference("random", band_hz=[0, 0.7], range_mm=[-4, 2], seed=2),
             60.0),
            ("random-reachable", paper_reference("random-reachable"),
             DEFAULT_DURATION_S["random-reachable"]),
            ("sine", paper_reference("sine"), DEFAULT_DURATION_S["sine"])]
    print("| training input | seed | free run: random / 2.6 V sine (mm) | "
          + " | ".join(f"{r[0]}: inverse / hybrid (mm)" for r in refs) + " |")
    print("|---|---|---|" + "---|" * len(refs))
    for name in args.excitations:
        for seed in args.seeds:
            u, y = plant_record(excitation(name, seed), seed)
            t0 = time.perf_counter()
            reg = make_lssvm(1e6, 1.0, n_samples=u.size, n_prototypes=800, seed=0)
            model = NarxModel(reg, input_lags=0, output_lags=0, input_memory_taus_s=TAUS_S,
                              include_voltage=False, dt_s=DT_S).fit(u, y)
            fit_s = time.perf_counter() - t0
            free = [np.sqrt(np.mean((model.simulate(cu) - cy) ** 2)) for cu, cy in checks]
            ff = ForwardInversionFeedforward(model)
            cells = []
            for _, ref, dur in refs:
                r = [run_tracking(ref, dur, mode, inverse=ff, plant=IpmcPlant(dt_s=DT_S))
                     .summary()["rmse_mm"] for mode in ("inverse", "hybrid")]
                cells.append(f"{r[0]:.4f} / {r[1]:.4f}")
            print(f"| {name} | {seed} | {free[0]:.4f} / {free[1]:.4f} | " + " | ".join(cells)
                  + f" |  <!-- fit {fit_s:.1f} s -->", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
