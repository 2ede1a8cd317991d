"""The fast paths of core.projection.ground equal the numpy calls they replace, bit for bit."""

from __future__ import annotations

import numpy as np

from lego_loam_py.core.projection.ground import _hypotf


def test_hypotf_equals_numpy_hypot_on_float32():
    rng = np.random.default_rng(11)
    n = 200_000
    exponent = rng.integers(-150, 125, n)  # subnormal to overflowing squares
    x = (rng.uniform(-2.0, 2.0, n) * 2.0**exponent).astype(np.float32)
    y = (rng.uniform(-2.0, 2.0, n) * 2.0 ** (exponent + rng.integers(-30, 30, n))).astype(np.float32)
    edges = np.array([0.0, -0.0, 1e-45, -1e-45, 1.0, 3e38, -3e38, np.nan, np.inf, -np.inf], dtype=np.float32)
    ex, ey = (grid.ravel() for grid in np.meshgrid(edges, edges))
    x, y = np.concatenate([x, ex]), np.concatenate([y, ey])
    with np.errstate(all='ignore'):
        ours, numpy_s = _hypotf(x, y), np.hypot(x, y)
    same = (ours.view(np.int32) == numpy_s.view(np.int32)) | (np.isnan(ours) & np.isnan(numpy_s))
    infinite_with_nan = (np.isinf(x) & np.isnan(y)) | (np.isnan(x) & np.isinf(y))
    assert same[~infinite_with_nan].all()
    assert np.isnan(ours[infinite_with_nan]).all()  # glibc's +inf: both compare false
