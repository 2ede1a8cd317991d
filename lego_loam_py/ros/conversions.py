"""ROS 2 message <-> core data conversions: the only place that touches message internals.

PointCloud2 goes through :mod:`lego_loam_py.core.pointcloud` (any layout, zero-copy reads, one memcpy for
writes: ``array.array.frombytes``; assigning an ndarray to ``msg.data`` would iterate per element).

The nodes publish their clouds and CloudInfo as serialized bytes (``Publisher.publish(bytes)``, written here by
:class:`_CdrWriter`): rclpy would otherwise convert the Python message into its C twin field by field (about
1.4 ms for a 20 000-point cloud, a third of a millisecond for a CloudInfo's 20 000 bools) before the middleware
serializes it again. Subscribers receive the same message either way.
The other way round, the nodes take clouds, CloudInfo, IMU samples and odometry as bytes (``raw=True``) and read
them here, without rclpy's message objects.
"""

from __future__ import annotations

import array
import functools
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion, TransformStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from sensor_msgs.msg import PointCloud2
from sensor_msgs.msg import PointField as PointFieldMsg
from std_msgs.msg import Header

from lego_loam_py.core.frames import bounded_covariance, matrix_to_quaternion, quaternion_pose
from lego_loam_py.core.pointcloud import (
    CloudBuffer,
    PointField,
    array_to_cloud,
    cloud_to_array,
    xyzi_array,
    xyzi_points,
)
from lego_loam_py.core.projection.cloud_info import CloudInfo as CloudInfoData
from lego_loam_py.core.validation import MAX_POSITION

