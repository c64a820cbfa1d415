"""Benchmark: LSSVM-NARX identification (ABC tuning + final fit) time and peak memory versus
record length (1k, 10k, 60k samples of the simulated rig at 100 Hz), beside scikit-learn's
KernelRidge with a grid search of the same number of candidate fits as an anchor.

Each case runs in a fresh subprocess so that its peak resident memory (ru_maxrss) is its own.
Not part of the pass/fail suite. Usage:

    .venv/bin/python benchmarks/bench_model_fit.py [--sizes 1000,10000,60000] [--budget 10x10]

The LSSVM-NARX recipe is the long-record one of docs/models.md: lags 6/6 at a fixed lag step
10, candidates and final model on at most 6000 regressor rows (evenly spaced; fixed-size with
500 prototypes above 2000 rows, exact below), holdout validation on 3000 samples. The
KernelRidge anchor fits the same rows (all of them, 70/30 holdout).

Goal: 60 000 samples tuned and fitted in <= 120 s, < 2 GB.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

CASE = r"""
import json, os, resource, sys, time
import numpy as np
from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import random_sine
kind, n, sources, cycles, lag_step = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), \
    int(sys.argv[4]), int(sys.argv[5])
recipe = json.loads(sys.argv[7])
_, u = random_sine(n / 100.0, 100.0, 3.0, seed=1)
y = IpmcPlant(seed=1).run(u).y_mm
out = {"kind": kind, "n": n}
t0 = time.perf_counter()
if kind == "lssvm-narx":
    from ipmc_model.tuning import identify_lssvm_narx
    model, tuning = identify_lssvm_narx(u, y, lag_step=lag_step, n_sources=sources,
                                        n_cycles=cycles, seed=0, **recipe)
    out["seconds"] = time.perf_counter() - t0
    out["tuning_seconds"] = tuning.seconds
    out["fits"] = tuning.nfev
    out["C"], out["sigma"] = tuning.C, tuning.sigma
    out["regressor"] = type(model.regressor_).__name__
    out["centers"] = int(model.regressor_.centers_.shape[0])
    st = model.stepper()
    ts = []
    for v in u[:2000]:
        t1 = time.perf_counter(); st.step(v); ts.append(time.perf_counter() - t1)
    out["step_us_median"] = float(np.median(ts) * 1e6)
else:
    from sklearn.kernel_ridge import KernelRidge
    from ipmc_model.narx import NarxModel
    from ipmc_model.lssvm import LSSVMRegressor
    # Same regressor rows as the NARX model (standardised, lags 3/3); holdout 70/30 split;
    # one-step score (KernelRidge has no free run). n_fits candidates on a square grid.
    n_fits = sources * (2 * cycles + 1)
    m = NarxModel(LSSVMRegressor(), lag_step=lag_step, input_lags=recipe["input_lags"],
                  output_lags=recipe["output_lags"])
    m.fit(u[:500], y[:500])  # only to get the row builder; rows below use this record's scaling
    m.u_mean_, m.u_scale_ = np.array([u.mean()]), np.array([u.std()])
    m.y_mean_, m.y_scale_ = float(y.mean()), float(y.std())
    X = m._rows(u[:, None], y)
    t = m._scale_y(y)[m.max_lag_:]
    cut = int(0.7 * len(t))
    side = int(np.ceil(np.sqrt(n_fits)))
    grid = [(a, g) for a in np.logspace(-7, 0, side) for g in np.logspace(-3, 1, side)][:n_fits]
    limit = float(sys.argv[6])
    done = 0
    for a, g in grid:
        kr = KernelRidge(alpha=a, kernel="rbf", gamma=g).fit(X[:cut], t[:cut])
        kr.predict(X[cut:])
        done += 1
        if time.perf_counter() - t0 > limit:
            break
    el = time.perf_counter() - t0
    out["fits_done"], out["fits"] = done, n_fits
    out["seconds"] = el if done == n_fits else el / done * n_fits
    out["extrapolated"] = done < n_fits
