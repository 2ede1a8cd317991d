"""Decisions on libm's atan2f without computing it equal those on the computed angle, also next to thresholds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lego_loam_py.core.params import Params
from lego_loam_py.core.parity import libm
from lego_loam_py.core.parity.atan2f_decisions import Atan2fSteps, atan2f_exceeds, first_float32_where
from lego_loam_py.core.parity.libm import atan2f
from lego_loam_py.core.projection.range_image import RangeImageProjection

F32 = np.float32


def points_near(angles: np.ndarray, rng: np.random.Generator, n: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """(y, x) float32 at random lengths: a third within a few ulp of the given angles, a third within 1e-5 rad,
    the rest anywhere on the circle."""
    third = n // 3
    centre = rng.choice(angles, size=n).astype(np.float64)
    offset = np.concatenate(
        [
            rng.integers(-8, 9, third) * np.abs(centre[:third]) * 2.0**-24,
            rng.uniform(-1e-5, 1e-5, third),
            np.zeros(n - 2 * third),
        ]
    )
    angle = centre + offset
    angle[2 * third :] = rng.uniform(-math.pi, math.pi, n - 2 * third)
    length = 10.0 ** rng.uniform(-2, 3, n)
    return (length * np.sin(angle)).astype(F32), (length * np.cos(angle)).astype(F32)


def test_comparisons_with_fixed_angles_equal_libm():
    rng = np.random.default_rng(1)
    theta = F32(60.0 / 180.0 * math.pi)
    y, x = points_near(np.array([theta]), rng)
    y = np.abs(y)  # the joins' case: y >= 0, angles in [0, pi]
    y[:50] = np.nan
    (ours,) = atan2f_exceeds(y, x, [theta], (0.0, math.pi))
    assert np.array_equal(ours, atan2f(y, x) > theta)
    band = [F32(-0.17453295), F32(0.17453294)]  # the ground's case: x >= 0, angles in [-pi/2, pi/2]
    y, x = points_near(np.array(band), rng)
    x = np.abs(x)
    x[:50] = np.nan
    angle = atan2f(y, x)
    ours = atan2f_exceeds(y, x, band, (-math.pi / 2, math.pi / 2))
    assert all(np.array_equal(o, angle > t) for o, t in zip(ours, band))
    # A threshold a half turn from the range's end: every element takes libm's angle, still right.
    (ours,) = atan2f_exceeds(y, x, [F32(3.0)], (-math.pi / 2, math.pi / 2))
    assert np.array_equal(ours, angle > F32(3.0))


def column_thresholds(projection: RangeImageProjection) -> tuple[np.ndarray, np.ndarray]:
    """(the float32 azimuths where the range-image columns begin, the columns of -pi and pi)."""
    column_of_angle = projection._column_of_azimuth  # the original's column (before wrapping) of atan2f(x, y)
    ends = column_of_angle(np.array([-math.pi, math.pi], dtype=F32))
    levels = np.arange(int(ends[0]) - 1, int(ends[1]) - 1, -1)
    return first_float32_where(lambda a: column_of_angle(a) <= levels, -math.pi, math.pi, len(levels)), ends


@pytest.mark.parametrize('preset', ['VLP-16', 'OS1-64'])
def test_azimuth_steps_equal_the_columns_of_libm_angles(preset):
    projection = RangeImageProjection(Params().replace(sensor__preset=preset))
    column_of_angle = projection._column_of_azimuth
    thresholds, ends = column_thresholds(projection)
    assert np.all(np.diff(thresholds) > 0) and len(thresholds) == projection.horizon_scan
    steps = Atan2fSteps(thresholds)
    rng = np.random.default_rng(2)
    x_coord, y_coord = points_near(thresholds, rng, 60000)
    # Azimuths quantised to 0.01 deg, as the velodyne driver sends them: many lie on a column boundary.
    quantised = np.radians(np.round(rng.uniform(0, 36000, 5000)) / 100.0)
    x_coord = np.concatenate([x_coord, (8.0 * np.sin(quantised)).astype(F32), np.zeros(3, F32)])
    y_coord = np.concatenate([y_coord, (8.0 * np.cos(quantised)).astype(F32), np.array([0, -1, 1], F32)])
    count, confirmed = steps.count(x_coord, y_coord)
    libm_column = column_of_angle(atan2f(x_coord, y_coord)).astype(np.int64)
    assert np.array_equal((int(ends[0]) - count)[confirmed], libm_column[confirmed])
    assert confirmed[40000:60000].mean() > 0.97  # (the angles anywhere: few need libm)
    assert np.array_equal(projection._columns(x_coord, y_coord), libm_column)
    native = steps.count(x_coord, y_coord)
    assert np.array_equal(native[0], steps.count(x_coord, y_coord, native=False)[0])


@pytest.mark.skipif(not hasattr(libm._libm_compat, 'atan2f_steps'), reason='the C extension is not built here')
def test_azimuth_steps_in_c_equal_numpys_passes_on_every_kind_of_coordinate():
    projection = RangeImageProjection(Params().replace(sensor__preset='HDL-64E'))
    steps = projection._azimuth_steps
    thresholds = column_thresholds(projection)[0]
    rng = np.random.default_rng(4)
    for trial in range(12):
        y, x = rng.normal(0.0, 20.0, (2, 30001)).astype(F32)  # (an odd length: a partial block at the end)
        y[rng.integers(0, len(y), 300)] = 0.0  # on the axes and at the origin
        x[rng.integers(0, len(x), 300)] = -0.0
        if trial % 3 == 0:  # overflowing cross products and lengths, NaN
            y[:40], x[40:80], y[80:90], x[90:95] = F32(3e38), F32(-3e38), np.nan, np.nan
        if trial % 4 == 1:  # within a few ulp of the column boundaries
            x, y = points_near(thresholds, rng, 30001)
        with np.errstate(over='ignore', invalid='ignore'):
            ours, expected = steps.count(y, x), steps.count(y, x, native=False)
        assert np.array_equal(ours[0], expected[0]) and np.array_equal(ours[1], expected[1])
        assert ours[0].dtype == np.int64 and ours[1].dtype == bool
    empty = steps.count(np.zeros(0, F32), np.zeros(0, F32))
    assert len(empty[0]) == 0 and len(empty[1]) == 0


def test_first_float32_where_finds_the_first_float_and_reports_none():
    limits = np.array([0.1, -2.5, 1e-30, 7.0], dtype=F32)
    found = first_float32_where(lambda v: v >= limits, -4.0, 4.0, 4)
    assert found[:3].tolist() == limits[:3].tolist() and found[3] == np.inf
    # Strictly greater: the float after the limit.
    found = first_float32_where(lambda v: v > limits[:3], -4.0, 4.0, 3)
    assert np.array_equal(found, np.nextafter(limits[:3], F32(np.inf)))