__all__ = [
    'stamp_to_ns',
    'ns_to_stamp',
    'make_header',
    'cloud_msg_to_buffer',
    'cloud_msg_to_array',
    'array_to_cloud_msg',
    'pose_to_odometry',
    'covariance_fields',
    'odometry_covariance',
    'odometry_to_pose',
    'pose_to_transform',
    'numpy_to_array',
    'xyzi_to_cloud_msg',
    'cloud_msg_to_xyzi',
    'cloud_info_to_msg',
    'cloud_info_from_msg',
    'imu_sample_from_serialized',
    'odometry_from_serialized',
    'serialized_stamp_ns',
    'cloud_info_from_serialized',
    'odometry_to_transform',
    'serialized_cloud',
    'serialized_xyzi_cloud',
    'serialized_cloud_info',
    'occupancy_grid_msg',
    'cloud_from_serialized',
    'SerializedCloud',
    'serialized_odometry',
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
_XCDR1 = {b'\x00\x00': '>', b'\x00\x01': '<'}  # encapsulation id -> byte order
_CDR_ENCAPSULATION = b'\x00\x01\x00\x00'  # what the messages written here start with: XCDR1, little endian
_XCDR2 = frozenset(bytes((0, k)) for k in range(6, 12))  # plain, delimited, parameter list; big, little endian


def serialized_stamp_ns(data: bytes) -> int | None:
    """Header stamp [ns] of a serialized message that starts with a std_msgs/Header (XCDR1, see above), or
    None for another encoding or too few bytes."""
    order = _XCDR1.get(bytes(data[:2]))
    if order is None or len(data) < 12:
        return None
    sec, nanosec = struct.unpack_from(order + 'iI', data, 4)
    return sec * 1_000_000_000 + nanosec


def imu_sample_from_serialized(data: bytes) -> tuple[float, tuple, tuple, tuple]:
    """``ImuBuffer.add``'s arguments (see :func:`lego_loam_py.core.imu.buffer.imu_sample`) straight from the bytes of a
    sensor_msgs/Imu as a ``raw=True`` subscription takes them: about ten times cheaper than rclpy's message
    objects (an IMU at 200 Hz costs a node more in messages than in their use). XCDR2 is read through rclpy's
    deserializer (:func:`_deserialized`); a message too short for its layout or in no CDR encoding raises ValueError."""
    if len(data) < 16:
        raise ValueError(f'serialized Imu of {len(data)} bytes is too short')
    order = _XCDR1.get(bytes(data[:2]))
    if order is None:
        from sensor_msgs.msg import Imu

        from lego_loam_py.core.imu.buffer import imu_sample

        return imu_sample(_deserialized(data, Imu, 'Imu'))
    sec, nanosec, name_length = struct.unpack_from(order + 'iII', data, 4)
    start = 4 + ((12 + name_length + 7) & ~7)  # (alignment counts from the end of the encapsulation)
    if start + 8 * _IMU_DOUBLES > len(data):
        raise ValueError(f'serialized Imu of {len(data)} bytes is too short for its frame id ({name_length} bytes)')
    v = struct.unpack_from(order + '37d', data, start)
    return (sec * 1_000_000_000 + nanosec) * 1e-9, v[0:4], v[13:16], v[25:28]


# A serialized nav_msgs/Odometry (XCDR1): the header as in an Imu, the child frame id (uint32 length + characters +
# NUL, aligned to 4), then 85 float64 aligned to 8: the pose (position, orientation x y z w), its covariance (36), the
# twist (linear, angular), its covariance (36).
_ODOMETRY_DOUBLES = 85


def odometry_from_serialized(data: bytes) -> SimpleNamespace | Odometry:
    """A nav_msgs/Odometry from the bytes a ``raw=True`` subscription takes, as plain attributes under the message's
    own paths (``header`` a std_msgs/Header, ``child_frame_id``, ``pose.pose.position.x`` ..., ``pose.covariance`` and
    ``twist.covariance`` as 36 floats, ``twist.twist.linear.x`` ...): everything here that reads an Odometry reads it.
    A fifth of what rclpy's message objects cost (some dozen nested constructors per message); the numbers are the
    message's own, bit for bit. XCDR2 is read through rclpy's deserializer (:func:`_deserialized`); bytes too short
    for their layout, or in no CDR encoding, raise ValueError."""
    if bytes(data[:2]) not in _XCDR1:
        return _deserialized(data, Odometry, 'Odometry')
    read = _CdrReader(data, 'Odometry')
    sec, nanosec = read.scalar('i4'), read.scalar('u4')
    frame_id, child_frame_id = read.string(), read.string()
    v = read.scalars('f8', _ODOMETRY_DOUBLES)

    def vector(x: float, y: float, z: float) -> SimpleNamespace:
        return SimpleNamespace(x=x, y=y, z=z)

    return SimpleNamespace(
        header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id),
        child_frame_id=child_frame_id,
        pose=SimpleNamespace(
            pose=SimpleNamespace(position=vector(*v[0:3]), orientation=SimpleNamespace(x=v[3], y=v[4], z=v[5], w=v[6])),
            covariance=v[7:43],
        ),
        twist=SimpleNamespace(
            twist=SimpleNamespace(linear=vector(*v[43:46]), angular=vector(*v[46:49])), covariance=v[49:85]
        ),
    )


def numpy_to_array(values: np.ndarray, typecode: str) -> array.array:
    """ndarray -> array.array with one memcpy (message sequence fields accept array.array directly)."""
    out = array.array(typecode)
    out.frombytes(np.ascontiguousarray(values, dtype=np.dtype(typecode).newbyteorder('=')).tobytes())
    return out


def cloud_msg_to_buffer(msg: PointCloud2) -> CloudBuffer:
    """The layout and bytes of a PointCloud2 message (no copy of the data)."""
    return CloudBuffer.of_message(msg)


def cloud_msg_to_array(msg: PointCloud2, flatten: bool = True) -> np.ndarray:
    """Structured array viewing the message's data (raises CloudLayoutError on an invalid layout)."""
    return cloud_to_array(cloud_msg_to_buffer(msg), flatten=flatten)


