"""Loop closure: the Scan Context descriptor, the verifying registration and its gates, the pairwise consistency
check, the robust loop factor, and the original's method kept for config/original.yaml."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lego_loam_py.core.frames import make_pose, rot_z
from lego_loam_py.core.loop.closure import LoopCloser, LoopResult, rotation_angle_deg
from lego_loam_py.core.loop.place_recognition import PlaceDatabase, ScanContextConfig, descriptor_distance, scan_context
from lego_loam_py.core.loop.registration import Registration, register
from lego_loam_py.core.mapping.pose_graph import PoseGraph
from lego_loam_py.core.params import Params, default_params_file, load_params
from tests.support.sweeps import room_world, sweep

LC = Params().loop_closure
ON = Params().replace(loop_closure__loop_closure_enable_flag=True)


def xyz(points) -> np.ndarray:
    return np.column_stack([points['x'], points['y'], points['z']]).astype(np.float64)


def lidar_pose(x: float, y: float, yaw_deg: float) -> np.ndarray:
    return make_pose(rot_z(math.radians(yaw_deg)), (x, y, 0.0))


def test_scan_context_cell_of_a_point_by_hand():
    # A point 10 m ahead, 1 m up: ring floor(10 / 50 * 20) = 4, sector floor((0 + pi) / 2 pi * 60) = 30, height
    # 1 + 2 (measured from 2 m below the sensor); a point behind the sensor's own body (0.5 m) is ignored.
    descriptor = scan_context(np.array([[10.0, 0.0, 1.0], [0.5, 0.0, 5.0]]))
    assert descriptor.shape == (20, 60)
    assert descriptor[4, 30] == pytest.approx(3.0)
    assert np.count_nonzero(descriptor) == 1
    # The highest point of a cell wins; below the reference height counts as 0.
    descriptor = scan_context(np.array([[10.0, 0.1, 1.0], [10.2, 0.1, 4.0], [30.0, 0.0, -3.0]]))
    assert descriptor[4, 30] == pytest.approx(6.0) and np.count_nonzero(descriptor) == 1


def test_the_descriptor_recognises_a_place_seen_turned_and_tells_the_turn():
    scene = room_world(seed=3)
    here = scan_context(xyz(sweep(scene, lidar_pose(1.0, 0.5, 0.0))))
    turned = scan_context(xyz(sweep(scene, lidar_pose(1.0, 0.5, 36.0))))  # same place, heading 36 deg left
    elsewhere = scan_context(xyz(sweep(room_world(seed=11), lidar_pose(-8.0, 6.0, 0.0))))
    database = PlaceDatabase()
    database.add(100, here)
    database.add(200, elsewhere)
    best = database.query(turned, count=2)
    assert best[0].key == 100
    assert best[0].distance < 0.5 * best[1].distance
    assert math.degrees(best[0].yaw) == pytest.approx(36.0, abs=6.0)  # within one sector
    # Excluded places are never returned.
    assert [m.key for m in database.query(turned, allowed=np.array([False, True]))] == [200]
    distance, shift = descriptor_distance(here, here[None])
    assert distance[0] == pytest.approx(0.0, abs=1e-6) and shift[0] == 0


def test_registration_recovers_a_known_offset_and_measures_the_fit():
    scene = room_world(seed=3)
    target_pose, source_pose = lidar_pose(0.0, 0.0, 0.0), lidar_pose(1.2, -0.6, 8.0)
    target = xyz(sweep(scene, target_pose, noise=0.01, seed=1))
    source = xyz(sweep(scene, source_pose, noise=0.01, seed=2))
    truth = np.linalg.inv(target_pose) @ source_pose
    start = lidar_pose(0.0, 0.0, 0.0)  # the place only: 1.3 m and 8 deg off
    fit = register(
        source,
        target,
        start,
        LC.registration_distances,
        LC.registration_iterations,
        LC.inlier_distance,
        LC.registration_points,
        LC.min_registration_sigma,
    )
    error = np.linalg.inv(truth) @ fit.pose
    assert np.linalg.norm(error[:3, 3]) < 0.05 and rotation_angle_deg(error) < 0.3
    assert fit.overlap > 0.8 and fit.rmse < LC.max_rmse and fit.constraint > LC.min_constraint
    assert np.all(np.linalg.eigvalsh(fit.information) > 0)


def test_registration_in_a_featureless_corridor_is_flagged_unconstrained():
    scene = room_world(corridor=True)
    target = xyz(sweep(scene, lidar_pose(0.0, 0.0, 0.0), noise=0.01, seed=1))
    source = xyz(sweep(scene, lidar_pose(3.0, 0.0, 0.0), noise=0.01, seed=2))
    fit = register(
        source,
        target,
        np.eye(4),
        LC.registration_distances,
        LC.registration_iterations,
        LC.inlier_distance,
        LC.registration_points,
        LC.min_registration_sigma,
    )
    # Walls, floor and ceiling fit at any shift along the corridor: that direction carries (almost) no
    # information, and the gate says so.
    assert fit.overlap > 0.8
    assert fit.constraint < LC.min_constraint
    along = np.linalg.inv(fit.information)[3, 3]  # variance of x (along the corridor)
    across = np.linalg.inv(fit.information)[4, 4]
    assert along > 10 * across


@pytest.mark.parametrize('misplaced_m', [0.0, 0.4])
def test_a_source_stacked_from_keyframes_that_disagree_is_turned_down(misplaced_m):
    """The registered view stacks the newest keyframe on the ones before it by their mapped poses. When the
    newest one was mapped 0.4 m off (to the side), the fit is a compromise about halfway between, and the
    newest keyframe's points alone would move it about 0.2 m: the gate turns the loop down. The same stack
    without the error passes with next to no shift."""
    from lego_loam_py.core.loop.closure import LoopCandidate

    scene = room_world(seed=3)
    target = xyz(sweep(scene, lidar_pose(0.0, 0.0, 0.0), noise=0.01, seed=1))
    before = xyz(sweep(scene, lidar_pose(0.8, 0.3, 5.0), noise=0.01, seed=2))
    newest = xyz(sweep(scene, lidar_pose(0.8, 0.3, 5.0), noise=0.01, seed=3)) + [0.0, misplaced_m, 0.0]
    source = np.concatenate([before, newest])
    marked = np.arange(len(source)) >= len(before)
    truth = lidar_pose(0.8, 0.3, 5.0)
    fit = register(
        source,
        target,
        np.eye(4),
        LC.registration_distances,
        LC.registration_iterations,
        LC.inlier_distance,
        LC.registration_points,
        LC.min_registration_sigma,
        subset=marked,
    )
    if misplaced_m:
        assert 0.12 < fit.subset_shift_m < 0.3 and fit.subset_shift_m > LC.max_source_shift
    else:
        assert fit.subset_shift_m < 0.03 and fit.subset_shift_deg < 0.2
        assert np.linalg.norm((np.linalg.inv(truth) @ fit.pose)[:3, 3]) < 0.05
    candidate = LoopCandidate(
        5,
        0,
        source,
        target,
        detector='radius',
        initial=np.eye(4),
        graph_relative=truth,
        path_m=100.0,
        latest_stamp_ns=2,
        candidate_stamp_ns=1,
        source_latest=marked,
    )
    result, _ = LoopCloser(ON.loop_closure).verify(candidate)
    assert result.reason.startswith('source inconsistent') == bool(misplaced_m), result.reason
    assert (result.reason == 'verified') == (not misplaced_m)


def verified(latest_stamp: int, candidate_stamp: int) -> LoopResult:
    return LoopResult(
        1,
        0,
        0.05,
        True,
        False,
        np.eye(4),
        reason='verified',
        latest_stamp_ns=latest_stamp,
        candidate_stamp_ns=candidate_stamp,
        information=np.eye(6),
    )


def fitted(pose: np.ndarray) -> Registration:
    return Registration(pose, 0.9, 0.05, 1000, 0.2, np.eye(6))


def test_a_loop_goes_in_once_a_second_one_agrees_with_it():
    """Keyframes along x every metre; the mapper thinks the second pass (stamps 100..) runs 2 m beside the first
    (drift). Loops that say 'the newest keyframe sits 0.2 m beside the old one' agree with each other; a loop
    that says it sits 5 m further along does not."""
    closer = LoopCloser(LC)
    poses = {k: lidar_pose(float(k), 0.0, 0.0) for k in range(10)}
    poses.update({100 + k: lidar_pose(float(k), 2.0, 0.0) for k in range(10)})
    s = 1_000_000_000
    loop_a = verified(101 * s, 1 * s)
    assert (
        closer.consistent(loop_a, fitted(lidar_pose(0.0, 0.2, 0.0)), {k * s: p for k, p in poses.items()}, 101 * s)
        == []
    )  # waits for a second loop
    wrong = verified(103 * s, 3 * s)
    assert (
        closer.consistent(wrong, fitted(lidar_pose(5.0, 0.2, 0.0)), {k * s: p for k, p in poses.items()}, 103 * s) == []
    )
    loop_b = verified(105 * s, 5 * s)
    ready = closer.consistent(loop_b, fitted(lidar_pose(0.0, 0.2, 0.0)), {k * s: p for k, p in poses.items()}, 105 * s)
    assert [p.result for p in ready] == [loop_a, loop_b]
    # A third loop that agrees with those in the graph goes in at once.
    loop_c = verified(107 * s, 7 * s)
    assert [
        p.result
        for p in closer.consistent(
            loop_c, fitted(lidar_pose(0.0, 0.2, 0.0)), {k * s: p for k, p in poses.items()}, 107 * s
        )
    ] == [loop_c]


def chain_graph(steps: int, step_m: float) -> tuple[PoseGraph, list[np.ndarray]]:
    graph = PoseGraph(Params().map_optimization)
    poses = [lidar_pose(step_m * k, 0.0, 0.0) for k in range(steps)]
    from lego_loam_py.core.frames import lidar_pose_to_camera, matrix_to_pose6

    six = [matrix_to_pose6(lidar_pose_to_camera(p)) for p in poses]
    graph.add_keyframe(0, six[0])
    for k in range(1, steps):
        graph.add_keyframe(k, six[k], previous6=six[k - 1])
    return graph, poses


@pytest.mark.parametrize('kernel, bent', [('huber', False), ('none', True)])
def test_one_wrong_loop_cannot_bend_a_short_stiff_chain_under_the_robust_kernel(kernel, bent):
    """A 20-keyframe straight chain (6 m) gets one loop saying its end sits 3 m to the side of its start: under
    the Huber kernel the pull is bounded and the chain stays within centimetres of the odometry; without a
    kernel the same constraint drags it (measured: 0.008 m with Huber, 0.43 m without)."""
    from lego_loam_py.core.frames import camera_pose_to_lidar, pose6_to_matrix

    graph, poses = chain_graph(20, 0.3)
    wrong = np.linalg.inv(poses[0]) @ lidar_pose(poses[-1][0, 3], 3.0, 0.0)  # end in the start's frame
    information = np.diag([1e4, 1e4, 1e4, 1e3, 1e3, 1e3])  # 1 cm rad / 3 cm
    graph.add_loop_constraint(0, 19, wrong, information, kernel, LC.robust_kernel_width)
    end = camera_pose_to_lidar(pose6_to_matrix(graph.poses([19])[0]))
    moved = abs(end[1, 3])
    assert (moved > 0.3) if bent else (moved < 0.05)


def test_a_right_loop_closes_a_long_drifted_chain_under_the_robust_kernel():
    """200 keyframes 1 m apart around a square whose odometry over-turns by 0.5 deg per corner-turn keyframe:
    the truth's loop (the last keyframe is back at the first) pulls the end back despite the kernel."""
    from lego_loam_py.core.frames import camera_pose_to_lidar, lidar_pose_to_camera, matrix_to_pose6, pose6_to_matrix

    truth, belief = [np.eye(4)], [np.eye(4)]
    for k in range(1, 200):
        turn = 90.0 if k % 50 == 0 else 0.0
        step = make_pose(rot_z(math.radians(turn)), (1.0, 0.0, 0.0))
        noisy = make_pose(rot_z(math.radians(turn + (2.0 if turn else 0.0))), (1.0, 0.0, 0.0))
        truth.append(truth[-1] @ step)
        belief.append(belief[-1] @ noisy)
    graph = PoseGraph(Params().map_optimization)
    six = [matrix_to_pose6(lidar_pose_to_camera(p)) for p in belief]
    graph.add_keyframe(0, six[0])
    for k in range(1, 200):
        graph.add_keyframe(k, six[k], previous6=six[k - 1])
    before = np.linalg.norm(belief[-1][:3, 3] - truth[-1][:3, 3])
    relative = np.linalg.inv(truth[0]) @ truth[-1]  # the last keyframe in the first's frame
    graph.add_loop_constraint(
        0, 199, relative, np.diag([1e4, 1e4, 1e4, 1e3, 1e3, 1e3]), 'huber', LC.robust_kernel_width
    )
    end = camera_pose_to_lidar(pose6_to_matrix(graph.poses([199])[0]))
    after = np.linalg.norm(end[:3, 3] - truth[-1][:3, 3])
    assert before > 3.0 and after < 0.1 * before


