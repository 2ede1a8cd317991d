"""The 2D occupancy grid (core/mapping/occupancy_grid.py, occupancy_ground.py, occupancy_files.py): hand-checkable
synthetic keyframes (a wall at a known place, the free cells before it, the unknown ones behind it, a redraw that
moves it, the sync that adds or redraws), the ground model's cases, nav2 map_server files and the message fields,
its parameters, the saved files of a mapping run, and a short simulated recording against the simulator's scene.
Float tolerances: cell centres are compared with np.allclose (1e-8 relative + 1e-5 m) against values exact to the
0.1 m lattice; heights of the ground model to 0.05 m."""

from __future__ import annotations

import math
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

import lego_loam_py.core.mapping.occupancy_grid as grid_module
import lego_loam_py.core.mapping.occupancy_ground as occupancy_ground
from lego_loam_py.core.frames import lidar_to_camera
from lego_loam_py.core.mapping import (
    FREE,
    FREE_THRESH,
    OCCUPIED,
    OCCUPIED_THRESH,
    UNKNOWN,
    Keyframe,
    OccupancyFilesError,
    OccupancyGrid,
    TernaryGrid,
    classify_keyframe,
    message_fields,
    read_occupancy_files,
    saved_occupancy_grid,
    write_occupancy_files,
)
from lego_loam_py.core.params import OccupancyGridParams, ParameterError, Params

REPO = Path(__file__).resolve().parents[1]
HEIGHT = 1.8  # the synthetic sensor above its flat ground [m]
WALL_X = 10.05  # the wall's face, in the middle of a 0.1 m cell [m, lidar x = map x]
WALL_HALF = 5.0  # it spans y in -5..5 m (points at the 0.1 m cells' centres), 3 m tall


def ground_rings(height: float = HEIGHT, slope: float = 0.0) -> np.ndarray:
    """(n, 3) lidar-frame points where a VLP-16's downward beams meet the ground ``z = -height + slope x``, every
    0.5 deg of azimuth, out to 40 m."""
    azimuth = np.radians(np.arange(0.0, 360.0, 0.5))
    out = []
    for elevation in np.radians(np.arange(-15.0, 0.0, 2.0)):
        direction = np.stack([np.cos(azimuth), np.sin(azimuth), np.full_like(azimuth, math.tan(elevation))], 1)
        # range along the horizontal: -height + slope r cos(a) = r tan(e)
        r = height / (slope * np.cos(azimuth) - math.tan(elevation))
        keep = (r > 0) & (r < 40.0)
        out.append(direction[keep] * r[keep, None])
    return np.concatenate(out)


def wall_scene() -> np.ndarray:
    """Flat ground with a 3 m wall across the x axis at WALL_X (its shadow removed from the ground)."""
    ground = ground_rings()
    shadow = (ground[:, 0] > WALL_X) & (np.abs(ground[:, 1]) * WALL_X / ground[:, 0] <= WALL_HALF)
    y, z = np.meshgrid(np.arange(-WALL_HALF + 0.05, WALL_HALF, 0.1), np.arange(-HEIGHT, 3.0 - HEIGHT, 0.1))
    wall = np.column_stack([np.full(y.size, WALL_X), y.ravel(), z.ravel()])
    return np.concatenate([ground[~shadow], wall])


def keyframe(index: int, lidar_points: np.ndarray, pose6=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)) -> Keyframe:
    """A keyframe whose clouds (camera axes, as mapOptimization keeps them) hold ``lidar_points``."""
    cloud = np.zeros((len(lidar_points), 4), np.float32)
    cloud[:, :3] = lidar_to_camera(lidar_points)
    empty = np.zeros((0, 4), np.float32)
    return Keyframe(index, 1_000_000_000 * (index + 1), np.array(pose6, float), empty, cloud, empty)


def cell(grid: TernaryGrid, x: float, y: float) -> int:
    """The value of the cell holding map point (x, y) (unknown outside the grid)."""
    col = int(math.floor((x - grid.origin[0]) / grid.resolution))
    row = int(math.floor((y - grid.origin[1]) / grid.resolution))
    inside = 0 <= row < grid.height and 0 <= col < grid.width
    return int(grid.cells[row, col]) if inside else UNKNOWN  # (the grid is cut to the cells ever seen)


def occupied_xy(grid: TernaryGrid) -> np.ndarray:
    return grid.cell_centres(OCCUPIED)


@pytest.fixture(scope='module')
def two_views():
    """Two keyframes at the sensor's place (a cell is free after two misses, occupied after one hit)."""
    points = wall_scene()
    return [keyframe(0, points), keyframe(1, points)]


# ------------------------------------------------------------------------------------------- the rendering


def test_the_wall_is_occupied_at_its_cells_free_before_it_unknown_behind(two_views):
    grid = OccupancyGrid(OccupancyGridParams(resolution=0.1))
    for kf in two_views:
        grid.add_keyframe(kf)
    ternary = grid.ternary()
    occupied = occupied_xy(ternary)
    # Every occupied cell is the wall's column x in [10.0, 10.1), and the wall is there all along its length.
    assert len(occupied) > 0
    assert np.allclose(occupied[:, 0], 10.05), np.unique(occupied[:, 0])
    assert np.abs(occupied[:, 1]).max() < WALL_HALF
    assert all(cell(ternary, WALL_X, y) == OCCUPIED for y in np.arange(-4.95, 5.0, 0.1))
    # Between the sensor and the wall: free (to 0.4 m, the obstacle margin, before it); behind it: unknown.
    assert all(cell(ternary, x, y) == FREE for x in np.arange(0.5, 9.5, 0.5) for y in (-2.0, 0.0, 3.0))
    assert all(cell(ternary, x, y) == UNKNOWN for x in np.arange(10.5, 19.0, 0.5) for y in (-2.0, 0.0, 3.0))
    # Sideways, where the ground was seen: free to 1 - 0.3 / 1.8 of the farthest ring within 30 m (21.7 m).
    assert cell(ternary, 0.0, 15.0) == FREE and cell(ternary, -15.0, 0.0) == FREE
    assert cell(ternary, 0.0, -28.0) == UNKNOWN


