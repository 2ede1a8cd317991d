"""``lego_loam_py convert``: real lidar recordings -> bags of PointCloud2 sweeps with ring and per-point time.

Inputs (auto-detected, or ``--format``):

* a Velodyne VLP-16 **pcap** (single or dual return): UDP data packets (1206 bytes, port 2368 unless
  ``--port``) decoded by :mod:`lego_loam_py.sensors.velodyne`; position packets (port 8308) are ignored;
* an **Ouster** pcap with its metadata JSON (``--metadata``; found automatically when a ``.json`` beside
  the pcap has a name the pcap's starts with): lidar packets decoded by :mod:`lego_loam_py.sensors.ouster`,
  IMU packets written as ``sensor_msgs/Imu`` (``--imu-topic``) plus a latched ``/tf_static``
  ``os_sensor -> os_imu``;
* a **ROS 1 or ROS 2 bag** of raw Velodyne packets (``velodyne_msgs/msg/VelodyneScan``; the type need not
  be installed: its definition is registered here). The packets of all messages are re-cut into rotations
  by the same decoder, anchored to the first ``VelodynePacket.stamp``;
* a **folder of scans** or a **KITTI sequence** (``--format scans|kitti``; a folder that is not a bag is taken
  for one), read as ``lego_loam_py run`` reads it (:mod:`lego_loam_py.inputs`): every scan as its file has it
  (its fields kept), stamped from ``times.txt``, and the folder's ground truth written beside the bag as
  ``ground_truth.tum``, so that a replay over DDS can be scored as the offline run is.

Output: a ROS 2 bag (mcap, or sqlite3) or a ROS 1 bag (``--ros1``) with one ``sensor_msgs/PointCloud2`` per
rotation on ``--topic`` (header stamp = time of the rotation's first firing; bag time = header stamp), in the
driver's point layout (``--layout driver``: x, y, z, intensity, ring, time at offsets 0/4/8/16/20/24,
32 B) or the ROS 1 driver's packed one (``--layout packed``, 22 B).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.typesys import get_types_from_msg

from lego_loam_py.bag.io import BagError, BagReader, BagWriter, make_cloud_msg, ros2_typestore
from lego_loam_py.core.frames import matrix_to_quaternion
from lego_loam_py.core.pointcloud import VELODYNE_PACKED_DTYPE, VELODYNE_POINT_DTYPE
from lego_loam_py.errors import LegoLoamError, UsageError
from lego_loam_py.sensors.ouster import IMU_PACKET_SIZE, OusterDecoder, OusterFormatError, OusterMetadata, decode_imu
from lego_loam_py.sensors.pcap import PcapError, UdpDatagrams, read_udp
from lego_loam_py.sensors.velodyne import PACKET_SIZE, VelodyneFormatError, Vlp16Decoder

__all__ = [
    'add_arguments',
    'main',
    'convert',
    'ConvertOptions',
    'ConvertSummary',
    'VELODYNE_SCAN_TYPES',
    'velodyne_scan_typestore',
    'velodyne_bag_packets',
    'detect_format',
    'ConvertError',
    'velodyne_decoder',
    'pcap_velodyne_chunks',
    'find_ouster_metadata',
    'ouster_lidar_packets',
    'ouster_scans',
]

VELODYNE_DATA_PORT = 2368
VELODYNE_SCAN = 'velodyne_msgs/msg/VelodyneScan'
# velodyne_msgs (ROS 2) definitions: bags of raw packets need them, and the package is rarely installed.
VELODYNE_SCAN_TYPES = {
    VELODYNE_SCAN: 'std_msgs/Header header\nVelodynePacket[] packets\n',
    'velodyne_msgs/msg/VelodynePacket': 'builtin_interfaces/Time stamp\nuint8[1206] data\n',
}
_FEED_PACKETS = 4096  # Velodyne packets decoded per vectorised step (bounds memory)
_OUSTER_BATCH_PACKETS = 1024  # Ouster packets (whole scans) decoded per step
_PCAP_MAGICS = {b'\xd4\xc3\xb2\xa1', b'\xa1\xb2\xc3\xd4', b'\x4d\x3c\xb2\xa1', b'\xa1\xb2\x3c\x4d', b'\x0a\x0d\x0d\x0a'}


class ConvertError(LegoLoamError, RuntimeError):
    """The input cannot be converted (a message for the user, no traceback)."""


@dataclass
class ConvertOptions:
    format: str = 'auto'  # auto, pcap, rosbag
    model: str = 'auto'  # auto (packets must claim VLP-16) or VLP-16 (forced)
    split: str = 'wrap'
    min_completeness: float = 0.95
    restamp_period: float | None = None  # [s]
    topic: str = '/velodyne_points'
    frame_id: str | None = None  # default: velodyne, or os_sensor for Ouster
    layout: str = 'driver'
    ros1: bool = False
    storage: str = 'mcap'
    compress: bool = False
    max_rotations: int | None = None
    metadata: Path | None = None
    port: int = VELODYNE_DATA_PORT
    input_topic: str | None = None
    imu_topic: str = '/imu/data'
    imu: bool = True


@dataclass
class ConvertSummary:
    sensor: str = ''
    source: str = ''
    packets: int = 0
    rotations: int = 0
    points: list[int] = field(default_factory=list)
    stamps_ns: list[int] = field(default_factory=list)
    imu_messages: int = 0
    dropped_incomplete: int = 0
    bad_packets: int = 0
    wall_time: float = 0.0
    notes: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        out = [f'{self.source}: {self.sensor}, {self.packets} packets -> {self.rotations} rotations']
        if self.points:
            counts = np.array(self.points)
            span = (self.stamps_ns[-1] - self.stamps_ns[0]) / 1e9
            out.append(
                f'  points per rotation min/median/max {counts.min()}/{int(np.median(counts))}/{counts.max()}'
                f', {counts.sum()} in all'
            )
            out.append(
                f'  stamps {self.stamps_ns[0] / 1e9:.6f} .. {self.stamps_ns[-1] / 1e9:.6f} s '
                f'({span:.3f} s from first to last)'
            )
        if self.imu_messages:
            out.append(f'  {self.imu_messages} IMU messages')
        if self.dropped_incomplete:
            out.append(f'  {self.dropped_incomplete} incomplete rotation(s) dropped (capture start/end, lost packets)')
        if self.bad_packets:
            out.append(f'  {self.bad_packets} malformed packet(s) skipped')
        rate = self.packets / self.wall_time if self.wall_time > 0 else 0.0
        out.append(
            f'  {self.wall_time:.2f} s ({rate:.0f} packets/s, '
            f'{self.rotations / self.wall_time if self.wall_time > 0 else 0:.1f} rotations/s)'
        )
        return out + [f'  note: {n}' for n in self.notes]


def velodyne_scan_typestore():
    """ROS 2 Kilted type store with velodyne_msgs/VelodyneScan and VelodynePacket registered."""
    store = ros2_typestore()
    types = {}
    for name, text in VELODYNE_SCAN_TYPES.items():
        if name not in store.fielddefs:
            types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def detect_format(path: Path) -> str:
    """'pcap', 'rosbag' or 'scans' from the path (bag directory / .bag / .db3 / .mcap, another folder) or the
    file's magic."""
    if (
        path.is_dir()
        and not (path / 'metadata.yaml').is_file()
        and not any(path.glob('*.db3'))
        and not any(path.glob('*.mcap'))
    ):
        return 'scans'
    if path.is_dir() or path.suffix in ('.bag', '.db3', '.mcap'):
        return 'rosbag'
    if path.is_file():
        with path.open('rb') as handle:
            if handle.read(4) in _PCAP_MAGICS:
                return 'pcap'
    raise ConvertError(f'{path}: neither a pcap file nor a bag (give --format pcap|rosbag)')


