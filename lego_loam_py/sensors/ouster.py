"""Ouster OS0/OS1/OS2 lidar and IMU packet decoder (numpy only, no ROS).

Reads the UDP packets of an Ouster sensor (firmware 2.x/3.x) with the sensor's metadata JSON (as saved by
Ouster Studio, ``ouster-cli`` or ``ouster_ros``; both the flat v2 layout and the nested newer one) and turns
them into one point cloud per scan (``frame_id`` of the packet header) and IMU samples.

Lidar packet layout (Ouster software user manual, "Lidar Data Format"; little-endian). Non-legacy profiles:
a 32-byte packet header (packet type u16 = 1, frame id u16, init id u24, serial u40), ``columns_per_packet``
columns of [timestamp u64 ns, measurement id u16, status u16 (bit 0: valid)] + ``pixels_per_column`` pixel
records, and a 32-byte footer. The LEGACY profile has no packet header/footer; its column header is
[timestamp u64, measurement id u16, frame id u16, encoder count u32] and its column ends with a u32 status
(0xFFFFFFFF = valid). Pixel records by ``udp_profile_lidar``:

==============================  =====  ================================================================
profile                          bytes  fields used here
==============================  =====  ================================================================
LEGACY                            12    range u32 & 0xFFFFF [mm], reflectivity u16 @4, signal u16 @6
RNG19_RFL8_SIG16_NIR16            12    range u32 & 0x7FFFF [mm], reflectivity u8 @4, signal u16 @6
RNG19_RFL8_SIG16_NIR16_DUAL       16    first return: range u32 & 0x7FFFF [mm], reflectivity u8 @3,
                                        signal u16 @8 (the second return is not used)
RNG15_RFL8_NIR8 (low bandwidth)    4    range (u16 & 0x7FFF) * 8 [mm], reflectivity u8 @2
==============================  =====  ================================================================

Geometry (the SDK's ``make_xyz_lut``): pixel (beam b, measurement id m) of a W-column scan points along
encoder angle ``te = 2 pi (1 - m / W)`` plus the beam's azimuth offset ``ta = -beam_azimuth_angles[b]`` at
elevation ``phi = beam_altitude_angles[b]``; the beam origin sits ``n = lidar_origin_to_beam_origin_mm``
from the lidar axis::

    direction = (cos(te + ta) cos(phi), sin(te + ta) cos(phi), sin(phi))
    offset    = n (cos(te) - direction_x, sin(te) - direction_y, -direction_z)
    p_lidar   = range * direction + offset          [mm, lidar frame]
    p_sensor  = R p_lidar + t                        (lidar_to_sensor_transform; output in metres)

Points are in the ``os_sensor`` frame (x forward, y left, z up, origin at the base of the sensor).

Conventions of the output, chosen for LeGO-LOAM: ``ring`` 0 is the LOWEST beam (Ouster's beam 0 is the
top one, so ring = pixels_per_column - 1 - beam); ``intensity`` is the signal photon count where the
profile carries one, else the calibrated reflectivity (low-bandwidth profile); ``time`` [s] runs from the
scan's first column; zero ranges (no return) are dropped. Points are in column (time) order, each column
from the top beam down. Sensor timestamps (internal oscillator, PTP or GPS) are anchored to the capture
time of the first lidar packet, as for Velodyne streams: header stamp = time of the scan's first valid
column on the capture clock.

IMU packets (LEGACY IMU profile, 48 bytes): system, accelerometer and gyroscope timestamps (u64 ns), then
acceleration x, y, z (float32, g) and angular velocity x, y, z (float32, deg/s), in the ``os_imu`` frame;
:func:`decode_imu` converts them to m/s^2 and rad/s.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lego_loam_py.core.pointcloud import VELODYNE_POINT_DTYPE, velodyne_points
from lego_loam_py.errors import LegoLoamError

__all__ = [
    'OusterMetadata',
    'OusterFormatError',
    'OusterScan',
    'ImuSamples',
    'OusterDecoder',
    'decode_imu',
    'STANDARD_GRAVITY',
    'IMU_PACKET_SIZE',
]

STANDARD_GRAVITY = 9.80665  # [m/s^2 per g], as ouster_ros
IMU_PACKET_SIZE = 48


class OusterFormatError(LegoLoamError, ValueError):
    """Metadata or packets this decoder cannot read."""


@dataclass(frozen=True)
class _Profile:
    pixel_bytes: int
    range_offset: int
    range_bytes: int  # 2 or 4
    range_mask: int
    range_scale: int  # [mm per count]
    reflectivity_offset: int
    reflectivity_bytes: int
    signal_offset: int | None


_PROFILES = {
    'LEGACY': _Profile(12, 0, 4, 0xFFFFF, 1, 4, 2, 6),
    'RNG19_RFL8_SIG16_NIR16': _Profile(12, 0, 4, 0x7FFFF, 1, 4, 1, 6),
    'RNG19_RFL8_SIG16_NIR16_DUAL': _Profile(16, 0, 4, 0x7FFFF, 1, 3, 1, 8),
    'RNG15_RFL8_NIR8': _Profile(4, 0, 2, 0x7FFF, 8, 2, 1, None),
}


def _find(meta: dict, *paths: str, default: Any = KeyError) -> Any:
    """The first of several dotted key paths present in ``meta`` (flat v2 and nested newer layouts)."""
    for path in paths:
        node: Any = meta
        for key in path.split('.'):
            if not isinstance(node, dict) or key not in node:
                break
            node = node[key]
        else:
            return node
    if default is KeyError:
        raise OusterFormatError(f'metadata lacks {paths[0]!r}')
    return default


@dataclass(frozen=True)
class OusterMetadata:
    """The parts of an Ouster sensor's metadata JSON that decoding needs (angles in deg, lengths in mm)."""

    prod_line: str
    serial: str
    firmware: str
    columns_per_frame: int
    columns_per_packet: int
    pixels_per_column: int
    column_window: tuple[int, int]
    udp_profile_lidar: str
    udp_profile_imu: str
    beam_altitude_angles: np.ndarray
    beam_azimuth_angles: np.ndarray
    lidar_origin_to_beam_origin_mm: float
    lidar_to_sensor_transform: np.ndarray  # (4, 4), translation in mm
    imu_to_sensor_transform: np.ndarray  # (4, 4), translation in mm
    udp_port_lidar: int
    udp_port_imu: int
    init_id: int

    @classmethod
    def from_json(cls, source: str | Path | dict) -> OusterMetadata:
        meta = source if isinstance(source, dict) else json.loads(Path(source).read_text())
        if not isinstance(meta, dict):
            raise OusterFormatError('Ouster metadata must be a JSON object')
        profile = str(
            _find(
                meta,
                'data_format.udp_profile_lidar',
                'lidar_data_format.udp_profile_lidar',
                'config_params.udp_profile_lidar',
                default='LEGACY',
            )
        )
        if profile not in _PROFILES:
            raise OusterFormatError(f"unsupported udp_profile_lidar '{profile}' (supported: {sorted(_PROFILES)})")
        altitude = np.asarray(_find(meta, 'beam_altitude_angles', 'beam_intrinsics.beam_altitude_angles'), float)
        azimuth = np.asarray(_find(meta, 'beam_azimuth_angles', 'beam_intrinsics.beam_azimuth_angles'), float)
        height = int(_find(meta, 'data_format.pixels_per_column', 'lidar_data_format.pixels_per_column'))
        width = int(_find(meta, 'data_format.columns_per_frame', 'lidar_data_format.columns_per_frame'))
        if altitude.shape != (height,) or azimuth.shape != (height,):
            raise OusterFormatError(
                f'metadata has {altitude.size} altitude / {azimuth.size} azimuth angles for {height} pixels per column'
            )
        window = _find(meta, 'data_format.column_window', 'lidar_data_format.column_window', default=[0, width - 1])
        lidar_to_sensor = np.asarray(
            _find(meta, 'lidar_to_sensor_transform', 'lidar_intrinsics.lidar_to_sensor_transform'), float
        ).reshape(4, 4)
        imu_to_sensor = np.asarray(
            _find(
                meta,
                'imu_to_sensor_transform',
                'imu_intrinsics.imu_to_sensor_transform',
                default=np.eye(4).ravel().tolist(),
            ),
            float,
        ).reshape(4, 4)
        return cls(
            prod_line=str(_find(meta, 'prod_line', 'sensor_info.prod_line', default='unknown')),
            serial=str(_find(meta, 'prod_sn', 'sensor_info.prod_sn', default='')),
            firmware=str(_find(meta, 'build_rev', 'sensor_info.build_rev', default='')),
            columns_per_frame=width,
            columns_per_packet=int(
                _find(meta, 'data_format.columns_per_packet', 'lidar_data_format.columns_per_packet', default=16)
            ),
            pixels_per_column=height,
            column_window=(int(window[0]), int(window[1])),
            udp_profile_lidar=profile,
            udp_profile_imu=str(
                _find(
                    meta,
                    'data_format.udp_profile_imu',
                    'lidar_data_format.udp_profile_imu',
                    'config_params.udp_profile_imu',
                    default='LEGACY',
                )
            ),
            beam_altitude_angles=altitude,
            beam_azimuth_angles=azimuth,
            lidar_origin_to_beam_origin_mm=float(
                _find(meta, 'lidar_origin_to_beam_origin_mm', 'beam_intrinsics.lidar_origin_to_beam_origin_mm')
            ),
            lidar_to_sensor_transform=lidar_to_sensor,
            imu_to_sensor_transform=imu_to_sensor,
            udp_port_lidar=int(_find(meta, 'udp_port_lidar', 'config_params.udp_port_lidar', default=7502) or 7502),
            udp_port_imu=int(_find(meta, 'udp_port_imu', 'config_params.udp_port_imu', default=7503) or 7503),
            init_id=int(_find(meta, 'initialization_id', 'sensor_info.initialization_id', default=0) or 0),
        )

    @property
    def legacy(self) -> bool:
        return self.udp_profile_lidar == 'LEGACY'

    @property
    def column_bytes(self) -> int:
        header, footer = (16, 4) if self.legacy else (12, 0)
        return header + self.pixels_per_column * _PROFILES[self.udp_profile_lidar].pixel_bytes + footer

    @property
    def lidar_packet_size(self) -> int:
        """[bytes] of one lidar UDP payload."""
        return (0 if self.legacy else 64) + self.columns_per_packet * self.column_bytes

    @property
    def window_columns(self) -> int:
        """Columns of a full scan inside ``column_window``."""
        start, end = self.column_window
        return (end - start) % self.columns_per_frame + 1


