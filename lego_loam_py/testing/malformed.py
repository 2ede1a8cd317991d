"""Malformed versions of every message type the nodes subscribe to: valid, boundary and absurd field values.

Each ``malformed_*`` function takes a numpy random generator and a valid message (from a real pipeline run)
and returns a copy in which one or a few fields, drawn from every field of the type, hold a boundary or an
absurd value: NaN, inf, 1e308, zero, negative, empty, huge, the wrong length, a stamp far away, a layout
that does not describe the data. The property tests (hypothesis draws the seed) and the DDS campaign
(``benchmarks/campaign.py``) use the same generators, so both cover the same inputs.

``MUTATORS`` maps each subscribed topic to its generator; ``KINDS`` lists, per generator, the mutations it draws
from (reported by the campaign).
"""

from __future__ import annotations

import array
import copy
import math

import numpy as np

__all__ = [
    'malformed_cloud',
    'malformed_cloud_info',
    'malformed_imu',
    'malformed_odometry',
    'MUTATORS',
    'SPECIAL',
    'SPECIAL32',
    'HUGE_CLOUD_POINTS',
]

# Values that break arithmetic: non-finite, the float extremes, signed zero, subnormals, and numbers that are
# finite but absurd for any sensor.
SPECIAL = [math.nan, math.inf, -math.inf, 1e308, -1e308, 3.4e38, 1e30, -1e30, 1e-30, -0.0, 0.0, 5e-324, 1e6, -1e6]
# The same for float32 fields (a message field of type float32 only carries float32 values).
SPECIAL32 = [math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e30, -1e30, 1e-30, -0.0, 0.0, 1e-45, 1e6, -1e6]
HUGE_CLOUD_POINTS = 2_000_000  # a cloud far beyond any range image (16 x 1800 = 28,800 pixels)


def _value(rng: np.random.Generator) -> float:
    return float(rng.choice(SPECIAL))


def _stamp(rng: np.random.Generator, header) -> None:
    """A stamp far from the data's: zero, the epoch's end, a day back or ahead, a fraction of a second ahead."""
    sec = int(header.stamp.sec)
    choice = rng.integers(6)
    if choice == 0:
        header.stamp.sec, header.stamp.nanosec = 0, 0
    elif choice == 1:
        header.stamp.sec = 2**31 - 1
    elif choice == 2:
        header.stamp.sec = max(0, sec - 86400)
    elif choice == 3:
        header.stamp.sec = min(2**31 - 1, sec + 86400)
    elif choice == 4:
        header.stamp.nanosec = int(rng.integers(0, 10**9))
    else:
        header.stamp.sec = min(2**31 - 1, sec + 1)


def _frame(rng: np.random.Generator, header) -> None:
    header.frame_id = str(rng.choice(['', 'x' * 10000, 'frame with spaces', '\u00e9\u00e8', '/velodyne']))