def array_to_cloud_msg(
    points: np.ndarray, header: Header, width: int | None = None, height: int = 1, is_dense: bool | None = None
) -> PointCloud2:
    """PointCloud2 carrying a structured array (layout taken from its dtype)."""
    buf = array_to_cloud(points, width=width, height=height, is_dense=is_dense)
    # Field checks stay on: with them, an array.array is stored as is; without, it is copied again.
    msg = PointCloud2(check_fields=True)
    msg.header = header
    msg.height, msg.width = buf.height, buf.width
    msg.fields = [PointFieldMsg(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in buf.fields]
    msg.is_bigendian = buf.is_bigendian
    msg.point_step = buf.point_step
    msg.row_step = buf.row_step
    data = array.array('B')
    data.frombytes(memoryview(buf.data))
    msg.data = data
    msg.is_dense = buf.is_dense
    return msg


def xyzi_to_cloud_msg(
    values: np.ndarray, header: Header, is_dense: bool = True, time: np.ndarray | None = None
) -> PointCloud2:
    """(N, 4) float32 x, y, z, intensity -> PointCloud2 in PCL's PointXYZI layout (as the original publishes),
    with a ``time`` field in the layout's padding when ``time`` is given."""
    return array_to_cloud_msg(xyzi_points(values, time), header, is_dense=is_dense)


class _CdrWriter:
    """The bytes of one message in XCDR1 little endian, as Fast DDS and Cyclone DDS exchange ROS messages: the
    4-byte encapsulation, then the fields in order, each aligned to its own size counted from the end of the
    encapsulation; strings and sequences start with their uint32 length (a string's counts its NUL). Padding
    bytes are zero (rclpy leaves them undefined; readers skip them)."""

    def __init__(self):
        self._parts: list = [_CDR_ENCAPSULATION]
        self._size = 0

    def _put(self, data, size: int) -> None:
        self._parts.append(data)
        self._size += size

    def _align(self, alignment: int) -> None:
        pad = -self._size % alignment
        if pad:
            self._put(bytes(pad), pad)

    def scalars(self, fmt: str, *values) -> None:
        """Values of one ``struct`` type (``fmt`` such as 'iI' or '3f': the alignment is its last type's)."""
        self._align(struct.calcsize(fmt[-1]))
        data = struct.pack('<' + fmt, *values)
        self._put(data, len(data))

    def string(self, text: str) -> None:
        data = text.encode() + b'\x00'
        self.scalars('I', len(data))
        self._put(data, len(data))

    def header(self, header: Header) -> None:
        # Wrapped to 32 bits as rclpy's C conversion does with a stamp beyond int32 (a bad input's, echoed).
        self.scalars('II', header.stamp.sec & 0xFFFFFFFF, header.stamp.nanosec & 0xFFFFFFFF)
        self.string(header.frame_id)

    def sequence(self, values: np.ndarray, dtype) -> None:
        """A sequence of ``dtype`` numbers (bool as uint8); the array's bytes are joined without a copy."""
        values = np.ascontiguousarray(values, dtype=np.dtype(dtype).newbyteorder('<'))
        self.scalars('I', values.size)
        self._align(values.dtype.alignment)
        self._put(memoryview(values).cast('B'), values.nbytes)

    def bytes(self) -> bytes:
        return b''.join(self._parts)


def serialized_cloud(points: np.ndarray, header: Header, is_dense: bool | None = None) -> bytes:
    """The serialized sensor_msgs/PointCloud2 that :func:`array_to_cloud_msg` would give."""
    buf = array_to_cloud(points, is_dense=is_dense)
    out = _CdrWriter()
    out.header(header)
    out.scalars('II', buf.height, buf.width)
    out.scalars('I', len(buf.fields))
    for field in buf.fields:
        out.string(field.name)
        out.scalars('I', field.offset)
        out.scalars('B', field.datatype)
        out.scalars('I', field.count)
    out.scalars('?', buf.is_bigendian)
    out.scalars('II', buf.point_step, buf.row_step)
    out.sequence(buf.data, np.uint8)
    out.scalars('?', buf.is_dense)
    return out.bytes()


def serialized_xyzi_cloud(
    values: np.ndarray, header: Header, is_dense: bool = True, time: np.ndarray | None = None
) -> bytes:
    """The serialized form of :func:`xyzi_to_cloud_msg` (PCL's PointXYZI layout, ``time`` in its padding)."""
    return serialized_cloud(xyzi_points(values, time), header, is_dense=is_dense)


def serialized_cloud_info(info: CloudInfoData, header: Header) -> bytes:
    """The serialized cloud_msgs/CloudInfo that :func:`cloud_info_to_msg` would give (the inverse of
    :func:`cloud_info_from_serialized`)."""
    out = _CdrWriter()
    out.header(header)
    out.sequence(info.start_ring_index, np.int32)
    out.sequence(info.end_ring_index, np.int32)
    out.scalars('3f', info.start_orientation, info.end_orientation, info.orientation_diff)
    out.sequence(np.asarray(info.segmented_cloud_ground_flag, dtype=bool), np.uint8)
    out.sequence(info.segmented_cloud_col_ind, np.uint32)
    out.sequence(info.segmented_cloud_range, np.float32)
    return out.bytes()


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
        start_orientation=np.float32(msg.start_orientation),
        end_orientation=np.float32(msg.end_orientation),
        orientation_diff=np.float32(msg.orientation_diff),
        segmented_cloud_ground_flag=np.array(msg.segmented_cloud_ground_flag, dtype=bool),
        segmented_cloud_col_ind=np.array(msg.segmented_cloud_col_ind, dtype=np.uint32),
        segmented_cloud_range=np.array(msg.segmented_cloud_range, dtype=np.float32),
    )