ru = resource.getrusage(resource.RUSAGE_SELF)
out["peak_rss_mb"] = ru.ru_maxrss / 1024.0
# CPU time of this process: the wall time on a shared machine depends on the other jobs
out["cpu_s"] = ru.ru_utime + ru.ru_stime
out["loadavg"] = os.getloadavg()[0]
print(json.dumps(out))
"""


def run_case(kind, n, sources, cycles, lag_step, limit_s, recipe):
    proc = subprocess.run([sys.executable, "-c", CASE, kind, str(n), str(sources), str(cycles),
                           str(lag_step), str(limit_s), json.dumps(recipe)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        return {"kind": kind, "n": n, "error": proc.stderr.strip().splitlines()[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="1000,10000,60000")
    p.add_argument("--budget", default="10x10", help="ABC SOURCESxCYCLES (default 10x10)")
    p.add_argument("--lag-step", type=int, default=10)
    p.add_argument("--lags", type=int, default=6, help="input and output lags")
    p.add_argument("--folds", type=int, default=1, help="tuning validation folds")
    p.add_argument("--prototypes", type=int, default=500)
    p.add_argument("--max-rows", type=int, default=6000,
                   help="regressor rows for tuning candidates and the final fit (evenly spaced)")
    p.add_argument("--max-val", type=int, default=3000, help="validation samples per fold")
    p.add_argument("--kr-limit-s", type=float, default=60.0,
                   help="stop the KernelRidge grid after this long and extrapolate")
    p.add_argument("--json", help="also write the rows as JSON")
    args = p.parse_args(argv)
    sources, cycles = (int(v) for v in args.budget.split("x"))
    recipe = {"input_lags": args.lags, "output_lags": args.lags, "n_folds": args.folds,
              "n_prototypes": args.prototypes, "max_train_rows": args.max_rows,
              "max_val_samples": args.max_val}
    print(f"# recipe: lags {args.lags}/{args.lags}, lag step {args.lag_step}, {recipe}",
          flush=True)
    print(f"# LSSVM-NARX identification (ABC {sources}x{cycles} free-run tuning + final fit) "
          f"vs KernelRidge grid of the same size; {os.cpu_count()} CPUs", flush=True)
    print("| samples | method | fits | wall time (s) | CPU time (s) | peak RSS (MB) | notes |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for n in (int(v) for v in args.sizes.split(",")):
        t0 = time.perf_counter()
        r = run_case("lssvm-narx", n, sources, cycles, args.lag_step, args.kr_limit_s, recipe)
        rows.append(r)
        if "error" in r:
            print(f"| {n} | LSSVM-NARX + ABC | - | - | - | - | failed: {r['error']} |",
                  flush=True)
        else:
            print(f"| {n} | LSSVM-NARX + ABC | {r['fits']} | {r['seconds']:.1f} | "
                  f"{r['cpu_s']:.1f} | {r['peak_rss_mb']:.0f} | {r['regressor']} "
                  f"({r['centers']} centres, load average {r['loadavg']:.1f}), "
                  f"C={r['C']:.3g}, sigma={r['sigma']:.3g}, tuning {r['tuning_seconds']:.1f} s, "
                  f"step {r['step_us_median']:.0f} us |", flush=True)
        if n > 20000:
            note = (f"infeasible: the {n - 3}^2 kernel matrix alone needs "
                    f"{(n * 0.7) ** 2 * 8 / 1e9:.1f} GB")
            print(f"| {n} | KernelRidge grid | {sources * (2 * cycles + 1)} | - | - | - | "
                  f"{note} |")
            rows.append({"kind": "kernel-ridge", "n": n, "note": note})
            continue
        r = run_case("kernel-ridge", n, sources, cycles, args.lag_step, args.kr_limit_s, recipe)
        rows.append(r)
        if "error" in r:
            print(f"| {n} | KernelRidge grid | - | - | - | - | failed: {r['error']} |",
                  flush=True)
        else:
            note = (f"extrapolated from {r['fits_done']} fits" if r["extrapolated"]
                    else "one-step holdout score")
            print(f"| {n} | KernelRidge grid | {r['fits']} | {r['seconds']:.1f} | "
                  f"{r['cpu_s']:.1f} | {r['peak_rss_mb']:.0f} | {note} |", flush=True)
        _ = t0
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
