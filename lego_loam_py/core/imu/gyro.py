"""The lidar's attitude integrated from the gyro, anchored to the IMU's orientation field.

A 9-axis unit's orientation output is a filter's estimate: gravity-referenced (its roll and pitch do not drift) but
noisy from sample to sample (a consumer module's 0.05 deg), tilted by a constant, and yawed by its magnetometer's
reference. featureAssociation needs the attitude only over a sweep and from one sweep to the next, where the gyro
is far finer (0.014 deg/s/sqrt(Hz): 0.004 deg over a sweep): :class:`GyroAttitude` integrates the angular rate
(lidar axes, the midpoint of consecutive samples, minus an estimated bias) from the orientation of the first sample,
and starts again from the orientation after a gap. Roll, pitch and yaw are the fixed-axis x, y, z angles of the
lidar's attitude in the world, as the orientation field's (REP-103, lidar axes).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ['GyroAttitude', 'rpy_of', 'matrix_of_rpy']


def matrix_of_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)``: the attitude of fixed-axis x, y, z angles [rad]."""
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def rpy_of(matrix: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) [rad] of an attitude (inverse of :func:`matrix_of_rpy`)."""
    (m00, _, _), (m10, _, _), (m20, m21, m22) = np.asarray(matrix).tolist()
    return math.atan2(m21, m22), math.asin(max(-1.0, min(1.0, -m20))), math.atan2(m10, m00)


_IDENTITY = np.eye(3)
_IDENTITY.flags.writeable = False


def _exp(rotation_vector: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation of a rotation vector [rad] ((3,) float64)."""
    # (np.linalg.norm's own operations, sqrt of the vector's dot with itself, without its checks: 200 samples a
    # second call this)
    angle = math.sqrt(rotation_vector.dot(rotation_vector))
    if angle < 1e-12:
        return np.eye(3)
    kx, ky, kz = (rotation_vector / angle).tolist()
    cross = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    return _IDENTITY + math.sin(angle) * cross + (1.0 - math.cos(angle)) * (cross @ cross)


class GyroAttitude:
    """The integrated attitude of one IMU stream (see the module docstring)."""

    def __init__(self) -> None:
        self.bias = np.zeros(3)  # [rad/s] lidar axes, taken off every rate from the next sample on
        self._attitude: np.ndarray | None = None
        self._rate: np.ndarray | None = None

    def restart(self) -> None:
        """Start again from the next sample's orientation (a gap, a cleared buffer)."""
        self._attitude, self._rate = None, None

    def update(
        self, dt: float | None, rate: tuple[float, float, float], orientation: tuple[float, float, float]
    ) -> tuple[float, float, float]:
        """The attitude (roll, pitch, yaw) after a sample with angular ``rate`` [rad/s] (lidar axes) and the
        orientation field's (roll, pitch, yaw), ``dt`` [s] after the previous one (None: start from it)."""
        rate = np.asarray(rate, dtype=float) - self.bias
        if dt is None or self._attitude is None or self._rate is None:
            self._attitude = matrix_of_rpy(*orientation)
        else:
            self._attitude = self._attitude @ _exp(0.5 * (self._rate + rate) * dt)
        self._rate = rate
        return rpy_of(self._attitude)
