"""The ``featureAssociation`` node: segmented scans (+ IMU) -> features, scan-to-scan odometry, 'last' clouds.

Subscribes /segmented_cloud, /segmented_cloud_info and /outlier_cloud (reliable, depth 1 as the original)
and synchronises them by stamp (within ``feature_association.sync_tolerance``); /imu/data (best effort,
depth 50) when ``sensor.imu_topic`` is set. Publishes, stamped with the scan:

* every scan: /laser_odom_to_init (nav_msgs/Odometry, camera_init -> laser_odom) and its TF;
* every ``skip_frame_num + 1`` scans: /laser_cloud_corner_last, /laser_cloud_surf_last, /outlier_cloud_last
  (frame ``camera``, LOAM camera axes);
* while subscribed: /laser_cloud_sharp, /laser_cloud_less_sharp, /laser_cloud_flat, /laser_cloud_less_flat.

Scans with an older stamp than the previous one are dropped (out of order or duplicate). A jump of more than a
second either way is believed once the next scan continues the new timeline (a single wrong stamp costs that
scan only): back in time (a bag restarted or looped) the odometry resets with a warning, forward it goes on.
Inconsistent inputs (CloudInfo arrays that do not match the cloud, ring indices outside it, non-finite or
absurd values) are dropped with a throttled warning; should the odometry ever become non-finite it resets
instead of publishing garbage. A reset keeps the IMU samples.
"""
from __future__ import annotations

import sys
import time

import numpy as np
from cloud_msgs.msg import CloudInfo
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, PointCloud2

from lego_loam_py.core.feature_association import FeatureAssociation, ScanInput
from lego_loam_py.core.frames import CAMERA_FRAME, CAMERA_INIT_FRAME, LASER_ODOM_FRAME
from lego_loam_py.core.pointcloud import CloudLayoutError
from lego_loam_py.core.image_projection import MAX_COORDINATE
from lego_loam_py.core.imu import imu_sample
from lego_loam_py.core.sync import StampOrder, StampSynchronizer
from lego_loam_py.ros import qos
from lego_loam_py.ros.conversions import (cloud_info_from_msg, cloud_msg_to_array, cloud_msg_to_xyzi, make_header,
                                          pose_to_odometry, stamp_to_ns, xyzi_to_cloud_msg)
from lego_loam_py.ros.node_base import LegoLoamNode
from lego_loam_py.ros.runtime import run_node
from lego_loam_py.ros.tf import TransformBroadcaster

__all__ = ['FeatureAssociationNode', 'main']

RESET_JUMP_NS = 1_000_000_000   # a jump back in time by more than this resets the odometry


