"""Real recordings -> PointCloud2 bags: the VLP-16 decoder reproduces the golden inputs of the C++ original
bit for bit, the Ouster decoder gives 128 plausible rings, the pcap reader copes with real-world captures
and ``lego_loam_py convert`` writes bags that read back (ROS 2 and ROS 1).

Recordings are read from ../shared/data (``shared_data`` fixture); outputs go to tmp_path.
"""

from __future__ import annotations

import struct
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.bag.convert import ConvertError, ConvertOptions, convert, velodyne_bag_packets
from lego_loam_py.bag.io import BagReader, cloud_msg_to_array
from lego_loam_py.core.pointcloud import VELODYNE_PACKED_DTYPE, VELODYNE_POINT_DTYPE
from lego_loam_py.sensors.ouster import OusterDecoder, OusterMetadata
from lego_loam_py.sensors.pcap import read_udp
from lego_loam_py.sensors.velodyne import (
    PACKET_SIZE,
    VLP16_ELEVATION_DEG,
    VelodyneFormatError,
    Vlp16Decoder,
    decode_vlp16,
)

CLI = str(Path(sys.executable).parent / 'lego_loam_py')
SINGLE_PCAP = 'real/vlp16_single_rotation_pcap/velodyne_example.pcap'
INDOOR_PCAP = 'real/vlp16_static_indoor_20hz_pcap/vlp-16-test-90deg-1-50-frames.pcap'
DUAL_BAG = 'real/vlp16_dual_return_4scans_rosbag2/1673400471837873222'
DUAL_PCD = 'real/vlp16_dual_return_4scans_rosbag2/1673400472138016708.pcd'
OUSTER = 'real/ouster_os128_pcaps_with_imu'
OS1_PCAP, OS1_JSON = 'OS-1-128_v2.3.0_1024x10_lb_n3.pcap', 'OS-1-128_v2.3.0_1024x10.json'
OS0_PCAP, OS0_JSON = 'OS-0-128-U1_v2.3.0_1024x10.pcap', 'OS-0-128-U1_v2.3.0_1024x10.json'

# golden name -> (decoder options that reproduce how the golden inputs were made)
GOLDEN = {
    'vlp16_single_rotation': dict(split='start'),
    'vlp16_static_indoor_20hz': dict(force_model=True, restamp_period_ns=100_000_000),
    'vlp16_dual_return_4scans': dict(),
}
FIELDS = ('x', 'y', 'z', 'intensity', 'ring', 'time')


def pcap_packets(path: Path) -> tuple[np.ndarray, np.ndarray]:
    udp = read_udp(path)
    data = udp.select((udp.dst_ports == 2368) & (udp.lengths == PACKET_SIZE))
    return data.gather(PACKET_SIZE), data.stamps_ns


def bag_packets(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with BagReader(path) as reader:
        chunks = list(velodyne_bag_packets(reader, '/velodyne_packets'))
    return np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks])


@pytest.fixture(scope='module')
def packets(shared_data):
    """Raw packets and capture stamps of the three VLP-16 recordings, by golden name."""
    return {
        'vlp16_single_rotation': pcap_packets(shared_data / SINGLE_PCAP),
        'vlp16_static_indoor_20hz': pcap_packets(shared_data / INDOOR_PCAP),
        'vlp16_dual_return_4scans': bag_packets(shared_data / DUAL_BAG),
    }


@pytest.fixture(scope='module')
def decoded(packets):
    return {name: decode_vlp16(*packets[name], **GOLDEN[name]) for name in GOLDEN}


def as_columns(points: np.ndarray) -> np.ndarray:
    """(n, 6) float32 x, y, z, intensity, ring, time, the golden npz layout."""
    return np.stack([points[f].astype(np.float32) for f in FIELDS], axis=1)


