"""The closed-form affine least squares the ground fits use (core.geometry.affine_fit) against NumPy's lstsq."""

from __future__ import annotations

import numpy as np
import pytest

from lego_loam_py.core.geometry import affine_fit


def test_an_exact_plane_gives_its_coefficients():
    u = np.array([0.0, 1.0, 0.0, 2.0, 5.0])
    v = np.array([0.0, 0.0, 1.0, 3.0, -1.0])
    z = 0.5 * u - 2.0 * v + 3.0
    assert affine_fit(u, v, z) == pytest.approx((0.5, -2.0, 3.0), abs=1e-12)


def test_samples_far_from_the_origin_lose_no_precision():
    # Centring keeps the condition of the samples' spread: 10 km out, a 1 m patch still gives the plane exactly.
    rng = np.random.default_rng(3)
    u, v = 1e4 + rng.uniform(0.0, 1.0, 50), -1e4 + rng.uniform(0.0, 1.0, 50)
    z = 0.01 * u + 0.02 * v - 1.5
    c_u, c_v, c_0 = affine_fit(u, v, z)
    assert (c_u, c_v) == pytest.approx((0.01, 0.02), abs=1e-9)
    assert np.abs(c_u * u + c_v * v + c_0 - z).max() < 1e-9


def test_noisy_ground_gives_lstsqs_plane():
    rng = np.random.default_rng(7)
    for _ in range(200):
        n = int(rng.integers(3, 5000))
        u = rng.uniform(-40.0, 40.0, n) + rng.uniform(-50.0, 50.0)
        v = rng.uniform(-40.0, 40.0, n)
        z = 0.02 * u - 0.01 * v - 1.7 + rng.normal(0.0, 0.05, n)
        design = np.stack([u, v, np.ones(n)], axis=1)
        expected = np.linalg.lstsq(design, z, rcond=None)[0]
        got = np.array(affine_fit(u, v, z))
        # The fitted heights agree to far below a millimetre's billionth: a ground test at a tolerance of centimetres
        # decides the same for every point but those within that of the tolerance.
        assert np.abs(design @ got - design @ expected).max() < 1e-10


def test_collinear_samples_take_lstsqs_minimum_norm_answer():
    u = np.linspace(0.0, 10.0, 20)
    v = 2.0 * u  # no plane is determined: lstsq picks the smallest coefficients
    z = 3.0 * u + 1.0
    design = np.stack([u, v, np.ones(len(u))], axis=1)
    expected = np.linalg.lstsq(design, z, rcond=None)[0]
    assert affine_fit(u, v, z) == pytest.approx(tuple(expected), abs=1e-12)
