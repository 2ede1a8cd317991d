"""The closed-form affine least squares the ground fits use (core.geometry.affine_fit) against NumPy's lstsq, and
the plane fits through neighbourhoods in C (fit_planes_at, native/geometry_kernels.c) against their NumPy version."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lego_loam_py.core import geometry
from lego_loam_py.core.geometry import affine_fit, fit_planes, fit_planes_at


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


# ----------------------------------------------------------- plane fits in C (native/geometry_kernels.c)

needs_kernel = pytest.mark.skipif(geometry._geometry_kernels is None, reason='the C extension is not built here')


def _same_bits(a, b) -> bool:
    return all(
        x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x.view(np.uint8), y.view(np.uint8))
        for x, y in zip(map(np.asarray, a), map(np.asarray, b))
    )


@pytest.mark.parametrize('native', [True, False], ids=['c_kernel', 'numpy'])
def test_points_on_a_plane_give_its_normal_and_offset(native):
    """Five points of the plane z = 2 (x, y anywhere): normal (0, 0, ±1) with n · p + offset = 0, so offset = -2 n_z;
    a sixth point 0.3 m above it breaks a 0.2 m bound, and a neighbourhood of one point repeated is singular."""
    if native and geometry._geometry_kernels is None:
        pytest.skip('the C extension is not built here')
    points = np.array(
        [[0, 0, 2, 9], [1, 0, 2, 9], [0, 1, 2, 9], [3, 2, 2, 9], [-1, 4, 2, 9], [0.5, 0.5, 2.3, 9]], np.float32
    )
    index = np.array([[0, 1, 2, 3, 4], [0, 1, 2, 3, 5], [0, 0, 0, 0, 0]])
    rows, normal, offset = fit_planes_at(points, index, 0.2, native=native)
    assert rows.tolist() == [0]
    assert np.abs(normal[0]) == pytest.approx([0.0, 0.0, 1.0], abs=1e-12)
    assert offset[0] == pytest.approx(-2.0 * normal[0, 2], abs=1e-12)
    assert fit_planes_at(points, index, 0.5, native=native)[0].tolist() == [0, 1]


@needs_kernel
@settings(max_examples=200, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.integers(3, 8),
    st.sampled_from([0.02, 0.2, 1.0]),
    st.sampled_from([0.0, 0.2]),
    st.sampled_from([0.01, 0.3, 5.0]),
)
def test_the_kernel_equals_numpy_bit_for_bit(seed, k, max_residual, min_aspect, spread):
    """Flat, curved and scattered neighbourhoods 60 m from the origin, repeated and collinear points, a fourth
    column: the same rows, normals and offsets, bit for bit, as fit_planes on the float64 copy."""
    rng = np.random.default_rng(seed)
    n = 400
    points = rng.standard_normal((n, 4)) * spread + np.append(rng.uniform(-60, 60, 3), 0.0)
    flat = rng.random(n) < 0.6
    points[flat, 2] = points[flat, 0] * 0.2 - points[flat, 1] * 0.1 + rng.standard_normal(flat.sum()) * 0.02 * spread
    points[rng.random(n) < 0.05, 1] = points[0, 1]  # a few points on one line with the first
    points = points.astype(np.float32)
    index = rng.integers(0, n, (300, k))
    index[:10] = index[:10, :1]  # one point repeated: a singular system
    expected = fit_planes(points[index, :3].astype(np.float64), max_residual, min_aspect)
    assert _same_bits(fit_planes_at(points, index, max_residual, min_aspect), expected)


@needs_kernel
def test_a_distance_at_the_bound_is_decided_as_numpy_decides_it():
    """With the bound set to a neighbourhood's own largest distance from its plane (as NumPy computes it), that
    neighbourhood lies exactly on the bound: the kernel leaves it to NumPy's sum, which keeps it; a bound one ulp
    lower drops it in both."""
    rng = np.random.default_rng(11)
    points = (rng.standard_normal((50, 3)) * [3.0, 3.0, 0.05] + [20.0, -5.0, 1.0]).astype(np.float32)
    index = rng.integers(0, 50, (40, 5))
    neighbours = points[index].astype(np.float64)
    rows, normal, offset = fit_planes(neighbours, np.inf)
    distances = np.abs(np.einsum('mki,mi->mk', neighbours[rows], normal) + offset[:, None]).max(axis=1)
    for bound in (distances[7], np.nextafter(distances[7], 0.0)):
        assert _same_bits(fit_planes_at(points, index, bound), fit_planes(neighbours, bound))
    assert rows[7] in fit_planes_at(points, index, distances[7])[0]
    assert rows[7] not in fit_planes_at(points, index, np.nextafter(distances[7], 0.0))[0]


@needs_kernel
def test_an_index_out_of_range_is_an_error_not_a_read_beyond_the_points():
    points = np.zeros((4, 3), np.float32)
    with pytest.raises(IndexError):
        geometry._geometry_kernels.plane_fits(
            points,
            3,
            np.array([0, 1, 2, 3, 4], np.int64),
            5,
            0.2,
            np.empty(3),
            np.empty(1),
            np.empty(9),
            np.empty(1, np.uint8),
        )
