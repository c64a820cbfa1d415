"""Launch files (ros2 launch is not on PyPI): every node they start must exist, and they must
start the same graph as `ipmc bringup`."""

from __future__ import annotations

import ast
from importlib.metadata import entry_points
from pathlib import Path

import pytest

from ipmc_control.bringup import graph_specs

LAUNCH_DIR = Path(__file__).resolve().parents[1] / "ros2_ws" / "src" / "ipmc_control" / "launch"


def launched_nodes(path: Path) -> list[tuple[str, str]]:
    """(package, executable) of every launch_ros ``Node(...)`` call in a launch file."""
    nodes = []
    for call in ast.walk(ast.parse(path.read_text())):
        if isinstance(call, ast.Call) and getattr(call.func, "id", "") == "Node":
            kw = {k.arg: k.value.value for k in call.keywords
                  if isinstance(k.value, ast.Constant)}
            nodes.append((kw["package"], kw["executable"]))
    return nodes


@pytest.mark.parametrize("name", ["sim.launch.py", "rig.launch.py"])
def test_launch_file_names_installed_executables(name):
    scripts = {(ep.dist.name if ep.dist else "", ep.name)
               for ep in entry_points(group="console_scripts")}
    nodes = launched_nodes(LAUNCH_DIR / name)
    assert len(nodes) >= 4
    for package, executable in nodes:
        assert (package.replace("_", "-"), executable) in {
            (d.replace("_", "-"), e) for d, e in scripts}, f"{package}/{executable} not installed"


@pytest.mark.parametrize("name,rig", [("sim.launch.py", None), ("rig.launch.py", "/dev/ttyX")])
def test_launch_file_starts_the_same_graph_as_bringup(name, rig):
    launched = sorted(exe for _, exe in launched_nodes(LAUNCH_DIR / name))
    specs = graph_specs(rig_port=rig, lockstep=False, model="m.json", mode="hybrid",
                        reference="sine", plant_effects=[], record="bag")
    assert launched == sorted(s.executable for s in specs)