def test_one_keyframe_alone_marks_hits_but_frees_nothing(two_views):
    """One miss (-0.4) stays above the free threshold (0.35: -0.62); one hit (0.85) is past the occupied one."""
    grid = OccupancyGrid(OccupancyGridParams(resolution=0.1))
    grid.add_keyframe(two_views[0])
    ternary = grid.ternary()
    assert cell(ternary, WALL_X, 0.0) == OCCUPIED
    assert ternary.counts()['free'] == 0


def test_a_redraw_moves_the_wall_with_the_poses_and_reuses_the_classification(two_views):
    grid = OccupancyGrid(OccupancyGridParams(resolution=0.1))
    for kf in two_views:
        grid.add_keyframe(kf)
    assert grid.classified == 2
    # 2 m forward in the map (camera_init z is map x): the wall is now at x = 12.05, and gone from 10.05.
    moved = [
        Keyframe(kf.index, kf.stamp_ns, kf.pose6 + [0, 0, 0, 0, 0, 2.0], kf.corner, kf.surf, kf.outlier)
        for kf in two_views
    ]
    grid.redraw(moved)
    ternary = grid.ternary()
    assert np.allclose(occupied_xy(ternary)[:, 0], 12.05)
    assert cell(ternary, WALL_X, 0.0) == FREE and cell(ternary, 12.05, 0.0) == OCCUPIED
    assert grid.classified == 2, 'a moved keyframe is not classified again'
    # Tilted by 5 deg (about camera z, the map's x: a roll), each keyframe is classified again.
    tilted = [
        Keyframe(kf.index, kf.stamp_ns, kf.pose6 + [0, 0, math.radians(5.0), 0, 0, 0], kf.corner, kf.surf, kf.outlier)
        for kf in moved
    ]
    grid.redraw(tilted)
    assert grid.classified == 4


def test_a_redraw_at_the_same_poses_gives_the_same_grid_as_adding_one_by_one(two_views):
    third = keyframe(2, wall_scene(), (0.0, math.radians(20.0), 0.0, 1.0, 0.0, -3.0))
    keyframes = [*two_views, third]
    grid = OccupancyGrid()
    for kf in keyframes:
        grid.add_keyframe(kf)
    before = grid.ternary()
    grid.redraw(keyframes)
    after = grid.ternary()
    assert before.origin == after.origin and np.array_equal(before.cells, after.cells)
    assert before.counts()['occupied'] > 0


def test_the_map_frame_is_camera_init_in_rep103_axes():
    """A keyframe turned 90 deg left (yaw about camera y, the map's z) sees the wall along the map's +y axis."""
    turned = [keyframe(k, wall_scene(), (0.0, math.radians(90.0), 0.0, 0.0, 0.0, 0.0)) for k in range(2)]
    grid = OccupancyGrid()
    for kf in turned:
        grid.add_keyframe(kf)
    occupied = occupied_xy(grid.ternary())
    assert np.allclose(occupied[:, 1], WALL_X) and np.abs(occupied[:, 0]).max() < WALL_HALF


def test_a_keyframes_points_are_its_three_clouds_in_lidar_axes_without_the_non_finite_ones():
    """Corner, surf and outlier points (camera axes, an intensity column) in that order, in lidar axes (x = camera
    z, y = camera x, z = camera y); a point with NaN or inf in any coordinate is left out, the others kept."""
    corner = np.array([[1.0, 2.0, 3.0, 0.5]], np.float32)
    surf = np.array([[4.0, 5.0, 6.0, 0.5], [np.nan, 0.0, 1.0, 0.5], [7.0, 8.0, 9.0, 0.5]], np.float32)
    outlier = np.array([[1.0, np.inf, 1.0, 0.5], [-1.0, -2.0, -3.0, np.nan]], np.float32)
    frame = type('Keyframe', (), {'corner': corner, 'surf': surf, 'outlier': outlier})
    points = grid_module.keyframe_points(frame)
    assert points.dtype == np.float32 and points.flags.c_contiguous
    assert points.tolist() == [[3.0, 1.0, 2.0], [6.0, 4.0, 5.0], [9.0, 7.0, 8.0], [-3.0, -1.0, -2.0]]
    frame.outlier = outlier[1:]
    assert grid_module.keyframe_points(frame).tolist() == [
        [3.0, 1.0, 2.0],
        [6.0, 4.0, 5.0],
        [9.0, 7.0, 8.0],
        [-3.0, -1.0, -2.0],
    ]
    frame.surf = surf[::2]  # all finite
    assert grid_module.keyframe_points(frame).tolist() == [
        [3.0, 1.0, 2.0],
        [6.0, 4.0, 5.0],
        [9.0, 7.0, 8.0],
        [-3.0, -1.0, -2.0],
    ]


