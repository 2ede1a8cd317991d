"""The fast paths of core.projection.laser_order equal the numpy calls they replace, bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lego_loam_py.core.projection.laser_order import (
    _DEG_PER_RAD,
    MIN_STEP_DEG,
    _laser_starts,
    _median_is_not_negative,
    _mod,
    median,
)


def _bits(value) -> bytes:
    return np.asarray(value, dtype=np.float64).tobytes()


@pytest.mark.parametrize('period', [2.0 * math.pi, 360.0, 0.1])
def test_mod_equals_numpy_mod_on_and_beyond_its_fast_range(period):
    rng = np.random.default_rng(7)
    edges = np.array(
        [0.0, -0.0, period, -period, 2.0 * period, 3.0 * period, -1.5 * period, -1e-300, -5e-324, 5e-324, -1e-17]
        + [np.nextafter(period, 0.0), np.nextafter(period, 9e9), np.nextafter(-period, 0.0)]
        + [np.nextafter(-period, -9e9), np.nextafter(2.0 * period, 0.0)]
    )
    inside = edges[(edges >= -period) & (edges < 2.0 * period)]
    for trial in range(60):
        values = rng.uniform(-period, 2.0 * period, int(rng.integers(0, 3000)))
        if len(values):
            values[rng.integers(0, len(values), 10)] = rng.choice(inside, 10)
        if trial % 5 == 0:
            values = np.round(values, 1)  # exact multiples and ties
        assert _bits(_mod(values, period)) == _bits(np.mod(values, period))
        if len(values):  # with the bounds given, computed in place
            low, high = float(values.min()), float(values.max())
            assert _bits(_mod(values + 0.0, period, (low, high))) == _bits(np.mod(values, period))
    for edge in edges:  # alone, each also decides the range check
        assert _bits(_mod(np.array([edge, 1.0]), period)) == _bits(np.mod(np.array([edge, 1.0]), period))
    with np.errstate(invalid='ignore'):
        for odd in (np.nan, np.inf, -np.inf):
            assert _bits(_mod(np.array([1.0, odd]), period)) == _bits(np.mod(np.array([1.0, odd]), period))


def test_median_and_its_sign_equal_numpy_median():
    rng = np.random.default_rng(3)
    for trial in range(300):
        n = int(rng.integers(1, 20000))
        kind = trial % 6
        if kind == 0:
            values = rng.normal(0.0, 1.0, n)
        elif kind == 1:
            values = np.abs(rng.normal(0.002, 0.01, n))
        elif kind == 2:
            values = np.round(rng.normal(0.0, 1.0, n), 2)  # many ties
        elif kind == 3:
            values = np.sort(rng.normal(0.0, 1.0, n))  # a sorted array: the strided sample is one-sided
        elif kind == 4:
            values = rng.choice([-0.0, 0.0, 1.0, -1.0, 5e-324, -5e-324], n)  # zeros of both signs in the middle
        else:
            values = rng.standard_cauchy(n)
        if trial % 37 == 0:
            values[rng.integers(0, n)] = np.nan
        with np.errstate(invalid='ignore'):
            assert _bits(median(values)) == _bits(np.median(values))
            assert _median_is_not_negative(values) == (float(np.median(values)) >= 0.0)
    for pair in ([-1e-300, 1e-300], [-5e-324, 5e-324], [-5e-324, 0.0], [-5e-324, -0.0], [-2.0, 1.0], [-1.0, 2.0]):
        for values in (np.array(pair), np.array(pair * 3000)):  # the middle pair straddles zero
            assert _median_is_not_negative(values) == (float(np.median(values)) >= 0.0)
    assert _median_is_not_negative(np.array([np.nan, 1.0])) is False  # np.median's NaN is not >= 0
    assert _median_is_not_negative(np.array([-0.0])) is True


def test_degrees_by_the_constant_equal_numpy_degrees():
    rng = np.random.default_rng(5)
    values = np.concatenate([rng.uniform(0.0, 2.0 * math.pi, 10000), [0.0, -0.0, math.pi, 2.0 * math.pi, 5e-324]])
    assert (values * _DEG_PER_RAD).tobytes() == np.degrees(values).tobytes()


def _starts_with_hypot(x, y, z):
    """_laser_starts as first written: np.hypot's elevations throughout."""
    x, y, z = (np.asarray(c, dtype=np.float64) for c in (x, y, z))
    elevation = np.arctan2(z, np.hypot(x, y))
    head = max(1, len(x) // 20)
    top_first = float(np.median(elevation[:head])) > float(np.median(elevation[-head:]))
    rise, threshold = np.diff(elevation), math.radians(MIN_STEP_DEG)
    return top_first, np.flatnonzero(rise < -threshold if top_first else rise > threshold) + 1


def test_laser_starts_from_the_fast_range_equal_those_from_hypot():
    rng = np.random.default_rng(9)
    threshold = math.radians(MIN_STEP_DEG)
    for trial in range(40):
        n = 2000
        rho = rng.uniform(0.5, 80.0, n)
        elevation = np.repeat(np.linspace(-0.4, 0.1, 20), n // 20)[:: 1 if trial % 2 else -1]
        elevation += rng.normal(0.0, 0.0005, n)
        if trial % 4 == 0:  # steps at the threshold itself, to within float32 rounding
            elevation[1::2] = elevation[::2] + threshold * (1 if trial % 8 else -1)
            rho[1::2] = rho[::2]
        azimuth = rng.uniform(-math.pi, math.pi, n)
        x, y = (rho * np.cos(azimuth)).astype(np.float32), (rho * np.sin(azimuth)).astype(np.float32)
        z = (rho * np.tan(elevation)).astype(np.float32)
        if trial == 5:
            z[7] = np.nan
        x64, y64, z64 = (c.astype(np.float64) for c in (x, y, z))
        top_first, starts = _laser_starts(x64, y64, z64, True)
        expected_top_first, expected = _starts_with_hypot(x, y, z)
        assert top_first == expected_top_first and np.array_equal(starts, expected)
        assert _laser_starts(x64, y64, z64, False)[1].tolist() == expected.tolist()