def test_the_verified_method_is_the_default_and_original_yaml_keeps_the_originals():
    default = Params().loop_closure
    assert default.loop_closure_enable_flag and default.method == 'verified'  # on by default
    original = load_params(default_params_file().parent / 'original.yaml').loop_closure
    assert not original.loop_closure_enable_flag and original.method == 'original'
    assert (
        original.history_keyframe_search_radius,
        original.history_keyframe_fitness_score,
        original.icp_max_correspondence_distance,
    ) == (7.0, 0.3, 100.0)


def test_scan_context_config_follows_the_parameters():
    closer = LoopCloser(
        Params().replace(loop_closure__scan_context_rings=10, loop_closure__scan_context_sectors=36).loop_closure
    )
    assert closer.places.config == ScanContextConfig(rings=10, sectors=36, max_radius=50.0)


def test_loop_markers_join_the_keyframes_of_each_accepted_loop():
    from std_msgs.msg import Header

    from lego_loam_py.ros.map_optimization_node import loop_markers

    positions = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.5, 0.0], [0.2, 0.1, 30.0]])
    markers = loop_markers(Header(frame_id='camera_init'), positions, [(3, 0), (2, 1)]).markers
    clear, lines, ends = markers
    assert clear.action == clear.DELETEALL and lines.type == lines.LINE_LIST and ends.type == ends.SPHERE_LIST
    assert [(p.x, p.y, p.z) for p in lines.points] == [
        (0.2, 0.1, 30.0),
        (0.0, 0.0, 0.0),
        (2.0, 0.5, 0.0),
        (1.0, 0.0, 0.0),
    ]
    assert all(m.header.frame_id == 'camera_init' for m in markers)


