"""``lego_loam_py viewer``: the running nodes shown in Rerun, from their standard topics (no change to the nodes).

It subscribes to what rviz2 shows with ``config/lego_loam.rviz`` and logs it as the offline viewer does
(:mod:`lego_loam_py.viewer`): the labelled scan (``/ground_cloud``, ``/segmented_cloud_pure``, ``/outlier_cloud``,
base_link), the features (``/laser_cloud_sharp``, ``/laser_cloud_flat``, camera), the global map
(``/laser_cloud_surround``, every 5 s), keyframes (``/key_pose_origin``), the three odometries and, from
``/diagnostics``, each node's median ms per scan and its counters. A scan is logged once its fused pose
(``/integrated_to_init``) is there. Subscribing makes the nodes publish the topics they publish only while
someone listens, as rviz2 does: that costs imageProjection and featureAssociation some time per scan.

    lego_loam_py viewer                      # a Rerun window (rerun-sdk's native viewer)
    lego_loam_py viewer --save live.rrd      # or into a file, no display needed
"""

from __future__ import annotations

import argparse

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from lego_loam_py.core.frames import CAMERA_TO_LIDAR, camera_pose_to_lidar
from lego_loam_py.ros import qos
from lego_loam_py.ros.conversions import cloud_msg_to_xyzi, odometry_to_pose, stamp_to_ns
from lego_loam_py.ros.runtime import run_node

__all__ = ['ViewerNode', 'add_arguments', 'main']

SCAN_TOPICS = ('/ground_cloud', '/segmented_cloud_pure', '/outlier_cloud', '/laser_cloud_sharp', '/laser_cloud_flat')
ODOMETRY_TOPICS = {'/laser_odom_to_init': 'odometry', '/aft_mapped_to_init': 'mapped', '/integrated_to_init': 'fused'}
HEALTH_COUNTERS = (
    'odometry_lost',
    'state_resets',
    'scans_dropped',
    'clouds_dropped',
    'callback_errors',
    'silent_periods',
    'loops_closed',
    'loops_rejected',
)
_KEPT_SCANS = 20  # scans waiting for their fused pose (older ones never got one)


def _camera_to_map(points: np.ndarray) -> np.ndarray:
    return np.asarray(points, dtype=np.float64)[:, :3] @ CAMERA_TO_LIDAR.T


class ViewerNode(Node):
    """Logs the pipeline's topics into a :class:`~lego_loam_py.viewer.scene.SceneLog`."""

    def __init__(self, scene, **kwargs):
        super().__init__('lego_loam_viewer', **kwargs)
        self.scene = scene
        self._scan_index: dict[int, int] = {}  # stamp [ns] -> scan index (order of first sight)
        self._clouds: dict[int, dict[str, np.ndarray]] = {}
        for topic in SCAN_TOPICS:
            self.create_subscription(
                PointCloud2, topic, lambda msg, t=topic: self.on_scan_cloud(t, msg), qos.reliable(5)
            )
        for topic, name in ODOMETRY_TOPICS.items():
            self.create_subscription(Odometry, topic, lambda msg, n=name: self.on_odometry(n, msg), qos.reliable(5))
        self.create_subscription(PointCloud2, '/laser_cloud_surround', self.on_map, qos.reliable(2))
        self.create_subscription(PointCloud2, '/key_pose_origin', self.on_keyframes, qos.reliable(2))
        self.create_subscription(DiagnosticArray, '/diagnostics', self.on_diagnostics, qos.reliable(10))
        self.logged_scans = 0

    def _at(self, stamp_ns: int) -> None:
        index = self._scan_index.setdefault(stamp_ns, len(self._scan_index))
        self.scene.at_scan(index, stamp_ns)

    def on_scan_cloud(self, topic: str, msg: PointCloud2) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self._scan_index.setdefault(stamp, len(self._scan_index))
        clouds = self._clouds.setdefault(stamp, {})
        points = cloud_msg_to_xyzi(msg)
        clouds[topic] = _camera_to_map(points) if topic.startswith('/laser_cloud') else points[:, :3]
        for old in sorted(self._clouds)[:-_KEPT_SCANS]:
            del self._clouds[old]

    def on_odometry(self, name: str, msg: Odometry) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        pose = camera_pose_to_lidar(odometry_to_pose(msg))
        self._at(stamp)
        self.scene.trajectory_pose(name, pose)
        if name != 'fused':
            return
        clouds = self._clouds.pop(stamp, None)
        self.scene.sensor_pose(pose)
        if clouds:
            empty = np.zeros((0, 3))
            self.scene.scan(*(clouds.get(t, empty) for t in SCAN_TOPICS[:3]))
            self.scene.features(*(clouds.get(t, empty) for t in SCAN_TOPICS[3:]))
            self.logged_scans += 1
            if self.logged_scans == 1:  # (on stdout: tools and tests wait for it)
                print(f'viewer: first scan logged (stamp {stamp})', flush=True)

    def on_map(self, msg: PointCloud2) -> None:
        self._at(stamp_to_ns(msg.header.stamp))
        self.scene.map_points(_camera_to_map(cloud_msg_to_xyzi(msg)))

    def on_keyframes(self, msg: PointCloud2) -> None:
        self._at(stamp_to_ns(msg.header.stamp))
        self.scene.keyframes(_camera_to_map(cloud_msg_to_xyzi(msg)))

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        """Each node's median ms per scan and its counters, as they stand once a second."""
        if not self._scan_index:
            return
        stamp = max(self._scan_index, key=self._scan_index.get)
        self._at(stamp)
        for status in msg.status:
            node = status.name.split(':')[-1].strip().lstrip('/')
            for item in status.values:
                try:
                    value = float(item.value)
                except ValueError:
                    continue
                if ' ' in item.key or '/' in item.key:  # (matched endpoints per topic: not plotted)
                    continue
                if item.key.endswith('_median_ms'):  # a stage's median over the recent scans
                    self.scene.scalar(f'timings/{node}/{item.key[: -len("_median_ms")]}', value)
                elif item.key.endswith('_last'):  # a measure of the latest scan (conditions, match ratios)
                    self.scene.scalar(f'health/{node}/{item.key[: -len("_last")]}', value)
                elif item.key in HEALTH_COUNTERS:
                    self.scene.scalar(f'health/{node}/{item.key}', value)

    def on_shutdown(self) -> None:
        self.scene.finish()
        print(f'viewer: {self.logged_scans} scans logged', flush=True)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        '--save',
        type=str,
        default=None,
        metavar='FILE.rrd',
        help='write the view to a Rerun recording (no display needed)',
    )
    parser.add_argument('--no-window', action='store_true', help='no viewer window (with --save)')


def main(args: argparse.Namespace) -> int:
    from lego_loam_py.errors import UsageError
    from lego_loam_py.viewer.scene import SceneLog

    if args.no_window and args.save is None:
        raise UsageError('--no-window needs --save FILE.rrd (nothing would be shown or kept)')
    scene = SceneLog('live', save=args.save, spawn=not args.no_window)
    return run_node(lambda: ViewerNode(scene), args.ros_args)