# ---------------------------------------------------------------------------------------------- PointCloud2
def malformed_cloud(rng: np.random.Generator, msg, huge: bool = False):
    """A PointCloud2 with a broken layout, broken values or a size no range image has (``huge``: 2,000,000
    points, a few tens of MB)."""
    from sensor_msgs.msg import PointCloud2, PointField

    if huge:
        out = copy.copy(msg)
        out.header = copy.deepcopy(msg.header)
        step = int(msg.point_step) or 16
        out.height, out.width, out.point_step, out.row_step = 1, HUGE_CLOUD_POINTS, step, step * HUGE_CLOUD_POINTS
        out.fields = copy.deepcopy(msg.fields)
        out.data = array.array('B', bytes(step * HUGE_CLOUD_POINTS))
        return out
    out = PointCloud2()
    out.header = copy.deepcopy(msg.header)
    out.height, out.width = int(msg.height), int(msg.width)
    out.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in msg.fields]
    out.is_bigendian, out.point_step, out.row_step, out.is_dense = (
        msg.is_bigendian,
        int(msg.point_step),
        int(msg.row_step),
        msg.is_dense,
    )
    data = np.frombuffer(bytes(msg.data), np.uint8).copy()
    kind = rng.integers(14)
    if kind == 0:  # values: NaN / inf / huge in x, y, z, intensity, ring, time
        n = out.width * out.height
        if n and out.point_step and out.fields and len(data) == n * out.point_step:
            view = data.reshape(n, out.point_step)
            field = out.fields[int(rng.integers(len(out.fields)))]
            rows = rng.random(n) < rng.choice([0.01, 0.5, 1.0])
            if field.datatype == 7:  # float32
                values = np.full(int(rows.sum()), rng.choice(SPECIAL32), np.float32)
                view[rows, field.offset : field.offset + 4] = values.view(np.uint8).reshape(-1, 4)
            elif field.datatype == 8:  # float64
                values = np.full(int(rows.sum()), _value(rng), np.float64)
                view[rows, field.offset : field.offset + 8] = values.view(np.uint8).reshape(-1, 8)
            else:
                view[rows, field.offset] = 255
    elif kind == 1:  # truncated or extra data
        data = (
            data[: int(rng.integers(0, max(1, len(data))))]
            if rng.random() < 0.5
            else np.concatenate([data, np.zeros(int(rng.integers(1, 64)), np.uint8)])
        )
    elif kind == 2:  # width / height that do not match the data
        out.width = int(rng.choice([0, 1, out.width + 1, 2**31 - 1, 2**32 - 1]))
        out.height = int(rng.choice([0, 1, 2, 65535, 2**32 - 1]))
    elif kind == 3:  # point_step / row_step
        out.point_step = int(rng.choice([0, 1, 3, 2**32 - 1]))
        out.row_step = int(rng.choice([0, 1, 2**32 - 1]))
    elif kind == 4:  # fields: missing x, duplicated, overlapping, beyond the point
        fields = out.fields
        choice = rng.integers(4)
        if choice == 0:
            out.fields = [f for f in fields if f.name != 'x']
        elif choice == 1:
            out.fields = fields + [PointField(name='x', offset=0, datatype=7, count=1)]
        elif choice == 2:
            out.fields = [PointField(name=f.name, offset=0, datatype=f.datatype, count=f.count) for f in fields]
        else:
            out.fields = fields + [PointField(name='beyond', offset=out.point_step + 100, datatype=7, count=1)]
    elif kind == 5 and out.fields:  # datatypes and counts that do not exist or do not fit
        field = out.fields[int(rng.integers(len(out.fields)))]
        field.datatype = int(rng.choice([0, 9, 255]))
        field.count = int(rng.choice([0, 2, 1000, 2**32 - 1]))
    elif kind == 6:  # big-endian claim
        out.is_bigendian = True
    elif kind == 7:
        _stamp(rng, out.header)
    elif kind == 8:
        _frame(rng, out.header)
    elif kind == 9:  # random bytes in a real layout
        data = rng.integers(0, 256, len(data), dtype=np.uint8)
    elif kind == 10:  # empty
        out.width, out.row_step, data = 0, 0, data[:0]
    elif kind == 11:  # plausible numbers, wrong geometry
        n = out.width * out.height
        if n and out.point_step >= 12 and len(data) == n * out.point_step:
            with np.errstate(all='ignore'):
                xyz = data.reshape(n, out.point_step)[:, :12].copy().view(np.float32) * np.float32(
                    rng.choice([0, 1e-3, 1e3])
                )
            data.reshape(n, out.point_step)[:, :12] = xyz.view(np.uint8)
    elif kind == 12:  # no fields at all
        out.fields = []
    else:  # several at once
        return malformed_cloud(rng, malformed_cloud(rng, msg))
    out.data = array.array('B', data.tobytes())
    return out


# ---------------------------------------------------------------------------------------------- CloudInfo
_INFO_ARRAYS = (
    ('start_ring_index', 'i'),
    ('end_ring_index', 'i'),
    ('segmented_cloud_col_ind', 'I'),
    ('segmented_cloud_range', 'f'),
    ('segmented_cloud_ground_flag', None),
)


def set_sequence(msg, name: str, values, typecode: str | None) -> None:
    """Set a CloudInfo array field from any values: a list of bools (``typecode`` None) or an array.array of
    ``typecode`` (the values cast, whatever they are)."""
    if typecode is None:
        setattr(msg, name, [bool(v) for v in values])
    else:
        buffer = array.array(typecode)
        buffer.frombytes(np.asarray(values).astype(np.dtype(typecode)).tobytes())
        setattr(msg, name, buffer)


