"""How low can the hold's RMSE go? The floor that the 3 V limit puts under a step reference.

    .venv/bin/python scripts/hold_floor.py [--targets -3 -4] [--seconds 60] [--effect creep]

A constant reference switched on at t = 0 asks the tip to jump from rest to the target; the
IPMC cannot. The fastest it can get there is with the full voltage from the first sample
(the double layer charges at most at its slew rate whatever the command), so every controller
bound by |u| <= u_max_v has at least the error of that full-voltage response until it first
reaches the target, plus the one sample the loop needs to see anything. This script computes
that error's RMSE over the whole run (every sample counts, as in the tracking table) on the
noise-free simulated plant: the hold's all-samples RMSE cannot go below it, whatever the model.
"""

from __future__ import annotations

import argparse

import numpy as np

from ipmc_driver.plant import IpmcPlant


def hold_floor_rmse(target_mm: float, seconds: float = 60.0, dt_s: float = 0.01,
                    effects=("creep",), u_max_v: float = 3.0) -> tuple[float, float]:
    """(floor RMSE over ``seconds``, time to first reach ``target_mm``), mm and s."""
    plant = IpmcPlant(effects=list(effects), dt_s=dt_s)
    n = int(round(seconds / dt_s))
    y = plant.run(np.full(n, np.copysign(u_max_v, target_mm))).y_true_mm
    y = np.concatenate([[0.0], y[:-1]])  # the first sample's tip is the rest position
    reached = np.flatnonzero(np.sign(target_mm) * (y - target_mm) >= 0)
    if reached.size == 0:
        return float(np.sqrt(np.mean((y - target_mm) ** 2))), float("inf")
    k = reached[0]
    err = np.zeros(n)
    err[:k] = y[:k] - target_mm
    return float(np.sqrt(np.mean(err ** 2))), k * dt_s


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--targets", type=float, nargs="+", default=[-3.0, -4.0], help="mm")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--effect", action="append", default=None,
                   help="plant effect(s) (default: creep, as in the table)")
    args = p.parse_args(argv)
    effects = args.effect if args.effect is not None else ["creep"]
    print("| target (mm) | first reached (s) | floor RMSE over the run (mm) |\n|---|---|---|")
    for target in args.targets:
        rmse, t_reach = hold_floor_rmse(target, args.seconds, effects=effects)
        print(f"| {target:+.1f} | {t_reach:.2f} | {rmse:.4f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
