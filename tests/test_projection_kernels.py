"""imageProjection's C kernels (native/projection_kernels.c) against their NumPy versions: the segmentation's
breadth-first search, the ground's vertical pairs and walk."""

import math

import numpy as np
import pytest

from lego_loam_py.core.params import Params
from lego_loam_py.core.projection import segmentation
from lego_loam_py.core.projection.segmentation import Segmentation, run_components

needs_kernel = pytest.mark.skipif(segmentation._projection_kernels is None, reason='the C extension is not built here')


def test_run_components_by_hand():
    # 7 nodes; edges 1-4, 4-6 and 2-5 (listed by their lower end); 0 and 3 alone.
    count, component = run_components(7, np.array([1, 2, 4]), np.array([4, 5, 6]))
    groups = {frozenset(np.flatnonzero(component == label).tolist()) for label in range(count)}
    assert groups == {frozenset({0}), frozenset({1, 4, 6}), frozenset({2, 5}), frozenset({3})}


def _scene(rng: np.random.Generator, rows: int, columns: int):
    """(ranges (rows * columns,) float32 with FLT_MAX where empty, filled, ground) of blocky surfaces at random
    depths with slopes, noise, holes, a few NaN ranges and ground in the lowest rows."""
    blocks = rng.uniform(2.0, 60.0, size=(rows // 2 + 1, columns // 5 + 1))
    image = np.kron(blocks, np.ones((2, 5)))[:rows, :columns]
    image *= 1.0 + rng.normal(0.0, rng.choice([0.0, 0.0005, 0.003]), size=image.shape)
    image += np.linspace(0.0, rng.uniform(0.0, 8.0), columns)[None, :]
    filled = rng.random(image.shape) > rng.uniform(0.0, 0.4)
    ground = np.zeros(image.shape, dtype=bool)
    ground[: rng.integers(0, rows // 2)] = rng.random((1, columns)) < 0.7
    ranges = np.where(filled, image, np.finfo(np.float32).max).astype(np.float32)
    ranges[rng.random(image.shape) < 0.002] = np.nan
    return ranges.reshape(-1), filled.reshape(-1), (ground & filled).reshape(-1)


@needs_kernel
@pytest.mark.parametrize(
    'preset, theta_deg',
    [('VLP-16', 60.0), ('HDL-64E', 60.0), ('VLP-32C', 60.0), ('OS1-128', 45.0), ('VLP-16', 0.02), ('OS1-32', 10.0)],
)
def test_the_breadth_first_segmentation_in_c_labels_as_numpy_does(preset, theta_deg):
    """Presets with even rows and with beam tables (an angle per pair of rows), theta such that the cross products
    decide, and one (0.02 deg) so near the end of beta's range that every pair takes libm's angle."""
    params = Params().replace(sensor__preset=preset, image_projection__segment_theta=math.radians(theta_deg))
    s = params.sensor
    columns = int(np.random.default_rng(0).choice([90, s.horizon_scan]))
    params = params.replace(sensor__horizon_scan=columns, sensor__ang_res_x=360.0 / columns)
    labeller = Segmentation(params)
    assert (len(labeller._directions) == 0) == (theta_deg < 0.1)
    kinds = set()
    for seed in range(4):
        ranges, filled, ground = _scene(np.random.default_rng(seed), s.n_scan, columns)
        ours = labeller.labels(ranges, filled, ground)
        expected = labeller.labels(ranges, filled, ground, native=False)
        assert ours.dtype == expected.dtype and np.array_equal(ours, expected)
        kinds |= {'segment' if 0 < label < segmentation.OUTLIER_LABEL else label for label in np.unique(ours).tolist()}
    assert kinds == {'segment', segmentation.OUTLIER_LABEL, segmentation.NO_LABEL}


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