# ------------------------------------------------------------------------------------------ golden parity
@pytest.mark.parametrize('name', list(GOLDEN))
def test_decoding_equals_golden_inputs_bit_for_bit(shared_data, decoded, name):
    golden = np.load(shared_data / 'golden' / f'{name}.npz')
    rotations = decoded[name]
    n = len(golden['stamps'])
    assert len(rotations) >= n
    for k in range(n):
        expected = golden[f's{k}_input']
        got = as_columns(rotations[k].points)
        assert got.shape == expected.shape, f'rotation {k}: {got.shape} vs {expected.shape}'
        equal = (got.view(np.uint32) == expected.view(np.uint32)).all(axis=1)
        assert equal.all(), f'rotation {k}: {np.count_nonzero(~equal)} of {len(equal)} points differ'
        assert rotations[k].stamp_ns == golden['stamps'][k]
        assert rotations[k].first_firing_ns == golden['orig_stamps'][k]
        assert rotations[k].first_azimuth_deg == golden['input_first_azimuth_deg'][k]
        assert rotations[k].last_azimuth_deg == golden['input_last_azimuth_deg'][k]
        if f's{k}_input_return_block' in golden:
            assert np.array_equal(rotations[k].return_block, golden[f's{k}_input_return_block'])


@pytest.mark.parametrize('name', list(GOLDEN))
def test_streaming_in_small_chunks_gives_the_same_rotations(packets, decoded, name):
    data, stamps = packets[name]
    small = decode_vlp16(data, stamps, chunk=7, **GOLDEN[name])
    assert len(small) == len(decoded[name])
    for a, b in zip(small, decoded[name]):
        assert a.stamp_ns == b.stamp_ns and np.array_equal(a.points, b.points)


def test_twenty_hz_recording_without_restamping_keeps_the_true_first_firings(shared_data, packets):
    golden = np.load(shared_data / 'golden' / 'vlp16_static_indoor_20hz.npz')
    rotations = decode_vlp16(*packets['vlp16_static_indoor_20hz'], force_model=True)
    assert [r.stamp_ns for r in rotations[:20]] == golden['orig_stamps'].tolist()
    assert len(rotations) == 50  # 50 full rotations; the fragments before the first and after the last wrap dropped
    assert np.allclose(np.diff([r.stamp_ns for r in rotations]) / 1e9, 0.05, atol=0.001)


def test_hdl32e_product_byte_needs_the_forced_model(packets):
    with pytest.raises(VelodyneFormatError, match='force the model'):
        decode_vlp16(*packets['vlp16_static_indoor_20hz'])


def test_wrap_split_of_the_single_rotation_capture_keeps_no_complete_rotation(packets):
    # The capture starts at 234 deg and wraps once: no wrap-to-wrap rotation, the start split is needed.
    assert decode_vlp16(*packets['vlp16_single_rotation']) == []
    fragments = decode_vlp16(*packets['vlp16_single_rotation'], min_completeness=0.5)
    assert len(fragments) == 1 and fragments[0].first_azimuth_deg < 0.5 and fragments[0].completeness < 0.8