def drive_around_the_yard(drift_deg_per_m: float, laps: float = 1.25):
    """Keyframes 1 m apart around a 24 x 16 m rectangle in the yard of room_world (its walls and boxes), one
    per second, as a mapper that over-turns by ``drift_deg_per_m`` would place them; returns the mapper-to-be's
    inputs: (stamps [ns], true poses, drifted poses (4x4, lidar axes), clouds (camera axes, sensor frame))."""
    from lego_loam_py.core.frames import lidar_to_camera
    from lego_loam_py.core.voxel import voxel_downsample

    scene = room_world(seed=5)
    corners = np.array([[-12.0, -8.0], [12.0, -8.0], [12.0, 8.0], [-12.0, 8.0]])
    path = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        n = int(round(np.linalg.norm(b - a)))
        path += [a + (b - a) * k / n for k in range(n)]
    path = np.array(path)
    count = int(laps * len(path))
    heading = np.arctan2(*(np.roll(path, -1, axis=0) - path)[:, ::-1].T)
    truth, drifted, clouds = [], [], []
    belief = lidar_pose(*path[0], math.degrees(heading[0]))
    for k in range(count):
        pose = lidar_pose(*path[k % len(path)], math.degrees(heading[k % len(path)]))
        if k:  # the true motion since the last keyframe, over-turned
            step = np.linalg.inv(truth[-1]) @ pose
            belief = belief @ make_pose(rot_z(math.radians(drift_deg_per_m)), (0, 0, 0)) @ step
        truth.append(pose)
        drifted.append(belief.copy())
        points = xyz(sweep(scene, pose, noise=0.01, seed=k))
        cloud = np.column_stack([lidar_to_camera(points), np.zeros(len(points))]).astype(np.float32)
        clouds.append(voxel_downsample(cloud, 0.3))
    return np.arange(count, dtype=np.int64) * 1_000_000_000, truth, drifted, clouds


