"""Table 1 characterisation: the paper's nine sine conditions on the (simulated) IPMC.

``ipmc characterize`` (also ``ros2 run ipmc_driver characterize``) runs 1, 2, 3 V at
0.5/2pi, 1/2pi, 5/2pi Hz, prints the tip-displacement range beside the paper's Table 1 and
writes the voltage / displacement / hysteresis-loop figures.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from .plant import EFFECTS, IpmcPlant, load_plant_params
from .signals import sine

AMPLITUDES_V = (1.0, 2.0, 3.0)
FREQUENCIES_HZ = (0.5 / (2 * math.pi), 1.0 / (2 * math.pi), 5.0 / (2 * math.pi))
FREQUENCY_LABELS = ("0.5/2pi", "1/2pi", "5/2pi")

# Paper, Table 1: (amplitude V, frequency label) -> (lower mm, upper mm, range mm).
PAPER_TABLE1 = {
    (1.0, "0.5/2pi"): (-0.9873, 0.8256, 1.8129),
    (1.0, "1/2pi"): (-1.1276, 0.8923, 2.0199),
    (1.0, "5/2pi"): (-1.1993, 0.8134, 2.0127),
    (2.0, "0.5/2pi"): (-2.5604, 1.988, 4.5484),
    (2.0, "1/2pi"): (-3.9327, 2.3796, 6.3123),
    (2.0, "5/2pi"): (-2.487, 2.7003, 5.1873),
    (3.0, "0.5/2pi"): (-4.7787, 2.6328, 7.4115),
    (3.0, "1/2pi"): (-8.7983, 2.5967, 11.395),
    (3.0, "5/2pi"): (-6.1326, 2.7528, 8.8854),
}


def run_condition(amplitude_v: float, frequency_hz: float, *, params: dict | None = None,
                  effects=(), seed: int = 0, rate_hz: float = 100.0, periods: int = 4,
                  settle_periods: int = 2, min_seconds: float = 12.0) -> dict:
    """Drive a fresh plant with a sine and measure the steady-state tip range.

    The first ``settle_periods`` periods are discarded (start-up transient); the range is taken
    over the rest. Returns the condition's record plus the time series (``t_s``, ``u_v``,
    ``y_mm``) for plotting.
    """
    period_s = 1.0 / frequency_hz
    n_periods = max(periods, math.ceil(min_seconds / period_s))
    t, u = sine(amplitude_v, frequency_hz, n_periods * period_s, rate_hz)
    plant = IpmcPlant(params=params, effects=effects, seed=seed, dt_s=1.0 / rate_hz)
    run = plant.run(u)
    keep = t >= settle_periods * period_s
    lower, upper = float(run.y_mm[keep].min()), float(run.y_mm[keep].max())
    return {
        "amplitude_v": amplitude_v,
        "frequency_hz": frequency_hz,
        "lower_mm": lower,
        "upper_mm": upper,
        "range_mm": upper - lower,
        "t_s": run.t_s[keep] - run.t_s[keep][0],
        "u_v": run.u_v[keep],
        "y_mm": run.y_mm[keep],
    }


def characterize(params: dict | None = None, effects=(), seed: int = 0,
                 rate_hz: float = 100.0) -> list[dict]:
    """Run the nine Table 1 conditions; a list of records in the paper's order."""
    return [run_condition(a, f, params=params, effects=effects, seed=seed, rate_hz=rate_hz)
            for a in AMPLITUDES_V for f in FREQUENCIES_HZ]


def frequency_label(frequency_hz: float) -> str:
    """The paper's name ("0.5/2pi", "1/2pi", "5/2pi") of the nearest Table 1 frequency."""
    return FREQUENCY_LABELS[int(np.argmin([abs(frequency_hz - f) for f in FREQUENCIES_HZ]))]


def paper_row(amplitude_v: float, frequency_hz: float) -> tuple[float, float, float]:
    """The paper's (lower, upper, range) in mm for one condition."""
    return PAPER_TABLE1[(amplitude_v, frequency_label(frequency_hz))]


