"""Minimal reader for classic pcap captures of lidar UDP traffic (numpy only, no ROS).

Sensors such as Velodyne and Ouster lidars stream UDP datagrams; tools like Wireshark, tcpdump, VeloView and
Ouster Studio save them as pcap files. :func:`read_udp` returns every IPv4/UDP datagram of such a file as
offsets into one memory-mapped buffer, so a multi-gigabyte capture is never copied: the decoders gather only
the payloads they need (:meth:`UdpDatagrams.gather`, one fancy-index per chunk).

Supported: classic pcap in both byte orders with microsecond or nanosecond timestamps; link types Ethernet
(with any number of 802.1Q / 802.1ad VLAN tags), Linux cooked capture v1 and v2, raw IPv4 and BSD loopback;
IPv4 with options; UDP. Fragmented IPv4 datagrams (an Ouster packet larger than the link MTU) are
reassembled. Not supported: pcapng (convert with ``editcap -F pcap in.pcapng out.pcap``), IPv6, TCP.

Walking the records is a short Python loop that only reads record headers (about 1 µs per record); all
protocol parsing is vectorised over the records.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lego_loam_py.errors import LegoLoamError

__all__ = ['PcapError', 'UdpDatagrams', 'read_udp']

_MAGIC = {  # magic as read little-endian -> (byte order, fraction-of-second unit in ns)
    0xA1B2C3D4: ('<', 1000),
    0xD4C3B2A1: ('>', 1000),
    0xA1B23C4D: ('<', 1),
    0x4D3CB2A1: ('>', 1),
}
_PCAPNG_MAGIC = 0x0A0D0D0A
LINKTYPE_NULL, LINKTYPE_ETHERNET, LINKTYPE_RAW_BSD, LINKTYPE_RAW = 0, 1, 12, 101
LINKTYPE_LINUX_SLL, LINKTYPE_IPV4, LINKTYPE_LINUX_SLL2 = 113, 228, 276
_ETHERTYPE_IPV4 = 0x0800
_VLAN_TAGS = (0x8100, 0x88A8, 0x9100)
_UDP = 17
_GATHER_BYTES = 64 << 20  # bytes gathered per fancy-index call (bounds the index array's memory)


class PcapError(LegoLoamError, ValueError):
    """The file is not a readable classic pcap capture."""


@dataclass
class UdpDatagrams:
    """UDP datagrams of a capture, in capture order. Payload i is ``buffers[buffer_ids[i]]
    [offsets[i]:offsets[i] + lengths[i]]``: buffer 0 is the (memory-mapped) file, buffer 1 holds
    datagrams reassembled from IPv4 fragments."""

    buffers: list[np.ndarray]  # uint8 arrays
    buffer_ids: np.ndarray  # (n,) uint8
    offsets: np.ndarray  # (n,) int64, payload start in its buffer
    lengths: np.ndarray  # (n,) int64, UDP payload length [bytes]
    stamps_ns: np.ndarray  # (n,) int64, capture time [ns since the epoch]
    src_ports: np.ndarray  # (n,) uint16
    dst_ports: np.ndarray  # (n,) uint16
    linktype: int = LINKTYPE_ETHERNET
    skipped: int = 0  # records that are not complete IPv4/UDP datagrams

    def __len__(self) -> int:
        return int(self.offsets.size)

    def select(self, mask: np.ndarray) -> UdpDatagrams:
        """The datagrams where ``mask`` (bool or index array) selects, same buffers."""
        return UdpDatagrams(
            self.buffers,
            self.buffer_ids[mask],
            self.offsets[mask],
            self.lengths[mask],
            self.stamps_ns[mask],
            self.src_ports[mask],
            self.dst_ports[mask],
            self.linktype,
            self.skipped,
        )

    def gather(self, length: int, indices: np.ndarray | None = None) -> np.ndarray:
        """(k, length) uint8 array of the first ``length`` payload bytes of datagrams ``indices`` (all by
        default). Every selected payload must be at least ``length`` bytes long."""
        idx = np.arange(len(self)) if indices is None else np.asarray(indices, dtype=np.int64)
        if idx.size and int(self.lengths[idx].min()) < length:
            raise ValueError(f'a selected datagram is shorter than {length} bytes')
        out = np.empty((idx.size, length), dtype=np.uint8)
        columns = np.arange(length, dtype=np.int64)
        step = max(1, _GATHER_BYTES // max(1, 8 * length))
        for buffer_id, buffer in enumerate(self.buffers):
            rows = np.flatnonzero(self.buffer_ids[idx] == buffer_id)
            for start in range(0, rows.size, step):
                part = rows[start : start + step]
                out[part] = buffer[self.offsets[idx[part]][:, None] + columns]
        return out

    def payload(self, i: int) -> bytes:
        """The payload of datagram ``i``."""
        start = int(self.offsets[i])
        return self.buffers[int(self.buffer_ids[i])][start : start + int(self.lengths[i])].tobytes()


def _be16(buf: np.ndarray, at: np.ndarray) -> np.ndarray:
    return (buf[at].astype(np.int64) << 8) | buf[at + 1]


def _record_index(buf: np.ndarray, order: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(data offset, captured length, ts seconds, ts fraction) of every record, walking the headers."""
    raw = memoryview(buf)
    header = struct.Struct(order + 'IIII')
    size = buf.size
    offsets, caplens, secs, fracs = [], [], [], []
    pos = 24
    while pos + 16 <= size:
        sec, frac, caplen, _ = header.unpack_from(raw, pos)
        if pos + 16 + caplen > size:
            break  # truncated last record (capture interrupted)
        offsets.append(pos + 16)
        caplens.append(caplen)
        secs.append(sec)
        fracs.append(frac)
        pos += 16 + caplen
    return (
        np.array(offsets, dtype=np.int64),
        np.array(caplens, dtype=np.int64),
        np.array(secs, dtype=np.int64),
        np.array(fracs, dtype=np.int64),
    )


