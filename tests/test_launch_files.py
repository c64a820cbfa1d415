"""Launch files (ros2 launch is not on PyPI): every node they start must exist, and they must
start the same graph, with the same parameters, as `ipmc bringup`.

The files are run against a stand-in for the parts of `launch` / `launch_ros` they use, which
evaluates node parameters by launch_ros's rules (values become YAML text and are parsed back; a
substitution that gives "" parses to None, which launch_ros refuses)."""

from __future__ import annotations

import runpy
import sys
import types
from importlib.metadata import entry_points
from pathlib import Path

import pytest
import yaml

from ipmc_control.bringup import graph_specs

LAUNCH_DIR = Path(__file__).resolve().parents[1] / "ros2_ws" / "src" / "ipmc_control" / "launch"


class _LaunchConfiguration:
    def __init__(self, name, default=None):
        self.name, self.default = name, default

    def perform(self, context):
        if self.name in context.launch_configurations:
            return context.launch_configurations[self.name]
        if self.default is None:
            raise LookupError(f"launch configuration {self.name!r} does not exist")
        return self.default


def _launch_ros_value(value, context=None):
    """A node parameter value as launch_ros (normalize + evaluate) hands it to the node."""
    if isinstance(value, _LaunchConfiguration):
        parsed = yaml.safe_load(value.perform(context))
        if not isinstance(parsed, bool | int | float | str | list):
            raise TypeError(f"launch_ros refuses {type(parsed)} (a substitution gave "
                            f"{value.perform(context)!r})")
        return parsed
    if isinstance(value, str):
        return yaml.safe_load(yaml.dump(value))
    if isinstance(value, bool | int | float):
        return value
    if isinstance(value, list | tuple):
        if not value:
            raise TypeError("launch_ros refuses an empty sequence")
        return [_launch_ros_value(v, context) for v in value]
    raise TypeError(f"launch_ros refuses a parameter value {value!r}")


def run_launch_file(path: Path, **arguments: str) -> dict[str, tuple[str, str, dict]]:
    """{node name: (package, executable, parameters)} that the launch file starts."""
    declared, opaque, nodes = {}, [], []

    class DeclareLaunchArgument:
        def __init__(self, name, default_value=None, description="", choices=None):
            declared[name] = default_value

    class OpaqueFunction:
        def __init__(self, function, args=None, kwargs=None):
            opaque.append(function)

    class Node:
        def __init__(self, **kw):
            nodes.append(kw)

    fake = {
        "launch": types.SimpleNamespace(LaunchDescription=list),
        "launch.actions": types.SimpleNamespace(DeclareLaunchArgument=DeclareLaunchArgument,
                                                OpaqueFunction=OpaqueFunction),
        "launch.substitutions": types.SimpleNamespace(LaunchConfiguration=_LaunchConfiguration),
        "launch_ros.actions": types.SimpleNamespace(Node=Node),
    }
    # ipmc_control.launching imports launch: load it afresh against this stand-in
    saved = {k: sys.modules.get(k) for k in [*fake, "ipmc_control.launching"]}
    sys.modules.pop("ipmc_control.launching", None)
    sys.modules.update(fake)
    try:
        runpy.run_path(str(path))["generate_launch_description"]()
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    unknown = set(arguments) - set(declared)
    assert not unknown, f"{path.name} does not declare {unknown}"
    missing = [n for n, d in declared.items() if d is None and n not in arguments]
    if missing:
        raise LookupError(f"{path.name} needs the launch argument(s) {missing}")
    context = types.SimpleNamespace(launch_configurations={**declared, **arguments})
    for function in opaque:
        function(context)
    launched = {}
    for kw in nodes:
        params = {}
        for block in kw.get("parameters", ()):
            params.update({k: _launch_ros_value(v, context) for k, v in block.items()})
        launched[kw["name"]] = (kw["package"], kw["executable"], params)
    return launched


def bringup_graph(**kw) -> dict[str, tuple[str, str, dict]]:
    """{node name: (package, executable, parameters)} of `ipmc bringup` (graph_specs)."""
    args = {"rig_port": None, "lockstep": False, "model": None, "mode": "hybrid",
            "reference": "sine", "plant_effects": [], "record": None, **kw}
    return {s.name: (s.package, s.executable, {k: _launch_ros_value(v)
                                               for k, v in s.params.items()})
            for s in graph_specs(**args)}


@pytest.mark.parametrize("name,args", [("sim.launch.py", {"model": "m.json"}),
                                       ("rig.launch.py", {"port": "/dev/ttyX"})])
def test_launch_file_names_installed_executables(name, args):
    scripts = {(ep.dist.name if ep.dist else "", ep.name)
               for ep in entry_points(group="console_scripts")}
    nodes = run_launch_file(LAUNCH_DIR / name, **args, mode="pid", record="bag").values()
    assert len(nodes) >= 4
    for package, executable, _ in nodes:
        assert (package.replace("_", "-"), executable) in {
            (d.replace("_", "-"), e) for d, e in scripts}, f"{package}/{executable} not installed"


