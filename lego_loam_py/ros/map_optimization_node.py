"""The ``mapOptimization`` node: scan-to-map refinement, keyframe pose graph, loop closure, saved maps.

Subscribes /laser_cloud_corner_last, /laser_cloud_surf_last, /outlier_cloud_last (reliable, depth 2),
/laser_odom_to_init (depth 5), synchronised by stamp within ``map_optimization.sync_tolerance``, and
/imu/data for the roll/pitch blend. Processes at most every ``mapping_process_interval`` and publishes:

* /aft_mapped_to_init (nav_msgs/Odometry, camera_init -> aft_mapped) and its TF; as in the original its
  twist fields carry the odometry pose the step started from (angular = rx, ry, rz; linear = tx, ty, tz),
  which transformFusion needs;
* while subscribed: /key_pose_origin (keyframe positions, intensity = index), /recent_cloud (surface map
  around the robot), /registered_cloud (the current scan in the map), /laser_cloud_surround (global map,
  every ``global_map_publish_period`` s), /history_cloud and /corrected_cloud (loop closure).

Loop closure (``loop_closure.loop_closure_enable_flag``) runs every ``loop_closure.period`` s in its own
callback group, so the ICP does not hold up the mapping steps. The service ``save_map``
(std_srvs/Trigger) and the shutdown hook write the maps and the keyframe trajectory to
``map_optimization.file_directory``.
"""
from __future__ import annotations

import sys
import time

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from sensor_msgs.msg import Imu, PointCloud2
from std_srvs.srv import Trigger

from lego_loam_py.core.frames import AFT_MAPPED_FRAME, CAMERA_INIT_FRAME, matrix_to_pose6, pose6_to_matrix
from lego_loam_py.core.map_optimization import MapOptimization, transform_cloud
from lego_loam_py.core.pointcloud import CloudLayoutError
from lego_loam_py.core.sync import StampSynchronizer
from lego_loam_py.ros import qos
from lego_loam_py.ros.conversions import (cloud_msg_to_xyzi, make_header, odometry_to_pose, pose_to_odometry,
                                          stamp_to_ns, xyzi_to_cloud_msg)
from lego_loam_py.ros.node_base import LegoLoamNode
from lego_loam_py.ros.runtime import run_node
from lego_loam_py.ros.tf import TransformBroadcaster

__all__ = ['MapOptimizationNode', 'main']

RESET_JUMP_NS = 1_000_000_000


