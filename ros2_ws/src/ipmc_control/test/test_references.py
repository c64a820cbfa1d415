"""Tests of the reference generators (ipmc_control.references). Plain pytest."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_control.pid import ControlParameterError
from ipmc_control.references import (
    KINDS,
    ConstantReference,
    FileReference,
    RandomSineReference,
    SineReference,
    StepTrainReference,
    make_reference,
)


def test_constant_holds_value():
    ref = ConstantReference(4.0)
    assert ref(0.0) == 4.0 and ref(1e6) == 4.0
    assert_allclose(ref(np.arange(5.0)), np.full(5, 4.0))


def test_sine_defaults_are_the_papers_and_values_are_right():
    ref = SineReference()
    assert ref.amplitude_mm == 2.5
    assert_allclose(ref.frequency_hz, 1.0 / (2.0 * math.pi), rtol=1e-15)
    # 1/2pi Hz is 1 rad/s: the peak is at t = pi/2 s.
    assert_allclose(ref(math.pi / 2.0), 2.5, rtol=1e-12)
    shifted = SineReference(1.0, 2.0, offset_mm=-3.0, phase_rad=math.pi / 2.0)
    assert_allclose(shifted(np.array([0.0, 0.25])), [-2.0, -4.0], atol=1e-12)


@pytest.mark.parametrize("ref", [
    SineReference(), RandomSineReference(seed=3), StepTrainReference(), ConstantReference(1.0),
])
def test_scalar_and_array_evaluation_agree(ref):
    t = np.linspace(-1.0, 37.0, 301)
    assert_allclose([ref(float(x)) for x in t], ref(t), rtol=1e-12, atol=1e-12)
    assert isinstance(ref(1.5), float)


def test_sample_gives_uniform_grid():
    t, y = SineReference(1.0, 1.0).sample(2.0, 100.0)
    assert t.shape == y.shape == (200,)
    assert_allclose(np.diff(t), 0.01, rtol=1e-9)
    with pytest.raises(ControlParameterError, match="rate_hz must be > 0"):
        SineReference().sample(1.0, 0.0)


def test_random_sine_spans_the_papers_range_within_band():
    ref = RandomSineReference()
    assert ref.band_hz == (0.0, 0.7) and ref.range_mm == (-9.0, 4.0)
    t, y = ref.sample(ref.period_s, 100.0)
    assert y.min() >= -9.0 and y.max() <= 4.0
    assert y.min() < -8.95 and y.max() > 3.95  # uses the whole range
    assert np.all((ref.frequencies_hz_ > 0.0) & (ref.frequencies_hz_ <= 0.7))
    # Spectrum: essentially all the (non-DC) energy lies inside the band.
    spec = np.abs(np.fft.rfft(y - y.mean())) ** 2
    f = np.fft.rfftfreq(y.size, 0.01)
    assert spec[f > 0.7 + 1e-9].sum() < 1e-6 * spec.sum()


def test_random_sine_is_seeded():
    t = np.linspace(0.0, 50.0, 500)
    assert_allclose(RandomSineReference(seed=7)(t), RandomSineReference(seed=7)(t), rtol=0)
    assert not np.allclose(RandomSineReference(seed=7)(t), RandomSineReference(seed=8)(t))


def test_random_sine_repeats_every_period():
    ref = RandomSineReference(band_hz=(0.1, 0.5), range_mm=(-1.0, 1.0), period_s=20.0, seed=1)
    t = np.linspace(0.0, 20.0, 101)
    assert_allclose(ref(t), ref(t + 20.0), atol=1e-9)


def test_random_sine_rejects_bad_parameters():
    with pytest.raises(ControlParameterError, match="band_hz must satisfy"):
        RandomSineReference(band_hz=(0.7, 0.1))
    with pytest.raises(ControlParameterError, match="range_mm must satisfy"):
        RandomSineReference(range_mm=(4.0, -9.0))
    with pytest.raises(ControlParameterError, match="holds no multiple"):
        RandomSineReference(band_hz=(0.101, 0.102), period_s=10.0)
    with pytest.raises(ControlParameterError, match="n_components"):
        RandomSineReference(n_components=0)


def test_step_train_holds_levels_and_repeats_or_holds_last():
    t = np.array([-1.0, 0.0, 0.99, 1.0, 2.5, 3.0, 4.5])
    rep = StepTrainReference([1.0, 2.0, 3.0], hold_s=1.0)
    assert_allclose(rep(t), [1.0, 1.0, 1.0, 2.0, 3.0, 1.0, 2.0])
    hold = StepTrainReference([1.0, 2.0, 3.0], hold_s=1.0, repeat=False)
    assert_allclose(hold(t), [1.0, 1.0, 1.0, 2.0, 3.0, 3.0, 3.0])
    assert hold.duration_s == 3.0 and rep.duration_s is None
    with pytest.raises(ControlParameterError, match="hold_s must be > 0"):
        StepTrainReference([1.0], hold_s=0.0)
    with pytest.raises(ControlParameterError, match="levels_mm"):
        StepTrainReference([])


def test_file_reference_interpolates_t_y_and_t_u_y_files(tmp_path):
    ty = tmp_path / "ref.csv"
    ty.write_text("t,y\n0.0,0.0\n1.0,2.0\n2.0,-2.0\n")
    ref = FileReference(ty)
    assert_allclose(ref(np.array([-1.0, 0.5, 1.5, 5.0])), [0.0, 1.0, 0.0, -2.0])
    assert ref.duration_s == 2.0
    tuy = tmp_path / "record.csv"
    tuy.write_text("# a comment\nt,u,y\n0.0,0.1,1.0\n0.5,0.2,3.0\n")
    assert_allclose(FileReference(tuy)(0.25), 2.0)


def test_file_reference_repeat_wraps_with_one_sample_gap(tmp_path):
    path = tmp_path / "ref.csv"
    path.write_text("t_s,y_mm\n0,0\n1,1\n2,2\n")
    ref = FileReference(path, repeat=True)
    assert_allclose(ref(np.array([3.0, 4.0, 5.5])), [0.0, 1.0, 2.0])


@pytest.mark.parametrize(("text", "match"), [
    ("t,y\n0,0\n0,1\n", "increase strictly"),
    ("t,x\n0,0\n1,1\n", "no column y"),
    ("t,y\n0,0\n1,nan\n", "non-finite"),
    ("t,y\n0,0\n", "at least 2 samples"),
    ("t,y\n0,0\n1,abc\n", "bad row"),
])
def test_file_reference_refuses_bad_files(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ControlParameterError, match=match):
        FileReference(path)


def test_file_reference_missing_file_says_which(tmp_path):
    with pytest.raises(ControlParameterError, match="cannot read reference file"):
        FileReference(tmp_path / "nope.csv")


def test_make_reference_builds_each_kind(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("t,y\n0,1\n1,1\n")
    built = {
        "constant": make_reference("constant", value_mm=4.0),
        "sine": make_reference("sine", amplitude_mm=1.0, frequency_hz=0.5),
        "random": make_reference("random", seed=2),
        "steps": make_reference("steps", levels_mm=[0.0, 1.0], hold_s=2.0),
        "file": make_reference("file", path=path),
    }
    assert set(built) == set(KINDS)
    assert built["constant"](0.0) == 4.0
    with pytest.raises(ControlParameterError, match="kind must be one of"):
        make_reference("ramp")
    with pytest.raises(ControlParameterError, match="bad parameters for a sine"):
        make_reference("sine", amplitude=1.0)


@pytest.mark.parametrize("ref", [
    SineReference(1.5, 0.3, offset_mm=1.0, phase_rad=0.4), RandomSineReference(seed=3),
    RandomSineReference(band_hz=(0.0, 0.7), range_mm=(-4.0, 2.0), seed=0),
])
def test_rate_is_the_derivative(ref):
    t = np.linspace(0.0, 60.0, 6001)
    numeric = np.gradient(ref(t), t)
    inner = slice(1, -1)
    assert_allclose(ref.rate(t)[inner], numeric[inner], atol=2e-3 * np.ptp(numeric))
    assert isinstance(ref.rate(1.5), float)
    assert_allclose(ref.rate(1.5), ref.rate(np.array([1.5]))[0], rtol=1e-12)


def test_rate_of_flat_references_is_zero(tmp_path):
    t = np.linspace(-1.0, 30.0, 3101)  # across every step of the train
    assert np.all(StepTrainReference().rate(t) == 0.0)
    assert np.all(ConstantReference(2.0).rate(t) == 0.0)
    f = tmp_path / "ramp.csv"
    f.write_text("t,y\n0,0\n1,2\n2,2\n")
    ref = FileReference(f)
    assert_allclose(ref.rate(np.array([0.5, 1.5])), [2.0, 0.0], atol=1e-9)
