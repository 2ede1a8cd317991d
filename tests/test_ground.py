"""The fast paths of core.projection.ground equal the numpy calls they replace, bit for bit."""

from __future__ import annotations

import numpy as np

from lego_loam_py.core.params import Params
from lego_loam_py.core.projection.ground import GroundRemoval, float32_hypot


def test_hypotf_equals_numpy_hypot_on_float32():
    rng = np.random.default_rng(11)
    n = 200_000
    exponent = rng.integers(-150, 125, n)  # subnormal to overflowing squares
    with np.errstate(over='ignore'):  # (some become inf)
        x = (rng.uniform(-2.0, 2.0, n) * 2.0**exponent).astype(np.float32)
        y = (rng.uniform(-2.0, 2.0, n) * 2.0 ** (exponent + rng.integers(-30, 30, n))).astype(np.float32)
    edges = np.array([0.0, -0.0, 1e-45, -1e-45, 1.0, 3e38, -3e38, np.nan, np.inf, -np.inf], dtype=np.float32)
    ex, ey = (grid.ravel() for grid in np.meshgrid(edges, edges))
    x, y = np.concatenate([x, ex]), np.concatenate([y, ey])
    with np.errstate(all='ignore'):
        ours, numpy_s = float32_hypot(x, y), np.hypot(x, y)
    same = (ours.view(np.int32) == numpy_s.view(np.int32)) | (np.isnan(ours) & np.isnan(numpy_s))
    infinite_with_nan = (np.isinf(x) & np.isnan(y)) | (np.isnan(x) & np.isinf(y))
    assert same[~infinite_with_nan].all()
    assert np.isnan(ours[infinite_with_nan]).all()  # glibc's +inf: both compare false


def _original_write_order(full: np.ndarray, filled: np.ndarray, remover: GroundRemoval) -> np.ndarray:
    """The original's groundMat as its loop writes it, pair after pair (slope test from the class itself)."""
    n, h, g = remover.n_scan, remover.horizon_scan, remover.params.sensor.ground_scan_ind
    p, f = full.reshape(n, h, 4), filled.reshape(n, h)
    mat = np.zeros((n, h), dtype=np.int8)
    for j in range(h):
        for i in range(g):
            if not (f[i, j] and f[i + 1, j]):
                mat[i, j] = -1
                continue
            dx, dy, dz = p[i + 1, j, :3] - p[i, j, :3]
            angle = np.arctan2(np.float64(dz), np.float64(np.sqrt(dx * dx + dy * dy)))
            if remover._slope_band(np.array([angle], dtype=np.float32))[0] == 1:
                mat[i, j] = mat[i + 1, j] = 1
    return (mat == 1).reshape(-1)


def test_pair_test_keeps_the_original_write_order():
    """Empty pixels, steep and flat pairs in every combination down the ground rows of each column."""
    params = Params().replace(image_projection__ground_rule='original', sensor__horizon_scan=360)
    remover = GroundRemoval(params)
    n, h = remover.n_scan, remover.horizon_scan
    rng = np.random.default_rng(2)
    for _ in range(5):
        full = np.full((n * h, 4), np.nan, dtype=np.float32)
        full[:, 0] = rng.uniform(5.0, 6.0, n * h)
        full[:, 1] = 0.0
        full[:, 2] = rng.choice([-1.5, -1.45, 0.5], n * h)  # flat or steep steps between rows
        filled = rng.random(n * h) < 0.8
        full[~filled] = np.nan
        expected = _original_write_order(full, filled, remover)
        assert np.array_equal(remover.ground(full, filled), expected)
        assert expected.any() and not expected.all()
