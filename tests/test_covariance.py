"""Pose covariances (core.frames, core.odometry.covariance, core.mapping.covariance, transformFusion): hand-checkable
geometry and chains, and that the three odometry topics carry finite, symmetric, positive-definite covariances.

Tolerances: closed forms of linear chains to 1e-9 relative (float64 rounding); numeric derivatives (forward
differences of step 1e-7) to 1e-6; the information of a registration against a noisy plane to 30 % of N/σ² (N of
about a thousand points: the estimate of σ² from the residuals has a relative spread of ~5 %, the weights and the
fitted planes add a little); iSAM2's marginals to 1e-4 relative (1e-8 absolute: the
keyframes' 1e-10 rotation variances at metres of lever)."""

from __future__ import annotations

import numpy as np
import pytest

from lego_loam_py.core.frames import (
    MAX_VARIANCE,
    bounded_covariance,
    compound_covariance,
    covariance_from_information,
    euler_to_matrix,
    make_pose,
    pose6_to_matrix,
    pose_error,
    pose_jacobian,
    relative_covariance,
    rot_y,
)
from lego_loam_py.core.params import Params

PARAMS = Params()


def is_covariance(matrix: np.ndarray) -> bool:
    """Finite, symmetric and positive definite."""
    matrix = np.asarray(matrix, dtype=float)
    return (
        matrix.shape == (6, 6)
        and bool(np.isfinite(matrix).all())
        and np.allclose(matrix, matrix.T, rtol=0, atol=1e-12 * max(1.0, np.abs(matrix).max()))
        and float(np.linalg.eigvalsh(matrix).min()) > 0
    )


# ------------------------------------------------------------------------------------------------ core.frames
def test_a_yaw_uncertainty_swings_the_position_across_the_travel():
    """A pose with only a rotation variance σ² about the vertical (camera y), followed by a motion of L metres
    forward (camera z): the position variance across the travel (camera x) is L² σ², along it nothing."""
    sigma2, length = 1e-4, 10.0
    parent = np.zeros((6, 6))
    parent[4, 4] = sigma2
    relative = make_pose(translation=[0.0, 0.0, length])
    out = compound_covariance(np.eye(4), parent, relative, np.zeros((6, 6)))
    assert out[0, 0] == pytest.approx(length**2 * sigma2, rel=1e-9)
    assert out[2, 2] == 0.0 and out[1, 1] == 0.0
    assert out[0, 4] == pytest.approx(length * sigma2, rel=1e-9)  # (x moves with the yaw error)
    assert out[4, 4] == sigma2


def test_a_chain_of_equal_steps_grows_its_variance_with_the_distance():
    """n steps of 1 m forward, each with an independent translation variance s² on every axis and no rotation
    error: the end's position variance is n s² on every axis (a random walk), and turning the chain's parent
    rotates that covariance with it."""
    s2, n = 4e-4, 25
    step = make_pose(translation=[0.0, 0.0, 1.0])
    step_covariance = np.diag([s2, s2, s2, 0.0, 0.0, 0.0])
    pose, covariance = np.eye(4), np.zeros((6, 6))
    traces = []
    for _ in range(n):
        covariance = compound_covariance(pose, covariance, step, step_covariance)
        pose = pose @ step
        traces.append(np.trace(covariance))
    np.testing.assert_allclose(np.diag(covariance)[:3], n * s2, rtol=1e-9)
    assert np.all(np.diff(traces) > 0)
    # An anisotropic step covariance (large along the travel, z) seen from a parent yawed 90 deg: along x.
    anisotropic = np.diag([1e-6, 1e-6, 1e-2, 0.0, 0.0, 0.0])
    turned = make_pose(rot_y(np.pi / 2))
    out = compound_covariance(turned, np.zeros((6, 6)), step, anisotropic)
    assert out[0, 0] == pytest.approx(1e-2, rel=1e-9) and out[2, 2] == pytest.approx(1e-6, rel=1e-9)


def test_the_relative_covariance_undoes_the_compounding():
    rng = np.random.default_rng(3)
    a = pose6_to_matrix([0.1, -0.4, 0.2, 3.0, -1.0, 7.0])
    d = pose6_to_matrix([-0.05, 0.3, 0.02, 0.5, 0.1, 2.0])
    m = rng.normal(size=(6, 6))
    cov_a, cov_d = m @ m.T * 1e-3, np.diag([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 3e-5])
    cov_b = compound_covariance(a, cov_a, d, cov_d)
    np.testing.assert_allclose(relative_covariance(a, cov_a, a @ d, cov_b), cov_d, rtol=1e-6, atol=1e-12)