class FeatureAssociationNode(LegoLoamNode):
    def __init__(self, **kwargs):
        super().__init__('featureAssociation', **kwargs)
        self.core = FeatureAssociation(self.params)
        fa = self.params.feature_association
        self.sync = StampSynchronizer(['cloud', 'info', 'outlier'], int(fa.sync_tolerance * 1e9))
        depth1 = qos.reliable(1)
        self.create_subscription(PointCloud2, '/segmented_cloud', lambda m: self.on_part('cloud', m), depth1)
        self.create_subscription(CloudInfo, '/segmented_cloud_info', lambda m: self.on_part('info', m), depth1)
        self.create_subscription(PointCloud2, '/outlier_cloud', lambda m: self.on_part('outlier', m), depth1)
        self.imu_subscription = None
        if self.params.sensor.imu_topic:
            self.imu_subscription = self.create_subscription(Imu, self.params.sensor.imu_topic, self.on_imu,
                                                             qos.sensor_input(50))
        self.pub_odometry = self.create_publisher(Odometry, '/laser_odom_to_init', qos.reliable(5))
        self.tf = TransformBroadcaster(self)
        last = qos.reliable(2)
        self.pub_corner_last = self.create_publisher(PointCloud2, '/laser_cloud_corner_last', last)
        self.pub_surf_last = self.create_publisher(PointCloud2, '/laser_cloud_surf_last', last)
        self.pub_outlier_last = self.create_publisher(PointCloud2, '/outlier_cloud_last', last)
        features = qos.reliable(1)
        self.pub_sharp = self.create_publisher(PointCloud2, '/laser_cloud_sharp', features)
        self.pub_less_sharp = self.create_publisher(PointCloud2, '/laser_cloud_less_sharp', features)
        self.pub_flat = self.create_publisher(PointCloud2, '/laser_cloud_flat', features)
        self.pub_less_flat = self.create_publisher(PointCloud2, '/laser_cloud_less_flat', features)
        self.order = StampOrder(RESET_JUMP_NS)
        self.get_logger().info(
            f'featureAssociation: IMU {self.params.sensor.imu_topic or "off"}, relative point time: '
            f'{fa.relative_time_source}, mapping every {fa.skip_frame_num + 1} scans')

    # ----------------------------------------------------------------------------------- inputs
    def on_part(self, name: str, msg) -> None:
        complete = self.add_part(self.sync, name, msg, self.params.feature_association.sync_tolerance)
        if complete is not None:
            self.on_scan(complete['cloud'], complete['info'], complete['outlier'])

    def on_imu(self, msg: Imu) -> None:
        reason = self.core.add_imu(*imu_sample(msg))
        if reason is not None:
            self.count('imu_dropped')
            self.warn('imu', f'IMU message dropped: {reason}')

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the last scan processed [ns]."""
        return self.order.last_ns

    def on_scan(self, cloud_msg: PointCloud2, info_msg, outlier_msg: PointCloud2) -> None:
        self.count('scans_in')
        self.drain(self.imu_subscription, self.on_imu)   # the IMU samples that came with this scan first
        stamp = stamp_to_ns(cloud_msg.header.stamp)
        decision = self.check_order(self.order, stamp, (cloud_msg, info_msg, outlier_msg),
                                    lambda held: stamp_to_ns(held[0].header.stamp), 'scan', 'scans_dropped')
        if decision is None:
            return
        if decision.action == 'reset':
            self.warn('reset', f'time jumped back by {-decision.jump_ns * 1e-9:.1f} s (bag restarted?): '
                               'odometry reset', period=0.0)
            self._reset()
        if decision.held is not None:
            self._process(*decision.held)
        self._process(cloud_msg, info_msg, outlier_msg)

    def _reset(self) -> None:
        """Start the odometry again (the IMU samples stay: they follow their own timeline)."""
        imu = self.core.imu
        self.core.reset()
        self.core.imu = imu
        self.order.reset()
        self.count('resets')

    def _process(self, cloud_msg: PointCloud2, info_msg, outlier_msg: PointCloud2) -> None:
        start = time.perf_counter()
        stamp = stamp_to_ns(cloud_msg.header.stamp)
        try:
            scan = self._scan_input(stamp, cloud_msg, info_msg, outlier_msg)
        except (CloudLayoutError, ValueError) as exc:
            self.count('scans_dropped')
            self.warn('bad_scan', f'scan dropped: {exc}')
            return
        try:
            result = self.core.process(scan)
        except Exception:
            self.count('scans_dropped')
            self.error('process_exception', 'unexpected error in featureAssociation; scan dropped')
            if not self._state_is_finite():
                self.warn('diverged', 'the odometry state is no longer finite: odometry reset', period=0.0)
                self._reset()
            return
        if not (self._state_is_finite() and _finite(result.corner_last) and _finite(result.surf_last)
                and _finite(result.outlier_last)):
            self.count('scans_dropped')
            self.warn('diverged', 'the odometry became non-finite: scan dropped, odometry reset', period=0.0)
            self._reset()
            return
        self.order.processed(stamp)
        self._publish(result, cloud_msg.header.stamp)
        self.count('scans')
        if result.imu_used:
            self.count('scans_with_imu')
        self.record_time('scan', time.perf_counter() - start)

    def _state_is_finite(self) -> bool:
        return bool(np.isfinite(self.core.transform_sum).all() and
                    np.isfinite(self.core.odometry.transform_cur).all())

    def _scan_input(self, stamp: int, cloud_msg, info_msg, outlier_msg) -> ScanInput:
        """Convert and validate the three messages (raises ValueError for inconsistent content)."""
        points = cloud_msg_to_array(cloud_msg)
        segmented = cloud_msg_to_xyzi(cloud_msg)
        outlier = cloud_msg_to_xyzi(outlier_msg)
        info = cloud_info_from_msg(info_msg)
        n = len(segmented)
        n_scan = self.params.sensor.n_scan
        lengths = {len(info.segmented_cloud_range), len(info.segmented_cloud_col_ind),
                   len(info.segmented_cloud_ground_flag)}
        if min(lengths) < n:  # the original publishes 28800-long arrays; only the first n matter
            raise ValueError(f'CloudInfo arrays ({sorted(lengths)}) are shorter than the segmented cloud ({n})')
        if len(info.start_ring_index) != n_scan or len(info.end_ring_index) != n_scan:
            raise ValueError(f'CloudInfo ring indices have {len(info.start_ring_index)}/{len(info.end_ring_index)} '
                             f'entries, sensor.n_scan is {n_scan}')
        if (info.end_ring_index > n).any() or (info.start_ring_index > n + 10).any() or \
                (info.start_ring_index < -10).any() or (info.end_ring_index < -10).any():
            raise ValueError('CloudInfo ring indices point outside the segmented cloud')
        if not (np.isfinite(segmented).all() and np.isfinite(outlier).all()):
            raise ValueError('non-finite values in the segmented or outlier cloud')
        if not ((np.abs(segmented[:, :3]) <= MAX_COORDINATE).all() and
                (np.abs(outlier[:, :3]) <= MAX_COORDINATE).all()):
            raise ValueError(f'coordinates beyond {MAX_COORDINATE:g} m in the segmented or outlier cloud')
        # The intensity of imageProjection's clouds is row + column / 10000: the row indexes the rings.
        if n and not ((segmented[:, 3] >= 0).all() and (segmented[:, 3] < n_scan).all()):
            raise ValueError(f'segmented cloud intensities are not row + column / 10000 with rows 0..{n_scan - 1}')
        angles = [info.start_orientation, info.end_orientation, info.orientation_diff]
        if not np.isfinite(angles).all() or not (np.abs(angles) <= 100.0).all() or info.orientation_diff == 0:
            raise ValueError('invalid sweep orientation in CloudInfo')
        info.segmented_cloud_range = info.segmented_cloud_range[:n]
        info.segmented_cloud_col_ind = info.segmented_cloud_col_ind[:n]
        info.segmented_cloud_ground_flag = info.segmented_cloud_ground_flag[:n]
        if not (np.isfinite(info.segmented_cloud_range).all() and
                (np.abs(info.segmented_cloud_range) <= 2 * MAX_COORDINATE).all()):
            raise ValueError('CloudInfo ranges are not finite or absurd')
        point_time = None
        if 'time' in (points.dtype.names or ()) and points['time'].ndim == 1:
            point_time = points['time']
            period = self.params.sensor.scan_period
            if not (np.isfinite(point_time).all() and (np.abs(point_time) <= 10 * period).all()):
                self.warn('bad_time', 'per-point time field not finite or far outside the sweep: ignored')
                point_time = None
        return ScanInput(stamp, segmented, info, outlier, point_time)

    # ---------------------------------------------------------------------------------- outputs
    def _publish(self, result, stamp) -> None:
        pose = result.pose
        header = make_header(stamp, CAMERA_INIT_FRAME)
        if not result.initialized:
            self.pub_odometry.publish(pose_to_odometry(pose, header, LASER_ODOM_FRAME))
            self.tf.send_pose(pose, stamp, CAMERA_INIT_FRAME, LASER_ODOM_FRAME)
        camera = make_header(stamp, CAMERA_FRAME)
        f = result.features
        for publisher, cloud in ((self.pub_sharp, f.sharp), (self.pub_less_sharp, f.less_sharp),
                                 (self.pub_flat, f.flat), (self.pub_less_flat, f.less_flat)):
            if publisher.get_subscription_count():
                publisher.publish(xyzi_to_cloud_msg(cloud, camera))
        if result.corner_last is not None:
            self.pub_corner_last.publish(xyzi_to_cloud_msg(result.corner_last, camera))
            self.pub_surf_last.publish(xyzi_to_cloud_msg(result.surf_last, camera))
        if result.outlier_last is not None:
            self.pub_outlier_last.publish(xyzi_to_cloud_msg(result.outlier_last, camera))


def _finite(cloud) -> bool:
    return cloud is None or bool(np.isfinite(cloud).all())


def main(args=None) -> int:
    return run_node(FeatureAssociationNode, args)


if __name__ == '__main__':
    sys.exit(main())
