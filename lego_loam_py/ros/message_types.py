"""Message classes from type names ('sensor_msgs/msg/PointCloud2')."""

from __future__ import annotations

import importlib

__all__ = ['get_message_class', 'message_type_name']


def get_message_class(msgtype: str) -> type:
    """The rclpy message class of 'pkg/msg/Type' (raises LookupError when not installed)."""
    parts = msgtype.split('/')
    if len(parts) == 2:  # 'pkg/Type' (ROS 1 style)
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts):
        raise LookupError(f"'{msgtype}' is not a message type name (expected 'package/msg/Type')")
    package, kind, name = parts
    try:
        module = importlib.import_module(f'{package}.{kind}')
        return getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise LookupError(f"message type '{msgtype}' is not installed") from exc


def message_type_name(cls: type) -> str:
    """'pkg/msg/Type' of an rclpy message class."""
    module = cls.__module__.split('.')
    return f'{module[0]}/{module[1]}/{cls.__name__}'