@dataclass
class OusterScan:
    """One scan (a ``frame_id``) decoded into a point cloud."""

    points: np.ndarray  # structured (x, y, z [m, os_sensor], intensity, ring, time)
    stamp_ns: int  # time of the first valid column on the capture clock [ns since the epoch]
    sensor_time_ns: int  # the same instant on the sensor's clock [ns]
    frame_id: int
    columns: int  # valid columns received
    completeness: float  # columns / columns in the column window
    duration: float  # [s] first to last valid column


@dataclass
class ImuSamples:
    """IMU samples in the ``os_imu`` frame."""

    stamps_ns: np.ndarray  # (n,) gyroscope read time on the capture clock [ns]
    linear_acceleration: np.ndarray  # (n, 3) [m/s^2]
    angular_velocity: np.ndarray  # (n, 3) [rad/s]


def _le(raw: np.ndarray, offset: int, nbytes: int) -> np.ndarray:
    """Little-endian unsigned integers of ``nbytes`` at ``offset`` along the last axis, as int64/uint64."""
    part = np.ascontiguousarray(raw[..., offset : offset + nbytes])
    dtype = {1: '<u1', 2: '<u2', 4: '<u4', 8: '<u8'}[nbytes]
    values = part.view(dtype)[..., 0]
    return values.astype(np.uint64 if nbytes == 8 else np.int64)


