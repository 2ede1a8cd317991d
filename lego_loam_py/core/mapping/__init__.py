"""Stage 3, mapOptimization and transformFusion: scan-to-map registration, keyframes and the pose graph, the map
bundle and map files, and the fusion of odometry and mapping.

Its public API, each name from the module that defines it (imported on first use)."""

from __future__ import annotations

from lego_loam_py.core._exports import lazy_exports

_EXPORTS = {
    'KeyframeCovariance': 'covariance',
    'MAX_REGISTRATION_VARIANCE': 'covariance',
    'mapped_covariance': 'covariance',
    'registration_covariance': 'covariance',
    'FACTOR_KINDS': 'map_bundle',
    'FORMAT': 'map_bundle',
    'FORMAT_VERSION': 'map_bundle',
    'GraphFactor': 'map_bundle',
    'KERNELS': 'map_bundle',
    'MANIFEST': 'map_bundle',
    'MapBundle': 'map_bundle',
    'MapBundleError': 'map_bundle',
    'check_compatible': 'map_bundle',
    'is_bundle': 'map_bundle',
    'read_bundle': 'map_bundle',
    'read_manifest': 'map_bundle',
    'reuse_parameters': 'map_bundle',
    'write_bundle': 'map_bundle',
    'write_map_files': 'map_files',
    'Keyframe': 'map_optimization',
    'MapOptimization': 'map_optimization',
    'MappingStep': 'map_optimization',
    'JUMP_M': 'odometry_continuity',
    'JUMP_M_PER_S': 'odometry_continuity',
    'JUMP_RAD': 'odometry_continuity',
    'JUMP_RAD_PER_S': 'odometry_continuity',
    'MAX_EXTRAPOLATION_S': 'odometry_continuity',
    'OdometryContinuity': 'odometry_continuity',
    'OdometryJump': 'odometry_continuity',
    'anchored_transform_bef': 'odometry_continuity',
    'scaled_motion': 'odometry_continuity',
    'PoseGraph': 'pose_graph',
    'RegistrationCounts': 'scan_to_map',
    'edge_correspondences': 'scan_to_map',
    'map_jacobian_rows': 'scan_to_map',
    'map_trees': 'scan_to_map',
    'plane_correspondences': 'scan_to_map',
    'register_scan_to_map': 'scan_to_map',
    'registration_information': 'scan_to_map',
    'TransformFusion': 'transform_fusion',
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