def test_the_pose_jacobian_of_a_six_vector():
    """At a general pose the derivative of the parent-frame error of ``pose6_to_matrix`` with respect to the
    translation part is the identity, and the rotation columns are those of ``R = Ry Rx Rz`` (the derivative with
    respect to ry is a turn about the parent's y axis)."""
    pose6 = np.array([0.2, -0.7, 0.3, 1.0, 2.0, 3.0])
    jacobian = pose_jacobian(pose6_to_matrix, pose6)
    np.testing.assert_allclose(jacobian[:3, 3:], np.eye(3), atol=1e-6)
    np.testing.assert_allclose(jacobian[:3, :3], 0.0, atol=1e-6)
    np.testing.assert_allclose(jacobian[3:, 1], [0.0, 1.0, 0.0], atol=1e-6)
    # Finite differences of the error itself agree.
    delta = np.array([1e-5, 0, 0, 0, 0, 0])
    error = pose_error(pose6_to_matrix(pose6), pose6_to_matrix(pose6 + delta))
    np.testing.assert_allclose(error, jacobian @ delta, atol=1e-9)
    assert np.allclose(euler_to_matrix(*pose6[:3]), pose6_to_matrix(pose6)[:3, :3])


def test_bounds_keep_a_covariance_finite_symmetric_and_positive_definite():
    assert is_covariance(bounded_covariance(np.zeros((6, 6))))
    assert is_covariance(bounded_covariance(np.diag([1.0, -1.0, 0, 0, 0, 1e30])))
    assert np.array_equal(bounded_covariance(np.full((6, 6), np.nan)), np.eye(6) * MAX_VARIANCE)
    # A degenerate direction of the information: large, not infinite, variance along it.
    information = np.diag([1e4, 1e4, 0.0, 1e4, 1e4, 1e4])
    covariance = covariance_from_information(information, max_variance=2.0)
    assert is_covariance(covariance) and covariance[2, 2] == pytest.approx(2.0) and covariance[0, 0] == 1e-4


# ------------------------------------------------------------------------------------- scan-to-map geometry
def plane_points(rng, normal_axis: int, offset: float, spans, step: float, noise: float = 0.0):
    """Points on the plane ``x[normal_axis] = offset`` (camera axes) over ``spans`` of the two other axes."""
    others = [k for k in range(3) if k != normal_axis]
    u, v = np.meshgrid(np.arange(*spans[0], step), np.arange(*spans[1], step))
    out = np.zeros((u.size, 4), dtype=np.float32)
    out[:, others[0]], out[:, others[1]] = u.ravel(), v.ravel()
    out[:, normal_axis] = offset + (rng.normal(0, noise, u.size) if noise else 0.0)
    return out


def register(planes_map, planes_scan):
    """Scan-to-map registration at the true pose (identity) and its covariance (camera_init axes)."""
    from lego_loam_py.core.gauss_newton import DegeneracyProjection
    from lego_loam_py.core.mapping.covariance import registration_covariance
    from lego_loam_py.core.mapping.scan_to_map import register_scan_to_map

    corner = np.array([[20.0, y, 20.0, 0.0] for y in np.arange(-1.0, 2.0, 0.1)], dtype=np.float32)  # (unused)
    surf_map, surf_scan = np.concatenate(planes_map), np.concatenate(planes_scan)
    params = PARAMS.replace(map_optimization__min_correspondences=10)
    pose, counts = register_scan_to_map(
        corner, surf_map, corner[:0], surf_scan, np.zeros(6), params, DegeneracyProjection(6)
    )
    return pose, counts, registration_covariance(pose, counts.information)


