"""``ipmc demo`` (``make demo``): the main job of ipmc-ros on the simulated rig, end to end.

1. Characterise the simulated IPMC: the paper's Table 1, beside the paper's numbers.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def _banner(text: str) -> None:
    print(f"\n=== {text} ===", flush=True)


def run_characterization(out: Path) -> None:
    from ipmc_driver.characterize import main as characterize_main

    _banner("1. Table 1: tip displacement range of the simulated IPMC vs the paper")
    characterize_main(["--json", str(out / "table1.json"), "--plots", str(out / "characterize")])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="ipmc demo",
        description="Run the ipmc-ros demonstration on the simulated rig; results go to --out.")
    parser.add_argument("--out", default="out", help="output directory (default: out)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    run_characterization(out)
    print(f"\ndemo finished in {time.monotonic() - t0:.0f} s; results in {out}/", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
