"""Message conversions the nodes take on their hot paths: serialized IMU samples, clouds and CloudInfo (read and
written) and the TF of an odometry."""

from __future__ import annotations

import math
import re
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
# Garbage our own readers take: an XCDR1 encapsulation (either byte order), then anything. Bytes labelled XCDR2 go to
# rclpy's deserializer, which can crash on garbage (test_only_cdr_encodings_reach_rclpys_deserializer).
xcdr1_garbage = st.tuples(st.sampled_from([b'\x00\x00', b'\x00\x01']), st.binary(max_size=800)).map(
    lambda t: t[0] + t[1]
)


def imu_message(frame_id: str, sec: int, nanosec: int, values):
    from sensor_msgs.msg import Imu

    msg = Imu()
    msg.header.frame_id = frame_id
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    o.x, o.y, o.z, o.w, w.x, w.y, w.z, a.x, a.y, a.z = values
    msg.orientation_covariance[0] = -1.0  # (covariances sit between the fields read: not taken)
    msg.angular_velocity_covariance[8] = 99.0
    return msg


def test_serialized_imu_by_hand():
    """The XCDR1 layout of sensor_msgs/Imu, written by hand: header, then 37 doubles aligned to 8."""
    from lego_loam_py.ros.conversions import imu_sample_from_serialized

    frame = b'imu\x00'  # length 4 with the NUL: doubles start at 4 + 16
    doubles = list(range(37))
    data = (
        b'\x00\x01\x00\x00' + struct.pack('<iII', 12, 500_000_000, len(frame)) + frame + struct.pack('<37d', *doubles)
    )
    stamp, orientation, gyro, accel = imu_sample_from_serialized(data)
    assert stamp == 12.5
    assert orientation == (0, 1, 2, 3) and gyro == (13, 14, 15) and accel == (25, 26, 27)
    # Big-endian, and a frame id that needs padding (length 2: header ends at 4 + 14, doubles at 4 + 16).
    data = b'\x00\x00\x00\x00' + struct.pack('>iII', 3, 0, 2) + b'a\x00' + b'\x00\x00' + struct.pack('>37d', *doubles)
    assert imu_sample_from_serialized(data) == (3.0, (0, 1, 2, 3), (13, 14, 15), (25, 26, 27))


@settings(max_examples=150, deadline=None)
@given(
    frame_id=st.text(alphabet='abcdefghijklmnopqrstuvwxyz_/0123456789', max_size=40),
    sec=st.integers(-(2**31), 2**31 - 1),
    nanosec=st.integers(0, 999_999_999),
    values=st.lists(finite, min_size=10, max_size=10),
)
def test_serialized_imu_equals_the_message(frame_id, sec, nanosec, values):
    """Whatever rclpy serializes, the bytes give exactly what the message object gives."""
    from rclpy.serialization import serialize_message

    from lego_loam_py.core.imu.buffer import imu_sample
    from lego_loam_py.ros.conversions import imu_sample_from_serialized

    msg = imu_message(frame_id, sec, nanosec, values)
    assert imu_sample_from_serialized(serialize_message(msg)) == imu_sample(msg)


@settings(max_examples=200, deadline=None)
@given(data=xcdr1_garbage)
def test_serialized_imu_garbage_is_a_value_error_or_a_sample(data):
    """Bytes that are no Imu raise ValueError (never another error, never a read past the end)."""
    from lego_loam_py.ros.conversions import imu_sample_from_serialized

    try:
        stamp, orientation, gyro, accel = imu_sample_from_serialized(data)
    except ValueError:
        return
    assert len(orientation) == 4 and len(gyro) == 3 and len(accel) == 3 and isinstance(stamp, float)


def test_truncated_serialized_imu_is_refused():
    from rclpy.serialization import serialize_message

    from lego_loam_py.ros.conversions import imu_sample_from_serialized

    data = serialize_message(imu_message('imu_link', 1, 2, [0.0, 0.0, 0.0, 1.0, 0.1, 0.2, 0.3, 0.0, 0.0, 9.8]))
    imu_sample_from_serialized(data)
    for cut in (0, 3, 15, 20, len(data) - 1):
        with pytest.raises(ValueError):
            imu_sample_from_serialized(data[:cut])


