"""IMU buffer of featureAssociation: attitude, gravity-free acceleration, and their integrals.

Each sample (sensor_msgs/Imu, 9-axis: orientation required) is processed as the original's ``imuHandler``:
roll, pitch, yaw from the orientation (REP-103, about x, y, z of the lidar), the gravity component
``g · R^T e_z`` removed from the specific force, the acceleration rotated into the gravity-aligned world
frame (LOAM camera axes), and shift, velocity and gyro angles integrated with constant acceleration
between samples.

The IMU's mounting (:class:`~lego_loam_py.core.frames.ImuMounting`, the ``imu.*`` parameters) is applied once,
as each sample enters the buffer, so that everything after it sees a sample of an IMU at the lidar origin with
its axes, on its clock: the stamp moves back by the time offset, the angular velocity and acceleration are
rotated into lidar axes, the attitude becomes the lidar's, and the lever arm's centripetal and tangential
acceleration ``alpha x r + omega x (omega x r)`` is taken off the accelerometer (``alpha`` from the rates of
consecutive samples, so that its integral is exactly the change of ``omega x r``). Identity mountings take the
original's path, untouched.

Robustness (deviations from the original, which would corrupt its ring buffer): samples with non-finite
values, a quaternion that is not of unit length (zero, or off by more than 10 %), an angular velocity above
100 rad/s or an acceleration above 1000 m/s^2 (no IMU measures that: garbage), older than or equal in time
to the newest sample are rejected with a reason; a sample more than ``reset_after`` (1 s) older than the
newest one means the source restarted (a bag looped): the buffer is cleared and starts again from it
(``resets`` counts these); after a gap longer than one sweep the integration restarts (velocity 0) instead of
using stale slots.

All arrays are in chronological order. Units: s, rad, m, m/s, m/s^2. Axes: camera axes (x left, y up,
z forward) for world vectors; ``angle`` integrates the raw gyro in lidar axes (x, y, z).
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.frames import ImuMounting, euler_to_matrices, rotate_by_euler
from lego_loam_py.core.imu.gyro import GyroAttitude
from lego_loam_py.core.validation import MAX_ACCELERATION, MAX_ANGULAR_VELOCITY, MAX_SPEED

try:  # imu_rotate's products and the attitudes in C (native/feature_kernels.c); optional, NumPy gives the same
    from lego_loam_py.core import _feature_kernels
except ImportError:
    _feature_kernels = None

__all__ = [
    'ImuBuffer',
    'ImuState',
    'SweepAttitude',
    'ImuSweep',
    'imu_sample',
    'imu_mounting',
    'imu_world_rotation',
    'imu_rotate',
    'MAX_ANGULAR_VELOCITY',
    'MAX_ACCELERATION',
    'UNCOVERED',
    'MAX_REACH',
    'MAX_GAP',
    'uncovered_counter',
    'uncovered_warning',
    'warn_uncovered',
]

QUATERNION_NORM_TOLERANCE = 0.1
RESYNC_AFTER = 3  # samples in a row stamped before the newest one that show the newest one's stamp was wrong
# [s] Stamps are float seconds (2.4e-7 s apart near 1.7e9 s): a stamp moved back by imu.time_offset may land one
# step after a scan stamped at the same instant, which must still count as covered.
STAMP_ROUNDING = 1e-6
# [s] A sweep may end this long after the newest sample (an IMU whose messages arrive late, or whose imu.time_offset
# moves them back a little too far): its attitude there is carried on at the last rate. Further, and across a gap
# this long between samples within a sweep, the IMU does not cover it.
MAX_REACH = 0.05
MAX_GAP = 0.05
RATE_BASELINE = 0.03  # [s] the last rate is measured over at least this much of the newest samples
# Why the IMU cannot cover a sweep (ImuBuffer.coverage), and what the user can do about it.
UNCOVERED = {
    'no_samples': 'no IMU sample has come yet',
    'starts_after_sweep': 'the IMU samples begin after the sweep began',
    'ends_before_sweep': "the newest IMU sample is older than the sweep's end by more than {reach:g} s: its messages "
    'arrive late, or imu.time_offset moves their stamps back too far',
    'gap': 'the IMU samples have a gap of more than {gap:g} s within the sweep (lost messages?)',
}


def uncovered_counter(reason: str) -> str:
    """The counter of the scans that went without the IMU for ``reason`` (a key of :data:`UNCOVERED`)."""
    return f'imu_unused_{reason}'


def warn_uncovered(count: int) -> bool:
    """Whether the ``count``-th scan without the IMU for one reason is warned about: from the third (a scan or two
    before the first samples is a normal start) and then every hundredth."""
    return count == 3 or (count > 3 and count % 100 == 0)


def uncovered_warning(reason: str, count: int, stamp_ns: int, time_offset: float) -> str:
    """The warning for scans without the IMU: why, how many so far, and what to change."""
    text = UNCOVERED[reason].format(reach=MAX_REACH, gap=MAX_GAP)
    advice = {
        'ends_before_sweep': f'; set imu.time_offset (now {time_offset:g} s) to the IMU stamp minus the lidar '
        'stamp of the same instant (lego_loam_py calibrate measures it)',
        'starts_after_sweep': f'; imu.time_offset (now {time_offset:g} s) may be too small',
        'no_samples': '; is sensor.imu_topic right, and is the IMU publishing?',
    }.get(reason, '')
    return f'IMU not used on the scan at {stamp_ns * 1e-9:.3f} s ({count} scans so far): {text}{advice}'


def imu_mounting(params) -> ImuMounting:
    """The IMU's mounting from the ``imu.*`` parameters (a :class:`~lego_loam_py.core.params.types.Params`)."""
    imu = params.imu
    return ImuMounting.from_rpy(imu.rotation_rpy, imu.translation, imu.orientation_rpy, imu.time_offset)


