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


def _product(a: tuple, b: tuple) -> tuple:
    """The 3x3 product of two row-major 9-tuples, each entry summed over k = 0, 1, 2 in that order."""
    return tuple(
        a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j] for i in range(3) for j in range(3)
    )


def _exp(vx: float, vy: float, vz: float) -> tuple:
    """Rodrigues: the rotation (row-major 9-tuple) of a rotation vector [rad]."""
    angle = math.sqrt(vx * vx + vy * vy + vz * vz)
    if angle < 1e-12:
        return (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    kx, ky, kz = vx / angle, vy / angle, vz / angle
    cross = (0.0, -kz, ky, kz, 0.0, -kx, -ky, kx, 0.0)
    square = _product(cross, cross)
    sine, versine = math.sin(angle), 1.0 - math.cos(angle)
    identity = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    return tuple(identity[i] + sine * cross[i] + versine * square[i] for i in range(9))


class GyroAttitude:
    """The integrated attitude of one IMU stream (see the module docstring).

    Scalar arithmetic in a fixed order (no BLAS: the same result on every machine), on ``state``, which the C
    kernel of :class:`~lego_loam_py.core.imu.buffer.ImuBuffer` updates the same way (native/feature_kernels.c).
    """

    def __init__(self) -> None:
        self.bias = np.zeros(3)  # [rad/s] lidar axes, taken off every rate from the next sample on
        # The attitude (row-major 3x3), the last rate less the bias [rad/s], and 1.0 once started (0.0: start
        # again from the next sample's orientation).
        self.state = np.zeros(13)

    def restart(self) -> None:
        """Start again from the next sample's orientation (a gap, a cleared buffer)."""
        self.state[12] = 0.0

    def update(
        self, dt: float | None, rate: tuple[float, float, float], orientation: tuple[float, float, float]
    ) -> tuple[float, float, float]:
        """The attitude (roll, pitch, yaw) after a sample with angular ``rate`` [rad/s] (lidar axes) and the
        orientation field's (roll, pitch, yaw), ``dt`` [s] after the previous one (None: start from it)."""
        bx, by, bz = self.bias.tolist()
        rx, ry, rz = float(rate[0]) - bx, float(rate[1]) - by, float(rate[2]) - bz
        state = self.state.tolist()
        if dt is None or state[12] == 0.0:
            attitude = tuple(matrix_of_rpy(*orientation).reshape(-1).tolist())
        else:
            px, py, pz = state[9:12]
            step = _exp(0.5 * (px + rx) * dt, 0.5 * (py + ry) * dt, 0.5 * (pz + rz) * dt)
            attitude = _product(tuple(state[:9]), step)
        self.state[:] = (*attitude, rx, ry, rz, 1.0)
        m = attitude
        return math.atan2(m[7], m[8]), math.asin(max(-1.0, min(1.0, -m[6]))), math.atan2(m[3], m[0])