def _layout(name: str) -> np.dtype:
    return VELODYNE_PACKED_DTYPE if name == 'packed' else VELODYNE_POINT_DTYPE


def find_ouster_metadata(pcap: Path) -> Path | None:
    """A .json beside the pcap whose stem starts the pcap's name (longest match), as Ouster tools name them."""
    candidates = [p for p in pcap.parent.glob('*.json') if pcap.stem.startswith(p.stem)]
    return max(candidates, key=lambda p: len(p.stem)) if candidates else None


class _Output:
    """The output bag and the summary; writes clouds and IMU messages in the requested flavour."""

    def __init__(self, path: Path, options: ConvertOptions, summary: ConvertSummary):
        self.options = options
        self.summary = summary
        self.bag = BagWriter(path, storage=options.storage, ros1=options.ros1, compress=options.compress)
        self.types = self.bag.types

    def cloud(self, stamp_ns: int, frame_id: str, points: np.ndarray) -> None:
        header = self.bag.header(stamp_ns, frame_id, seq=self.summary.rotations)
        self.bag.write_msg(self.options.topic, stamp_ns, make_cloud_msg(self.types, header, points))
        self.summary.rotations += 1
        self.summary.points.append(int(points.size))
        self.summary.stamps_ns.append(int(stamp_ns))

    def done(self) -> bool:
        limit = self.options.max_rotations
        return limit is not None and self.summary.rotations >= limit

    def static_transform(self, stamp_ns: int, parent: str, child: str, matrix_mm: np.ndarray) -> None:
        T = self.types
        q = matrix_to_quaternion(matrix_mm[:3, :3])
        t = matrix_mm[:3, 3] / 1000.0
        transform = T['geometry_msgs/msg/TransformStamped'](
            header=self.bag.header(stamp_ns, parent),
            child_frame_id=child,
            transform=T['geometry_msgs/msg/Transform'](
                translation=T['geometry_msgs/msg/Vector3'](x=float(t[0]), y=float(t[1]), z=float(t[2])),
                rotation=T['geometry_msgs/msg/Quaternion'](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
            ),
        )
        if 'tf2_msgs/msg/TFMessage' not in self.bag.typestore.fielddefs:  # the ROS 1 store lacks it
            self.bag.typestore.register(
                get_types_from_msg('geometry_msgs/TransformStamped[] transforms', 'tf2_msgs/msg/TFMessage')
            )
        msg = self.types['tf2_msgs/msg/TFMessage'](transforms=[transform])
        self.bag.add_topic('/tf_static', msg.__msgtype__, latching=True)
        self.bag.write_msg('/tf_static', stamp_ns, msg)

    def imu(self, stamp_ns: int, frame_id: str, acceleration: np.ndarray, angular_velocity: np.ndarray) -> None:
        T = self.types
        covariance = np.zeros(9)
        unknown = np.zeros(9)
        unknown[0] = -1.0  # REP-145: no orientation estimate
        msg = T['sensor_msgs/msg/Imu'](
            header=self.bag.header(stamp_ns, frame_id, seq=self.summary.imu_messages),
            orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=unknown,
            angular_velocity=T['geometry_msgs/msg/Vector3'](
                x=float(angular_velocity[0]), y=float(angular_velocity[1]), z=float(angular_velocity[2])
            ),
            angular_velocity_covariance=covariance,
            linear_acceleration=T['geometry_msgs/msg/Vector3'](
                x=float(acceleration[0]), y=float(acceleration[1]), z=float(acceleration[2])
            ),
            linear_acceleration_covariance=covariance,
        )
        self.bag.write_msg(self.options.imu_topic, stamp_ns, msg)
        self.summary.imu_messages += 1

    def close(self) -> None:
        self.bag.close()


# ---------------------------------------------------------------------------------------------- Velodyne
def velodyne_decoder(options: ConvertOptions) -> Vlp16Decoder:
    """The VLP-16 decoder the options ask for (model, split, completeness, restamping, point layout)."""
    period = None if options.restamp_period is None else int(round(options.restamp_period * 1e9))
    return Vlp16Decoder(
        force_model=options.model.upper() == 'VLP-16',
        split=options.split,
        min_completeness=options.min_completeness,
        restamp_period_ns=period,
        point_dtype=_layout(options.layout),
    )


def _run_velodyne(chunks: Iterator[tuple[np.ndarray, np.ndarray]], output: _Output, options: ConvertOptions) -> None:
    decoder = velodyne_decoder(options)
    frame_id = options.frame_id or 'velodyne'
    summary = output.summary
    try:
        for packets, stamps in chunks:
            summary.packets += len(packets)
            for rotation in decoder.feed(packets, stamps):
                output.cloud(rotation.stamp_ns, frame_id, rotation.points)
                if output.done():
                    break
            if output.done():
                break
        else:
            for rotation in decoder.finish():
                if not output.done():
                    output.cloud(rotation.stamp_ns, frame_id, rotation.points)
    except VelodyneFormatError as exc:
        raise ConvertError(str(exc)) from exc
    stats = decoder.stats
    summary.dropped_incomplete += stats.incomplete_rotations
    summary.bad_packets += stats.bad_packets
    mode = {0x37: 'strongest return', 0x38: 'last return', 0x39: 'dual return'}.get(stats.return_mode, '?')
    summary.sensor = f'VLP-16 ({mode}{", model forced" if decoder.force_model else ""})'


def pcap_velodyne_chunks(udp: UdpDatagrams) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    for start in range(0, len(udp), _FEED_PACKETS):
        index = np.arange(start, min(start + _FEED_PACKETS, len(udp)))
        yield udp.gather(PACKET_SIZE, index), udp.stamps_ns[index]


def velodyne_bag_packets(
    reader: BagReader, topic: str, chunk: int = _FEED_PACKETS
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Raw packets of the VelodyneScan messages on ``topic``, in order, as ((n, 1206) uint8 data,
    (n,) VelodynePacket.stamp [ns]) chunks of about ``chunk`` packets."""
    store = velodyne_scan_typestore()
    packets: list[np.ndarray] = []
    stamps: list[int] = []
    for message in reader.messages(topics=[topic]):
        scan = store.deserialize_cdr(message.data, VELODYNE_SCAN)
        for packet in scan.packets:
            packets.append(packet.data)
            stamps.append(packet.stamp.sec * 1_000_000_000 + packet.stamp.nanosec)
        if len(packets) >= chunk:
            yield np.stack(packets).astype(np.uint8, copy=False), np.array(stamps, dtype=np.int64)
            packets, stamps = [], []
    if packets:
        yield np.stack(packets).astype(np.uint8, copy=False), np.array(stamps, dtype=np.int64)


# ---------------------------------------------------------------------------------------------- Ouster
def _run_ouster(udp: UdpDatagrams, metadata_path: Path, output: _Output, options: ConvertOptions) -> None:
    summary = output.summary
    try:
        meta = OusterMetadata.from_json(metadata_path)
    except (OSError, ValueError) as exc:
        raise ConvertError(f'cannot read Ouster metadata {metadata_path}: {exc}') from exc
    lidar = ouster_lidar_packets(udp, meta)
    decoder = OusterDecoder(meta, min_completeness=options.min_completeness, point_dtype=_layout(options.layout))
    frame_id = options.frame_id or 'os_sensor'
    summary.sensor = (
        f'Ouster {meta.prod_line} {meta.columns_per_frame}x{meta.pixels_per_column} {meta.udp_profile_lidar}'
    )
    summary.packets += len(lidar)
    period = None if options.restamp_period is None else int(round(options.restamp_period * 1e9))
    first_stamp = None
    for scan in ouster_scans(lidar, decoder, meta):
        if output.done():
            break
        first_stamp = scan.stamp_ns if first_stamp is None else first_stamp
        stamp = scan.stamp_ns if period is None else first_stamp + summary.rotations * period
        output.cloud(stamp, frame_id, scan.points)
    summary.dropped_incomplete += decoder.stats.incomplete_scans
    summary.bad_packets += decoder.stats.bad_packets
    imu = udp.select((udp.dst_ports == meta.udp_port_imu) & (udp.lengths == IMU_PACKET_SIZE))
    if options.imu and len(imu) and summary.rotations and decoder.clock_offset_ns is not None:
        if meta.udp_profile_imu != 'LEGACY':
            summary.notes.append(f'IMU profile {meta.udp_profile_imu} is not supported: no IMU messages written')
            return
        samples = decode_imu(imu.gather(IMU_PACKET_SIZE), decoder.clock_offset_ns)
        if options.max_rotations is not None:  # IMU up to the end of the last converted scan
            keep = samples.stamps_ns <= summary.stamps_ns[-1] + int(0.1e9)
        else:
            keep = np.ones(len(samples.stamps_ns), dtype=bool)
        output.static_transform(int(summary.stamps_ns[0]), frame_id, 'os_imu', meta.imu_to_sensor_transform)
        for stamp, acceleration, gyro in zip(
            samples.stamps_ns[keep], samples.linear_acceleration[keep], samples.angular_velocity[keep]
        ):
            output.imu(int(stamp), 'os_imu', acceleration, gyro)


def ouster_lidar_packets(udp: UdpDatagrams, meta: OusterMetadata) -> UdpDatagrams:
    """The capture's Ouster lidar packets (the metadata's port and packet size); ConvertError without any."""
    lidar = udp.select((udp.dst_ports == meta.udp_port_lidar) & (udp.lengths == meta.lidar_packet_size))
    if len(lidar) == 0:
        raise ConvertError(
            f'no Ouster lidar packets ({meta.lidar_packet_size} bytes for {meta.udp_profile_lidar}, '
            f'port {meta.udp_port_lidar}) in the capture: does the metadata belong to it?'
        )
    return lidar


def ouster_scans(lidar: UdpDatagrams, decoder: OusterDecoder, meta: OusterMetadata) -> Iterator:
    """The decoder's scans of the lidar packets, in order, decoded in batches of whole frames (bounded memory)."""
    frames = decoder.frame_ids(lidar.gather(OusterDecoder.HEAD_BYTES))
    starts = np.concatenate([[0], np.flatnonzero(np.diff(frames)) + 1])
    batch_start = 0
    try:
        for k in range(1, len(starts) + 1):
            end = int(starts[k]) if k < len(starts) else len(lidar)
            if end - batch_start < _OUSTER_BATCH_PACKETS and k < len(starts):
                continue
            index = np.arange(batch_start, end)
            yield from decoder.decode(lidar.gather(meta.lidar_packet_size, index), lidar.stamps_ns[index])
            batch_start = end
    except OusterFormatError as exc:
        raise ConvertError(str(exc)) from exc


# ---------------------------------------------------------------------------------------------- driver
def _describe_udp(udp: UdpDatagrams) -> str:
    if not len(udp):
        return 'no UDP datagrams'
    pairs, counts = np.unique(np.stack([udp.dst_ports.astype(np.int64), udp.lengths]), axis=1, return_counts=True)
    return ', '.join(f'{n} x {size} B to port {port}' for (port, size), n in zip(pairs.T.tolist(), counts.tolist()))


def convert(source: Path, destination: Path, options: ConvertOptions) -> ConvertSummary:
    """Convert ``source`` into the bag ``destination`` (which must not exist); see the module docstring."""
    source, destination = Path(source), Path(destination)
    if not source.exists():
        raise ConvertError(f'{source}: no such file or directory')
    kind = detect_format(source) if options.format == 'auto' else options.format
    if kind in ('rosbag1', 'rosbag2'):
        kind = 'rosbag'
    if options.split not in ('wrap', 'start'):
        raise ConvertError("--split must be 'wrap' or 'start'")
    if destination.exists():
        raise ConvertError(f'{destination} exists already; bags are never overwritten')
    summary = ConvertSummary(source=str(source))
    started = time.perf_counter()
    try:
        _convert(source, destination, kind, options, summary)
    except BaseException:
        _remove_partial(destination)
        raise
    summary.wall_time = time.perf_counter() - started
    return summary


def _remove_partial(path: Path) -> None:
    """Remove the output of a failed conversion (created by this run: it did not exist before)."""
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists():
        path.unlink()


def _convert(source: Path, destination: Path, kind: str, options: ConvertOptions, summary: ConvertSummary) -> None:
    if kind == 'pcap':
        try:
            udp = read_udp(source)
        except (PcapError, OSError) as exc:
            raise ConvertError(str(exc)) from exc
        velodyne = udp.select((udp.dst_ports == options.port) & (udp.lengths == PACKET_SIZE))
        metadata = options.metadata
        if metadata is None and len(velodyne) == 0:
            metadata = find_ouster_metadata(source)
            if metadata is not None:
                summary.notes.append(f'Ouster metadata: {metadata}')
        if metadata is None and len(velodyne) == 0:
            raise ConvertError(
                f'{source}: no Velodyne data packets ({PACKET_SIZE} B to port {options.port}); '
                f'the capture holds {_describe_udp(udp)}. For an Ouster capture give --metadata.'
            )
        output = _Output(destination, options, summary)
        try:
            if metadata is not None:
                _run_ouster(udp, Path(metadata), output, options)
            else:
                _run_velodyne(pcap_velodyne_chunks(velodyne), output, options)
        finally:
            output.close()
    elif kind == 'rosbag':
        try:
            reader = BagReader(source)
            reader.open()
        except BagError as exc:
            raise ConvertError(str(exc)) from exc
        try:
            topics = [t for t, m in reader.topics().items() if m == VELODYNE_SCAN]
            if options.input_topic is not None:
                if options.input_topic not in topics:
                    raise ConvertError(
                        f'{source}: topic {options.input_topic} with {VELODYNE_SCAN} not found '
                        f'(bag topics: {reader.topics()})'
                    )
                topics = [options.input_topic]
            if len(topics) != 1:
                raise ConvertError(
                    f'{source}: expected one {VELODYNE_SCAN} topic, found {topics or "none"} '
                    f'(bag topics: {reader.topics()}); choose one with --input-topic'
                )
            output = _Output(destination, options, summary)
            try:
                _run_velodyne(velodyne_bag_packets(reader, topics[0]), output, options)
            finally:
                output.close()
        finally:
            reader.close()
    elif kind in ('scans', 'kitti'):
        _run_scan_folder(source, kind, destination, options, summary)
    else:
        raise ConvertError(f"unknown format '{kind}' (pcap, rosbag, scans or kitti)")


def _run_scan_folder(
    source: Path, kind: str, destination: Path, options: ConvertOptions, summary: ConvertSummary
) -> None:
    """A folder of scans (or a KITTI sequence) -> clouds as its files hold them, and its ground truth beside."""
    from lego_loam_py.formats import write_tum_atomic
    from lego_loam_py.inputs import Scan, SourceError, open_source
    from lego_loam_py.inputs.sidecars import GROUND_TRUTH, sidecar_path

    try:
        recording = open_source(source, kind)
    except SourceError as exc:
        raise ConvertError(str(exc)) from exc
    summary.sensor = f'{kind} folder'
    output = _Output(destination, options, summary)
    try:
        with recording:
            for item in recording.items():
                if isinstance(item, Scan):
                    output.cloud(item.stamp_ns, options.frame_id or 'velodyne', item.points)
                    if output.done():
                        break
            truth = recording.ground_truth()
    finally:
        output.close()
    if truth is not None:
        write_tum_atomic(sidecar_path(destination, GROUND_TRUTH), *truth)
        summary.notes.append(f'ground truth ({len(truth)} poses) beside the bag')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        'input',
        type=Path,
        help='pcap file (Velodyne VLP-16 or Ouster), a ROS 1/ROS 2 bag of '
        'velodyne_msgs/VelodyneScan raw packets, or a folder of scans / '
        'KITTI sequence',
    )
    parser.add_argument(
        '-o',
        '--output',
        type=Path,
        required=True,
        metavar='OUT_BAG',
        help='output bag: a ROS 2 bag directory, or a ROS 1 .bag file with --ros1 (must not exist)',
    )
    parser.add_argument(
        '--format',
        choices=['auto', 'pcap', 'rosbag', 'rosbag1', 'rosbag2', 'scans', 'kitti'],
        default='auto',
        help='input kind (default: auto-detected from the path and file magic)',
    )
    parser.add_argument(
        '--model',
        choices=['auto', 'VLP-16'],
        default='auto',
        help="Velodyne model: auto = trust the packets' product id (must say VLP-16); VLP-16 = decode "
        'as VLP-16 whatever the packets claim (early VLP-16 firmware reports HDL-32E)',
    )
    parser.add_argument(
        '--split',
        choices=['wrap', 'start'],
        default='wrap',
        help="cut rotations at azimuth 0 (wrap, as the driver) or at the first firing's azimuth "
        '(start: a capture of one sweep)',
    )
    parser.add_argument(
        '--min-completeness',
        type=float,
        default=0.95,
        metavar='F',
        help='drop rotations covering less than this fraction of 360 deg, gaps from lost packets '
        'excluded (default 0.95): the fragments at the start and end of a capture',
    )
    parser.add_argument(
        '--restamp-period',
        type=float,
        default=None,
        metavar='S',
        help='header stamp k = stamp 0 + k*S (e.g. 0.1 to feed a 20 Hz recording to LeGO-LOAM, '
        'which assumes 10 Hz); the per-point time field is not rescaled',
    )
    parser.add_argument('--topic', default='/velodyne_points', help='output cloud topic (default /velodyne_points)')
    parser.add_argument('--frame-id', default=None, help='cloud frame id (default velodyne; os_sensor for Ouster)')
    parser.add_argument(
        '--layout',
        choices=['driver', 'packed'],
        default='driver',
        help='point layout: driver = x,y,z,intensity,ring,time at 0/4/8/16/20/24, 32 B (ROS 2 '
        'velodyne driver); packed = 0/4/8/12/16/18, 22 B (ROS 1 driver)',
    )
    parser.add_argument('--ros1', action='store_true', help='write a ROS 1 .bag instead of a ROS 2 bag')
    parser.add_argument('--storage', choices=['mcap', 'sqlite3'], default='mcap', help='ROS 2 storage (default mcap)')
    parser.add_argument('--compress', action='store_true', help='zstd-compress the ROS 2 bag')
    parser.add_argument('--max-rotations', type=int, default=None, metavar='N', help='stop after N rotations')
    parser.add_argument(
        '--metadata',
        type=Path,
        default=None,
        metavar='JSON',
        help='Ouster sensor metadata (.json); selects the Ouster decoder',
    )
    parser.add_argument(
        '--port', type=int, default=VELODYNE_DATA_PORT, help=f'Velodyne data UDP port (default {VELODYNE_DATA_PORT})'
    )
    parser.add_argument(
        '--input-topic', default=None, help='VelodyneScan topic of an input bag (default: the only one)'
    )
    parser.add_argument('--imu-topic', default='/imu/data', help='IMU topic for Ouster captures (default /imu/data)')
    parser.add_argument('--no-imu', action='store_true', help='do not convert Ouster IMU packets')
    parser.add_argument('-q', '--quiet', action='store_true', help='no summary')


