"""PointCloud2 memory layout <-> numpy structured arrays, without ROS imports.

A PointCloud2 is a byte buffer described by ``fields`` (name, offset, datatype, count), ``point_step``,
``row_step``, ``width``, ``height`` and ``is_bigendian``. :func:`cloud_to_array` turns that description
into a numpy structured dtype and views the buffer through it (zero copy when rows are not padded), so any
layout works: the velodyne driver's, Ouster's, xyz-only clouds, padded or big-endian ones, organised
clouds (height > 1). :func:`array_to_cloud` goes the other way. The ROS message adapters live in
``lego_loam_py.ros.conversions`` (rclpy messages) and ``lego_loam_py.bag.io`` (rosbags messages); both
only move attributes in and out of :class:`CloudBuffer`. What the fields of each driver's layout mean (points at
the origin, rings counted from the top, time fields in any unit) is :mod:`lego_loam_py.core.projection.driver_layouts`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lego_loam_py.errors import LegoLoamError

__all__ = [
    'CloudLayoutError',
    'PointField',
    'CloudBuffer',
    'DATATYPE_TO_NUMPY',
    'NUMPY_TO_DATATYPE',
    'dtype_from_fields',
    'fields_from_dtype',
    'cloud_to_array',
    'array_to_cloud',
    'xyz_array',
    'VELODYNE_POINT_DTYPE',
    'VELODYNE_PACKED_DTYPE',
    'velodyne_points',
    'has_field',
    'POINT_XYZI_DTYPE',
    'POINT_XYZIT_DTYPE',
    'xyzi_points',
    'xyzi_array',
]

# sensor_msgs/PointField datatype constants.
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
DATATYPE_TO_NUMPY: dict[int, str] = {
    INT8: 'i1',
    UINT8: 'u1',
    INT16: 'i2',
    UINT16: 'u2',
    INT32: 'i4',
    UINT32: 'u4',
    FLOAT32: 'f4',
    FLOAT64: 'f8',
}
NUMPY_TO_DATATYPE: dict[str, int] = {v: k for k, v in DATATYPE_TO_NUMPY.items()}


MAX_POINT_STEP = 1 << 20  # bytes per point; real layouts use 12-64 (numpy cannot even describe > 2**31 - 1)


class CloudLayoutError(LegoLoamError, ValueError):
    """The fields / sizes of a PointCloud2 do not describe its data."""


@dataclass(frozen=True)
class PointField:
    """One entry of PointCloud2.fields."""

    name: str
    offset: int
    datatype: int
    count: int = 1


@dataclass
class CloudBuffer:
    """Everything of a PointCloud2 but its header: layout, sizes and the raw bytes."""

    fields: Sequence[PointField]
    point_step: int
    width: int
    height: int = 1
    row_step: int | None = None  # None: width * point_step
    is_bigendian: bool = False
    is_dense: bool = True
    data: bytes | bytearray | memoryview | np.ndarray = b''

    @classmethod
    def of_message(cls, msg) -> CloudBuffer:
        """The layout and bytes of a PointCloud2 message, an rclpy or a rosbags one (no copy of the data)."""
        return cls(
            fields=[PointField(f.name, int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields],
            point_step=int(msg.point_step),
            width=int(msg.width),
            height=int(msg.height),
            row_step=int(msg.row_step),
            is_bigendian=bool(msg.is_bigendian),
            is_dense=bool(msg.is_dense),
            data=msg.data,
        )


def dtype_from_fields(fields: Sequence[PointField], point_step: int, is_bigendian: bool = False) -> np.dtype:
    """Structured dtype with the fields at their offsets and itemsize ``point_step``.

    Raises :class:`CloudLayoutError` for unknown datatypes, duplicate or empty names, fields reaching past
    ``point_step`` and overlapping fields.
    """
    if point_step <= 0:
        raise CloudLayoutError(f'point_step must be positive, got {point_step}')
    if point_step > MAX_POINT_STEP:
        raise CloudLayoutError(f'point_step {point_step} is absurd (more than {MAX_POINT_STEP} bytes per point)')
    order = '>' if is_bigendian else '<'
    names, formats, offsets = [], [], []
    spans = []
    for f in fields:
        if not f.name:
            raise CloudLayoutError('a field has an empty name')
        if f.name in names:
            raise CloudLayoutError(f"field '{f.name}' appears twice")
        if f.datatype not in DATATYPE_TO_NUMPY:
            raise CloudLayoutError(f"field '{f.name}' has unknown datatype {f.datatype}")
        if f.count < 1:
            # count 0 occurs in some drivers for padding entries: such a field carries no data.
            continue
        base = np.dtype(order + DATATYPE_TO_NUMPY[f.datatype])
        size = base.itemsize * f.count
        if f.offset < 0 or f.offset + size > point_step:
            raise CloudLayoutError(
                f"field '{f.name}' (offset {f.offset}, {size} bytes) does not fit in point_step {point_step}"
            )
        spans.append((f.offset, f.offset + size, f.name))
        names.append(f.name)
        formats.append(base if f.count == 1 else (base, (f.count,)))
        offsets.append(f.offset)
    spans.sort()
    for (_, end_a, name_a), (start_b, _, name_b) in zip(spans, spans[1:]):
        if start_b < end_a:
            raise CloudLayoutError(f"fields '{name_a}' and '{name_b}' overlap")
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': point_step})


def fields_from_dtype(dtype: np.dtype) -> tuple[list[PointField], int, bool]:
    """(fields, point_step, is_bigendian) describing a structured dtype.

    Sub-array fields become ``count`` > 1. All fields must share one byte order.
    """
    if dtype.names is None:
        raise CloudLayoutError('a point cloud array needs a structured dtype with named fields')
    fields: list[PointField] = []
    byteorders = set()
    for name in dtype.names:
        sub, offset = dtype.fields[name][:2]
        count = 1
        if sub.subdtype is not None:
            sub, shape = sub.subdtype
            count = int(np.prod(shape))
        code = sub.kind + str(sub.itemsize)
        if code not in NUMPY_TO_DATATYPE:
            raise CloudLayoutError(f"field '{name}' has dtype {sub}, which PointCloud2 cannot carry")
        if sub.itemsize > 1:  # '=' is native order, '|' not applicable (1-byte types)
            big = sub.byteorder == '>' or (sub.byteorder == '=' and sys.byteorder == 'big')
            byteorders.add('>' if big else '<')
        fields.append(PointField(name, int(offset), NUMPY_TO_DATATYPE[code], count))
    if len(byteorders) > 1:
        raise CloudLayoutError('all fields of a point cloud must have the same byte order')
    return fields, int(dtype.itemsize), byteorders == {'>'}


def cloud_to_array(cloud: CloudBuffer, flatten: bool = True) -> np.ndarray:
    """View the cloud's bytes as a structured array of shape (height*width,) or (height, width).

    Zero copy unless rows carry padding (row_step > width*point_step) and ``flatten`` is requested.
    Raises :class:`CloudLayoutError` when the layout does not describe the data.
    """
    dtype = dtype_from_fields(cloud.fields, cloud.point_step, cloud.is_bigendian)
    width, height = int(cloud.width), int(cloud.height)
    if width < 0 or height < 0:
        raise CloudLayoutError(f'negative cloud size {width}x{height}')
    row_step = width * cloud.point_step if cloud.row_step is None else int(cloud.row_step)
    if row_step < width * cloud.point_step:
        raise CloudLayoutError(f'row_step {row_step} is smaller than width*point_step {width * cloud.point_step}')
    buffer = cloud.data
    if isinstance(buffer, np.ndarray):
        buffer = buffer.view(np.uint8).reshape(-1)
    size = memoryview(buffer).nbytes
    expected = row_step * height
    if size != expected:
        raise CloudLayoutError(
            f'data has {size} bytes but width*height*point_step says {expected} '
            f'({width}x{height} points of {cloud.point_step} bytes, row_step {row_step})'
        )
    if width == 0 or height == 0:
        empty = np.zeros(0, dtype=dtype)
        return empty if flatten else empty.reshape(height, width)
    if row_step == width * cloud.point_step:
        array = np.frombuffer(buffer, dtype=dtype, count=width * height)
        return array if flatten else array.reshape(height, width)
    raw = np.frombuffer(buffer, dtype=np.uint8)
    grid = np.ndarray((height, width), dtype=dtype, buffer=raw, strides=(row_step, cloud.point_step))
    return grid.reshape(-1) if flatten else grid


def array_to_cloud(
    points: np.ndarray, width: int | None = None, height: int = 1, is_dense: bool | None = None
) -> CloudBuffer:
    """CloudBuffer holding the bytes of a structured array (one copy, into a contiguous buffer).

    ``points`` of shape (N,) become an unorganised cloud (height 1); a 2-D array keeps its shape.
    ``is_dense`` defaults to "no non-finite x/y/z".
    """
    if points.ndim == 2:
        height, width = points.shape
    elif width is None:
        width = points.shape[0] if height == 1 else points.shape[0] // height
    if width * height != points.size:
        raise CloudLayoutError(f'{points.size} points do not form a {width}x{height} cloud')
    fields, point_step, bigendian = fields_from_dtype(points.dtype)
    data = np.ascontiguousarray(points).view(np.uint8).reshape(-1)
    if is_dense is None:
        is_dense = True
        if all(has_field(points, n) for n in 'xyz') and points.size:
            is_dense = all(bool(np.isfinite(points[n]).all()) for n in 'xyz')
    return CloudBuffer(
        fields=fields,
        point_step=point_step,
        width=int(width),
        height=int(height),
        row_step=int(width) * point_step,
        is_bigendian=bigendian,
        is_dense=is_dense,
        data=data,
    )


def has_field(points: np.ndarray, name: str) -> bool:
    return points.dtype.names is not None and name in points.dtype.names


def xyz_array(points: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    """(N, 3) coordinates of a structured cloud (any numeric x/y/z types) as a new array."""
    for name in 'xyz':
        if not has_field(points, name):
            raise CloudLayoutError(f"the cloud has no '{name}' field (fields: {points.dtype.names})")
    out = np.empty((points.size, 3), dtype=dtype)
    flat = points.reshape(-1)
    out[:, 0] = flat['x']
    out[:, 1] = flat['y']
    out[:, 2] = flat['z']
    return out


# The ROS velodyne driver's PointXYZIRT layout (PCL alignment pads x,y,z to 16 bytes): x, y, z, intensity
# float32 at 0/4/8/16, ring uint16 at 20, time float32 (s since the sweep's first firing) at 24.
VELODYNE_POINT_DTYPE = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 'ring', 'time'],
        'formats': ['<f4', '<f4', '<f4', '<f4', '<u2', '<f4'],
        'offsets': [0, 4, 8, 16, 20, 24],
        'itemsize': 32,
    }
)


# The ROS 1 velodyne_pointcloud driver's packed PointcloudXYZIRT (the golden bags use it): x, y, z,
# intensity float32 at 0/4/8/12, ring uint16 at 16, time float32 at 18, point_step 22.
VELODYNE_PACKED_DTYPE = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 'ring', 'time'],
        'formats': ['<f4', '<f4', '<f4', '<f4', '<u2', '<f4'],
        'offsets': [0, 4, 8, 12, 16, 18],
        'itemsize': 22,
    }
)


# PCL's PointXYZI as pcl::toROSMsg publishes it (what every LeGO-LOAM topic carries): x, y, z float32 at
# 0/4/8, intensity float32 at 16, point_step 32.
POINT_XYZI_DTYPE = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity'],
        'formats': ['<f4', '<f4', '<f4', '<f4'],
        'offsets': [0, 4, 8, 16],
        'itemsize': 32,
    }
)


# The same with a per-point time [s since the sweep start] in PointXYZI's padding (offset 20): readers that
# look fields up by name (PCL, rviz, the original's nodes) see a plain PointXYZI.
POINT_XYZIT_DTYPE = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 'time'],
        'formats': ['<f4', '<f4', '<f4', '<f4', '<f4'],
        'offsets': [0, 4, 8, 16, 20],
        'itemsize': 32,
    }
)


def xyzi_points(values: np.ndarray, time: np.ndarray | None = None) -> np.ndarray:
    """(N, 4) x, y, z, intensity (and optional (N,) time) -> PCL PointXYZI layout (+ time at offset 20)."""
    values = np.asarray(values, dtype=np.float32).reshape(-1, 4)
    out = np.zeros(len(values), dtype=POINT_XYZI_DTYPE if time is None else POINT_XYZIT_DTYPE)
    out['x'], out['y'], out['z'], out['intensity'] = values.T
    if time is not None:
        out['time'] = time
    return out


def xyzi_array(points: np.ndarray) -> np.ndarray:
    """Structured cloud with x, y, z and intensity (any types) -> float32 (N, 4)."""
    names = ('x', 'y', 'z', 'intensity')
    for name in names:
        if not has_field(points, name):
            raise CloudLayoutError(f"the cloud has no '{name}' field (fields: {points.dtype.names})")
    # A field at a time into its column: copying an (N, 3) block into (N, 4) rows goes three values at a time,
    # three times slower than the four columns.
    out = np.empty((points.size, 4), dtype=np.float32)
    flat = points.reshape(-1)
    for column, name in enumerate(names):
        out[:, column] = flat[name]
    return out


def velodyne_points(
    xyz: np.ndarray,
    intensity: np.ndarray | None = None,
    ring: np.ndarray | None = None,
    time: np.ndarray | None = None,
    dtype: np.dtype = VELODYNE_POINT_DTYPE,
) -> np.ndarray:
    """Structured array in the velodyne driver's layout from plain arrays (missing fields are 0)."""
    xyz = np.asarray(xyz)
    out = np.zeros(len(xyz), dtype=dtype)
    out['x'], out['y'], out['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if intensity is not None:
        out['intensity'] = intensity
    if ring is not None:
        out['ring'] = ring
    if time is not None:
        out['time'] = time
    return out
