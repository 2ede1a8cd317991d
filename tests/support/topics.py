"""The original LeGO-LOAM's topics (docs/original.md §4) as lego_loam_py publishes them: type, frame, child frame.

Frames are the original's without the leading slash. ``SENSOR_FRAME`` marks CloudInfo, whose header is the
input cloud's (the simulated bags' lidar frame is ``velodyne``).
"""

from __future__ import annotations

SENSOR_FRAME = 'velodyne'

# topic -> (publisher node, message type 'pkg/msg/Type', header frame, child frame or None)
ALWAYS = {
    '/segmented_cloud': ('imageProjection', 'sensor_msgs/msg/PointCloud2', 'base_link', None),
    '/segmented_cloud_info': ('imageProjection', 'cloud_msgs/msg/CloudInfo', SENSOR_FRAME, None),
    '/outlier_cloud': ('imageProjection', 'sensor_msgs/msg/PointCloud2', 'base_link', None),
    '/laser_odom_to_init': ('featureAssociation', 'nav_msgs/msg/Odometry', 'camera_init', 'laser_odom'),
    '/laser_cloud_corner_last': ('featureAssociation', 'sensor_msgs/msg/PointCloud2', 'camera', None),
    '/laser_cloud_surf_last': ('featureAssociation', 'sensor_msgs/msg/PointCloud2', 'camera', None),
    '/outlier_cloud_last': ('featureAssociation', 'sensor_msgs/msg/PointCloud2', 'camera', None),
    '/aft_mapped_to_init': ('mapOptimization', 'nav_msgs/msg/Odometry', 'camera_init', 'aft_mapped'),
    '/integrated_to_init': ('transformFusion', 'nav_msgs/msg/Odometry', 'camera_init', 'camera'),
}

# Published only while subscribed (the original's getNumSubscribers() != 0).
GATED = {
    '/full_cloud_projected': ('imageProjection', 'sensor_msgs/msg/PointCloud2', 'base_link', None),
    '/full_cloud_info': ('imageProjection', 'sensor_msgs/msg/PointCloud2', 'base_link', None),
    '/ground_cloud': ('imageProjection', 'sensor_msgs/msg/PointCloud2', 'base_link', None),
    '/segmented_cloud_pure': ('imageProjection', 'sensor_msgs/msg/PointCloud2', 'base_link', None),
    '/laser_cloud_sharp': ('featureAssociation', 'sensor_msgs/msg/PointCloud2', 'camera', None),
    '/laser_cloud_less_sharp': ('featureAssociation', 'sensor_msgs/msg/PointCloud2', 'camera', None),
    '/laser_cloud_flat': ('featureAssociation', 'sensor_msgs/msg/PointCloud2', 'camera', None),
    '/laser_cloud_less_flat': ('featureAssociation', 'sensor_msgs/msg/PointCloud2', 'camera', None),
    '/key_pose_origin': ('mapOptimization', 'sensor_msgs/msg/PointCloud2', 'camera_init', None),
    '/registered_cloud': ('mapOptimization', 'sensor_msgs/msg/PointCloud2', 'camera_init', None),
    '/recent_cloud': ('mapOptimization', 'sensor_msgs/msg/PointCloud2', 'camera_init', None),
    '/laser_cloud_surround': ('mapOptimization', 'sensor_msgs/msg/PointCloud2', 'camera_init', None),
    # Not in the original: the 2D occupancy grid for nav2 (latched; occupancy_grid.enabled, on by default).
    '/map': ('mapOptimization', 'nav_msgs/msg/OccupancyGrid', 'map', None),
}

# Loop closure only (off by default): /history_cloud, /corrected_cloud (camera_init), and,
# not in the original, /loop_closures (latched markers of the accepted loops).
LOOP_CLOSURE = {
    '/history_cloud': ('mapOptimization', 'sensor_msgs/msg/PointCloud2', 'camera_init', None),
    '/corrected_cloud': ('mapOptimization', 'sensor_msgs/msg/PointCloud2', 'camera_init', None),
    '/loop_closures': ('mapOptimization', 'visualization_msgs/msg/MarkerArray', 'camera_init', None),
}

# (parent, child) on /tf, and on the latched /tf_static.
TF_DYNAMIC = {('camera_init', 'laser_odom'), ('camera_init', 'aft_mapped'), ('camera_init', 'camera')}
TF_STATIC = {('map', 'camera_init'), ('camera', 'base_link')}

ALL = {**ALWAYS, **GATED, **LOOP_CLOSURE}


def message_class(type_name: str):
    """The rclpy message class of 'pkg/msg/Type'."""
    import importlib

    package, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)
