"""Frames and angles: axis swaps, the LOAM Euler convention, quaternions, poses, the static transforms."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from lego_loam_py.core import frames as F

angles = st.floats(-np.pi, np.pi, allow_nan=False)
half_pi = st.floats(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, allow_nan=False)


def tf_rpy_quaternion(roll, pitch, yaw):
    """tf::createQuaternionMsgFromRollPitchYaw: fixed-axis roll about x, pitch about y, yaw about z."""
    return Rotation.from_euler('xyz', [roll, pitch, yaw]).as_quat()


def tf_get_rpy(q):
    """tf::Matrix3x3(q).getRPY -> (roll, pitch, yaw)."""
    return Rotation.from_quat(q).as_euler('xyz')


def test_axis_swap_by_hand():
    lidar = np.array([[1.0, 2.0, 3.0]])  # x fwd, y left, z up
    camera = F.lidar_to_camera(lidar)
    assert camera.tolist() == [[2.0, 3.0, 1.0]]  # x_c = y_l (left), y_c = z_l (up), z_c = x_l (forward)
    assert F.camera_to_lidar(camera).tolist() == lidar.tolist()
    assert np.allclose(F.LIDAR_TO_CAMERA @ lidar[0], camera[0])
    # Ahead of the sensor is +z in camera axes; the deskew azimuth -atan2(x_c, z_c) of a point to the
    # left (+y lidar) is -90 deg.
    left = F.lidar_to_camera(np.array([0.0, 1.0, 0.0]))
    assert np.isclose(-np.arctan2(left[0], left[2]), -np.pi / 2)


def test_elementary_rotations_are_right_handed():
    assert np.allclose(F.rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(F.rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1])
    assert np.allclose(F.rot_y(np.pi / 2) @ [0, 0, 1], [1, 0, 0])


@settings(max_examples=300)
@given(rx=half_pi, ry=angles, rz=angles)
def test_euler_round_trip(rx, ry, rz):
    R = F.euler_to_matrix(rx, ry, rz)
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(F.wrap_angle(np.subtract(F.matrix_to_euler(R), (rx, ry, rz))), 0, atol=1e-9)


@settings(max_examples=300)
@given(rx=half_pi, ry=angles, rz=angles)
def test_loam_euler_is_zyx_in_lidar_axes(rx, ry, rz):
    """Ry(ry) Rx(rx) Rz(rz) in camera axes equals Rz(yaw=ry) Ry(pitch=rx) Rx(roll=rz) in lidar axes."""
    camera = F.euler_to_matrix(rx, ry, rz)
    lidar = F.CAMERA_TO_LIDAR @ camera @ F.LIDAR_TO_CAMERA
    assert np.allclose(lidar, F.rot_z(ry) @ F.rot_y(rx) @ F.rot_x(rz))


@settings(max_examples=300)
@given(rx=half_pi, ry=angles, rz=angles)
def test_published_quaternion_matches_the_originals_formula(rx, ry, rz):
    """The original publishes (-q0.y, -q0.z, q0.x, q0.w) with q0 = RPY(rz, -rx, -ry)."""
    q0 = tf_rpy_quaternion(rz, -rx, -ry)
    original = np.array([-q0[1], -q0[2], q0[0], q0[3]])
    ours = F.euler_to_quaternion(rx, ry, rz)
    assert np.allclose(ours, original, atol=1e-9) or np.allclose(ours, -original, atol=1e-9)
    # The original's reader: tf quaternion (q.z, -q.x, -q.y, q.w) -> getRPY -> rx=-pitch, ry=-yaw, rz=roll.
    roll, pitch, yaw = tf_get_rpy([ours[2], -ours[0], -ours[1], ours[3]])
    assert np.allclose(F.wrap_angle(np.array([-pitch, -yaw, roll]) - [rx, ry, rz]), 0, atol=1e-9)
    assert np.allclose(F.wrap_angle(np.subtract(F.quaternion_to_euler(ours), (rx, ry, rz))), 0, atol=1e-9)


@settings(max_examples=200)
@given(rx=half_pi, ry=angles, rz=angles, t=st.lists(st.floats(-10, 10), min_size=3, max_size=3))
def test_pose6_round_trip_and_inverse(rx, ry, rz, t):
    v = np.array([rx, ry, rz, *t])
    T = F.pose6_to_matrix(v)
    back = F.matrix_to_pose6(T)
    assert np.allclose(F.wrap_angle(back[:3] - v[:3]), 0, atol=1e-9) and np.allclose(back[3:], v[3:])
    assert np.allclose(T @ F.invert_pose(T), np.eye(4), atol=1e-12)
    p = np.array([[1.0, -2.0, 3.0]])
    assert np.allclose(F.transform_points(T, p)[0], T[:3, :3] @ p[0] + T[:3, 3])


def test_pose_composition_order():
    """T_ab @ T_bc maps c-coordinates into a: a point 1 m ahead of c, with c 2 m ahead of b turned 90 deg."""
    T_ab = F.make_pose(F.rot_z(np.pi / 2), [2.0, 0.0, 0.0])
    T_bc = F.make_pose(np.eye(3), [1.0, 0.0, 0.0])
    assert np.allclose(F.transform_points(T_ab @ T_bc, [[1.0, 0.0, 0.0]]), [[2.0, 2.0, 0.0]])


def test_static_transforms_match_the_launch_file():
    """run.launch: map->camera_init 0 0 0 1.570795 0 1.570795; camera->base_link 0 0 0 -1.570795 -1.570795 0
    (static_transform_publisher args x y z yaw pitch roll)."""

    def launch(yaw, pitch, roll):
        return Rotation.from_euler('ZYX', [yaw, pitch, roll]).as_matrix()

    assert np.allclose(F.MAP_T_CAMERA_INIT[:3, :3], launch(1.570795, 0, 1.570795), atol=1e-5)
    assert np.allclose(F.CAMERA_T_BASE_LINK[:3, :3], launch(-1.570795, -1.570795, 0), atol=1e-5)
    # map -> camera_init -> (identity) camera -> base_link is the identity at the start.
    assert np.allclose(F.MAP_T_CAMERA_INIT @ F.CAMERA_T_BASE_LINK, np.eye(4))


@settings(max_examples=200)
@given(rx=half_pi, ry=angles, rz=angles, t=st.lists(st.floats(-50, 50), min_size=3, max_size=3))
def test_camera_pose_to_lidar_agrees_with_the_tf_chain(rx, ry, rz, t):
    """base_link in map = map->camera_init * camera_init->camera * camera->base_link."""
    camera = F.make_pose(F.euler_to_matrix(rx, ry, rz), t)
    chain = F.MAP_T_CAMERA_INIT @ camera @ F.CAMERA_T_BASE_LINK
    lidar = F.camera_pose_to_lidar(camera)
    assert np.allclose(lidar, chain)
    assert np.allclose(F.lidar_pose_to_camera(lidar), camera)
    # The translation (tx, ty, tz) in camera axes is (tz, tx, ty) in lidar axes.
    assert np.allclose(lidar[:3, 3], [t[2], t[0], t[1]])


def test_quaternion_helpers_round_trip():
    for q in Rotation.random(50, random_state=1).as_quat():
        R = F.quaternion_to_matrix(q)
        back = F.matrix_to_quaternion(R)
        assert back[3] >= 0 and (np.allclose(back, q) or np.allclose(back, -q))
    with pytest.raises(ValueError):
        F.quaternion_to_matrix([0.0, 0.0, 0.0, 0.0])


def test_wrap_angle():
    assert np.allclose(F.wrap_angle(np.array([3 * np.pi, -3 * np.pi / 2, 0.1])), [-np.pi, np.pi / 2, 0.1])


def test_rotate_by_euler_is_the_matrix_product_for_every_point():
    """The deskewing's batched rotation equals ``left @ Ry Rx Rz @ p`` point by point (to rounding: its
    summation order is fixed, the matrix product's may depend on the CPU's SIMD kernels)."""
    from lego_loam_py.core.frames import euler_to_matrix, rotate_by_euler

    rng = np.random.default_rng(4)
    n = 257
    rx, ry, rz = rng.uniform(-np.pi, np.pi, (3, n))
    left = euler_to_matrix(*rng.uniform(-np.pi, np.pi, 3))
    xyz = rng.normal(scale=30.0, size=(n, 3)).astype(np.float32)
    got = rotate_by_euler(left, rx, ry, rz, xyz)
    expected = np.array([left @ euler_to_matrix(rx[k], ry[k], rz[k]) @ xyz[k].astype(np.float64) for k in range(n)])
    assert got.shape == (n, 3) and got.dtype == np.float64
    assert np.abs(got - expected).max() <= 1e-12 * np.abs(xyz).max()
    assert np.array_equal(
        rotate_by_euler(np.eye(3), np.zeros(2), np.zeros(2), np.zeros(2), xyz[:2]), xyz[:2].astype(np.float64)
    )


# ---- the NumPy rotation conversions give scipy's Rotation's bits (frames no longer imports scipy.spatial)
def _same_bits(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def _random_quaternions(rng, n: int) -> list[np.ndarray]:
    """Random quaternions of any scale, and the hard cases: w about 0 (turns near 180 deg), w < 0, axis-aligned,
    signed zeros, not normalised."""
    out = list(rng.normal(size=(n, 4)) * rng.choice([1e-3, 1.0, 1e3], size=(n, 1)))
    for w in (0.0, -0.0, 1e-17, -1e-17, 1e-9, -1e-9):
        for axis in np.eye(3):
            for scale in (1.0, -1.0, 2.5):
                out.append(np.array([*(scale * axis), w]))
    near = rng.normal(size=(n // 4, 4))
    near[:, 3] = rng.choice([0.0, 1e-12, -1e-12, 1e-6, -1e-6], size=n // 4)
    out += list(near)
    out += [np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0, -1.0]), np.array([-0.0, 0.0, -0.0, 1.0])]
    return out


def test_quaternion_and_matrix_conversions_are_scipys_bit_for_bit():
    rng = np.random.default_rng(7)
    for q in _random_quaternions(rng, 4000):
        matrix = Rotation.from_quat(q).as_matrix()
        assert _same_bits(F.quaternion_to_matrix(q), matrix), q
        translation = rng.normal(size=3) * 100
        assert _same_bits(F.quaternion_pose(q, translation), F.make_pose(matrix, translation)), q
        # exact rotations, nearly orthogonal ones (scipy's Markley step), perturbed ones (its SVD projection) and
        # ones about its tolerances (1e-12 off the diagonal of m m^T, 1e-5 on it) where the fast check defers to it
        for m in (matrix, *(matrix + rng.normal(size=(3, 3)) * s for s in (1e-14, 4e-13, 2e-12, 3e-6, 1e-4))):
            expected = Rotation.from_matrix(m).as_quat()
            assert _same_bits(F.matrix_to_quaternion(m), -expected if expected[3] < 0 else expected), m
            assert _same_bits(F.matrix_to_rpy(m), Rotation.from_matrix(m).as_euler('xyz', degrees=True)), m


def test_rotation_vector_conversions_are_scipys_bit_for_bit():
    rng = np.random.default_rng(9)
    # and small turns about both sides of the series' switch (1e-3 rad)
    small = rng.normal(size=(1000, 4))
    small[:, :3] *= rng.choice([1e-9, 1e-6, 1e-4, 4.9e-4, 5.1e-4, 1e-3], size=(1000, 1))
    for q in _random_quaternions(rng, 3000) + list(small):
        matrix = Rotation.from_quat(q).as_matrix()
        expected = Rotation.from_matrix(matrix)
        assert _same_bits(F.rotation_vector(matrix), expected.as_rotvec()), q
        assert F.rotation_angle(matrix) == float(expected.magnitude()), q
        vector = expected.as_rotvec() * rng.choice([1.0, 0.3, 1e-3, 1e-4])
        assert _same_bits(F.vector_to_matrix(vector), Rotation.from_rotvec(vector).as_matrix()), vector
    motion = F.make_pose(Rotation.from_rotvec([0.2, -0.1, 0.4]).as_matrix(), [1.0, 2.0, -0.5])
    quarter = Rotation.from_rotvec([0.05, -0.025, 0.1]).as_matrix()
    assert np.allclose(F.scaled_motion(motion, 0.25)[:3, :3], quarter, rtol=0.0, atol=1e-15)
    assert np.array_equal(F.scaled_motion(motion, 0.25)[:3, 3], [0.25, 0.5, -0.125])
    half = F.scaled_motion(motion, 0.5)
    assert np.allclose(half[:3, :3] @ half[:3, :3], motion[:3, :3], rtol=0.0, atol=1e-12)


def test_rotation_stacks_are_scipys_to_a_few_ulps():
    rng = np.random.default_rng(10)
    n = 5000
    # every scale, the small-angle series and both sides of a half turn
    vectors = rng.normal(size=(n, 3)) * rng.choice([1e-6, 1e-3, 0.01, 0.5, 3.0], size=(n, 1))
    vectors[:10] = np.eye(3)[rng.integers(0, 3, 10)] * np.pi * rng.choice([-1.0, 1.0], size=(10, 1))
    quaternions = F.vectors_to_quaternions(vectors)
    assert np.allclose(quaternions, Rotation.from_rotvec(vectors).as_quat(), rtol=0.0, atol=1e-15)
    others = Rotation.from_rotvec(vectors[::-1] * 0.7).as_quat()
    products = F.quaternion_products(quaternions, others)
    expected = (Rotation.from_quat(quaternions) * Rotation.from_quat(others)).as_quat()
    assert np.allclose(products, expected, rtol=0.0, atol=1e-15)
    back = F.quaternions_to_vectors(products)
    assert np.allclose(back, Rotation.from_quat(products).as_rotvec(), rtol=0.0, atol=5e-15)
    # broadcasting, as the IMU check composes (m, 1, 4) shifts with (1, n, 4) increments
    grid = F.quaternion_products(quaternions[:3, None], others[None, :4])
    assert grid.shape == (3, 4, 4) and np.allclose(grid[2, 1], F.quaternion_products(quaternions[2], others[1]))


def test_rpy_conversions_are_scipys_bit_for_bit_including_gimbal_lock():
    rng = np.random.default_rng(8)
    special = np.array([0.0, -0.0, 90.0, -90.0, 180.0, -180.0, 45.0, 1e-9])
    cases = list(rng.uniform(-400.0, 400.0, size=(3000, 3))) + list(rng.choice(special, size=(1000, 3)))
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')  # (gimbal lock: both warn)
        for rpy in cases:
            matrix = Rotation.from_euler('xyz', rpy, degrees=True).as_matrix()
            assert _same_bits(F.rpy_to_matrix(rpy), matrix), rpy
            assert _same_bits(F.matrix_to_rpy(matrix), Rotation.from_matrix(matrix).as_euler('xyz', degrees=True))


def test_rotation_conversions_refuse_what_scipy_refuses():
    for q in (np.zeros(4), np.array([np.nan, 0.0, 0.0, 1.0])):
        with pytest.raises(ValueError, match='zero norm'):
            F.quaternion_to_matrix(q)
    with pytest.raises(ValueError, match='Non-positive determinant'):
        F.matrix_to_quaternion(np.diag([1.0, 1.0, -1.0]))
    with pytest.warns(UserWarning, match='Gimbal lock'):
        F.matrix_to_rpy(F.rpy_to_matrix((10.0, 90.0, 0.0)))
    # stacks go to scipy itself
    stack = Rotation.from_euler('xyz', [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]).as_matrix()
    assert _same_bits(F.matrix_to_rpy(stack), Rotation.from_matrix(stack).as_euler('xyz', degrees=True))
