"""The ``transformFusion`` node: /laser_odom_to_init corrected by /aft_mapped_to_init -> /integrated_to_init.

Publishes, for every odometry message, /integrated_to_init (nav_msgs/Odometry, camera_init -> camera) and
the TF camera_init -> camera; once at start-up, latched on /tf_static, the original launch file's static
transforms map -> camera_init and camera -> base_link, so the whole tree map -> ... -> base_link exists
without any other node. A mapping result older than the odometry stream by more than a second after a jump
back in time is discarded (bag restarted).
"""
from __future__ import annotations

import sys

import numpy as np
from nav_msgs.msg import Odometry

from lego_loam_py.core.frames import CAMERA_FRAME, CAMERA_INIT_FRAME, pose6_to_matrix
from lego_loam_py.core.transform_fusion import TransformFusion
from lego_loam_py.ros import qos
from lego_loam_py.ros.conversions import make_header, odometry_to_pose, pose_to_odometry, stamp_to_ns
from lego_loam_py.ros.node_base import LegoLoamNode
from lego_loam_py.ros.runtime import run_node
from lego_loam_py.ros.tf import StaticTransformBroadcaster, TransformBroadcaster, original_static_transforms

__all__ = ['TransformFusionNode', 'main']

RESET_JUMP_NS = 1_000_000_000


class TransformFusionNode(LegoLoamNode):
    def __init__(self, **kwargs):
        super().__init__('transformFusion', **kwargs)
        self.core = TransformFusion()
        self.create_subscription(Odometry, '/laser_odom_to_init', self.on_odometry, qos.reliable(5))
        self.create_subscription(Odometry, '/aft_mapped_to_init', self.on_mapped, qos.reliable(5))
        self.pub_integrated = self.create_publisher(Odometry, '/integrated_to_init', qos.reliable(5))
        self.tf = TransformBroadcaster(self)
        self.static_tf = StaticTransformBroadcaster(self)
        self.static_tf.send(original_static_transforms(self.get_clock().now().nanoseconds))
        self.last_stamp_ns: int | None = None

    def on_mapped(self, msg: Odometry) -> None:
        try:
            aft = odometry_to_pose(msg)
            twist = msg.twist.twist
            bef6 = np.array([twist.angular.x, twist.angular.y, twist.angular.z,
                             twist.linear.x, twist.linear.y, twist.linear.z])
            if not np.isfinite(bef6).all():
                raise ValueError('the twist fields (the pre-mapping pose) are not finite')
            bef = pose6_to_matrix(bef6)
        except ValueError as exc:
            self.count('mapped_dropped')
            self.warn('bad_mapped', f'/aft_mapped_to_init dropped: {exc}')
            return
        self.core.on_mapped(aft, bef)
        self.count('mapped')

    def on_odometry(self, msg: Odometry) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        if self.last_stamp_ns is not None and stamp < self.last_stamp_ns - RESET_JUMP_NS:
            self.warn('reset', f'time jumped back by {(self.last_stamp_ns - stamp) * 1e-9:.1f} s: map correction '
                               'reset', period=0.0)
            self.core.reset()
        try:
            odometry = odometry_to_pose(msg)
        except ValueError as exc:
            self.count('odometry_dropped')
            self.warn('bad_odometry', f'/laser_odom_to_init dropped: {exc}')
            return
        self.last_stamp_ns = stamp
        mapped = self.core.integrate(odometry)
        header = make_header(msg.header.stamp, CAMERA_INIT_FRAME)
        self.pub_integrated.publish(pose_to_odometry(mapped, header, CAMERA_FRAME))
        self.tf.send_pose(mapped, msg.header.stamp, CAMERA_INIT_FRAME, CAMERA_FRAME)
        self.count('integrated')


def main(args=None) -> int:
    return run_node(TransformFusionNode, args)


if __name__ == '__main__':
    sys.exit(main())
