"""lego_loam_py: LeGO-LOAM lidar odometry and mapping for ROS 2, in Python.

``lego_loam_py.core`` holds the algorithms and conventions (numpy/scipy/gtsam/open3d, never rclpy);
``lego_loam_py.ros`` the thin rclpy nodes and message conversions; ``lego_loam_py.bag`` bag I/O.
"""

__version__ = '0.1.0'
