"""Benchmark: the GPI model (rate-dependent generalised Prandtl-Ishlinskii, ``ipmc identify``'s
default family) on data it was not designed on, every figure free run from the input alone.

Sections (each prints its table; ``--only NAME`` runs one):

* ``rig``: the simulated IPMC, identified on one ``mixed`` record (600 s, seed 1), and on a
  random sine alone (240 s, as ``make demo``'s LSSVM-NARX), validated on ``mixed`` records of
  seeds 2 and 3 and on the paper's three validation sets (as ``make demo`` simulates them);
  the sensor's noise floor beside.
* ``duhem``: a plant of another structure (``ipmc_model/test/duhem_plant.py``: Duhem
  hysteresis, two relaxations, polynomial asymmetry, 40 ms delay), seeds 11-13, beside a
  linear ARX(6, 6). Never used to choose the structure.
* ``piezo``: the measured piezo record of ``../shared/data``: identified on the first half,
  free run of the whole record scored on the second; fit % beside ARX(6, 6) and PI (NNLS).
* ``boucwen``: the Bouc-Wen benchmark, identified on the training multisine, free run on the
  test multisine and sine sweep from zero state, RMSE in metres beside PNLSS's 1.87e-5.
* ``periodic``: one sine identified (the default and ``--model lssvm-narx``), a random sine
  validated, beside a linear ARX(6, 6): does the model collapse on another input?
* ``time``: ``ipmc identify --data F --out M`` (the default comparison and the refit) on a
  60 000-sample record: wall and CPU time (on one BLAS thread the CPU time is the wall time
  of an otherwise idle machine).

Not part of the pass/fail suite. Usage: ``.venv/bin/python benchmarks/bench_gpi.py [--only S]``.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
sys.path.insert(0, str(ROOT / "ros2_ws" / "src" / "ipmc_model" / "test"))

from ipmc_driver.plant import IpmcPlant  # noqa: E402
from ipmc_driver.signals import mixed  # noqa: E402
from ipmc_driver.simulate_cli import make_input  # noqa: E402
from ipmc_model.hysteresis import GeneralizedPI  # noqa: E402
from ipmc_model.metrics import fit_percent  # noqa: E402
from ipmc_model.play import PrandtlIshlinskii  # noqa: E402
from ipmc_model.selection import LinearArx  # noqa: E402

PAPER_SETS = {  # name: (input, amplitude V, frequency Hz, seconds, seed), as make demo's
    "2 V @ 1/2pi Hz": ("sine", 2.0, 1 / (2 * math.pi), 40.0, 7),
    "3 V @ 5/2pi Hz": ("sine", 3.0, 5 / (2 * math.pi), 40.0, 7),
    "random sine II": ("random-sine", 3.0, 0.8, 60.0, 2),
}
PAPER_RMSE_MM = {"2 V @ 1/2pi Hz": 0.131, "3 V @ 5/2pi Hz": 0.126, "random sine II": 0.094}


def _rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def _mixed_record(seed: int, seconds: float = 600.0):
    _, u = mixed(seconds, 100.0, 3.0, (0.02, 0.8), seed=seed)
    return u, IpmcPlant(seed=seed).run(u).y_mm


def rig() -> None:
    p = IpmcPlant().params
    floor = math.hypot(p["noise_std_mm"], p["resolution_mm"] / math.sqrt(12))
    _, u_rs = make_input("random-sine", amplitude_v=3.0, frequency_hz=1.0, seconds=240.0,
                         rate_hz=100.0, seed=1)
    records = {"mixed seed 1, 600 s": _mixed_record(1),
               "random sine 240 s (no holds)": (u_rs, IpmcPlant(seed=1).run(u_rs).y_mm)}
    vals = {f"mixed seed {seed}": _mixed_record(seed) for seed in (2, 3)}
    for name, (kind, amp, f, sec, seed) in PAPER_SETS.items():
        _, uv = make_input(kind, amplitude_v=amp, frequency_hz=f, seconds=sec, rate_hz=100.0,
                           seed=seed)
        vals[name] = (uv, IpmcPlant(seed=seed).run(uv).y_mm)
    for train, (u, y) in records.items():
        m = GeneralizedPI().fit(u, y)
        print(f"rig: identified on {train} in {m.fit_seconds_:.1f} s; noise floor "
              f"{floor:.4f} mm")
        print(f"{'validation record':<24} {'free-run RMSE':>14} {'x floor':>8} {'paper':>8}")
        for name, (uv, yv) in vals.items():
            e = _rmse(m.simulate(uv), yv)
            paper = f"{PAPER_RMSE_MM[name]:>8.3f}" if name in PAPER_RMSE_MM else ""
            print(f"{name:<24} {e:>11.4f} mm {e / floor:>8.1f} {paper}")


def duhem() -> None:
    from duhem_plant import NOISE_FLOOR_MM, duhem_plant

    print(f"duhem: noise floor {NOISE_FLOOR_MM:.4f} mm; identified on mixed 300 s, validated "
          "on mixed 300 s of seed + 100")
    print(f"{'seed':<6} {'GPI free run':>13} {'x floor':>8} {'ARX(6,6)':>10}")
    for seed in (11, 12, 13):
        _, u = mixed(300.0, 100.0, 3.0, (0.02, 0.8), seed=seed)
        _, uv = mixed(300.0, 100.0, 3.0, (0.02, 0.8), seed=seed + 100)
        y, yv = duhem_plant(u, seed), duhem_plant(uv, seed + 100)
        e = _rmse(GeneralizedPI().fit(u, y).simulate(uv), yv)
        ea = _rmse(LinearArx().fit(u, y).simulate(uv), yv)
        print(f"{seed:<6} {e:>10.4f} mm {e / NOISE_FLOOR_MM:>8.1f} {ea:>7.4f} mm")


def piezo() -> None:
    d = np.genfromtxt(DATA / "piezo_smarthysteresis" / "hysteresis_v_150_1hz.csv",
                      delimiter=",")
    t, y, u = d[:, 1], d[:, 2], d[:, 3]
    dt = float(np.median(np.diff(t)))
    cut = u.size // 2
    print(f"piezo: {u.size} samples at {1 / dt:.0f} Hz; fit on the first half, free run of the "
          "whole record scored on the second")
    print(f"{'model':<10} {'fit % (2nd half)':>17} {'RMSE um':>9}")
    models = {"GPI": GeneralizedPI(dt_s=dt), "ARX(6,6)": LinearArx(),
              "PI (NNLS)": PrandtlIshlinskii(n_operators=10, method="nnls")}
    for name, m in models.items():
        ys = m.fit(u[:cut], y[:cut]).simulate(u)
        fit, e = fit_percent(y[cut:], ys[cut:]), _rmse(ys[cut:], y[cut:])
        print(f"{name:<10} {fit:>17.2f} {e:>9.4f}")


def boucwen() -> None:
    def load(name):
        d = np.loadtxt(DATA / "boucwen" / name, delimiter=",", skiprows=1)
        return d[:, 0], d[:, 1] * 1e3  # N, mm (the model's output unit; reported in m)

    u, y = load("train_multisine.csv")
    t0 = time.perf_counter()
    m = GeneralizedPI(dt_s=1 / 750.0).fit(u, y)
    arx = LinearArx().fit(u, y)
    print(f"boucwen: identified on the training multisine ({u.size} samples) in "
          f"{time.perf_counter() - t0:.1f} s; free run from zero state, RMSE in m")
    print(f"{'test record':<16} {'GPI':>10} {'ARX(6,6)':>10} {'PNLSS':>10}")
    for name in ("test_multisine.csv", "test_sinesweep.csv"):
        uv, yv = load(name)
        e, ea = _rmse(m.simulate(uv), yv) * 1e-3, _rmse(arx.simulate(uv), yv) * 1e-3
        ref = "1.87e-05" if "multisine" in name else "-"
        print(f"{name[:-4]:<16} {e:>10.3g} {ea:>10.3g} {ref:>10}")


def periodic() -> None:
    """One periodic sine (2.5 V, 0.25 Hz, 120 s) identified, a random sine validated: the
    default ``ipmc identify`` and the LSSVM-NARX it tunes when forced, beside ARX(6, 6)."""
    from ipmc_driver.dataio import Record, save_csv
    from ipmc_driver.signals import random_sine, sine
    from ipmc_model.persistence import load_model

    _, u = sine(2.5, 0.25, 120.0)
    y = IpmcPlant(seed=8).run(u).y_mm
    _, uv = random_sine(60.0, 100.0, 3.0, band_hz=(0.02, 0.8), seed=9)
    yv = IpmcPlant(seed=9).run(uv).y_mm
    print("periodic: identified on one sine (2.5 V, 0.25 Hz, 120 s), free run on a random sine")
    with tempfile.TemporaryDirectory() as tmp:
        csv = save_csv(Record(t_s=np.arange(u.size) / 100.0, u_v=u, y_mm=y),
                       Path(tmp) / "sine.csv")
        for label, extra in (("default (ipmc identify)", []),
                             ("lssvm-narx (--model lssvm-narx)", ["--model", "lssvm-narx"])):
            out = Path(tmp) / "m.json"
            subprocess.run([sys.executable, "-m", "ipmc_driver.cli", "identify", "--data",
                            str(csv), *extra, "--out", str(out)], check=True,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            m = load_model(out)
            lag = int(getattr(m, "max_lag_", 0))
            ys = m.simulate(uv, yv[:lag]) if lag else m.simulate(uv)
            print(f"{label:<34} {_rmse(ys[lag:], yv[lag:]):.4f} mm")
    print(f"{'ARX(6, 6)':<34} {_rmse(LinearArx(6, 6).fit(u, y).simulate(uv), yv):.4f} mm")


def timing() -> None:
    u, y = _mixed_record(1)
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "rec.csv"
        np.savetxt(csv, np.column_stack([np.arange(u.size) / 100.0, u, y]), delimiter=",",
                   header="t,u,y", comments="", fmt="%.9g")
        t0, cpu0 = time.perf_counter(), _children_cpu_s()
        subprocess.run([sys.executable, "-m", "ipmc_driver.cli", "identify", "--data", str(csv),
                        "--out", str(Path(tmp) / "m.json")], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        # One BLAS thread (the ipmc command's default): the CPU time is the wall time the
        # command takes on a machine nothing else loads.
        print(f"time: ipmc identify --data F --out M on {u.size} samples: "
              f"{time.perf_counter() - t0:.1f} s wall, {_children_cpu_s() - cpu0:.1f} s CPU "
              f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


SECTIONS = {"rig": rig, "duhem": duhem, "piezo": piezo, "boucwen": boucwen,
            "periodic": periodic, "time": timing}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", choices=tuple(SECTIONS), action="append")
    for name in p.parse_args().only or SECTIONS:
        SECTIONS[name]()
        print(flush=True)


if __name__ == "__main__":
    main()
