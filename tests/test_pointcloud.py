"""PointCloud2 <-> numpy for any layout, through the core and through real rclpy messages."""

from __future__ import annotations

import array

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lego_loam_py.core.pointcloud import (
    FLOAT32,
    FLOAT64,
    INT8,
    UINT8,
    UINT16,
    UINT32,
    VELODYNE_POINT_DTYPE,
    CloudBuffer,
    CloudLayoutError,
    PointField,
    array_to_cloud,
    cloud_to_array,
    dtype_from_fields,
    fields_from_dtype,
    velodyne_points,
    xyz_array,
)
from lego_loam_py.ros.conversions import array_to_cloud_msg, cloud_msg_to_array, make_header

# Ouster driver (ouster-ros) point layout: padding after xyz, u32 t, u16 reflectivity/ring/ambient, u32 range.
OUSTER_FIELDS = [
    PointField('x', 0, FLOAT32),
    PointField('y', 4, FLOAT32),
    PointField('z', 8, FLOAT32),
    PointField('intensity', 16, FLOAT32),
    PointField('t', 20, UINT32),
    PointField('reflectivity', 24, UINT16),
    PointField('ring', 26, UINT16),
    PointField('ambient', 28, UINT16),
    PointField('range', 32, UINT32),
]
OUSTER_STEP = 48