def test_a_drifted_lap_of_the_yard_is_closed_with_right_loops_only():
    """1.25 laps with 0.05 deg/m of yaw drift: back at the start the mapper is ~1 m off. Loops found and verified
    on the way take out most of the newest keyframe's error (the drift after the last loop stays), and every
    accepted loop's constraint is within 0.1 m / 0.5 deg of the true relative pose, while the places that look
    alike across the small yard (descriptor distances 0.19-0.29) are left out by the drift bound."""
    from lego_loam_py.core.frames import camera_pose_to_lidar, lidar_pose_to_camera, matrix_to_pose6, pose6_to_matrix
    from lego_loam_py.core.mapping.map_optimization import MapOptimization

    stamps, truth, drifted, clouds = drive_around_the_yard(0.05)
    mapper = MapOptimization(ON)
    empty = np.zeros((0, 4), np.float32)
    for k, (stamp, pose, cloud) in enumerate(zip(stamps, drifted, clouds)):
        if k:  # the mapper's own motion since its last keyframe (it keeps any correction a loop made)
            step = np.linalg.inv(drifted[k - 1]) @ pose
            mapper.transform_aft = matrix_to_pose6(
                pose6_to_matrix(mapper.keyframes[-1].pose6) @ lidar_pose_to_camera(step)
            )
        else:
            mapper.transform_aft = mapper.transform_tobe = matrix_to_pose6(lidar_pose_to_camera(pose))
        mapper.latest_odometry_ns = int(stamp)
        assert mapper._save_keyframe(int(stamp), empty, cloud, empty)
        candidate = mapper.detect_loop()
        if candidate is not None:
            mapper.close_loop(candidate)
    error_before = np.linalg.norm(drifted[-1][:3, 3] - truth[-1][:3, 3])
    newest = camera_pose_to_lidar(pose6_to_matrix(mapper.keyframes[-1].pose6))
    # Both trajectories start at the first keyframe's true pose: compare directly.
    error_after = np.linalg.norm(newest[:3, 3] - truth[-1][:3, 3])
    accepted = [loop for loop in mapper.loops if loop.accepted]
    assert error_before > 0.8
    assert len(accepted) >= 2 and error_after < 0.25 * error_before
    # Places alike 15-28 m from the graph's estimate were never registered: beyond the drift the path allows.
    assert mapper.loop_method.closer.too_far > 0
    for loop in accepted:
        true_relative = np.linalg.inv(truth[loop.latest]) @ truth[loop.candidate]
        error = np.linalg.inv(true_relative) @ camera_pose_to_lidar(loop.relative)
        assert np.linalg.norm(error[:3, 3]) < 0.1 and rotation_angle_deg(error) < 0.5


