"""The closed-form affine least squares the ground fits use (core.geometry.affine_fit) against NumPy's lstsq; the
plane and line fits through neighbourhoods in C (fit_planes_at, line_fits_at, native/geometry_kernels.c) against
their NumPy versions, and the grid search for neighbours (GridNeighbours) against cKDTree."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from lego_loam_py.core import geometry
from lego_loam_py.core.geometry import (
    GridNeighbours,
    affine_fit,
    fit_planes,
    fit_planes_at,
    line_fits_at,
    nearest_within,
    pairs_within,
    squared_lengths,
)


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_squared_lengths_are_numpys_row_sums_bit_for_bit(dtype):
    """Rows of every magnitude (the order of the additions shows in the last bits), signed zeros, inf and NaN, and
    the (n, 4) clouds with intensity the stages pass: the same values as NumPy's sum over each row."""
    rng = np.random.default_rng(7)
    points = rng.standard_normal((20_000, 4)) * rng.choice([1e-20, 1e-3, 1.0, 1e3, 1e15], (20_000, 4))
    points[:4, :3] = [[-0.0, 0.0, -0.0], [np.inf, 1.0, 2.0], [np.nan, 0.0, 0.0], [3.0, 4.0, 12.0]]
    points = points.astype(dtype)
    with np.errstate(over='ignore'):
        got, expected = squared_lengths(points), (points[:, :3].astype(np.float64) ** 2).sum(axis=1)
    assert got.dtype == np.float64 and np.array_equal(got, expected, equal_nan=True)
    assert got[3] == 169.0 and np.signbit(got[0]) == np.signbit(expected[0])
    assert squared_lengths(np.zeros((0, 3), dtype)).shape == (0,)


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


@pytest.mark.parametrize('native', [True, False], ids=['c_kernel', 'numpy'])
def test_points_along_a_line_give_its_direction_and_centroid(native):
    """Five points on the line through (10, -4, 1) along (1, 2, 2) / 3, two metres apart: a line, its centroid the
    middle point, its direction that of the line (either sign); a cross of five points 2 m apart along that line and
    across it spreads as much across as along (no line); one point repeated has no direction (no line)."""
    if native and geometry._geometry_kernels is None:
        pytest.skip('the C extension is not built here')
    along = np.array([1.0, 2.0, 2.0]) / 3.0
    line = np.array([10.0, -4.0, 1.0]) + np.outer([-4.0, -2.0, 0.0, 2.0, 4.0], along)
    across = np.array([2.0, -2.0, 1.0]) / 3.0  # (perpendicular to along)
    cross = line[2] + np.array([[0.0, 0.0], [2.0, 0.0], [-2.0, 0.0], [0.0, 2.0], [0.0, -2.0]]) @ [along, across]
    points = np.concatenate([line, cross, np.ones((5, 3))])
    points = np.concatenate([points, np.full((len(points), 1), 7.0)], axis=1).astype(np.float32)
    index = np.arange(15).reshape(3, 5)
    rows, centroid, direction = line_fits_at(points, index, 3.0, native=native)
    assert rows.tolist() == [0]
    assert centroid[0] == pytest.approx(points[2, :3], abs=1e-6)
    assert np.abs(direction[0] @ along) == pytest.approx(1.0, abs=1e-12)
    assert np.linalg.norm(direction[0]) == pytest.approx(1.0, abs=1e-12)