def random_velodyne(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return velodyne_points(
        rng.normal(size=(n, 3)) * 20, rng.uniform(0, 255, n), rng.integers(0, 16, n), np.sort(rng.uniform(0, 0.1, n))
    )


def test_velodyne_layout_is_the_drivers():
    fields, step, big = fields_from_dtype(VELODYNE_POINT_DTYPE)
    assert step == 32 and not big
    assert [(f.name, f.offset, f.datatype) for f in fields] == [
        ('x', 0, FLOAT32),
        ('y', 4, FLOAT32),
        ('z', 8, FLOAT32),
        ('intensity', 16, FLOAT32),
        ('ring', 20, UINT16),
        ('time', 24, FLOAT32),
    ]


def test_velodyne_round_trip_is_exact_and_zero_copy():
    points = random_velodyne(28800)
    buf = array_to_cloud(points)
    assert buf.width == 28800 and buf.height == 1 and buf.row_step == 28800 * 32 and buf.is_dense
    back = cloud_to_array(buf)
    assert back.dtype == points.dtype and np.array_equal(back, points)
    assert np.shares_memory(back, buf.data)  # a view, not a copy


def test_golden_driver_layout_packed_22_bytes():
    """The layout of the golden bags (PointcloudXYZIRT packed: point_step 22, ring at 16, time at 18)."""
    fields = [
        PointField('x', 0, FLOAT32),
        PointField('y', 4, FLOAT32),
        PointField('z', 8, FLOAT32),
        PointField('intensity', 12, FLOAT32),
        PointField('ring', 16, UINT16),
        PointField('time', 18, FLOAT32),
    ]
    raw = bytearray(22 * 3)
    np.frombuffer(raw, dtype='<f4', count=1, offset=22 + 8)[0] = -1.5  # z of point 1
    np.frombuffer(raw, dtype='<u2', count=1, offset=44 + 16)[0] = 15  # ring of point 2
    np.frombuffer(raw, dtype='<f4', count=1, offset=44 + 18)[0] = 0.0999  # time of point 2 (unaligned)
    cloud = cloud_to_array(CloudBuffer(fields, 22, 3, data=bytes(raw)))
    assert cloud['z'][1] == np.float32(-1.5) and cloud['ring'][2] == 15
    assert cloud['time'][2] == np.float32(0.0999)


def test_ouster_like_layout():
    n = 64 * 1024
    raw = np.zeros(n * OUSTER_STEP, dtype=np.uint8)
    grid = np.ndarray((n,), dtype=dtype_from_fields(OUSTER_FIELDS, OUSTER_STEP), buffer=raw)
    grid['x'] = np.arange(n)
    grid['ring'] = np.arange(n) % 64
    grid['t'] = np.arange(n) * 1000
    cloud = cloud_to_array(CloudBuffer(OUSTER_FIELDS, OUSTER_STEP, width=1024, height=64, data=raw))
    assert cloud.shape == (n,)
    assert np.array_equal(cloud['x'], np.arange(n, dtype=np.float32))
    assert np.array_equal(cloud['ring'], np.arange(n) % 64) and cloud['t'][-1] == (n - 1) * 1000
    organised = cloud_to_array(CloudBuffer(OUSTER_FIELDS, OUSTER_STEP, width=1024, height=64, data=raw), flatten=False)
    assert organised.shape == (64, 1024) and organised['ring'][5, 7] == (5 * 1024 + 7) % 64


def test_xyz_only_cloud():
    points = np.zeros(5, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4')])
    points['z'] = [1, 2, 3, 4, 5]
    buf = array_to_cloud(points)
    assert buf.point_step == 12 and [f.name for f in buf.fields] == ['x', 'y', 'z']
    back = cloud_to_array(buf)
    assert np.array_equal(back['z'], [1, 2, 3, 4, 5]) and 'intensity' not in back.dtype.names
    assert xyz_array(back).shape == (5, 3)


def test_big_endian_cloud_reads_the_right_values():
    dtype = np.dtype(
        {
            'names': ['x', 'y', 'z', 'ring'],
            'formats': ['>f8', '>f8', '>f8', '>u2'],
            'offsets': [0, 8, 16, 24],
            'itemsize': 32,
        }
    )
    points = np.zeros(4, dtype=dtype)
    points['x'] = [1.25, -2.5, 3.75, 1e6]
    points['ring'] = [0, 1, 513, 65535]
    buf = array_to_cloud(points)
    assert buf.is_bigendian and buf.fields[0].datatype == FLOAT64
    back = cloud_to_array(buf)
    assert np.array_equal(back['x'], [1.25, -2.5, 3.75, 1e6]) and np.array_equal(back['ring'], [0, 1, 513, 65535])
    # Bytes are really big-endian: the first byte of x = 1.25 (0x3FF4...) is 0x3F.
    assert bytes(buf.data[:2]) == b'\x3f\xf4'


def test_organised_cloud_with_row_padding():
    """height > 1 and row_step > width * point_step (padding at the end of each row)."""
    width, height, step, pad = 7, 3, 16, 5
    row_step = width * step + pad
    raw = bytearray(row_step * height)
    fields = [
        PointField('x', 0, FLOAT32),
        PointField('y', 4, FLOAT32),
        PointField('z', 8, FLOAT32),
        PointField('intensity', 12, FLOAT32),
    ]
    for r in range(height):
        for c in range(width):
            np.frombuffer(raw, '<f4', 1, r * row_step + c * step)[0] = 10 * r + c
    buf = CloudBuffer(fields, step, width, height, row_step, data=bytes(raw))
    grid = cloud_to_array(buf, flatten=False)
    assert grid.shape == (3, 7) and grid['x'][2, 6] == 26
    flat = cloud_to_array(buf)
    assert np.array_equal(flat['x'], [10 * r + c for r in range(3) for c in range(7)])


def test_count_greater_than_one_and_small_types():
    dtype = np.dtype(
        {
            'names': ['x', 'y', 'z', 'rgb', 'label'],
            'formats': ['<f4', '<f4', '<f4', ('u1', (3,)), 'i1'],
            'offsets': [0, 4, 8, 12, 15],
            'itemsize': 16,
        }
    )
    points = np.zeros(3, dtype=dtype)
    points['rgb'] = [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    points['label'] = [-1, 0, 1]
    buf = array_to_cloud(points)
    assert [(f.name, f.datatype, f.count) for f in buf.fields][3:] == [('rgb', UINT8, 3), ('label', INT8, 1)]
    back = cloud_to_array(buf)
    assert np.array_equal(back['rgb'], points['rgb']) and np.array_equal(back['label'], [-1, 0, 1])


def test_non_finite_points_make_a_non_dense_cloud():
    points = random_velodyne(10)
    points['x'][3] = np.nan
    assert not array_to_cloud(points).is_dense
    assert array_to_cloud(random_velodyne(10)).is_dense


def test_empty_cloud():
    empty = np.zeros(0, dtype=VELODYNE_POINT_DTYPE)
    buf = array_to_cloud(empty)
    assert buf.width == 0 and len(cloud_to_array(buf)) == 0
    assert len(cloud_to_array(CloudBuffer(buf.fields, 32, width=0, height=0, data=b''))) == 0


@pytest.mark.parametrize(
    'fields,step,width,height,row_step,size,message',
    [
        ([PointField('x', 0, FLOAT32)], 4, 10, 1, None, 39, 'data has 39 bytes but width*height*point_step says 40'),
        ([PointField('x', 0, FLOAT32)], 4, 10, 2, None, 40, 'says 80'),
        ([PointField('x', 0, FLOAT32), PointField('y', 2, FLOAT32)], 8, 1, 1, None, 8, "'x' and 'y' overlap"),
        ([PointField('x', 0, FLOAT64)], 4, 1, 1, None, 4, 'does not fit in point_step 4'),
        ([PointField('x', 0, 9)], 4, 1, 1, None, 4, 'unknown datatype 9'),
        ([PointField('x', 0, FLOAT32), PointField('x', 4, FLOAT32)], 8, 1, 1, None, 8, "'x' appears twice"),
        ([PointField('', 0, FLOAT32)], 4, 1, 1, None, 4, 'empty name'),
        ([PointField('x', 0, FLOAT32)], 0, 1, 1, None, 0, 'point_step must be positive'),
        ([PointField('x', 0, FLOAT32)], 4, 10, 1, 20, 20, 'row_step 20 is smaller than width*point_step 40'),
    ],
)
def test_invalid_layouts_raise_clear_errors(fields, step, width, height, row_step, size, message):
    with pytest.raises(CloudLayoutError, match=message.replace('*', r'\*').replace('(', r'\(')):
        cloud_to_array(CloudBuffer(fields, step, width, height, row_step, data=bytes(size)))


def test_missing_xyz_is_a_clear_error():
    cloud = cloud_to_array(
        CloudBuffer([PointField('x', 0, FLOAT32), PointField('y', 4, FLOAT32)], 8, 2, data=bytes(16))
    )
    with pytest.raises(CloudLayoutError, match="no 'z' field"):
        xyz_array(cloud)


_DATATYPES = st.sampled_from([1, 2, 3, 4, 5, 6, 7, 8])


@st.composite
def layouts(draw):
    """Random valid layouts: x, y, z plus extra fields of any type, any order, padding, either endianness."""
    names = ['x', 'y', 'z'] + draw(
        st.lists(st.sampled_from(['intensity', 'ring', 'time', 't', 'range']), unique=True, max_size=5)
    )
    names = draw(st.permutations(names))
    offset = 0
    fields = []
    for name in names:
        datatype = draw(_DATATYPES)
        size = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}[datatype]
        offset += draw(st.integers(0, 3))
        fields.append(PointField(name, offset, datatype))
        offset += size
    step = offset + draw(st.integers(0, 8))
    return fields, step, draw(st.booleans())


@settings(max_examples=200, deadline=None)
@given(layout=layouts(), width=st.integers(0, 40), height=st.integers(1, 3), seed=st.integers(0, 2**31))
def test_any_layout_round_trips(layout, width, height, seed):
    fields, step, big = layout
    rng = np.random.default_rng(seed)
    raw = rng.integers(0, 256, width * height * step, dtype=np.uint8).tobytes()
    cloud = cloud_to_array(CloudBuffer(fields, step, width, height, data=raw, is_bigendian=big))
    assert cloud.shape == (width * height,)
    # Each field reads the bytes at its offset with its type and byte order.
    for f in fields:
        dtype = np.dtype(
            ('>' if big else '<') + {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}[f.datatype]
        )
        expected = np.array(
            [np.frombuffer(raw, dtype, 1, i * step + f.offset)[0] for i in range(width * height)], dtype=dtype
        )
        assert cloud[f.name].tobytes() == expected.tobytes()
    again = array_to_cloud(cloud, width=width, height=height)
    assert bytes(again.data) == raw and again.point_step == step
    if any(f.datatype not in (1, 2) for f in fields):  # byte order is moot for 1-byte fields only
        assert again.is_bigendian == big
    assert [(f.name, f.offset, f.datatype) for f in again.fields] == [(f.name, f.offset, f.datatype) for f in fields]


# ------------------------------------------------------------------------------------------------ rclpy messages


def test_rclpy_message_round_trip():
    points = random_velodyne(1000, seed=3)
    msg = array_to_cloud_msg(points, make_header(1_700_000_000_123_456_789, 'velodyne'))
    assert isinstance(msg.data, array.array) and len(msg.data) == 32000
    assert msg.header.stamp.sec == 1_700_000_000 and msg.header.stamp.nanosec == 123_456_789
    assert (msg.width, msg.height, msg.point_step, msg.row_step, msg.is_dense) == (1000, 1, 32, 32000, True)
    assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'intensity', 'ring', 'time']
    back = cloud_msg_to_array(msg)
    assert np.array_equal(back, points) and np.shares_memory(back, msg.data)


def test_rclpy_message_survives_serialization():
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2

    points = random_velodyne(500, seed=4)
    msg = array_to_cloud_msg(points, make_header(5, 'base_link'))
    again = deserialize_message(serialize_message(msg), PointCloud2)
    assert np.array_equal(cloud_msg_to_array(again), points)
