"""TF publishing without tf2_ros (not installable from PyPI): /tf and latched /tf_static.

Messages are tf2_msgs/TFMessage, so rviz2, tf2_echo and every tf2 listener understand them. The static
broadcaster behaves like tf2_ros's: one transient-local publisher that re-sends the accumulated set of
static transforms, so subscribers that start late still receive all of them.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

from lego_loam_py.core import frames
from lego_loam_py.ros.conversions import pose_to_transform

__all__ = [
    'TransformBroadcaster',
    'StaticTransformBroadcaster',
    'original_static_transforms',
    'TF_QOS',
    'TF_STATIC_QOS',
]

TF_QOS = QoSProfile(
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
)
TF_STATIC_QOS = QoSProfile(
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
)


class TransformBroadcaster:
    """Publishes dynamic transforms on /tf."""

    def __init__(self, node: Node, topic: str = '/tf'):
        self._publisher = node.create_publisher(TFMessage, topic, TF_QOS)

    def send(self, transforms: TransformStamped | Iterable[TransformStamped]) -> None:
        if isinstance(transforms, TransformStamped):
            transforms = [transforms]
        self._publisher.publish(TFMessage(transforms=list(transforms)))

    def send_pose(self, pose: np.ndarray, stamp: Time | int, parent: str, child: str) -> None:
        self.send(pose_to_transform(pose, stamp, parent, child))

    def send_serialized(self, data: bytes) -> None:
        """A serialized TFMessage (see :func:`~lego_loam_py.ros.conversions.serialized_odometry`)."""
        self._publisher.publish(data)


class StaticTransformBroadcaster:
    """Publishes static transforms on latched /tf_static, keeping one entry per child frame."""

    def __init__(self, node: Node, topic: str = '/tf_static'):
        self._publisher = node.create_publisher(TFMessage, topic, TF_STATIC_QOS)
        self._by_child: dict[str, TransformStamped] = {}

    def send(self, transforms: TransformStamped | Iterable[TransformStamped]) -> None:
        if isinstance(transforms, TransformStamped):
            transforms = [transforms]
        for t in transforms:
            self._by_child[t.child_frame_id] = t
        self._publisher.publish(TFMessage(transforms=list(self._by_child.values())))


def original_static_transforms(stamp: Time | int = 0) -> list[TransformStamped]:
    """The two static transforms of the original run.launch: map->camera_init and camera->base_link."""
    return [
        pose_to_transform(frames.MAP_T_CAMERA_INIT, stamp, frames.MAP_FRAME, frames.CAMERA_INIT_FRAME),
        pose_to_transform(frames.CAMERA_T_BASE_LINK, stamp, frames.CAMERA_FRAME, frames.BASE_LINK_FRAME),
    ]
