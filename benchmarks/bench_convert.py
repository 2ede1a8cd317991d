"""Speed of the recording converter: VLP-16 decoding alone and pcap -> mcap end to end.

    .venv/bin/python benchmarks/bench_convert.py
Input: the 20 Hz VLP-16 pcap of ../shared/data repeated 20 times (38 040 packets, 50 s of sensor time, the
device clock continued across the copies). A VLP-16 sends 754 packets/s; target: well above real time.
"""

from __future__ import annotations

import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from lego_loam_py.bag.convert import ConvertOptions, convert
from lego_loam_py.sensors.pcap import read_udp
from lego_loam_py.sensors.velodyne import PACKET_SIZE, decode_vlp16

SHARED = Path(__file__).resolve().parents[2] / 'shared' / 'data'
PCAP = SHARED / 'real' / 'vlp16_static_indoor_20hz_pcap' / 'vlp-16-test-90deg-1-50-frames.pcap'
PACKETS_PER_SECOND = 754  # VLP-16, single return


def repeated_stream(copies: int) -> tuple[np.ndarray, np.ndarray]:
    udp = read_udp(PCAP)
    udp = udp.select((udp.dst_ports == 2368) & (udp.lengths == PACKET_SIZE))
    data, stamps = udp.gather(PACKET_SIZE), udp.stamps_ns
    device = data[:, 1200:1204].copy().view('<u4').reshape(-1).astype(np.int64)
    span_us = int(device[-1] - device[0]) + 1327
    out = np.concatenate([data] * copies)
    shifted = np.concatenate([device + k * span_us for k in range(copies)])
    out[:, 1200:1204] = (shifted % 3_600_000_000).astype('<u4').view(np.uint8).reshape(-1, 4)
    return out, np.concatenate([stamps + k * span_us * 1000 for k in range(copies)])


def write_pcap(path: Path, data: np.ndarray, stamps: np.ndarray) -> None:
    ethernet = b'\xff' * 6 + b'\x60\x76\x88\x00\x00\x00\x08\x00'
    records = [struct.pack('<IHHiIII', 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)]
    for stamp, payload in zip(stamps.tolist(), data):
        udp = struct.pack('>HHHH', 2368, 2368, PACKET_SIZE + 8, 0) + payload.tobytes()
        ip = (
            struct.pack(
                '>BBHHHBBH4s4s', 0x45, 0, 20 + len(udp), 0, 0, 64, 17, 0, b'\xc0\xa8\x01\xc9', b'\xff\xff\xff\xff'
            )
            + udp
        )
        frame = ethernet + ip
        records.append(struct.pack('<IIII', stamp // 10**9, stamp % 10**9 // 1000, len(frame), len(frame)) + frame)
    path.write_bytes(b''.join(records))


def main() -> None:
    if not PCAP.is_file():
        sys.exit(f'{PCAP} not found')
    data, stamps = repeated_stream(20)
    seconds = len(data) / PACKETS_PER_SECOND
    start = time.perf_counter()
    rotations = decode_vlp16(data, stamps, force_model=True)
    decode = time.perf_counter() - start
    print(
        f'decode only: {len(data)} packets, {len(rotations)} rotations in {decode:.2f} s = '
        f'{len(data) / decode:.0f} packets/s, {len(rotations) / decode:.0f} rotations/s, '
        f'x{seconds / decode:.0f} real time'
    )
    with tempfile.TemporaryDirectory() as folder:
        pcap = Path(folder) / 'stream.pcap'
        write_pcap(pcap, data, stamps)
        start = time.perf_counter()
        summary = convert(pcap, Path(folder) / 'out', ConvertOptions(model='VLP-16'))
        total = time.perf_counter() - start
    print(
        f'pcap -> mcap: {summary.rotations} rotations in {total:.2f} s = {len(data) / total:.0f} packets/s, '
        f'x{seconds / total:.0f} real time'
    )


if __name__ == '__main__':
    main()
