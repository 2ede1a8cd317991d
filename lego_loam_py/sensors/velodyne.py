"""Velodyne VLP-16 packet decoder: raw 1206-byte UDP payloads -> one point cloud per sensor rotation.

Vectorised over all packets of a chunk (numpy only, no ROS). The arithmetic is the ROS 1
``velodyne_pointcloud`` driver's (1.7.0, ``unpack_vlp16``) with its stock ``VLP16db.yaml`` calibration, in
float32 as in the driver, so the clouds equal the driver's bit for bit (see "Bit-exactness" below).

Packet layout (VLP-16 user manual, little-endian)::

    12 data blocks of 100 bytes: flag 0xFFEE (bytes FF EE), azimuth u16 [0.01 deg, clockwise seen from
        above], then 32 channel records of 3 bytes: distance u16 [2 mm, 0 = no return], reflectivity u8.
        Channels 0-15 are firing sequence 0 of the block (lasers 0-15), channels 16-31 sequence 1.
    bytes 1200-1203: timestamp u32 [µs since the top of the hour] of the packet's first firing
    byte 1204: return mode (0x37 strongest, 0x38 last, 0x39 dual)
    byte 1205: product id (0x22 VLP-16, 0x21 HDL-32E, ...)

Timing: a firing sequence (16 lasers) takes 55.296 µs, lasers fire 2.304 µs apart. In single-return modes
a packet holds 24 sequences (two per block). In dual-return mode blocks come in pairs (2k, 2k+1) that hold
the same two sequences: block 2k the last return, block 2k+1 the strongest (or second-strongest when the
last is the strongest); when a laser saw only one echo both blocks carry the same value.

Geometry, per point (REP-103 sensor axes of frame ``velodyne``: x forward, y left, z up)::

    az  = round(block_az + diff * (laser*2.304 + sequence*55.296) / 110.592) % 36000    [0.01 deg]
    x   = d cos(v) cos(az),   y = -d cos(v) sin(az),   z = d sin(v)

with ``d = raw * 0.002`` m, ``v`` the laser's elevation (-15, 1, -13, 3, ..., -1, 15 deg for laser 0..15),
``diff`` the azimuth step to the next block (next block pair in dual mode; the packet's last block reuses
the previous step; the 35999 -> 0 wrap is taken modulo 36000) and round = half away from zero. ``ring`` is
0 for the lowest beam (-15 deg) up to 15 (+15 deg). ``intensity`` is the raw reflectivity byte.

Time: a firing's absolute time is the packet's device timestamp + 55.296 µs per sequence + 2.304 µs per
laser, in integer nanoseconds. The device clock (which restarts every hour) is unwrapped and anchored to
the capture time of the stream's first packet (pcap timestamp or ``VelodynePacket.stamp``): capture times
are bursty, the device clock is not. A rotation's header stamp is the time of its first firing sequence
and each point's ``time`` [s, float32] is measured from it.

Rotations: the stream is cut at firing-sequence granularity, where the sequence azimuth crosses the cut
azimuth: 0 (``split='wrap'``, as the driver) or the azimuth of the stream's first sequence
(``split='start'``, for captures holding one sweep that does not pass the wrap twice). A rotation whose
azimuth span, less gaps from lost packets, covers less than ``min_completeness`` of 360 deg (such as the
stream's first and last fragments) is dropped. Points keep firing order: packet, block, sequence, laser;
in dual mode packet, block pair, block (first, then second), sequence, laser, both blocks with the pair's
azimuth and time.

Bit-exactness: cos/sin tables hold, for every 0.01 deg step ``i``, the float32 nearest to cos/sin of the
float32 angle ``float(radians(0.01f * i))``, i.e. what a correctly rounded ``cosf`` gives (glibc's
``cosf`` differs from it by one ulp for about 1.4 % of the steps; the golden inputs of the C++ original
were made with correctly rounded tables, and this decoder reproduces them bit for bit). Deviations from the
driver: the wrap difference is taken modulo 36000 (the driver reuses the previous difference or drops the
block), and in dual mode both blocks of a pair get the pair's interpolation and timing (the driver uses
the single-return tables for dual packets).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lego_loam_py.core.pointcloud import VELODYNE_POINT_DTYPE, velodyne_points
from lego_loam_py.errors import LegoLoamError

__all__ = [
    'PACKET_SIZE',
    'RETURN_STRONGEST',
    'RETURN_LAST',
    'RETURN_DUAL',
    'PRODUCT_VLP16',
    'PRODUCT_HDL32E',
    'PRODUCT_NAMES',
    'VLP16_ELEVATION_DEG',
    'VLP16_RING',
    'SEQUENCE_NS',
    'LASER_NS',
    'VelodyneFormatError',
    'Rotation',
    'DecoderStats',
    'Vlp16Decoder',
    'decode_vlp16',
    'sequence_azimuths',
]

PACKET_SIZE = 1206
BLOCKS_PER_PACKET = 12
BLOCK_SIZE = 100
BLOCK_FLAG = 0xEEFF  # bytes FF EE read little-endian
LASERS = 16
RETURN_STRONGEST, RETURN_LAST, RETURN_DUAL = 0x37, 0x38, 0x39
PRODUCT_HDL32E, PRODUCT_VLP16 = 0x21, 0x22
PRODUCT_NAMES = {
    0x21: 'HDL-32E',
    0x22: 'VLP-16',
    0x24: 'VLP-16 Hi-Res',
    0x28: 'VLP-32C',
    0x31: 'Velarray',
    0xA1: 'VLS-128',
}
RETURN_MODE_NAMES = {RETURN_STRONGEST: 'strongest', RETURN_LAST: 'last', RETURN_DUAL: 'dual'}

SEQUENCE_NS = 55_296  # one firing sequence of 16 lasers [ns]
LASER_NS = 2_304  # between two lasers of a sequence [ns]
DEVICE_CLOCK_PERIOD_US = 3_600_000_000  # the device timestamp counts µs since the top of the hour
FULL_TURN = 36_000  # [0.01 deg]

#: Elevation [deg] of laser id 0..15 (VLP16db.yaml) and its ring (0 = lowest beam).
VLP16_ELEVATION_DEG = np.array([-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15], dtype=np.float64)
VLP16_RING = np.argsort(np.argsort(VLP16_ELEVATION_DEG)).astype(np.uint16)

_F32 = np.float32
# Float32 constants and the per-laser, per-sequence time offsets of the driver (vlp16 timing, in µs).
_DISTANCE_RESOLUTION = _F32(0.002)
_BLOCK_DURATION = _F32(110.592)
_OFFSET_US = np.arange(LASERS, dtype=_F32)[None, :] * _F32(2.304) + np.arange(2, dtype=_F32)[:, None] * _F32(
    55.296
)  # (sequence, laser)


def _tables() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """cos/sin of every 0.01 deg step and of the 16 elevations, as the driver's float32 tables."""
    step = _F32(0.01) * np.arange(FULL_TURN, dtype=_F32)  # float32 product, as in the driver
    angle = (step.astype(np.float64) * np.pi / 180.0).astype(_F32)  # angles::from_degrees, stored as float
    vertical = np.radians(VLP16_ELEVATION_DEG).astype(_F32)  # vert_correction [rad] read as float
    as64 = np.float64
    return (
        np.cos(angle.astype(as64)).astype(_F32),
        np.sin(angle.astype(as64)).astype(_F32),
        np.cos(vertical.astype(as64)).astype(_F32),
        np.sin(vertical.astype(as64)).astype(_F32),
    )