def test_the_summary_lists_accepted_loops_and_counts_why_others_were_turned_down():
    from lego_loam_py.results import LoopClosures

    s = 1_000_000_000
    accepted = LoopResult(
        83,
        3,
        0.027,
        True,
        True,
        np.eye(4),
        detector='scan_context',
        score=0.004,
        overlap=0.99,
        reason='accepted',
        latest_stamp_ns=183 * s,
        candidate_stamp_ns=103 * s,
        correction_m=0.79,
        correction_deg=3.95,
        applied_m=0.75,
    )
    drifted = LoopResult(40, 0, 0.05, True, False, np.eye(4), reason='correction 28.62 m beyond the drift')
    unconfirmed = LoopResult(50, 1, 0.05, True, False, np.eye(4), reason='pending')
    loops = LoopClosures.of([drifted, accepted, unconfirmed], first_stamp_ns=100 * s)
    assert (loops.accepted, loops.rejected) == (1, 2)
    assert loops.rejected_because == {'correction': 1, 'pending': 1}
    (entry,) = loops.loops
    assert entry['time_s'] == 83.0 and (entry['latest'], entry['candidate']) == (83, 3)
    assert entry['detector'] == 'scan_context' and entry['correction_m'] == 0.79
    lines = loops.lines()
    assert lines[0] == 'loop closures: 1 accepted, 2 rejected (correction 1, pending 1)'
    assert 'keyframe 83 -> 3 (scan_context, score 0.004)' in lines[1] and 'correction 0.790 m / 3.95 deg' in lines[1]


def test_the_original_method_is_kept_radius_candidate_icp_and_fitness_variances():
    """method: original (what config/original.yaml selects when loop closure is switched on): the nearest old
    keyframe within 7 m, point-to-point ICP, accepted on its fitness, variances = fitness on all six axes."""
    from lego_loam_py.core.frames import lidar_pose_to_camera, matrix_to_pose6
    from lego_loam_py.core.mapping.map_optimization import MapOptimization

    stamps, truth, _, clouds = drive_around_the_yard(0.0, laps=1.1)
    mapper = MapOptimization(ON.replace(loop_closure__method='original'))
    empty = np.zeros((0, 4), np.float32)
    for stamp, pose, cloud in zip(stamps, truth, clouds):
        mapper.transform_aft = mapper.transform_tobe = matrix_to_pose6(lidar_pose_to_camera(pose))
        mapper.latest_odometry_ns = int(stamp)
        mapper.current_position = mapper.transform_aft[3:].copy()
        mapper._save_keyframe(int(stamp), cloud, cloud, empty)
    candidate = mapper.detect_loop()
    assert candidate is not None and candidate.latest == len(stamps) - 1
    assert np.linalg.norm(mapper._positions[candidate.candidate] - mapper._positions[candidate.latest]) <= 7.0
    loop = mapper.close_loop(candidate)
    assert loop.accepted and loop.fitness <= 0.3
    np.testing.assert_array_equal(loop.variances, np.full(6, loop.fitness))


