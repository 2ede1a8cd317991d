"""imageProjection's C kernel (native/projection_kernels.c): the segments' connected components, by hand and
against SciPy's, which it replaces."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lego_loam_py.core.projection import segmentation
from lego_loam_py.core.projection.segmentation import run_components

needs_kernel = pytest.mark.skipif(segmentation._projection_kernels is None, reason='the C extension is not built here')


def _partition(component: np.ndarray) -> set[frozenset[int]]:
    """The sets of nodes sharing a component: what the labels depend on, whatever the numbering."""
    groups: dict[int, set[int]] = {}
    for node, label in enumerate(component.tolist()):
        groups.setdefault(label, set()).add(node)
    return {frozenset(group) for group in groups.values()}


@needs_kernel
def test_components_by_hand_are_numbered_by_their_lowest_node():
    # 7 nodes; edges 1-4, 4-6 and 2-5 (listed by their lower end); 0 and 3 alone.
    count, component = run_components(7, np.array([1, 2, 4]), np.array([4, 5, 6]))
    assert count == 4
    assert component.tolist() == [0, 1, 2, 3, 1, 2, 1]


@needs_kernel
def test_a_chain_linked_from_its_top_end_first_still_has_its_lowest_node_as_root():
    # Edges joined highest first: every union links two roots the other way round from the last one.
    lower = np.array([0, 1, 2, 3, 4])
    upper = np.array([5, 5, 4, 4, 5])
    count, component = run_components(6, lower, upper)
    assert count == 1 and component.tolist() == [0] * 6


@needs_kernel
def test_an_edge_beyond_the_nodes_is_refused():
    with pytest.raises(ValueError, match='outside'):
        run_components(3, np.array([0]), np.array([3]))


@needs_kernel
@settings(max_examples=200, deadline=None)
@given(
    st.integers(min_value=1, max_value=60).flatmap(
        lambda n: st.tuples(
            st.just(n), st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=3 * n)
        )
    )
)
def test_the_kernel_finds_scipys_components(graph):
    nodes, edges = graph
    edges = sorted(edges)  # (the segmentation's edges come by ascending lower end)
    lower = np.array([a for a, _ in edges], dtype=np.int64)
    upper = np.array([b for _, b in edges], dtype=np.int64)
    count, component = run_components(nodes, lower, upper)
    scipy_count, scipy_component = run_components(nodes, lower, upper, native=False)
    assert count == scipy_count
    assert _partition(component) == _partition(np.asarray(scipy_component))
    firsts = [int(np.flatnonzero(component == label)[0]) for label in range(count)]
    assert firsts == sorted(firsts)  # numbered in the order of their lowest nodes


@needs_kernel
def test_image_projection_runs_a_scan_without_importing_scipy():
    """With the kernel, imageProjection's node process never loads SciPy (0.1-0.2 s of CPU for csgraph)."""
    import subprocess
    import sys

    code = (
        'import sys\n'
        'import numpy as np\n'
        'from lego_loam_py.core.params import Params\n'
        'from lego_loam_py.core.projection.image_projection import ImageProjection\n'
        'from lego_loam_py.core.projection.range_image import ProjectionInput\n'
        'rng = np.random.default_rng(0)\n'
        'azimuth = rng.uniform(-np.pi, np.pi, 20000); elevation = np.radians(rng.uniform(-15, 15, 20000))\n'
        'r = rng.uniform(2, 30, 20000)\n'
        'xyz = np.stack([r * np.cos(elevation) * np.cos(azimuth), r * np.cos(elevation) * np.sin(azimuth),\n'
        '                r * np.sin(elevation)], axis=1).astype(np.float32)\n'
        'result = ImageProjection(Params()).process(ProjectionInput(xyz=xyz, ring=None))\n'
        'assert len(result.segmented_cloud) > 0\n'
        'print(sorted(m for m in sys.modules if m.split(".")[0] == "scipy"))\n'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == '[]', out.stdout + out.stderr


def _ground_scene(seed: int, columns: int):
    """A range image's lowest rows over rolling ground with raised objects, empty pixels and noise: the planes,
    row steps, filled mask and pair-test ground that GroundRemoval._refine_ground takes."""
    from lego_loam_py.core.params import Params

    rng = np.random.default_rng(seed)
    params = Params().replace(sensor__horizon_scan=columns, sensor__ang_res_x=360.0 / columns)
    top = params.sensor.ground_scan_ind + 2
    azimuth = np.linspace(-np.pi, np.pi, columns, endpoint=False)
    reach = np.linspace(3.0, 25.0, top)[:, None] * (1.0 + 0.05 * rng.random((top, columns)))
    x, y = reach * np.cos(azimuth), reach * np.sin(azimuth)
    z = -1.7 + 0.3 * np.sin(x / 7.0) + rng.normal(0.0, 0.03, (top, columns))
    raised = rng.random((top, columns)) < 0.1
    z = np.where(raised, z + rng.uniform(0.2, 1.5, (top, columns)), z)
    planes = tuple(a.astype(np.float32) for a in (x, y, z))
    steps = tuple(a[1:] - a[:-1] for a in planes)
    n = params.sensor.n_scan
    filled = np.zeros((n, columns), dtype=bool)
    filled[:top] = rng.random((top, columns)) > 0.1
    ground = np.zeros((n, columns), dtype=bool)
    ground[: top - 1] = filled[: top - 1] & (rng.random((top - 1, columns)) > 0.2)
    return params, planes, steps, filled, ground


@needs_kernel
@pytest.mark.parametrize('seed', range(6))
def test_the_vertical_pairs_in_c_are_numpys(seed):
    """Walls on the ground: pixels right above each other (a vertical pair) and near it, NaN steps."""
    from lego_loam_py.core.projection.ground import GroundRemoval

    params, (x, y, z), _, filled, ground = _ground_scene(seed, 1800)
    rng = np.random.default_rng(seed)
    wall = rng.random(x.shape) < 0.2  # this pixel's point goes on the one below it, higher (or nearly so)
    wall[0] = False
    below = np.roll(wall, -1, axis=0)
    lean = rng.choice([0.0, 1e-3, 0.03, 0.2], size=x.shape).astype(np.float32)
    x = np.where(wall, np.roll(x, 1, axis=0) * (1 + lean), x).astype(np.float32)
    y = np.where(wall, np.roll(y, 1, axis=0) * (1 + lean), y).astype(np.float32)
    z = np.where(wall, np.roll(z, 1, axis=0) + rng.uniform(0.0, 0.5, x.shape), z).astype(np.float32)
    x[rng.random(x.shape) < 0.01] = np.nan
    planes = (x, y, z)
    steps = tuple(a[1:] - a[:-1] for a in planes)
    removal = GroundRemoval(params)
    native = removal._refine_ground(planes, steps, filled, ground)
    numpy = removal._refine_ground(planes, steps, filled, ground, native=False)
    assert np.array_equal(native, numpy)
    assert np.count_nonzero(ground[: len(x)] & (wall | below) & ~native[: len(x)]) > 100  # (walls taken out)


@needs_kernel
def test_a_vertical_pair_by_hand_and_at_its_bounds():
    """Pairs of a pixel at 20 m and one above it: 1 m further out and 3 m higher is not vertical (the gap is
    exactly 0.05 x 20 m in float32); 0.9 m further and 3 m higher is; 0.9 m further and 1.6 m higher is not."""
    from lego_loam_py.core.params import Params
    from lego_loam_py.core.projection.ground import GroundRemoval

    params = Params().replace(sensor__horizon_scan=3, sensor__ang_res_x=120.0)
    removal = GroundRemoval(params)
    x = np.array([[20.0, 20.0, 20.0], [21.0, 20.9, 20.9]], dtype=np.float32)
    y = np.zeros_like(x)
    z = np.array([[-1.7, -1.7, -1.7], [1.3, 1.3, -0.1]], dtype=np.float32)
    planes = (x, y, z)
    steps = tuple(a[1:] - a[:-1] for a in planes)
    filled = np.zeros((params.sensor.n_scan, 3), dtype=bool)
    filled[:2] = True
    ground = filled.copy()
    for native in (True, False):
        kept = removal._refine_ground(planes, steps, filled, ground, native=native)
        assert kept[:2].tolist() == [[True, False, True], [True, False, True]]


@needs_kernel
@pytest.mark.parametrize('seed', range(20))
def test_the_ground_walk_in_c_keeps_what_numpys_keeps(seed):
    from lego_loam_py.core.projection.ground import GroundRemoval

    params, planes, steps, filled, ground = _ground_scene(seed, 360 if seed % 2 else 1800)
    removal = GroundRemoval(params)
    native = removal._refine_ground(planes, steps, filled, ground)
    numpy = removal._refine_ground(planes, steps, filled, ground, native=False)
    assert native.shape == numpy.shape and np.array_equal(native, numpy)
    assert 0 < np.count_nonzero(native) < np.count_nonzero(ground)  # (the walk kept some and dropped some)


@needs_kernel
def test_the_ground_walk_by_hand():
    """One column of three candidates, 1 m apart: the first, on the plane, seeds it; the second rises 0.5 m, within
    tan(20 deg) x 1 m + 0.15 m = 0.51 m of it (kept); the third rises 1 m over the second (dropped)."""
    x = np.array([[5.0], [6.0], [7.0]], np.float32)  # [m], rows bottom up
    y = np.zeros((3, 1), np.float32)
    z = np.array([[0.0], [0.5], [1.5]], np.float32)
    ground = np.ones((3, 1), dtype=bool)
    far = np.ones((3, 1), dtype=bool)
    on_plane = np.array([[True], [False], [False]])
    slope = float(np.tan(np.radians(20.0)))
    segmentation._projection_kernels.ground_walk(x, y, z, 3, 1, ground, far, on_plane, slope, 0.15)
    assert ground[:, 0].tolist() == [True, True, False]


@needs_kernel
@pytest.mark.parametrize('slope_deg', [20.0, 45.0, 0.0])
def test_the_ground_walk_decides_rises_at_the_threshold_as_hypot_does(slope_deg):
    """Second candidates set to rise within a few float32 steps of tan(slope) x hypot(dx, dy) + tolerance above a
    seeded first one: the kernel's shortcut for the horizontal gap leaves these to libm's hypot, so every column
    keeps or drops its second point as NumPy's float64 hypot decides."""
    rng = np.random.default_rng(int(slope_deg))
    columns, tolerance = 4000, 0.15
    slope = float(np.tan(np.radians(slope_deg)))
    x0 = rng.uniform(-30.0, 30.0, columns).astype(np.float32)
    y0 = rng.uniform(-30.0, 30.0, columns).astype(np.float32)
    z0 = rng.uniform(-2.0, 0.0, columns).astype(np.float32)
    x1 = (x0 + rng.uniform(-2.0, 2.0, columns)).astype(np.float32)
    y1 = (y0 + rng.uniform(-2.0, 2.0, columns)).astype(np.float32)
    gap = np.hypot(x1.astype(np.float64) - x0, y1.astype(np.float64) - y0)
    rise = (gap * slope + tolerance).astype(np.float32)
    z1 = (z0 + rise).astype(np.float32)
    for _ in range(3):  # (a float32 step or two either way of the threshold, at random)
        z1 = np.where(rng.random(columns) < 0.5, np.nextafter(z1, np.float32(np.inf)), z1)
        z1 = np.where(rng.random(columns) < 0.5, np.nextafter(z1, np.float32(-np.inf)), z1)
    z1 = np.where(rng.random(columns) < 0.5, z0 - (z1 - z0), z1)  # (falls as well as rises)
    x, y, z = (np.stack([a, b]) for a, b in ((x0, x1), (y0, y1), (z0, z1)))
    ground = np.ones((2, columns), dtype=bool)
    on_plane = np.array([[True] * columns, [False] * columns])
    far = np.ones((2, columns), dtype=bool)
    segmentation._projection_kernels.ground_walk(x, y, z, 2, columns, ground, far, on_plane, slope, tolerance)
    dx, dy, dz = (b.astype(np.float64) - a for a, b in ((x0, x1), (y0, y1), (z0, z1)))
    expected = np.abs(dz) <= np.hypot(dx, dy) * slope + tolerance
    assert ground[0].all()
    assert np.array_equal(ground[1], expected)
    assert 0.2 < expected.mean() < 0.8  # (both sides of the threshold are tested)