@needs_kernel
@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(2, 8), st.sampled_from([0.01, 0.3, 5.0]), st.sampled_from([1.0, 3.0]))
def test_the_line_kernel_equals_numpy(seed, k, spread, eigen_ratio):
    """Lines, planes and blobs 60 m from the origin, repeated points, a fourth column: the same neighbourhoods
    found to lie along a line, the centroids bit for bit, the directions LAPACK's to 1e-12 (either sign)."""
    rng = np.random.default_rng(seed)
    n = 400
    points = rng.standard_normal((n, 4)) * spread + np.append(rng.uniform(-60, 60, 3), 0.0)
    linear = rng.random(n) < 0.5
    points[linear, 1:3] = points[linear, :1] * [0.3, -0.2] + rng.standard_normal((linear.sum(), 2)) * 0.01 * spread
    points = points.astype(np.float32)
    index = rng.integers(0, n, (300, k))
    index[:10] = index[:10, :1]  # one point repeated: no spread at all
    index[10:150] = np.flatnonzero(linear)[rng.integers(0, linear.sum(), (140, k))]  # along a line
    rows, centroid, direction = line_fits_at(points, index, eigen_ratio)
    expected_rows, expected_centroid, expected_direction = line_fits_at(points, index, eigen_ratio, native=False)
    centred = points[index, :3].astype(np.float64)
    centred -= centred.mean(axis=1)[:, None]
    values = np.linalg.eigvalsh(np.einsum('mki,mkj->mij', centred, centred) / k)
    differing = np.setxor1d(rows, expected_rows)  # only where the ratio ties, to rounding
    assert (np.abs(values[differing, 2] - eigen_ratio * values[differing, 1]) <= 1e-9 * values[differing, 2]).all()
    _, mine, theirs = np.intersect1d(rows, expected_rows, return_indices=True)
    assert np.array_equal(centroid[mine], expected_centroid[theirs])
    cosines = np.abs(np.einsum('ij,ij->i', direction[mine], expected_direction[theirs]))
    assert (1.0 - cosines).max(initial=0.0) < 1e-12
    assert len(rows) > 0


@needs_kernel
def test_the_line_kernel_refuses_an_index_out_of_range():
    points = np.zeros((4, 3), np.float32)
    with pytest.raises(IndexError):
        line_fits_at(points, np.array([[0, 1, 4]]), 3.0)


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


# ---------------------------------------------------- the neighbour search on a grid (GridNeighbours)