def test_a_keyframe_without_a_finite_pose_or_too_far_is_refused_and_the_grid_kept(two_views):
    grid = OccupancyGrid(OccupancyGridParams(max_cells=2_000_000))
    grid.add_keyframe(two_views[0])
    before = grid.ternary()
    lost = keyframe(5, wall_scene(), (0.0, 0.0, 0.0, np.nan, 0.0, 0.0))
    with pytest.raises(ValueError, match='no finite pose'):
        grid.add_keyframe(lost)
    with pytest.raises(ValueError, match='no finite pose'):
        grid.redraw([*two_views, lost])
    far = keyframe(6, wall_scene(), (0.0, 0.0, 0.0, 0.0, 0.0, 5000.0))  # 5 km ahead: 5060 x 60 m at 0.1 m
    with pytest.raises(ValueError, match='max_cells'):
        grid.add_keyframe(far)
    after = grid.ternary()
    assert after.origin == before.origin and np.array_equal(after.cells, before.cells)


def test_sync_adds_the_new_keyframes_and_redraws_when_a_pose_moved(two_views):
    """sync() is what the node calls: new keyframes are added (the same grid as adding them one by one), the same
    list again changes nothing, a moved pose or a dropped keyframe redraws from all of them."""
    third = keyframe(2, wall_scene(), (0.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    grid, reference = OccupancyGrid(), OccupancyGrid()
    assert grid.sync(two_views[:1]) == 'added' and grid.sync(two_views) == 'added'
    version = grid.version
    assert grid.sync(two_views) == 'unchanged' and grid.version == version and grid.redraws == 0
    for kf in two_views:
        reference.add_keyframe(kf)
    assert np.array_equal(grid.ternary().cells, reference.ternary().cells)
    assert grid.sync([*two_views, third]) == 'added' and grid.redraws == 0
    # A loop closure moved every pose 2 m forward (camera z = map x): redrawn, the wall moves with them.
    moved = [
        Keyframe(kf.index, kf.stamp_ns, kf.pose6 + [0, 0, 0, 0, 0, 2.0], kf.corner, kf.surf, kf.outlier)
        for kf in [*two_views, third]
    ]
    assert grid.sync(moved) == 'redrawn' and grid.redraws == 1 and grid.version > version
    assert cell(grid.ternary(), 12.05, 0.0) == OCCUPIED and cell(grid.ternary(), WALL_X, 0.0) == FREE
    # Fewer keyframes (a heal dropped one): redrawn without it.
    assert grid.sync(moved[:2]) == 'redrawn' and grid.keyframes_added == 2


def test_a_saved_map_round_trips_its_grid_and_an_older_map_gets_one_drawn(tmp_path, two_views):
    """saved_occupancy_grid: the map_server files of a saved map, read back to the same cells, origin and
    resolution; a map folder without them (saved before the grid existed) has its grid drawn from its keyframes."""
    from lego_loam_py.core.mapping import MapOptimization

    mapper = MapOptimization(Params())
    mapper.keyframes = list(two_views)
    written = mapper.save(tmp_path / 'with')
    assert written['occupancy_yaml'].name == 'occupancy.yaml' and written['occupancy_image'].name == 'occupancy.pgm'
    expected = OccupancyGrid(Params().occupancy_grid)
    expected.sync(two_views)
    expected = expected.ternary()
    loaded = saved_occupancy_grid(tmp_path / 'with', Params().occupancy_grid)
    assert np.array_equal(loaded.cells, expected.cells) and loaded.resolution == expected.resolution
    assert loaded.origin == pytest.approx(expected.origin, abs=1e-9) and loaded.frame_id == 'map'
    (tmp_path / 'with' / 'occupancy.yaml').unlink()
    (tmp_path / 'with' / 'occupancy.pgm').unlink()
    drawn = saved_occupancy_grid(tmp_path / 'with', Params().occupancy_grid)
    assert np.array_equal(drawn.cells, expected.cells) and drawn.origin == expected.origin
    # occupancy_grid.enabled false: no grid files.
    off = MapOptimization(Params().replace(occupancy_grid__enabled=False))
    off.keyframes = list(two_views)
    assert 'occupancy_yaml' not in off.save(tmp_path / 'without')
    assert not (tmp_path / 'without' / 'occupancy.yaml').exists() and off.occupancy_problem is None
    # A grid that cannot be made (more cells than max_cells): the rest of the map is saved, and the save says why.
    small = MapOptimization(Params().replace(occupancy_grid__max_cells=1000))
    small.keyframes = list(two_views)
    written = small.save(tmp_path / 'too_big')
    assert 'occupancy_yaml' not in written and (tmp_path / 'too_big' / 'trajectory.tum').is_file()
    assert 'the occupancy grid was not saved' in small.occupancy_problem and 'max_cells 1000' in small.occupancy_problem


# ------------------------------------------------------------------------------------------- the ground


def test_ground_on_a_slope_is_ground_not_an_obstacle():
    up = np.array([0.0, 0.0, 1.0])
    for slope in (0.0, 0.3, -0.3):
        scan = classify_keyframe(ground_rings(slope=slope), up, OccupancyGridParams())
        assert len(scan.obstacles) == 0, (slope, len(scan.obstacles))
        assert len(scan.ground) > 0.9 * len(
            ground_rings(slope=slope)[np.hypot(*ground_rings(slope=slope)[:, :2].T) <= 30.0]
        )
        assert scan.sensor_height == pytest.approx(HEIGHT, abs=0.05)


def test_a_car_beside_the_sensor_whose_ground_is_unseen_is_an_obstacle():
    """A VLP-16 1.8 m up sees no ground nearer than 6.7 m: a car's top 3 m to the side has only itself under it,
    and the local ground plane says it stands 0.9-1.1 m above the ground."""
    x, y = np.meshgrid(np.arange(-2.0, 2.0, 0.1), np.arange(-3.9, -3.0, 0.1))
    top = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 1.0 - HEIGHT)])
    scan = classify_keyframe(np.concatenate([ground_rings(), top]), np.array([0.0, 0.0, 1.0]), OccupancyGridParams())
    assert len(scan.obstacles) == len(top)
    assert np.allclose(np.sort(scan.obstacles[:, 2]), top[:, 2])