@pytest.mark.parametrize("lockstep", ["false", "true"])
@pytest.mark.parametrize("model,record", [("m.json", "bag"), ("m.json", ""), ("", "bag"),
                                          ("", "")])
def test_sim_launch_starts_the_same_graph_as_bringup(lockstep, model, record):
    mode = "hybrid" if model else "pid"
    launched = run_launch_file(LAUNCH_DIR / "sim.launch.py", model=model, record=record,
                               mode=mode, lockstep=lockstep, reference="steps",
                               plant_effects="['creep', 'drift']")
    expected = bringup_graph(lockstep=lockstep == "true", model=model or None, mode=mode,
                             reference="steps", plant_effects=["creep", "drift"],
                             record=record or None)
    assert launched == expected
    if lockstep == "true":     # the listener counts that the old launch file left at defaults
        listeners = 1 + bool(model) + bool(record)
        assert launched["reference"][2]["min_subscribers"] == listeners
        assert launched["sim_plant"][2]["lockstep_min_subscribers"] == listeners


def test_rig_launch_starts_the_same_graph_as_bringup():
    launched = run_launch_file(LAUNCH_DIR / "rig.launch.py", port="/dev/ttyX", model="m.json",
                               record="bag")
    assert launched == bringup_graph(rig_port="/dev/ttyX", model="m.json", record="bag")
    with pytest.raises(LookupError, match="port"):
        run_launch_file(LAUNCH_DIR / "rig.launch.py", model="m.json")


def test_launch_arguments_are_checked_and_both_models_are_served(tmp_path):
    sim = LAUNCH_DIR / "sim.launch.py"
    with pytest.raises(ValueError, match="mode hybrid needs a model"):
        run_launch_file(sim)
    with pytest.raises(ValueError, match="lockstep"):
        run_launch_file(sim, mode="pid", lockstep="yes please")
    assert run_launch_file(sim, mode="pid", plant_effects="creep, delay")["sim_plant"][2][
        "effects"] == ["creep", "delay"]
    # An inverse model for the feedforward and a forward model for the prediction.
    server = run_launch_file(sim, model="inv.json", forward_model="fwd.json")["model_server"][2]
    assert server["inverse_model_file"] == str(Path("inv.json").resolve())
    assert server["model_file"] == str(Path("fwd.json").resolve())
    assert server["history_voltage"] == "clamped"


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
    # An augmented model's feedforward (ipmc identify --inverse --effects-from) is an inverse.
    from ipmc_model.effects import AugmentedModel, Effect, save_augmented
    from ipmc_model.persistence import load_model

    after = save_augmented(AugmentedModel(load_model(plain), [Effect(
        "creep", tau_s=20.0, gain_mm_per_v=-0.12)], 0.01), tmp_path / "model_after.json")
    aug = tmp_path / "aug.json"
    assert ipmc(["identify", *common, "--inverse", "--output-lags", "2", "--effects-from",
                 str(after), "--out", str(aug)]) == 0
    params = feedforward_server_params(str(aug))
    assert params == {"inverse_model_file": str(aug.resolve())}
    from ipmc_model.effects import AugmentedInverse
    from ipmc_model.nodes.model_server import load_model_set

    assert isinstance(load_model_set("", params["inverse_model_file"])[1], AugmentedInverse)
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
    lists by then; the plant also waits for the controller's stamped commands. In real time
    the reference's time 0 waits for the same listeners (model_server subscribes once its
    model has loaded), the plant does not wait."""
    specs = {s.name: s.params for s in graph_specs(
        rig_port=None, lockstep=True, model=model, mode="hybrid", reference="sine",
        plant_effects=[], record=record)}
    assert specs["reference"]["min_subscribers"] == listeners
    assert specs["sim_plant"]["lockstep_min_subscribers"] == listeners
    assert specs["sim_plant"]["lockstep_min_command_publishers"] == 1
    if record:  # the recorder's start subscriptions wait for the outputs it records
        assert specs["recorder"]["await_publishers"] == ["/ipmc/command"] + (
            ["/ipmc/feedforward", "/ipmc/predicted", "/ipmc/residual"] if model else [])
        assert set(specs["recorder"]["await_publishers"]) <= set(specs["recorder"]["topics"])
    realtime = {s.name: s.params for s in graph_specs(
        rig_port=None, lockstep=False, model=model, mode="hybrid", reference="sine",
        plant_effects=[], record=record)}
    assert realtime["reference"]["min_subscribers"] == listeners
    assert "lockstep_min_command_publishers" not in realtime["sim_plant"]
    assert "await_publishers" not in realtime.get("recorder", {})