def test_node_takes_serialized_imu_and_drops_unreadable_bytes(context):
    """featureAssociation's polled IMU subscription hands it bytes: a valid sample goes into the buffer, bytes
    that are no Imu are dropped with a warning, and the node goes on."""
    from rclpy.serialization import serialize_message

    from lego_loam_py.ros.feature_association_node import FeatureAssociationNode
    from tests.support.inprocess import make_node

    fa, rec = make_node(context, FeatureAssociationNode)
    good = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.1, 0.0, 0.0, 9.81]
    fa.on_imu(serialize_message(imu_message('imu', 100, 0, good)))
    fa.on_imu(b'\x00\x01\x00\x00garbage')
    fa.on_imu(serialize_message(imu_message('imu', 100, 5_000_000, good)))
    assert len(fa.core.imu) == 2
    assert fa.counters['imu_dropped'] == 1
    assert any('IMU message dropped: unreadable message' in text for _, text in rec.warnings)
    assert not rec.errors
    fa.destroy_node()


def test_nodes_take_serialized_clouds_and_drop_unreadable_bytes(context):
    """imageProjection's raw cloud subscription hands it bytes: a scan is segmented from them, bytes that are
    no PointCloud2 are dropped with a warning, and the next scan goes through."""
    from rclpy.serialization import serialize_message

    from lego_loam_py.ros.image_projection_node import ImageProjectionNode
    from tests.support.inprocess import campus_messages, make_node

    ip, rec = make_node(context, ImageProjectionNode)
    clouds = [m for t, m in campus_messages(0.5) if t == '/velodyne_points']
    ip.on_cloud(serialize_message(clouds[0]))
    ip.on_cloud(b'\x00\x01\x00\x00garbage')
    ip.on_cloud(serialize_message(clouds[1]))
    assert [m.header.stamp for m in rec.out('/segmented_cloud')] == [clouds[0].header.stamp, clouds[1].header.stamp]
    assert ip.counters['clouds_dropped'] == 1
    assert any('dropping unreadable cloud' in text for _, text in rec.warnings)
    assert not rec.errors
    ip.destroy_node()