_COS_AZ, _SIN_AZ, _COS_EL, _SIN_EL = _tables()


class VelodyneFormatError(LegoLoamError, ValueError):
    """The packets are not VLP-16 packets this decoder can read (wrong size, model or mixed modes)."""


@dataclass
class Rotation:
    """One sensor rotation (sweep) decoded into a point cloud."""

    points: np.ndarray  # structured array (x, y, z, intensity, ring, time) in the requested layout
    stamp_ns: int  # header stamp [ns]: first firing, or the restamped time
    first_firing_ns: int  # time of the rotation's first firing sequence [ns since the epoch]
    first_azimuth_deg: float  # azimuth of the first / last firing sequence (clockwise, 0.01 deg steps)
    last_azimuth_deg: float
    n_sequences: int  # firing sequences in the rotation
    completeness: float  # azimuth span (less gaps) / 360 deg
    return_block: np.ndarray  # (n,) uint8: 0 = first block of a dual-return pair (or single return), 1 = second
    dual_return: bool

    @property
    def duration(self) -> float:
        """[s] from the first to the last firing sequence."""
        return (self.n_sequences - 1) * SEQUENCE_NS * 1e-9


@dataclass
class DecoderStats:
    packets: int = 0
    bad_packets: int = 0  # packets with a block flag other than 0xFFEE (dropped whole)
    rotations: int = 0  # rotations emitted
    incomplete_rotations: int = 0  # fragments dropped for covering less than min_completeness
    product_id: int | None = None
    return_mode: int | None = None
    notes: list[str] = field(default_factory=list)


