"""A ROS user's path: `colcon build` of the workspace, then an installed executable runs."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent


@pytest.mark.timeout(300)
def test_colcon_build_installs_runnable_executables(tmp_path):
    colcon = VENV_BIN / "colcon"
    if not colcon.exists():
        pytest.fail("colcon is missing from the venv: requirements.txt must install it")
    ws = tmp_path / "ws"
    ws.mkdir()
    env = {"PATH": f"{VENV_BIN}:/usr/bin:/bin", "HOME": str(tmp_path),
           "AMENT_PREFIX_PATH": str(VENV_BIN.parent)}
    build = subprocess.run(
        [str(colcon), "--log-base", str(ws / "log"), "build", "--base-paths",
         str(ROOT / "ros2_ws" / "src"), "--build-base", str(ws / "build"),
         "--install-base", str(ws / "install")],
        cwd=ws, env=env, capture_output=True, text=True, timeout=240)
    assert build.returncode == 0, build.stdout + build.stderr
    assert "3 packages finished" in build.stdout
    install = ws / "install"
    for pkg, exe in [("ipmc_driver", "sim_plant"), ("ipmc_driver", "recorder"),
                     ("ipmc_model", "identify"), ("ipmc_control", "controller")]:
        assert (install / pkg / "lib" / pkg / exe).exists(), f"{pkg}/{exe} not installed"
    assert (install / "ipmc_driver" / "share" / "ipmc_driver" / "package.xml").exists()

    # The installed copy (not the editable one) runs, with its shipped default parameters.
    script = (f"source {install}/setup.bash && "
              f"{install}/ipmc_driver/lib/ipmc_driver/sim_plant --help && "
              "python3 -c 'import ipmc_driver.plant as p; print(p.__file__); "
              "print(p.load_plant_params()[\"u_max_v\"])'")
    run = subprocess.run(["bash", "-c", script], env=env, capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "usage: sim_plant" in run.stdout
    assert str(install) in run.stdout and "3.0" in run.stdout
    shutil.rmtree(ws, ignore_errors=True)