def test_three_orthogonal_planes_hold_every_direction():
    """A floor, a side wall and a front wall (camera axes: y up, x left, z forward), the scan with 1 cm of noise
    across each plane: every direction is held, each variance tiny, and the translation's variance across a plane
    is N/σ² of the floor's N points."""
    from lego_loam_py.core.mapping.covariance import MAX_REGISTRATION_VARIANCE

    rng = np.random.default_rng(0)
    spans = {1: ((-3, 3), (2, 8)), 0: ((-1.5, 1.5), (2, 8)), 2: ((-3, 3), (-1.5, 1.5))}
    offsets = {1: -1.5, 0: 3.0, 2: 8.0}
    planes_map = [plane_points(rng, axis, offsets[axis], spans[axis], 0.1) for axis in (1, 0, 2)]
    planes_scan = [plane_points(rng, axis, offsets[axis], spans[axis], 0.2, noise=0.01) for axis in (1, 0, 2)]
    _, counts, covariance = register(planes_map, planes_scan)
    assert is_covariance(covariance) and not counts.degenerate
    values = np.linalg.eigvalsh(covariance)
    assert values.max() < 1e-5 < MAX_REGISTRATION_VARIANCE
    assert values.max() / values.min() < 1e3  # well conditioned (m² and rad² at some metres' lever)
    # Only the floor's N points hold the height (ty) on their own: its information is N / σ² with σ = 1 cm (the
    # marginal variance is larger, the height sharing the floor with the tilts, whose lever is metres).
    n_floor = len(planes_scan[0])
    assert counts.information[4, 4] == pytest.approx(n_floor / 1e-4, rel=0.3)
    assert covariance[1, 1] > 1e-4 / n_floor


def test_a_single_plane_or_a_corridor_leaves_the_unheld_directions_large():
    """Only a floor: the position along it (x, z), and the turn about its normal (rot y) are not held and get the
    registration's bound; the height and the two tilts stay small. A corridor (floor, two walls, ceiling along z):
    the largest-variance direction is the corridor's axis."""
    from lego_loam_py.core.mapping.covariance import MAX_REGISTRATION_VARIANCE

    rng = np.random.default_rng(1)
    floor_map = plane_points(rng, 1, -1.5, ((-4, 4), (-4, 8)), 0.1)
    floor_scan = plane_points(rng, 1, -1.5, ((-4, 4), (-4, 8)), 0.25, noise=0.01)
    _, counts, covariance = register([floor_map], [floor_scan])
    assert is_covariance(covariance) and counts.degenerate
    for k in (0, 2, 4):  # x, z, rot y
        assert covariance[k, k] == pytest.approx(MAX_REGISTRATION_VARIANCE, rel=1e-3)
    for k in (1, 3, 5):  # y, rot x, rot z
        assert covariance[k, k] < 1e-5

    # The map runs 10 m beyond the scan at both ends: no end of the corridor in sight.
    planes = [(1, -1.5, (-1.9, 1.9)), (1, 1.5, (-1.9, 1.9)), (0, -2.0, (-1.4, 1.4)), (0, 2.0, (-1.4, 1.4))]
    corridor_map = [plane_points(rng, axis, offset, (across, (-16, 16)), 0.1) for axis, offset, across in planes]
    corridor_scan = [
        plane_points(rng, axis, offset, (across, (-6, 6)), 0.25, noise=0.01) for axis, offset, across in planes
    ]
    _, counts, covariance = register(corridor_map, corridor_scan)
    values, vectors = np.linalg.eigh(covariance[:3, :3])
    assert abs(vectors[2, 2]) > 0.999  # the principal axis is z, the corridor's
    assert values[2] > 100 * values[1] and values[1] < 1e-5  # (neighbourhoods fitted across grid rows tilt a little)


# ----------------------------------------------------------------------------------------- the odometry's
def test_a_sweep_motion_covariance_is_the_parameters_turned_into_the_motion():
    """At θ = 0 the motion T(θ)⁻¹ moves by -t and turns by -r: the motion's covariance is the parameters'
    (rotation and translation blocks swapped into ROS order), the variances scaled by ``scale``; the IMU prior adds
    its information to the rotations, unscaled (the scale is of the points' residuals); no registration: the
    per-sweep bound."""
    from lego_loam_py.core.odometry.covariance import MAX_MOTION_VARIANCE, motion_covariance

    variances = np.array([1e-6, 2e-6, 3e-6, 1e-4, 2e-4, 3e-4])  # rx, ry, rz, tx, ty, tz
    out = motion_covariance(np.zeros(6), np.diag(1 / variances), scale=4.0)
    np.testing.assert_allclose(np.diag(out), 4.0 * np.concatenate([variances[3:], variances[:3]]), rtol=1e-6)
    prior = np.diag([1e6, 1e6, 1e6, 0, 0, 0])
    out = motion_covariance(np.zeros(6), np.diag(1 / variances), prior_information=prior, scale=2.0)
    assert out[3, 3] == pytest.approx(1 / (1e6 / 2 + 1e6), rel=1e-6) and out[0, 0] == pytest.approx(2e-4, rel=1e-6)
    assert np.array_equal(motion_covariance(np.zeros(6), None), np.eye(6) * MAX_MOTION_VARIANCE)


