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
    _projection_kernels,
    median,
    rows_from_laser_order,
)

needs_kernels = pytest.mark.skipif(_projection_kernels is None, reason='the C extension is not built here')


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
        if _projection_kernels is not None:  # the steps taken in C: the same decisions, the same fallback
            in_c = _laser_starts(x64, y64, z64, True, _projection_kernels)
            assert in_c[0] == expected_top_first and np.array_equal(in_c[1], expected)
            assert np.array_equal(_laser_starts(x64, y64, z64, False, _projection_kernels)[1], expected)


@needs_kernels
def test_the_median_of_magnitudes_in_c_equals_numpys_or_leaves_it_to_numpy():
    rng = np.random.default_rng(11)
    for trial in range(400):
        n = int(rng.choice([1, 2, 3, 7, 4095, 4096, 4097, 9000, 50001]))
        kind = trial % 7
        if kind == 0:
            values = rng.normal(0.0, 1.0, n)
        elif kind == 1:
            values = np.round(rng.normal(0.0, 0.01, n), 3)  # many ties
        elif kind == 2:
            values = np.sort(rng.normal(0.0, 1.0, n))  # sorted: the strided sample is one-sided
        elif kind == 3:  # periodic with the sample's stride: the sample sees one value only
            values = np.tile(rng.normal(0.0, 1.0, 7), n // 7 + 1)[:n]
            values[:: max(1, n // 512)] = 0.5
        elif kind == 4:
            values = rng.choice([-0.0, 0.0, 1.0, -1.0, 5e-324, -5e-324], n)  # zeros in the middle
        elif kind == 5:
            values = np.concatenate([np.full(n // 2, 1e-3), rng.uniform(5.0, 6.0, n - n // 2)])  # a gap at the middle
        else:
            values = rng.standard_cauchy(n)
        if trial % 29 == 0:
            values[rng.integers(0, n)] = np.nan
        answer = _projection_kernels.abs_median(values)
        with np.errstate(invalid='ignore'):
            expected = np.median(np.abs(values))
        if answer is None:  # NaN, or a zero among the middle values (np.median chooses its sign)
            middle = np.sort(np.abs(values))[[(n - 1) // 2, n // 2]]
            assert np.isnan(expected) or not middle.all()
        else:
            assert _bits(answer) == _bits(expected)
    assert _projection_kernels.abs_median(np.zeros(0)) is None


@needs_kernels
@pytest.mark.parametrize('top_first', [True, False])
def test_rows_of_a_cloud_stored_laser_by_laser_are_the_same_in_c_and_in_numpy(top_first):
    rng = np.random.default_rng(13 + top_first)
    lasers, per_turn = 32, 1500
    elevation = np.repeat(np.linspace(0.05, -0.5, lasers)[:: 1 if top_first else -1], per_turn)
    azimuth = np.tile(np.linspace(0.3, 0.3 + 2.0 * math.pi, per_turn, endpoint=False), lasers)
    for trial in range(8):
        kept = rng.random(len(azimuth)) > 0.1  # (gaps where nothing returned)
        rho = rng.uniform(2.0, 60.0, kept.sum())
        x = (rho * np.cos(azimuth[kept] * (1 if trial % 2 else -1))).astype(np.float32)
        y = (rho * np.sin(azimuth[kept] * (1 if trial % 2 else -1))).astype(np.float32)
        z = (rho * np.tan(elevation[kept] + rng.normal(0.0, 2e-4, kept.sum()))).astype(np.float32)
        if trial == 3:
            z[100] = np.nan  # (every NaN path: NumPy's median, its remainder)
        if trial == 5:  # steps at the threshold itself
            z[1::2] = rho[1::2] * np.tan(np.arctan2(z[::2], rho[::2])[: len(z[1::2])] - math.radians(MIN_STEP_DEG))
        rows = rows_from_laser_order(x, y, z, 64)
        expected = rows_from_laser_order(x, y, z, 64, native=False)
        assert (rows is None and expected is None) or np.array_equal(rows, expected)
        if trial not in (3, 5):
            assert rows is not None and len(np.unique(rows)) == lasers
