"""The IMU: its samples (mounting applied, the attitude from the gyro or the orientation field), its use over a sweep,
the check that it is mounted as the parameters say, and how well it agrees with the lidar.

Its public API, each name from the module that defines it (imported on first use)."""

from __future__ import annotations

from lego_loam_py.core._exports import lazy_exports

_EXPORTS = {
    'ImuAgreement': 'agreement',
    'MIN_SPAN': 'agreement',
    'FULL_TRUST': 'agreement',
    'WINDOW': 'agreement',
    'AlignmentFit': 'alignment',
    'GyroTrack': 'alignment',
    'OrientationTrack': 'alignment',
    'axis_name': 'alignment',
    'best_rotation': 'alignment',
    'fit_alignment': 'alignment',
    'nearest_right_angle_rotation': 'alignment',
    'shifted_increments': 'alignment',
    'ImuBuffer': 'buffer',
    'ImuState': 'buffer',
    'ImuSweep': 'buffer',
    'MAX_ACCELERATION': 'buffer',
    'MAX_ANGULAR_VELOCITY': 'buffer',
    'MAX_GAP': 'buffer',
    'MAX_REACH': 'buffer',
    'SweepAttitude': 'buffer',
    'UNCOVERED': 'buffer',
    'imu_mounting': 'buffer',
    'imu_rotate': 'buffer',
    'imu_sample': 'buffer',
    'imu_world_rotation': 'buffer',
    'uncovered_counter': 'buffer',
    'uncovered_warning': 'buffer',
    'warn_uncovered': 'buffer',
    'GyroAttitude': 'gyro',
    'matrix_of_rpy': 'gyro',
    'rpy_of': 'gyro',
    'AlignmentEvent': 'monitor',
    'EXPLAINED': 'monitor',
    'ImuAlignmentMonitor': 'monitor',
    'MAX_GROUND_TILT': 'monitor',
    'MappingImuCheck': 'monitor',
    'REPEAT_AFTER': 'monitor',
    'SIGNIFICANCE': 'monitor',
    'SweepImuCheck': 'monitor',
    'deskew_with_imu': 'sweep',
    'rotate_at_points': 'sweep',
    'sweep_attitude': 'sweep',
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
