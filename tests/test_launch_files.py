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


def test_bringup_serves_each_kind_of_feedforward_model_as_model_server_expects(tmp_path):
    from ipmc_control.bringup import feedforward_server_params
    from ipmc_driver.cli import main as ipmc

    data = tmp_path / "d.csv"
    assert ipmc(["simulate", "--input", "mixed", "--seconds", "20", "--seed", "2",
                 "--out", str(data)]) == 0
    fwd, inv, plain = tmp_path / "fwd.json", tmp_path / "inv.json", tmp_path / "plain.json"
    common = ["--data", str(data), "--model", "lssvm-narx", "--tune", "none", "--C", "100",
              "--sigma", "1", "--prototypes", "50"]
    assert ipmc(["identify", *common, "--input-memory-taus", "0.3", "0.5", "--no-raw-voltage",
                 "--out", str(fwd)]) == 0
    assert ipmc(["identify", *common, "--inverse", "--output-lags", "2", "--out", str(inv)]) == 0
    assert ipmc(["identify", *common, "--input-lags", "2", "--output-lags", "2",
                 "--out", str(plain)]) == 0
    assert feedforward_server_params(str(fwd)) == {"model_file": str(fwd.resolve()),
                                                   "feedforward": "forward-inversion"}
    assert feedforward_server_params(str(inv)) == {"inverse_model_file": str(inv.resolve())}
    # Not a feedforward model, or not a model: model_server gets it as the inverse and says why.
    assert feedforward_server_params(str(plain)) == {"inverse_model_file": str(plain.resolve())}
    assert feedforward_server_params(str(tmp_path / "none.json")) == {
        "inverse_model_file": str((tmp_path / "none.json").resolve())}
    specs = graph_specs(rig_port=None, lockstep=True, model=str(fwd), mode="hybrid",
                        reference="sine", plant_effects=[], record=None)
    server = next(s for s in specs if s.name == "model_server")
    assert server.params["feedforward"] == "forward-inversion"
    assert server.params["model_file"] == str(fwd.resolve())


@pytest.mark.parametrize("model,record,listeners", [("m.json", "bag", 3), (None, None, 1)])
def test_lockstep_bringup_waits_for_every_listener_it_starts(model, record, listeners):
    """In lock-step, time and the reference's first samples wait until every node started
    that listens (controller, model_server, recorder) has matched, not only those the graph
    lists by then; the plant also waits for the controller's stamped commands."""
    specs = {s.name: s.params for s in graph_specs(
        rig_port=None, lockstep=True, model=model, mode="hybrid", reference="sine",
        plant_effects=[], record=record)}
    assert specs["reference"]["min_subscribers"] == listeners
    assert specs["sim_plant"]["lockstep_min_subscribers"] == listeners
    assert specs["sim_plant"]["lockstep_min_command_publishers"] == 1
    realtime = {s.name: s.params for s in graph_specs(
        rig_port=None, lockstep=False, model=model, mode="hybrid", reference="sine",
        plant_effects=[], record=record)}
    assert "min_subscribers" not in realtime["reference"]
    assert "lockstep_min_command_publishers" not in realtime["sim_plant"]