# ------------------------------------------------------------------------------------------ geometry and time
@pytest.mark.parametrize('name', list(GOLDEN))
def test_sixteen_rings_at_the_vlp16_elevations(packets, decoded, name):
    data = packets[name][0]
    # Laser 0 (-15 deg, ring 0) of the dual-return recording never returns (raw distance 0 in every packet:
    # the beam hits the sensor's mount); all other lasers do.
    laser_has_returns = (
        (data[:, :1200].reshape(-1, 12, 100)[:, :, 4:].reshape(-1, 12, 2, 16, 3)[..., :2] != 0)
        .any(axis=-1)
        .any(axis=(0, 1, 2))
    )
    expected_rings = set(range(16)) if name != 'vlp16_dual_return_4scans' else set(range(1, 16))
    assert set(np.flatnonzero(laser_has_returns) // 2 + 8 * (np.flatnonzero(laser_has_returns) % 2)) == expected_rings
    for rotation in decoded[name]:
        p = rotation.points
        assert set(np.unique(p['ring']).tolist()) == expected_rings
        elevation = np.degrees(np.arctan2(p['z'].astype(float), np.hypot(p['x'].astype(float), p['y'].astype(float))))
        expected = np.sort(VLP16_ELEVATION_DEG)[p['ring']]
        assert np.abs(elevation - expected).max() < 0.05
        assert np.array_equal(expected, -15.0 + 2.0 * p['ring'])


@pytest.mark.parametrize(
    'name, sweep',
    [('vlp16_single_rotation', 0.1), ('vlp16_static_indoor_20hz', 0.05), ('vlp16_dual_return_4scans', 0.1)],
)
def test_point_times_increase_within_each_sweep(decoded, name, sweep):
    for rotation in decoded[name]:
        t = rotation.points['time']
        assert t.min() >= 0.0
        assert t.max() == pytest.approx(sweep, abs=0.002)
        # Single return: message order is firing order. Dual return: each block of a pair in firing order.
        for block in np.unique(rotation.return_block):
            assert (np.diff(t[rotation.return_block == block]) >= 0).all()
        assert rotation.duration == pytest.approx(sweep, abs=0.002)


def read_pcd(path: Path) -> np.ndarray:
    """Binary PCD (v0.7) as a structured array."""
    raw = path.read_bytes()
    end = raw.index(b'DATA binary\n') + len(b'DATA binary\n')
    header = dict(line.split(' ', 1) for line in raw[:end].decode().splitlines() if not line.startswith('#'))
    names, sizes, types = header['FIELDS'].split(), header['SIZE'].split(), header['TYPE'].split()
    dtype = np.dtype([(n, '<' + {'F': 'f', 'U': 'u', 'I': 'i'}[t] + s) for n, s, t in zip(names, sizes, types)])
    return np.frombuffer(raw[end:], dtype=dtype, count=int(header['POINTS']))


def test_dual_return_matches_the_reference_pcd_after_its_filter(shared_data, decoded):
    """The .pcd (nebula's decoding of the last scan) drops the second block of a pair when it repeats the
    first (one echo) and ranges < 0.5 m; it also cuts its scan at slightly different azimuths. Within its
    azimuth window, our last rotation after exactly that rule has its point count and (ring, distance)
    multiset."""
    pcd = read_pcd(shared_data / DUAL_PCD)
    rotation = decoded['vlp16_dual_return_4scans'][-1]
    p = rotation.points
    distance_raw = np.round(np.sqrt(p['x'].astype(float) ** 2 + p['y'] ** 2 + p['z'] ** 2) / 0.002).astype(int)
    # A second-block point repeats the first block when the same laser of the same firing has the same range.
    first = rotation.return_block == 0
    key = np.stack([np.round(p['time'] / 1e-9).astype(np.int64), p['ring']], axis=1)
    first_range = {tuple(k): d for k, d in zip(key[first].tolist(), distance_raw[first].tolist())}
    duplicate = np.array(
        [
            b == 1 and first_range.get(tuple(k)) == d
            for b, k, d in zip(rotation.return_block.tolist(), key.tolist(), distance_raw.tolist())
        ]
    )
    kept = ~duplicate & (distance_raw * np.float32(0.002) >= np.float32(0.5))
    azimuth = np.round(np.degrees(np.arctan2(-p['y'].astype(float), p['x'].astype(float))) % 360 * 100).astype(int)
    pcd_azimuth = np.round(np.degrees(pcd['azimuth'].astype(float)) * 100).astype(int)
    window = (azimuth >= pcd_azimuth.min()) & (azimuth <= pcd_azimuth.max())
    assert np.count_nonzero(kept & window) == len(pcd) == 14831
    ours = Counter(zip(p['ring'][kept & window].tolist(), distance_raw[kept & window].tolist()))
    theirs = Counter(zip(pcd['channel'].tolist(), np.round(pcd['distance'] / 0.002).astype(int).tolist()))
    assert ours == theirs
    # about half of all points are one-echo duplicates; the window only trims the two ends of the sweep
    assert 0.45 < duplicate.mean() < 0.55
    assert np.count_nonzero(kept & ~window) < 0.01 * len(pcd)


# ------------------------------------------------------------------------------------------ Ouster
@pytest.fixture(scope='module')
def ouster_bags(shared_data, tmp_path_factory):
    out = tmp_path_factory.mktemp('ouster')
    folder = shared_data / OUSTER
    summaries = {
        'os1': convert(folder / OS1_PCAP, out / 'os1', ConvertOptions()),  # metadata found beside the pcap
        'os0': convert(
            folder / OS0_PCAP, out / 'os0.bag', ConvertOptions(metadata=folder / OS0_JSON, ros1=True, layout='packed')
        ),
    }
    return out, summaries


def test_ouster_scans_have_128_rings_and_plausible_geometry(shared_data, ouster_bags):
    out, summaries = ouster_bags
    assert summaries['os1'].rotations == 3 and summaries['os0'].rotations == 1
    for bag, json_name in [(out / 'os1', OS1_JSON), (out / 'os0.bag', OS0_JSON)]:
        meta = OusterMetadata.from_json(shared_data / OUSTER / json_name)
        with BagReader(bag) as reader:
            clouds = [reader.deserialize(m) for m in reader.messages(['/velodyne_points'])]
        stamps = [c.header.stamp.sec * 10**9 + c.header.stamp.nanosec for c in clouds]
        assert np.allclose(np.diff(stamps) / 1e9, 0.1, atol=0.001)
        for cloud in clouds:
            assert cloud.header.frame_id == 'os_sensor'
            p = cloud_msg_to_array(cloud)
            assert p.size > 0.7 * 128 * 1024
            assert np.array_equal(np.unique(p['ring']), np.arange(128))
            r = np.sqrt(p['x'].astype(float) ** 2 + p['y'] ** 2 + p['z'] ** 2)
            assert r.min() > 0.0 and r.max() < 0x7FFF * 8e-3 + 0.1  # low-bandwidth profile: 15 bits of 8 mm
            # Ring 0 is the lowest beam: seen from its beam origin (undo lidar_to_sensor, then step back the
            # lidar_origin_to_beam_origin offset), every point lies at its beam's altitude angle.
            transform = meta.lidar_to_sensor_transform
            xyz = np.stack([p['x'], p['y'], p['z']], axis=1).astype(float)
            lidar = (xyz - transform[:3, 3] / 1000.0) @ transform[:3, :3]
            beam_azimuth = -np.radians(meta.beam_azimuth_angles[127 - p['ring']])
            beam = lidar
            for _ in range(3):  # encoder angle = azimuth of the ray from the beam origin - the beam's azimuth
                encoder = np.arctan2(beam[:, 1], beam[:, 0]) - beam_azimuth
                beam = lidar - meta.lidar_origin_to_beam_origin_mm / 1000.0 * np.stack(
                    [np.cos(encoder), np.sin(encoder), np.zeros_like(encoder)], axis=1
                )
            elevation = np.degrees(np.arcsin(beam[:, 2] / np.linalg.norm(beam, axis=1)))
            expected = meta.beam_altitude_angles[127 - p['ring']]
            usable = r > 0.5
            assert np.abs(elevation - expected)[usable].max() < 0.001  # deg; float32 rounding only
            ring_median = np.array([np.median(elevation[usable & (p['ring'] == k)]) for k in range(128)])
            assert (np.diff(ring_median) > 0).all()
            t = p['time']
            assert t.min() == 0.0 and 0.095 < t.max() < 0.1 and (np.diff(t) >= 0).all()


def test_ouster_imu_packets_become_imu_messages(ouster_bags):
    out, summaries = ouster_bags
    assert summaries['os1'].imu_messages == 30
    with BagReader(out / 'os1') as reader:
        imus = [reader.deserialize(m) for m in reader.messages(['/imu/data'])]
        tf = [reader.deserialize(m) for m in reader.messages(['/tf_static'])]
    assert len(imus) == 30 and imus[0].header.frame_id == 'os_imu'
    assert tf[0].transforms[0].child_frame_id == 'os_imu' and tf[0].transforms[0].header.frame_id == 'os_sensor'
    stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in imus])
    assert np.allclose(np.diff(stamps) / 1e9, 0.01, atol=0.0005)  # 100 Hz
    gravity = [
        np.linalg.norm([m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]) for m in imus
    ]
    assert 8.0 < np.mean(gravity) < 12.0
    assert all(abs(m.angular_velocity.z) < 0.5 for m in imus) and imus[0].orientation_covariance[0] == -1.0


