"""Feedforward from the inverse LSSVM-NARX vs from the inverted FORWARD model .

    .venv/bin/python scripts/forward_inversion_experiment.py --out-dir build/forward_inversion

1. Training data and the inverse model exactly as docs/control.md's recipe (``ipmc simulate``
   and ``ipmc identify`` in process).
2. The forward model: an NFIR LSSVM in the voltage low-passed with 0.3 and 0.5 s (no raw
   voltage, no output lags; see ipmc_model.forward_inversion for why), trained on the same
   kind of record but with a wider band (random-sine voltage 0.02-0.8 Hz, 3 V, 300 s, seed 1),
   C = 1e6, sigma = 1, 800 prototypes. Chosen on held-out references only (random sines
   0-0.7 Hz, -4..2 mm, seeds 1 and 2) and on free-run records (seeds 5 and 6).
3. ``run_tracking`` (noisy simulated plant, the paper's PID) in modes inverse and hybrid on
   the held-out references, then on the test references random-reachable (seed 0) and sine;
   per-step feedforward compute time (step + record_applied) p50 / p99.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from ipmc_control.demo import INVERSE, TRAIN_INVERSE
from ipmc_control.experiment import DEFAULT_DURATION_S, paper_reference, run_tracking
from ipmc_control.references import make_reference
from ipmc_driver.dataio import load_record
from ipmc_driver.plant import IpmcPlant
from ipmc_driver.simulate_cli import main as simulate_main
from ipmc_model.forward_inversion import ForwardInversionFeedforward
from ipmc_model.identify_cli import identify_main
from ipmc_model.narx import NarxModel, make_lssvm
from ipmc_model.persistence import load_model, save_model

TAUS_S = (0.3, 0.5)
DT_S = 0.01


def fit_forward(data_csv: Path, C: float, sigma: float, prototypes: int) -> NarxModel:
    rec = load_record(data_csv)
    reg = make_lssvm(C, sigma, n_samples=rec.u_v.size, n_prototypes=prototypes, seed=0)
    model = NarxModel(reg, input_lags=0, output_lags=0, input_memory_taus_s=TAUS_S,
                      include_voltage=False, dt_s=DT_S)
    return model.fit(rec.u_v, rec.y_mm)  # the model builds its voltage channels itself


class Timed:
    """Wraps a feedforward; records the wall time of each step + record_applied, s."""

    def __init__(self, ff):
        self.ff, self.times_s = ff, []

    def stepper(self):
        inner, times = self.ff.stepper(), self.times_s

        class _S:
            def step(self, r_mm):
                self._t0 = time.perf_counter()
                return inner.step(r_mm)

            def record_applied(self, u_v):
                inner.record_applied(u_v)
                times.append(time.perf_counter() - self._t0)

        return _S()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out-dir", default="build/forward_inversion")
    p.add_argument("--C", type=float, default=1e6)
    p.add_argument("--sigma", type=float, default=1.0)
    p.add_argument("--prototypes", type=int, default=800)
    p.add_argument("--band-hz", type=float, default=0.8, help="top of the forward data's band")
    args = p.parse_args(argv)
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("OMP_NUM_THREADS", "1")

    train = out / "train.csv"
    simulate_main([*TRAIN_INVERSE, "--out", str(train)])
    identify_main(["--data", str(train), *INVERSE, "--out", str(out / "inverse.json")])
    inverse = load_model(out / "inverse.json")
    fwd_data = out / "forward_train.csv"
    simulate_main(["--input", "random-sine", "--amplitude", "3", "--frequency",
                   f"{args.band_hz:g}", "--seconds", "300", "--seed", "1", "--out",
                   str(fwd_data)])
    t0 = time.perf_counter()
    forward = fit_forward(fwd_data, args.C, args.sigma, args.prototypes)
    print(f"forward model fitted in {time.perf_counter() - t0:.1f} s")
    meta = {"data": str(fwd_data), "C": args.C, "sigma": args.sigma}
    save_model(forward, out / "forward.json", metadata=meta)
    for v_seed, amp in ((5, "3"), (6, "2")):  # free-run check on records it never saw
        vcsv = out / f"validation_{v_seed}.csv"
        simulate_main(["--input", "random-sine", "--amplitude", amp, "--frequency", "0.7",
                       "--seconds", "60", "--seed", str(v_seed), "--out", str(vcsv)])
        rec = load_record(vcsv)
        ys = forward.simulate(rec.u_v)
        print(f"forward free-run RMSE on {vcsv.name} ({amp} V, 0-0.7 Hz): "
              f"{np.sqrt(np.mean((ys - rec.y_mm) ** 2)):.4f} mm")
    fwd_ff = ForwardInversionFeedforward(load_model(out / "forward.json"))  # channels from file

    refs = [("held-out random seed 1", make_reference("random", band_hz=[0, 0.7],
                                                      range_mm=[-4, 2], seed=1), 60.0),
            ("held-out random seed 2", make_reference("random", band_hz=[0, 0.7],
                                                      range_mm=[-4, 2], seed=2), 60.0),
            ("random-reachable (test)", paper_reference("random-reachable"),
             DEFAULT_DURATION_S["random-reachable"]),
            ("sine (test)", paper_reference("sine"), DEFAULT_DURATION_S["sine"])]
    rows, record = [], []
    for ff_name, ff in (("(a) inverse LSSVM-NARX (recipe)", inverse),
                        ("(b) forward inversion", fwd_ff)):
        for ref_name, ref, dur in refs:
            cells = {}
            for mode in ("inverse", "hybrid"):
                timed = Timed(ff)
                res = run_tracking(ref, dur, mode, inverse=timed, plant=IpmcPlant(dt_s=DT_S))
                s = res.summary()
                us = np.array(timed.times_s) * 1e6
                cells[mode] = (s["rmse_mm"], np.percentile(us, 50), np.percentile(us, 99))
                record.append({"feedforward": ff_name, "reference": ref_name, "mode": mode,
                               **s, "ff_p50_us": cells[mode][1], "ff_p99_us": cells[mode][2]})
            rows.append(f"| {ff_name} | {ref_name} | {cells['inverse'][0]:.4f} | "
                        f"{cells['hybrid'][0]:.4f} | {cells['hybrid'][1]:.0f} / "
                        f"{cells['hybrid'][2]:.0f} |")
            print(rows[-1], flush=True)
    (out / "results.json").write_text(json.dumps(record, indent=1))
    print("\n| feedforward | reference | inverse only RMSE (mm) | hybrid RMSE (mm) | "
          "ff step p50 / p99 (us) |\n|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
