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
from lego_loam_py.ros.conversions import pose_to_transform, transform_to_pose

__all__ = [
    'TransformBroadcaster',
    'StaticTransformBroadcaster',
    'original_static_transforms',
    'StaticTransformListener',
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


def original_static_transforms(
    stamp: Time | int = 0, map_frame: str = frames.MAP_FRAME, lidar_is_base_link: bool = True
) -> list[TransformStamped]:
    """The two static transforms of the original run.launch: map->camera_init and camera->base_link. The second
    only while ``base_link`` is the lidar itself: in the REP-105 tree base_link is the robot's body, whose parent is
    odom (a frame has one parent in tf2)."""
    out = [pose_to_transform(frames.MAP_T_CAMERA_INIT, stamp, map_frame, frames.CAMERA_INIT_FRAME)]
    if lidar_is_base_link:
        out.append(pose_to_transform(frames.CAMERA_T_BASE_LINK, stamp, frames.CAMERA_FRAME, frames.BASE_LINK_FRAME))
    return out


class StaticTransformListener:
    """The static transforms on latched /tf_static (a robot_state_publisher's), looked up as a chain of them."""

    def __init__(self, node: Node, topic: str = '/tf_static'):
        self._parent_of: dict[str, tuple[str, np.ndarray]] = {}  # child -> (parent, parent_T_child)
        node.create_subscription(TFMessage, topic, self._on_transforms, TF_STATIC_QOS)

    def _on_transforms(self, msg: TFMessage) -> None:
        for t in msg.transforms:
            pose = transform_to_pose(t)
            if np.isfinite(pose).all():
                self._parent_of[t.child_frame_id.lstrip('/')] = (t.header.frame_id.lstrip('/'), pose)

    def lookup(self, parent: str, child: str) -> np.ndarray | None:
        """4x4 ``parent_T_child`` along the static tree (child up to parent), or None while not (yet) known."""
        pose, frame = np.eye(4), child
        for _ in range(len(self._parent_of) + 1):
            if frame == parent:
                return pose
            if frame not in self._parent_of:
                return None
            frame, step = self._parent_of[frame]
            pose = step @ pose
        return None  # (a cycle)
