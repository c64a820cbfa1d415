"""Every parameter of model_server, controller, reference, sim_plant and recorder refuses bad
values with a reason: at start-up (the node is not built; ``main`` prints one sentence and
exits 1) and at run time (``set_parameters`` answers unsuccessful with the reason).

The table covers each node's whole parameter table (a parameter added without a row fails
``test_the_table_covers_every_parameter``). Start-up cases build the node in this process with
parameter overrides; a few run the real executables to see the one sentence and the exit code.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")
from rclpy.parameter import Parameter  # noqa: E402

from ipmc_control.nodes import controller, reference  # noqa: E402
from ipmc_driver.node_runtime import ParameterError  # noqa: E402
from ipmc_driver.nodes import recorder, sim_plant  # noqa: E402
from ipmc_model.nodes import model_server  # noqa: E402

VENV_BIN = Path(sys.executable).parent
MODULES = {"model_server": (model_server, model_server.ModelServer),
           "controller": (controller, controller.Controller),
           "reference": (reference, reference.ReferenceNode),
           "sim_plant": (sim_plant, sim_plant.SimPlant),
           "recorder": (recorder, recorder.Recorder)}

# Values out of range, per parameter (a value of the wrong type is added for every one).
OUT_OF_RANGE = {
    "model_server": {
        "u_max_v": [0.0, 3.5, float("nan")], "history_voltage": ["measured"],
        "feedforward": ["both"], "reference_max_delay_s": [-0.1],
        "monitor_residual": ["two_step"], "monitor_test": ["t"], "monitor_window": [-1],
        "monitor_reference": [0], "monitor_bias_factor": [0.0], "monitor_growth": [0.5],
        "monitor_lags": [0], "monitor_decimate": [0], "monitor_check_every": [-5],
        "monitor_patience": [0], "diagnostics_period_s": [0.0]},
    "controller": {
        "rate_hz": [0.0, -100.0], "trigger": ["sample"], "mode": ["open"], "k": [-1.0],
        "ti_s": [0.0], "td_s": [-0.1], "n": [0.0], "tracking_time_constant": [-1.0],
        "u_clamp_max": [5.0, float("inf")], "u_clamp_min": [1.0, -4.0],
        "antiwindup_strategy": ["clamp"], "feedforward_timeout_s": [0.0],
        "measurement_timeout_s": [-1.0], "diagnostics_period_s": [0.0],
        "pair_wait_s": [0.0]},
    "reference": {
        "rate_hz": [0.0], "preview_s": [-0.01], "min_subscribers": [-1], "kind": ["square"],
        "value_mm": [float("nan")], "amplitude_mm": [float("inf")], "frequency_hz": [0.0],
        "offset_mm": [float("nan")], "phase_rad": [float("inf")], "band_hz": [[0.7, 0.1]],
        "range_mm": [[4.0, -9.0], [1.0]], "n_components": [0], "period_s": [0.0],
        "seed": [-1], "levels_mm": [[float("nan")]], "hold_s": [0.0]},
    "sim_plant": {
        "rate_hz": [0.0], "clock_mode": ["fast"], "lockstep_timeout_s": [0.0],
        "lockstep_min_subscribers": [-1], "lockstep_min_clock_subscribers": [-2],
        "lockstep_min_command_publishers": [-1], "effects": [["wobble"]], "seed": [-1],
        "diagnostics_period_s": [0.0]},
    "recorder": {
        "topics": [[""], ["ipmc/voltage"]], "storage": ["rosbag"], "split_s": [0.0],
        "flush_s": [-1.0]},
}
# Run-time only (the loader decides; a missing file at start-up is served as "no model").
RUN_TIME_ONLY = {"model_server": {"model_file": ["/nonexistent/model.json"],
                                  "inverse_model_file": ["/nonexistent/inverse.json"]},
                 "reference": {"path": ["/nonexistent/reference.csv"]}}


def _wrong_type(default):
    """A value of another type than ``default``'s: what a typo on the command line gives."""
    if isinstance(default, bool):
        return "yes"
    if isinstance(default, float):
        return 2   # an integer where a float is expected (-p k:=2)
    if isinstance(default, int):
        return 2.5
    if isinstance(default, str):
        return 5
    return 5       # a number where a list is expected


