"""The IMU over one sweep, as featureAssociation uses it: the attitude at the sweep start and at each point's own
time (the sweep-start model), or the points deskewed with it and its shift (the original model).

Each function takes the IMU buffer (:class:`~lego_loam_py.core.imu.buffer.ImuBuffer`, lidar axes and clock once its
mounting is applied), the sweep's start ``t_start`` [s] and its period [s]. When the samples cannot cover the
sweep, the result is the reason instead (a key of :data:`~lego_loam_py.core.imu.buffer.UNCOVERED`: no sample yet, the
samples begin after the sweep, end too long before it, or leave a gap), so that the scan that goes without the IMU
is counted and warned about, never dropped in silence. Camera axes throughout.
"""

from __future__ import annotations

import numpy as np

from lego_loam_py.core.imu.buffer import ImuBuffer, ImuSweep, SweepAttitude, imu_rotate, imu_world_rotation

__all__ = ['sweep_attitude', 'rotate_at_points', 'deskew_with_imu']

_F32 = np.float32


def sweep_attitude(imu: ImuBuffer, rel: np.ndarray, t_start: float, period: float) -> SweepAttitude | str:
    """The IMU attitude at the sweep start, and what :func:`rotate_at_points` needs for the points' own times
    (``rel`` = relative times of the prepared points); the reason when the IMU does not cover the sweep."""
    uncovered = imu.coverage(t_start, t_start + period)
    if uncovered is not None:
        return uncovered
    state = imu.interpolate([t_start])
    r_start = imu_world_rotation(state.roll, state.pitch, state.yaw)[0]
    return SweepAttitude(
        t_start=t_start, r_start=r_start, rel=rel, roll_start=float(state.roll[0]), pitch_start=float(state.pitch[0])
    )


def rotate_at_points(
    imu: ImuBuffer, left: np.ndarray, attitude: SweepAttitude, index: np.ndarray, cloud: np.ndarray, period: float
) -> np.ndarray:
    """(n, 3) float64 ``left @ R @ p`` of the ``cloud`` points, R the IMU attitude at the time of the prepared point
    ``index`` each comes from (only the features need them)."""
    times = attitude.t_start + attitude.rel[index] * period
    return imu.rotate_at(times, left, cloud)


def deskew_with_imu(
    imu: ImuBuffer, points: np.ndarray, rel: np.ndarray, t_start: float, period: float
) -> ImuSweep | str:
    """Rotate every point (in place) into the sweep-start frame with the IMU attitude and remove the IMU's
    non-linear shift; returns the sweep's IMU quantities, or the reason when the IMU does not cover the sweep."""
    t_end = t_start + period
    uncovered = imu.coverage(t_start, t_end)
    if uncovered is not None:
        return uncovered
    point_times = t_start + rel * period
    # The start attitude is the IMU's at the sweep start (s = 0). The original takes the segmented cloud's first
    # point, which is ordered by ring and column and therefore lies behind the sensor, mid-sweep.
    state = imu.interpolate(np.concatenate(([t_start, t_end], point_times)))
    r_start, r_end = imu_world_rotation(state.roll[:2], state.pitch[:2], state.yaw[:2])
    v_start = state.velocity[0]
    dt = point_times - t_start
    shift = (state.shift[2:] - state.shift[0] - v_start[None, :] * dt[:, None]) @ r_start  # R_S^T (.)
    rotated = imu_rotate(r_start.T, state.roll[2:], state.pitch[2:], state.yaw[2:], points)
    points[:, :3] = (rotated + shift).astype(_F32)
    shift_end = r_start.T @ (state.shift[1] - state.shift[0] - v_start * period)
    velocity_change = r_start.T @ (state.velocity[1] - v_start)
    return ImuSweep(
        roll_start=float(state.roll[0]),
        pitch_start=float(state.pitch[0]),
        delta_end=r_start.T @ r_end,
        shift_end=shift_end,
        velocity_change=velocity_change,
    )