def test_what_the_registration_cannot_see_grows_with_the_turn_the_speed_change_and_the_speed():
    """The deskewing's errors (core.odometry.covariance.unmodelled_covariance), each a standard deviation per
    axis: ``turn |t| |φ|`` and ``stamp_jitter |t| / period`` for the position, ``change |Δt|`` for the change of the
    motion since the last sweep; the rotation's change counts only without a gyro."""
    from lego_loam_py.core.frames import make_pose, rot_y
    from lego_loam_py.core.odometry.covariance import unmodelled_covariance

    straight = make_pose(None, [0.0, 0.0, 0.5])
    turning = make_pose(rot_y(0.1), [0.0, 0.0, 0.5])
    assert np.array_equal(unmodelled_covariance(straight, None, True, 0.1, 0.5, 0.5, 0.0), np.zeros((6, 6)))
    out = unmodelled_covariance(turning, None, True, 0.1, 0.5, 0.0, 0.0)
    np.testing.assert_allclose(np.diag(out), [(0.5 * 0.5 * 0.1) ** 2] * 3 + [0.0] * 3, rtol=1e-9)
    out = unmodelled_covariance(straight, None, True, 0.1, 0.0, 0.0, 0.001)
    np.testing.assert_allclose(np.diag(out)[:3], [(0.5 * 0.01) ** 2] * 3, rtol=1e-9)
    slower = make_pose(None, [0.0, 0.0, 0.4])
    out = unmodelled_covariance(straight, slower, True, 0.1, 0.0, 0.5, 0.0)
    np.testing.assert_allclose(np.diag(out), [(0.5 * 0.1) ** 2] * 3 + [0.0] * 3, rtol=1e-9)
    with_gyro = unmodelled_covariance(turning, straight, True, 0.1, 0.0, 0.5, 0.0)
    without = unmodelled_covariance(turning, straight, False, 0.1, 0.0, 0.5, 0.0)
    assert np.all(np.diag(with_gyro)[3:] == 0.0)
    np.testing.assert_allclose(np.diag(without)[3:], [(0.5 * 0.1) ** 2] * 3, rtol=1e-9)


def test_the_odometry_covariance_grows_along_the_campus_and_the_mapped_one_stays_bounded(tmp_path):
    """The offline pipeline on the first 4 s of bags/campus_8s: every published covariance is finite, symmetric and
    positive definite once bounded (core.frames.bounded_covariance, what the messages carry); the odometry's
    position variance grows with the distance, the mapped pose's stays below the odometry's by the end, and the
    trajectories are those of a run that never looks at the covariances."""
    from lego_loam_py.offline import run_bag
    from tests.support.inprocess import CAMPUS

    result = run_bag(CAMPUS, PARAMS, progress=False, max_scans=40, mapping_thread=False)
    assert len(result.odometry_covariance) >= 30 and len(result.mapped_covariance) >= 5
    for covariance in result.odometry_covariance + result.integrated_covariance + result.mapped_covariance:
        assert is_covariance(bounded_covariance(covariance))
    position = np.array([np.trace(c[:3, :3]) for c in result.odometry_covariance])
    assert np.all(np.diff(position) >= 0) and position[-1] > 2 * position[5]
    assert np.trace(result.mapped_covariance[-1][:3, :3]) < position[-1]
    assert all(m is not None for m in result.motion_covariance)


def test_the_mapped_covariance_adds_what_the_odometry_covariance_grew_by_since_the_last_input():
    """map_optimization.covariance_deskew: the mapped pose's covariance is the registration's and the map's plus
    what the odometry's pose covariance grew by since the previous mapping input (the sweeps whose motion estimate
    deskewed the scan). Against a run with covariance_deskew 0 on the first 4 s of bags/campus_8s: the same poses,
    and each mapped covariance larger by a rotated copy of core.frames.relative_covariance of the odometry
    covariances skip_frame_num + 1 sweeps apart (same trace, rtol 1e-6: the rotation keeps the trace)."""
    from lego_loam_py.core.params.validation import params_from_mapping
    from lego_loam_py.offline import run_bag
    from tests.support.inprocess import CAMPUS

    assert PARAMS.map_optimization.covariance_deskew == 1.0
    with_term = run_bag(CAMPUS, PARAMS, progress=False, max_scans=40, mapping_thread=False)
    without = params_from_mapping({'map_optimization.covariance_deskew': 0.0})
    plain = run_bag(CAMPUS, without, progress=False, max_scans=40, mapping_thread=False)
    np.testing.assert_array_equal(np.asarray(with_term.mapped), np.asarray(plain.mapped))
    index = {stamp: i for i, stamp in enumerate(with_term.stamps)}
    apart = PARAMS.feature_association.skip_frame_num + 1
    odometry, covariance = with_term.odometry, with_term.odometry_covariance
    checked = 0
    for stamp, mapped, base in zip(with_term.mapped_stamps, with_term.mapped_covariance, plain.mapped_covariance):
        added = mapped - base
        assert float(np.linalg.eigvalsh(added).min()) > -1e-12
        i = index.get(stamp, 0)
        if i >= apart:
            grown = relative_covariance(odometry[i - apart], covariance[i - apart], odometry[i], covariance[i])
            np.testing.assert_allclose(np.trace(added), np.trace(grown), rtol=1e-6)
            assert np.trace(added) > 1.001 * np.trace(with_term.motion_covariance[i])  # (more than the last sweep)
            checked += 1
    assert checked >= 5


