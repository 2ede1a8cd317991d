"""``lego_loam_py viewer`` over DDS: it takes the nodes' standard topics and saves them to a .rrd."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.testing.nodes import read_until, release

pytest.importorskip('rerun')
CLI = Path(sys.executable).parent / 'lego_loam_py'


def test_the_viewer_process_logs_the_scans_it_hears_with_their_fused_pose(rclpy_context, processes, tmp_path):
    import rclpy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import make_header, pose_to_odometry, xyzi_to_cloud_msg
    from tests.test_viewer import _entities_and_scan_steps

    rrd = tmp_path / 'live.rrd'
    viewer = processes.start([CLI, 'viewer', '--save', rrd, '--no-window'])
    node = rclpy.create_node('viewer_feeder', context=rclpy_context)
    clouds = node.create_publisher(PointCloud2, '/outlier_cloud', qos.reliable(5))
    fused = node.create_publisher(Odometry, '/integrated_to_init', qos.reliable(5))
    points = np.random.default_rng(0).uniform(-5, 5, (500, 4)).astype(np.float32)
    stop = threading.Event()

    def feed() -> None:  # a scan and its fused pose every 0.1 s until the viewer has logged one (bounded)
        for k in range(300):
            if stop.is_set():
                return
            header = make_header(1_000_000_000 + k * 100_000_000, 'base_link')
            clouds.publish(xyzi_to_cloud_msg(points, header))
            pose = np.eye(4)
            pose[2, 3] = 0.1 * k  # camera z = forward
            fused.publish(pose_to_odometry(pose, make_header(header.stamp, 'camera_init'), 'camera'))
            stop.wait(0.1)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        read_until(viewer, 'viewer: first scan logged', timeout=60)
    finally:
        stop.set()
        feeder.join(10)
    out, err = processes.stop(viewer)
    assert viewer.returncode == 0, err
    assert 'scans logged' in out
    entities, steps = _entities_and_scan_steps(rrd)
    assert {'/world/lidar', '/world/lidar/scan'} <= entities
    assert any(e.startswith('/world/trajectory/fused/') for e in entities)
    assert len(steps['/world/lidar/scan']) >= 1
    release(node)