def test_a_crown_over_seen_ground_is_no_obstacle_nor_ground():
    """Points 2.5-4 m above the ground, 12-14 m off, over ground the lidar sees: above the band, and not ground."""
    rng = np.random.default_rng(0)
    crown = np.column_stack(
        [rng.uniform(12.0, 14.0, 300), rng.uniform(-1.0, 1.0, 300), rng.uniform(2.5, 4.0, 300) - HEIGHT]
    )
    scan = classify_keyframe(np.concatenate([ground_rings(), crown]), np.array([0.0, 0.0, 1.0]), OccupancyGridParams())
    assert len(scan.obstacles) == 0
    assert not np.isin(scan.ground[:, 2], crown[:, 2].astype(np.float32)).any()


def test_bad_parameters_are_refused_with_their_names():
    with pytest.raises(ParameterError, match="'occupancy_grid.resolution' must be positive"):
        Params().replace(occupancy_grid__resolution=0.0)
    with pytest.raises(ParameterError, match="'occupancy_grid.min_height' must lie in 0..max_height"):
        Params().replace(occupancy_grid__min_height=2.0, occupancy_grid__max_height=1.0)
    with pytest.raises(ParameterError, match='free_threshold < 0.5 < occupied_threshold'):
        Params().replace(occupancy_grid__occupied_threshold=0.4)
    with pytest.raises(ParameterError, match='at most 4000 cells'):
        Params().replace(occupancy_grid__resolution=0.01, occupancy_grid__max_range=50.0)
    with pytest.raises(ParameterError, match="'occupancy_grid.enabled' must be a boolean"):
        Params().replace(occupancy_grid__enabled='yes')
    grid = Params().occupancy_grid  # (the defaults: a ground robot with a VLP-16)
    assert (grid.enabled, grid.resolution, grid.min_height, grid.max_height, grid.max_range) == (
        True,
        0.1,
        0.3,
        2.0,
        30.0,
    )


# ------------------------------------------------ the C kernels against NumPy (native/occupancy_kernels.c)

needs_kernel = pytest.mark.skipif(grid_module._occupancy_kernels is None, reason='the C extension is not built here')


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


@pytest.fixture
def kernel_calls(monkeypatch) -> Counter:
    """How often each C kernel is called (a comparison of C with NumPy must reach C, not fall back to NumPy)."""
    kernels, calls = grid_module._occupancy_kernels, Counter()

    class Counting:
        def __getattr__(self, name):
            def counted(*args):
                calls[name] += 1
                return getattr(kernels, name)(*args)

            return counted

    for module in (grid_module, occupancy_ground):
        monkeypatch.setattr(module, '_occupancy_kernels', Counting())
    return calls


def random_scene(rng: np.random.Generator) -> np.ndarray:
    """(n, 3) lidar-frame points: ground rings on a random slope and a few boxes' faces standing on it, 0.2-3 m
    tall, 3-25 m off (obstacles, ground and the shadows between)."""
    slope = float(rng.uniform(-0.2, 0.2))
    parts = [ground_rings(slope=slope)]
    for _ in range(int(rng.integers(2, 8))):
        centre = rng.uniform(3.0, 25.0) * np.array([math.cos(a := rng.uniform(0, 2 * math.pi)), math.sin(a)])
        half = rng.uniform(0.2, 2.0, 2)
        u, z = np.meshgrid(np.arange(-1.0, 1.0, 0.05), np.arange(0.0, rng.uniform(0.2, 3.0), 0.1))
        for axis in (0, 1):
            for side in (-1.0, 1.0):
                face = np.zeros((u.size, 2))
                face[:, axis] = side * half[axis]
                face[:, 1 - axis] = u.ravel() * half[1 - axis]
                xy = centre + face
                parts.append(np.column_stack([xy, -HEIGHT + slope * xy[:, 0] + z.ravel()]))
    return np.concatenate(parts)


