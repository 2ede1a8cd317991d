"""QoS profiles of the original's topics (docs/original.md §4, §14).

Sensor inputs are best effort, which matches both reliable and best-effort publishers (drivers use either).
Internal topics are reliable keep-last with the original's queue sizes: depth 1 means a slow node always
works on the latest message, as the original's ROS 1 queues of size 1 do.
"""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = ['sensor_input', 'reliable', 'latched']


def sensor_input(depth: int) -> QoSProfile:
    """Subscriber QoS for driver topics (/velodyne_points, /imu/data)."""
    return QoSProfile(
        depth=depth,
        history=HistoryPolicy.KEEP_LAST,
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
    )


def reliable(depth: int) -> QoSProfile:
    """Reliable keep-last QoS for topics between the nodes."""
    return QoSProfile(
        depth=depth,
        history=HistoryPolicy.KEEP_LAST,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def latched(depth: int = 1) -> QoSProfile:
    """Transient-local QoS: late subscribers receive the last message(s)."""
    return QoSProfile(
        depth=depth,
        history=HistoryPolicy.KEEP_LAST,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
