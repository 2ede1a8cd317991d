"""Stage 2, featureAssociation: each sweep's times and deskewing, its features, and the scan-to-scan odometry
(the sweep-start model and the original's), with the outputs moved to the header stamp's instant.

Its public API, each name from the module that defines it (imported on first use)."""

from __future__ import annotations

from lego_loam_py.core._exports import lazy_exports

_EXPORTS = {
    'CornerCorrespondences': 'correspondences',
    'LastCloud': 'correspondences',
    'SurfCorrespondences': 'correspondences',
    'find_corner_correspondences': 'correspondences',
    'find_surf_correspondences': 'correspondences',
    'MAX_MOTION_VARIANCE': 'covariance',
    'OdometryCovariance': 'covariance',
    'motion_covariance': 'covariance',
    'sweep_motion': 'covariance',
    'FeatureAssociation': 'feature_association',
    'FeatureAssociationResult': 'feature_association',
    'ScanInput': 'feature_association',
    'FeatureExtractor': 'features',
    'ScanFeatures': 'features',
    'occluded_mask': 'features',
    'smoothness': 'features',
    'LaserOdometry': 'laser_odometry',
    'OdometryStats': 'laser_odometry',
    'OriginalOdometry': 'laser_odometry',
    'SweepStartOdometry': 'laser_odometry',
    'make_laser_odometry': 'laser_odometry',
    'StampInstant': 'sweep',
    'SweepStartFrame': 'sweep',
    'accumulate': 'sweep',
    'imu_free_motion': 'sweep',
    'motion_to_theta': 'sweep',
    'plane_jacobian_rows': 'sweep',
    'relative_time': 'sweep',
    'relative_time_from_azimuth': 'sweep',
    'relative_time_of': 'sweep',
    'ring_of': 'sweep',
    'start_jacobian': 'sweep',
    'sweep_angles': 'sweep',
    'sweep_rotation': 'sweep',
    'transform_to_end': 'sweep',
    'transform_to_start': 'sweep',
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