_STRUCT_CODES = {'u1': 'B', 'u4': 'I', 'i4': 'i', 'f4': 'f', 'f8': 'd'}  # numpy code -> struct's


class _CdrReader:
    """Reads the fields of one XCDR1 message in order (the layout of :class:`_CdrWriter`, either byte order):
    arrays are views of the bytes, never copies. Bytes that end inside a field raise ValueError."""

    def __init__(self, data, what: str):
        self.order = _XCDR1[bytes(data[:2])]
        self.body = memoryview(data)[4:]  # (alignment counts from the end of the encapsulation)
        self.position = 0
        self.what = what

    def array(self, dtype: str, count: int | None = None) -> np.ndarray:
        """``count`` numbers of ``dtype`` (numpy code without byte order), or a sequence (its uint32 length
        first) when ``count`` is None."""
        item = np.dtype(self.order + dtype)
        if count is None:
            count = self.scalar('u4')
        self.position = (self.position + item.alignment - 1) & ~(item.alignment - 1)
        end = self._end(count * item.itemsize, count)
        values = np.frombuffer(self.body, dtype=item, count=count, offset=self.position)
        self.position = end
        return values

    def scalar(self, dtype: str):
        """One number of ``dtype`` (numpy code: 'u1', 'u4', 'i4', 'f4', 'f8') as a Python int or float."""
        return self.scalars(dtype, 1)[0]

    def scalars(self, dtype: str, count: int) -> tuple:
        """``count`` numbers of ``dtype`` as Python ints or floats (struct reads them: a message's few scalars cost
        more through NumPy than its arrays)."""
        code = _STRUCT_CODES[dtype]
        size = struct.calcsize(code)
        self.position = (self.position + size - 1) & ~(size - 1)
        end = self._end(size * count, count)
        values = struct.unpack_from(f'{self.order}{count}{code}', self.body, self.position)
        self.position = end
        return values

    def string(self) -> str:
        length = self.scalar('u4')
        end = self._end(length, length)
        text = bytes(self.body[self.position : end])
        self.position = end
        return text.rstrip(b'\x00').decode('utf-8', errors='replace')

    def _end(self, size: int, count: int) -> int:
        """Where a field of ``size`` bytes from the current position ends; ValueError past the bytes."""
        end = self.position + size
        if end > len(self.body):
            raise ValueError(
                f'serialized {self.what} of {len(self.body) + 4} bytes ends inside its {count}-element field'
            )
        return end

    def stamp_ns(self) -> int:
        return self.scalar('i4') * 1_000_000_000 + self.scalar('u4')


def _deserialized(data: bytes, message_type, what: str):
    """rclpy's reading of bytes in XCDR2, the other CDR encoding a middleware may send ROS messages in (ValueError when
    they are not that message). Any other encapsulation is refused here: rclpy's deserializer reads garbage past its
    end and can crash the process on it (random bytes labelled as parameter lists did, in a test), so only an
    encoding a serializer can have produced reaches it."""
    if bytes(data[:2]) not in _XCDR2:
        raise ValueError(
            f'not a serialized {what}: encapsulation {bytes(data[:2]).hex() or "missing"} is no CDR encoding'
        )
    from rclpy.serialization import deserialize_message

    try:
        return deserialize_message(bytes(data), message_type)
    except Exception as exc:  # rclpy raises its RMWError for bytes that are no such message
        raise ValueError(f'not a serialized {what} ({exc})') from None