def imu_world_rotation(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(n, 3, 3) attitudes in camera axes, ``Ry(yaw) Rx(pitch) Rz(roll)`` (= REP-103 ZYX in lidar axes)."""
    return euler_to_matrices(pitch, yaw, roll)


def imu_rotate(
    left: np.ndarray, roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray, xyz: np.ndarray, native: bool = True
) -> np.ndarray:
    """(n, 3) float64 ``left @ imu_world_rotation(roll, pitch, yaw)[n] @ xyz[n]``, without the (n, 3, 3)
    attitudes (:func:`~lego_loam_py.core.frames.rotate_by_euler`). For float32 points (the features, every scan)
    the products after the sines and cosines run in C when the extension is built, the same operations in one
    pass instead of some twenty NumPy calls over (3, 3, n) arrays; ``native=False``: always rotate_by_euler (the
    tests compare the two)."""
    if native and hasattr(_feature_kernels, 'euler_rotate') and _rotatable_in_c(xyz):
        angles = np.array([np.asarray(a, dtype=float).reshape(-1) for a in (pitch, yaw, roll)])  # as rotate_by_euler
        if angles.shape[1] == len(xyz):
            out = np.empty(angles.shape)
            _feature_kernels.euler_rotate(
                np.ascontiguousarray(left, dtype=np.float64), np.cos(angles), np.sin(angles), xyz, out
            )
            return out.T
    return rotate_by_euler(left, pitch, yaw, roll, xyz)


def _rotatable_in_c(xyz) -> bool:
    """Whether the C rotations (:func:`imu_rotate`, :meth:`ImuBuffer.rotate_at`) take these points: (n, >= 3)
    float32, C-contiguous."""
    return (
        isinstance(xyz, np.ndarray)
        and xyz.dtype == np.float32
        and xyz.ndim == 2
        and xyz.shape[1] >= 3
        and xyz.flags.c_contiguous
    )


def _quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """3x3 rotation of a unit quaternion (x, y, z, w)."""
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass
class ImuState:
    """IMU quantities interpolated at given times (arrays of the query's length)."""

    roll: np.ndarray
    pitch: np.ndarray
    yaw: np.ndarray
    velocity: np.ndarray  # (n, 3) world, camera axes
    shift: np.ndarray  # (n, 3) world, camera axes
    angle: np.ndarray  # (n, 3) integrated gyro, lidar axes


@dataclass
class SweepAttitude:
    """The IMU over one sweep, as featureAssociation's sweep-start model takes it (camera axes)."""

    t_start: float  # sweep start [s]
    r_start: np.ndarray  # (3, 3) IMU attitude at the sweep start
    rel: np.ndarray  # (n,) relative times of the prepared points, for their own attitudes
    roll_start: float  # [rad]
    pitch_start: float  # [rad]


@dataclass
class ImuSweep:
    """What featureAssociation's original model takes from the IMU over one sweep (camera axes, sweep-start frame)."""

    roll_start: float  # [rad]
    pitch_start: float  # [rad]
    delta_end: np.ndarray  # (3, 3) rotation from the sweep end's attitude to the start's
    shift_end: np.ndarray  # (3,) non-linear shift at the sweep end [m]
    velocity_change: np.ndarray  # (3,) velocity change over the sweep [m/s]


class ImuBuffer:
    """Bounded ring of processed IMU samples (``capacity`` = the original's imuQueLength).

    Samples are processed with scalar math (a 200 Hz IMU feeds two nodes: per-sample numpy or scipy calls
    would cost more than the algorithm) and kept as rows; the arrays the queries use are extended by the rows
    added since, when a scan asks for them.
    """

    def __init__(
        self,
        capacity: int = 200,
        gravity: float = 9.81,
        scan_period: float = 0.1,
        mounting: ImuMounting | None = None,
        reset_after: float = 1.0,
        gyro_attitude: bool = False,
    ):
        self.capacity = int(capacity)
        self.gravity = float(gravity)
        self.scan_period = float(scan_period)
        self.mounting = mounting if mounting is not None and not mounting.is_identity else None
        # What add() applies (None: nothing to do): rates and accelerations into lidar axes; the orientation's
        # frame to the lidar's (R_world_lidar = R_world_orientation @ this); the lever arm [m]; the offset [s].
        m = self.mounting
        self._to_lidar = m.rotation if m is not None and not np.array_equal(m.rotation, np.eye(3)) else None
        self._orientation_to_lidar = m.rotation_lidar_orientation.T if m is not None and m.rotates else None
        self._lever_arm = tuple(float(v) for v in m.lever_arm) if m is not None and np.any(m.lever_arm) else None
        self._time_offset = m.time_offset if m is not None else 0.0
        self._last_rate: tuple[float, float, float] | None = None  # lidar-axes rate of the newest sample
        self.reset_after = float(reset_after)
        self.resets = 0
        # One row per sample: time, roll, pitch, yaw, velocity (3), shift (3), angle (3).
        self._rows: deque[tuple[float, ...]] = deque(maxlen=self.capacity)
        self._arrays: np.ndarray | None = None
        self._appended = 0  # rows appended since _arrays was built
        self._rate, self._rate_table = None, None  # _newest_rate() of the table _rate_table (see attitude)
        self._behind: list[float] = []  # stamps of the samples rejected in a row as older than the newest
        self.rejected: dict[str, int] = {}
        self.accepted = 0  # samples taken since the buffer was made (a clear keeps the count)
        # The attitude of the rows: the orientation field's, or integrated from the gyro (core.gyro_attitude).
        self.gyro = GyroAttitude() if gyro_attitude else None
        self.native = True  # the common case of add() in C when the extension is built (tests compare)

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def _native(self) -> bool:
        """Whether :meth:`add` may take a sample in C (the extension is built; only a time offset to apply)."""
        return (
            self.native
            and hasattr(_feature_kernels, 'imu_sample')  # (None, or an extension built before it)
            and self._to_lidar is None
            and self._orientation_to_lidar is None
            and self._lever_arm is None
        )

    def _table_and_rate(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_table` and the newest samples' rates of it (:meth:`_newest_rate`), computed once per table: the
        attitudes of a scan's calls carry on at the same rates."""
        table = self._table()
        if self._rate_table is not table:
            self._rate, self._rate_table = self._newest_rate(), table
        return table, self._rate

    def _table(self) -> np.ndarray:
        if self._arrays is None or self._appended >= len(self._rows):
            self._arrays = np.array(self._rows, dtype=float).reshape(-1, 13)
        elif self._appended:
            # Only the rows appended since (a scan's worth of samples, not the whole buffer, each scan): the rows
            # still kept are the newest of the old table, the same values.
            kept = len(self._rows) - self._appended
            new = list(itertools.islice(self._rows, kept, None))
            self._arrays = np.concatenate((self._arrays[len(self._arrays) - kept :], np.array(new, dtype=float)))
        self._appended = 0
        return self._arrays

    @property
    def _time(self) -> np.ndarray:
        return self._table()[:, 0]

    @property
    def _rpy(self) -> np.ndarray:
        return self._table()[:, 1:4]

    @property
    def _velocity(self) -> np.ndarray:
        return self._table()[:, 4:7]

    @property
    def _shift(self) -> np.ndarray:
        return self._table()[:, 7:10]

    @property
    def _angle(self) -> np.ndarray:
        return self._table()[:, 10:13]

    @property
    def times(self) -> np.ndarray:
        return self._time

    def health_problem(self) -> str | None:
        """Why the integrated state is not sane (non-finite, or a velocity no vehicle reaches), or None."""
        if not self._rows:
            return None
        last = np.asarray(self._rows[-1], dtype=np.float64)
        if not np.isfinite(last).all():
            return 'the IMU integration is not finite'
        speed = float(np.abs(last[4:7]).max())
        if speed > MAX_SPEED:
            return f'the IMU-integrated velocity reaches {speed:.3g} m/s (bound {MAX_SPEED:g} m/s)'
        return None

    def clear(self) -> None:
        """Forget every sample (the rejection and reset counters are kept)."""
        self._rows.clear()
        self._arrays = None
        self._appended = 0
        self._behind = []
        self._last_rate = None
        if self.gyro is not None:
            self.gyro.restart()

    def _reject(self, reason: str) -> str:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return reason

    def add(self, stamp: float, orientation_xyzw, angular_velocity, linear_acceleration) -> str | None:
        """Process one sample; returns None when accepted, else why it was rejected.

        The common case (a sample taken, no rotation or lever arm to apply) runs in C when the extension is built
        (:meth:`_add_native`), the same operations in one call; everything else here."""
        if self._native:
            row = self._add_native(stamp, orientation_xyzw, angular_velocity, linear_acceleration)
            if row is not None:
                self._rows.append(row)
                self._appended += 1
                self.accepted += 1
                if self._behind:
                    self._behind = []
                return None
        try:
            qx, qy, qz, qw = (float(v) for v in orientation_xyzw)
            gx, gy, gz = (float(v) for v in angular_velocity)
            ax, ay, az = (float(v) for v in linear_acceleration)
            stamp = float(stamp)
        except (TypeError, ValueError):
            return self._reject('malformed sample')
        values = (stamp, qx, qy, qz, qw, gx, gy, gz, ax, ay, az)
        if not all(math.isfinite(v) for v in values):
            return self._reject('non-finite value')
        scale = max(abs(qx), abs(qy), abs(qz), abs(qw))
        norm = (
            scale * math.sqrt((qx / scale) ** 2 + (qy / scale) ** 2 + (qz / scale) ** 2 + (qw / scale) ** 2)
            if scale > 0
            else 0.0
        )  # no overflow for huge values
        if norm < 1e-6:
            return self._reject('zero-norm orientation quaternion (the IMU must provide orientation)')
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            return self._reject('orientation quaternion is not of unit length')
        if max(abs(gx), abs(gy), abs(gz)) > MAX_ANGULAR_VELOCITY:
            return self._reject(f'angular velocity beyond {MAX_ANGULAR_VELOCITY:g} rad/s')
        if max(abs(ax), abs(ay), abs(az)) > MAX_ACCELERATION:
            return self._reject(f'acceleration beyond {MAX_ACCELERATION:g} m/s^2')
        if self._time_offset:
            stamp -= self._time_offset  # the lidar's time of the measurement
        last = self._rows[-1] if self._rows else None
        if last is not None and stamp < last[0] - self.reset_after:
            self.clear()  # the source restarted (a bag looped): start again from this sample
            self.resets += 1
            last = None
        if last is not None and stamp <= last[0]:
            # A sample stamped a little ahead of time would hold back every later one: after RESYNC_AFTER
            # samples in a row stamped before it (and after each other), it is the wrong one: start again.
            if stamp < last[0] and (not self._behind or stamp > self._behind[-1]):
                self._behind.append(stamp)
            else:
                self._behind = [stamp] if stamp < last[0] else []
            if len(self._behind) < RESYNC_AFTER:
                return self._reject('stamp not newer than the previous sample (out of order or duplicate)')
            self.clear()
            self.resets += 1
            last = None
        self._behind = []
        qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
        if self._orientation_to_lidar is None:
            # Fixed-axis x, y, z angles (tf getRPY) of the unit quaternion.
            roll = math.atan2(2.0 * (qw * qx + qy * qz), 1.0 - 2.0 * (qx * qx + qy * qy))
            pitch = math.asin(max(-1.0, min(1.0, 2.0 * (qw * qy - qz * qx))))
            yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        else:  # the attitude of the lidar: R_world_lidar = R_world_orientation R_orientation_lidar
            r = _quaternion_matrix(qx, qy, qz, qw) @ self._orientation_to_lidar
            roll = math.atan2(r[2, 1], r[2, 2])
            pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
            yaw = math.atan2(r[1, 0], r[0, 0])
        if self._to_lidar is not None:  # rates and accelerations in lidar axes
            gx, gy, gz = (self._to_lidar @ np.array([gx, gy, gz])).tolist()
            ax, ay, az = (self._to_lidar @ np.array([ax, ay, az])).tolist()
        if self._lever_arm is not None:
            ax, ay, az = self._at_lidar_origin((ax, ay, az), (gx, gy, gz), stamp, last)
        attitude = (roll, pitch, yaw)
        if self.gyro is not None:  # (the orientation field's roll and pitch still take gravity off below)
            following = last is not None and stamp - last[0] < self.scan_period
            attitude = self.gyro.update(stamp - last[0] if following else None, (gx, gy, gz), attitude)
        # Gravity-free acceleration in the body frame, re-ordered into camera axes (x=y_l, y=z_l, z=x_l).
        g = self.gravity
        cr, sr, cp, sp, cy, sy = (
            math.cos(roll),
            math.sin(roll),
            math.cos(pitch),
            math.sin(pitch),
            math.cos(yaw),
            math.sin(yaw),
        )
        bx, by, bz = ay - sr * cp * g, az - cr * cp * g, ax + sp * g
        # World acceleration: Ry(yaw) Rx(pitch) Rz(roll) (camera axes, as imu_world_rotation) times the body one.
        wx = (cy * cr + sy * sp * sr) * bx + (-cy * sr + sy * sp * cr) * by + sy * cp * bz
        wy = cp * sr * bx + cp * cr * by - sp * bz
        wz = (-sy * cr + cy * sp * sr) * bx + (sy * sr + cy * sp * cr) * by + cy * cp * bz
        if last is not None and stamp - last[0] < self.scan_period:
            dt = stamp - last[0]
            v0, s0, a0 = last[4:7], last[7:10], last[10:13]
            world = (wx, wy, wz)
            velocity = tuple(v + w * dt for v, w in zip(v0, world))
            shift = tuple(s + v * dt + w * dt * dt / 2 for s, v, w in zip(s0, v0, world))
            angle = tuple(a + w * dt for a, w in zip(a0, (gx, gy, gz)))
        else:  # first sample, or after a gap: restart the integration
            velocity = (0.0, 0.0, 0.0)
            shift = last[7:10] if last is not None else (0.0, 0.0, 0.0)
            angle = last[10:13] if last is not None else (0.0, 0.0, 0.0)
        self._rows.append((stamp, *attitude, *velocity, *shift, *angle))
        self._appended += 1
        self.accepted += 1
        return None

    def _add_native(self, stamp, orientation_xyzw, angular_velocity, linear_acceleration) -> tuple | None:
        """The row :meth:`add` makes of a sample it takes, from native/feature_kernels.c's ``imu_sample``; None for
        any other sample (rejected, out of order, a restart), which :meth:`add` then handles itself."""
        gyro = self.gyro
        try:
            return _feature_kernels.imu_sample(
                stamp,
                orientation_xyzw,
                angular_velocity,
                linear_acceleration,
                self._rows[-1] if self._rows else None,
                self._time_offset,
                self.reset_after,
                self.scan_period,
                self.gravity,
                QUATERNION_NORM_TOLERANCE,
                MAX_ANGULAR_VELOCITY,
                MAX_ACCELERATION,
                None if gyro is None else gyro.state,
                None if gyro is None else np.ascontiguousarray(gyro.bias, dtype=np.float64),
            )
        except (TypeError, ValueError, OverflowError):  # (not numbers: add says why)
            return None

    def _at_lidar_origin(self, acceleration, rate, stamp: float, last) -> tuple[float, float, float]:
        """The specific force at the lidar origin from the one at the IMU's (lidar axes, m/s^2): without the
        rotation's tangential ``alpha x r`` and centripetal ``omega x (omega x r)`` terms, ``r`` the lever arm.
        ``alpha`` is the change of rate since the previous sample over the time between them (the interval this
        sample's acceleration is integrated over), 0 for the first sample and after a gap."""
        rx, ry, rz = self._lever_arm
        wx, wy, wz = rate
        previous, self._last_rate = self._last_rate, rate
        alpha = (0.0, 0.0, 0.0)
        if previous is not None and last is not None and 0.0 < stamp - last[0] < self.scan_period:
            dt = stamp - last[0]
            alpha = ((wx - previous[0]) / dt, (wy - previous[1]) / dt, (wz - previous[2]) / dt)
        # omega x r, then omega x (omega x r) and alpha x r.
        vx, vy, vz = wy * rz - wz * ry, wz * rx - wx * rz, wx * ry - wy * rx
        cx, cy, cz = wy * vz - wz * vy, wz * vx - wx * vz, wx * vy - wy * vx
        tx, ty, tz = alpha[1] * rz - alpha[2] * ry, alpha[2] * rx - alpha[0] * rz, alpha[0] * ry - alpha[1] * rx
        ax, ay, az = acceleration
        return ax - tx - cx, ay - ty - cy, az - tz - cz

    def covers(self, start: float, end: float, tolerance: float = MAX_REACH) -> bool:
        """True when samples exist at or before ``start`` (within ``STAMP_ROUNDING``) and at or after
        ``end - tolerance``."""
        return len(self._time) >= 2 and self._time[0] <= start + STAMP_ROUNDING and self._time[-1] >= end - tolerance

    def coverage(self, start: float, end: float) -> str | None:
        """Why the samples cannot cover the sweep from ``start`` to ``end`` [s] (a key of :data:`UNCOVERED`), or
        None when they can: from a sample at or before its start to one at most :data:`MAX_REACH` before its end
        (the attitude is carried on beyond it), with no gap over :data:`MAX_GAP` between."""
        times = self._time
        if len(times) < 2:
            return 'no_samples'
        if times[0] > start + STAMP_ROUNDING:
            return 'starts_after_sweep'
        if times[-1] < end - MAX_REACH:
            return 'ends_before_sweep'
        first = max(int(np.searchsorted(times, start + STAMP_ROUNDING, side='right')) - 1, 0)
        last = int(np.searchsorted(times, end, side='left'))
        within = times[first : last + 1]
        if len(within) > 1 and float(np.max(np.diff(within))) > MAX_GAP:
            return 'gap'
        return None

    def interpolate(self, times: np.ndarray) -> ImuState:
        """Linear interpolation at ``times`` [s] (held at the ends); yaw interpolated across +-pi."""
        back, front, ratio = self._bracket(times)

        def lerp(values):
            a, b = values[back], values[front]
            r = ratio.reshape((-1,) + (1,) * (values.ndim - 1))
            return a + (b - a) * r

        rpy = self._lerp_attitude(back, front, ratio, np.atleast_1d(np.asarray(times, dtype=float)))
        return ImuState(
            roll=rpy[:, 0],
            pitch=rpy[:, 1],
            yaw=rpy[:, 2],
            velocity=lerp(self._velocity),
            shift=lerp(self._shift),
            angle=lerp(self._angle),
        )

    def attitude(self, times: np.ndarray, native: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(roll, pitch, yaw) of :meth:`interpolate`, without the other quantities (deskewing needs only these). The
        bracketing, interpolation and carrying on in C when the extension is built (one pass instead of some
        thirty NumPy calls, several times a scan); ``native=False`` runs the NumPy version (the tests compare the
        two)."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        if native and hasattr(_feature_kernels, 'imu_lerp') and times.ndim == 1 and len(self._rows):
            rpy = np.empty((len(times), 3))
            table, rate = self._table_and_rate()
            _feature_kernels.imu_lerp(table, np.ascontiguousarray(times), rpy, MAX_REACH, STAMP_ROUNDING, rate)
        else:
            rpy = self._lerp_attitude(*self._bracket(times), times)
        return rpy[:, 0], rpy[:, 1], rpy[:, 2]

    def rotate_at(self, times: np.ndarray, left: np.ndarray, xyz: np.ndarray, native: bool = True) -> np.ndarray:
        """(n, 3) float64 ``imu_rotate(left, *self.attitude(times), xyz)``: the (n, >= 3) points ``xyz`` turned by
        the IMU attitude at their ``times`` [s] and then by ``left`` (3x3). For float32 points in one C pass when
        the extension is built (the attitudes, their sines and cosines and the products, bit for bit);
        ``native=False``: attitude and imu_rotate in NumPy (the tests compare the two)."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        if (
            native
            and hasattr(_feature_kernels, 'imu_rotate_at')
            and len(self._rows)
            and times.ndim == 1
            and _rotatable_in_c(xyz)
            and len(xyz) == len(times)
        ):
            table, rate = self._table_and_rate()
            out = np.empty((3, len(times)))
            _feature_kernels.imu_rotate_at(
                table,
                np.ascontiguousarray(times),
                MAX_REACH,
                STAMP_ROUNDING,
                rate,
                np.ascontiguousarray(left, dtype=np.float64),
                xyz,
                out,
            )
            return out.T
        return imu_rotate(left, *self.attitude(times, native), xyz, native)

    def _bracket(self, times: np.ndarray):
        """(sample before, sample after, fraction between them) of each time."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        n = len(self._time)
        front = np.clip(np.searchsorted(self._time, times, side='left'), 0, n - 1)
        back = np.maximum(front - 1, 0)
        span = self._time[front] - self._time[back]
        with np.errstate(invalid='ignore', divide='ignore'):
            ratio = np.where(span > 0, (times - self._time[back]) / span, 1.0)
        ratio = np.clip(ratio, 0.0, 1.0)
        beyond = times >= self._time[-1]
        ratio[beyond] = 1.0
        return back, front, ratio

    def _lerp_attitude(
        self, back: np.ndarray, front: np.ndarray, ratio: np.ndarray, times: np.ndarray | None = None
    ) -> np.ndarray:
        """(n, 3) roll, pitch, yaw, the yaw unwrapped across +-pi; beyond the newest sample (``times`` given)
        carried on at the last rate (at most :data:`MAX_REACH`)."""
        rpy_back, rpy_front = self._rpy[back], self._rpy[front]
        rpy = rpy_back + (rpy_front - rpy_back) * ratio[:, None]
        yaw_back, yaw_front = rpy_back[:, 2], rpy_front[:, 2]
        jump = yaw_front - yaw_back
        unwrapped_back = yaw_back + np.where(jump > np.pi, 2 * np.pi, np.where(jump < -np.pi, -2 * np.pi, 0.0))
        rpy[:, 2] = unwrapped_back + (yaw_front - unwrapped_back) * ratio
        if times is not None:
            self._carry_on(rpy, times)
        return rpy

    def _carry_on(self, rpy: np.ndarray, times: np.ndarray) -> None:
        """Carry the attitudes ``rpy`` (n, 3) at ``times`` beyond the newest sample on at the last rate (at most
        :data:`MAX_REACH`), in place."""
        # (float stamps near 1.7e9 s land up to a microsecond past an equal sample's)
        ahead = np.minimum(times - self._time[-1], MAX_REACH)
        if np.any(ahead > STAMP_ROUNDING):
            rpy += np.where(ahead > STAMP_ROUNDING, ahead, 0.0)[:, None] * self._newest_rate()[None, :]

    def _newest_rate(self) -> np.ndarray:
        """(3,) roll, pitch, yaw rates [rad/s] over the newest :data:`RATE_BASELINE` s of samples (0 with one)."""
        times = self._time
        back = max(int(np.searchsorted(times, times[-1] - RATE_BASELINE, side='right')) - 1, 0)
        span = times[-1] - times[back]
        if span <= 0.0:
            return np.zeros(3)
        change = self._rpy[-1] - self._rpy[back]
        change[2] = (change[2] + np.pi) % (2 * np.pi) - np.pi
        return change / span


def imu_sample(msg) -> tuple[float, tuple, tuple, tuple]:
    """``ImuBuffer.add``'s arguments from a sensor_msgs/Imu (an rclpy or a rosbags message, read by attribute):
    (stamp [s], orientation (x, y, z, w), angular velocity [rad/s], linear acceleration [m/s^2])."""
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    stamp_s = (int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)) * 1e-9
    return stamp_s, (o.x, o.y, o.z, o.w), (w.x, w.y, w.z), (a.x, a.y, a.z)
