"""Frames, axes and angle conventions of LeGO-LOAM, in one place (docs/original.md §5).

Two axis conventions meet in LeGO-LOAM:

* **lidar axes** (REP-103): x forward, y left, z up. Input clouds, ``base_link`` and ``map`` use them.
* **LOAM camera axes**: x left, y up, z forward, i.e. ``(x_c, y_c, z_c) = (y_l, z_l, x_l)``. Everything inside
  featureAssociation / mapOptimization / transformFusion and every published pose (``camera_init``,
  ``camera``, ``laser_odom``, ``aft_mapped``) uses them.

Poses are 4x4 homogeneous matrices ``T`` mapping child coordinates into parent coordinates
(``p_parent = R p_child + t``), as a TF transform parent->child does. The original stores rotations as
Euler triples (rx, ry, rz) in camera axes composed as ``R = Ry(ry) Rx(rx) Rz(rz)``; in lidar terms these are
(pitch, yaw, roll). The six-vector ``(rx, ry, rz, tx, ty, tz)`` is the original's ``transformSum`` /
``transformTobeMapped`` layout. Quaternions are (x, y, z, w), as in ROS messages.

The TF tree of the original launch file::

    map --(static)--> camera_init --> camera --(static)--> base_link

where ``map -> camera_init`` turns camera axes into lidar axes and ``camera -> base_link`` does the reverse.
There ``base_link`` is the lidar itself. With ``frames.rep105`` the tree a navigation stack expects is published
beside it (:class:`Rep105Frames`)::

    map --> odom --> base_link --(static)--> lidar          map --(static)--> camera_init --> camera

**Pose covariance** (:func:`compound_covariance` and the functions beside it): the 6x6 covariance of a pose
``T = [R, p]`` (child in parent) is that of its error expressed *in the parent frame*, in ROS's order (x, y, z,
rot x, rot y, rot z): ``δp = p_true - p`` in the parent's axes [m] and ``δφ`` the rotation vector of
``R_true R^T``, a small rotation about the parent's axes [rad] (``R_true = exp([δφ]x) R``). That is what
``nav_msgs/Odometry.pose.covariance`` means with the parent as ``header.frame_id``; for the original's topics the
parent is ``camera_init`` and its axes are LOAM camera axes. A relative motion (pose k in pose k-1) has its
covariance in pose k-1's axes by the same rule, so chaining is :func:`compound_covariance`.

**The IMU on the lidar** (:class:`ImuMounting`, set by the ``imu.*`` parameters): the IMU is a rigid body
fixed to the lidar (``base_link``), described as the static transform ``base_link -> imu`` would be:

* ``rotation`` ``R_lidar_imu``: the IMU axes in lidar axes, ``v_lidar = R_lidar_imu v_imu`` for its angular
  velocity and acceleration; given as (roll, pitch, yaw) [deg], ``R = Rz(yaw) Ry(pitch) Rx(roll)`` about the
  fixed x, y, z axes (:func:`rpy_to_matrix`; tf2's ``setRPY`` and ``static_transform_publisher --roll --pitch
  --yaw --frame-id base_link --child-frame-id imu``). An IMU yawed 90 deg to the left has its x axis along the
  lidar's y: ``(0, 0, 90)``; one mounted upside down about its x axis: ``(180, 0, 0)``.
* ``lever_arm`` [m]: the IMU origin in the lidar frame (lidar axes), the translation of that transform. The
  accelerometer there feels ``a_lidar + alpha x r + omega x (omega x r)``.
* ``orientation_rotation`` ``R_imu_orientation``: the axes of the frame whose attitude the orientation field
  reports, in IMU axes (identity: the IMU's own, as REP-145 asks; some 9-axis units report another one). The
  orientation is that frame's attitude in a gravity-aligned world with z up, so the lidar's attitude is
  ``R_world_lidar = R_world_orientation (R_lidar_imu R_imu_orientation)^T``.
* ``time_offset`` [s]: the IMU's stamp minus the lidar's stamp of the same instant (Kalibr's
  ``timeshift_cam_imu`` sign, ``t_imu = t_lidar + offset``); a sample stamped ``t`` was measured at lidar time
  ``t - time_offset``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from lego_loam_py.core.indexing import copy_columns, xyz_columns

__all__ = [
    'MAP_FRAME',
    'LIDAR_TO_CAMERA_COLUMNS',
    'CAMERA_TO_LIDAR_COLUMNS',
    'CAMERA_INIT_FRAME',
    'CAMERA_FRAME',
    'BASE_LINK_FRAME',
    'LASER_ODOM_FRAME',
    'AFT_MAPPED_FRAME',
    'LIDAR_TO_CAMERA',
    'CAMERA_TO_LIDAR',
    'lidar_to_camera',
    'camera_to_lidar',
    'rot_x',
    'rot_y',
    'rot_z',
    'GENERATOR_X',
    'GENERATOR_Y',
    'GENERATOR_Z',
    'euler_to_matrix',
    'euler_to_matrices',
    'rotate_by_euler',
    'matrix_to_euler',
    'quaternion_to_matrix',
    'quaternion_pose',
    'matrix_to_quaternion',
    'euler_to_quaternion',
    'quaternion_to_euler',
    'make_pose',
    'pose6_to_matrix',
    'matrix_to_pose6',
    'invert_pose',
    'camera_pose_to_lidar',
    'lidar_pose_to_camera',
    'MAP_T_CAMERA_INIT',
    'CAMERA_T_BASE_LINK',
    'transform_points',
    'transform_cloud',
    'wrap_angle',
    'rpy_to_matrix',
    'matrix_to_rpy',
    'rotation_vector',
    'rotation_angle',
    'vector_to_matrix',
    'scaled_motion',
    'vectors_to_quaternions',
    'quaternion_products',
    'quaternions_to_vectors',
    'ImuMounting',
    'Rep105Frames',
    'body_twist',
    'MIN_VARIANCE',
    'MAX_VARIANCE',
    'skew',
    'rotation_log',
    'pose_error',
    'pose_jacobian',
    'bounded_covariance',
    'covariance_from_information',
    'rotate_covariance',
    'transformed_covariance',
    'compound_covariance',
    'relative_covariance',
]

# Frame ids, without the original's leading slashes (invalid in tf2).
MAP_FRAME = 'map'
CAMERA_INIT_FRAME = 'camera_init'
CAMERA_FRAME = 'camera'
BASE_LINK_FRAME = 'base_link'
LASER_ODOM_FRAME = 'laser_odom'
AFT_MAPPED_FRAME = 'aft_mapped'

# p_camera = LIDAR_TO_CAMERA @ p_lidar, i.e. (x_c, y_c, z_c) = (y_l, z_l, x_l).
LIDAR_TO_CAMERA = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
CAMERA_TO_LIDAR = LIDAR_TO_CAMERA.T.copy()


# The lidar-axes coordinate each camera axis takes (camera x = lidar y, y = z, z = x), and the reverse.
LIDAR_TO_CAMERA_COLUMNS = (1, 2, 0)
CAMERA_TO_LIDAR_COLUMNS = (2, 0, 1)


def lidar_to_camera(points: np.ndarray) -> np.ndarray:
    """(..., 3) lidar-axes coordinates -> camera axes (a new array)."""
    return np.asarray(points)[..., list(LIDAR_TO_CAMERA_COLUMNS)]


def camera_to_lidar(points: np.ndarray) -> np.ndarray:
    """(..., 3) camera-axes coordinates -> lidar axes (a new array)."""
    return np.asarray(points)[..., list(CAMERA_TO_LIDAR_COLUMNS)]


def rot_x(angle: float) -> np.ndarray:
    """Rotation about x by ``angle`` [rad] (right-handed)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# Generators of the three rotations: d/da rot_x(a) = rot_x(a) @ GENERATOR_X, and likewise for y and z. The