def _u16(a: np.ndarray, lo: int) -> np.ndarray:
    return a[..., lo].astype(np.int64) | (a[..., lo + 1].astype(np.int64) << 8)


def sequence_azimuths(packets: np.ndarray, dual: bool) -> np.ndarray:
    """(n, sequences per packet) int64 azimuth [0.01 deg] of each firing sequence's first laser."""
    n = packets.shape[0]
    block_az = _u16(packets[:, : BLOCKS_PER_PACKET * BLOCK_SIZE].reshape(n, BLOCKS_PER_PACKET, BLOCK_SIZE), 2)
    base, diff = _block_steps(block_az, dual)
    seq = base.astype(_F32)[:, :, None] + (diff.astype(_F32)[:, :, None] * _OFFSET_US[:, 0]) / _BLOCK_DURATION
    return (_round_half_away(seq) % FULL_TURN).reshape(n, -1)


def _block_steps(block_az: np.ndarray, dual: bool) -> tuple[np.ndarray, np.ndarray]:
    """(azimuth, step to the next block or block pair) per block (pair), int64 [0.01 deg]."""
    base = block_az[:, ::2] if dual else block_az
    diff = np.empty_like(base)
    diff[:, :-1] = (base[:, 1:] - base[:, :-1]) % FULL_TURN
    diff[:, -1] = diff[:, -2]
    return base, diff


def _coverage(unwrapped: np.ndarray) -> float:
    """Fraction of a turn swept by consecutive firing sequences (unwrapped azimuths [0.01 deg]): the span
    from the first to the last sequence, minus gaps (steps over 4x the median step: lost packets, a paused
    capture)."""
    if unwrapped.size < 2:
        return 0.0
    steps = np.diff(unwrapped)
    typical = max(float(np.median(steps)), 1.0)
    return float(steps[steps <= 4.0 * typical].sum()) / FULL_TURN


def _round_half_away(values: np.ndarray) -> np.ndarray:
    """C's round() of non-negative float32 values, as int64 (exact in float64)."""
    return np.floor(values.astype(np.float64) + 0.5).astype(np.int64)


