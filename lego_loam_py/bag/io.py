"""Reading and writing bags with rosbags (pure Python; no rclpy, no rosbag2_py).

* :class:`BagReader` reads ROS 1 ``.bag`` files and ROS 2 bags (``.db3`` or ``.mcap``) and yields every
  message as ROS 2 CDR bytes: ROS 1 messages are converted to their ROS 2 types (header stamps and frame
  ids carry over; ROS 1's ``Header.seq`` is dropped).
* :class:`BagWriter` writes ROS 2 bags (mcap by default, sqlite3 on request) or ROS 1 bags, from CDR
  bytes or from rosbags message objects.
* :func:`ros2_typestore` is the Kilted type store plus every message type installed on this machine that
  it lacks (``cloud_msgs/msg/CloudInfo`` above all), found through ``AMENT_PREFIX_PATH``.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection, Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from lego_loam_py.core.pointcloud import CloudBuffer, array_to_cloud, cloud_to_array
from lego_loam_py.errors import LegoLoamError

__all__ = [
    'BagError',
    'BagReader',
    'BagWriter',
    'BagMessage',
    'ros2_typestore',
    'ros1_typestore',
    'resolve_bag_path',
    'cloud_msg_to_array',
    'make_cloud_msg',
    'CLOUD_INFO_MSG_TYPE',
]

CLOUD_INFO_MSG_TYPE = 'cloud_msgs/msg/CloudInfo'
_FOREVER = QosTime(2147483647, 4294967295)
# Offered QoS of a latched topic (/tf_static), as rosbag2 records it.
_LATCHED_QOS = [
    Qos(
        QosHistory.KEEP_LAST,
        1,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL,
        _FOREVER,
        _FOREVER,
        QosLiveliness.AUTOMATIC,
        _FOREVER,
        avoid_ros_namespace_conventions=False,
    )
]
_ROS1_RENAMES = {'tf/msg/tfMessage': 'tf2_msgs/msg/TFMessage'}


class BagError(LegoLoamError, RuntimeError):
    """A bag cannot be opened, read or written."""


def _msg_files() -> dict[str, Path]:
    """'pkg/msg/Type' -> .msg file of every message installed in an AMENT_PREFIX_PATH prefix."""
    found: dict[str, Path] = {}
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    source_tree = Path(__file__).resolve().parents[2]
    for prefix in prefixes:
        for path in Path(prefix, 'share').glob('*/msg/*.msg'):
            found.setdefault(f'{path.parent.parent.name}/msg/{path.stem}', path)
    # The source tree's CloudInfo, for tools run from a checkout without an installed interface package.
    found.setdefault(CLOUD_INFO_MSG_TYPE, source_tree / 'cloud_msgs' / 'msg' / 'CloudInfo.msg')
    return found


_PRIMITIVES = {
    'bool',
    'byte',
    'char',
    'float32',
    'float64',
    'int8',
    'uint8',
    'int16',
    'uint16',
    'int32',
    'uint32',
    'int64',
    'uint64',
    'string',
    'wstring',
    'time',
    'duration',
}


def _msg_dependencies(text: str, package: str) -> list[str]:
    """Message types referenced by the fields of a .msg text, as 'pkg/msg/Type'."""
    out = []
    for line in text.splitlines():
        parts = line.split('#', 1)[0].split()
        if len(parts) < 2:
            continue
        base = re.sub(r'(\[[^\]]*\]|<=\d+)$', '', parts[0])  # strip array and bound suffixes
        base = re.sub(r'<=\d+$', '', base)
        if base in _PRIMITIVES:
            continue
        if '/' in base:
            out.append(base.replace('/', '/msg/', 1))
        elif base == 'Header':
            out.append('std_msgs/msg/Header')
        else:
            out.append(f'{package}/msg/{base}')
    return out


def _register_installed(store: Typestore, msgtype: str, files: dict[str, Path]) -> bool:
    """Register ``msgtype`` and the types it references from installed .msg files; False if not found."""
    if msgtype in store.fielddefs:
        return True
    path = files.get(msgtype)
    if path is None or not path.is_file():
        return False
    text = path.read_text()
    for dependency in _msg_dependencies(text, msgtype.split('/')[0]):
        if not _register_installed(store, dependency, files):
            return False
    store.register(get_types_from_msg(text, msgtype))
    return True


@functools.lru_cache(maxsize=1)
def _base_store() -> Typestore:
    return get_typestore(Stores.ROS2_KILTED)


def ros2_typestore(extra_types: Iterable[str] = (CLOUD_INFO_MSG_TYPE,)) -> Typestore:
    """ROS 2 Kilted type store plus the installed types named in ``extra_types`` (a fresh store)."""
    store = get_typestore(Stores.ROS2_KILTED)
    files = _msg_files()
    for msgtype in extra_types:
        _register_installed(store, msgtype, files)
    return store


def ros1_typestore() -> Typestore:
    return get_typestore(Stores.ROS1_NOETIC)


def resolve_bag_path(path: str | Path) -> Path:
    """A ROS 1 ``.bag`` file or a ROS 2 bag directory; a ``.db3``/``.mcap`` file inside a bag directory
    stands for its directory."""
    path = Path(path).expanduser()
    if not path.exists():
        raise BagError(f'bag not found: {path}')
    if path.is_file() and path.suffix in ('.db3', '.mcap') and (path.parent / 'metadata.yaml').is_file():
        return path.parent
    if path.is_dir() and not (path / 'metadata.yaml').is_file():
        raise BagError(f'{path} is a directory without metadata.yaml: not a ROS 2 bag')
    if path.is_file() and path.suffix != '.bag':
        raise BagError(f'{path}: expected a ROS 1 .bag file or a ROS 2 bag directory (with metadata.yaml)')
    return path


@dataclass(frozen=True)
class BagMessage:
    """One message of a bag, as ROS 2 CDR bytes."""

    topic: str
    msgtype: str  # ROS 2 name, e.g. 'sensor_msgs/msg/PointCloud2'
    timestamp: int  # recording time [ns]
    data: bytes  # CDR, ready for rclpy's Publisher.publish(bytes)


class BagReader:
    """Reads a ROS 1 or ROS 2 bag; :meth:`messages` yields ROS 2 CDR for both. Use as a context manager."""

    def __init__(self, path: str | Path):
        self.path = resolve_bag_path(path)
        try:
            self._reader = AnyReader([self.path], default_typestore=_base_store())
        except Exception as exc:  # rosbags raises several error types for unreadable bags
            raise BagError(f'cannot open bag {self.path}: {exc}') from exc
        self._open = False
        self._converters: dict[str, Callable[[bytes | memoryview], bytes]] = {}
        self._dst_store: Typestore | None = None

    def __enter__(self) -> BagReader:
        self.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def open(self) -> None:
        if not self._open:
            try:
                self._reader.open()
            except Exception as exc:
                raise BagError(f'cannot read bag {self.path}: {exc}') from exc
            self._open = True

    def close(self) -> None:
        if self._open:
            self._reader.close()
            self._open = False

    @property
    def is_ros1(self) -> bool:
        return not self._reader.is2

    @property
    def start_time(self) -> int:
        return self._reader.start_time

    @property
    def end_time(self) -> int:
        return self._reader.end_time

    @property
    def duration(self) -> float:
        """[s] from the first to the last message."""
        return max(0, self._reader.end_time - self._reader.start_time) / 1e9

    @property
    def message_count(self) -> int:
        return self._reader.message_count

    def topics(self) -> dict[str, str]:
        """topic -> ROS 2 message type."""
        return {c.topic: _ROS1_RENAMES.get(c.msgtype, c.msgtype) for c in self._reader.connections}

    def topic_counts(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for c in self._reader.connections:
            counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        return counts

    def _converter(self, connection: Connection) -> Callable[[bytes | memoryview], bytes]:
        if not self.is_ros1:
            return bytes
        key = connection.msgtype
        if key not in self._converters:
            from rosbags.convert.converter import generate_message_converter

            if self._dst_store is None:
                self._dst_store = get_typestore(Stores.ROS2_KILTED)
            dst_type = _ROS1_RENAMES.get(key, key)
            if dst_type not in self._dst_store.fielddefs:
                # A type unknown to ROS 2 Kilted: keep its ROS 1 layout minus Header.seq.
                typs = get_types_from_msg(self._reader.typestore.generate_msgdef(key, ros_version=2)[0], dst_type)
                typs.pop('std_msgs/msg/Header', None)
                self._dst_store.register(typs)
            convert = generate_message_converter(
                self._reader.typestore, self._dst_store, key, dst_type, {}, src_is2=False, dst_is2=True
            )
            self._converters[key] = lambda raw: bytes(convert(raw))
        return self._converters[key]

    def messages(
        self, topics: Iterable[str] | None = None, start: int | None = None, stop: int | None = None
    ) -> Iterator[BagMessage]:
        """Messages in recording-time order, as ROS 2 CDR. ``start``/``stop`` are absolute [ns]."""
        self.open()
        wanted = set(topics) if topics else None
        connections = [c for c in self._reader.connections if wanted is None or c.topic in wanted]
        if not connections:
            return
        for connection, timestamp, raw in self._reader.messages(connections=connections, start=start, stop=stop):
            yield BagMessage(
                connection.topic,
                _ROS1_RENAMES.get(connection.msgtype, connection.msgtype),
                int(timestamp),
                self._converter(connection)(raw),
            )

    def deserialize(self, message: BagMessage) -> Any:
        """A rosbags message object (ROS 2 types) for a :class:`BagMessage`."""
        store = self._dst_store if self.is_ros1 and self._dst_store is not None else self._reader.typestore
        if message.msgtype not in store.fielddefs:
            store = ros2_typestore([message.msgtype])
        return store.deserialize_cdr(message.data, message.msgtype)


class BagWriter:
    """Writes a ROS 2 bag (``storage`` 'mcap' or 'sqlite3') or, with ``ros1=True``, a ROS 1 bag.

    ``compress`` stores mcap chunks zstd-compressed (readable by rosbag2 and rosbags alike).
    Use as a context manager; the bag is complete once :meth:`close` ran. Message objects for
    :meth:`write_msg` come from :attr:`typestore` (``writer.types['sensor_msgs/msg/Imu']``).
    """

    def __init__(
        self,
        path: str | Path,
        storage: str = 'mcap',
        ros1: bool = False,
        extra_types: Iterable[str] = (CLOUD_INFO_MSG_TYPE,),
        compress: bool = False,
    ):
        self.path = Path(path)
        self.ros1 = ros1
        if self.path.exists():
            raise BagError(f'{self.path} exists already; bags are never overwritten')
        if ros1:
            self.typestore = ros1_typestore()
            self._writer: Any = Writer1(self.path)
        else:
            plugins = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3, 'db3': StoragePlugin.SQLITE3}
            if storage not in plugins:
                raise BagError(f"unknown storage '{storage}' (use mcap or sqlite3)")
            self.typestore = ros2_typestore(extra_types)
            self._writer = Writer2(self.path, version=8, storage_plugin=plugins[storage])
            if compress:  # zstd chunks inside the mcap / sqlite3 file, as rosbag2's storage compression
                self._writer.set_compression(
                    CompressionMode.STORAGE if storage == 'mcap' else CompressionMode.FILE, CompressionFormat.ZSTD
                )
        self._connections: dict[str, Connection] = {}
        self._writer.open()

    @property
    def types(self) -> dict[str, type]:
        return self.typestore.types

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def add_topic(self, topic: str, msgtype: str, latching: bool = False) -> None:
        """Declare a topic (done implicitly by the first write)."""
        if topic in self._connections:
            return
        if msgtype not in self.typestore.fielddefs and not _register_installed(self.typestore, msgtype, _msg_files()):
            raise BagError(f"message type '{msgtype}' is not installed on this machine")
        if self.ros1:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self.typestore, latching=int(latching)
            )
        else:
            qos = _LATCHED_QOS if latching else []
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self.typestore, offered_qos_profiles=qos
            )

    def write_raw(
        self, topic: str, msgtype: str, timestamp: int, data: bytes | memoryview, latching: bool = False
    ) -> None:
        """Write serialized bytes (CDR for ROS 2 bags, ROS 1 serialization for ROS 1 bags)."""
        self.add_topic(topic, msgtype, latching)
        self._writer.write(self._connections[topic], int(timestamp), data)

    def write_msg(self, topic: str, timestamp: int, msg: Any) -> None:
        """Serialize and write a message object of :attr:`typestore`."""
        msgtype = msg.__msgtype__
        if self.ros1:
            data = self.typestore.serialize_ros1(msg, msgtype)
        else:
            data = self.typestore.serialize_cdr(msg, msgtype)
        self.write_raw(topic, msgtype, timestamp, data)

    def header(self, stamp_ns: int, frame_id: str, seq: int = 0) -> Any:
        """std_msgs/Header of this bag's flavour."""
        time = self.types['builtin_interfaces/msg/Time'](
            sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)
        )
        if self.ros1:
            return self.types['std_msgs/msg/Header'](seq=seq, stamp=time, frame_id=frame_id)
        return self.types['std_msgs/msg/Header'](stamp=time, frame_id=frame_id)

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None


def make_cloud_msg(types: dict[str, type], header: Any, points: np.ndarray) -> Any:
    """rosbags sensor_msgs/PointCloud2 carrying a structured array."""
    buf = array_to_cloud(points)
    field_type = types['sensor_msgs/msg/PointField']
    fields = [field_type(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in buf.fields]
    return types['sensor_msgs/msg/PointCloud2'](
        header=header,
        height=buf.height,
        width=buf.width,
        fields=fields,
        is_bigendian=buf.is_bigendian,
        point_step=buf.point_step,
        row_step=buf.row_step,
        data=np.asarray(buf.data, dtype=np.uint8),
        is_dense=buf.is_dense,
    )


def cloud_msg_to_array(msg: Any, flatten: bool = True) -> np.ndarray:
    """Structured array of a rosbags PointCloud2 object."""
    return cloud_to_array(CloudBuffer.of_message(msg), flatten=flatten)