# odometry's and the mapping's Jacobians are built from them.
GENERATOR_X = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
GENERATOR_Y = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
GENERATOR_Z = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


def euler_to_matrix(rx: float, ry: float, rz: float) -> np.ndarray:
    """LOAM Euler angles [rad] (camera axes) -> rotation ``Ry(ry) @ Rx(rx) @ Rz(rz)``.

    In lidar axes the same rotation is the usual ZYX ``Rz(yaw=ry) Ry(pitch=rx) Rx(roll=rz)``.
    """
    return rot_y(ry) @ rot_x(rx) @ rot_z(rz)


def _euler_entries(rx: np.ndarray, ry: np.ndarray, rz: np.ndarray) -> np.ndarray:
    """(3, 3, n): the entries of ``Ry(ry) @ Rx(rx) @ Rz(rz)`` for (n,) angles, each entry a contiguous row."""
    angles = np.array([np.asarray(a, dtype=float).reshape(-1) for a in (rx, ry, rz)])
    (cx, cy, cz), (sx, sy, sz) = np.cos(angles), np.sin(angles)
    sy_sx, cy_sx = sy * sx, cy * sx
    out = np.empty((3, 3, angles.shape[1]))
    out[0, 0] = cy * cz + sy_sx * sz
    out[0, 1] = -cy * sz + sy_sx * cz
    out[0, 2] = sy * cx
    out[1, 0] = cx * sz
    out[1, 1] = cx * cz
    out[1, 2] = -sx
    out[2, 0] = -sy * cz + cy_sx * sz
    out[2, 1] = sy * sz + cy_sx * cz
    out[2, 2] = cy * cx
    return out


def euler_to_matrices(rx: np.ndarray, ry: np.ndarray, rz: np.ndarray) -> np.ndarray:
    """Vectorised :func:`euler_to_matrix`: (n,) angle arrays -> (n, 3, 3) rotations ``Ry Rx Rz``."""
    return _euler_entries(rx, ry, rz).transpose(2, 0, 1).copy()