def test_the_optimized_trajectory_moves_each_pose_with_its_last_keyframe():
    """Keyframes at 1 s and 3 s at x = 1 and 3 m; the graph later moved the second by 0.5 m along y. Poses before
    the second keyframe stay (the first keyframe is the graph's anchor), from 3 s on they follow the second."""
    from types import SimpleNamespace

    from lego_loam_py.core.frames import camera_pose_to_lidar, lidar_pose_to_camera, matrix_to_pose6
    from lego_loam_py.core.pipeline import RunResult

    s = 1_000_000_000
    camera = [lidar_pose_to_camera(lidar_pose(x, 0.0, 0.0)) for x in (0.5, 1.0, 2.0, 3.0, 3.5)]
    # (the first mapping step has no map yet: it publishes the identity, while its keyframe sits at the odometry)
    record = RunResult(
        stamps=[0, 1 * s, 2 * s, 3 * s, 4 * s],
        integrated=camera,
        mapped_stamps=[1 * s, 3 * s],
        mapped=[np.eye(4), camera[3]],
    )
    moved = lidar_pose_to_camera(lidar_pose(3.0, 0.5, 0.0))
    record.mapper = SimpleNamespace(
        builds_map=True,
        keyframes=[
            SimpleNamespace(stamp_ns=1 * s, pose6=matrix_to_pose6(camera[1])),
            SimpleNamespace(stamp_ns=3 * s, pose6=matrix_to_pose6(moved)),
        ],
    )
    stamps, poses = record.optimized_trajectory()
    assert list(stamps) == [0, s, 2 * s, 3 * s, 4 * s]
    np.testing.assert_allclose(
        poses[:, :3, 3], [[0.5, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0.5, 0], [3.5, 0.5, 0]], atol=1e-9
    )
    assert np.allclose(camera_pose_to_lidar(camera[0]), poses[0])


def test_the_loop_clouds_for_rviz_are_put_into_the_world():
    """/history_cloud is the candidate's map in camera_init, /corrected_cloud the newest keyframes where the
    registration put them: a candidate at 10 m forward, the newest keyframe found 2 m further (lidar axes)."""
    from types import SimpleNamespace

    from lego_loam_py.core.frames import lidar_pose_to_camera, lidar_to_camera
    from lego_loam_py.ros.map_optimization_node import loop_cloud_in_world

    params = Params().replace(loop_closure__loop_closure_enable_flag=True)
    candidate = SimpleNamespace(
        candidate_pose=lidar_pose_to_camera(lidar_pose(10.0, 0.0, 0.0)),
        target=np.array([[1.0, 0.0, 0.0]]),
        source=np.array([[1.0, 0.0, 0.0]]),
    )
    result = SimpleNamespace(relative=lidar_pose_to_camera(np.linalg.inv(lidar_pose(2.0, 0.0, 0.0))))
    from lego_loam_py.core.loop.methods import make_loop_method

    method = make_loop_method(params.loop_closure)
    target = loop_cloud_in_world(candidate, method, 'target')
    corrected = loop_cloud_in_world(candidate, method, 'corrected', result)
    np.testing.assert_allclose(target[:, :3], lidar_to_camera(np.array([[11.0, 0.0, 0.0]])), atol=1e-6)
    np.testing.assert_allclose(corrected[:, :3], lidar_to_camera(np.array([[13.0, 0.0, 0.0]])), atol=1e-6)


def test_the_result_lines_give_the_optimised_accuracy_after_the_published_one():
    from lego_loam_py.evaluation import TrajectoryMetrics
    from lego_loam_py.outputs import result_lines
    from lego_loam_py.results import RunOutputs

    def metrics(ate: float) -> TrajectoryMetrics:
        return TrajectoryMetrics(100, 50.0, ate, ate, ate, ate, 1.0, 10.0, 0.1, 0.2, 0.4, 0.5)

    lines = result_lines(
        RunOutputs(trajectory_length_m=50.0, poses=100, accuracy=metrics(0.2), accuracy_optimized=metrics(0.1))
    )
    assert lines[1].startswith('accuracy vs ground truth: ATE RMSE 0.200 m')
    assert lines[2].startswith('  after the loop closures (trajectory_optimized.tum): ATE RMSE 0.100 m')
    assert len(lines) == 3
