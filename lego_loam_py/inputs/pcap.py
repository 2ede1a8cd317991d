"""Velodyne VLP-16 and Ouster pcap captures as a source, decoded on the fly (no ``convert`` step).

The decoding is ``lego_loam_py convert``'s (:mod:`lego_loam_py.bag.convert` over :mod:`lego_loam_py.sensors`): the
same rotations, points (x y z intensity ring time) and stamps as a bag converted from the capture, and for an
Ouster capture its IMU packets as samples without orientation (as ``convert`` writes them). The capture is an
Ouster one when it has no Velodyne data packets and a metadata JSON is given or found beside it (a ``.json``
whose name starts the pcap's). Each scan reaches the pipeline with the IMU samples up to its last point.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from lego_loam_py.bag.convert import (
    VELODYNE_DATA_PORT,
    ConvertError,
    ConvertOptions,
    find_ouster_metadata,
    ouster_lidar_packets,
    ouster_scans,
    pcap_velodyne_chunks,
    velodyne_decoder,
)
from lego_loam_py.inputs.source import ImuSample, Scan, Source, SourceError, SourceItem
from lego_loam_py.sensors.ouster import IMU_PACKET_SIZE, OusterDecoder, OusterMetadata, decode_imu
from lego_loam_py.sensors.pcap import PcapError, read_udp
from lego_loam_py.sensors.velodyne import PACKET_SIZE, VelodyneFormatError

__all__ = ['PcapSource', 'is_pcap']

_PCAP_MAGICS = {b'\xd4\xc3\xb2\xa1', b'\xa1\xb2\xc3\xd4', b'\x4d\x3c\xb2\xa1', b'\xa1\xb2\x3c\x4d'}
_NO_ORIENTATION = (0.0, 0.0, 0.0, 1.0)  # (convert writes the same, with covariance[0] = -1)


def is_pcap(path: Path) -> bool:
    """A classic pcap file (by its magic number)."""
    if not path.is_file():
        return False
    with path.open('rb') as handle:
        return handle.read(4) in _PCAP_MAGICS


class PcapSource(Source):
    """A pcap capture; ``model`` 'VLP-16' decodes Velodyne packets as VLP-16 whatever model they claim (early
    firmware says HDL-32E), ``metadata`` is an Ouster capture's JSON (found beside the pcap when None)."""

    kind = 'pcap'

    def __init__(
        self, path: str | Path, model: str = 'auto', metadata: str | Path | None = None, port: int = VELODYNE_DATA_PORT
    ):
        self.path = Path(path)
        self.name = self.path.stem
        try:
            self._udp = read_udp(self.path)
        except (PcapError, OSError) as exc:
            raise SourceError(f'{self.path}: {exc}') from None
        self._options = ConvertOptions(format='pcap', model=model, port=port)
        self._velodyne = self._udp.select((self._udp.dst_ports == port) & (self._udp.lengths == PACKET_SIZE))
        self.metadata = Path(metadata) if metadata is not None else None
        if self.metadata is None and len(self._velodyne) == 0:
            self.metadata = find_ouster_metadata(self.path)
        if self.metadata is None and len(self._velodyne) == 0:
            raise SourceError(
                f'{self.path}: no Velodyne data packets ({PACKET_SIZE} B to port {port}) and no Ouster '
                'metadata JSON beside it; for an Ouster capture give --metadata'
            )
        self._meta = None
        if self.metadata is not None:
            try:
                self._meta = OusterMetadata.from_json(self.metadata)
            except (OSError, ValueError) as exc:
                raise SourceError(f'cannot read Ouster metadata {self.metadata}: {exc}') from None
        stamps = self._udp.stamps_ns
        self._span_s = float(stamps[-1] - stamps[0]) * 1e-9 if len(stamps) else 0.0

    @property
    def duration_s(self) -> float:
        """[s] from the capture's first to its last packet."""
        return self._span_s

    def describe(self) -> str:
        if self._meta is not None:
            return (
                f'Ouster pcap {self.path} ({self._meta.prod_line} {self._meta.columns_per_frame}x'
                f'{self._meta.pixels_per_column}, metadata {self.metadata})'
            )
        return f'Velodyne pcap {self.path} ({len(self._velodyne)} data packets, decoded as VLP-16)'

    def items(self) -> Iterator[SourceItem]:
        try:
            if self._meta is not None:
                yield from self._ouster_items()
            else:
                yield from self._velodyne_items()
        except (ConvertError, VelodyneFormatError) as exc:  # (the message names run's --model where it helps)
            raise SourceError(f'{self.path}: {exc}') from None

    def _velodyne_items(self) -> Iterator[SourceItem]:
        decoder = velodyne_decoder(self._options)
        for packets, stamps in pcap_velodyne_chunks(self._velodyne):
            for rotation in decoder.feed(packets, stamps):
                yield _scan(rotation.stamp_ns, rotation.points)
        for rotation in decoder.finish():
            yield _scan(rotation.stamp_ns, rotation.points)

    def _ouster_items(self) -> Iterator[SourceItem]:
        meta = self._meta
        decoder = OusterDecoder(meta, min_completeness=self._options.min_completeness)
        scans = (
            _scan(scan.stamp_ns, scan.points)
            for scan in ouster_scans(ouster_lidar_packets(self._udp, meta), decoder, meta)
        )
        first = next(scans, None)  # (the decoder knows the sensor's clock once it decoded a scan)
        if first is None:
            return
        imu = self._udp.select((self._udp.dst_ports == meta.udp_port_imu) & (self._udp.lengths == IMU_PACKET_SIZE))
        samples: Iterator[SourceItem] = iter(())
        if len(imu) and meta.udp_profile_imu == 'LEGACY' and decoder.clock_offset_ns is not None:
            decoded = decode_imu(imu.gather(IMU_PACKET_SIZE), decoder.clock_offset_ns)
            samples = (
                ImuSample((int(t) * 1e-9, _NO_ORIENTATION, tuple(w), tuple(a)), int(t))
                for t, w, a in zip(
                    decoded.stamps_ns, decoded.angular_velocity.tolist(), decoded.linear_acceleration.tolist()
                )
            )
        merged = heapq.merge(_chain(first, scans), samples, key=lambda item: item.received_ns)
        yield from merged


def _chain(first: SourceItem, rest: Iterator[SourceItem]) -> Iterator[SourceItem]:
    yield first
    yield from rest


def _scan(stamp_ns: int, points: np.ndarray) -> Scan:
    """A decoded rotation, received once its last point was measured."""
    last = float(points['time'].max()) if len(points) else 0.0
    return Scan(int(stamp_ns), points, int(stamp_ns) + int(round(last * 1e9)))