class Vlp16Decoder:
    """Streaming VLP-16 decoder: :meth:`feed` chunks of packets, get the rotations they complete;
    :meth:`finish` returns the last one.

    Parameters (all optional):

    * ``force_model``: decode as VLP-16 whatever the product byte says (some VLP-16 firmware reports
      0x21, HDL-32E). Without it, packets that do not claim a VLP-16 raise :class:`VelodyneFormatError`.
    * ``split``: ``'wrap'`` (cut at azimuth 0, as the driver) or ``'start'`` (cut at the azimuth of the
      first firing sequence: one full sweep from the capture's start).
    * ``min_completeness``: drop rotations whose azimuth span, less gaps (lost packets), is below this
      fraction of 360 deg.
    * ``restamp_period_ns``: header stamp of rotation k = stamp of rotation 0 + k * period (the ``time``
      field is not rescaled). For feeding a 20 Hz recording to a pipeline that assumes 10 Hz.
    * ``point_dtype``: layout of :attr:`Rotation.points` (``VELODYNE_POINT_DTYPE``, 32 B, or
      ``VELODYNE_PACKED_DTYPE``, the ROS 1 driver's 22 B).
    """

    def __init__(
        self,
        *,
        force_model: bool = False,
        split: str = 'wrap',
        min_completeness: float = 0.95,
        restamp_period_ns: int | None = None,
        point_dtype: np.dtype = VELODYNE_POINT_DTYPE,
    ):
        if split not in ('wrap', 'start'):
            raise ValueError(f"split must be 'wrap' or 'start', got {split!r}")
        if not 0.0 <= min_completeness <= 1.0:
            raise ValueError('min_completeness must be within [0, 1]')
        if restamp_period_ns is not None and restamp_period_ns <= 0:
            raise ValueError('restamp_period_ns must be positive')
        self.force_model = force_model
        self.split = split
        self.min_completeness = min_completeness
        self.restamp_period_ns = restamp_period_ns
        self.point_dtype = np.dtype(point_dtype)
        self.stats = DecoderStats()
        self._dual: bool | None = None
        self._cut: int | None = 0 if split == 'wrap' else None
        self._anchor: tuple[int, int] | None = None  # (capture ns, unwrapped device µs) of the first packet
        self._last_device_us: int | None = None  # unwrapped device time of the last packet fed
        self._pending = np.zeros((0, PACKET_SIZE), np.uint8)
        self._pending_ns = np.zeros(0, np.int64)  # first-firing time of each pending packet
        self._pending_skip = 0  # sequences of pending[0] before the open rotation
        self._first_stamp: int | None = None

    @property
    def sequences_per_packet(self) -> int:
        return 12 if self._dual else 24

    # ---------------------------------------------------------------- input checks and clock
    def _validate(self, packets: np.ndarray) -> np.ndarray:
        """Mask of packets to keep; sets the return mode and checks the model on first use."""
        n = packets.shape[0]
        flags = _u16(packets[:, : BLOCKS_PER_PACKET * BLOCK_SIZE].reshape(n, BLOCKS_PER_PACKET, BLOCK_SIZE), 0)
        good = (flags == BLOCK_FLAG).all(axis=1)
        self.stats.bad_packets += int(n - good.sum())
        if not good.any():
            return good
        modes = np.unique(packets[good, 1204])
        products = np.unique(packets[good, 1205])
        unknown = [m for m in modes.tolist() if m not in RETURN_MODE_NAMES]
        if unknown:
            raise VelodyneFormatError(
                f'unknown return mode byte(s) {[hex(m) for m in unknown]} '
                '(expected 0x37 strongest, 0x38 last or 0x39 dual)'
            )
        dual = modes == RETURN_DUAL
        if dual.any() and not dual.all() or (self._dual is not None and bool(dual[0]) != self._dual):
            raise VelodyneFormatError('the stream mixes single- and dual-return packets')
        self._dual = bool(dual[0])
        if self.stats.return_mode is None:
            self.stats.return_mode = int(modes[0])
            self.stats.product_id = int(products[0])
        if not self.force_model and (products != PRODUCT_VLP16).any():
            names = ', '.join(f'0x{p:02x} ({PRODUCT_NAMES.get(p, "unknown")})' for p in products.tolist())
            raise VelodyneFormatError(
                f'packets claim product id {names}, not 0x22 (VLP-16). If the sensor is a VLP-16 whose '
                'firmware reports another id (early VLP-16 firmware says 0x21, HDL-32E), force the model '
                '(--model VLP-16 / force_model=True).'
            )
        return good

    def _firing_times(self, packets: np.ndarray, capture_ns: np.ndarray) -> np.ndarray:
        """Absolute time [ns] of each packet's first firing: device clock unwrapped, anchored to the
        capture time of the stream's first packet."""
        device = packets[:, 1200:1204].copy().view('<u4').reshape(-1).astype(np.int64)
        previous = device[0] if self._last_device_us is None else self._last_device_us % DEVICE_CLOCK_PERIOD_US
        steps = np.diff(np.concatenate([[previous], device]))
        hours = np.cumsum(steps < -DEVICE_CLOCK_PERIOD_US // 2)
        base = 0 if self._last_device_us is None else self._last_device_us - previous
        unwrapped = base + device + hours * DEVICE_CLOCK_PERIOD_US
        if self._anchor is None:
            self._anchor = (int(capture_ns[0]), int(unwrapped[0]))
        self._last_device_us = int(unwrapped[-1])
        return self._anchor[0] + (unwrapped - self._anchor[1]) * 1000

    # ---------------------------------------------------------------- streaming interface
    def feed(self, packets: np.ndarray, capture_ns: np.ndarray) -> list[Rotation]:
        """Decode a chunk of packets ((n, 1206) uint8, capture times [ns]); returns completed rotations."""
        packets = np.asarray(packets)
        capture_ns = np.asarray(capture_ns, dtype=np.int64).reshape(-1)
        if packets.ndim != 2 or packets.shape[1] != PACKET_SIZE or packets.dtype != np.uint8:
            raise VelodyneFormatError(f'expected (n, {PACKET_SIZE}) uint8 packets, got {packets.shape} {packets.dtype}')
        if capture_ns.size != packets.shape[0]:
            raise ValueError('one capture time per packet is needed')
        self.stats.packets += packets.shape[0]
        if packets.shape[0] == 0:
            return []
        good = self._validate(packets)
        packets, capture_ns = packets[good], capture_ns[good]
        if packets.shape[0] == 0:
            return []
        times = self._firing_times(packets, capture_ns)
        data = np.concatenate([self._pending, packets]) if self._pending.size else packets
        times = np.concatenate([self._pending_ns, times]) if self._pending_ns.size else times
        return self._assemble(data, times, final=False)

    def finish(self) -> list[Rotation]:
        """The open rotation, if complete enough; the decoder is empty afterwards."""
        if not self._pending.size:
            return []
        data, times = self._pending, self._pending_ns
        return self._assemble(data, times, final=True)

    # ---------------------------------------------------------------- rotations
    def _assemble(self, data: np.ndarray, times: np.ndarray, final: bool) -> list[Rotation]:
        per_packet = self.sequences_per_packet
        azimuth = sequence_azimuths(data, self._dual).reshape(-1)[self._pending_skip :]
        if self._cut is None:
            self._cut = int(azimuth[0])
        wraps = np.concatenate([[0], np.cumsum(np.diff(azimuth) < -FULL_TURN // 2)])
        unwrapped = azimuth + FULL_TURN * wraps
        turn = np.floor_divide(unwrapped - self._cut, FULL_TURN)
        rotation_of = turn - turn[0]  # 0 for the open rotation, then 1, 2, ...
        starts = np.flatnonzero(np.diff(rotation_of)) + 1  # first sequence of every later rotation
        bounds = np.concatenate([[0], starts, [azimuth.size]])
        n_complete = len(bounds) - 1 if final else len(bounds) - 2
        rotations: list[Rotation] = []
        for k in range(n_complete):
            s0, s1 = int(bounds[k]), int(bounds[k + 1])
            completeness = _coverage(unwrapped[s0:s1])
            if completeness < self.min_completeness:
                self.stats.incomplete_rotations += 1
                continue
            rotations.append(
                self._decode_rotation(
                    data,
                    times,
                    s0 + self._pending_skip,
                    s1 + self._pending_skip,
                    azimuth[s0],
                    azimuth[s1 - 1],
                    completeness,
                )
            )
        if final:
            keep_from = azimuth.size
        else:
            keep_from = int(bounds[-2])
        first_seq = keep_from + self._pending_skip
        first_packet = first_seq // per_packet
        self._pending = data[first_packet:].copy() if not final else data[:0]
        self._pending_ns = times[first_packet:].copy() if not final else times[:0]
        self._pending_skip = first_seq - first_packet * per_packet if not final else 0
        return rotations

    def _decode_rotation(
        self, data: np.ndarray, times: np.ndarray, s0: int, s1: int, first_az: int, last_az: int, completeness: float
    ) -> Rotation:
        """Points of the firing sequences [s0, s1) (indices over ``data``'s sequences)."""
        per_packet = self.sequences_per_packet
        p0, p1 = s0 // per_packet, (s1 - 1) // per_packet + 1
        packets, packet_ns = data[p0:p1], times[p0:p1]
        dual = bool(self._dual)
        n = packets.shape[0]
        returns = 2 if dual else 1
        groups = BLOCKS_PER_PACKET // returns
        blocks = packets[:, : BLOCKS_PER_PACKET * BLOCK_SIZE].reshape(n, BLOCKS_PER_PACKET, BLOCK_SIZE)
        base, diff = _block_steps(_u16(blocks, 2), dual)  # (n, groups)
        # (packet, group, sequence, laser): the driver's float32 azimuth interpolation.
        az = base.astype(_F32)[:, :, None, None] + (diff.astype(_F32)[:, :, None, None] * _OFFSET_US) / _BLOCK_DURATION
        az = _round_half_away(az) % FULL_TURN
        records = blocks[:, :, 4:].reshape(n, groups, returns, 2, LASERS, 3)  # (packet, group, return, seq, laser)
        distance_raw = _u16(records, 0)
        shape = distance_raw.shape
        sequence = (
            np.arange(n)[:, None, None] * per_packet
            + np.arange(groups)[None, :, None] * 2
            + np.arange(2)[None, None, :]
            + p0 * per_packet
        )  # (packet, group, seq)
        sequence = np.broadcast_to(sequence[:, :, None, :, None], shape)
        keep = (distance_raw != 0) & (sequence >= s0) & (sequence < s1)
        laser = np.broadcast_to(np.arange(LASERS), shape)[keep]
        azimuth = np.broadcast_to(az[:, :, None], shape)[keep]
        d = distance_raw[keep].astype(_F32) * _DISTANCE_RESOLUTION
        xy = d * _COS_EL[laser]
        xyz = np.empty((d.size, 3), dtype=_F32)
        xyz[:, 0] = xy * _COS_AZ[azimuth]
        xyz[:, 1] = -(xy * _SIN_AZ[azimuth])
        xyz[:, 2] = d * _SIN_EL[laser]
        first_ns = int(packet_ns[(s0 - p0 * per_packet) // per_packet]) + (s0 % per_packet) * SEQUENCE_NS
        fire_ns = (
            packet_ns[:, None, None, None, None]
            + (np.arange(groups)[None, :, None, None, None] * 2 + np.arange(2)[None, None, None, :, None]) * SEQUENCE_NS
            + np.arange(LASERS)[None, None, None, None, :] * LASER_NS
        )
        rel_ns = np.broadcast_to(fire_ns, shape)[keep] - first_ns
        points = velodyne_points(
            xyz, records[..., 2][keep], VLP16_RING[laser], (rel_ns / 1e9).astype(_F32), dtype=self.point_dtype
        )
        return_block = np.broadcast_to(np.arange(returns, dtype=np.uint8)[None, None, :, None, None], shape)[keep]
        if self._first_stamp is None:
            self._first_stamp = first_ns
        stamp = first_ns
        if self.restamp_period_ns is not None:
            stamp = self._first_stamp + self.stats.rotations * self.restamp_period_ns
        self.stats.rotations += 1
        return Rotation(
            points=points,
            stamp_ns=stamp,
            first_firing_ns=first_ns,
            first_azimuth_deg=first_az / 100.0,
            last_azimuth_deg=last_az / 100.0,
            n_sequences=s1 - s0,
            completeness=float(completeness),
            return_block=np.ascontiguousarray(return_block),
            dual_return=dual,
        )


def decode_vlp16(packets: np.ndarray, capture_ns: np.ndarray, *, chunk: int = 4096, **options) -> list[Rotation]:
    """All rotations of a packet stream (see :class:`Vlp16Decoder` for the options)."""
    decoder = Vlp16Decoder(**options)
    rotations: list[Rotation] = []
    for start in range(0, len(packets), chunk):
        rotations += decoder.feed(packets[start : start + chunk], capture_ns[start : start + chunk])
    return rotations + decoder.finish()
