"""Stage 3, mapOptimization and transformFusion: scan-to-map registration, keyframes and the pose graph, the map
bundle and map files, the 2D occupancy grid for nav2, and the fusion of odometry and mapping.

Its public API, each name from the module that defines it (imported on first use)."""

from __future__ import annotations

from lego_loam_py.core._exports import lazy_exports

_EXPORTS = {
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
    'FREE': 'occupancy_grid',
    'OCCUPIED': 'occupancy_grid',
    'UNKNOWN': 'occupancy_grid',
    'KeyframeScan': 'occupancy_ground',
    'classify_keyframe': 'occupancy_ground',
    'OccupancyGrid': 'occupancy_grid',
    'OccupancyGridFields': 'occupancy_grid',
    'TernaryGrid': 'occupancy_grid',
    'keyframe_lidar_pose': 'occupancy_grid',
    'keyframe_points': 'occupancy_grid',
    'message_fields': 'occupancy_grid',
    'FREE_THRESH': 'occupancy_files',
    'OCCUPIED_THRESH': 'occupancy_files',
    'OCCUPANCY_NAME': 'occupancy_files',
    'OccupancyFilesError': 'occupancy_files',
    'read_occupancy_files': 'occupancy_files',
    'write_occupancy_files': 'occupancy_files',
    'saved_occupancy_grid': 'occupancy_files',
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
    'TransformFusion': 'transform_fusion',
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
