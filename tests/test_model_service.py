"""model_server's rules without DDS: ipmc_model.model_service driven message by message.

The reference queue (overload: the newest answered, late and lost references counted), the
feedforward (limit, history, restarts), the pairing of predictions and measurements by stamp,
and the /diagnostics statuses that report them.
"""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import random_sine
from ipmc_model.model_service import (
    OK,
    WARN,
    ModelService,
    Reference,
    ReferenceQueue,
    build_monitor,
    feedforward_status,
    load_served_models,
    model_status,
)

MS = 1_000_000
MONITOR = dict(monitor_residual="free_run", monitor_test="auto", monitor_window=0,
               monitor_reference=1200, monitor_bias_factor=1.5, monitor_growth=0.0,
               monitor_lags=20, monitor_decimate=10, monitor_check_every=50,
               monitor_patience=3)


def test_importing_the_core_leaves_rclpy_out():
    code = ("import sys, ipmc_model.model_service; "
            "assert 'rclpy' not in sys.modules, 'rclpy imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """A forward and an inverse LSSVM-NARX fitted on 20 s of the plant (150 centres)."""
    from ipmc_model.lssvm import FixedSizeLSSVMRegressor
    from ipmc_model.narx import InverseNarxModel, NarxModel
    from ipmc_model.persistence import save_model

    _, u = random_sine(20.0, 100.0, amplitude=2.5, seed=1)
    run = IpmcPlant(seed=1).run(u)
    reg = FixedSizeLSSVMRegressor(C=100.0, sigma=3.0, n_prototypes=150, seed=0)
    d = tmp_path_factory.mktemp("service")
    forward = NarxModel(reg, lag_step=5).fit(run.u_v, run.y_mm)
    inverse = InverseNarxModel(reg, lag_step=5).fit(run.u_v, run.y_mm)
    return (forward, str(save_model(forward, d / "forward.json")),
            inverse, str(save_model(inverse, d / "inverse.json")), run)


def _service(models, **kwargs) -> ModelService:
    _, forward_file, _, inverse_file, _ = models
    service = ModelService(build_monitor(MONITOR), **kwargs)
    service.install(load_served_models(forward_file, inverse_file))
    return service


def _ref(k: int, y_mm: float = 1.0, received_ms: float | None = None) -> Reference:
    return Reference(k * 10 * MS, y_mm, int((k * 10 if received_ms is None else received_ms)
                                            * MS))


# -- the reference queue --------------------------------------------------------------------------
def test_queue_answers_every_reference_in_time_in_order():
    q = ReferenceQueue(max_delay_s=0.1)
    for k in range(5):
        q.offer(_ref(k), sequence=k + 1)
    due, late = q.take(now_ns=45 * MS)
    assert [r.stamp_ns for r in due] == [k * 10 * MS for k in range(5)] and late == []
    assert len(q) == 0 and q.stale == q.lost == 0


def test_queue_skips_late_references_but_always_answers_the_newest():
    q = ReferenceQueue(max_delay_s=0.1)
    for k in range(30):                       # received every 10 ms, taken at 300 ms
        q.offer(_ref(k), sequence=k + 1)
    due, late = q.take(now_ns=300 * MS)
    assert [r.stamp_ns // (10 * MS) for r in due] == list(range(20, 30))
    assert len(late) == 20 and q.stale == 20
    q.offer(_ref(30, received_ms=0.0))        # alone and late: still the newest, answered
    due, late = q.take(now_ns=10_000 * MS)
    assert len(due) == 1 and late == [] and q.stale == 20


def test_queue_with_no_delay_limit_answers_everything():
    q = ReferenceQueue(max_delay_s=0.0)
    for k in range(30):
        q.offer(_ref(k))
    due, late = q.take(now_ns=10_000 * MS)
    assert len(due) == 30 and late == [] and q.stale == 0


def test_queue_counts_references_lost_before_they_arrived():
    q = ReferenceQueue()
    for seq in (1, 2, 5, 6, 10):              # 3, 4, 7, 8, 9 never arrived
        q.offer(_ref(seq), sequence=seq)
    assert q.lost == 5
    q.offer(_ref(0), sequence=1)              # a new publisher starts again: no loss
    q.offer(_ref(1), sequence=2)
    assert q.lost == 5
    q.offer(_ref(2), sequence=9, one_publisher=False)   # two publishers: numbers interleave
    assert q.lost == 5


# -- the feedforward ------------------------------------------------------------------------------
def test_feedforward_is_the_inverse_stepper_limited_to_u_max(models):
    _, _, inverse, _, _ = models
    service = _service(models, u_max_v=0.25, history_voltage="clamped")
    expected = inverse.stepper()
    refs = [2.0 * math.sin(0.05 * k) - 1.0 for k in range(200)]
    for r in refs:
        ff = service.answer(r)
        u = expected.step(r)
        u_ff = min(0.25, max(-0.25, u))
        expected.record_applied(u_ff)
        assert ff.u_v == pytest.approx(u_ff, abs=1e-12) and ff.clamped == (u != u_ff)
    assert service.ff_count == 200 and 0 < service.ff_clamped < 200


def test_skipped_references_keep_the_stepper_on_its_time_base(models):
    """A skipped (late) reference enters the history with the last voltage held, and the next
    answer is that of a stepper that went through it: the feedforward does not slip a sample."""
    _, _, inverse, _, _ = models
    service = _service(models, history_voltage="clamped")
    y, u = [], []
    for k in range(50):
        y.append(math.sin(0.1 * k))
        u.append(service.answer(y[-1]).u_v)
    late = [_ref(50 + i, math.sin(0.1 * (50 + i))) for i in range(3)]
    service.skip(late)
    y += [r.y_mm for r in late]
    u += [u[-1]] * 3
    got = service.answer(math.sin(5.3)).u_v
    want = inverse.stepper(np.array(y), np.array(u)).step(math.sin(5.3))
    assert got == pytest.approx(max(-3.0, min(3.0, want)), abs=1e-9)


def test_invalid_references_are_counted_not_answered(models):
    service = _service(models)
    assert service.answer(math.nan) is None and service.ff_invalid == 1
    assert service.unanswered == 1


def test_diagnostics_report_every_unanswered_reference(models):
    service = _service(models)
    feedforward_status(service, now_s=0.0)
    q = service.queue
    for k in range(30):
        q.offer(_ref(k), sequence=k + 1 + (k >= 10) * 5)   # 5 lost on the way
    due, late = q.take(now_ns=400 * MS)                  # limit 0.2 s: 20 late
    service.skip(late)
    for ref in due:
        service.answer(ref.y_mm)
    status = feedforward_status(service, now_s=1.0)
    values = status.values
    assert status.level == WARN
    assert values["count"] == len(due) and values["skipped_late"] == len(late) == 20
    assert values["lost"] == 5 and values["skipped"] == 25
    assert "25 references unanswered" in status.message
    assert feedforward_status(service, now_s=2.0).level == OK   # none in the next period


# -- prediction, residual and reloads ------------------------------------------------------------
def test_predictions_pair_with_measurements_by_stamp_in_either_order(models):
    forward, _, _, _, run = models
    service = _service(models)
    stepper = forward.stepper()
    residuals = []
    for k in range(300):
        stamp = k * 10 * MS
        if k % 2:   # the measurement first, then the voltage
            assert service.measure(stamp, run.y_mm[k]) is None
            y_free, e = service.predict(stamp, run.u_v[k])
        else:
            y_free, e = service.predict(stamp, run.u_v[k])
            assert e is None
            e = service.measure(stamp, run.y_mm[k])
        assert y_free == pytest.approx(stepper.step(run.u_v[k]), abs=1e-12)
        assert e == pytest.approx(run.y_mm[k] - y_free, abs=1e-12)
        residuals.append(e)
    assert service.residual_count == 300 and service.pred_count == 300
    assert service.measure(10**12, 1.0) is None     # no partner: kept, not paired
    assert service.predict(0, math.nan) == (None, None)


def test_a_failed_reload_keeps_the_models_in_use(models, tmp_path):
    forward, forward_file, _, _, _ = models
    service = _service(models)
    ok, msg = service.reload()
    assert ok and "lssvm-narx" in msg
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    from dataclasses import replace
    service.models = replace(service.models, model_file=str(broken))
    ok, msg = service.reload()
    assert not ok and "broken.json" in msg
    status = model_status(service)
    assert status.level == WARN and "last reload failed" in status.message
    assert service.serves_prediction and service.serves_feedforward


def test_a_model_gone_stale_is_told_once_with_the_commands_that_find_what_changed(models):
    """The monitor's turn to stale is a note the node logs (and bringup's console shows)
    naming the diagnosis of the recorded run with the served model."""
    _, forward_file, _, _, _ = models
    service = _service(models)
    rng = np.random.default_rng(0)
    stale_at = None
    for k in range(40_000):
        stamp = k * 10 * MS
        y_free, _ = service.predict(stamp, 0.5 * math.sin(k / 50))
        drift_mm = 0.0 if k < 15_000 else 1e-5 * (k - 15_000)   # the rig starts to drift
        service.measure(stamp, y_free + rng.normal(0, 0.005) + drift_mm)
        if stale_at is None and any(kind == "stale" for kind, _ in service.notes):
            stale_at = k
    stale = [text for kind, text in service.notes if kind == "stale"]
    assert stale_at is not None and stale_at > 15_000, stale_at
    assert len(stale) == 1, stale   # told at the turn, not at every sample after it
    assert stale[0].startswith("model stale: ")
    assert f"ipmc diagnose --data BAG --model {forward_file}" in stale[0]
