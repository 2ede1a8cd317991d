"""The ``featureAssociation`` node: segmented scans (+ IMU) -> features, scan-to-scan odometry, 'last' clouds.

Subscribes /segmented_cloud, /segmented_cloud_info and /outlier_cloud (reliable, depth 1 as the original)
and synchronises them by stamp (within ``feature_association.sync_tolerance``); /imu/data (best effort,
depth 200, polled: the samples are taken with each scan, no wake-up per sample) when ``sensor.imu_topic`` is
set, and then /aft_mapped_to_init (reliable, depth 5), mapOptimization's poses, against which the IMU check
compares the IMU's turn (``imu.alignment_check``; an IMU that disagrees is warned about and not used, see
:mod:`lego_loam_py.core.imu.monitor`). Publishes, stamped with the scan:

* every scan: /laser_odom_to_init (nav_msgs/Odometry, camera_init -> laser_odom) and its TF;
* every ``skip_frame_num + 1`` scans: /laser_cloud_corner_last, /laser_cloud_surf_last, /outlier_cloud_last
  (frame ``camera``, LOAM camera axes);
* while subscribed: /laser_cloud_sharp, /laser_cloud_less_sharp, /laser_cloud_flat, /laser_cloud_less_flat.

Scans with an older stamp than the previous one are dropped (out of order or duplicate). A jump of more than a
second is believed once later scans continue the new timeline (a wrong stamp costs that scan only): forward,
the next scan; back in time, three scans in a row, and then, when the new timeline starts before the current
one did (a bag restarted or looped), the odometry resets with a warning; otherwise the scans ahead had wrong
stamps and the node carries on (see :class:`lego_loam_py.ros.sync.StampOrder`).
Inputs are checked against what imageProjection can produce, each part on arrival (see
:mod:`lego_loam_py.core.validation`), and dropped with a throttled warning; should the odometry's state ever be
poisoned anyway, it restarts from the next scan at the pose reached so far. A reset keeps the IMU samples.
"""

from __future__ import annotations

import copy
import sys
import time

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, PointCloud2

from cloud_msgs.msg import CloudInfo
from lego_loam_py.core import validation
from lego_loam_py.core.frames import CAMERA_FRAME, CAMERA_INIT_FRAME, LASER_ODOM_FRAME
from lego_loam_py.core.guard import SCANS_DROPPED, SCANS_PROCESSED, SCANS_WITH_IMU
from lego_loam_py.core.imu.buffer import uncovered_counter, uncovered_warning, warn_uncovered
from lego_loam_py.core.odometry.feature_association import FeatureAssociation, ScanInput
from lego_loam_py.ros import qos
from lego_loam_py.ros.conversions import (
    cloud_info_from_msg,
    cloud_info_from_serialized,
    cloud_msg_to_array,
    cloud_msg_to_xyzi,
    make_header,
    odometry_to_pose,
    serialized_odometry,
    serialized_stamp_ns,
    serialized_xyzi_cloud,
    stamp_to_ns,
)
from lego_loam_py.ros.node_base import LegoLoamNode
from lego_loam_py.ros.runtime import run_node
from lego_loam_py.ros.sync import StampOrder, StampSynchronizer
from lego_loam_py.ros.tf import TransformBroadcaster

__all__ = ['FeatureAssociationNode', 'main']

RESET_JUMP_NS = 1_000_000_000  # a jump back in time by more than this resets the odometry
INPUT_TOPICS = {'cloud': '/segmented_cloud', 'info': '/segmented_cloud_info', 'outlier': '/outlier_cloud'}
IMU_QUEUE_DEPTH = 200  # IMU samples kept between two scans (1 s at 200 Hz)


