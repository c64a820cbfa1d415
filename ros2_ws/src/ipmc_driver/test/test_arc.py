"""Arc compensation (paper Eq. 1): values, validity range, inverse, flags."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_driver.arc import ArcGeometry, ArcRangeError


def test_defaults_match_paper():
    geo = ArcGeometry()
    assert geo.l1_mm == 27.0
    assert geo.half_span_mm == pytest.approx(math.sqrt(27.0**2 - geo.l2_mm**2), rel=1e-12)


def test_compensate_matches_eq1_by_hand():
    geo = ArcGeometry(l1_mm=27.0, l2_mm=20.0, d_mm=150.0)
    x = 147.0
    expected = 27.0 * math.sin(math.atan((150.0 - 147.0) / 20.0))
    assert geo.compensate(x) == pytest.approx(expected, rel=1e-12)
    assert geo.compensate_scalar(x) == pytest.approx(expected, rel=1e-12)
    assert geo.compensate(150.0) == 0.0
    assert geo.compensate(152.0) < 0.0  # reading further away: tip moved away from the sensor


def test_validity_range_lower_open_upper_closed():
    geo = ArcGeometry(l1_mm=27.0, l2_mm=20.0, d_mm=150.0)
    lo, hi = geo.reading_range_mm
    s = 27.0 * math.sin(math.acos(20.0 / 27.0))
    assert_allclose((lo, hi), (150.0 - s, 150.0 + s), rtol=0, atol=1e-12)
    assert not geo.in_range(lo)
    assert geo.in_range(hi)
    assert geo.in_range(np.nextafter(lo, np.inf))
    assert not geo.in_range(np.nextafter(hi, np.inf))


def test_out_of_range_readings_flagged_not_numbers():
    geo = ArcGeometry()
    lo, hi = geo.reading_range_mm
    x = np.array([lo - 1.0, lo, 150.0, hi, hi + 0.5, np.nan, np.inf])
    assert list(geo.in_range(x)) == [False, False, True, True, False, False, False]
    y = geo.compensate(x)
    assert np.isnan(y[[0, 1, 4, 5, 6]]).all()
    assert np.isfinite(y[[2, 3]]).all()
    with pytest.raises(ArcRangeError, match="outside the valid range"):
        geo.compensate_scalar(hi + 0.5)


def test_inverse_round_trip_inside_range():
    geo = ArcGeometry(l1_mm=27.0, l2_mm=18.0, d_mm=200.0)
    lo, hi = geo.displacement_range_mm
    y = np.linspace(lo * 0.999, hi * 0.999, 201)
    x = geo.reading(y)
    assert geo.in_range(x).all()
    assert_allclose(geo.compensate(x), y, rtol=0, atol=1e-9)


def test_reading_scalar_matches_vectorised_inverse():
    geo = ArcGeometry()
    for y in (-10.0, -0.5, 0.0, 0.01, 7.3):
        assert geo.reading_scalar(y) == pytest.approx(geo.reading(y), abs=1e-12)
    assert geo.reading_scalar(geo.half_span_mm) is None
    assert geo.reading_scalar(float("nan")) is None


def test_inverse_outside_range_is_nan():
    geo = ArcGeometry()
    _, hi = geo.displacement_range_mm
    assert math.isnan(geo.reading(hi + 0.1))
    assert math.isnan(geo.reading(30.0))


def test_small_angle_is_nearly_linear():
    # For small deflections y ~ (L1/L2) (d - x): the laser sees the tip scaled by L2/L1.
    geo = ArcGeometry(l1_mm=27.0, l2_mm=20.0, d_mm=150.0)
    assert geo.compensate(150.0 - 0.01) == pytest.approx(27.0 / 20.0 * 0.01, rel=1e-6)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(l2_mm=27.0), "l2_mm must be in"),
        (dict(l2_mm=0.0), "l2_mm must be in"),
        (dict(l1_mm=-1.0), "l1_mm must be > 0"),
        (dict(d_mm=float("nan")), "d_mm must be a finite number"),
    ],
)
def test_invalid_geometry_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ArcGeometry(**kwargs)