def cloud_info_from_serialized(data: bytes, copy: bool = True) -> tuple[int, CloudInfoData]:
    """(header stamp [ns], the core's CloudInfo) straight from the bytes of a cloud_msgs/CloudInfo as a
    ``raw=True`` subscription takes them. rclpy's message holds the ground flags as a Python list of some
    20 000 bools, which costs featureAssociation more than the rest of the message; here every array is one
    ``frombuffer`` (``copy=False``: views of ``data``, enough to check their lengths). XCDR2 goes through rclpy's
    deserializer (:func:`_deserialized`); bytes too short for the lengths they announce raise ValueError."""
    if bytes(data[:2]) not in _XCDR1:
        from cloud_msgs.msg import CloudInfo

        msg = _deserialized(data, CloudInfo, 'CloudInfo')
        return stamp_to_ns(msg.header.stamp), cloud_info_from_msg(msg)
    read = _CdrReader(data, 'CloudInfo')
    stamp = read.stamp_ns()
    read.string()  # the frame id
    start_ring_index, end_ring_index = read.array('i4'), read.array('i4')
    start_orientation, end_orientation, orientation_diff = read.array('f4', 3)
    ground_flag = read.array('u1') != 0
    col_ind, ranges = read.array('u4'), read.array('f4')

    def native(values: np.ndarray, dtype) -> np.ndarray:
        return values.astype(dtype, copy=copy)

    return stamp, CloudInfoData(
        start_ring_index=native(start_ring_index, np.int32),
        end_ring_index=native(end_ring_index, np.int32),
        start_orientation=np.float32(start_orientation),
        end_orientation=np.float32(end_orientation),
        orientation_diff=np.float32(orientation_diff),
        segmented_cloud_ground_flag=ground_flag,
        segmented_cloud_col_ind=native(col_ind, np.uint32),
        segmented_cloud_range=native(ranges, np.float32),
    )


@dataclass
class SerializedCloud:
    """A sensor_msgs/PointCloud2 read from its bytes (:func:`cloud_from_serialized`): the message's fields,
    ``data`` a view of the bytes. Everything that reads a PointCloud2 message here reads it too."""

    header: Header
    height: int
    width: int
    fields: list
    is_bigendian: bool
    point_step: int
    row_step: int
    data: memoryview
    is_dense: bool


def cloud_from_serialized(data: bytes) -> SerializedCloud | PointCloud2:
    """A PointCloud2 from the bytes a ``raw=True`` subscription takes, without rclpy's copy of the data into a
    Python message (half a millisecond for a VLP-16 scan); XCDR2 through rclpy's deserializer (:func:`_deserialized`).
    Bytes too short for what they announce raise ValueError."""
    if bytes(data[:2]) not in _XCDR1:
        return _deserialized(data, PointCloud2, 'PointCloud2')
    read = _CdrReader(data, 'PointCloud2')
    sec, nanosec = read.scalar('i4'), read.scalar('u4')
    header = Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=read.string())
    height, width = (int(v) for v in read.array('u4', 2))
    fields = []
    for _ in range(read.scalar('u4')):
        name = read.string()
        offset, datatype, count = read.scalar('u4'), read.scalar('u1'), read.scalar('u4')
        fields.append(PointField(name, offset, datatype, count))
    is_bigendian = bool(read.scalar('u1'))
    point_step, row_step = (int(v) for v in read.array('u4', 2))
    points = read.array('u1')
    return SerializedCloud(
        header=header,
        height=height,
        width=width,
        fields=fields,
        is_bigendian=is_bigendian,
        point_step=point_step,
        row_step=row_step,
        data=memoryview(points),
        is_dense=bool(read.scalar('u1')),
    )