def _scattered_cloud(rng, n: int, spread: float, reach: float, repeats: bool) -> np.ndarray:
    """(n, 4) float32 points spread normally by ``spread`` [m] about a centre within ``reach`` [m] of the origin; with
    ``repeats`` a quarter of them copies of others (points at exactly the same distance from any query)."""
    points = rng.standard_normal((n, 4)) * spread + np.append(rng.uniform(-reach, reach, 3), 0.0)
    if repeats:
        points[rng.integers(0, n, n // 4 + 1)] = points[rng.integers(0, n, n // 4 + 1)]
    return points.astype(np.float32)


def _kd_tree_answer(points, queries, k, max_sq_dist):
    from scipy.spatial import cKDTree

    return nearest_within(
        cKDTree(points[:, :3].astype(np.float64), balanced_tree=False), queries[:, :3], k, max_sq_dist
    )


def test_a_lattice_gives_the_neighbours_one_counts_by_hand():
    """Points every 0.5 m on a 5 x 5 x 1 lattice; a query 0.1 m above (1, 1, 0) has that point first, then its four
    neighbours 0.5 m away in the plane (equal distances: in the kd-tree's order); a query 3 m away has none within
    1 m; the fifth neighbour exactly 1 m away fails the gate, which is strict (d^2 < max)."""
    grid_xy = np.stack(np.meshgrid(np.arange(5) * 0.5, np.arange(5) * 0.5, indexing='ij'), -1).reshape(-1, 2)
    points = np.concatenate([grid_xy, np.zeros((25, 1)), np.ones((25, 1))], axis=1).astype(np.float32)
    queries = np.array([[1.0, 1.0, 0.1], [1.0, 1.0, 3.0], [0.0, 0.0, 0.0]], np.float32)
    neighbours = GridNeighbours(points, 1.0)
    used, index = neighbours.nearest_within(queries, 5, 1.0)
    assert used.tolist() == [0]
    assert index[0, 0] == 12 and sorted(index[0, 1:].tolist()) == [7, 11, 13, 17]
    # From the corner (0, 0): 0, then 0.5 m (two), 0.707 m, then 1 m (two): the fifth at exactly 1 m is not < 1.
    assert neighbours.nearest_within(queries[2:], 5, 1.0)[0].tolist() == []
    assert neighbours.nearest_within(queries[2:], 4, 1.0)[0].tolist() == [0]
    # The same without equal distances (which go to the kd-tree): four points nearer, the fifth exactly 1 m away.
    lone = np.array([[0.1, 0, 0], [0, 0.2, 0], [0, 0, 0.3], [-0.4, 0, 0], [1, 0, 0], [0, 1.5, 0]], np.float32)
    alone = GridNeighbours(lone, 1.0)
    assert alone.nearest_within(queries[2:], 5, 1.0)[0].tolist() == []
    assert alone.nearest_within(queries[2:], 4, 1.0)[1].tolist() == [[0, 1, 2, 3]]
    assert alone._tree is None
    for k in (4, 5):
        expected = _kd_tree_answer(points, queries, k, 1.0)
        got = neighbours.nearest_within(queries, k, 1.0)
        assert np.array_equal(got[0], expected[0]) and np.array_equal(got[1], expected[1])


@needs_kernel
@settings(max_examples=150, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.integers(1, 3000),
    st.sampled_from([0.3, 3.0, 30.0]),
    st.sampled_from([2, 5, 8]),
    st.sampled_from([1.0, 0.25, 4.0]),
    st.booleans(),
)
def test_the_grid_answers_as_the_kd_tree_bit_for_bit(seed, n, spread, k, max_sq_dist, duplicates):
    """Sparse and crowded maps far from the origin, with repeated points (equal distances, which the kd-tree's own
    order decides) or without: the same rows, the same neighbours in the same order."""
    assume(spread < 30.0 or max_sq_dist > 0.25)  # (otherwise mostly wider than MAX_CELLS: the kd-tree itself)
    rng = np.random.default_rng(seed)
    points = _scattered_cloud(rng, n, spread, 500.0, duplicates)
    queries = (points[rng.integers(0, n, 400), :3] + rng.standard_normal((400, 3)) * spread * 0.2).astype(np.float32)
    neighbours = GridNeighbours(points, max_sq_dist)  # (maps over MAX_CELLS cells wide: the kd-tree)
    used, index = neighbours.nearest_within(queries, k, max_sq_dist)
    expected_used, expected_index = _kd_tree_answer(points, queries, k, max_sq_dist)
    assert np.array_equal(used, expected_used) and np.array_equal(index, expected_index)


@needs_kernel
def test_equal_distances_are_left_to_the_kd_tree_and_everything_else_is_not():
    rng = np.random.default_rng(5)
    points = rng.uniform(-5, 5, (2000, 3)).astype(np.float32)
    queries = points[:50] + np.float32(0.01)
    neighbours = GridNeighbours(points, 1.0)
    neighbours.nearest_within(queries, 5, 1.0)
    assert neighbours._tree is None  # (no two candidates at the same distance: no kd-tree built)
    twice = np.concatenate([points, points[:50]])  # each of the first 50 points twice
    neighbours = GridNeighbours(twice, 1.0)
    used, index = neighbours.nearest_within(queries, 5, 1.0)
    assert neighbours._tree is not None
    expected = _kd_tree_answer(twice, queries, 5, 1.0)
    assert np.array_equal(used, expected[0]) and np.array_equal(index, expected[1])


@pytest.mark.parametrize('far', [np.nan, 1e9, np.inf], ids=['not_a_number', 'a_point_a_million_km_out', 'infinite'])
def test_points_the_grid_cannot_hold_are_searched_by_the_kd_tree(far):
    rng = np.random.default_rng(9)
    points = rng.uniform(-20, 20, (500, 4)).astype(np.float32)
    points[7, 0] = far
    queries = rng.uniform(-20, 20, (200, 3)).astype(np.float32)
    neighbours = GridNeighbours(points, 4.0)
    assert neighbours._grid is None
    if np.isfinite(far):
        used, index = neighbours.nearest_within(queries, 3, 4.0)
        expected = _kd_tree_answer(points, queries, 3, 4.0)
        assert np.array_equal(used, expected[0]) and np.array_equal(index, expected[1])


def _kd_tree_nearest(points, queries, max_sq_dist, **layout):
    from scipy.spatial import cKDTree

    distance, nearest = cKDTree(points[:, :3].astype(np.float64), **layout).query(queries.astype(np.float64), k=1)
    near = np.flatnonzero(distance.astype(np.float64) ** 2 < max_sq_dist)
    return near, nearest[near]


def test_the_nearest_point_is_found_beyond_the_first_cells_and_not_beyond_the_gate():
    """Cells of 1 m, a gate of 5 m: a point 3.5 m from the query is found after four shells of cells, although the
    query's own cell and its neighbours hold nothing; one 5 m away fails the gate (strictly below 25 m^2); a nearer
    point one cell over is taken before a farther one in the query's own cell."""
    points = np.array([[3.5, 0.0, 0.0], [30.0, 5.0, 0.0], [11.1, 0.0, 0.0], [12.05, 0.0, 0.0]], np.float32)
    queries = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [11.95, 0.0, 0.0]], np.float32)
    search = GridNeighbours(points, cell=1.0)
    near, index = search.nearest_one(queries, 25.0)
    assert near.tolist() == [0, 2] and index.tolist() == [0, 3]
    assert search._tree is None  # (all on the grid)