@settings(max_examples=100, deadline=None)
@given(
    frame_id=st.text(alphabet='abcdefghijklmnopqrstuvwxyz_/0123456789', max_size=13),
    sec=st.integers(-(2**31), 2**31 - 1),
    nanosec=st.integers(0, 999_999_999),
    rings=st.integers(0, 70),
    points=st.integers(0, 3000),
    seed=st.integers(0, 2**32 - 1),
)
def test_serialized_cloud_info_equals_the_message(frame_id, sec, nanosec, rings, points, seed):
    """featureAssociation reads CloudInfo from its bytes: whatever rclpy serializes (every frame id length, so
    every alignment; empty and long arrays), the stamp and arrays are exactly those of the message object, in
    the same dtypes; cut short anywhere, the bytes are a ValueError."""
    from rclpy.serialization import serialize_message

    from cloud_msgs.msg import CloudInfo
    from lego_loam_py.ros.conversions import cloud_info_from_msg, cloud_info_from_serialized

    rng = np.random.default_rng(seed)
    msg = CloudInfo()
    msg.header.frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec = frame_id, sec, nanosec
    msg.start_ring_index = rng.integers(-(2**31), 2**31, rings, dtype=np.int64).astype(np.int32).tolist()
    msg.end_ring_index = rng.integers(-(2**31), 2**31, rings, dtype=np.int64).astype(np.int32).tolist()
    msg.start_orientation, msg.end_orientation, msg.orientation_diff = (
        float(np.float32(v)) for v in rng.normal(size=3)
    )
    msg.segmented_cloud_ground_flag = (rng.random(points) < 0.5).tolist()
    msg.segmented_cloud_col_ind = rng.integers(0, 2**32, points, dtype=np.uint64).astype(np.uint32).tolist()
    msg.segmented_cloud_range = rng.normal(size=points).astype(np.float32).tolist()
    data = serialize_message(msg)
    stamp, info = cloud_info_from_serialized(data)
    expected = cloud_info_from_msg(msg)
    assert stamp == sec * 1_000_000_000 + nanosec
    for name, value in vars(expected).items():
        got = getattr(info, name)
        assert np.asarray(got).dtype == np.asarray(value).dtype and np.array_equal(got, value), name
    for cut in sorted({0, 5, 12, len(data) // 2, len(data) - 1}):
        with pytest.raises(ValueError):
            cloud_info_from_serialized(data[:cut])


@settings(max_examples=60, deadline=None)
@given(
    frame_id=st.text(alphabet='abcdefghijklmnopqrstuvwxyz_/0123456789', max_size=13),
    sec=st.integers(-(2**31), 2**31 - 1),
    nanosec=st.integers(0, 999_999_999),
    points=st.integers(0, 3000),
    timed=st.booleans(),
    dense=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
)
def test_serialized_clouds_are_the_messages_rclpy_would_send(frame_id, sec, nanosec, points, timed, dense, seed):
    """The nodes publish clouds and CloudInfo as bytes they write themselves: for every frame id length (so
    every alignment), empty and long arrays, with and without the time field, rclpy reads back exactly the
    message the nodes built before, from bytes as long as rclpy's own (only padding may differ)."""
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2

    from cloud_msgs.msg import CloudInfo
    from lego_loam_py.core.projection.image_projection import CloudInfo as CloudInfoData
    from lego_loam_py.ros.conversions import (
        cloud_from_serialized,
        cloud_info_from_serialized,
        cloud_info_to_msg,
        cloud_msg_to_xyzi,
        make_header,
        serialized_cloud_info,
        serialized_xyzi_cloud,
        xyzi_to_cloud_msg,
    )

    rng = np.random.default_rng(seed)
    header = make_header(sec * 1_000_000_000 + nanosec, frame_id)
    values = rng.normal(scale=30.0, size=(points, 4)).astype(np.float32)
    time = rng.random(points).astype(np.float32) if timed else None
    expected = xyzi_to_cloud_msg(values, header, is_dense=dense, time=time)
    data = serialized_xyzi_cloud(values, header, is_dense=dense, time=time)
    assert isinstance(data, bytes) and len(data) == len(serialize_message(expected))
    assert deserialize_message(data, PointCloud2) == expected
    # ... and read back from the bytes (as the nodes' raw subscriptions do) it is that message again.
    read = cloud_from_serialized(serialize_message(expected))
    assert read.header == expected.header and (read.height, read.width) == (expected.height, expected.width)
    assert [(f.name, f.offset, f.datatype, f.count) for f in read.fields] == [
        (f.name, f.offset, f.datatype, f.count) for f in expected.fields
    ]
    assert (read.is_bigendian, read.point_step, read.row_step, read.is_dense) == (
        expected.is_bigendian,
        expected.point_step,
        expected.row_step,
        expected.is_dense,
    )
    assert bytes(read.data) == bytes(expected.data)
    assert np.array_equal(cloud_msg_to_xyzi(read), values) and np.array_equal(cloud_msg_to_xyzi(expected), values)
    for cut in sorted({5, 12, len(data) // 2, len(data) - 2}):
        with pytest.raises(ValueError):
            cloud_from_serialized(data[:cut])

    info = CloudInfoData(
        start_ring_index=rng.integers(-(2**31), 2**31, 16, dtype=np.int64).astype(np.int32),
        end_ring_index=rng.integers(-(2**31), 2**31, 16, dtype=np.int64).astype(np.int32),
        start_orientation=np.float32(rng.normal()),
        end_orientation=np.float32(rng.normal()),
        orientation_diff=np.float32(rng.normal()),
        segmented_cloud_ground_flag=rng.random(points) < 0.5,
        segmented_cloud_col_ind=rng.integers(0, 2**32, points, dtype=np.uint64).astype(np.uint32),
        segmented_cloud_range=rng.normal(size=points).astype(np.float32),
    )
    expected = cloud_info_to_msg(info, header)
    data = serialized_cloud_info(info, header)
    assert len(data) == len(serialize_message(expected))
    assert deserialize_message(data, CloudInfo) == expected
    stamp, back = cloud_info_from_serialized(data)
    assert stamp == sec * 1_000_000_000 + nanosec
    assert all(np.array_equal(getattr(back, name), value) for name, value in vars(info).items())


def test_transform_of_an_odometry_carries_its_pose_and_frames():
    from lego_loam_py.core.frames import euler_to_matrix
    from lego_loam_py.ros.conversions import make_header, odometry_to_transform, pose_to_odometry, pose_to_transform

    pose = np.eye(4)
    pose[:3, :3] = euler_to_matrix(0.1, -0.7, 2.5)
    pose[:3, 3] = (1.5, -2.0, 30.25)
    odometry = pose_to_odometry(pose, make_header(1_234_000_000_007, 'camera_init'), 'laser_odom')
    transform = odometry_to_transform(odometry)
    expected = pose_to_transform(pose, 1_234_000_000_007, 'camera_init', 'laser_odom')
    assert transform.header == expected.header and transform.child_frame_id == 'laser_odom'
    assert transform.transform == expected.transform
    q = transform.transform.rotation
    assert math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0, rel_tol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    frame_id=st.text(alphabet='abcdefghijklmnopqrstuvwxyz_/0123456789', max_size=13),
    child=st.text(alphabet='abcdefghijklmnopqrstuvwxyz_', min_size=1, max_size=13),
    sec=st.integers(-(2**31), 2**31 - 1),
    nanosec=st.integers(0, 999_999_999),
    angles=st.tuples(*[st.floats(-3.1, 3.1)] * 3),
    position=st.tuples(*[st.floats(-1e4, 1e4)] * 3),
    twist=st.one_of(st.none(), st.tuples(*[st.floats(-1e3, 1e3)] * 6)),
)
def test_serialized_odometry_and_its_transform_are_the_messages_rclpy_would_send(
    frame_id, child, sec, nanosec, angles, position, twist
):
    """Every node publishes its pose as an Odometry and the same transform on /tf, serialized by hand: rclpy
    reads them back as exactly the messages pose_to_odometry and odometry_to_transform give (twist fields,
    which mapOptimization fills with its pre-mapping pose, included)."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message
    from tf2_msgs.msg import TFMessage

    from lego_loam_py.core.frames import euler_to_matrix
    from lego_loam_py.ros.conversions import make_header, odometry_to_transform, pose_to_odometry, serialized_odometry

    pose = np.eye(4)
    pose[:3, :3] = euler_to_matrix(*angles)
    pose[:3, 3] = position
    header = make_header(sec * 1_000_000_000 + nanosec, frame_id)
    extra = {} if twist is None else dict(twist_angular=twist[:3], twist_linear=twist[3:])
    expected = pose_to_odometry(pose, header, child, **extra)
    odometry, transforms = serialized_odometry(pose, header, child, **extra)
    assert deserialize_message(odometry, Odometry) == expected
    assert deserialize_message(transforms, TFMessage) == TFMessage(transforms=[odometry_to_transform(expected)])


def test_the_header_stamp_is_read_from_a_serialized_message():
    """mapOptimization tells odometry publishers apart by the stamp of each serialized message it polls."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message

    from lego_loam_py.ros.conversions import serialized_stamp_ns

    msg = Odometry()
    msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = 1_700_000_000, 123, 'camera_init'
    data = serialize_message(msg)
    assert serialized_stamp_ns(data) == 1_700_000_000_000_000_123
    assert serialized_stamp_ns(data[:8]) is None  # too short for a stamp
    assert serialized_stamp_ns(b'\x00\x03' + data[2:]) is None  # another encoding (parameter list)


def test_an_occupancy_grid_message_holds_the_grid_row_major_from_its_origin():
    """nav_msgs/OccupancyGrid of a 3 x 4 grid: frame, stamp (also the map load time), resolution, size, origin pose
    and the cells row by row from the origin (row 0: the lowest y), as a serialized round trip gives them back."""
    from nav_msgs.msg import OccupancyGrid
    from rclpy.serialization import deserialize_message, serialize_message

    from lego_loam_py.core.mapping import TernaryGrid, message_fields
    from lego_loam_py.ros.conversions import occupancy_grid_msg

    cells = np.full((3, 4), -1, np.int8)
    cells[0, 0], cells[0, 1:], cells[2, 3] = 100, 0, 100
    grid = TernaryGrid(0.05, (-1.25, 2.5), cells, origin_yaw=math.pi / 2)
    msg = deserialize_message(serialize_message(occupancy_grid_msg(message_fields(grid), 1_500_000_000)), OccupancyGrid)
    assert msg.header.frame_id == 'map' and (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1, 500_000_000)
    assert msg.info.map_load_time == msg.header.stamp
    assert msg.info.resolution == pytest.approx(0.05, rel=1e-7)  # (a float32 field)
    assert (msg.info.width, msg.info.height) == (4, 3)
    o = msg.info.origin
    assert (o.position.x, o.position.y, o.position.z) == (-1.25, 2.5, 0.0)
    assert (o.orientation.x, o.orientation.y, o.orientation.z, o.orientation.w) == pytest.approx(
        (0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)), abs=1e-12
    )
    assert list(msg.data) == [100, 0, 0, 0, -1, -1, -1, -1, -1, -1, -1, 100]


@pytest.mark.parametrize(
    ('orientation', 'position', 'problem'),
    [
        ((0.0, 0.0, math.nan, 1.0), (0.0, 0.0, 0.0), 'not finite'),
        ((0.0, 0.0, 0.0, 1.0), (math.inf, 0.0, 0.0), 'not finite'),
        ((0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 'zero norm'),
        ((0.0, 0.0, 0.0, 1.2), (0.0, 0.0, 0.0), 'not of unit length'),
        ((1e200, 0.0, 0.0, 1e200), (0.0, 0.0, 0.0), 'not of unit length'),  # (no overflow on the way)
        ((0.0, 0.0, 0.0, 1.0), (0.0, -2e9, 0.0), 'position beyond'),
    ],
)
def test_odometry_poses_that_are_no_pose_are_refused(orientation, position, problem):
    from nav_msgs.msg import Odometry

    from lego_loam_py.ros.conversions import odometry_to_pose

    msg = Odometry()
    p = msg.pose.pose
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = orientation
    p.position.x, p.position.y, p.position.z = position
    with pytest.raises(ValueError, match=problem):
        odometry_to_pose(msg)


def test_an_odometry_pose_is_its_quaternion_normalised_and_its_position():
    from nav_msgs.msg import Odometry

    from lego_loam_py.core.frames import make_pose, quaternion_to_matrix
    from lego_loam_py.ros.conversions import odometry_to_pose

    msg = Odometry()
    p = msg.pose.pose
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = 0.1, -0.2, 0.3, 0.95  # (norm 1.03)
    p.position.x, p.position.y, p.position.z = 1.5, -2.0, 3.25
    expected = make_pose(quaternion_to_matrix([0.1, -0.2, 0.3, 0.95]), [1.5, -2.0, 3.25])
    assert np.array_equal(odometry_to_pose(msg), expected)
    assert np.allclose(odometry_to_pose(msg)[:3, :3] @ odometry_to_pose(msg)[:3, :3].T, np.eye(3), atol=1e-12)


def _odometry_numbers(msg) -> list[float]:
    """The 85 numbers of an Odometry (or of what odometry_from_serialized reads), in the message's order."""
    p, t = msg.pose.pose, msg.twist.twist
    return [
        *(p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y, p.orientation.z),
        p.orientation.w,
        *msg.pose.covariance,
        *(t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z),
        *msg.twist.covariance,
    ]


def test_serialized_odometry_read_by_hand():
    """The XCDR1 layout of nav_msgs/Odometry, written by hand: the header, the child frame id aligned to 4, then 85
    doubles aligned to 8 (pose, its covariance, twist, its covariance); either byte order."""
    from lego_loam_py.ros.conversions import odometry_from_serialized

    doubles = [float(k) for k in range(85)]
    # frame id 'map' (4 with the NUL: ends at 16), child 'ab' (length at 16, 3 characters: ends at 23, doubles at 24)
    body = struct.pack('<iII', 7, 250, 4) + b'map\x00' + struct.pack('<I', 3) + b'ab\x00' + b'\x00'
    read = odometry_from_serialized(b'\x00\x01\x00\x00' + body + struct.pack('<85d', *doubles))
    assert (read.header.stamp.sec, read.header.stamp.nanosec, read.header.frame_id) == (7, 250, 'map')
    assert read.child_frame_id == 'ab'
    assert _odometry_numbers(read) == doubles
    assert read.pose.pose.orientation.w == 6.0 and read.twist.twist.angular.z == 48.0
    # Big-endian, a frame id that needs padding before the child's length (2: ends at 14, length at 16) and a child
    # whose doubles start right after it (length 8 with the NUL: ends at 28, doubles at 32).
    body = struct.pack('>iII', -3, 0, 2) + b'a\x00' + b'\x00\x00' + struct.pack('>I', 8) + b'abcdefg\x00' + b'\x00' * 4
    read = odometry_from_serialized(b'\x00\x00\x00\x00' + body + struct.pack('>85d', *doubles))
    assert (read.header.stamp.sec, read.header.frame_id, read.child_frame_id) == (-3, 'a', 'abcdefg')
    assert _odometry_numbers(read) == doubles


@settings(max_examples=100, deadline=None)
@given(
    frame_id=st.text(alphabet='abcdefghijklmnopqrstuvwxyz_/0123456789', max_size=20),
    child=st.text(alphabet='abcdefghijklmnopqrstuvwxyz_', max_size=20),
    sec=st.integers(-(2**31), 2**31 - 1),
    nanosec=st.integers(0, 999_999_999),
    values=st.lists(st.floats(width=64), min_size=85, max_size=85),
)
def test_serialized_odometry_reads_as_the_message(frame_id, child, sec, nanosec, values):
    """Whatever rclpy serializes, the bytes read as the message: header, child frame and all 85 numbers bit for bit
    (NaN and infinities included), and the pose and covariance the nodes take of it are the same."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message

    from lego_loam_py.ros.conversions import odometry_covariance, odometry_from_serialized, odometry_to_pose

    msg = Odometry()
    msg.header.frame_id, msg.child_frame_id = frame_id, child
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    p, t = msg.pose.pose, msg.twist.twist
    p.position.x, p.position.y, p.position.z = values[0:3]
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = values[3:7]
    msg.pose.covariance = values[7:43]
    t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z = values[43:49]
    msg.twist.covariance = values[49:85]
    read = odometry_from_serialized(serialize_message(msg))
    assert read.header == msg.header and read.child_frame_id == child
    assert np.array_equal(np.array(_odometry_numbers(read)), np.array(_odometry_numbers(msg)), equal_nan=True)
    assert np.array(_odometry_numbers(read)).tobytes() == np.array(_odometry_numbers(msg)).tobytes()
    for convert in (odometry_to_pose, odometry_covariance):
        try:
            expected = convert(msg)
        except ValueError as exc:
            with pytest.raises(ValueError, match=re.escape(str(exc))):
                convert(read)
            continue
        got = convert(read)
        assert (got is None and expected is None) or got.tobytes() == expected.tobytes()


@settings(max_examples=200, deadline=None)
@given(data=xcdr1_garbage)
def test_serialized_odometry_garbage_is_a_value_error_or_an_odometry(data):
    """Bytes that are no Odometry raise ValueError (never another error, never a read past the end)."""
    from lego_loam_py.ros.conversions import odometry_from_serialized

    try:
        read = odometry_from_serialized(data)
    except ValueError:
        return
    assert len(_odometry_numbers(read)) == 85


def test_truncated_serialized_odometry_is_refused():
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message

    from lego_loam_py.ros.conversions import odometry_from_serialized

    msg = Odometry()
    msg.header.frame_id, msg.child_frame_id = 'camera_init', 'laser_odom'
    data = serialize_message(msg)
    odometry_from_serialized(data)
    for cut in (0, 3, 15, 20, 30, 40, len(data) - 1):
        with pytest.raises(ValueError):
            odometry_from_serialized(data[:cut])


def test_nodes_take_serialized_odometry_and_drop_unreadable_bytes(context):
    """transformFusion's raw odometry subscriptions hand it bytes: a pose is fused and published from them, bytes
    that are no Odometry are dropped with a warning and a counter, and the next message goes through."""
    from rclpy.serialization import serialize_message

    from lego_loam_py.ros.conversions import make_header, pose_to_odometry
    from lego_loam_py.ros.transform_fusion_node import TransformFusionNode
    from tests.support.inprocess import make_node

    tf, rec = make_node(context, TransformFusionNode)

    def odometry(stamp_ns: int, x: float) -> bytes:
        pose = np.eye(4)
        pose[0, 3] = x
        return serialize_message(pose_to_odometry(pose, make_header(stamp_ns, 'camera_init'), 'laser_odom'))

    tf.on_odometry(odometry(10**9, 0.5))
    tf.on_odometry(b'\x00\x01\x00\x00garbage')
    tf.on_mapped(b'\x00\x01\x00\x00' + b'\x00' * 30)
    tf.on_odometry(odometry(10**9 + 10**8, 0.75))
    out = rec.out('/integrated_to_init')
    assert [m.header.stamp.nanosec for m in out] == [0, 100_000_000]
    assert [m.pose.pose.position.x for m in out] == [0.5, 0.75]
    assert tf.counters['odometry_dropped'] == 1 and tf.counters['mapped_dropped'] == 1
    assert any('/laser_odom_to_init dropped' in text for _, text in rec.warnings)
    assert any('/aft_mapped_to_init dropped' in text for _, text in rec.warnings)
    assert not rec.errors
    tf.destroy_node()


@settings(max_examples=300, deadline=None)
@given(data=xcdr1_garbage, cut=st.integers(0, 400))
def test_serialized_cloud_and_cloud_info_garbage_or_cut_short_is_a_value_error(data, cut):
    """Bytes that are no PointCloud2 or CloudInfo, or a real one cut short anywhere, raise ValueError (never another
    error, never a read past the end)."""
    from rclpy.serialization import serialize_message

    from lego_loam_py.ros.conversions import (
        cloud_from_serialized,
        cloud_info_from_serialized,
        make_header,
        xyzi_to_cloud_msg,
    )

    points = np.arange(40, dtype=np.float32).reshape(10, 4)
    cloud = serialize_message(xyzi_to_cloud_msg(points, make_header(10**9, 'camera')))
    for read, whole in ((cloud_from_serialized, cloud), (cloud_info_from_serialized, None)):
        candidates = [data]
        if whole is not None:
            candidates.append(whole[: min(cut, len(whole) - 1)])
        for candidate in candidates:
            try:
                read(candidate)
            except ValueError:
                pass


def test_only_cdr_encodings_reach_rclpys_deserializer(monkeypatch):
    """Bytes in XCDR1 are read here; in XCDR2 (another serializer's output) by rclpy's deserializer; in any other
    encapsulation, or too short to have one, they are refused with ValueError before rclpy sees them: its
    deserializer reads garbage past the end and crashed the test process on random bytes labelled as parameter
    lists."""
    import rclpy.serialization

    from lego_loam_py.ros import conversions

    handed = []

    def deserialize(data, message_type):
        handed.append(bytes(data[:2]))
        raise RuntimeError('not that message')

    monkeypatch.setattr(rclpy.serialization, 'deserialize_message', deserialize)
    readers = (
        conversions.odometry_from_serialized,
        conversions.imu_sample_from_serialized,
        conversions.cloud_from_serialized,
        conversions.cloud_info_from_serialized,
    )
    body = bytes(range(40))
    for read in readers:
        for head in (b'\x00\x02', b'\x00\x03', b'\x00\x04', b'\x00\x0c', b'\x12\x34', b'\x01\x07'):
            with pytest.raises(ValueError, match='is no CDR encoding'):
                read(head + body)
        assert not handed, read
        for head in (b'\x00\x06', b'\x00\x07', b'\x00\x0b'):
            with pytest.raises(ValueError, match='not a serialized'):
                read(head + body)
        assert handed == [b'\x00\x06', b'\x00\x07', b'\x00\x0b'], read
        handed.clear()