def _network_offsets(
    buf: np.ndarray, linktype: int, data: np.ndarray, caplen: np.ndarray, order: str
) -> tuple[np.ndarray, np.ndarray]:
    """(offset of the IPv4 header, is IPv4) for every record of the given link type."""
    if linktype == LINKTYPE_ETHERNET:
        ok = caplen >= 14
        at = np.where(ok, data + 12, 0)
        ethertype = np.where(ok, _be16(buf, at), 0)
        l3 = data + 14
        for _ in range(3):  # VLAN tags (802.1Q, QinQ): 4 bytes each before the real ethertype
            tagged = ok & np.isin(ethertype, _VLAN_TAGS) & (l3 + 4 <= data + caplen)
            if not tagged.any():
                break
            ethertype = np.where(tagged, _be16(buf, np.where(tagged, l3 + 2, 0)), ethertype)
            l3 = np.where(tagged, l3 + 4, l3)
        return l3, ok & (ethertype == _ETHERTYPE_IPV4)
    if linktype == LINKTYPE_LINUX_SLL:
        ok = caplen >= 16
        return data + 16, ok & (_be16(buf, np.where(ok, data + 14, 0)) == _ETHERTYPE_IPV4)
    if linktype == LINKTYPE_LINUX_SLL2:
        ok = caplen >= 20
        return data + 20, ok & (_be16(buf, np.where(ok, data, 0)) == _ETHERTYPE_IPV4)
    if linktype in (LINKTYPE_RAW, LINKTYPE_RAW_BSD, LINKTYPE_IPV4):
        ok = caplen >= 1
        return data, ok & ((buf[np.where(ok, data, 0)] >> 4) == 4)
    if linktype == LINKTYPE_NULL:  # 4-byte address family in the capturing host's byte order
        ok = caplen >= 4
        at = np.where(ok, data, 0)
        family = np.stack([buf[at + i] for i in range(4)], axis=1).view('<u4' if order == '<' else '>u4')
        return data + 4, ok & (family.reshape(-1) == 2)
    raise PcapError(
        f'unsupported pcap link type {linktype} (supported: Ethernet, Linux cooked, raw IPv4, BSD loopback)'
    )


def _reassemble(
    buf: np.ndarray, records: np.ndarray, l3: np.ndarray, ihl: np.ndarray, total: np.ndarray, stamps: np.ndarray
) -> tuple[bytearray, list[tuple[int, int, int, int, int, int]]]:
    """Reassemble fragmented IPv4/UDP datagrams. Returns (payload bytes, [(record, offset in the bytes,
    payload length, src port, dst port, stamp of the last fragment)])."""
    groups: dict[tuple, list[tuple[int, int, int, bool]]] = {}
    for r in records:
        start = int(l3[r])
        header = buf[start : start + 20].tobytes()
        ident, flags_frag = struct.unpack_from('>HH', header, 4)
        key = (header[12:20], ident)
        more = bool(flags_frag & 0x2000)
        offset = (flags_frag & 0x1FFF) * 8
        groups.setdefault(key, []).append((offset, int(r), more, True))
    out = bytearray()
    found = []
    for parts in groups.values():
        parts.sort()
        data = bytearray()
        complete = parts[0][0] == 0 and not parts[-1][2]
        for offset, r, _, _ in parts:
            if offset != len(data):
                complete = False
                break
            start = int(l3[r] + ihl[r])
            data += buf[start : int(l3[r] + total[r])].tobytes()
        if not complete or len(data) < 8:
            continue
        src, dst, udp_length = struct.unpack_from('>HHH', data, 0)
        if udp_length < 8 or udp_length > len(data):
            continue
        last = max(p[1] for p in parts)
        found.append((min(p[1] for p in parts), len(out), udp_length - 8, src, dst, int(stamps[last])))
        out += data[8:udp_length]
    return out, found