def test_ouster_geometry_conventions_on_a_synthetic_packet():
    """One beam at elevation 0, no beam offset, identity extrinsics: measurement id 0 looks along +x, id W/4
    along -y (the encoder turns clockwise seen from above); ring 0 is the lowest beam."""
    width, height = 1024, 2
    meta = OusterMetadata.from_json(
        {
            'prod_line': 'OS-1-2',
            'beam_altitude_angles': [10.0, 0.0],
            'beam_azimuth_angles': [0.0, 0.0],
            'lidar_origin_to_beam_origin_mm': 0.0,
            'lidar_to_sensor_transform': np.eye(4).ravel().tolist(),
            'data_format': {
                'pixels_per_column': height,
                'columns_per_frame': width,
                'columns_per_packet': 16,
                'column_window': [0, width - 1],
                'udp_profile_lidar': 'RNG19_RFL8_SIG16_NIR16',
            },
        }
    )
    packets = np.zeros((width // 16, meta.lidar_packet_size), dtype=np.uint8)
    for p in range(width // 16):
        packets[p, 0:2] = [1, 0]  # packet type: lidar
        for c in range(16):
            m = p * 16 + c
            at = 32 + c * meta.column_bytes
            packets[p, at : at + 12] = np.frombuffer(struct.pack('<QHH', 10**9 + m * 97_656, m, 1), np.uint8)
            if m in (0, width // 4):
                pixel = at + 12 + 1 * 12  # beam 1 (elevation 0)
                packets[p, pixel : pixel + 8] = np.frombuffer(struct.pack('<IBBH', 2000, 7, 0, 55), np.uint8)
    scans = OusterDecoder(meta).decode(packets, np.full(len(packets), 5 * 10**18))
    assert len(scans) == 1
    p = scans[0].points
    assert np.allclose(np.stack([p['x'], p['y'], p['z']], axis=1), [[2.0, 0.0, 0.0], [0.0, -2.0, 0.0]], atol=1e-6)
    assert p['ring'].tolist() == [0, 0] and p['intensity'].tolist() == [55.0, 55.0]
    assert p['time'][1] == pytest.approx(256 * 97_656e-9)
    assert scans[0].stamp_ns == 5 * 10**18


# ------------------------------------------------------------------------------------------ pcap reader
def pcap_bytes(
    frames: list[tuple[int, bytes]], big_endian: bool = False, nanoseconds: bool = False, linktype: int = 1
) -> bytes:
    order = '>' if big_endian else '<'
    magic = 0xA1B23C4D if nanoseconds else 0xA1B2C3D4
    out = [struct.pack(order + 'IHHiIII', magic, 2, 4, 0, 0, 65535, linktype)]
    for stamp_ns, frame in frames:
        sec, rest = divmod(stamp_ns, 10**9)
        out.append(struct.pack(order + 'IIII', sec, rest if nanoseconds else rest // 1000, len(frame), len(frame)))
        out.append(frame)
    return b''.join(out)


def ipv4_udp(payload: bytes, src_port: int = 2368, dst_port: int = 2368, ident: int = 1) -> list[bytes]:
    """IPv4 packet(s) of one UDP datagram; split into fragments of 1000 bytes when longer."""
    udp = struct.pack('>HHHH', src_port, dst_port, len(payload) + 8, 0) + payload
    pieces = [udp[i : i + 1000] for i in range(0, len(udp), 1000)] if len(udp) > 1400 else [udp]
    out = []
    for k, piece in enumerate(pieces):
        flags = (0x2000 if k < len(pieces) - 1 else 0) | (k * 1000 // 8)
        out.append(
            struct.pack(
                '>BBHHHBBH4s4s',
                0x45,
                0,
                20 + len(piece),
                ident,
                flags,
                64,
                17,
                0,
                bytes([192, 168, 1, 201]),
                bytes([255, 255, 255, 255]),
            )
            + piece
        )
    return out


def test_pcap_variants_give_the_same_packets(tmp_path, packets):
    data, stamps = packets['vlp16_single_rotation']
    data, stamps = data[:30], stamps[:30]
    ethernet = b'\xff' * 6 + b'\x60\x76\x88\x00\x00\x00'
    variants = {
        'big_endian_ns_vlan': (
            dict(big_endian=True, nanoseconds=True),
            lambda ip: ethernet + b'\x81\x00\x00\x05\x08\x00' + ip,
        ),
        'linux_sll': (dict(linktype=113), lambda ip: b'\x00' * 14 + b'\x08\x00' + ip),
        'raw_ipv4': (dict(linktype=101), lambda ip: ip),
    }
    for name, (kwargs, frame) in variants.items():
        frames = [(int(t), frame(ip)) for t, d in zip(stamps, data) for ip in ipv4_udp(d.tobytes())]
        frames.insert(5, (int(stamps[5]), frame(ipv4_udp(b'\x00' * 512, 8308, 8308)[0])))  # a position packet
        path = tmp_path / f'{name}.pcap'
        path.write_bytes(pcap_bytes(frames, **kwargs))
        got, got_stamps = pcap_packets(path)
        assert np.array_equal(got, data), name
        assert np.array_equal(got_stamps, stamps), name


def test_pcap_reassembles_fragmented_datagrams(tmp_path):
    payload = np.random.default_rng(3).integers(0, 256, 8448, dtype=np.uint8).tobytes()
    fragments = ipv4_udp(payload, 7502, 7502, ident=77)
    assert len(fragments) == 9
    ethernet = b'\x00' * 12 + b'\x08\x00'
    path = tmp_path / 'fragments.pcap'
    path.write_bytes(pcap_bytes([(10**18 + k, ethernet + f) for k, f in enumerate(fragments)]))
    udp = read_udp(path)
    assert len(udp) == 1 and udp.lengths[0] == 8448 and udp.dst_ports[0] == 7502
    assert udp.payload(0) == payload and udp.gather(8448)[0].tobytes() == payload


# ------------------------------------------------------------------------------------------ robustness
def test_device_clock_hour_wrap_is_unwrapped(packets, decoded):
    data, stamps = packets['vlp16_single_rotation']
    shifted = data.copy()
    device = shifted[:, 1200:1204].copy().view('<u4').reshape(-1).astype(np.int64)
    offset = 3_600_000_000 - int(device[40])  # the device clock passes the hour at packet 40
    shifted[:, 1200:1204] = ((device + offset) % 3_600_000_000).astype('<u4').view(np.uint8).reshape(-1, 4)
    rotations = decode_vlp16(shifted, stamps, split='start')
    assert len(rotations) == 1
    assert rotations[0].stamp_ns == decoded['vlp16_single_rotation'][0].stamp_ns
    assert np.array_equal(rotations[0].points, decoded['vlp16_single_rotation'][0].points)


def test_packets_with_a_bad_block_flag_are_dropped(packets):
    data, stamps = packets['vlp16_static_indoor_20hz']
    broken = data.copy()
    broken[500, 300] = 0x00  # block 3's flag
    decoder = Vlp16Decoder(force_model=True)
    rotations = decoder.feed(broken, stamps) + decoder.finish()
    assert decoder.stats.bad_packets == 1 and decoder.stats.packets == len(data)
    assert len(rotations) == 50


def test_lost_packets_make_a_rotation_incomplete_only_beyond_the_threshold(packets, decoded):
    data, stamps = packets['vlp16_static_indoor_20hz']
    reference = decode_vlp16(data, stamps, force_model=True)
    # 20 Hz: 905 sequences of 0.4 deg per rotation, 24 per packet. Rotation 0 starts near packet 16.
    first = {r.first_firing_ns: k for k, r in enumerate(reference)}
    keep = np.ones(len(data), dtype=bool)
    keep[16 + 38 * 10 + 10] = False  # one packet (9.6 deg, 2.7 %) lost in rotation 10
    keep[16 + 38 * 20 + 5 : 16 + 38 * 20 + 25] = False  # 20 packets (190 deg) lost in rotation 20
    decoder = Vlp16Decoder(force_model=True)
    rotations = decoder.feed(data[keep], stamps[keep]) + decoder.finish()
    assert len(rotations) == 49
    kept = [first[r.first_firing_ns] for r in rotations]
    assert 20 not in kept and 10 in kept
    damaged = rotations[kept.index(10)]
    assert 0.95 < damaged.completeness < 0.98
    assert damaged.points.size < reference[10].points.size


def test_packed_layout(packets):
    rotation = decode_vlp16(*packets['vlp16_dual_return_4scans'], point_dtype=VELODYNE_PACKED_DTYPE)[0]
    assert rotation.points.dtype == VELODYNE_PACKED_DTYPE and rotation.points.dtype.itemsize == 22


# ------------------------------------------------------------------------------------------ bags and CLI
def read_clouds(path: Path) -> list[tuple[int, int, str, np.ndarray, bytes]]:
    """(bag time, header stamp, frame id, points, data bytes) of every /velodyne_points message."""
    out = []
    with BagReader(path) as reader:
        for message in reader.messages(['/velodyne_points']):
            msg = reader.deserialize(message)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            out.append((message.timestamp, stamp, msg.header.frame_id, cloud_msg_to_array(msg), bytes(msg.data)))
    return out


def test_converted_bag_reads_back_through_the_rclpy_conversion(shared_data, decoded, tmp_path):
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    from lego_loam_py.ros.conversions import cloud_msg_to_array as ros_cloud_to_array

    summary = convert(shared_data / DUAL_BAG, tmp_path / 'dual', ConvertOptions(storage='sqlite3', compress=True))
    assert summary.rotations == 4 and summary.points == [r.points.size for r in decoded['vlp16_dual_return_4scans']]
    with BagReader(tmp_path / 'dual') as reader:
        messages = list(reader.messages(['/velodyne_points']))
    assert len(messages) == 4
    for message, rotation in zip(messages, decoded['vlp16_dual_return_4scans']):
        msg = deserialize_message(message.data, PointCloud2)
        assert msg.header.frame_id == 'velodyne' and msg.point_step == VELODYNE_POINT_DTYPE.itemsize
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == rotation.stamp_ns == message.timestamp
        assert np.array_equal(ros_cloud_to_array(msg), rotation.points)


def test_ros1_raw_packet_bag_converts_like_the_ros2_one(packets, decoded, tmp_path):
    """A ROS 1 bag of velodyne_msgs/VelodyneScan (definitions stored in the bag, as rosbag records them)."""
    from rosbags.typesys import get_types_from_msg

    from lego_loam_py.bag.io import BagWriter

    data, stamps = packets['vlp16_dual_return_4scans']
    with BagWriter(tmp_path / 'raw.bag', ros1=True) as bag:
        bag.typestore.register(
            {
                **get_types_from_msg('Header header\nVelodynePacket[] packets', 'velodyne_msgs/msg/VelodyneScan'),
                **get_types_from_msg('time stamp\nuint8[1206] data', 'velodyne_msgs/msg/VelodynePacket'),
            }
        )
        T = bag.types
        for k, start in enumerate(range(0, len(data), 151)):
            part = slice(start, start + 151)
            scan = T['velodyne_msgs/msg/VelodyneScan'](
                header=bag.header(int(stamps[part][0]), 'velodyne', k),
                packets=[
                    T['velodyne_msgs/msg/VelodynePacket'](
                        stamp=T['builtin_interfaces/msg/Time'](sec=int(s // 10**9), nanosec=int(s % 10**9)), data=d
                    )
                    for d, s in zip(data[part], stamps[part])
                ],
            )
            bag.write_msg('/velodyne_packets', int(stamps[part][-1]), scan)
    convert(tmp_path / 'raw.bag', tmp_path / 'out', ConvertOptions())
    clouds = read_clouds(tmp_path / 'out')
    assert len(clouds) == 4
    for cloud, rotation in zip(clouds, decoded['vlp16_dual_return_4scans']):
        assert cloud[1] == rotation.stamp_ns and np.array_equal(cloud[3], rotation.points)


def run_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([CLI, 'convert', *map(str, args)], capture_output=True, text=True, timeout=120)


def test_cli_ros1_output_equals_the_golden_ros1_bag(shared_data, tmp_path):
    result = run_cli(shared_data / DUAL_BAG, '-o', tmp_path / 'dual.bag', '--ros1', '--layout', 'packed')
    assert result.returncode == 0, result.stderr
    assert '4 rotations' in result.stdout and '29154/29179/29234' in result.stdout
    ours = read_clouds(tmp_path / 'dual.bag')
    golden = read_clouds(shared_data / 'golden' / 'vlp16_dual_return_4scans.bag')
    assert BagReader(tmp_path / 'dual.bag').is_ros1
    assert len(ours) == len(golden) == 4
    for a, b in zip(ours, golden):
        assert a[:3] == b[:3] and a[4] == b[4]


def test_cli_restamped_20hz_equals_the_golden_ros2_bag(shared_data, tmp_path):
    result = run_cli(
        shared_data / INDOOR_PCAP,
        '-o',
        tmp_path / 'indoor',
        '--model',
        'VLP-16',
        '--restamp-period',
        '0.1',
        '--max-rotations',
        '20',
        '--layout',
        'packed',
    )
    assert result.returncode == 0, result.stderr
    ours = read_clouds(tmp_path / 'indoor')
    golden = read_clouds(shared_data / 'golden' / 'vlp16_static_indoor_20hz_ros2')
    assert len(ours) == len(golden) == 20
    for a, b in zip(ours, golden):
        assert a[:3] == b[:3] and a[4] == b[4]


def test_cli_errors_are_clear_and_leave_no_output(shared_data, tmp_path):
    result = run_cli(shared_data / INDOOR_PCAP, '-o', tmp_path / 'out')
    assert result.returncode == 1 and '--model VLP-16' in result.stderr and 'Traceback' not in result.stderr
    assert not (tmp_path / 'out').exists()
    not_lidar = tmp_path / 'empty.pcap'
    not_lidar.write_bytes(pcap_bytes([(10**18, b'\x00' * 12 + b'\x08\x00' + ipv4_udp(b'hello', 53, 53)[0])]))
    result = run_cli(not_lidar, '-o', tmp_path / 'out')
    assert result.returncode == 1 and 'no Velodyne data packets' in result.stderr and '5 B to port 53' in result.stderr
    (tmp_path / 'exists').mkdir()
    result = run_cli(shared_data / SINGLE_PCAP, '-o', tmp_path / 'exists', '--split', 'start')
    assert result.returncode == 1 and 'exists already' in result.stderr


def test_convert_single_rotation_pcap(shared_data, tmp_path):
    summary = convert(shared_data / SINGLE_PCAP, tmp_path / 'single', ConvertOptions(split='start'))
    assert summary.rotations == 1 and summary.points == [28385]
    clouds = read_clouds(tmp_path / 'single')
    assert clouds[0][1] == 1525347606362040000 and clouds[0][2] == 'velodyne'
    with pytest.raises(ConvertError, match='no such file'):
        convert(shared_data / 'real' / 'missing.pcap', tmp_path / 'x', ConvertOptions())