@needs_kernel
@pytest.mark.parametrize('seed', range(4))
def test_the_disk_update_in_c_is_numpys_bit_for_bit(seed, kernel_calls):
    """One keyframe's update of its window of the grid (_update_window), in C and in NumPy, one after another on
    the same arrays: random log-odds (some past the clamp's bounds, some at them, -0.0, NaN), random free ranges
    (inf among them) and hits, windows flush with each edge of the arrays and inside: the same bits."""
    rng = np.random.default_rng(seed)
    params = OccupancyGridParams(
        max_range=float(rng.uniform(1.0, 4.0)),
        angular_resolution_deg=float(rng.choice([0.5, 3.0, 45.0])),
        hit_log_odds=float(rng.uniform(0.1, 3.0)),
        miss_log_odds=-float(rng.uniform(0.1, 3.0)),
        min_log_odds=-float(rng.uniform(0.5, 3.0)),
        max_log_odds=float(rng.uniform(0.5, 3.0)),
    )
    disk = grid_module._make_disk(params)
    size = 2 * disk.reach + 1
    height, width = size + int(rng.integers(0, 30)), size + int(rng.integers(0, 30))
    log_odds = rng.uniform(-5.0, 5.0, (height, width)).astype(np.float32)
    pick = rng.random(log_odds.shape)
    log_odds[pick < 0.05] = np.float32(params.min_log_odds)
    log_odds[pick > 0.95] = np.float32(params.max_log_odds)
    log_odds[(pick > 0.5) & (pick < 0.52)] = -0.0
    log_odds[(pick > 0.6) & (pick < 0.61)] = np.nan  # (never in a grid, but np.clip keeps it: so must C)
    observed = rng.random(log_odds.shape) < 0.3
    arrays = {native: (log_odds.copy(), observed.copy()) for native in (True, False)}
    corners = [(0, 0), (width - size, height - size), (0, height - size), (width - size, 0)]
    corners.append((int(rng.integers(0, width - size + 1)), int(rng.integers(0, height - size + 1))))
    for corner in corners:
        free_range = rng.uniform(-1.0, 1.2 * params.max_range, disk.count + 1).astype(np.float32)
        free_range[rng.random(disk.count + 1) < 0.05] = np.inf
        free_range[-1] = 0.0
        hit = rng.random((size, size)) < 0.1
        for native, (lo, seen) in arrays.items():
            grid_module._update_window(lo, seen, corner, disk, free_range, hit, params, native)
        assert same_bits(arrays[True][0], arrays[False][0]), corner
        assert same_bits(arrays[True][1], arrays[False][1]), corner
    lo = arrays[True][0]
    assert (lo == np.float32(params.min_log_odds)).any() and (lo == np.float32(params.max_log_odds)).any()
    assert kernel_calls['update_disk'] == len(corners)