def main(args: argparse.Namespace) -> int:
    if args.max_rotations is not None and args.max_rotations < 1:
        raise UsageError('--max-rotations must be at least 1')
    if args.restamp_period is not None and args.restamp_period <= 0:
        raise UsageError('--restamp-period must be positive')
    if not 0.0 <= args.min_completeness <= 1.0:
        raise UsageError('--min-completeness must be within [0, 1]')
    options = ConvertOptions(
        format=args.format,
        model=args.model,
        split=args.split,
        min_completeness=args.min_completeness,
        restamp_period=args.restamp_period,
        topic=args.topic,
        frame_id=args.frame_id,
        layout=args.layout,
        ros1=args.ros1,
        storage=args.storage,
        compress=args.compress,
        max_rotations=args.max_rotations,
        metadata=args.metadata,
        port=args.port,
        input_topic=args.input_topic,
        imu_topic=args.imu_topic,
        imu=not args.no_imu,
    )
    output = args.output
    if args.ros1 and output.suffix != '.bag':
        output = output.with_suffix('.bag')
    if output.exists():
        raise ConvertError(f'{output} exists already; bags are never overwritten')
    summary = convert(args.input, output, options)
    if summary.rotations == 0:
        print(f'warning: no complete rotation in {args.input}; {output} holds no cloud', file=sys.stderr)
    if not args.quiet:
        print('\n'.join(summary.lines()))
        print(f'  -> {output}')
    return 0