def covariance_fields(covariance: np.ndarray | None) -> list[float]:
    """The 36 numbers of a message's pose covariance (row-major 6x6, ROS order x, y, z, rot x, rot y, rot z) of a
    core covariance (:mod:`lego_loam_py.core.frames`: in header.frame_id's axes), bounded to be finite, symmetric
    and positive definite; None: 36 zeros (unknown)."""
    if covariance is None:
        return [0.0] * 36
    return bounded_covariance(covariance).reshape(-1).tolist()


def odometry_covariance(msg: Odometry) -> np.ndarray | None:
    """The 6x6 pose covariance of an Odometry message, or None when it is unknown (all zeros), not finite or absurd
    (beyond 1e12: no sensor's pose is that uncertain and such numbers would overflow what is computed from them)."""
    covariance = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)
    if not np.isfinite(covariance).all() or not covariance.any() or np.abs(covariance).max() > 1e12:
        return None
    return covariance


def pose_to_odometry(
    pose: np.ndarray,
    header: Header,
    child_frame_id: str,
    twist_angular: Sequence[float] | None = None,
    twist_linear: Sequence[float] | None = None,
    pose_covariance: np.ndarray | None = None,
    twist_covariance: np.ndarray | None = None,
) -> Odometry:
    """nav_msgs/Odometry with the pose of ``child_frame_id`` in ``header.frame_id`` (4x4 matrix) and its 6x6
    covariance (:func:`covariance_fields`; None: zeros).

    The twist fields are filled only when given (mapOptimization uses them to carry a pose, as the
    original does); the twist covariance (linear, angular; child_frame_id's axes) only with a true twist (the REP-105
    odometry's), else zero.
    """
    msg = Odometry()
    msg.header = header
    msg.child_frame_id = child_frame_id
    q = matrix_to_quaternion(pose[:3, :3])
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = (float(v) for v in pose[:3, 3])
    p.orientation = Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
    msg.pose.covariance = covariance_fields(pose_covariance)
    if twist_covariance is not None:
        msg.twist.covariance = covariance_fields(twist_covariance)
    if twist_angular is not None:
        a = msg.twist.twist.angular
        a.x, a.y, a.z = (float(v) for v in twist_angular)
    if twist_linear is not None:
        lin = msg.twist.twist.linear
        lin.x, lin.y, lin.z = (float(v) for v in twist_linear)
    return msg


def serialized_odometry(
    pose: np.ndarray,
    header: Header,
    child_frame_id: str,
    twist_angular: Sequence[float] | None = None,
    twist_linear: Sequence[float] | None = None,
    pose_covariance: np.ndarray | None = None,
) -> tuple[bytes, bytes]:
    """The serialized nav_msgs/Odometry that :func:`pose_to_odometry` would give, and the tf2_msgs/TFMessage
    carrying its transform (:func:`odometry_to_transform`): the two every node publishes per pose, from one
    quaternion. Each is one ``struct`` pack of the layout :class:`_CdrWriter` would write field by field (the same
    bytes; a few Python calls instead of some forty, three times a scan)."""
    q = matrix_to_quaternion(pose[:3, :3])
    position = [float(v) for v in pose[:3, 3]]
    orientation = [float(v) for v in q]
    frame, child = header.frame_id.encode(), child_frame_id.encode()
    odometry_layout, transform_layout = _pose_layouts(len(frame), len(child))
    stamp = (header.stamp.sec & 0xFFFFFFFF, header.stamp.nanosec & 0xFFFFFFFF)  # (wrapped as _CdrWriter.header)
    twist = [float(v) for v in (twist_linear if twist_linear is not None else (0.0, 0.0, 0.0))] + [
        float(v) for v in (twist_angular if twist_angular is not None else (0.0, 0.0, 0.0))
    ]
    odometry = odometry_layout.pack(
        *stamp,
        len(frame) + 1,
        frame,
        len(child) + 1,
        child,
        *position,
        *orientation,
        *covariance_fields(pose_covariance),  # the pose, its covariance
        *twist,
        *_ZERO_COVARIANCE,  # the twist (linear, angular), its covariance (no twist)
    )
    transforms = transform_layout.pack(1, *stamp, len(frame) + 1, frame, len(child) + 1, child, *position, *orientation)
    return _CDR_ENCAPSULATION + odometry, _CDR_ENCAPSULATION + transforms


