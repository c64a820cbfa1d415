"""``ipmc simulate``: run the simulated IPMC offline and write ``t,u,y`` (s, V, mm) as CSV."""

from __future__ import annotations

import argparse
import sys

from .dataio import Record, check_plausibility, print_notes, save_csv
from .plant import EFFECTS, IpmcPlant, load_plant_params
from .signals import mixed, random_sine, random_steps, sine
from .validation import check_output_file

INPUTS = ("sine", "random-sine", "steps", "mixed")


def make_input(kind: str, *, amplitude_v: float, frequency_hz: float, seconds: float,
               rate_hz: float, seed: int):
    """The drive voltage (V) of one of ``INPUTS``; returns ``(t_s, u_v)``."""
    if kind == "sine":
        return sine(amplitude_v, frequency_hz, seconds, rate_hz)
    if kind == "random-sine":
        # frequency_hz is the top of the band: the paper's random sines stay below ~0.8 Hz.
        return random_sine(seconds, rate_hz, amplitude_v, band_hz=(0.02, frequency_hz),
                           seed=seed)
    if kind == "steps":
        return random_steps(seconds, rate_hz, amplitude_v, seed=seed)
    if kind == "mixed":
        # Random sine over the band, a slow random sine, then held levels: see signals.mixed.
        return mixed(seconds, rate_hz, amplitude_v, band_hz=(0.02, frequency_hz), seed=seed)
    raise ValueError(f"unknown input '{kind}'; choose one of {', '.join(INPUTS)}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="ipmc simulate",
        description="Drive the simulated IPMC offline; write t,u,y (s, V, mm) as CSV.")
    parser.add_argument("--input", choices=INPUTS, default="random-sine",
                        help="drive signal (default random-sine)")
    parser.add_argument("--amplitude", type=float, default=3.0, help="peak voltage, V")
    parser.add_argument("--frequency", type=float, default=0.8,
                        help="sine frequency, or top of the random-sine (and mixed) band, Hz")
    parser.add_argument("--seconds", type=float, default=120.0, help="duration, s")
    parser.add_argument("--rate-hz", type=float, default=100.0, help="sample rate, Hz")
    parser.add_argument("--seed", type=int, default=0, help="seed of the input and the noise")
    parser.add_argument("--effect", action="extend", nargs="+", default=[], choices=EFFECTS,
                        help="optional plant effect(s) to switch on (repeatable)")
    parser.add_argument("--params", help="plant parameter YAML (default: the shipped one)")
    parser.add_argument("--out", required=True,
                        help="output CSV file (.csv; checked before the run, written whole or "
                             "not at all)")
    args = parser.parse_args(argv)
    try:
        check_output_file(args.out, option="--out", suffixes=(".csv",))
        if args.amplitude > 3.0:
            print("ipmc simulate: note: the H-bridge limits the drive to 3 V", file=sys.stderr)
        t, u = make_input(args.input, amplitude_v=args.amplitude, frequency_hz=args.frequency,
                          seconds=args.seconds, rate_hz=args.rate_hz, seed=args.seed)
        plant = IpmcPlant(load_plant_params(args.params), effects=args.effect, seed=args.seed,
                          dt_s=1.0 / args.rate_hz)
        run = plant.run(u)
        record = Record(t_s=run.t_s, u_v=run.u_v, y_mm=run.y_mm)
        # the plant parameters (--params) set the record's scale: warn here about what
        # ipmc identify would find implausible in the file
        print_notes("ipmc simulate", check_plausibility(record, source=str(args.out),
                                                        allow_implausible=True))
        path = save_csv(record, args.out)
    except (ValueError, OSError) as exc:
        print(f"ipmc simulate: error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {path}: {t.size} samples at {args.rate_hz:g} Hz, input {args.input}, "
          f"effects {args.effect or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
