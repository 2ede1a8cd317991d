"""IMU buffer of featureAssociation: attitude, gravity-free acceleration, and their integrals.

Each sample (sensor_msgs/Imu, 9-axis: orientation required) is processed as the original's ``imuHandler``:
roll, pitch, yaw from the orientation (REP-103, about x, y, z of the lidar), the gravity component
``g · R^T e_z`` removed from the specific force, the acceleration rotated into the gravity-aligned world
frame (LOAM camera axes), and shift, velocity and gyro angles integrated with constant acceleration
between samples. The IMU is assumed axis-aligned with the lidar unless ``imu_to_lidar`` says otherwise.

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

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from lego_loam_py.core.frames import euler_to_matrices

__all__ = ['ImuBuffer', 'ImuState', 'imu_world_rotation', 'MAX_ANGULAR_VELOCITY', 'MAX_ACCELERATION']

MAX_ANGULAR_VELOCITY = 100.0   # [rad/s] anything faster is garbage (gyros saturate at 35-70 rad/s)
MAX_ACCELERATION = 1000.0      # [m/s^2] about 100 g (accelerometers saturate at 16-200 g)
QUATERNION_NORM_TOLERANCE = 0.1


def imu_world_rotation(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(n, 3, 3) attitudes in camera axes, ``Ry(yaw) Rx(pitch) Rz(roll)`` (= REP-103 ZYX in lidar axes)."""
    return euler_to_matrices(pitch, yaw, roll)


@dataclass
class ImuState:
    """IMU quantities interpolated at given times (arrays of the query's length)."""

    roll: np.ndarray
    pitch: np.ndarray
    yaw: np.ndarray
    velocity: np.ndarray   # (n, 3) world, camera axes
    shift: np.ndarray      # (n, 3) world, camera axes
    angle: np.ndarray      # (n, 3) integrated gyro, lidar axes


