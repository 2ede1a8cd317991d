"""ROS 2 message <-> core data conversions: the only place that touches message internals.

PointCloud2 goes through :mod:`lego_loam_py.core.pointcloud` (any layout, zero-copy reads, one memcpy for
writes: ``array.array.frombytes``; assigning an ndarray to ``msg.data`` would iterate per element).
"""
from __future__ import annotations

import array
import struct
from typing import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion, TransformStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2
from sensor_msgs.msg import PointField as PointFieldMsg
from std_msgs.msg import Header

from lego_loam_py.core.frames import matrix_to_quaternion, quaternion_to_matrix
from lego_loam_py.core.image_projection import CloudInfo as CloudInfoData
from lego_loam_py.core.validation import MAX_POSITION
from lego_loam_py.core.pointcloud import (CloudBuffer, PointField, array_to_cloud, cloud_to_array, xyzi_array,
                                          xyzi_points)

__all__ = [
    'stamp_to_ns', 'ns_to_stamp', 'make_header', 'cloud_msg_to_buffer', 'cloud_msg_to_array',
    'array_to_cloud_msg', 'pose_to_odometry', 'odometry_to_pose', 'pose_to_transform',
    'numpy_to_array', 'xyzi_to_cloud_msg', 'cloud_msg_to_xyzi', 'cloud_info_to_msg', 'cloud_info_from_msg',
    'imu_sample_from_serialized', 'serialized_stamp_ns', 'cloud_info_from_serialized', 'odometry_to_transform',
    'MAX_POSITION',
]


def stamp_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds -> builtin_interfaces/Time (floor division keeps nanosec in [0, 1e9))."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def make_header(stamp: Time | int, frame_id: str) -> Header:
    """Header from a Time message or integer nanoseconds."""
    return Header(stamp=ns_to_stamp(stamp) if isinstance(stamp, int) else stamp, frame_id=frame_id)


# A serialized sensor_msgs/Imu (XCDR1, as Fast DDS and Cyclone DDS send ROS messages): 4 bytes of
# encapsulation, the header (int32 sec, uint32 nanosec, the frame id as uint32 length + characters + NUL),
# then 37 float64 aligned to 8 bytes from the end of the encapsulation: orientation (x, y, z, w), its
# covariance (9), angular velocity (3), its covariance (9), linear acceleration (3), its covariance (9).
_IMU_DOUBLES = 37
_XCDR1 = {b'\x00\x00': '>', b'\x00\x01': '<'}   # encapsulation id -> byte order


def serialized_stamp_ns(data: bytes) -> int | None:
    """Header stamp [ns] of a serialized message that starts with a std_msgs/Header (XCDR1, see above), or
    None for another encoding or too few bytes."""
    order = _XCDR1.get(bytes(data[:2]))
    if order is None or len(data) < 12:
        return None
    sec, nanosec = struct.unpack_from(order + 'iI', data, 4)
    return sec * 1_000_000_000 + nanosec


def imu_sample_from_serialized(data: bytes) -> tuple[float, tuple, tuple, tuple]:
    """``ImuBuffer.add``'s arguments (see :func:`lego_loam_py.core.imu.imu_sample`) straight from the bytes of a
    sensor_msgs/Imu as a ``raw=True`` subscription takes them: about ten times cheaper than rclpy's message
    objects (an IMU at 200 Hz costs a node more in messages than in their use). Other encodings are read
    through rclpy's deserializer; a message too short for its layout raises ValueError."""
    if len(data) < 16:
        raise ValueError(f'serialized Imu of {len(data)} bytes is too short')
    order = _XCDR1.get(bytes(data[:2]))
    if order is None:
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import Imu

        from lego_loam_py.core.imu import imu_sample
        try:
            return imu_sample(deserialize_message(bytes(data), Imu))
        except Exception as exc:   # rclpy raises its RMWError for bytes that are no Imu
            raise ValueError(f'not a serialized Imu ({exc})') from None
    sec, nanosec, name_length = struct.unpack_from(order + 'iII', data, 4)
    start = 4 + ((12 + name_length + 7) & ~7)   # (alignment counts from the end of the encapsulation)
    if start + 8 * _IMU_DOUBLES > len(data):
        raise ValueError(f'serialized Imu of {len(data)} bytes is too short for its frame id ({name_length} bytes)')
    v = struct.unpack_from(order + '37d', data, start)
    return (sec * 1_000_000_000 + nanosec) * 1e-9, v[0:4], v[13:16], v[25:28]


def numpy_to_array(values: np.ndarray, typecode: str) -> array.array:
    """ndarray -> array.array with one memcpy (message sequence fields accept array.array directly)."""
    out = array.array(typecode)
    out.frombytes(np.ascontiguousarray(values, dtype=np.dtype(typecode).newbyteorder('=')).tobytes())
    return out