@needs_kernel
def test_the_disk_update_in_c_refuses_a_window_outside_the_arrays_or_a_bin_past_the_ranges():
    """A window reaching past the arrays is refused before anything is written; a bin outside the free ranges (the
    sentinel bin without its entry, a negative bin) raises rather than read beyond them."""
    params = OccupancyGridParams(max_range=1.0)
    disk = grid_module._make_disk(params)
    size = 2 * disk.reach + 1
    log_odds, observed = np.zeros((size + 2, size + 2), np.float32), np.zeros((size + 2, size + 2), bool)
    free_range = np.ones(disk.count + 1, np.float32)
    rest = (np.zeros((size, size), bool), 0.85, -0.4, -2.0, 3.5)
    kernel = grid_module._occupancy_kernels.update_disk
    with pytest.raises(ValueError, match='outside the arrays'):
        kernel(log_odds, observed, size + 2, 3, 0, size, disk.ranges, disk.bins, free_range, *rest)
    assert not log_odds.any() and not observed.any()
    negative = disk.bins.copy()
    negative[size // 2, size // 2] = -1
    for bins, ranges in ((disk.bins, free_range[:-1]), (negative, free_range)):
        with pytest.raises(IndexError, match='free_range'):
            kernel(log_odds, observed, size + 2, 1, 1, size, disk.ranges, bins, ranges, *rest)


@needs_kernel
def test_the_grid_drawn_with_c_is_numpys_bit_for_bit(kernel_calls):
    """Keyframes added in turn to a grid drawn with the C kernels and to one drawn by NumPy alone
    (OccupancyGrid(native=False)): the same classification, log-odds, observed cells and grid, bit for bit. The
    wall seen twice from one place (log-odds large enough that cells reach both clamp bounds), then from places at
    the edge of the grid so far (the arrays grow), then random scenes at random poses."""
    rng = np.random.default_rng(3)
    params = OccupancyGridParams(hit_log_odds=2.0, miss_log_odds=-1.5, min_log_odds=-2.0, max_log_odds=3.5)
    poses = [(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)] * 2 + [(0.0, 0.5, 0.0, 0.0, 0.0, 31.0), (0.0, -2.0, 0.0, 35.0, 0.0, 0.0)]
    keyframes = [keyframe(k, wall_scene(), pose) for k, pose in enumerate(poses)]
    for k in range(len(keyframes), len(keyframes) + 6):
        pose = (*rng.normal(0.0, 0.02, 1), rng.uniform(-math.pi, math.pi), *rng.normal(0.0, 0.02, 1))
        keyframes.append(
            keyframe(k, random_scene(rng), (*pose, *rng.uniform(-40.0, 40.0, 1), 0.0, rng.uniform(-40, 40)))
        )
    grids = {native: OccupancyGrid(params, native=native) for native in (True, False)}
    shapes = set()
    for kf in keyframes:
        for grid in grids.values():
            grid.add_keyframe(kf)
        c, n = grids[True], grids[False]
        assert same_bits(c._log_odds, n._log_odds) and same_bits(c._observed, n._observed), kf.index
        assert np.array_equal(c._corner, n._corner)
        shapes.add(c._log_odds.shape)
    for key, scan in grids[True]._scans.items():
        other = grids[False]._scans[key]
        assert same_bits(scan.obstacles, other.obstacles) and same_bits(scan.ground, other.ground), key
        assert scan.sensor_height == other.sensor_height
    a, b = grids[True].ternary(), grids[False].ternary()
    assert same_bits(a.cells, b.cells) and a.origin == b.origin
    lo = grids[True]._log_odds
    assert len(shapes) >= 3, 'the arrays grew as keyframes came at their edge'
    assert (lo == np.float32(3.5)).any() and (lo == np.float32(-2.0)).any(), 'cells at both clamp bounds'
    assert a.counts()['occupied'] > 500 and a.counts()['free'] > 10 * a.counts()['occupied']
    assert kernel_calls['update_disk'] == kernel_calls['coarse_cone'] == len(keyframes)
    assert kernel_calls['pair_offsets'] == kernel_calls['pairs_count'] == len(keyframes)
    assert kernel_calls['pairs_min'] == 2 * len(keyframes)  # (the slope cone and the ground under each point)
    assert kernel_calls['lowest_in_cells'] == 2 * len(keyframes)  # (the 1 m cells and the 0.2 m columns)


@needs_kernel
@pytest.mark.parametrize('seed', range(6))
def test_the_coarse_cone_in_c_is_numpys_bit_for_bit(seed, kernel_calls):
    """_coarse_cone over random cells and heights (inf and -inf among them, NaN in some: np.minimum propagates it),
    cells 0.2-1 m, slopes 0-2, radii of none, less than a cell, one cell and several: the same bits."""
    rng = np.random.default_rng(seed)
    span = int(rng.integers(1, 40))
    cells = np.unique(rng.integers(-span, span + 1, (int(rng.integers(1, 600)), 2)), axis=0) + rng.integers(-99, 99, 2)
    lowest = rng.normal(0.0, 5.0, len(cells))
    lowest[rng.random(len(cells)) < 0.1] = np.inf
    lowest[rng.random(len(cells)) < 0.02] = -np.inf
    if seed % 3 == 2:
        lowest[rng.random(len(cells)) < 0.02] = np.nan
    for cell_size, slope, radius in (
        (1.0, 0.5, 6.0),
        (1.0, 0.5, 0.0),
        (0.5, 0.0, 0.3),
        (1.0, 2.0, 1.0),
        (0.2, 0.7, 1.5),
    ):
        native = occupancy_ground._coarse_cone(cells, lowest, cell_size, slope, radius)
        numpy = occupancy_ground._coarse_cone(cells, lowest, cell_size, slope, radius, native=False)
        assert same_bits(native, numpy), (cell_size, slope, radius)
        assert np.isinf(numpy).any() and np.isfinite(numpy).any()
    assert kernel_calls['coarse_cone'] == 5


# --------------------------------------------------------------------------------- files and the message


def small_grid() -> TernaryGrid:
    cells = np.full((3, 4), UNKNOWN, np.int8)
    cells[0, 0] = OCCUPIED  # row 0: at the origin, the lowest y
    cells[0, 1:] = FREE
    cells[2, 3] = OCCUPIED  # the top right corner
    return TernaryGrid(0.05, (-1.25, 2.5), cells)


def test_map_server_files_round_trip_with_the_image_flipped(tmp_path):
    grid = small_grid()
    paths = write_occupancy_files(tmp_path, grid, 'site')
    assert sorted(p.name for p in tmp_path.iterdir()) == ['site.pgm', 'site.yaml']  # no temporaries left
    import yaml

    meta = yaml.safe_load(paths['yaml'].read_text())
    assert meta == {
        'image': 'site.pgm',
        'mode': 'trinary',
        'resolution': 0.05,
        'origin': [-1.25, 2.5, 0.0],
        'negate': 0,
        'occupied_thresh': OCCUPIED_THRESH,
        'free_thresh': FREE_THRESH,
    }
    data = paths['image'].read_bytes()
    assert data.startswith(b'P5\n')
    pixels = np.frombuffer(data[-12:], np.uint8).reshape(3, 4)
    # The image's first row is the grid's top row (row 2), its last row the grid's row 0.
    assert pixels.tolist() == [[205, 205, 205, 0], [205, 205, 205, 205], [0, 254, 254, 254]]
    back = read_occupancy_files(paths['yaml'])
    assert back.resolution == 0.05 and back.origin == (-1.25, 2.5) and back.origin_yaw == 0.0
    assert np.array_equal(back.cells, grid.cells)


def test_the_trinary_pixels_read_as_map_server_reads_them(tmp_path):
    """map_server's occupancy of a pixel is (255 - value) / 255: the thresholds written put 0 above occupied_thresh,
    254 below free_thresh and 205 between."""
    occupancy = {value: (255 - value) / 255 for value in (0, 254, 205)}
    assert occupancy[0] > OCCUPIED_THRESH and occupancy[254] < FREE_THRESH
    assert FREE_THRESH <= occupancy[205] <= OCCUPIED_THRESH
    # A map_server map of another tool: negate, its own thresholds and a text PGM with comments.
    (tmp_path / 'other.pgm').write_text('P2\n# made elsewhere\n3 1\n# max\n255\n255 0 100\n')
    (tmp_path / 'other.yaml').write_text(
        'image: other.pgm\nresolution: 0.1\norigin: [1.0, 2.0, 0.5]\nnegate: 1\n'
        'occupied_thresh: 0.9\nfree_thresh: 0.1\n'
    )
    grid = read_occupancy_files(tmp_path / 'other.yaml')
    assert grid.cells.tolist() == [[OCCUPIED, FREE, UNKNOWN]] and grid.origin_yaw == 0.5


def test_unreadable_map_server_files_say_what_is_wrong(tmp_path):
    write_occupancy_files(tmp_path, small_grid())
    image = tmp_path / 'occupancy.pgm'
    image.write_bytes(image.read_bytes()[:-3])
    with pytest.raises(OccupancyFilesError, match='truncated'):
        read_occupancy_files(tmp_path / 'occupancy.yaml')
    (tmp_path / 'bad.yaml').write_text('image: occupancy.pgm\nresolution: 0.1\n')
    with pytest.raises(OccupancyFilesError, match='needs origin'):
        read_occupancy_files(tmp_path / 'bad.yaml')
    with pytest.raises(OccupancyFilesError, match='cannot read'):
        read_occupancy_files(tmp_path / 'missing.yaml')
    with pytest.raises(OccupancyFilesError, match='empty'):
        write_occupancy_files(tmp_path, TernaryGrid(0.1, (0.0, 0.0), np.zeros((0, 0), np.int8)))


def test_message_fields_are_row_major_from_the_origin():
    grid = small_grid()
    fields = message_fields(grid)
    assert (fields.frame_id, fields.resolution, fields.width, fields.height) == ('map', 0.05, 4, 3)
    assert fields.origin_position == (-1.25, 2.5, 0.0) and fields.origin_orientation == (0.0, 0.0, 0.0, 1.0)
    assert fields.data.typecode == 'b' and len(fields.data) == 12
    assert list(fields.data) == grid.cells.ravel().tolist()
    assert fields.data[0] == OCCUPIED and fields.data[2 * 4 + 3] == OCCUPIED
    turned = message_fields(TernaryGrid(0.1, (0.0, 0.0), grid.cells, origin_yaw=math.pi / 2))
    assert turned.origin_orientation == pytest.approx((0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)))