class MapOptimizationNode(LegoLoamNode):
    def __init__(self, **kwargs):
        super().__init__('mapOptimization', **kwargs)
        self.core = MapOptimization(self.params)
        mo, lc = self.params.map_optimization, self.params.loop_closure
        self.sync = StampSynchronizer(['corner', 'surf', 'outlier', 'odometry'], int(mo.sync_tolerance * 1e9))
        depth2 = qos.reliable(2)
        self.create_subscription(PointCloud2, '/laser_cloud_corner_last', lambda m: self.on_part('corner', m), depth2)
        self.create_subscription(PointCloud2, '/laser_cloud_surf_last', lambda m: self.on_part('surf', m), depth2)
        self.create_subscription(PointCloud2, '/outlier_cloud_last', lambda m: self.on_part('outlier', m), depth2)
        self.create_subscription(Odometry, '/laser_odom_to_init', lambda m: self.on_part('odometry', m),
                                 qos.reliable(5))
        if self.params.sensor.imu_topic:
            self.create_subscription(Imu, self.params.sensor.imu_topic, self.on_imu, qos.sensor_input(50))
        self.pub_aft_mapped = self.create_publisher(Odometry, '/aft_mapped_to_init', qos.reliable(5))
        self.tf = TransformBroadcaster(self)
        self.pub_key_poses = self.create_publisher(PointCloud2, '/key_pose_origin', depth2)
        self.pub_surround = self.create_publisher(PointCloud2, '/laser_cloud_surround', depth2)
        self.pub_recent = self.create_publisher(PointCloud2, '/recent_cloud', depth2)
        self.pub_registered = self.create_publisher(PointCloud2, '/registered_cloud', depth2)
        self.pub_history = self.create_publisher(PointCloud2, '/history_cloud', depth2)
        self.pub_corrected = self.create_publisher(PointCloud2, '/corrected_cloud', depth2)
        self.create_service(Trigger, 'save_map', self.on_save_map)
        self.last_stamp_ns: int | None = None
        self.last_step_stamp = None
        background = MutuallyExclusiveCallbackGroup()
        self.create_timer(mo.global_map_publish_period, self.publish_global_map, callback_group=background)
        if lc.loop_closure_enable_flag:
            self.create_timer(lc.period, self.loop_closure, callback_group=MutuallyExclusiveCallbackGroup())
        self.get_logger().info(f'mapOptimization: every {mo.mapping_process_interval} s, loop closure '
                               f'{"on" if lc.loop_closure_enable_flag else "off"}, maps saved to {mo.file_directory}')

    # ------------------------------------------------------------------------------------------ inputs
    def on_part(self, name: str, msg) -> None:
        try:
            complete = self.sync.add(name, stamp_to_ns(msg.header.stamp), msg)
        except Exception:
            self.error('sync_exception', 'unexpected error while synchronising inputs')
            return
        if self.sync.dropped:
            self.count('unmatched_inputs', self.sync.dropped)
            self.sync.dropped = 0
        if complete is not None:
            self.on_inputs(complete)

    def on_imu(self, msg: Imu) -> None:
        o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
        reason = self.core.imu.add(stamp_to_ns(msg.header.stamp) * 1e-9, (o.x, o.y, o.z, o.w), (w.x, w.y, w.z),
                                   (a.x, a.y, a.z))
        if reason is not None:
            self.count('imu_dropped')
            self.warn('imu', f'IMU message dropped: {reason}')

    def on_inputs(self, parts: dict) -> None:
        start = time.perf_counter()
        odometry = parts['odometry']
        stamp = stamp_to_ns(odometry.header.stamp)
        if self.last_stamp_ns is not None and stamp <= self.last_stamp_ns:
            if stamp < self.last_stamp_ns - RESET_JUMP_NS:
                self._reset_after_time_jump(stamp)
            else:
                self.count('inputs_dropped')
                self.warn('order', 'input older than or as old as the previous one dropped (out of order/duplicate)')
                return
        try:
            transform_sum = matrix_to_pose6(odometry_to_pose(odometry))
            corner = cloud_msg_to_xyzi(parts['corner'])
            surf = cloud_msg_to_xyzi(parts['surf'])
            outlier = cloud_msg_to_xyzi(parts['outlier'])
            for name, cloud in (('corner', corner), ('surf', surf), ('outlier', outlier)):
                if not np.isfinite(cloud[:, :3]).all():
                    raise ValueError(f'non-finite coordinates in the {name} cloud')
        except (CloudLayoutError, ValueError) as exc:
            self.count('inputs_dropped')
            self.warn('bad_input', f'mapping input dropped: {exc}')
            return
        self.last_stamp_ns = stamp
        try:
            step = self.core.process(stamp, transform_sum, corner, surf, outlier)
        except Exception:
            self.count('steps_failed')
            self.error('process_exception', 'unexpected error in mapOptimization; step skipped')
            return
        if step is None:
            self.count('inputs_skipped_by_interval')
            return
        self.count('steps')
        if step.keyframe_added:
            self.count('keyframes')
        self._publish(step, odometry.header.stamp)
        self.record_time('step', time.perf_counter() - start)

    def _reset_after_time_jump(self, stamp: int) -> None:
        """A bag restarted: keep the map built so far on disk, then start a new one."""
        mo = self.params.map_optimization
        jump = (self.last_stamp_ns - stamp) * 1e-9
        saved = ''
        if self.core.keyframes and mo.save_map_on_shutdown:
            try:
                self.core.save(mo.file_directory)
                saved = f'; the previous map was saved to {mo.file_directory}'
            except OSError as exc:
                saved = f'; saving the previous map failed: {exc}'
        self.warn('reset', f'time jumped back by {jump:.1f} s (bag restarted?): mapping reset{saved}', period=0.0)
        self.core = MapOptimization(self.params)
        self.sync.clear()
        self.count('resets')

    # ----------------------------------------------------------------------------------------- outputs
    def _publish(self, step, stamp) -> None:
        pose = pose6_to_matrix(step.transform_aft)
        header = make_header(stamp, CAMERA_INIT_FRAME)
        bef = step.transform_bef
        self.pub_aft_mapped.publish(pose_to_odometry(pose, header, AFT_MAPPED_FRAME, twist_angular=bef[:3],
                                                     twist_linear=bef[3:]))
        self.tf.send_pose(pose, stamp, CAMERA_INIT_FRAME, AFT_MAPPED_FRAME)
        self.last_step_stamp = stamp
        if self.pub_key_poses.get_subscription_count():
            poses = self.core.keyframe_poses()
            key = np.concatenate([poses[:, 3:], np.arange(len(poses))[:, None]], axis=1)
            self.pub_key_poses.publish(xyzi_to_cloud_msg(key, header))
        if self.pub_recent.get_subscription_count():
            self.pub_recent.publish(xyzi_to_cloud_msg(self.core.last_maps[1], header))
        if self.pub_registered.get_subscription_count():
            corner, surf = self.core.last_scan
            registered = transform_cloud(np.concatenate([corner, surf]), step.transform_aft)
            self.pub_registered.publish(xyzi_to_cloud_msg(registered, header))

    def publish_global_map(self) -> None:
        if self.last_step_stamp is None or not self.pub_surround.get_subscription_count():
            return
        try:
            cloud = self.core.global_map()
        except Exception:
            self.error('global_map', 'building the global map failed')
            return
        self.pub_surround.publish(xyzi_to_cloud_msg(cloud, make_header(self.last_step_stamp, CAMERA_INIT_FRAME)))

    def loop_closure(self) -> None:
        try:
            candidate = self.core.detect_loop()
            if candidate is None:
                return
            result = self.core.close_loop(candidate)
        except Exception:
            self.error('loop_exception', 'loop closure failed')
            return
        stamp = self.last_step_stamp
        if stamp is not None and self.pub_history.get_subscription_count():
            self.pub_history.publish(xyzi_to_cloud_msg(candidate.target, make_header(stamp, CAMERA_INIT_FRAME)))
        if result.accepted:
            self.count('loops_closed')
            self.get_logger().info(f'loop closed: keyframe {result.latest} -> {result.candidate} '
                                   f'(ICP fitness {result.fitness:.3f})')
            if stamp is not None and self.pub_corrected.get_subscription_count():
                corrected = candidate.source.copy()
                corrected[:, :3] = corrected[:, :3] @ result.correction[:3, :3].T + result.correction[:3, 3]
                self.pub_corrected.publish(xyzi_to_cloud_msg(corrected, make_header(stamp, CAMERA_INIT_FRAME)))
        else:
            self.count('loops_rejected')

    def on_save_map(self, request, response):
        directory = self.params.map_optimization.file_directory
        try:
            written = self.core.save(directory)
            response.success = True
            response.message = f'saved {len(self.core.keyframes)} keyframes: ' + ', '.join(str(p) for p in written.values())
        except Exception as exc:  # report, never crash the node
            response.success = False
            response.message = f'saving to {directory} failed: {exc}'
        return response

    def on_shutdown(self) -> None:
        mo = self.params.map_optimization
        if mo.save_map_on_shutdown and self.core.keyframes:
            try:
                written = self.core.save(mo.file_directory)
                self.get_logger().info(f'map saved: {", ".join(str(p) for p in written.values())}')
            except Exception as exc:
                self.get_logger().error(f'saving the map to {mo.file_directory} failed: {exc}')
        super().on_shutdown()


def main(args=None) -> int:
    return run_node(MapOptimizationNode, args, threads=2)


if __name__ == '__main__':
    sys.exit(main())