def cloud_msg_to_buffer(msg: PointCloud2) -> CloudBuffer:
    """The layout and bytes of a PointCloud2 message (no copy of the data)."""
    return CloudBuffer(
        fields=[PointField(f.name, int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields],
        point_step=int(msg.point_step), width=int(msg.width), height=int(msg.height),
        row_step=int(msg.row_step), is_bigendian=bool(msg.is_bigendian), is_dense=bool(msg.is_dense),
        data=msg.data)


def cloud_msg_to_array(msg: PointCloud2, flatten: bool = True) -> np.ndarray:
    """Structured array viewing the message's data (raises CloudLayoutError on an invalid layout)."""
    return cloud_to_array(cloud_msg_to_buffer(msg), flatten=flatten)


def array_to_cloud_msg(points: np.ndarray, header: Header, width: int | None = None, height: int = 1,
                       is_dense: bool | None = None) -> PointCloud2:
    """PointCloud2 carrying a structured array (layout taken from its dtype)."""
    buf = array_to_cloud(points, width=width, height=height, is_dense=is_dense)
    # Field checks stay on: with them, an array.array is stored as is; without, it is copied again.
    msg = PointCloud2(check_fields=True)
    msg.header = header
    msg.height, msg.width = buf.height, buf.width
    msg.fields = [PointFieldMsg(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                  for f in buf.fields]
    msg.is_bigendian = buf.is_bigendian
    msg.point_step = buf.point_step
    msg.row_step = buf.row_step
    data = array.array('B')
    data.frombytes(memoryview(buf.data))
    msg.data = data
    msg.is_dense = buf.is_dense
    return msg


def xyzi_to_cloud_msg(values: np.ndarray, header: Header, is_dense: bool = True,
                      time: np.ndarray | None = None) -> PointCloud2:
    """(N, 4) float32 x, y, z, intensity -> PointCloud2 in PCL's PointXYZI layout (as the original publishes),
    with a ``time`` field in the layout's padding when ``time`` is given."""
    return array_to_cloud_msg(xyzi_points(values, time), header, is_dense=is_dense)


def cloud_msg_to_xyzi(msg: PointCloud2) -> np.ndarray:
    """PointCloud2 with x, y, z, intensity (any layout) -> float32 (N, 4)."""
    return xyzi_array(cloud_msg_to_array(msg))


def cloud_info_to_msg(info: CloudInfoData, header: Header):
    """cloud_msgs/CloudInfo from the core's CloudInfo (arrays as long as the segmented cloud)."""
    from cloud_msgs.msg import CloudInfo

    msg = CloudInfo(check_fields=True)  # with checks on, array.array values are stored without a copy
    msg.header = header
    msg.start_ring_index = numpy_to_array(info.start_ring_index, 'i')
    msg.end_ring_index = numpy_to_array(info.end_ring_index, 'i')
    msg.start_orientation = float(info.start_orientation)
    msg.end_orientation = float(info.end_orientation)
    msg.orientation_diff = float(info.orientation_diff)
    msg.segmented_cloud_col_ind = numpy_to_array(info.segmented_cloud_col_ind, 'I')
    msg.segmented_cloud_range = numpy_to_array(info.segmented_cloud_range, 'f')
    # bool[] is a list; checking 20k elements costs milliseconds and they are bools by construction.
    msg._check_fields = False
    msg.segmented_cloud_ground_flag = np.asarray(info.segmented_cloud_ground_flag, dtype=bool).tolist()
    msg._check_fields = True
    return msg


def cloud_info_from_msg(msg) -> CloudInfoData:
    """The core's CloudInfo from a cloud_msgs/CloudInfo message (copies of the arrays)."""
    return CloudInfoData(
        start_ring_index=np.array(msg.start_ring_index, dtype=np.int32),
        end_ring_index=np.array(msg.end_ring_index, dtype=np.int32),
        start_orientation=np.float32(msg.start_orientation), end_orientation=np.float32(msg.end_orientation),
        orientation_diff=np.float32(msg.orientation_diff),
        segmented_cloud_ground_flag=np.array(msg.segmented_cloud_ground_flag, dtype=bool),
        segmented_cloud_col_ind=np.array(msg.segmented_cloud_col_ind, dtype=np.uint32),
        segmented_cloud_range=np.array(msg.segmented_cloud_range, dtype=np.float32))


def cloud_info_from_serialized(data: bytes, copy: bool = True) -> tuple[int, CloudInfoData]:
    """(header stamp [ns], the core's CloudInfo) straight from the bytes of a cloud_msgs/CloudInfo as a
    ``raw=True`` subscription takes them. rclpy's message holds the ground flags as a Python list of some
    20 000 bools, which costs featureAssociation more than the rest of the message; here every array is one
    ``frombuffer`` (``copy=False``: views of ``data``, enough to check their lengths). Other encodings go
    through rclpy's deserializer; bytes too short for the lengths they announce raise ValueError."""
    order = _XCDR1.get(bytes(data[:2]))
    if order is None:
        from rclpy.serialization import deserialize_message
        from cloud_msgs.msg import CloudInfo
        try:
            msg = deserialize_message(bytes(data), CloudInfo)
        except Exception as exc:   # rclpy raises its RMWError for bytes that are no CloudInfo
            raise ValueError(f'not a serialized CloudInfo ({exc})') from None
        return stamp_to_ns(msg.header.stamp), cloud_info_from_msg(msg)
    body = memoryview(data)[4:]   # (CDR alignment counts from the end of the encapsulation)
    position = 0

    def take(dtype: str, count: int | None = None):
        nonlocal position
        item = np.dtype(order + dtype)
        position = (position + item.alignment - 1) & ~(item.alignment - 1)
        if count is None:   # a sequence: its uint32 length first
            count = int(take('u4', 1)[0])
            position = (position + item.alignment - 1) & ~(item.alignment - 1)
        end = position + count * item.itemsize
        if end > len(body):
            raise ValueError(f'serialized CloudInfo of {len(data)} bytes ends inside its {count}-element field')
        values = np.frombuffer(body, dtype=item, count=count, offset=position)
        position = end
        return values

    sec, nanosec, name_length = (int(v) for v in (*take('i4', 1), *take('u4', 1), *take('u4', 1)))
    take('u1', name_length)   # the frame id and its NUL
    start_ring_index, end_ring_index = take('i4'), take('i4')
    start_orientation, end_orientation, orientation_diff = take('f4', 3)
    ground_flag = take('u1') != 0
    col_ind, ranges = take('u4'), take('f4')

    def native(values: np.ndarray, dtype) -> np.ndarray:
        return values.astype(dtype, copy=copy)

    return sec * 1_000_000_000 + nanosec, CloudInfoData(
        start_ring_index=native(start_ring_index, np.int32), end_ring_index=native(end_ring_index, np.int32),
        start_orientation=np.float32(start_orientation), end_orientation=np.float32(end_orientation),
        orientation_diff=np.float32(orientation_diff), segmented_cloud_ground_flag=ground_flag,
        segmented_cloud_col_ind=native(col_ind, np.uint32), segmented_cloud_range=native(ranges, np.float32))


def pose_to_odometry(pose: np.ndarray, header: Header, child_frame_id: str,
                     twist_angular: Sequence[float] | None = None,
                     twist_linear: Sequence[float] | None = None) -> Odometry:
    """nav_msgs/Odometry with the pose of ``child_frame_id`` in ``header.frame_id`` (4x4 matrix).

    The twist fields are filled only when given (mapOptimization uses them to carry a pose, as the
    original does).
    """
    msg = Odometry()
    msg.header = header
    msg.child_frame_id = child_frame_id
    q = matrix_to_quaternion(pose[:3, :3])
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = (float(v) for v in pose[:3, 3])
    p.orientation = Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
    if twist_angular is not None:
        a = msg.twist.twist.angular
        a.x, a.y, a.z = (float(v) for v in twist_angular)
    if twist_linear is not None:
        lin = msg.twist.twist.linear
        lin.x, lin.y, lin.z = (float(v) for v in twist_linear)
    return msg




def odometry_to_pose(msg: Odometry) -> np.ndarray:
    """4x4 pose of an Odometry message.

    Raises ValueError for non-finite values, a quaternion that is not of unit length (zero, or off by more
    than 10 %: garbage, not a rotation) and positions beyond ``MAX_POSITION``.
    """
    p = msg.pose.pose
    q = np.array([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w])
    t = np.array([p.position.x, p.position.y, p.position.z])
    if not (np.isfinite(q).all() and np.isfinite(t).all()):
        raise ValueError('odometry pose is not finite')
    scale = float(np.abs(q).max())
    norm = scale * float(np.linalg.norm(q / scale)) if scale > 0 else 0.0   # no overflow for huge values
    if norm < 1e-6:
        raise ValueError('odometry orientation quaternion has zero norm')
    if abs(norm - 1.0) > 0.1:
        raise ValueError(f'odometry orientation quaternion is not of unit length (norm {norm:.3g})')
    if not (np.abs(t) <= MAX_POSITION).all():
        raise ValueError(f'odometry position beyond {MAX_POSITION:g} m')
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(q)
    pose[:3, 3] = t
    return pose


def odometry_to_transform(msg: Odometry) -> TransformStamped:
    """The TransformStamped header.frame_id -> child_frame_id of an Odometry message's pose (the TF every node
    sends with its odometry: same stamp, same numbers, no second quaternion from the matrix)."""
    out = TransformStamped()
    out.header = msg.header
    out.child_frame_id = msg.child_frame_id
    p = msg.pose.pose
    out.transform.translation.x, out.transform.translation.y, out.transform.translation.z = \
        p.position.x, p.position.y, p.position.z
    out.transform.rotation = p.orientation
    return out


def pose_to_transform(pose: np.ndarray, stamp: Time | int, parent: str, child: str) -> TransformStamped:
    """TransformStamped parent->child carrying the pose of ``child`` in ``parent``."""
    msg = TransformStamped()
    msg.header = make_header(stamp, parent)
    msg.child_frame_id = child
    q = matrix_to_quaternion(pose[:3, :3])
    tr = msg.transform
    tr.translation.x, tr.translation.y, tr.translation.z = (float(v) for v in pose[:3, 3])
    tr.rotation = Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
    return msg