_ZERO_COVARIANCE = (0.0,) * 36


@functools.lru_cache(maxsize=64)
def _pose_layouts(frame_length: int, child_length: int) -> tuple[struct.Struct, struct.Struct]:
    """The XCDR1 layouts (after the encapsulation) of an Odometry and of a TFMessage with one transform, for frame
    ids of these lengths [bytes, without the NUL]: each field aligned to its own size, padding zero."""

    def strings(at: int) -> tuple[str, int]:  # header.frame_id then child_frame_id, from offset ``at``
        layout = ''
        for length in (frame_length, child_length):
            pad = -at % 4
            layout += f'{pad}xI{length + 1}s'
            at += pad + 4 + length + 1
        return layout, at

    head, at = strings(8)  # (after the stamp)
    odometry = struct.Struct(f'<II{head}{-at % 8}x85d')  # pose 7, covariance 36, twist 6, covariance 36
    head, at = strings(12)  # (after the transform count and the stamp)
    transform = struct.Struct(f'<III{head}{-at % 8}x7d')
    return odometry, transform


def odometry_to_pose(msg: Odometry) -> np.ndarray:
    """4x4 pose of an Odometry message.

    Raises ValueError for non-finite values, a quaternion that is not of unit length (zero, or off by more
    than 10 %: garbage, not a rotation) and positions beyond ``MAX_POSITION``.
    """
    p = msg.pose.pose
    q = [float(v) for v in (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)]
    t = [float(v) for v in (p.position.x, p.position.y, p.position.z)]
    if not all(math.isfinite(v) for v in (*q, *t)):
        raise ValueError('odometry pose is not finite')
    norm = math.hypot(*q)  # (no overflow for huge values)
    if norm < 1e-6:
        raise ValueError('odometry orientation quaternion has zero norm')
    if abs(norm - 1.0) > 0.1:
        raise ValueError(f'odometry orientation quaternion is not of unit length (norm {norm:.3g})')
    if any(abs(v) > MAX_POSITION for v in t):
        raise ValueError(f'odometry position beyond {MAX_POSITION:g} m')
    return quaternion_pose(q, t)


def odometry_to_transform(msg: Odometry) -> TransformStamped:
    """The TransformStamped header.frame_id -> child_frame_id of an Odometry message's pose (the TF every node
    sends with its odometry: same stamp, same numbers, no second quaternion from the matrix)."""
    out = TransformStamped()
    out.header = msg.header
    out.child_frame_id = msg.child_frame_id
    p = msg.pose.pose
    out.transform.translation.x, out.transform.translation.y, out.transform.translation.z = (
        p.position.x,
        p.position.y,
        p.position.z,
    )
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


def occupancy_grid_msg(fields, stamp: Time | int) -> OccupancyGrid:
    """A nav_msgs/OccupancyGrid of ``fields`` (core.mapping.occupancy_grid.OccupancyGridFields: the frame, the
    resolution [m], the size, the origin's pose, the int8 cells row-major from the origin); ``stamp`` is both the
    header's and ``info.map_load_time`` (when this grid was made)."""
    msg = OccupancyGrid()
    msg.header = make_header(stamp, fields.frame_id)
    msg.info.map_load_time = msg.header.stamp
    msg.info.resolution = float(fields.resolution)
    msg.info.width, msg.info.height = int(fields.width), int(fields.height)
    position, orientation = msg.info.origin.position, msg.info.origin.orientation
    position.x, position.y, position.z = (float(v) for v in fields.origin_position)
    orientation.x, orientation.y, orientation.z, orientation.w = (float(v) for v in fields.origin_orientation)
    msg.data = fields.data  # (an array.array('b'): taken as is, no per-element copy)
    return msg


def transform_to_pose(transform: TransformStamped) -> np.ndarray:
    """4x4 pose of ``child_frame_id`` in ``header.frame_id`` carried by a TransformStamped (the inverse of
    :func:`pose_to_transform`)."""
    translation, rotation = transform.transform.translation, transform.transform.rotation
    return quaternion_pose(
        (rotation.x, rotation.y, rotation.z, rotation.w), (translation.x, translation.y, translation.z)
    )