def rotate_by_euler(left: np.ndarray, rx: np.ndarray, ry: np.ndarray, rz: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """``(left @ euler_to_matrix(rx[n], ry[n], rz[n])) @ xyz[n]`` for every point: (n, 3) float64 (a view).

    Bit for bit ``np.einsum('nij,nj->ni', np.einsum('ij,njk->nik', left, euler_to_matrices(rx, ry, rz)), xyz)``
    (which the deskewing used) in a few calls on whole arrays instead of einsum's generic loops and (n, 3, 3)
    arrays: the first einsum sums j = 0, 1, 2 in turn; the second, NumPy's baseline SIMD kernel with two lanes,
    sums (j = 0 + j = 2) + j = 1. Both start from +0, so a zero sum is never -0: ``+ 0.0`` does the same here
    (the sign of a zero in the intermediate matrix cannot reach a non-zero sum, and zero sums are made +0).
    """
    entries = _euler_entries(rx, ry, rz)
    left = np.asarray(left, dtype=np.float64)
    product = (
        left[:, 0, None, None] * entries[0] + left[:, 1, None, None] * entries[1] + left[:, 2, None, None] * entries[2]
    )  # (3, 3, n): left @ R
    x, y, z = np.asarray(xyz)[:, :3].T.astype(np.float64)
    return ((product[:, 0] * x + product[:, 2] * z) + product[:, 1] * y + 0.0).T


def matrix_to_euler(rotation: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`euler_to_matrix`: (rx, ry, rz) [rad] with rx in [-pi/2, pi/2]."""
    r = np.asarray(rotation)
    rx = float(np.arcsin(np.clip(-r[1, 2], -1.0, 1.0)))
    ry = float(np.arctan2(r[0, 2], r[2, 2]))
    rz = float(np.arctan2(r[1, 0], r[1, 1]))
    return rx, ry, rz


def quaternion_to_matrix(quaternion: np.ndarray) -> np.ndarray:
    """(x, y, z, w) -> 3x3 rotation (the quaternion is normalised first)."""
    q = np.asarray(quaternion, dtype=float)
    if q.shape != (4,):
        return _scipy_rotation().from_quat(q).as_matrix()
    return _matrix_of_quaternion(*_normalised(*q.tolist(), raise_on_zero=True))


def quaternion_pose(quaternion: Sequence[float], translation: Sequence[float]) -> np.ndarray:
    """4x4 pose of a quaternion (x, y, z, w; normalised first) and a translation [m]: the rotation
    :func:`quaternion_to_matrix` gives, built in one array from Python floats (a message's pose, several times a
    scan: every NumPy call saved counts in a node woken with cold caches)."""
    (r0, r1, r2) = _rows_of_quaternion(*_normalised(*(float(v) for v in quaternion), raise_on_zero=True))
    tx, ty, tz = (float(v) for v in translation)
    return np.array([[*r0, tx], [*r1, ty], [*r2, tz], [0.0, 0.0, 0.0, 1.0]])


def matrix_to_quaternion(rotation: np.ndarray, canonical: bool = True) -> np.ndarray:
    """3x3 rotation -> (x, y, z, w), with w >= 0 when ``canonical`` (else the sign scipy's from_matrix picks)."""
    q = _quaternion_of_matrix(rotation)
    return -q if canonical and q[3] < 0 else q


def euler_to_quaternion(rx: float, ry: float, rz: float) -> np.ndarray:
    """The quaternion the original publishes for LOAM Euler angles (camera axes), as (x, y, z, w).

    The original builds it as tf RPY(roll=rz, pitch=-rx, yaw=-ry) with components shuffled to
    (-q.y, -q.z, q.x, q.w); that is exactly the quaternion of ``Ry(ry) Rx(rx) Rz(rz)``.
    """
    return matrix_to_quaternion(euler_to_matrix(rx, ry, rz))


def quaternion_to_euler(quaternion: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`euler_to_quaternion`: LOAM (rx, ry, rz) [rad] from a published quaternion."""
    return matrix_to_euler(quaternion_to_matrix(quaternion))


def make_pose(rotation: np.ndarray | None = None, translation: np.ndarray | None = None) -> np.ndarray:
    """4x4 homogeneous pose from a 3x3 rotation and a translation (identity parts when omitted)."""
    pose = np.eye(4)
    if rotation is not None:
        pose[:3, :3] = rotation
    if translation is not None:
        pose[:3, 3] = translation
    return pose


def pose6_to_matrix(pose6: np.ndarray) -> np.ndarray:
    """The original's six-vector (rx, ry, rz, tx, ty, tz) -> 4x4 pose (p_world = R p + t)."""
    rx, ry, rz, tx, ty, tz = (float(v) for v in pose6)
    return make_pose(euler_to_matrix(rx, ry, rz), (tx, ty, tz))


def matrix_to_pose6(pose: np.ndarray) -> np.ndarray:
    """4x4 pose -> six-vector (rx, ry, rz, tx, ty, tz)."""
    return np.array([*matrix_to_euler(pose[:3, :3]), *pose[:3, 3]])


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 pose."""
    inverse = np.eye(4)
    rotation_t = pose[:3, :3].T
    inverse[:3, :3] = rotation_t
    inverse[:3, 3] = -rotation_t @ pose[:3, 3]
    return inverse


_CAMERA_TO_LIDAR_4 = make_pose(CAMERA_TO_LIDAR)
_LIDAR_TO_CAMERA_4 = make_pose(LIDAR_TO_CAMERA)


def camera_pose_to_lidar(pose_camera: np.ndarray) -> np.ndarray:
    """A pose between two camera-axes frames (e.g. camera in camera_init) -> the same motion in lidar
    axes (base_link in map): ``A T A^-1`` with ``A`` the camera->lidar axis change."""
    return _CAMERA_TO_LIDAR_4 @ pose_camera @ _LIDAR_TO_CAMERA_4


def lidar_pose_to_camera(pose_lidar: np.ndarray) -> np.ndarray:
    """Inverse of :func:`camera_pose_to_lidar`."""
    return _LIDAR_TO_CAMERA_4 @ pose_lidar @ _CAMERA_TO_LIDAR_4


# Static transforms of the original run.launch (parent -> child poses):
#   map -> camera_init: yaw 90 deg, roll 90 deg, i.e. camera_init axes expressed in lidar axes;
#   camera -> base_link: yaw -90 deg, pitch -90 deg, i.e. lidar axes expressed in camera axes.
MAP_T_CAMERA_INIT = make_pose(CAMERA_TO_LIDAR)
CAMERA_T_BASE_LINK = make_pose(LIDAR_TO_CAMERA)


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 pose to (N, 3) points: ``R p + t``."""
    return np.asarray(points) @ pose[:3, :3].T + pose[:3, 3]


def transform_cloud(points: np.ndarray, pose6: np.ndarray) -> np.ndarray:
    """(n, 4) float32 points (camera axes, intensity kept) mapped with a world-convention pose six-vector."""
    out = np.empty_like(points, dtype=np.float32)
    copy_columns(out, transform_points(pose6_to_matrix(pose6), xyz_columns(points)))
    out[:, 3] = points[:, 3]
    return out


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    """Angle(s) wrapped into [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def rpy_to_matrix(roll_pitch_yaw_deg) -> np.ndarray:
    """(roll, pitch, yaw) [deg] -> 3x3 ``Rz(yaw) Ry(pitch) Rx(roll)`` (REP-103 angles about the fixed x, y, z axes,
    as tf2's ``setRPY``)."""
    angles = np.asarray(roll_pitch_yaw_deg, dtype=float)
    if angles.shape != (3,):
        return _scipy_rotation().from_euler('xyz', angles, degrees=True).as_matrix()
    roll, pitch, yaw = np.deg2rad(angles).tolist()
    # Extrinsic x, y, z: q = q_z(yaw) (q_y(pitch) q_x(roll)), elementary quaternions composed in full (their zero
    # terms included, so that signed zeros come out as scipy's do).
    q = _compose(_elementary(2, yaw), _compose(_elementary(1, pitch), _elementary(0, roll)))
    return _matrix_of_quaternion(*q)


def matrix_to_rpy(rotation: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rpy_to_matrix`: (roll, pitch, yaw) [deg], pitch within [-90, 90] (at +-90 deg the roll and
    yaw share one axis and the yaw takes all of it)."""
    if np.shape(rotation) != (3, 3):
        return _scipy_rotation().from_matrix(np.asarray(rotation, dtype=float)).as_euler('xyz', degrees=True)
    x, y, z, w = _quaternion_of_matrix(rotation).tolist()
    # Bernardes & Viollet (2022) for the Tait-Bryan sequence x, y, z (extrinsic), as scipy's as_euler.
    a, b, c, d = w - y, x + z, y + w, z - x
    pitch = 2.0 * math.atan2(float(np.hypot(c, d)), float(np.hypot(a, b)))
    half_sum, half_diff = math.atan2(b, a), math.atan2(d, c)
    if abs(pitch) <= 1e-7:
        angles = [2.0 * half_sum, pitch, 0.0]
    elif abs(pitch - math.pi) <= 1e-7:
        angles = [-(2.0 * half_diff), pitch, 0.0]
    else:
        angles = [half_sum - half_diff, pitch, half_sum + half_diff]
    angles[1] -= math.pi / 2
    for i, angle in enumerate(angles):
        if angle < -math.pi:
            angles[i] = angle + 2.0 * math.pi
        elif angle > math.pi:
            angles[i] = angle - 2.0 * math.pi
    if abs(pitch) <= 1e-7 or abs(pitch - math.pi) <= 1e-7:
        warnings.warn(
            'Gimbal lock detected. Setting third angle to zero since it is not possible to uniquely determine all '
            'angles.',
            stacklevel=2,
        )
    return np.rad2deg(np.array(angles))


# ---- Rotation conversions: scipy's Rotation (1.17) bit for bit, in NumPy and Python floats. scipy.spatial costs a
# node 0.25-0.4 s of CPU to import (kd-trees, sparse matrices, qhull, the array-API layer) where only these few
# formulas are used; a node that needs scipy.spatial for its kd-trees imports it there. Same operations in the
# same order as scipy's Cython (IEEE doubles, libm's sqrt, atan2 and hypot), checked against scipy on random and
# edge-case inputs (tests/test_frames.py). Anything but a single rotation goes to scipy.


def rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """3x3 rotation -> its rotation vector (axis times angle [rad], the angle within [0, pi]), as scipy's
    ``Rotation.from_matrix(rotation).as_rotvec()``."""
    x, y, z, w = _quaternion_of_matrix(rotation).tolist()
    # scipy's canonical sign: w > 0, or the first non-zero of x, y, z positive for a half turn (w = 0)
    if w < 0 or (w == 0 and (x < 0 or (x == 0 and (y < 0 or (y == 0 and z < 0))))):
        x, y, z, w = -x, -y, -z, -w
    angle = 2 * math.atan2(math.sqrt(x * x + y * y + z * z), w)
    if angle <= 1e-3:  # (the series of angle / sin(angle / 2))
        angle2 = angle * angle
        scale = 2 + angle2 / 12 + 7 * angle2 * angle2 / 2880
    else:
        scale = angle / math.sin(angle / 2)
    return np.array([scale * x, scale * y, scale * z])


def rotation_angle(rotation: np.ndarray) -> float:
    """The angle [rad] of a 3x3 rotation, within [0, pi], as scipy's ``Rotation.from_matrix(rotation).magnitude()``."""
    x, y, z, w = _quaternion_of_matrix(rotation).tolist()
    return 2 * math.atan2(math.sqrt(x * x + y * y + z * z), abs(w))


def vector_to_matrix(rotation_vector: np.ndarray) -> np.ndarray:
    """A rotation vector (axis times angle [rad]) -> 3x3 rotation, as scipy's
    ``Rotation.from_rotvec(rotation_vector).as_matrix()``."""
    x, y, z = (float(v) for v in np.asarray(rotation_vector, dtype=float).reshape(3))
    angle = math.sqrt(x * x + y * y + z * z)
    if angle <= 1e-3:  # (the series of sin(angle / 2) / angle)
        angle2 = angle * angle
        scale = 0.5 - angle2 / 48 + angle2 * angle2 / 3840
    else:
        scale = math.sin(angle / 2) / angle
    return _matrix_of_quaternion(scale * x, scale * y, scale * z, math.cos(angle / 2))


def scaled_motion(motion: np.ndarray, scale: float) -> np.ndarray:
    """The 4x4 motion ``motion`` made ``scale`` times (its rotation vector and its translation scaled), as a
    constant velocity would over ``scale`` times its duration."""
    out = np.eye(4)
    out[:3, :3] = vector_to_matrix(rotation_vector(motion[:3, :3]) * scale)
    out[:3, 3] = np.asarray(motion[:3, 3], dtype=float) * scale
    return out


# Stacks of rotations, vectorised with scipy's formulas (the IMU check's thousands of shifted turns a fit): equal to
# scipy's within a few 1e-16, not always bit for bit (NumPy's SIMD atan2 and scipy's compiled products may round
# the last bit differently).


def vectors_to_quaternions(vectors: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors [rad] -> (..., 4) unit quaternions (x, y, z, w), as ``Rotation.from_rotvec``."""
    vectors = np.asarray(vectors, dtype=float)
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    angle = np.sqrt(x * x + y * y + z * z)
    small = angle <= 1e-3  # (the series of sin(angle / 2) / angle)
    angle2 = angle * angle
    scale = np.where(small, 0.5 - angle2 / 48 + angle2 * angle2 / 3840, np.sin(angle / 2) / np.where(small, 1.0, angle))
    return np.concatenate([vectors * scale[..., None], np.cos(angle / 2)[..., None]], axis=-1)


def quaternion_products(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions ``p q`` (x, y, z, w; the rotation q first, then p), as scipy's ``Rotation p * q``."""
    px, py, pz, pw = np.moveaxis(np.asarray(p, dtype=float), -1, 0)
    qx, qy, qz, qw = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    product = np.stack(
        [
            pw * qx + qw * px + (py * qz - pz * qy),
            pw * qy + qw * py + (pz * qx - px * qz),
            pw * qz + qw * pz + (px * qy - py * qx),
            pw * qw - (px * qx + py * qy + pz * qz),
        ],
        axis=-1,
    )
    return product / np.sqrt(np.einsum('...i,...i->...', product, product))[..., None]


def quaternions_to_vectors(quaternions: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w) -> (..., 3) rotation vectors [rad], angles within [0, pi], as
    ``Rotation.as_rotvec``."""
    x, y, z, w = np.moveaxis(np.asarray(quaternions, dtype=float), -1, 0)
    # scipy's canonical sign, as in rotation_vector
    flip = (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
    sign = np.where(flip, -1.0, 1.0)
    x, y, z, w = x * sign, y * sign, z * sign, w * sign
    angle = 2 * np.arctan2(np.sqrt(x * x + y * y + z * z), w)
    small = angle <= 1e-3  # (the series of angle / sin(angle / 2))
    angle2 = angle * angle
    scale = np.where(
        small, 2 + angle2 / 12 + 7 * angle2 * angle2 / 2880, angle / np.where(small, 1.0, np.sin(angle / 2))
    )
    return np.stack([scale * x, scale * y, scale * z], axis=-1)


def _scipy_rotation():
    from scipy.spatial.transform import Rotation

    return Rotation


def _normalised(x: float, y: float, z: float, w: float, raise_on_zero: bool = False) -> tuple[float, ...]:
    """(x, y, z, w) / its norm; a zero norm leaves it as it is (from_quat raises for a zero or NaN norm)."""
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if raise_on_zero and (norm == 0 or math.isnan(norm)):
        raise ValueError('Found zero norm quaternions in `quat`.')
    if norm == 0:
        return x, y, z, w
    return x / norm, y / norm, z / norm, w / norm


def _rows_of_quaternion(x: float, y: float, z: float, w: float) -> list[list[float]]:
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return [
        [x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
        [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
        [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2],
    ]


def _matrix_of_quaternion(x: float, y: float, z: float, w: float) -> np.ndarray:
    return np.array(_rows_of_quaternion(x, y, z, w))


def _clearly_orthonormal(m: list[list[float]]) -> bool:
    """Whether the 3x3 ``m`` passes scipy's checks (positive determinant; ``m m^T`` close to the identity: within
    1e-12 off the diagonal, 1e-12 + 1e-5 on it) with a margin no rounding of the checks' own arithmetic can cross:
    the common case decided in Python floats, 20x faster than np.isclose on the product. False sends the matrix
    through the checks themselves."""
    (a, b, c), (d, e, f), (g, h, i) = m
    if not (a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)) > 0.5:
        return False
    rows = ((a, b, c), (d, e, f), (g, h, i))
    for r in range(3):
        for s in range(r, 3):
            p, q = rows[r], rows[s]
            dot = p[0] * q[0] + p[1] * q[1] + p[2] * q[2]
            # Half of each tolerance: the product's rounding (a few 1e-16) never moves a value across it.
            if not abs(dot - (1.0 if r == s else 0.0)) <= (0.5e-5 if r == s else 0.5e-12):
                return False
    return True


def _quaternion_of_matrix(rotation: np.ndarray) -> np.ndarray:
    """3x3 rotation -> unit (x, y, z, w) as scipy's from_matrix: refused when its determinant is not positive,
    projected onto the rotations (SVD) when not orthogonal to 1e-12, then Markley's method."""
    matrix = np.array(rotation, dtype=float)[np.newaxis]
    m = matrix[0].tolist()
    if not _clearly_orthonormal(m):
        dets = np.linalg.det(matrix)
        if np.any(dets <= 0):
            raise ValueError(
                f'Non-positive determinant (left-handed or null coordinate frame) in rotation matrix 0: {matrix[0]}.'
            )
        if not np.all(np.isclose(matrix @ np.transpose(matrix, (0, 2, 1)), np.eye(3), atol=1e-12)):
            u, _, vt = np.linalg.svd(matrix)
            matrix = u @ vt
        m = matrix[0].tolist()
    trace = m[0][0] + m[1][1] + m[2][2]
    decision = (m[0][0], m[1][1], m[2][2], trace)
    choice = 0
    for i in range(1, 4):  # the first largest (NaN never wins)
        if decision[i] > decision[choice]:
            choice = i
    q = [0.0, 0.0, 0.0, 0.0]
    if choice != 3:
        i = choice
        j = (i + 1) % 3
        k = (j + 1) % 3
        q[i] = 1 - trace + 2 * m[i][i]
        q[j] = m[j][i] + m[i][j]
        q[k] = m[k][i] + m[i][k]
        q[3] = m[k][j] - m[j][k]
    else:
        q = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1], 1 + trace]
    return np.array(_normalised(*q))


def _elementary(axis: int, angle: float) -> list[float]:
    q = [0.0, 0.0, 0.0, math.cos(angle / 2)]
    q[axis] = math.sin(angle / 2)
    return q


def _compose(p: list[float], q: list[float]) -> list[float]:
    """The quaternion product p q."""
    cross = (p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0])
    return [
        p[3] * q[0] + q[3] * p[0] + cross[0],
        p[3] * q[1] + q[3] * p[1] + cross[1],
        p[3] * q[2] + q[3] * p[2] + cross[2],
        p[3] * q[3] - p[0] * q[0] - p[1] * q[1] - p[2] * q[2],
    ]


@dataclass(frozen=True, eq=False)
class ImuMounting:
    """How the IMU sits on the lidar and how its clock relates to the lidar's (see the module docstring, which
    spells the conventions out; :func:`lego_loam_py.core.imu.buffer.imu_mounting` builds it from the ``imu.*``
    parameters)."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))  # R_lidar_imu
    lever_arm: np.ndarray = field(default_factory=lambda: np.zeros(3))  # IMU origin, lidar frame [m]
    orientation_rotation: np.ndarray = field(default_factory=lambda: np.eye(3))  # R_imu_orientation
    time_offset: float = 0.0  # IMU stamp - lidar stamp [s]

    @classmethod
    def from_rpy(
        cls,
        rotation_rpy=(0.0, 0.0, 0.0),
        lever_arm=(0.0, 0.0, 0.0),
        orientation_rpy=(0.0, 0.0, 0.0),
        time_offset: float = 0.0,
    ) -> ImuMounting:
        """From (roll, pitch, yaw) angles [deg], the lever arm [m] and the time offset [s]. Zero angles give
        exact identity matrices."""

        def rotation(rpy) -> np.ndarray:
            return np.eye(3) if not np.any(rpy) else rpy_to_matrix(rpy)

        return cls(
            rotation(rotation_rpy),
            np.asarray(lever_arm, dtype=float).copy(),
            rotation(orientation_rpy),
            float(time_offset),
        )

    @property
    def rotates(self) -> bool:
        """True unless the IMU axes and its orientation's axes are exactly the lidar's."""
        return not (np.array_equal(self.rotation, np.eye(3)) and np.array_equal(self.orientation_rotation, np.eye(3)))

    @property
    def is_identity(self) -> bool:
        """True when the IMU is taken as it is: lidar axes, at the lidar origin, on the lidar's clock."""
        return not self.rotates and not np.any(self.lever_arm) and self.time_offset == 0.0

    @property
    def rotation_lidar_orientation(self) -> np.ndarray:
        """3x3 ``R_lidar_imu R_imu_orientation``: the axes of the orientation field's frame in lidar axes."""
        return self.rotation @ self.orientation_rotation

    def describe(self) -> str:
        """The mounting as the parameters spell it, e.g. ``rotation_rpy [0, 0, 90] deg, ...``."""

        def angles(matrix: np.ndarray) -> str:
            return '[' + ', '.join(f'{a:.6g}' for a in np.round(matrix_to_rpy(matrix), 4) + 0.0) + ']'

        return (
            f'rotation_rpy {angles(self.rotation)} deg, translation [{", ".join(f"{v:g}" for v in self.lever_arm)}]'
            f' m, orientation_rpy {angles(self.orientation_rotation)} deg, time_offset {self.time_offset:g} s'
        )


@dataclass(frozen=True, eq=False)
class Rep105Frames:
    """The REP-105 tree ``map -> odom -> base_link -> lidar`` from the original's poses (``frames.rep105``).

    ``map`` is the original's ``map``, the saved maps' frame: the lidar's pose at the start in REP-103 axes.
    ``odom`` is ``base_link`` at the start, so ``odom -> base_link`` starts at identity and is the odometry
    (continuous, never corrected); ``map -> odom`` is what the mapping (or, in localization, the fix in the saved map)
    adds to it. ``base_T_lidar`` is the lidar's pose on the robot (``base_link -> lidar``): its origin in base_link
    [m] and its axes, so ``p_base = R p_lidar + t``.
    """

    base_T_lidar: np.ndarray = field(default_factory=lambda: np.eye(4))

    @classmethod
    def from_mount(cls, translation=(0.0, 0.0, 0.0), rotation_rpy=(0.0, 0.0, 0.0)) -> Rep105Frames:
        """From the lidar's origin in base_link [m] and its axes as (roll, pitch, yaw) [deg]."""
        rotation = np.eye(3) if not np.any(rotation_rpy) else rpy_to_matrix(rotation_rpy)
        return cls(make_pose(rotation, np.asarray(translation, dtype=float)))

    def base_in(self, camera_pose: np.ndarray) -> np.ndarray:
        """4x4 base_link pose in the frame where the lidar started (REP-103 axes), from a LOAM pose of the lidar
        (``camera`` in ``camera_init``): ``map -> base_link`` for a mapped pose, and (see :meth:`odom_to_base`)
        the odometry's motion of base_link."""
        return camera_pose_to_lidar(camera_pose) @ invert_pose(self.base_T_lidar)

    def odom_to_base(self, odometry_camera_pose: np.ndarray) -> np.ndarray:
        """4x4 ``odom -> base_link`` from the odometry's LOAM pose (/laser_odom_to_init)."""
        return self.base_T_lidar @ self.base_in(odometry_camera_pose)

    def map_to_odom(self, mapped_camera_pose: np.ndarray, odometry_camera_pose: np.ndarray) -> np.ndarray:
        """4x4 ``map -> odom``: the mapped (or localized) pose of the same instant over the odometry's
        (/integrated_to_init and /laser_odom_to_init); ``inv(base_T_lidar)`` while they agree."""
        return self.base_in(mapped_camera_pose) @ invert_pose(self.odom_to_base(odometry_camera_pose))

    def base_in_covariance(self, camera_pose: np.ndarray, covariance: np.ndarray) -> np.ndarray:
        """The covariance of :meth:`base_in` (base_link in map, REP-103 axes) from the LOAM pose's (camera_init)."""
        return transformed_covariance(covariance, _CAMERA_TO_LIDAR_4, camera_pose, invert_pose(self.base_T_lidar))

    def odom_to_base_covariance(self, odometry_camera_pose: np.ndarray, covariance: np.ndarray) -> np.ndarray:
        """The covariance of :meth:`odom_to_base` (in odom, REP-103 axes) from the odometry's (camera_init)."""
        axes = self.base_T_lidar @ _CAMERA_TO_LIDAR_4
        return transformed_covariance(covariance, axes, odometry_camera_pose, invert_pose(axes))

    def twist_covariance(
        self,
        previous_camera_pose: np.ndarray,
        previous_covariance: np.ndarray,
        camera_pose: np.ndarray,
        covariance: np.ndarray,
        dt: float,
    ) -> np.ndarray:
        """The covariance of :func:`body_twist` of base_link between two odometry poses ``dt`` [s] apart, from
        their covariances (one chain): the motion's in between, in base_link's axes, over ``dt^2``."""
        motion = relative_covariance(previous_camera_pose, previous_covariance, camera_pose, covariance)
        return rotate_covariance(motion, self.base_T_lidar[:3, :3] @ CAMERA_TO_LIDAR) / (dt * dt)


def body_twist(previous: np.ndarray, current: np.ndarray, dt: float) -> np.ndarray:
    """(vx, vy, vz, wx, wy, wz): the mean velocity [m/s] and angular velocity [rad/s] between two 4x4 poses of one
    body ``dt`` [s] apart, in the body's frame at ``current`` (nav_msgs/Odometry's twist in child_frame_id)."""
    rotation = current[:3, :3]
    linear = rotation.T @ (current[:3, 3] - previous[:3, 3]) / dt
    angular = rotation_log(previous[:3, :3].T @ rotation) / dt
    return np.concatenate([linear, angular])


# ----------------------------------------------------------------------------------------- pose covariance
# Bounds on the variances of a published covariance [m^2, rad^2]: positive definite however well a direction is
# held, and large but finite where nothing holds it (a degenerate direction).
MIN_VARIANCE = 1e-12
MAX_VARIANCE = 1e6


def skew(v: np.ndarray) -> np.ndarray:
    """3x3 ``[v]x`` with ``[v]x w = v x w``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotation_log(rotation: np.ndarray) -> np.ndarray:
    """The rotation vector [rad] of a 3x3 rotation matrix (closed form; the small 3x3s of a covariance's
    derivatives would spend most of their time building scipy Rotation objects)."""
    r = np.asarray(rotation, dtype=float)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])  # 2 sin(angle) * unit axis
    cos = max(-1.0, min(1.0, (r[0, 0] + r[1, 1] + r[2, 2] - 1.0) / 2.0))
    angle = float(np.arccos(cos))
    if angle < 1e-6:
        return 0.5 * axis  # sin(angle) ~ angle
    if angle > np.pi - 1e-4:  # (near a half turn the antisymmetric part vanishes)
        return rotation_vector(r)
    return axis * (angle / (2.0 * np.sin(angle)))


def pose_error(reference: np.ndarray, other: np.ndarray) -> np.ndarray:
    """The six-vector error ``(δp, δφ)`` of 4x4 ``other`` from 4x4 ``reference`` in the parent frame (see the module
    docstring): ``other = [exp([δφ]x) R, p + δp]``; [m, rad]."""
    rotation = np.asarray(other)[:3, :3] @ np.asarray(reference)[:3, :3].T
    return np.concatenate([other[:3, 3] - reference[:3, 3], rotation_log(rotation)])


def pose_jacobian(pose_of, x: np.ndarray, step: float = 1e-7) -> np.ndarray:
    """(6, n) derivative of the parent-frame error (:func:`pose_error`) of the 4x4 ``pose_of(x)`` with respect to
    the n-vector ``x``, by forward differences (n + 1 evaluations, a few 4x4 products each; the maps it serves are
    smooth, so the step's truncation error, ~1e-7 relative, is far below what a covariance needs)."""
    x = np.asarray(x, dtype=float)
    centre = pose_of(x)
    out = np.empty((6, len(x)))
    for k in range(len(x)):
        shifted = x.copy()
        shifted[k] += step
        out[:, k] = pose_error(centre, pose_of(shifted)) / step
    return out


def bounded_covariance(
    covariance: np.ndarray, min_variance: float = MIN_VARIANCE, max_variance: float = MAX_VARIANCE
) -> np.ndarray:
    """The symmetric part of ``covariance`` with its eigenvalues clipped to [min_variance, max_variance]: finite,
    symmetric and positive definite (a non-finite input gives ``max_variance`` on the diagonal)."""
    covariance = np.asarray(covariance, dtype=float)
    n = len(covariance)
    if not np.isfinite(covariance).all():
        return np.eye(n) * max_variance
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    out = (vectors * np.clip(values, min_variance, max_variance)) @ vectors.T
    return 0.5 * (out + out.T)


def covariance_from_information(
    information: np.ndarray, max_variance: float = MAX_VARIANCE, min_variance: float = MIN_VARIANCE
) -> np.ndarray:
    """The covariance of an information matrix (Fisher information of a least-squares estimate), a direction
    holding less than ``1 / max_variance`` (a degenerate direction) given ``max_variance`` instead of an infinite
    one."""
    information = np.asarray(information, dtype=float)
    if not np.isfinite(information).all():
        return np.eye(len(information)) * max_variance
    values, vectors = np.linalg.eigh(0.5 * (information + information.T))
    variances = 1.0 / np.clip(values, 1.0 / max_variance, 1.0 / min_variance)
    return bounded_covariance((vectors * variances) @ vectors.T, min_variance, max_variance)


def rotate_covariance(covariance: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """A pose covariance expressed in axes rotated by ``rotation`` (3x3, new from old): ``B Σ Bᵀ`` with ``B`` =
    diag(rotation, rotation)."""
    block = np.zeros((6, 6))
    block[:3, :3] = block[3:, 3:] = rotation
    return block @ covariance @ block.T


def transformed_covariance(covariance: np.ndarray, left: np.ndarray, pose: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The covariance of ``left @ pose @ right`` (4x4 each, ``left`` and ``right`` known exactly) from ``pose``'s,
    both as errors in the parent frame (:func:`pose_error`): the rotation error turned by ``left``'s rotation, the
    position error too, plus what the rotation error swings ``right``'s offset by."""
    rotation = np.asarray(left)[:3, :3]
    jacobian = np.zeros((6, 6))
    jacobian[:3, :3] = jacobian[3:, 3:] = rotation
    jacobian[:3, 3:] = -rotation @ skew(np.asarray(pose)[:3, :3] @ np.asarray(right)[:3, 3])
    out = jacobian @ np.asarray(covariance, dtype=float) @ jacobian.T
    return 0.5 * (out + out.T)


def compound_covariance(
    parent: np.ndarray, parent_covariance: np.ndarray, relative: np.ndarray, relative_covariance: np.ndarray
) -> np.ndarray:
    """Covariance of ``parent @ relative`` (4x4 each) in the parent's parent frame, the two errors independent:
    ``F Σ_parent Fᵀ + G Σ_relative Gᵀ`` with ``F = [[I, -[R_parent t_relative]x], [0, I]]`` (a rotation error of
    the parent swings the relative translation) and ``G = diag(R_parent, R_parent)`` (the relative covariance is in
    the parent's axes). Along a chain the variances grow with the distance travelled, as an odometry's do."""
    rotation = np.asarray(parent)[:3, :3]
    lever = np.eye(6)
    lever[:3, 3:] = -skew(rotation @ np.asarray(relative)[:3, 3])
    out = lever @ parent_covariance @ lever.T + rotate_covariance(relative_covariance, rotation)
    return 0.5 * (out + out.T)


def relative_covariance(
    earlier: np.ndarray, earlier_covariance: np.ndarray, later: np.ndarray, later_covariance: np.ndarray
) -> np.ndarray:
    """Covariance of ``earlier^-1 @ later`` in ``earlier``'s axes when ``later`` was compounded from ``earlier``
    along one chain (:func:`compound_covariance`): what the chain added in between, ``Σ_later - F Σ_earlier Fᵀ``
    rotated into the earlier pose's axes, made positive semi-definite (clipping rounding)."""
    rotation = np.asarray(earlier)[:3, :3]
    lever = np.eye(6)
    lever[:3, 3:] = -skew(np.asarray(later)[:3, 3] - np.asarray(earlier)[:3, 3])
    added = later_covariance - lever @ earlier_covariance @ lever.T
    return bounded_covariance(rotate_covariance(added, rotation.T), min_variance=0.0)