def format_table(records: list[dict]) -> str:
    """Table 1 beside the paper's numbers, as fixed-width text."""
    lines = [
        "Table 1: IPMC tip displacement range, simulated plant vs paper (mm)",
        f"{'V':>3} {'f (Hz)':>11} | {'lower':>7} {'upper':>7} {'range':>7} | "
        f"{'paper lo':>8} {'paper up':>8} {'paper rg':>8} | {'range err':>9}",
        "-" * 86,
    ]
    for rec in records:
        plo, pup, prg = paper_row(rec["amplitude_v"], rec["frequency_hz"])
        label = frequency_label(rec["frequency_hz"])
        err = 100.0 * (rec["range_mm"] - prg) / prg
        lines.append(
            f"{rec['amplitude_v']:>3.0f} {label:>11} | {rec['lower_mm']:>7.3f} "
            f"{rec['upper_mm']:>7.3f} {rec['range_mm']:>7.3f} | {plo:>8.3f} {pup:>8.3f} "
            f"{prg:>8.3f} | {err:>+8.1f}%")
    return "\n".join(lines)


def plot_records(records: list[dict], out_dir: Path) -> list[Path]:
    """Write one PNG per condition (voltage, displacement, loop) and a summary bar chart."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for rec in records:
        label = frequency_label(rec["frequency_hz"])
        fig = plt.figure(figsize=(10, 5))
        ax_u = fig.add_subplot(2, 2, 1)
        ax_y = fig.add_subplot(2, 2, 3, sharex=ax_u)
        ax_l = fig.add_subplot(1, 2, 2)
        ax_u.plot(rec["t_s"], rec["u_v"], "b-", lw=1)
        ax_u.set_ylabel("voltage (V)")
        ax_y.plot(rec["t_s"], rec["y_mm"], "r-", lw=1)
        ax_y.set_ylabel("tip displacement (mm)")
        ax_y.set_xlabel("time (s)")
        ax_l.plot(rec["u_v"], rec["y_mm"], "k-", lw=0.8)
        ax_l.set_xlabel("voltage (V)")
        ax_l.set_ylabel("tip displacement (mm)")
        ax_l.set_title(f"{rec['amplitude_v']:.0f} V, {label} Hz: range {rec['range_mm']:.2f} mm")
        ax_l.grid(True, alpha=0.3)
        fig.tight_layout()
        path = out_dir / f"table1_{rec['amplitude_v']:.0f}V_{label.replace('/', '_')}Hz.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)

    fig, ax = plt.subplots(figsize=(8, 4))
    x = np.arange(len(records))
    ax.bar(x - 0.2, [r["range_mm"] for r in records], 0.4, label="simulated plant")
    ax.bar(x + 0.2, [paper_row(r["amplitude_v"], r["frequency_hz"])[2] for r in records], 0.4,
           label="paper Table 1")
    ax.set_xticks(x, [f"{r['amplitude_v']:.0f}V\n"
                      f"{frequency_label(r['frequency_hz'])}"
                      for r in records])
    ax.set_ylabel("tip displacement range (mm)")
    ax.legend()
    fig.tight_layout()
    path = out_dir / "table1_ranges.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="ipmc characterize",
        description="Run the paper's nine sine conditions (Table 1) on the simulated IPMC, "
                    "print the ranges beside the paper's, and write figures.")
    parser.add_argument("--params", help="plant parameter YAML (default: the shipped one)")
    parser.add_argument("--effect", action="extend", nargs="+", default=[], choices=EFFECTS,
                        help="optional plant effect(s) to switch on (repeatable)")
    parser.add_argument("--seed", type=int, default=0, help="sensor-noise seed")
    parser.add_argument("--rate-hz", type=float, default=100.0, help="sample rate (Hz)")
    parser.add_argument("--json", metavar="OUT", help="write the nine conditions as JSON")
    parser.add_argument("--plots", metavar="DIR", default="out/characterize",
                        help="directory for PNG figures (default: out/characterize; '' = none)")
    args = parser.parse_args(argv)
    try:
        params = load_plant_params(args.params)
    except ValueError as exc:
        print(f"ipmc characterize: {exc}", file=sys.stderr)
        return 2
    records = characterize(params, effects=args.effect, seed=args.seed, rate_hz=args.rate_hz)
    print(format_table(records))
    keys = ("amplitude_v", "frequency_hz", "lower_mm", "upper_mm", "range_mm")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(
            {"conditions": [{k: float(r[k]) for k in keys} for r in records]}, indent=2) + "\n")
        print(f"wrote {args.json}")
    if args.plots:
        paths = plot_records(records, Path(args.plots))
        print(f"wrote {len(paths)} figures to {args.plots}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
