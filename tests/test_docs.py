"""The product speaks of itself: no development history in README, docs, code, --help or a
generated diagnosis report (history lives in git log and CHANGELOG.md)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HISTORY = re.compile(r"\bsessions? \d|\bmust[- ]shows?\b|\bissue \d|\bthe control issue\b|"
                     r"2-core machine shared", re.IGNORECASE)


def _tracked() -> list[Path]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.split()
    return [ROOT / f for f in out
            if f.endswith((".py", ".md", ".yaml", ".txt", ".cfg", ".toml")) or f == "Makefile"]


def test_no_history_wording_in_the_tree():
    hits = []
    for path in _tracked():
        if path.name == "CHANGELOG.md" or path == Path(__file__).resolve():
            continue
        for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if HISTORY.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()[:80]}")
    assert not hits, "\n".join(hits)


def test_readme_and_docs_stay_short():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 200
    assert sum(len(p.read_text().splitlines()) for p in (ROOT / "docs").glob("*.md")) <= 1500


def test_help_and_a_generated_report_have_no_history(tmp_path):
    from ipmc_driver.dataio import Record
    from ipmc_driver.plant import IpmcPlant
    from ipmc_driver.signals import random_steps
    from ipmc_model.diagnosis import diagnose
    from ipmc_model.diagnosis.report import write_report

    for cmd in ("identify", "evaluate", "diagnose", "track", "bringup", "simulate"):
        out = subprocess.run([sys.executable, "-m", "ipmc_driver.cli", cmd, "--help"],
                             capture_output=True, text=True)
        text = out.stdout + out.stderr
        assert not HISTORY.search(text), f"ipmc {cmd} --help: {HISTORY.search(text)}"
    _, u = random_steps(60.0, 50.0, 2.0, seed=1)
    run = IpmcPlant(seed=1, dt_s=0.02).run(u)
    rec = Record(run.t_s, u, run.y_mm)
    d = diagnose(rec.t_s, rec.u_v, rec.y_mm, candidates=["drift", "delay"])
    write_report(d, tmp_path, "steps")
    for name in ("report.md", "summary.json"):
        assert not HISTORY.search((tmp_path / name).read_text())
    assert np.isfinite(d.rmse_before_mm)
