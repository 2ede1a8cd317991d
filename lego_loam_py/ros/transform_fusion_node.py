"""The ``transformFusion`` node: /laser_odom_to_init corrected by /aft_mapped_to_init -> /integrated_to_init.

Publishes, for every odometry message, /integrated_to_init (nav_msgs/Odometry, camera_init -> camera) and
the TF camera_init -> camera; once at start-up, latched on /tf_static, the original launch file's static
transforms map -> camera_init and camera -> base_link, so the whole tree map -> ... -> base_link exists
without any other node.

In localization (``map_optimization.mode: localization``) a fused pose is published only while the last
/aft_mapped_to_init is at most ``localization.max_correction_age`` older than the odometry: before the first fix
in the saved map, and once mapOptimization lost track, no pose goes out as if it were in the map's frame.

Odometry older than the previous message is dropped (out of order or duplicate); a jump of more than a
second is believed once later messages continue the new timeline (forward the next one, back three in a
row), and back to before the current timeline began (a bag restarted) it resets the map correction. A mapping
result from before that reset, or stamped more than ``MAPPED_AHEAD_NS`` after the latest odometry (the old
timeline, after a jump back), is discarded. Poses that
are not finite, not unit quaternions or absurdly far are dropped with a throttled warning.

With ``frames.rep105`` (:class:`~lego_loam_py.core.frames.Rep105Frames`) it also publishes, for every odometry
message, the REP-105 tree on /tf: ``odom -> base_link`` (the odometry, always) and ``map -> odom`` (the mapping's
correction; in localization only while /integrated_to_init is), the odometry as nav_msgs/Odometry on
``frames.odometry_topic`` (twist in base_link) and base_link's pose in the map on ``frames.pose_topic``; the lidar's
mounting on base_link comes from the ``frames.lidar_*`` parameters (published on /tf_static) or from /tf_static.
The static ``camera -> base_link`` is then left out: base_link's parent is odom.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry

from lego_loam_py.core.frames import CAMERA_FRAME, CAMERA_INIT_FRAME, Rep105Frames, body_twist, pose6_to_matrix
from lego_loam_py.core.mapping.transform_fusion import TransformFusion
from lego_loam_py.ros import qos
from lego_loam_py.ros.conversions import (
    MAX_POSITION,
    make_header,
    odometry_covariance,
    odometry_to_pose,
    pose_to_odometry,
    pose_to_transform,
    serialized_odometry,
    stamp_to_ns,
)
from lego_loam_py.ros.node_base import LegoLoamNode
from lego_loam_py.ros.runtime import run_node
from lego_loam_py.ros.sync import StampOrder
from lego_loam_py.ros.tf import (
    StaticTransformBroadcaster,
    StaticTransformListener,
    TransformBroadcaster,
    original_static_transforms,
)

__all__ = ['TransformFusionNode', 'main']

RESET_JUMP_NS = 1_000_000_000
MAPPED_AHEAD_NS = 1_000_000_000  # a mapping result is never ahead of the odometry it was computed from


class TransformFusionNode(LegoLoamNode):
    def __init__(self, **kwargs):
        super().__init__('transformFusion', **kwargs)
        localizing = self.params.map_optimization.mode == 'localization'
        self.core = TransformFusion(int(self.params.localization.max_correction_age * 1e9) if localizing else None)
        # (serialized: read by odometry_from_serialized, without rclpy's message objects)
        self.create_subscription(Odometry, '/laser_odom_to_init', self.on_odometry, qos.reliable(5), raw=True)
        self.create_subscription(Odometry, '/aft_mapped_to_init', self.on_mapped, qos.reliable(5), raw=True)
        self.pub_integrated = self.create_publisher(Odometry, '/integrated_to_init', qos.reliable(5))
        self.tf = TransformBroadcaster(self)
        self.static_tf = StaticTransformBroadcaster(self)
        frames = self.params.frames
        now = self.get_clock().now().nanoseconds
        self.static_tf.send(original_static_transforms(now, frames.map_frame, lidar_is_base_link=not frames.rep105))
        self.rep105: Rep105Frames | None = None  # the REP-105 tree, once the lidar's mounting is known
        self._mount_listener: StaticTransformListener | None = None
        # The previous odometry: (stamp [ns], odom -> base_link, its LOAM pose, that one's covariance or None).
        self._previous_base: tuple | None = None
        if frames.rep105:
            self.pub_rep105_odometry = self.create_publisher(Odometry, frames.odometry_topic, qos.reliable(5))
            self.pub_rep105_pose = self.create_publisher(PoseWithCovarianceStamped, frames.pose_topic, qos.reliable(5))
            if frames.lidar_mount == 'parameters':
                self.rep105 = Rep105Frames.from_mount(frames.lidar_translation, frames.lidar_rotation_rpy)
                mount = pose_to_transform(self.rep105.base_T_lidar, now, frames.base_frame, frames.lidar_frame)
                self.static_tf.send(mount)
            else:
                self._mount_listener = StaticTransformListener(self)
        self.order = StampOrder(RESET_JUMP_NS)
        self._timeline_start_ns: int | None = None  # first odometry integrated since the last reset

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the last odometry message integrated [ns]."""
        return self.order.last_ns

    def on_mapped(self, msg: Odometry | bytes) -> None:
        ok, msg = self.take_odometry(msg, 'mapped_dropped', '/aft_mapped_to_init dropped', 'bad_mapped')
        if not ok:
            return
        stamp = stamp_to_ns(msg.header.stamp)
        last = self.order.newest_ns  # (an odometry message held after a gap counts: mapping may have used it)
        if (last is not None and stamp > last + MAPPED_AHEAD_NS) or (
            self._timeline_start_ns is not None and stamp < self._timeline_start_ns
        ):
            self.count('mapped_dropped')
            self.warn(
                'stale_mapped',
                f'/aft_mapped_to_init stamped {(stamp - (last or stamp)) * 1e-9:+.1f} s from the '
                'odometry dropped: it belongs to the timeline before a restart',
            )
            return
        try:
            aft = odometry_to_pose(msg)
            twist = msg.twist.twist
            bef6 = np.array(
                [twist.angular.x, twist.angular.y, twist.angular.z, twist.linear.x, twist.linear.y, twist.linear.z]
            )
            if not np.isfinite(bef6).all():
                raise ValueError('the twist fields (the pre-mapping pose) are not finite')
            if not ((np.abs(bef6[:3]) <= 100.0).all() and (np.abs(bef6[3:]) <= MAX_POSITION).all()):
                raise ValueError('the twist fields (the pre-mapping pose) are absurd')
            bef = pose6_to_matrix(bef6)
        except ValueError as exc:
            self.count('mapped_dropped')
            self.warn('bad_mapped', f'/aft_mapped_to_init dropped: {exc}')
            return
        self.core.on_mapped(aft, bef, stamp, odometry_covariance(msg))
        self.count('mapped')

    def on_odometry(self, msg: Odometry | bytes) -> None:
        self.count('odometry_in')
        ok, msg = self.take_odometry(msg, 'odometry_dropped', '/laser_odom_to_init dropped', 'bad_odometry')
        if not ok:
            return
        decision = self.check_order(
            self.order,
            stamp_to_ns(msg.header.stamp),
            msg,
            lambda m: stamp_to_ns(m.header.stamp),
            'odometry message',
            'odometry_dropped',
        )
        if decision is None:  # dropped or held
            return
        if decision.action == 'reset':
            self.warn(
                'reset', f'time jumped back by {-decision.jump_ns * 1e-9:.1f} s: map correction reset', period=0.0
            )
            self.core.reset()
            self.order.reset()
            self._previous_base = None
            self._timeline_start_ns = stamp_to_ns((decision.held[0] if decision.held else msg).header.stamp)
            self.count('resets')
        for held in decision.held:
            self._integrate(held)
        self._integrate(msg)

    def _integrate(self, msg: Odometry) -> None:
        start = time.perf_counter()
        ok, odometry = self.take(
            lambda: odometry_to_pose(msg), 'odometry_dropped', '/laser_odom_to_init dropped', 'bad_odometry'
        )
        if not ok:
            return
        stamp_ns = stamp_to_ns(msg.header.stamp)
        covariance = odometry_covariance(msg)
        if self.params.frames.rep105:
            self._publish_odom_frame(msg, odometry, covariance, stamp_ns)
        if not self.core.publishable(stamp_ns):  # (localization without a recent fix: withheld, not silent by fault)
            self.order.processed(stamp_ns)
            self.count('withheld_not_localized')
            self.warn(
                'not_localized',
                'no /integrated_to_init: mapOptimization has no recent fix in the saved map (see /localization_status)',
            )
            return
        self.input_valid()
        problem = self.core.health_problem()
        mapped = self.core.integrate(odometry, covariance, stamp_ns) if problem is None else None
        if problem is None and not (np.isfinite(mapped).all() and np.abs(mapped[:3, 3]).max() <= MAX_POSITION):
            problem = 'the fused pose is not finite or absurd'
        if problem is not None:
            # Only the correction can be poisoned (each odometry message is checked): start again without it;
            # the next /aft_mapped_to_init brings it back.
            self.core.reset()
            self.state_reset(problem, 'map correction reset (the next mapping result restores it)')
            mapped = self.core.integrate(odometry, covariance, stamp_ns)
        self.order.processed(stamp_ns)
        header = make_header(msg.header.stamp, CAMERA_INIT_FRAME)
        integrated, transform = serialized_odometry(
            mapped, header, CAMERA_FRAME, pose_covariance=self.core.covariance if covariance is not None else None
        )
        self.pub_integrated.publish(integrated)
        self.tf.send_serialized(transform)
        if self.rep105 is not None:
            self._publish_map_frame(msg, mapped, odometry)
        self.count('integrated')
        self.output_published()
        self.record_time('odometry', time.perf_counter() - start)  # conversion, fusion and publishing

    def _mount_known(self) -> bool:
        """Whether the REP-105 frames can be published: the lidar's mounting is known (from the parameters, or
        once /tf_static carried base_frame -> lidar_frame)."""
        if self.rep105 is None and self._mount_listener is not None:
            frames = self.params.frames
            base_T_lidar = self._mount_listener.lookup(frames.base_frame, frames.lidar_frame)
            if base_T_lidar is None:
                self.count('rep105_waiting_for_mount')
                self.warn(
                    'no_mount',
                    f'no REP-105 frames yet: /tf_static has no {frames.base_frame} -> {frames.lidar_frame} '
                    '(frames.lidar_mount: tf_static; is a robot_state_publisher running?)',
                )
                return False
            self.rep105 = Rep105Frames(base_T_lidar)
            self.get_logger().info(f'lidar mounting read from /tf_static: {frames.base_frame} -> {frames.lidar_frame}')
        return self.rep105 is not None

    def _publish_odom_frame(
        self, msg: Odometry, odometry: np.ndarray, covariance: np.ndarray | None, stamp_ns: int
    ) -> None:
        """odom -> base_link on /tf and the odometry topic (REP-103 axes, twist in base_link, their covariances)."""
        if not self._mount_known():
            return
        frames = self.params.frames
        odom_T_base = self.rep105.odom_to_base(odometry)
        pose_covariance = twist_covariance = None
        if covariance is not None:
            pose_covariance = self.rep105.odom_to_base_covariance(odometry, covariance)
        twist = np.zeros(6)
        previous = self._previous_base
        if previous is not None and stamp_ns > previous[0]:
            dt = (stamp_ns - previous[0]) * 1e-9
            twist = body_twist(previous[1], odom_T_base, dt)
            if covariance is not None and previous[3] is not None:
                twist_covariance = self.rep105.twist_covariance(previous[2], previous[3], odometry, covariance, dt)
        self._previous_base = (stamp_ns, odom_T_base, odometry, covariance)
        header = make_header(msg.header.stamp, frames.odom_frame)
        out = pose_to_odometry(
            odom_T_base,
            header,
            frames.base_frame,
            twist_angular=twist[3:],
            twist_linear=twist[:3],
            pose_covariance=pose_covariance,
            twist_covariance=twist_covariance,
        )
        self.pub_rep105_odometry.publish(out)
        self.tf.send(pose_to_transform(odom_T_base, msg.header.stamp, frames.odom_frame, frames.base_frame))

    def _publish_map_frame(self, msg: Odometry, mapped: np.ndarray, odometry: np.ndarray) -> None:
        """map -> odom on /tf and base_link's pose in the map."""
        frames = self.params.frames
        map_T_odom = self.rep105.map_to_odom(mapped, odometry)
        self.tf.send(pose_to_transform(map_T_odom, msg.header.stamp, frames.map_frame, frames.odom_frame))
        pose = PoseWithCovarianceStamped()
        pose.header = make_header(msg.header.stamp, frames.map_frame)
        covariance = (
            self.rep105.base_in_covariance(mapped, self.core.covariance) if self.core.covariance.any() else None
        )
        pose.pose = pose_to_odometry(
            self.rep105.base_in(mapped), pose.header, frames.base_frame, pose_covariance=covariance
        ).pose
        self.pub_rep105_pose.publish(pose)


def main(args=None) -> int:
    return run_node(TransformFusionNode, args)


if __name__ == '__main__':
    sys.exit(main())