@needs_kernel
@settings(max_examples=150, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.integers(1, 3000),
    st.sampled_from([0.3, 3.0, 30.0]),
    st.sampled_from([0.5, 1.0, 2.0]),
    st.sampled_from([25.0, 1.0]),
    st.booleans(),
)
def test_the_nearest_point_on_the_grid_is_the_kd_trees_bit_for_bit(seed, n, spread, cell, max_sq_dist, duplicates):
    """Any cell size, sparse and crowded clouds, queries near and far, repeated points (equal distances: the kd-tree
    of the given layout decides, as featureAssociation's always did)."""
    rng = np.random.default_rng(seed)
    points = _scattered_cloud(rng, n, spread, 100.0, duplicates)
    queries = (points[rng.integers(0, n, 400), :3] + rng.standard_normal((400, 3)) * spread).astype(np.float32)
    layout = {'leafsize': 32, 'balanced_tree': False, 'compact_nodes': False}
    near, index = GridNeighbours(points, cell=cell, **layout).nearest_one(queries, max_sq_dist)
    expected_near, expected_index = _kd_tree_nearest(points, queries, max_sq_dist, **layout)
    assert np.array_equal(near, expected_near) and np.array_equal(index, expected_index)


# ------------------------------------------------------- pairs of 2D points within a radius (pairs_within)


def test_pairs_on_a_lattice_include_those_exactly_at_the_radius():
    """Points every 0.5 m on a line and one 0.3 m off it: within 0.5 m, each neighbour on the line (exactly 0.5 m:
    included, as cKDTree.query_pairs includes it) and the point off the line with the one beside it."""
    xy = np.array([[0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [0.5, 0.3]])
    first, second = pairs_within(xy, 0.5)
    assert sorted(zip(first.tolist(), second.tolist())) == [(0, 1), (1, 2), (1, 3)]
    assert first.dtype == second.dtype == np.int64


@settings(max_examples=150, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.integers(0, 2000),
    st.sampled_from([0.25, 0.7, 2.0]),
    st.sampled_from([0.05, 1.0, 5.0]),
    st.booleans(),
)
def test_the_pairs_are_the_kd_trees_set(seed, n, radius, spread, lattice):
    """Sparse and crowded points, on a lattice (distances exactly at the radius) or not: the same pairs as
    cKDTree.query_pairs, each once with i < j."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    xy = rng.uniform(-50, 50, (n, 2)) * spread
    if lattice:
        xy = np.round(xy * 4) / 4
    first, second = pairs_within(xy, radius)
    expected = cKDTree(xy).query_pairs(radius) if n else set()
    got = list(zip(first.tolist(), second.tolist()))
    assert len(got) == len(set(got)) and set(got) == expected and all(i < j for i, j in got)


def test_points_the_grid_cannot_hold_are_paired_by_the_kd_tree():
    xy = np.array([[0.0, 0.0], [0.3, 0.0], [1e18, 0.0], [1e18, 0.2]])
    first, second = pairs_within(xy, 0.5)
    assert sorted(zip(first.tolist(), second.tolist())) == [(0, 1), (2, 3)]
