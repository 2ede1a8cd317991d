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
"""

from __future__ import annotations

import sys
import time

import numpy as np
from nav_msgs.msg import Odometry

from lego_loam_py.core.frames import CAMERA_FRAME, CAMERA_INIT_FRAME, pose6_to_matrix
from lego_loam_py.core.mapping.transform_fusion import TransformFusion
from lego_loam_py.ros import qos
from lego_loam_py.ros.conversions import (
    MAX_POSITION,
    make_header,
    odometry_covariance,
    odometry_to_pose,
    serialized_odometry,
    stamp_to_ns,
)
from lego_loam_py.ros.node_base import LegoLoamNode
from lego_loam_py.ros.runtime import run_node
from lego_loam_py.ros.sync import StampOrder
from lego_loam_py.ros.tf import StaticTransformBroadcaster, TransformBroadcaster, original_static_transforms

__all__ = ['TransformFusionNode', 'main']

RESET_JUMP_NS = 1_000_000_000
MAPPED_AHEAD_NS = 1_000_000_000  # a mapping result is never ahead of the odometry it was computed from


class TransformFusionNode(LegoLoamNode):
    def __init__(self, **kwargs):
        super().__init__('transformFusion', **kwargs)
        localizing = self.params.map_optimization.mode == 'localization'
        self.core = TransformFusion(int(self.params.localization.max_correction_age * 1e9) if localizing else None)
        self.create_subscription(Odometry, '/laser_odom_to_init', self.on_odometry, qos.reliable(5))
        self.create_subscription(Odometry, '/aft_mapped_to_init', self.on_mapped, qos.reliable(5))
        self.pub_integrated = self.create_publisher(Odometry, '/integrated_to_init', qos.reliable(5))
        self.tf = TransformBroadcaster(self)
        self.static_tf = StaticTransformBroadcaster(self)
        self.static_tf.send(original_static_transforms(self.get_clock().now().nanoseconds))
        self.order = StampOrder(RESET_JUMP_NS)
        self._timeline_start_ns: int | None = None  # first odometry integrated since the last reset

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the last odometry message integrated [ns]."""
        return self.order.last_ns

    def on_mapped(self, msg: Odometry) -> None:
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

    def on_odometry(self, msg: Odometry) -> None:
        self.count('odometry_in')
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
        covariance = odometry_covariance(msg)
        mapped = self.core.integrate(odometry, covariance, stamp_ns) if problem is None else None
        if problem is None and not (np.isfinite(mapped).all() and np.abs(mapped[:3, 3]).max() <= MAX_POSITION):
            problem = 'the fused pose is not finite or absurd'
        if problem is not None:
            # Only the correction can be poisoned (each odometry message is checked): start again without it;
            # the next /aft_mapped_to_init brings it back.
            self.core.reset()
            self.state_reset(problem, 'map correction reset (the next mapping result restores it)')
            mapped = self.core.integrate(odometry, covariance, stamp_ns)
        self.order.processed(stamp_to_ns(msg.header.stamp))
        header = make_header(msg.header.stamp, CAMERA_INIT_FRAME)
        odometry, transform = serialized_odometry(
            mapped, header, CAMERA_FRAME, pose_covariance=self.core.covariance if covariance is not None else None
        )
        self.pub_integrated.publish(odometry)
        self.tf.send_serialized(transform)
        self.count('integrated')
        self.output_published()
        self.record_time('odometry', time.perf_counter() - start)  # conversion, fusion and publishing


def main(args=None) -> int:
    return run_node(TransformFusionNode, args)


if __name__ == '__main__':
    sys.exit(main())