def test_the_sweep_covariance_is_what_the_odometry_covariance_grew_by_in_the_map_axes():
    """core.mapping.covariance.SweepCovariance on a compounded chain: each step's covariance back (rtol 1e-9),
    turned into the axes of the map where the sweep ended at a pose off the odometry by a drift rotation; unknown
    covariances and a restart give zeros."""
    from lego_loam_py.core.frames import rotate_covariance
    from lego_loam_py.core.mapping.covariance import SweepCovariance

    step = make_pose(euler_to_matrix(0.01, 0.05, -0.02), [0.1, 0.0, 1.0])
    step_covariance = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6]) + 1e-7
    drift = make_pose(euler_to_matrix(0.0, 0.3, 0.0), [1.0, 2.0, 3.0])  # map from odometry
    sweeps = SweepCovariance()
    pose, covariance = np.eye(4), np.zeros((6, 6))
    sweeps.add(pose, covariance)
    assert not sweeps.deskewing(drift @ pose, 1.0).any()
    for _ in range(6):
        start = pose
        covariance = compound_covariance(pose, covariance, step, step_covariance)
        pose = pose @ step
        sweeps.add(pose, covariance)
        np.testing.assert_allclose(sweeps.covariance, step_covariance, rtol=1e-9, atol=1e-15)
        expected = 0.5 * rotate_covariance(step_covariance, (drift @ start)[:3, :3])
        np.testing.assert_allclose(sweeps.deskewing(drift @ pose, 0.5), expected, rtol=1e-9, atol=1e-15)
    sweeps.add(pose @ step, None)
    assert not sweeps.deskewing(pose, 1.0).any()
    sweeps.reset()
    sweeps.add(pose, covariance)
    assert not sweeps.deskewing(pose, 1.0).any()


# ----------------------------------------------------------------------------------------- the keyframes'
def test_keyframe_covariance_is_a_random_walk_that_a_loop_closure_shrinks():
    """Keyframes 1 m apart along z, each registered with translation variance s² (rotation ~0): keyframe n has
    n s² per axis. A loop constraint from keyframe 0 to keyframe n with translation variance s²: n s² · s² /
    (n s² + s²) = n/(n+1) s²."""
    import gtsam

    from lego_loam_py.core.frames import camera_pose_to_lidar
    from lego_loam_py.core.mapping.covariance import KeyframeCovariance

    s2, n = 1e-2, 8
    registration = np.diag([s2, s2, s2, 1e-10, 1e-10, 1e-10])
    graph = KeyframeCovariance()
    poses = [make_pose(translation=[0.0, 0.0, float(k)]) for k in range(n + 1)]
    graph.add_keyframe(poses[0], None)
    for k in range(1, n + 1):
        covariance = graph.add_keyframe(poses[k], registration)
        np.testing.assert_allclose(np.diag(covariance)[:3], k * s2, rtol=1e-5)
    relative = camera_pose_to_lidar(np.linalg.inv(poses[0]) @ poses[n])
    noise = gtsam.noiseModel.Gaussian.Covariance(np.diag([1e-10, 1e-10, 1e-10, s2, s2, s2]))  # (rot, trans)
    graph.add_loop(0, n, relative, noise)
    np.testing.assert_allclose(np.diag(graph.covariance())[:3], n / (n + 1) * s2, rtol=1e-4)
    assert is_covariance(graph.covariance())
    # Keyframes dropped as poisoned (core.mapping.map_optimization heal): the kept ones keep their covariances.
    kept = graph.kept([0, 3, n], [poses[0], poses[3], poses[n]])
    assert len(kept) == 3
    for new, old in ((1, 3), (2, n)):
        np.testing.assert_allclose(kept.covariance(new), graph.covariance(old), rtol=1e-4, atol=1e-8)