# ------------------------------------------------------------------------- a simulated recording, the truth


def test_a_short_simulated_recording_puts_its_occupied_cells_on_the_scene(campus_map):
    """bags/campus_8s mapped (20 keyframes, 13 m): the occupied cells lie on the scene's obstacles 0.3-2 m above
    the ground (benchmarks/occupancy_grid.py: 99 % on a whole lap)."""
    from lego_loam_py.core.mapping import keyframe_lidar_pose, read_bundle
    from lego_loam_py.sim.output import true_poses

    sys.path.insert(0, str(REPO / 'benchmarks'))
    from occupancy_grid import SceneTruth

    bundle = read_bundle(campus_map)
    keyframes = [
        Keyframe(k, int(bundle.stamps_ns[k]), bundle.poses6[k], bundle.corner[k], bundle.surf[k], bundle.outlier[k])
        for k in range(len(bundle))
    ]
    grid = OccupancyGrid(OccupancyGridParams(resolution=0.1))
    for kf in keyframes:
        grid.add_keyframe(kf)
    ternary = grid.ternary()
    counts = ternary.counts()
    assert counts['occupied'] >= 300 and counts['free'] >= 20 * counts['occupied'], counts
    simulated = bundle.source['simulated']
    truth = true_poses(simulated, bundle.stamps_ns)
    mapped = np.array([keyframe_lidar_pose(kf.pose6) for kf in keyframes])
    world_from_map = truth[0] @ np.linalg.inv(mapped[0])  # the map placed by its first keyframe
    centres = ternary.cell_centres() @ world_from_map[:2, :2].T + world_from_map[:2, 3]
    near = SceneTruth(simulated, truth[:, :2, 3]).within(centres, 2 * 0.1 + 0.1)
    assert near.mean() >= 0.9, f'{near.mean():.3f} of {len(near)} occupied cells on a true obstacle'


def test_the_run_saves_the_grid_beside_the_map_and_it_loads_back(campus_map):
    """A mapping run's save (``lego_loam_py run``'s, here the campus_map fixture's) writes occupancy.yaml and
    occupancy.pgm beside the other map files: the map_server metadata, and the grid of the saved keyframes."""
    import yaml

    from lego_loam_py.core.mapping import read_bundle

    meta = yaml.safe_load((campus_map / 'occupancy.yaml').read_text())
    assert meta['image'] == 'occupancy.pgm' and meta['mode'] == 'trinary' and meta['resolution'] == 0.1
    grid = read_occupancy_files(campus_map / 'occupancy.yaml')
    bundle = read_bundle(campus_map)
    redrawn = OccupancyGrid(Params().occupancy_grid)
    redrawn.sync(
        Keyframe(k, int(bundle.stamps_ns[k]), bundle.poses6[k], bundle.corner[k], bundle.surf[k], bundle.outlier[k])
        for k in range(len(bundle))
    )
    redrawn = redrawn.ternary()
    assert np.array_equal(grid.cells, redrawn.cells) and grid.origin == pytest.approx(redrawn.origin, abs=1e-9)
    assert grid.counts()['occupied'] > 100