def malformed_cloud_info(rng: np.random.Generator, msg):
    """A CloudInfo with arrays of other lengths or impossible values, orientations NaN / 0 / 1e-30 / huge /
    inconsistent, or a stamp far away."""
    out = copy.copy(msg)
    out.header = copy.deepcopy(msg.header)
    kind = rng.integers(5)
    if kind <= 1:
        name, typecode = _INFO_ARRAYS[int(rng.integers(len(_INFO_ARRAYS)))]
        values = np.array(getattr(msg, name))
        how = rng.integers(5)
        if how == 0:
            values = values[: int(rng.integers(0, max(1, len(values))))]
        elif how == 1:
            values = np.concatenate([values, values[: int(rng.integers(1, 50))]])
        elif how == 2:
            values = values[:0]
        elif typecode == 'f':
            values = values.astype(np.float32)
            values[rng.random(len(values)) < 0.2] = np.float32(rng.choice(SPECIAL32))
        elif typecode in ('i', 'I'):
            limits = np.iinfo(np.int32 if typecode == 'i' else np.uint32)
            values = rng.integers(limits.min, limits.max, len(values), endpoint=True)
        set_sequence(out, name, values, typecode)
    elif kind <= 3:
        for name in ('start_orientation', 'end_orientation', 'orientation_diff'):
            if rng.random() < 0.5:
                setattr(out, name, float(rng.choice([*SPECIAL32, 0.1, 6.0, -7.0, 2 * math.pi, 4 * math.pi])))
    else:
        _stamp(rng, out.header)
    return out


# -------------------------------------------------------------------------------------------------- Imu
def malformed_imu(rng: np.random.Generator, msg):
    """An Imu message with NaN / huge / zero / non-unit orientation, absurd rates, absurd covariances or a
    stamp far away."""
    out = copy.deepcopy(msg)
    kind = rng.integers(6)
    if kind == 0:
        o = out.orientation
        o.x, o.y, o.z, o.w = (
            float(v)
            for v in rng.choice(
                [(0, 0, 0, 0), (1e200, 0, 0, 1e200), (0, 0, 0, 1e-7), (math.nan, 0, 0, 1), (0.5, 0.5, 0.5, 0.6)]
            )
        )
    elif kind == 1:
        w = out.angular_velocity
        w.x, w.y, w.z = _value(rng), _value(rng), float(rng.choice([0.0, 99.9, 100.1, -150.0]))
    elif kind == 2:
        a = out.linear_acceleration
        a.x, a.y, a.z = _value(rng), float(rng.choice([999.0, 1001.0, -2e4])), _value(rng)
    elif kind == 3:
        name = str(
            rng.choice(['orientation_covariance', 'angular_velocity_covariance', 'linear_acceleration_covariance'])
        )
        setattr(out, name, [float(_value(rng)) for _ in range(9)])
    elif kind == 4:
        _stamp(rng, out.header)
    else:
        _frame(rng, out.header)
    return out


# --------------------------------------------------------------------------------------------- Odometry
def malformed_odometry(rng: np.random.Generator, msg):
    """An Odometry message with a position or a twist (mapOptimization's pre-mapping pose, read by
    transformFusion) that is NaN or absurd, a quaternion that is not a rotation, or a stamp far away."""
    out = copy.deepcopy(msg)
    kind = rng.integers(6)
    p, q = out.pose.pose.position, out.pose.pose.orientation
    if kind == 0:
        p.x, p.y, p.z = _value(rng), float(rng.choice([1e6, 1e6 + 1, -5e5])), _value(rng)
    elif kind == 1:
        q.x, q.y, q.z, q.w = (
            float(v)
            for v in rng.choice(
                [(0, 0, 0, 0), (math.nan, 0, 0, 1), (0, 0, 0, 2), (1e308, 1e308, 0, 0), (0.6, 0, 0, 0.6)]
            )
        )
    elif kind == 2:
        t = out.twist.twist
        t.angular.x, t.linear.y, t.linear.z = _value(rng), _value(rng), float(rng.choice([1e6, 1e7]))
    elif kind == 3:
        out.pose.covariance = [float(_value(rng))] * 36
    elif kind == 4:
        _stamp(rng, out.header)
    else:
        out.child_frame_id = str(rng.choice(['', 'x' * 5000]))
        _frame(rng, out.header)
    return out


MUTATORS = {
    '/velodyne_points': malformed_cloud,
    '/segmented_cloud': malformed_cloud,
    '/outlier_cloud': malformed_cloud,
    '/segmented_cloud_info': malformed_cloud_info,
    '/imu/data': malformed_imu,
    '/laser_cloud_corner_last': malformed_cloud,
    '/laser_cloud_surf_last': malformed_cloud,
    '/outlier_cloud_last': malformed_cloud,
    '/laser_odom_to_init': malformed_odometry,
    '/aft_mapped_to_init': malformed_odometry,
}