def test_the_fused_covariance_is_the_mapped_one_and_what_the_odometry_added_since():
    """transformFusion: before any mapping result the fused covariance is the odometry's; after one (mapped pose
    ``aft`` of the odometry pose ``bef``) it is ``aft``'s compounded with the odometry's growth from ``bef``."""
    from lego_loam_py.core.mapping.transform_fusion import TransformFusion

    step = make_pose(rot_y(0.02), [0.0, 0.0, 1.0])
    step_covariance = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6])
    fusion = TransformFusion()
    pose, covariance, history = np.eye(4), np.zeros((6, 6)), []
    for k in range(10):
        covariance = compound_covariance(pose, covariance, step, step_covariance)
        pose = pose @ step
        history.append((pose, covariance))
        fusion.integrate(pose, covariance, 1000 + k)
        if k < 5:
            np.testing.assert_allclose(fusion.covariance, covariance, rtol=1e-12)
        if k == 4:
            aft, aft_covariance = make_pose(translation=[0.1, 0.0, 5.0]), np.eye(6) * 1e-5
            fusion.on_mapped(aft, pose, 1004, aft_covariance)
    bef, bef_covariance = history[4]
    expected, chained = aft_covariance, aft
    for _ in range(5):
        expected = compound_covariance(chained, expected, step, step_covariance)
        chained = chained @ step
    np.testing.assert_allclose(fusion.covariance, expected, rtol=1e-6, atol=1e-15)
    assert np.trace(fusion.covariance) < np.trace(history[-1][1])


# ------------------------------------------------------------------------------------------------- the nodes
def message_covariance(msg) -> np.ndarray:
    return np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)


def test_the_three_topics_carry_finite_symmetric_positive_definite_covariances(context, tmp_path):
    """featureAssociation, mapOptimization and transformFusion in this process on the first 3 s of the campus: every
    /laser_odom_to_init, /aft_mapped_to_init and /integrated_to_init carries a finite, symmetric, positive-definite
    pose covariance (the odometry's growing along the way, the fused one never below the mapped one it starts
    from), and zero twist covariance (no node publishes a twist; mapOptimization's twist fields carry the
    pre-mapping pose, as the original's)."""
    from lego_loam_py.ros.map_optimization_node import MapOptimizationNode
    from lego_loam_py.ros.transform_fusion_node import TransformFusionNode
    from lego_loam_py.testing.messages import restamped, stamp_of
    from tests.support.inprocess import make_node, mapping_inputs, pipeline_outputs

    outputs = pipeline_outputs(context, tmp_path)
    odometry = outputs['odometry']
    assert len(odometry) >= 20
    for msg in odometry:
        assert is_covariance(message_covariance(msg)) and not any(msg.twist.covariance)
    position = [np.trace(message_covariance(m)[:3, :3]) for m in odometry]
    assert np.all(np.diff(position) >= 0) and position[-1] > 2 * position[3]

    mapping, recorder = make_node(context, MapOptimizationNode, tmp_path)
    fusion, fused = make_node(context, TransformFusionNode)
    mapped_seen = 0
    by_stamp = {stamp_of(parts[0]): parts for parts in mapping_inputs(outputs)}
    for msg in odometry:
        stamp = stamp_of(msg)
        if stamp in by_stamp:
            for name, part in zip(('corner', 'surf', 'outlier', 'odometry'), by_stamp[stamp]):
                mapping.on_part(name, restamped(part, stamp))
            for aft in recorder.out('/aft_mapped_to_init')[mapped_seen:]:
                fusion.on_mapped(aft)
            mapped_seen = len(recorder.out('/aft_mapped_to_init'))
        fusion.on_odometry(msg)
    mapped = recorder.out('/aft_mapped_to_init')
    integrated = fused.out('/integrated_to_init')
    assert len(mapped) >= 4 and len(integrated) == len(odometry)
    for msg in mapped + integrated:
        assert is_covariance(message_covariance(msg)) and not any(msg.twist.covariance)
    assert np.trace(message_covariance(integrated[-1])) >= np.trace(message_covariance(mapped[-1])) * (1 - 1e-9)
    assert not recorder.errors and not fused.errors
    mapping.destroy_node()
    fusion.destroy_node()