@dataclass
class DecodeStats:
    packets: int = 0
    bad_packets: int = 0  # wrong size or packet type
    scans: int = 0
    incomplete_scans: int = 0
    notes: list[str] = field(default_factory=list)


class OusterDecoder:
    """Decodes lidar packets into :class:`OusterScan` clouds (see the module docstring for conventions).

    ``min_completeness``: drop scans with fewer valid columns than this fraction of the column window (the
    partial scans at the start and end of a capture). ``point_dtype``: output layout.
    """

    def __init__(
        self, metadata: OusterMetadata, *, min_completeness: float = 0.95, point_dtype: np.dtype = VELODYNE_POINT_DTYPE
    ):
        self.meta = metadata
        self.profile = _PROFILES[metadata.udp_profile_lidar]
        self.min_completeness = min_completeness
        self.point_dtype = np.dtype(point_dtype)
        self.stats = DecodeStats()
        self.clock_offset_ns: int | None = None  # capture clock - sensor clock
        self._direction, self._offset = self._lut()

    def _lut(self) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) unit directions (in the sensor frame) and offsets [mm] per beam and measurement id."""
        m = self.meta
        width = m.columns_per_frame
        encoder = 2.0 * np.pi * (1.0 - np.arange(width) / width)  # (W,)
        azimuth = -np.radians(m.beam_azimuth_angles)[:, None]  # (H, 1)
        altitude = np.radians(m.beam_altitude_angles)[:, None]
        direction = np.stack(
            np.broadcast_arrays(
                np.cos(encoder + azimuth) * np.cos(altitude),
                np.sin(encoder + azimuth) * np.cos(altitude),
                np.sin(altitude) + 0.0 * encoder,
            ),
            axis=-1,
        )
        offset = (
            np.stack(
                np.broadcast_arrays(
                    np.cos(encoder) - direction[..., 0], np.sin(encoder) - direction[..., 1], -direction[..., 2]
                ),
                axis=-1,
            )
            * m.lidar_origin_to_beam_origin_mm
        )
        rotation = m.lidar_to_sensor_transform[:3, :3]
        translation = m.lidar_to_sensor_transform[:3, 3]
        return direction @ rotation.T, offset @ rotation.T + translation

    #: Leading bytes of a lidar packet that :meth:`frame_ids` needs.
    HEAD_BYTES = 12

    def frame_ids(self, heads: np.ndarray) -> np.ndarray:
        """Scan (frame) id of each packet from its first :attr:`HEAD_BYTES` bytes, (n, >= 12) uint8; lets a
        caller cut a long capture into batches of whole scans without reading the packets."""
        return _le(np.asarray(heads), 10 if self.meta.legacy else 2, 2)

    def decode(self, packets: np.ndarray, capture_ns: np.ndarray) -> list[OusterScan]:
        """All scans of (n, lidar_packet_size) uint8 packets with their capture times [ns]. A scan is a run of
        consecutive packets with the same frame id: pass whole scans (see :meth:`frame_ids`)."""
        m, prof = self.meta, self.profile
        packets = np.asarray(packets)
        capture_ns = np.asarray(capture_ns, dtype=np.int64)
        self.stats.packets += len(packets)
        if packets.ndim != 2 or packets.shape[1] != m.lidar_packet_size:
            raise OusterFormatError(
                f'expected (n, {m.lidar_packet_size}) lidar packets for profile '
                f'{m.udp_profile_lidar}, got {packets.shape}'
            )
        if not m.legacy:
            good = _le(packets, 0, 2) == 1
            self.stats.bad_packets += int((~good).sum())
            packets, capture_ns = packets[good], capture_ns[good]
        if len(packets) == 0:
            return []
        n, cpp, height = len(packets), m.columns_per_packet, m.pixels_per_column
        start = 0 if m.legacy else 32
        columns = packets[:, start : start + cpp * m.column_bytes].reshape(n, cpp, m.column_bytes)
        stamps = _le(columns, 0, 8).astype(np.int64)  # (n, cpp) sensor ns
        measurement = _le(columns, 8, 2)
        if m.legacy:
            frame = _le(columns[:, 0], 10, 2)
            valid = _le(columns, m.column_bytes - 4, 4) == 0xFFFFFFFF
            pixels = columns[:, :, 16 : 16 + height * prof.pixel_bytes]
        else:
            frame = _le(packets, 2, 2)
            valid = (_le(columns, 10, 2) & 1) == 1
            pixels = columns[:, :, 12 : 12 + height * prof.pixel_bytes]
        valid &= measurement < m.columns_per_frame
        pixels = pixels.reshape(n, cpp, height, prof.pixel_bytes)
        if self.clock_offset_ns is None:
            first = int(np.argmax(valid[0])) if valid[0].any() else 0
            self.clock_offset_ns = int(capture_ns[0]) - int(stamps[0, first])
        # Scans: runs of consecutive packets with the same frame id.
        breaks = np.flatnonzero(np.diff(frame)) + 1
        scans = []
        for p0, p1 in zip(np.concatenate([[0], breaks]), np.concatenate([breaks, [n]])):
            scan = self._scan(int(frame[p0]), stamps[p0:p1], measurement[p0:p1], valid[p0:p1], pixels[p0:p1])
            if scan is not None:
                scans.append(scan)
        return scans

    def _scan(
        self, frame_id: int, stamps: np.ndarray, measurement: np.ndarray, valid: np.ndarray, pixels: np.ndarray
    ) -> OusterScan | None:
        m, prof = self.meta, self.profile
        height = m.pixels_per_column
        columns = int(np.unique(measurement[valid]).size)
        completeness = columns / m.window_columns
        if completeness < self.min_completeness:
            self.stats.incomplete_scans += 1
            return None
        raw = _le(pixels, prof.range_offset, prof.range_bytes)  # (p, cpp, H)
        range_mm = (raw & prof.range_mask) * prof.range_scale
        keep = (range_mm > 0) & valid[:, :, None]
        beam = np.broadcast_to(np.arange(height), keep.shape)[keep]
        column = np.broadcast_to(measurement[:, :, None], keep.shape)[keep]
        r = range_mm[keep].astype(np.float64)
        xyz = (r[:, None] * self._direction[beam, column] + self._offset[beam, column]) * 1e-3
        if prof.signal_offset is not None:
            intensity = _le(pixels, prof.signal_offset, 2)[keep]
        else:
            intensity = _le(pixels, prof.reflectivity_offset, prof.reflectivity_bytes)[keep]
        first_ns = int(stamps[valid].min())
        last_ns = int(stamps[valid].max())
        time = ((np.broadcast_to(stamps[:, :, None], keep.shape)[keep] - first_ns) / 1e9).astype(np.float32)
        ring = (height - 1 - beam).astype(np.uint16)
        points = velodyne_points(xyz.astype(np.float32), intensity, ring, time, dtype=self.point_dtype)
        self.stats.scans += 1
        return OusterScan(
            points=points,
            stamp_ns=first_ns + int(self.clock_offset_ns),
            sensor_time_ns=first_ns,
            frame_id=frame_id,
            columns=columns,
            completeness=completeness,
            duration=(last_ns - first_ns) / 1e9,
        )


def decode_imu(packets: np.ndarray, clock_offset_ns: int) -> ImuSamples:
    """IMU samples of (n, 48) uint8 LEGACY IMU packets; ``clock_offset_ns`` = capture - sensor clock."""
    packets = np.asarray(packets)
    if packets.ndim != 2 or packets.shape[1] != IMU_PACKET_SIZE:
        raise OusterFormatError(f'expected (n, {IMU_PACKET_SIZE}) IMU packets, got {packets.shape}')
    gyro_ns = _le(packets, 16, 8).astype(np.int64)
    values = np.ascontiguousarray(packets[:, 24:48]).view('<f4').astype(np.float64)  # (n, 6)
    return ImuSamples(
        stamps_ns=gyro_ns + int(clock_offset_ns),
        linear_acceleration=values[:, :3] * STANDARD_GRAVITY,
        angular_velocity=np.radians(values[:, 3:]),
    )
