"""Voxel-grid downsampling with PCL's VoxelGrid semantics, alone and per group (ring)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from lego_loam_py.core import voxel
from lego_loam_py.core.voxel import VoxelAccumulator, voxel_downsample, voxel_downsample_groups


def test_centroids_in_voxel_index_order():
    # Leaf 1 m, grid anchored at floor(min) = (0, 0, 0): voxel index x + 2 y (x fastest; 2 voxels along x).
    points = np.array(
        [
            [1.5, 0.5, 0.0, 10.0],  # voxel (1, 0) -> index 1
            [0.2, 0.2, 0.0, 1.0],  # voxel (0, 0) -> index 0
            [0.4, 0.6, 0.0, 3.0],  # voxel (0, 0)
            [0.5, 1.5, 0.0, 7.0],
        ],
        dtype=np.float32,
    )  # voxel (0, 1) -> index 2
    out, counts = voxel_downsample(points, 1.0, return_counts=True)
    assert np.allclose(out, [[0.3, 0.4, 0.0, 2.0], [1.5, 0.5, 0.0, 10.0], [0.5, 1.5, 0.0, 7.0]])
    assert counts.tolist() == [2, 1, 1]


def test_grid_is_anchored_at_the_bounding_box_and_ignores_non_finite_points():
    points = np.array([[-0.1, 0.0, 0.0], [0.1, 0.0, 0.0], [np.nan, 0.0, 0.0], [0.0, np.inf, 0.0]], np.float32)
    # Voxels of 1 m from floor(-0.1) = -1: the two points fall on either side of 0.
    assert len(voxel_downsample(points, 1.0)) == 2


def test_groups_are_filtered_on_their_own_grids():
    # The same two points in one group share a voxel; in two groups they stay apart, ordered by group.
    points = np.array([[0.1, 0.0, 0.0], [0.2, 0.0, 0.0]], np.float32)
    assert len(voxel_downsample_groups(points, np.array([0, 0]), 1.0)) == 1
    out = voxel_downsample_groups(points, np.array([5, 2]), 1.0)
    assert np.array_equal(out, points[::-1])


@settings(max_examples=200, deadline=None)
@given(
    arrays(
        np.float32,
        st.tuples(st.integers(1, 300), st.just(4)),
        elements=st.floats(-50, 50, width=32) | st.just(np.float32(np.nan)),
    ),
    st.integers(0, 2**31 - 1),
    st.sampled_from([0.05, 0.2, 0.4, 1.0]),
)
def test_grouped_filter_equals_one_filter_per_group(points, seed, leaf):
    groups = np.random.default_rng(seed).integers(0, 16, len(points))
    parts = [voxel_downsample(points[groups == g], leaf) for g in np.unique(groups)]
    expected = np.concatenate(parts)
    assert np.array_equal(voxel_downsample_groups(points, groups, leaf), expected, equal_nan=True)


def test_accumulator_sums_voxels_across_clouds_and_forgets_removed_ones():
    # Leaf 1 m. Cloud a: two points in voxel (0, 0, 0); cloud b: one in (0, 0, 0), one in (-1, 0, 0).
    a = np.array([[0.2, 0.2, 0.2, 1.0], [0.4, 0.4, 0.4, 3.0]], np.float32)
    b = np.array([[0.6, 0.6, 0.6, 5.0], [-0.5, 0.5, 0.5, 9.0]], np.float32)
    union = VoxelAccumulator(1.0)
    union.add('a', a)
    union.add('b', b)
    # PCL order: increasing x within a row, so (-1, 0, 0) comes first; (0, 0, 0) averages three points.
    assert np.allclose(union.centroids(), [[-0.5, 0.5, 0.5, 9.0], [0.4, 0.4, 0.4, 3.0]])
    union.remove('a')
    assert np.allclose(union.centroids(), [[-0.5, 0.5, 0.5, 9.0], [0.6, 0.6, 0.6, 5.0]])
    union.remove('b')
    assert len(union) == 0 and union.centroids().shape == (0, 4)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), leaf=st.sampled_from([0.2, 0.4, 1.0]))
def test_accumulator_equals_one_filter_of_the_union_through_adds_and_removes(seed, leaf):
    rng = np.random.default_rng(seed)
    clouds = {}
    union = VoxelAccumulator(leaf)
    for step in range(12):
        if clouds and rng.random() < 0.35:
            gone = rng.choice(sorted(clouds))
            del clouds[gone]
            union.remove(gone)
        else:
            size = int(rng.integers(0, 200))
            centre = rng.uniform(-60, 60, 3)
            cloud = np.concatenate([centre + rng.normal(0, 2.0, (size, 3)), rng.uniform(0, 100, (size, 1))], 1)
            clouds[step] = cloud.astype(np.float32)
            union.add(step, clouds[step])
        expected = (
            voxel_downsample(np.concatenate(list(clouds.values())).reshape(-1, 4), leaf)
            if clouds
            else np.zeros((0, 4), np.float32)
        )
        assert union.centroids().shape == expected.shape
        assert np.allclose(union.centroids(), expected, atol=1e-4)
    rebuilt = VoxelAccumulator(leaf)
    rebuilt.rebuild(clouds)
    assert np.allclose(rebuilt.centroids(), union.centroids(), atol=1e-5)


# ---------------------------------------------------------------- the C kernel (native/voxel_kernels.c)

needs_kernel = pytest.mark.skipif(voxel._voxel_kernels is None, reason='the C extension is not built here')


@pytest.mark.parametrize('native', [True, False], ids=['c_kernel', 'numpy'])
def test_a_voxels_sum_is_its_first_point_plus_the_sum_of_the_others(native):
    """np.add.reduceat's order, which the kernel keeps: 1 + (2^-24 + 2^-24) = 1 + 2^-23, where adding in turn
    would round 1 + 2^-24 back to 1 twice."""
    if native and voxel._voxel_kernels is None:
        pytest.skip('the C extension is not built here')
    tiny = np.float32(2.0**-24)
    points = np.array([[1.0, 0.0, 0.0], [tiny, 0.0, 0.0], [tiny, 0.0, 0.0]], np.float32)
    out, counts = voxel_downsample(points, 100.0, return_counts=True, native=native)
    assert counts.tolist() == [3]
    assert out[0, 0] == np.float32(np.float32(1.0 + 2.0**-23) / np.float32(3.0))
    assert np.float32(np.float32(1.0) + tiny) + tiny == np.float32(1.0)  # (in turn, it would be 1 / 3)


@needs_kernel
@settings(max_examples=300, deadline=None)
@given(
    st.integers(1, 400),
    st.integers(3, 6),
    st.integers(0, 2**31 - 1),
    st.sampled_from([0.05, 0.2, 0.4, 1.0, 50.0]),
    st.integers(1, 40),
)
def test_the_kernel_equals_numpy_bit_for_bit(n, columns, seed, leaf, groups_count):
    """Sparse and crowded voxels (up to hundreds of points: NumPy's pairwise sums), signed zeros, NaN in the
    other columns and points beyond the grid's range: the same bits, the same order, the same counts."""
    rng = np.random.default_rng(seed)
    points = (rng.standard_normal((n, columns)) * 10.0 ** rng.uniform(-1, 2, (n, 1))).astype(np.float32)
    points[rng.random(n) < 0.2, :3] = -0.0
    points[rng.random(n) < 0.05, 3:] = np.nan
    points[rng.random(n) < 0.05, 0] = np.inf
    groups = rng.integers(0, groups_count, n)
    for a, b in (
        (voxel_downsample_groups(points, groups, leaf), voxel_downsample_groups(points, groups, leaf, native=False)),
        (voxel_downsample(points, leaf), voxel_downsample(points, leaf, native=False)),
    ):
        assert a.shape == b.shape and a.dtype == b.dtype == np.float32
        assert np.array_equal(a.view(np.uint32), b.view(np.uint32))
    _, counts = voxel_downsample(points, leaf, return_counts=True)
    _, numpy_counts = voxel_downsample(points, leaf, return_counts=True, native=False)
    assert np.array_equal(counts, numpy_counts)


@needs_kernel
@pytest.mark.parametrize('seed', range(3))
def test_the_kernel_equals_numpy_on_groups_of_thousands(seed):
    """Groups of thousands of points (the kernel sorts those by radix, short ones otherwise) over grids of a few
    cells to some 10^12, with voxels of one point and of hundreds: the same bits, order and counts as NumPy's."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(200, 5000, 6)
    parts = [(rng.standard_normal((size, 4)) * 10.0 ** rng.uniform(-1, 3)).astype(np.float32) for size in sizes]
    points, groups = np.concatenate(parts), np.repeat(np.arange(len(parts)), sizes)
    for leaf in (0.01, 0.2, 5.0):
        a = voxel_downsample_groups(points, groups, leaf)
        b = voxel_downsample_groups(points, groups, leaf, native=False)
        assert a.shape == b.shape and np.array_equal(a.view(np.uint32), b.view(np.uint32)), leaf
        (c, counts), (d, numpy_counts) = (voxel_downsample(points, leaf, return_counts=True, native=n) for n in (1, 0))
        assert np.array_equal(c.view(np.uint32), d.view(np.uint32)) and np.array_equal(counts, numpy_counts)
        assert 1 < len(a) < len(points) or leaf == 0.01


@needs_kernel
def test_a_grid_too_large_for_the_kernels_sort_keys_is_filtered_by_numpy():
    """Points 400 km apart on a 1 cm grid: some 10^19 cells, beyond the kernel's 63-bit keys. The kernel declines
    (returns -1) and the NumPy code filters them, the same as asking for it (its own order: its voxel index
    overflows int64 there too)."""
    points = np.array([[-2e5, -2e5, -50.0, 1.0], [2e5, 2e5, 50.0, 2.0], [2e5, 2e5, 50.0, 4.0]], np.float32)
    out, counts = np.empty_like(points), np.empty(3, dtype=np.int64)
    inverse = float(np.float32(1.0) / np.float32(0.01))
    assert voxel._voxel_kernels.voxel_groups(points, 4, np.zeros(1, dtype=np.int64), inverse, out, counts) == -1
    a, a_counts = voxel_downsample(points, 0.01, return_counts=True)
    b, b_counts = voxel_downsample(points, 0.01, return_counts=True, native=False)
    assert np.array_equal(a, b) and np.array_equal(a_counts, b_counts) and sorted(a_counts.tolist()) == [1, 2]


@needs_kernel
@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.05, 0.2, 1.0]), st.integers(1, 6))
def test_the_kernel_equals_numpy_on_rings_that_pass_a_voxel_twice(seed, leaf, rings):
    """Points along paths, as a ring's are: runs of neighbours in one voxel, and paths that come back to voxels they
    left (a ring closing, a wall seen twice), so that one voxel's points come from several runs: the same bits,
    order and counts as NumPy's."""
    rng = np.random.default_rng(seed)
    parts = []
    for ring in range(rings):
        steps = rng.normal(scale=leaf / 4, size=(int(rng.integers(1, 300)), 3))
        path = np.cumsum(steps, axis=0)
        back = path[:: -int(rng.integers(1, 4))] + rng.normal(scale=leaf / 20, size=(1, 3))  # the way back
        # ... ending where the path began, so that a voxel is shared however short the path came out.
        xyz = np.concatenate((path, back, path[:1]))
        part = np.empty((len(xyz), 4), np.float32)
        part[:, :3] = xyz
        part[:, 3] = ring + rng.random(len(xyz))
        parts.append(part)
    points = np.concatenate(parts)
    groups = np.repeat(np.arange(rings), [len(part) for part in parts])
    a = voxel_downsample_groups(points, groups, leaf)
    b = voxel_downsample_groups(points, groups, leaf, native=False)
    assert a.shape == b.shape and np.array_equal(a.view(np.uint32), b.view(np.uint32))
    assert len(a) < len(points)  # (voxels shared: the case this test is about)