class ImuBuffer:
    """Bounded ring of processed IMU samples (``capacity`` = the original's imuQueLength)."""

    def __init__(self, capacity: int = 200, gravity: float = 9.81, scan_period: float = 0.1,
                 imu_to_lidar: np.ndarray | None = None, reset_after: float = 1.0):
        self.capacity = int(capacity)
        self.gravity = float(gravity)
        self.scan_period = float(scan_period)
        self.imu_to_lidar = None if imu_to_lidar is None else np.asarray(imu_to_lidar, dtype=float)
        self.reset_after = float(reset_after)
        self.resets = 0
        self._time = np.zeros(0)
        self._rpy = np.zeros((0, 3))
        self._velocity = np.zeros((0, 3))
        self._shift = np.zeros((0, 3))
        self._angle = np.zeros((0, 3))
        self.rejected: dict[str, int] = {}

    def __len__(self) -> int:
        return len(self._time)

    @property
    def times(self) -> np.ndarray:
        return self._time

    def clear(self) -> None:
        """Forget every sample (the rejection and reset counters are kept)."""
        rejected, resets = self.rejected, self.resets
        self.__init__(self.capacity, self.gravity, self.scan_period, self.imu_to_lidar, self.reset_after)
        self.rejected, self.resets = rejected, resets

    def _reject(self, reason: str) -> str:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return reason

    def add(self, stamp: float, orientation_xyzw, angular_velocity, linear_acceleration) -> str | None:
        """Process one sample; returns None when accepted, else why it was rejected."""
        q = np.asarray(orientation_xyzw, dtype=float)
        gyro = np.asarray(angular_velocity, dtype=float)
        acc = np.asarray(linear_acceleration, dtype=float)
        if q.shape != (4,) or gyro.shape != (3,) or acc.shape != (3,):
            return self._reject('malformed sample')
        if not (np.isfinite(stamp) and np.isfinite(q).all() and np.isfinite(gyro).all() and np.isfinite(acc).all()):
            return self._reject('non-finite value')
        scale = float(np.abs(q).max())
        norm = scale * float(np.linalg.norm(q / scale)) if scale > 0 else 0.0   # no overflow for huge values
        if norm < 1e-6:
            return self._reject('zero-norm orientation quaternion (the IMU must provide orientation)')
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            return self._reject('orientation quaternion is not of unit length')
        if not (np.abs(gyro) <= MAX_ANGULAR_VELOCITY).all():
            return self._reject(f'angular velocity beyond {MAX_ANGULAR_VELOCITY:g} rad/s')
        if not (np.abs(acc) <= MAX_ACCELERATION).all():
            return self._reject(f'acceleration beyond {MAX_ACCELERATION:g} m/s^2')
        if len(self._time) and stamp < self._time[-1] - self.reset_after:
            self.clear()   # the source restarted (a bag looped): start again from this sample
            self.resets += 1
        if len(self._time) and stamp <= self._time[-1]:
            return self._reject('stamp not newer than the previous sample (out of order or duplicate)')
        rotation = Rotation.from_quat(q / np.linalg.norm(q))
        if self.imu_to_lidar is not None:
            # Measurements in lidar axes: rotate vectors; the attitude becomes that of the lidar.
            gyro = self.imu_to_lidar @ gyro
            acc = self.imu_to_lidar @ acc
            rotation = rotation * Rotation.from_matrix(self.imu_to_lidar.T)
        roll, pitch, yaw = rotation.as_euler('xyz')  # fixed-axis x, y, z = tf getRPY
        # Gravity-free acceleration in the body frame, re-ordered into camera axes (x=y_l, y=z_l, z=x_l).
        g = self.gravity
        body = np.array([acc[1] - np.sin(roll) * np.cos(pitch) * g,
                         acc[2] - np.cos(roll) * np.cos(pitch) * g,
                         acc[0] + np.sin(pitch) * g])
        world = imu_world_rotation(roll, pitch, yaw)[0] @ body
        if len(self._time) and stamp - self._time[-1] < self.scan_period:
            dt = stamp - self._time[-1]
            velocity = self._velocity[-1] + world * dt
            shift = self._shift[-1] + self._velocity[-1] * dt + world * dt * dt / 2
            angle = self._angle[-1] + gyro * dt
        else:  # first sample, or after a gap: restart the integration
            velocity = np.zeros(3)
            shift = self._shift[-1] if len(self._time) else np.zeros(3)
            angle = self._angle[-1] if len(self._time) else np.zeros(3)
        keep = self.capacity - 1
        self._time = np.append(self._time[-keep:], stamp)
        self._rpy = np.vstack([self._rpy[-keep:], [roll, pitch, yaw]])
        self._velocity = np.vstack([self._velocity[-keep:], velocity])
        self._shift = np.vstack([self._shift[-keep:], shift])
        self._angle = np.vstack([self._angle[-keep:], angle])
        return None

    def covers(self, start: float, end: float, tolerance: float = 0.02) -> bool:
        """True when samples exist at or before ``start`` and at or after ``end - tolerance``."""
        return len(self._time) >= 2 and self._time[0] <= start and self._time[-1] >= end - tolerance

    def interpolate(self, times: np.ndarray) -> ImuState:
        """Linear interpolation at ``times`` [s] (held at the ends); yaw interpolated across +-pi."""
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

        def lerp(values):
            a, b = values[back], values[front]
            r = ratio.reshape((-1,) + (1,) * (values.ndim - 1))
            return a + (b - a) * r

        rpy = lerp(self._rpy)
        yaw_back, yaw_front = self._rpy[back, 2], self._rpy[front, 2]
        jump = yaw_front - yaw_back
        unwrapped_back = yaw_back + np.where(jump > np.pi, 2 * np.pi, np.where(jump < -np.pi, -2 * np.pi, 0.0))
        rpy[:, 2] = unwrapped_back + (yaw_front - unwrapped_back) * ratio
        return ImuState(roll=rpy[:, 0], pitch=rpy[:, 1], yaw=rpy[:, 2], velocity=lerp(self._velocity),
                        shift=lerp(self._shift), angle=lerp(self._angle))