def _cases(when: str) -> list:
    cases = []
    for node_name, (module, _) in MODULES.items():
        for name, spec in module.PARAMETERS.items():
            values = [_wrong_type(spec.default), *OUT_OF_RANGE[node_name].get(name, [])]
            if when == "run":
                values += RUN_TIME_ONLY.get(node_name, {}).get(name, [])
            cases += [pytest.param(node_name, name, v, id=f"{node_name}-{name}-{v!r}")
                      for v in values]
    return cases


def _base(node_name: str, tmp_path) -> list:
    """Overrides every node needs here (a recorder writes its bag under tmp_path)."""
    return ([Parameter("output", value=str(tmp_path / "bag"))] if node_name == "recorder"
            else [])


def _build(node_name: str, context, overrides: list):
    return MODULES[node_name][1](context=context, parameter_overrides=overrides)


def test_the_table_covers_every_parameter():
    for node_name, (module, _) in MODULES.items():
        extra = set(OUT_OF_RANGE[node_name]) | set(RUN_TIME_ONLY.get(node_name, {}))
        assert extra <= set(module.PARAMETERS), (node_name, extra - set(module.PARAMETERS))


@pytest.mark.parametrize(("node_name", "name", "value"), _cases("start"))
def test_a_bad_value_at_start_up_is_refused_in_one_sentence(node_name, name, value,
                                                            rclpy_context, tmp_path):
    overrides = _base(node_name, tmp_path) + [Parameter(name, value=value)]
    with pytest.raises(ValueError) as refused:
        node = _build(node_name, rclpy_context, overrides)
        node.destroy_node()
    text = str(refused.value)
    assert isinstance(refused.value, ParameterError) or name in text, text
    assert name in text and "\n" not in text, text


@pytest.fixture(scope="module")
def running(rclpy_context, tmp_path_factory):
    """One node of each kind with its defaults, built once for the run-time cases."""
    tmp = tmp_path_factory.mktemp("nodes")
    nodes = {n: _build(n, rclpy_context, _base(n, tmp)) for n in MODULES}
    yield nodes
    for node in nodes.values():
        node.destroy_node()


@pytest.mark.parametrize(("node_name", "name", "value"), _cases("run"))
def test_a_bad_value_at_run_time_is_refused_with_a_reason(node_name, name, value, running):
    node = running[node_name]
    before = node.get_parameter(name).value
    (result,) = node.set_parameters([Parameter(name, value=value)])
    assert not result.successful, f"{name}:={value!r} accepted"
    # the reason names the parameter, or the file it could not load
    assert result.reason and (name in result.reason or str(value) in result.reason
                              or "read-only" in result.reason
                              or "Wrong parameter type" in result.reason), result.reason
    assert node.get_parameter(name).value == before


@pytest.mark.parametrize(("executable", "argument", "sentence"), [
    ("controller", "k:=2", "controller: error: parameter k must be a float (write 2.0, not 2), "
                           "got 2 (integer)"),
    ("sim_plant", "lockstep_timeout_s:=abc", "sim_plant: error: parameter lockstep_timeout_s "
                                             "must be a float, got abc (string)"),
    ("model_server", "u_max_v:=5.0", "model_server: error: parameter u_max_v must be in (0, "
                                     "3], got 5.0"),
    ("reference", "use_sim_time:=1", "reference: error: parameter use_sim_time must be true "
                                     "or false, got 1 (integer)"),
])
def test_the_executable_says_one_sentence_and_exits_1(executable, argument, sentence,
                                                      ros_env):
    run = subprocess.run([str(VENV_BIN / executable), "--ros-args", "-p", argument],
                         env=ros_env, capture_output=True, text=True, timeout=60)
    assert run.returncode == 1, run.stderr
    assert run.stderr.strip() == sentence