class FeatureAssociationNode(LegoLoamNode):
    def __init__(self, **kwargs):
        super().__init__('featureAssociation', **kwargs)
        self.core = FeatureAssociation(self.params)
        fa = self.params.feature_association
        self.sync = StampSynchronizer(['cloud', 'info', 'outlier'], int(fa.sync_tolerance * 1e9))
        depth1 = qos.reliable(1)
        # All three serialized: read from their bytes (cloud_from_serialized, cloud_info_from_serialized).
        self.create_subscription(PointCloud2, '/segmented_cloud', lambda m: self.on_part('cloud', m), depth1, raw=True)
        self.create_subscription(
            CloudInfo, '/segmented_cloud_info', lambda m: self.on_part('info', m), depth1, raw=True
        )
        self.create_subscription(PointCloud2, '/outlier_cloud', lambda m: self.on_part('outlier', m), depth1, raw=True)
        self.imu_subscription = None
        if self.params.sensor.imu_topic:  # taken with each scan (1 s of samples wait at 200 Hz)
            self.imu_subscription = self.create_polled_subscription(
                Imu, self.params.sensor.imu_topic, qos.sensor_input(IMU_QUEUE_DEPTH), raw=True
            )
            if self.params.imu.alignment_check:  # mapOptimization's poses: the lidar's turn, for the IMU check
                self.create_subscription(Odometry, '/aft_mapped_to_init', self.on_mapped, qos.reliable(5), raw=True)
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
            f'{fa.relative_time_source}, mapping every {fa.skip_frame_num + 1} scans; poses at the header stamp, '
            f'taken at {self.params.sensor.stamp_position:g} of the sweep (sensor.stamp_position: 0 its start, 1 its '
            'end, as the Velodyne ROS driver stamps unless timestamp_first_packet is true)'
        )

    # ----------------------------------------------------------------------------------- inputs
    def on_part(self, name: str, msg) -> None:
        """One of the three inputs: checked on its own (size first, then content) before it may join a set, so
        that a bad message can never take a valid scan's place among its partners."""
        if name != 'info':
            ok, msg = self.take_cloud(msg, 'scans_dropped', f'{INPUT_TOPICS[name]} dropped unread', 'bad_scan')
            if not ok:
                return
        ok, _ = self.take(
            lambda: self._check_size(name, msg),
            'scans_dropped',
            f'{INPUT_TOPICS[name]} dropped unread',
            'oversized',
            msg,
        )
        if not ok:
            return
        ok, decoded = self.take(lambda: self._decode(name, msg), 'scans_dropped', 'scan dropped', 'bad_scan')
        if not ok:
            return
        stamp_ns = None
        if isinstance(msg, bytes):  # (another encoding than XCDR1: the deserializer reads the stamp)
            stamp_ns = serialized_stamp_ns(msg) or cloud_info_from_serialized(msg, copy=False)[0]
        complete = self.add_part(
            self.sync, name, msg, self.params.feature_association.sync_tolerance, item=(msg, decoded), stamp_ns=stamp_ns
        )
        if complete is not None:
            self.on_scan(complete['cloud'], complete['info'], complete['outlier'])

    def _decode(self, name: str, msg):
        """The content of one input, checked against what imageProjection produces."""
        if name == 'info':
            info = cloud_info_from_serialized(msg)[1] if isinstance(msg, bytes) else cloud_info_from_msg(msg)
            validation.check_cloud_info(INPUT_TOPICS[name], info, self.params)
            return info
        cloud = cloud_msg_to_xyzi(msg)
        validation.check_cloud(INPUT_TOPICS[name], cloud, self.params.sensor.n_scan if name == 'cloud' else None)
        if name == 'outlier':
            return cloud
        point_time = None
        points = cloud_msg_to_array(msg)
        if 'time' in (points.dtype.names or ()) and points['time'].ndim == 1:
            point_time = points['time']
            period = self.params.sensor.scan_period
            if not (np.isfinite(point_time).all() and (np.abs(point_time) <= 10 * period).all()):
                self.warn('bad_time', 'per-point time field not finite or far outside the sweep: ignored')
                point_time = None
        return cloud, point_time

    def on_imu(self, msg) -> None:
        """A sensor_msgs/Imu, or its serialized bytes (see :meth:`LegoLoamNode.take_imu`)."""
        self.take_imu(msg, self.core.add_imu)

    def on_mapped(self, msg: Odometry | bytes) -> None:
        """mapOptimization's pose of a scan (or its bytes): compared with the IMU's turn by the core's IMU check."""
        ok, msg = self.take_odometry(msg, 'mapped_dropped', '/aft_mapped_to_init dropped', 'bad_mapped')
        if not ok:
            return
        try:
            pose = odometry_to_pose(msg)
        except ValueError as exc:
            self.count('mapped_dropped')
            self.warn('bad_mapped', f'/aft_mapped_to_init dropped: {exc}')
            return
        self.report_imu_alignment(self.core.add_mapped_pose(stamp_to_ns(msg.header.stamp), pose))

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the last scan processed [ns]."""
        return self.order.last_ns

    def on_scan(self, cloud, info, outlier) -> None:
        """A synchronised scan: each part is (message, decoded content)."""
        self.count('scans_in')
        self.drain(self.imu_subscription, self.on_imu)  # the IMU samples that came with this scan first
        stamp = stamp_to_ns(cloud[0].header.stamp)
        decision = self.check_order(
            self.order,
            stamp,
            (cloud, info, outlier),
            lambda held: stamp_to_ns(held[0][0].header.stamp),
            'scan',
            'scans_dropped',
        )
        if decision is None:
            return
        if decision.action == 'reset':
            self.warn(
                'reset',
                f'time jumped back by {-decision.jump_ns * 1e-9:.1f} s (bag restarted?): odometry reset',
                period=0.0,
            )
            self._reset()
        for held in decision.held:
            self._process(*held)
        self._process(cloud, info, outlier)

    def _reset(self) -> None:
        """Start the odometry again (the IMU samples stay: they follow their own timeline)."""
        self.core.reset(keep_imu=True)
        self.order.reset()
        self.count('resets')

    def _process(self, cloud, info, outlier) -> None:
        start = time.perf_counter()
        cloud_msg = cloud[0]
        stamp = stamp_to_ns(cloud_msg.header.stamp)
        try:
            scan = self._scan_input(stamp, cloud[1], info[1], outlier[1])
        except ValueError as exc:  # InputRejected is a ValueError
            # Each part passed its own checks, but the CloudInfo does not fit the cloud: one of them belongs to
            # another scan (a wrong stamp). The CloudInfo goes; the clouds wait for the one that fits them.
            self.count('scans_dropped')
            self.warn('bad_scan', f'CloudInfo dropped: {exc}')
            for name, part in (('cloud', cloud), ('outlier', outlier)):
                self.sync.add(name, stamp_to_ns(part[0].header.stamp), part)
            return
        self.input_valid()
        try:
            result = self.core.process(scan)
        except Exception:
            self.count('scans_dropped')
            self.error('process_exception', 'unexpected error in featureAssociation; scan dropped')
            heal = self.guard.after_failure(self.core.health_problem())
            if heal is not None:
                self._heal(heal)
            return
        heal = self.guard.after_step(self.core.health_problem() or _cloud_problem(result))
        if heal is not None:
            self.count(SCANS_DROPPED)
            self._heal(heal)
            return
        self.order.processed(stamp)
        self._publish(result, cloud_msg.header.stamp)
        self.output_published()
        self.count(SCANS_PROCESSED)
        if result.imu_used:
            self.count(SCANS_WITH_IMU)
        if result.imu_uncovered is not None:
            counter = uncovered_counter(result.imu_uncovered)
            self.count(counter)
            if warn_uncovered(self.counters[counter]):
                self.warn(
                    counter,
                    uncovered_warning(
                        result.imu_uncovered, self.counters[counter], result.stamp_ns, self.params.imu.time_offset
                    ),
                )
        self.report_imu_alignment(result.imu_alignment)
        if result.odometry is not None:
            self._report_conditioning(result.odometry)
        self.record_time('scan', time.perf_counter() - start)

    def _report_conditioning(self, stats) -> None:
        """How well the scan held the odometry: each stage's condition (smallest eigenvalue of its normal
        matrix) and the share of sharp points matched (in the statistics and on /diagnostics), counters of
        degenerate scans, of stages that had to use the walls, of stages that could not run and of scans
        where the odometry was lost, and a throttled warning for the last three."""
        if stats.corner_match_ratio == stats.corner_match_ratio:
            self.record_value('corner_match_ratio', stats.corner_match_ratio)
        if stats.lost:
            self.count('odometry_lost')
            self.warn(
                'odometry_lost',
                f'odometry lost (only {stats.extra["lost_match_ratio"]:.0%} of the sharp points '
                'matched, a turn too fast for the lidar alone?): '
                + (
                    'registered again from standing still'
                    if stats.recovered
                    else 'standing still matched no better; the estimate is kept'
                ),
            )
        for stage, label in (('surf', 'roll, pitch and height'), ('corner', 'yaw and horizontal position')):
            condition = getattr(stats, f'{stage}_condition')
            if condition == condition:  # NaN: the stage did not run
                self.record_value(f'{stage}_condition', condition)
            else:
                self.count(f'{stage}_stage_skipped')
                self.warn(
                    f'{stage}_skipped',
                    f'odometry: too few correspondences for the {label}; that part of the motion is predicted only',
                )
            if getattr(stats, f'{stage}_degenerate'):
                self.count(f'{stage}_degenerate')
            if getattr(stats, f'{stage}_walls'):
                self.count(f'{stage}_wall_fallback')
                self.warn(
                    f'{stage}_walls',
                    f'odometry: few features for the {label}; walls and ceiling used '
                    'instead (degenerate surroundings, e.g. a corridor)',
                )

    def _check_size(self, name: str, msg) -> None:
        """imageProjection's clouds and CloudInfo arrays hold at most one entry per range-image pixel: anything
        bigger is rejected on its header, before it is decoded or kept for synchronisation."""
        limit = validation.derived_points_limit(self.params)
        if name == 'info':
            arrays = cloud_info_from_serialized(msg, copy=False)[1] if isinstance(msg, bytes) else msg
            for field in ('segmented_cloud_range', 'segmented_cloud_col_ind', 'segmented_cloud_ground_flag'):
                validation.check_count(
                    f'{INPUT_TOPICS[name]}.{field} length',
                    len(getattr(arrays, field)),
                    limit,
                    'pixels of the range image',
                )
        else:
            validation.check_count(
                f'{INPUT_TOPICS[name]} points', int(msg.width) * int(msg.height), limit, 'pixels of the range image'
            )

    def _heal(self, problem: str) -> None:
        """The odometry state is poisoned: start it again from the next scan, keeping the pose reached so far
        (when sane) and the IMU samples (when sane)."""
        self.core.restart()
        self.state_reset(problem, 'odometry restarted from the next scan (pose so far kept)')

    def _scan_input(self, stamp: int, cloud, info, outlier) -> ScanInput:
        """The scan from its three decoded parts, once they fit together (raises InputRejected otherwise)."""
        segmented, point_time = cloud
        n = len(segmented)
        validation.check_cloud_info(INPUT_TOPICS['info'], info, self.params, n)
        info = copy.copy(info)  # (the decoded part may be held for a later scan: never change it)
        info.segmented_cloud_range = info.segmented_cloud_range[:n]
        info.segmented_cloud_col_ind = info.segmented_cloud_col_ind[:n]
        info.segmented_cloud_ground_flag = info.segmented_cloud_ground_flag[:n]
        return ScanInput(stamp, segmented, info, outlier, point_time)

    # ---------------------------------------------------------------------------------- outputs
    def _publish(self, result, stamp) -> None:
        pose = result.pose
        header = make_header(stamp, CAMERA_INIT_FRAME)
        if not result.initialized or result.resumed:  # (after a restart the pose reached so far goes on)
            odometry, transform = serialized_odometry(
                pose, header, LASER_ODOM_FRAME, pose_covariance=result.pose_covariance
            )
            self.pub_odometry.publish(odometry)
            self.tf.send_serialized(transform)
        camera = make_header(stamp, CAMERA_FRAME)
        f = result.features
        for publisher, cloud in (
            (self.pub_sharp, f.sharp),
            (self.pub_less_sharp, f.less_sharp),
            (self.pub_flat, f.flat),
            (self.pub_less_flat, f.less_flat),
        ):
            if publisher.get_subscription_count():
                publisher.publish(serialized_xyzi_cloud(cloud, camera))
        if result.corner_last is not None:
            self.pub_corner_last.publish(serialized_xyzi_cloud(result.corner_last, camera))
            self.pub_surf_last.publish(serialized_xyzi_cloud(result.surf_last, camera))
        if result.outlier_last is not None:
            self.pub_outlier_last.publish(serialized_xyzi_cloud(result.outlier_last, camera))


def _cloud_problem(result) -> str | None:
    """Why the clouds about to be published are not sane, or None."""
    for name in ('corner_last', 'surf_last', 'outlier_last'):
        problem = validation.cloud_problem(name, getattr(result, name))
        if problem is not None:
            return problem
    return None


def main(args=None) -> int:
    return run_node(FeatureAssociationNode, args)


if __name__ == '__main__':
    sys.exit(main())
