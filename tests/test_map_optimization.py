"""mapOptimization core: line/plane fitting, Jacobians, scan-to-map recovery, iSAM2 loop correction,
keyframes and the surrounding map, golden parity, saving."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lego_loam_py.core.frames import matrix_to_quaternion, pose6_to_matrix, transform_cloud, transform_points
from lego_loam_py.core.geometry import GridNeighbours
from lego_loam_py.core.mapping import scan_to_map
from lego_loam_py.core.mapping.map_optimization import MapOptimization
from lego_loam_py.core.mapping.scan_to_map import edge_correspondences, map_jacobian_rows, plane_correspondences
from lego_loam_py.core.odometry.feature_association import FeatureAssociation, ScanInput
from lego_loam_py.core.params import Params, default_params_file, load_params
from lego_loam_py.core.pipeline import Pipeline
from lego_loam_py.core.projection.image_projection import ImageProjection, prepare_input
from lego_loam_py.core.voxel import voxel_downsample
from tests.support.sweeps import room_world, sweep

PARAMS = Params()


def cloud(points) -> np.ndarray:
    points = np.asarray(points, dtype=np.float32)
    return np.concatenate([points, np.zeros((len(points), 1), np.float32)], axis=1)


def search(points: np.ndarray) -> GridNeighbours:
    """The scan-to-map search in a map of ``points``."""
    return GridNeighbours(points, PARAMS.map_optimization.knn_max_sq_dist)


@pytest.mark.parametrize('native', [True, False], ids=['c_kernel', 'numpy'])
def test_edge_fit_by_hand(native):
    """Map points on the vertical line x = 1, z = 2 (camera axes): a query 0.3 m off it gets distance 0.3 and
    the unit gradient pointing away from the line."""
    line = cloud([[1.0, y, 2.0] for y in np.linspace(-0.4, 0.4, 9)])
    query = cloud([[1.3, 0.05, 2.0]])
    index, coeff = edge_correspondences(query, search(line), line, PARAMS, native=native)
    assert list(index) == [0]
    weight = 1 - 0.9 * 0.3
    assert coeff[0, 3] == pytest.approx(weight * 0.3, rel=1e-4)
    assert np.allclose(coeff[0, :3] / weight, [1.0, 0.0, 0.0], atol=1e-4)
    # A square grid of points on a plane is not a line: rejected by the eigenvalue test.
    grid = np.stack(np.meshgrid(np.linspace(-0.3, 0.3, 7), np.linspace(-0.3, 0.3, 7)), -1).reshape(-1, 2)
    plane = cloud(np.column_stack([1.0 + grid[:, 0], grid[:, 1], np.full(len(grid), 2.0)]))
    assert len(edge_correspondences(cloud([[1.0, 0.0, 2.1]]), search(plane), plane, PARAMS, native=native)[0]) == 0


@pytest.mark.parametrize('native', [True, False], ids=['c_kernel', 'numpy'])
def test_plane_fit_by_hand(native):
    rng = np.random.default_rng(1)
    floor = cloud(np.column_stack([rng.uniform(-0.5, 0.5, 50), np.full(50, -1.5), rng.uniform(4, 5, 50)]))
    query = cloud([[0.0, -1.2, 4.5]])
    index, coeff = plane_correspondences(query, search(floor), floor, PARAMS, native=native)
    assert list(index) == [0]
    distance = coeff[0, 3] / (1 - 0.9 * 0.3 / math.sqrt(np.linalg.norm([0, -1.2, 4.5])))
    assert abs(distance) == pytest.approx(0.3, rel=1e-3)
    assert np.allclose(np.abs(coeff[0, :3]) / np.linalg.norm(coeff[0, :3]), [0, 1, 0], atol=1e-6)
    # Neighbours off the plane by more than 0.2 m invalidate it: a checkerboard of two levels 0.5 m apart.
    grid = np.stack(np.meshgrid(np.arange(-3, 4) * 0.3, np.arange(-3, 4) * 0.3), -1).reshape(-1, 2)
    level = np.where((np.round(grid[:, 0] / 0.3) + np.round(grid[:, 1] / 0.3)) % 2 == 0, -1.5, -1.0)
    bumpy = cloud(np.column_stack([grid[:, 0], level, 4.5 + grid[:, 1]]))
    assert len(plane_correspondences(cloud([[0.0, -1.25, 4.5]]), search(bumpy), bumpy, PARAMS, native=native)[0]) == 0


@pytest.mark.skipif(
    not hasattr(scan_to_map._geometry_kernels, 'map_plane_terms'), reason='the C extension is not built'
)
def test_the_terms_kernels_refuse_rows_out_of_range_and_buffers_that_do_not_match():
    kernels = scan_to_map._geometry_kernels
    points, kept, coeff = np.zeros((4, 3), np.float32), np.empty(1, np.int64), np.empty((1, 4))
    with pytest.raises(IndexError, match='map_plane_terms'):
        kernels.map_plane_terms(points, 3, np.array([4]), np.zeros((1, 3)), np.zeros(1), 0.9, 0.1, kept, coeff)
    with pytest.raises(IndexError, match='map_line_terms'):
        kernels.map_line_terms(
            points, 3, np.array([-1]), np.zeros((1, 3)), np.zeros((1, 3)), 0.1, 0.9, 0.1, kept, coeff
        )
    with pytest.raises(ValueError, match='map_line_terms'):  # (directions of one column)
        kernels.map_line_terms(points, 3, np.array([0]), np.zeros((1, 3)), np.zeros(1), 0.1, 0.9, 0.1, kept, coeff)


@pytest.mark.skipif(
    not hasattr(scan_to_map._geometry_kernels, 'map_plane_terms'), reason='the C extension is not built'
)
@pytest.mark.parametrize('seed', range(8))
def test_the_terms_kernels_equal_numpy_bit_for_bit(seed):
    """Edges (ten vertical poles) and planes (a tilted floor and two walls) 40-60 m from the origin, 0-2 cm of
    noise, queries near them and far off, some exactly on a pole (zero distance: no gradient), one column of
    intensities: the same rows and coefficients, bit for bit, as the NumPy code after the fits."""
    rng = np.random.default_rng(seed)
    noise = (0.0, 0.005, 0.02)[seed % 3]
    poles = np.concatenate(
        [
            np.column_stack([np.full(30, x), np.linspace(-1.0, 2.0, 30), np.full(30, z)])
            for x, z in rng.uniform(-3, 3, (10, 2))
        ]
    )
    floor = np.column_stack([rng.uniform(-4, 4, 800), np.zeros(800), rng.uniform(-4, 4, 800)])
    floor[:, 1] = -1.5 + 0.05 * floor[:, 0] - 0.02 * floor[:, 2]
    walls = np.column_stack([np.full(400, 4.0), rng.uniform(-1.5, 2.0, 400), rng.uniform(-4, 4, 400)])
    walls = np.concatenate([walls, walls[:, [2, 1, 0]]])
    offset = np.append(rng.uniform(40.0, 60.0, 3) * rng.choice([-1.0, 1.0], 3), 0.0)
    world = np.concatenate([poles, floor, walls])
    world += rng.normal(0.0, noise, world.shape)
    world = (np.column_stack([world, rng.uniform(0, 16, len(world))]) + offset).astype(np.float32)
    queries = world[rng.integers(0, len(world), 600)] + np.append(rng.normal(0.0, 0.2, 3), 0.0).astype(np.float32)
    queries[:20, :3] = world[:20, :3]  # on a pole
    queries = np.ascontiguousarray(queries, dtype=np.float32)
    tree = search(world)
    for correspondences in (edge_correspondences, plane_correspondences):
        native, reference = (correspondences(queries, tree, world, PARAMS, native=flag) for flag in (True, False))
        assert len(reference[0]) > 10
        assert np.array_equal(native[0], reference[0])
        assert native[1].shape == reference[1].shape
        assert np.array_equal(native[1].view(np.int64), reference[1].view(np.int64))


def test_a_plane_needs_neighbours_that_span_one_not_a_ring_of_points_along_a_line():
    """The 5 nearest map points along one lidar ring lie on a line, about which any plane fits within the
    residual gate: with ``plane_min_aspect`` (0.2) such a neighbourhood makes no plane, a patch does. The
    principal spreads are checked by hand."""
    from lego_loam_py.core.geometry import fit_planes, principal_spreads

    ring = np.array([[[x, -1.8, 10.0 + 0.002 * x * x] for x in (-0.8, -0.4, 0.0, 0.4, 0.8)]])  # a ring arc
    patch = np.array([[[0.0, -1.8, 10.0], [1.0, -1.8, 10.0], [0.0, -1.8, 10.5], [1.0, -1.8, 10.5], [0.5, -1.8, 10.25]]])
    # The patch: variance 4 x 0.5^2 / 5 = 0.2 m^2 across x, 4 x 0.25^2 / 5 = 0.05 m^2 along z.
    along, across = principal_spreads(patch)
    assert along[0] == pytest.approx(math.sqrt(0.2), rel=1e-9) and across[0] == pytest.approx(math.sqrt(0.05), rel=1e-9)
    along, across = principal_spreads(ring)  # 0.57 m RMS along x; the arc bends by 1.3 mm
    assert along[0] == pytest.approx(math.sqrt(0.32), rel=1e-3) and across[0] < 0.001
    assert len(fit_planes(ring, 0.2)[0]) == 1 and len(fit_planes(ring, 0.2, 0.2)[0]) == 0
    assert len(fit_planes(patch, 0.2, 0.2)[0]) == 1
    assert PARAMS.map_optimization.plane_min_aspect == 0.2
    original = load_params(default_params_file().parent / 'original.yaml').map_optimization
    assert original.plane_min_aspect == 0.0


@pytest.mark.parametrize('seed', range(3))
def test_map_jacobian_matches_finite_differences(seed):
    rng = np.random.default_rng(seed)
    pose = rng.normal(0, [0.2, 1.0, 0.2, 5, 1, 5])
    points = cloud(rng.normal(0, 10, (30, 3)))
    coeff = np.concatenate([rng.normal(size=(30, 3)), rng.normal(size=(30, 1))], axis=1)
    rows = map_jacobian_rows(points, coeff, pose)

    def residual(p):
        return np.einsum('ni,ni->n', coeff[:, :3], transform_points(pose6_to_matrix(p), points[:, :3].astype(float)))

    for k in range(6):
        step = np.zeros(6)
        step[k] = 1e-6
        numeric = (residual(pose + step) - residual(pose - step)) / 2e-6
        assert np.allclose(rows[:, k], numeric, atol=1e-5), k


def features_of(scene, pose):
    params = PARAMS.replace(feature_association__relative_time_source='point_time')
    r = ImageProjection(params).process(prepare_input(sweep(scene, pose), params))
    fa = FeatureAssociation(params)
    return fa.extractor.extract(fa.prepare_points(ScanInput.from_segmentation(0, r)), r.cloud_info)


def test_scan_registered_to_a_map_of_itself_under_a_known_offset_is_recovered():
    scene = room_world(seed=2)
    f = features_of(scene, np.eye(4))
    mo = MapOptimization(PARAMS)
    corner_map = voxel_downsample(f.less_sharp, 0.2)
    surf_map = voxel_downsample(f.less_flat, 0.4)
    corner_ds, surf_ds = corner_map.copy(), surf_map.copy()
    truth = np.zeros(6)
    start = np.array([0.01, math.radians(2.0), -0.01, 0.15, -0.05, 0.2])  # offset of the initial guess
    pose = mo.register_to_map(corner_map, surf_map, corner_ds, surf_ds, start)
    assert np.abs(pose[3:] - truth[3:]).max() < 0.01
    assert math.degrees(np.abs(pose[:3] - truth[:3]).max()) < 0.05


def plane_grid(
    axis: int, at: float, first: tuple[float, float], second: tuple[float, float], spacing: float
) -> np.ndarray:
    """Points on the plane ``coordinate[axis] = at`` [m], a grid over the other two coordinates (in order)."""
    u, v = (np.arange(low, high + 1e-9, spacing) for low, high in (first, second))
    u, v = (g.ravel() for g in np.meshgrid(u, v))
    points = np.empty((len(u), 3))
    points[:, axis] = at
    points[:, [i for i in range(3) if i != axis]] = np.column_stack([u, v])
    return points


def corridor_surfaces(end_walls: bool) -> np.ndarray:
    """A 2.2 m wide corridor around the sensor in camera axes (x left, y up, z forward): walls at x = ±1.1 m
    along z, the floor (y = -1.6) and the ceiling (y = 1.0) seen only in two 1.2 x 1.2 m patches of 25 points
    each (as by a lidar looking along a corridor), and optionally walls across it at z = ±14 m."""
    walls = [plane_grid(0, x, (-1.5, 0.9), (-13.5, 13.5), 0.25) for x in (-1.1, 1.1)]
    floor = plane_grid(1, -1.6, (-0.6, 0.6), (4.0, 5.2), 0.3)
    ceiling = plane_grid(1, 1.0, (-0.6, 0.6), (-5.2, -4.0), 0.3)
    ends = [plane_grid(2, z, (-1.0, 1.0), (-1.5, 0.9), 0.2) for z in (-14.0, 14.0)] if end_walls else []
    assert len(floor) == len(ceiling) == 25
    return cloud(np.concatenate(walls + [floor, ceiling] + ends))


def register_in_corridor(end_walls: bool, start: np.ndarray, **overrides):
    """The corridor's surfaces seen from the origin (3 mm noise) registered to themselves from ``start``:
    (pose, RegistrationCounts)."""
    from lego_loam_py.core.gauss_newton import DegeneracyProjection
    from lego_loam_py.core.mapping.scan_to_map import register_scan_to_map

    surfaces = corridor_surfaces(end_walls)
    scan = surfaces.copy()
    scan[:, :3] += np.random.default_rng(0).normal(0, 0.003, (len(scan), 3)).astype(np.float32)
    none = np.zeros((0, 4), np.float32)
    return register_scan_to_map(none, surfaces, none, scan, start, PARAMS.replace(**overrides), DegeneracyProjection(6))


def test_a_corridor_height_held_by_fifty_floor_and_ceiling_matches_is_not_degenerate():
    """The condition (smallest eigenvalue of the normal matrix) counts the full-weight correspondences holding
    the worst direction: here the height, held only by the 50 floor and ceiling points. That registers it to
    the millimetre; the original's threshold (100) called it degenerate and kept the initial guess's 5 cm."""
    start = np.array([0.0, 0.0, math.radians(0.5), 0.0, 0.05, 0.0])  # 0.5 deg roll, 5 cm too high
    pose, counts = register_in_corridor(True, start)
    assert 45 < counts.condition < 50 and not counts.degenerate  # 50 matches of weight 0.98-1
    assert np.abs(pose[3:]).max() < 0.002 and math.degrees(np.abs(pose[:3]).max()) < 0.05
    pose, counts = register_in_corridor(True, start, map_optimization__degeneracy_threshold=100.0)
    assert counts.degenerate and counts.condition < 50
    assert pose[4] == pytest.approx(0.05, abs=0.002)  # the height was never registered


def test_scan_to_map_holds_what_the_map_cannot_see_and_registers_the_rest():
    """Without the walls across it, nothing in the corridor faces along it: motion along it (camera z) is
    unobservable, found degenerate by the default threshold and held at the initial guess, while the height,
    the side offset and the roll are registered."""
    start = np.array([0.0, 0.0, math.radians(0.5), 0.04, 0.05, 0.3])
    pose, counts = register_in_corridor(False, start)
    assert counts.degenerate and counts.condition < 1.0
    assert pose[5] == pytest.approx(0.3, abs=0.001)
    # (Held 0.3 m along, the floor and ceiling patches' edges lose some matches: a few mm, not the 4-5 cm.)
    assert np.abs(pose[3:5]).max() < 0.005 and math.degrees(np.abs(pose[:3]).max()) < 0.1


def test_isam2_loop_factor_corrects_a_drifted_chain():
    """A square loop driven with odometry that over-turns: one loop factor pulls the chain back."""
    mo = MapOptimization(PARAMS)
    true_poses, drifted = [], []
    truth = np.eye(4)
    belief = np.eye(4)
    empty = np.zeros((0, 4), np.float32)
    for k in range(40):
        step = np.eye(4)
        turn = math.pi / 2 if k % 10 == 9 else 0.0
        step[:3, :3] = pose6_to_matrix([0, turn, 0, 0, 0, 0])[:3, :3]
        step[2, 3] = 2.0  # 2 m forward (camera z)
        truth = truth @ step
        noisy = step.copy()
        noisy[:3, :3] = pose6_to_matrix([0, turn + math.radians(1.5), 0, 0, 0, 0])[:3, :3]  # 1.5 deg over-turn
        belief = belief @ noisy
        true_poses.append(truth.copy())
        mo.transform_aft = mo.transform_tobe = np.array(
            [*__import__('lego_loam_py.core.frames', fromlist=['x']).matrix_to_euler(belief[:3, :3]), *belief[:3, 3]]
        )
        assert mo._save_keyframe(k, empty, empty, empty)
        drifted.append(pose6_to_matrix(mo.keyframes[-1].pose6))
    error_before = np.linalg.norm(drifted[-1][:3, 3] - true_poses[-1][:3, 3])
    # The last keyframe is back at the first one's place: tell the graph so.
    relative = np.linalg.inv(true_poses[-1]) @ true_poses[0]
    mo.add_loop_factor(39, 0, relative, np.full(6, 1e-4))
    corrected = [pose6_to_matrix(kf.pose6) for kf in mo.keyframes]
    error_after = np.linalg.norm(corrected[-1][:3, 3] - true_poses[-1][:3, 3])
    assert error_before > 5.0 and error_after < 0.5 * error_before
    mean_before = np.mean([np.linalg.norm(d[:3, 3] - t[:3, 3]) for d, t in zip(drifted, true_poses)])
    mean_after = np.mean([np.linalg.norm(c[:3, 3] - t[:3, 3]) for c, t in zip(corrected, true_poses)])
    assert mean_after < 0.6 * mean_before


def moved(x: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = x  # forward (lidar x)
    return pose


def test_keyframes_every_0_3_m_and_the_surrounding_map():
    scene = room_world(seed=8)
    mo = MapOptimization(PARAMS)
    added = []
    for k in range(8):
        f = features_of(scene, moved(0.16 * k))
        odometry = np.array([0, 0, 0, 0, 0, 0.16 * k])  # the odometry agrees: 16 cm per step (camera z)
        step = mo.process(k * 400_000_000, odometry, f.less_sharp, f.less_flat, np.zeros((0, 4), np.float32))
        added.append(step.keyframe_added)
        assert abs(step.transform_aft[5] - 0.16 * k) < 0.03
    assert added == [True, False, True, False, True, False, True, False]
    assert len(mo.keyframes) == 4
    ids = mo._surrounding_ids()
    # The original picks keyframes through a 1 m voxel grid of their positions and truncates the averaged
    # index of each voxel (quirk 8.5): compute that independently.
    positions = np.array([kf.pose6[3:] for kf in mo.keyframes])
    cells = np.floor(positions / 1.0)
    expected = sorted({int(np.mean([i for i in range(4) if (cells[i] == cell).all()])) for cell in cells})
    assert ids == expected and mo._corner_accumulator.ids() <= set(ids)
    # Steps closer than mapping_process_interval are skipped.
    assert (
        mo.process(7 * 400_000_000 + 200_000_000, np.zeros(6), f.less_sharp, f.less_flat, np.zeros((0, 4), np.float32))
        is None
    )


def test_keypose_pick_latest_maps_a_second_pass_with_its_own_keyframes():
    # Two passes along the same 30 m (keyframes 2 m apart): 0..15 going, 16..31 coming back over them.
    mo = MapOptimization(PARAMS.replace(map_optimization__keypose_pick='latest'))
    empty = np.zeros((0, 4), np.float32)
    path = np.concatenate([np.arange(16) * 2.0, np.arange(16) * 2.0]) + 0.5
    for k, z in enumerate(path):
        mo.transform_aft = mo.transform_tobe = np.array([0, 0, 0, 0, 0, z])
        mo._save_keyframe(k, empty, empty, empty)
    mo.current_position = np.array([0, 0, 0.5])
    assert mo._surrounding_ids() == list(range(16, 32))  # each place's latest keyframe: the second pass
    # The original averages the indices in each 1 m voxel (quirk 8.5): place j holds keyframes j and j + 16,
    # so it picks j + 8, a keyframe 16 m away from place j.
    original = MapOptimization(PARAMS)
    original.keyframes, original._positions = mo.keyframes, mo._positions
    original.current_position = mo.current_position
    assert original._surrounding_ids() == list(range(8, 24))


def test_surrounding_map_radius_and_recent_modes():
    mo = MapOptimization(PARAMS)
    empty = np.zeros((0, 4), np.float32)
    for k in range(60):
        mo.transform_aft = mo.transform_tobe = np.array([0, 0, 0, 0, 0, 2.0 * k])
        mo._save_keyframe(k, empty, empty, empty)
    mo.current_position = np.array([0, 0, 0.0])
    ids = mo._surrounding_ids()
    assert max(ids) <= 25 and min(ids) == 0  # within 50 m
    verified = MapOptimization(PARAMS.replace(loop_closure__loop_closure_enable_flag=True))
    verified.keyframes, verified._positions, verified.current_position = (
        mo.keyframes,
        mo._positions,
        mo.current_position,
    )
    assert verified._surrounding_ids() == ids  # the verified loop closure keeps the radius
    loop_mode = MapOptimization(
        PARAMS.replace(loop_closure__loop_closure_enable_flag=True, loop_closure__method='original')
    )
    loop_mode.keyframes, loop_mode._positions = mo.keyframes, mo._positions
    assert loop_mode._surrounding_ids() == list(range(10, 60))  # the last 50


def test_map_equals_the_originals_on_golden_data(shared_data):
    """The one-scan pipeline (imageProjection -> featureAssociation -> mapOptimization, as ``lego_loam_py run``
    chains them) maps the original's inputs to the original's /aft_mapped_to_init."""
    params = load_params(default_params_file().parent / 'original.yaml')
    g = np.load(shared_data / 'golden' / 'vlp16_static_indoor_20hz.npz')
    pipeline = Pipeline(params, warn=pytest.fail)
    for k in range(len(g['stamps'])):
        inp = g[f's{k}_input']
        cloud = np.zeros(len(inp), dtype=[('x', np.float32), ('y', np.float32), ('z', np.float32), ('ring', np.uint16)])
        cloud['x'], cloud['y'], cloud['z'], cloud['ring'] = inp[:, 0], inp[:, 1], inp[:, 2], inp[:, 4]
        pipeline.process_scan(cloud, int(g['stamps'][k]))
    mapped = np.array(pipeline.finish().mapped)
    ours = np.array([[*pose[:3, 3], *matrix_to_quaternion(pose[:3, :3])] for pose in mapped])
    theirs = g['aft_mapped_to_init']
    assert ours.shape == theirs.shape
    assert np.abs(ours[:, :3] - theirs[:, :3]).max() < 1e-5
    assert np.abs(np.abs(ours[:, 3:]) - np.abs(theirs[:, 3:])).max() < 1e-6


def test_save_writes_complete_files_atomically(tmp_path):
    from lego_loam_py.formats import read_pcd, read_tum

    scene = room_world(seed=9)
    mo = MapOptimization(PARAMS)
    for k in range(4):
        f = features_of(scene, moved(0.4 * k))
        mo.process(
            k * 400_000_000, np.array([0, 0, 0, 0, 0, 0.4 * k]), f.less_sharp, f.less_flat, np.zeros((0, 4), np.float32)
        )
    written = mo.save(tmp_path)
    assert set(written) == {
        'global_map',
        'corner_map',
        'surface_map',
        'trajectory',
        'trajectory_tum',
        'trajectory_camera_init_tum',
        'map_bundle',
        'map_bundle_data',
        'occupancy_yaml',  # (the 2D occupancy grid, nav2 map_server files: tests/test_occupancy_grid.py)
        'occupancy_image',
    }
    stamps, poses = read_tum(written['trajectory_tum'])
    assert len(stamps) == len(mo.keyframes) == 4
    # REP-103 map axes: the 0.4 m steps along camera z are steps along x.
    assert np.allclose(poses[:, :3, 3], [[0.4 * k, 0, 0] for k in range(4)], atol=0.05)
    points = read_pcd(written['global_map'])
    assert len(points) > 500 and points.shape[1] == 4
    # The floor (1.5 m below the sensor) is at z = -1.5 in the map frame.
    assert abs(np.percentile(points[:, 2], 5) + 1.5) < 0.3
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in written.values())


def test_transform_cloud_is_the_world_convention():
    pose = np.array([0.1, 0.5, -0.2, 1.0, 2.0, 3.0])
    points = cloud([[1.0, 0.0, 0.0], [0.0, 0.0, 5.0]])
    assert np.allclose(
        transform_cloud(points, pose)[:, :3],
        transform_points(pose6_to_matrix(pose), points[:, :3].astype(float)),
        atol=1e-5,
    )


def test_the_pcd_writer_writes_the_bytes_open3d_writes_and_reads(tmp_path):
    """write_pcd_atomic writes binary PCD itself (no 0.8 s open3d import for a fixed header): the same bytes as
    open3d's own writer, for x y z and x y z intensity, NaN and infinity included; read_pcd reads that layout back
    exactly by itself, and leaves every other to open3d."""
    import open3d as o3d

    from lego_loam_py.formats import _read_own_pcd, read_pcd, write_pcd_atomic

    rng = np.random.default_rng(5)
    for columns in (3, 4, 5):
        points = (rng.normal(size=(1000, columns)) * 50).astype(np.float32)
        points[7, 0], points[9, 2] = np.nan, np.inf
        ours = write_pcd_atomic(tmp_path / f'ours{columns}.pcd', points)
        cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(points[:, :3])))
        if columns > 3:
            cloud.point['intensity'] = o3d.core.Tensor(np.ascontiguousarray(points[:, 3:4]))
        assert o3d.t.io.write_point_cloud(str(tmp_path / f'open3d{columns}.pcd'), cloud, write_ascii=False)
        assert ours.read_bytes() == (tmp_path / f'open3d{columns}.pcd').read_bytes()
        expected = points[:, : min(columns, 4)]
        assert np.array_equal(read_pcd(ours), expected, equal_nan=True)  # (read without open3d)
        read_by_open3d = o3d.t.io.read_point_cloud(str(ours)).point['positions'].numpy()
        assert np.array_equal(read_by_open3d, expected[:, :3], equal_nan=True)
        # Any other layout is open3d's to read: ASCII here, and a body shorter than its header says.
        assert o3d.t.io.write_point_cloud(str(tmp_path / f'ascii{columns}.pcd'), cloud, write_ascii=True)
        assert np.allclose(read_pcd(tmp_path / f'ascii{columns}.pcd'), expected, rtol=1e-6, equal_nan=True)
        cut = tmp_path / f'cut{columns}.pcd'
        cut.write_bytes(ours.read_bytes()[:-4])
        assert _read_own_pcd(cut) is None and _read_own_pcd(ours) is not None
    as_float64 = write_pcd_atomic(tmp_path / 'float64.pcd', rng.normal(size=(10, 3)))
    assert read_pcd(as_float64).dtype == np.float32 and read_pcd(as_float64).shape == (10, 3)


def test_an_empty_map_is_saved_as_a_valid_empty_pcd(tmp_path):
    """A save before the first keyframe (or of a map without outliers) writes valid empty files, not none and
    not an error (open3d refuses to write an empty cloud; our writer makes the header in every case)."""
    from lego_loam_py.formats import pcd_is_complete, read_pcd, write_pcd_atomic

    for columns in (3, 4):
        path = write_pcd_atomic(tmp_path / f'empty{columns}.pcd', np.zeros((0, columns), np.float32))
        assert pcd_is_complete(path)
        assert read_pcd(path).shape == (0, columns)
    written = MapOptimization(PARAMS).save(tmp_path / 'map')
    assert all(pcd_is_complete(p) for name, p in written.items() if p.suffix == '.pcd')
    assert read_pcd(written['global_map']).shape == (0, 4)


def _translation(z: float) -> np.ndarray:
    pose = np.eye(4)
    pose[2, 3] = z  # forward, in camera axes
    return pose


def test_odometry_continuity_tells_a_restart_from_motion():
    from lego_loam_py.core.mapping.odometry_continuity import OdometryContinuity

    continuity = OdometryContinuity()
    ns = 100_000_000  # 0.1 s
    # 10 m/s forward, one publisher: motion.
    assert all(continuity.check(k * ns, _translation(float(k)), b'a') is None for k in range(20))
    # 100 m in 0.1 s: no vehicle does that.
    jump = continuity.check(20 * ns, _translation(119.0), b'a')
    assert jump is not None and jump.distance_m == 100.0 and abs(jump.dt_s - 0.1) < 1e-9 and not jump.new_publisher
    assert jump.previous[0] == 19 * ns and jump.older is not None and jump.older[0] == 18 * ns
    # Back at the origin after 3 s (featureAssociation restarted): 119 m in 3 s is plausible motion, the origin is not.
    jump = continuity.check(50 * ns, np.eye(4), b'a')
    assert jump is not None and jump.older is None  # (the pose before the last belonged to the old frame)
    # Another publisher: 0.2 m is motion, 1 m is a restart elsewhere (only the publisher tells).
    assert continuity.check(51 * ns, _translation(0.2), b'b') is None
    jump = continuity.check(52 * ns, _translation(1.2), b'c')
    assert jump is not None and jump.new_publisher and 'featureAssociation restarted)' in jump.describe()
    continuity.forget()
    assert continuity.check(53 * ns, _translation(500.0), b'd') is None


def test_reanchoring_continues_from_the_last_mapped_pose_at_the_last_speed():
    """Odometry and map frames agree (T_aft = T_bef); the odometry drove to z = 10 m at 10 m/s, went away for
    0.5 s and came back at its origin: the next prediction is where the vehicle is now, z = 15 m."""
    from lego_loam_py.core.frames import invert_pose, matrix_to_pose6, pose6_to_matrix
    from lego_loam_py.core.mapping.odometry_continuity import (
        MAX_EXTRAPOLATION_S,
        OdometryContinuity,
        anchored_transform_bef,
    )

    ns = 100_000_000
    continuity = OdometryContinuity()
    continuity.check(99 * ns, _translation(9.0))
    continuity.check(100 * ns, _translation(10.0))
    jump = continuity.check(105 * ns, np.eye(4))
    assert jump is not None
    same = matrix_to_pose6(_translation(10.0))
    bef = anchored_transform_bef(jump, np.eye(4), same, same)
    predicted = pose6_to_matrix(same) @ invert_pose(pose6_to_matrix(bef)) @ np.eye(4)
    np.testing.assert_allclose(predicted, _translation(15.0), atol=1e-9)
    # After a gap longer than MAX_EXTRAPOLATION_S the vehicle is taken to have stopped where it was.
    continuity.check(200 * ns, _translation(3.0))
    continuity.check(210 * ns, _translation(4.0))
    jump = continuity.check(210 * ns + int((MAX_EXTRAPOLATION_S + 1) * 1e9), np.eye(4))
    assert jump is not None
    bef = anchored_transform_bef(jump, np.eye(4), same, same)
    np.testing.assert_allclose(pose6_to_matrix(same) @ invert_pose(pose6_to_matrix(bef)), _translation(4.0), atol=1e-9)