def read_udp(path: str | Path) -> UdpDatagrams:
    """Every IPv4/UDP datagram of the classic pcap file ``path``, in capture order.

    Capture timestamps are converted to integer nanoseconds since the epoch. Raises :class:`PcapError` for
    files that are not classic pcap (pcapng included) or use an unsupported link type.
    """
    path = Path(path)
    if path.stat().st_size < 24:
        raise PcapError(f'{path}: too short for a pcap file')
    buf = np.memmap(path, dtype=np.uint8, mode='r')
    magic = int(np.frombuffer(buf[:4], '<u4')[0])
    if magic == _PCAPNG_MAGIC:
        raise PcapError(f'{path} is pcapng; convert it to classic pcap first: editcap -F pcap IN OUT')
    if magic not in _MAGIC:
        raise PcapError(f'{path}: not a pcap file (magic 0x{magic:08x})')
    order, frac_ns = _MAGIC[magic]
    linktype = struct.unpack_from(order + 'I', buf[:24].tobytes(), 20)[0] & 0x0FFFFFFF
    data, caplen, secs, fracs = _record_index(buf, order)
    stamps = secs * 1_000_000_000 + fracs * frac_ns
    empty = np.zeros(0, dtype=np.int64)
    if data.size == 0:
        return UdpDatagrams(
            [buf],
            empty.astype(np.uint8),
            empty,
            empty,
            empty,
            empty.astype(np.uint16),
            empty.astype(np.uint16),
            linktype,
        )
    l3, is_ipv4 = _network_offsets(buf, linktype, data, caplen, order)
    end = data + caplen
    ok = is_ipv4 & (l3 + 20 <= end)
    at = np.where(ok, l3, 0)
    ihl = (buf[at] & 0x0F).astype(np.int64) * 4
    total = _be16(buf, at + 2)
    protocol = buf[at + 9]
    flags_frag = _be16(buf, at + 6)
    fragmented = (flags_frag & 0x3FFF) != 0  # more-fragments flag or a non-zero fragment offset
    ok &= (protocol == _UDP) & (ihl >= 20) & (total >= ihl)
    # Some capture writers (VeloView's position packets) leave a wrong, too large IPv4 total length: an
    # unfragmented datagram is accepted when its UDP length fits in the bytes actually captured.
    available = np.minimum(total, end - l3)
    whole = ok & ~fragmented & (available >= ihl + 8)
    udp = np.where(whole, l3 + ihl, 0)
    udp_length = _be16(buf, udp + 4)
    whole &= (udp_length >= 8) & (udp_length <= available - ihl)
    ok &= fragmented & (l3 + total <= end) | whole
    rows = np.flatnonzero(whole)
    offsets, lengths = udp[rows] + 8, udp_length[rows] - 8
    src, dst = _be16(buf, udp[rows]), _be16(buf, udp[rows] + 2)
    record_of = rows
    buffer_ids = np.zeros(rows.size, dtype=np.uint8)
    stamps_out = stamps[rows]
    buffers: list[np.ndarray] = [buf]
    n_fragments = int((ok & fragmented).sum())
    if n_fragments:
        extra, found = _reassemble(buf, np.flatnonzero(ok & fragmented), l3, ihl, total, stamps)
        if found:
            buffers.append(np.frombuffer(bytes(extra), dtype=np.uint8))
            f = np.array(found, dtype=np.int64)
            record_of = np.concatenate([record_of, f[:, 0]])
            offsets = np.concatenate([offsets, f[:, 1]])
            lengths = np.concatenate([lengths, f[:, 2]])
            src = np.concatenate([src, f[:, 3]])
            dst = np.concatenate([dst, f[:, 4]])
            stamps_out = np.concatenate([stamps_out, f[:, 5]])
            buffer_ids = np.concatenate([buffer_ids, np.ones(len(found), dtype=np.uint8)])
        order_idx = np.argsort(record_of, kind='stable')
        offsets, lengths, src, dst, stamps_out, buffer_ids = (
            a[order_idx] for a in (offsets, lengths, src, dst, stamps_out, buffer_ids)
        )
    skipped = int(data.size - rows.size - n_fragments)
    return UdpDatagrams(
        buffers,
        buffer_ids,
        offsets.astype(np.int64),
        lengths.astype(np.int64),
        stamps_out.astype(np.int64),
        src.astype(np.uint16),
        dst.astype(np.uint16),
        linktype,
        skipped,
    )