@pytest.mark.parametrize('native', [True, False])
def test_the_slope_cone_and_the_ground_carried_over_between_neighbouring_columns_by_hand(native):
    """Three columns, (0, 0) and (3, 4) 5 m apart and (10, 0) alone within 6 m: the cone rises 0.5 m a metre from
    each neighbour, the ground is carried along the gradient (0.1, 0.2) each way (+1.1 m from the first to the
    second, -1.1 m back), a column outside the base lends nothing, and the count is of neighbours in the mask. With
    the C passes over the pairs and with NumPy's."""
    if native and grid_module._occupancy_kernels is None:
        pytest.skip('the C extension is not built here')
    xy = np.array([[0.0, 0.0], [3.0, 4.0], [10.0, 0.0]])
    neighbours = occupancy_ground._Neighbours(xy, 6.0, native)
    assert neighbours.native == native
    z = np.array([5.0, 1.0, 0.0])
    assert neighbours.cone(z, 0.5).tolist() == [3.5, 1.0, 0.0]
    assert neighbours.cone(z, 0.5, base=np.array([False, True, True])).tolist() == [3.5, 1.0, 0.0]
    assert neighbours.cone(z, 0.5, base=np.array([True, False, True])).tolist() == [5.0, 7.5, 0.0]
    gradient = np.array([0.1, 0.2])
    ground = neighbours.ground_under(z, np.array([True, True, True]), gradient)
    assert ground == pytest.approx([1.0 - 1.1, 1.0, 0.0], abs=1e-12)
    ground = neighbours.ground_under(z, np.array([True, False, False]), gradient)
    assert ground[0] == 5.0 and ground[1] == pytest.approx(6.1, abs=1e-12) and ground[2] == math.inf
    assert neighbours.count(np.array([True, True, True])).tolist() == [1, 1, 0]
    assert neighbours.count(np.array([True, False, True])).tolist() == [0, 0, 0]


@needs_kernel
@pytest.mark.parametrize('seed', range(4))
def test_the_passes_over_neighbouring_columns_in_c_are_numpys_bit_for_bit(seed, kernel_calls):
    """_Neighbours over random columns (clustered, so that many pairs share points, duplicates among them): the
    pairs' offsets and distances, the slope cone with and without a base, the ground carried along a gradient and
    the counts in a mask, in C and in NumPy: the same bits. Heights with inf among them, as the cone's base gives."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-30.0, 30.0, (int(rng.integers(3, 12)), 2))
    xy = (centres[rng.integers(0, len(centres), 2000)] + rng.normal(0.0, 1.5, (2000, 2))).round(1)
    z = rng.normal(0.0, 2.0, len(xy))
    z[rng.random(len(z)) < 0.05] = np.inf
    base = rng.random(len(xy)) < 0.6
    gradient = rng.normal(0.0, 0.3, 2)
    c, n = (occupancy_ground._Neighbours(xy, 1.2, native) for native in (True, False))
    assert c.native and not n.native and len(c.first) > 10 * len(xy)
    assert same_bits(c.offset, n.offset) and same_bits(c.distance, n.distance)
    for slope in (0.0, 0.4, 1.7):
        assert same_bits(c.cone(z, slope), n.cone(z, slope))
        assert same_bits(c.cone(z, slope, base), n.cone(z, slope, base))
    assert same_bits(c.ground_under(z, base, gradient), n.ground_under(z, base, gradient))
    assert np.array_equal(c.count(base), n.count(base))
    assert kernel_calls['pairs_min'] == 7 and kernel_calls['pairs_count'] == 1


@needs_kernel
def test_the_passes_over_pairs_refuse_a_pair_outside_the_points():
    """A pair naming a point past the arrays (or before them) is an IndexError, not a read beyond them."""
    kernels = occupancy_ground._occupancy_kernels
    x, z = np.zeros(3), np.zeros(3)
    for first, second in (([0, 3], [1, 2]), ([0, 1], [-1, 2])):
        first, second = np.array(first, np.int64), np.array(second, np.int64)
        with pytest.raises(IndexError, match='outside the points'):
            kernels.pair_offsets(x, x, first, second, np.empty((2, 2)), np.empty(2))
        with pytest.raises(IndexError, match='outside the points'):
            kernels.pairs_min(np.zeros(3), first, second, z, np.zeros(2), -1.0, b'')
        with pytest.raises(IndexError, match='outside the points'):
            kernels.pairs_count(first, second, np.ones(3, bool), np.empty(3, np.int64))


@needs_kernel
@pytest.mark.parametrize('seed', range(4))
def test_the_cells_and_their_lowest_points_in_c_are_numpys(seed, kernel_calls):
    """_cells over random points (heights rounded so that a cell holds equal lowest heights, -0.0 beside 0.0,
    points far apart and close): the same cells, order, lowest points (the first of equal ones) and heights in C
    as NumPy's lexsort gives; a NaN height is left to NumPy."""
    rng = np.random.default_rng(seed)
    xy = np.concatenate([rng.normal(0.0, 3.0, (3000, 2)), rng.uniform(-80.0, 80.0, (500, 2))])
    z = rng.normal(0.0, 1.0, len(xy)).round(1)
    z[rng.random(len(z)) < 0.05] = -0.0
    for size in (0.2, 1.0, 7.0):
        native, numpy = occupancy_ground._cells(xy, z, size), occupancy_ground._cells(xy, z, size, native=False)
        for a, b in zip(native, numpy):
            assert same_bits(a, b), size
        assert len(numpy[3]) < len(xy) and (np.bincount(numpy[1]) > 1).any()
    assert kernel_calls['lowest_in_cells'] == 3
    z[7] = np.nan
    native, numpy = occupancy_ground._cells(xy, z, 1.0), occupancy_ground._cells(xy, z, 1.0, native=False)
    assert all(same_bits(a, b) for a, b in zip(native, numpy))
