"""Recordings other than bags (lego_loam_py.inputs): the kind guessed from the path, KITTI sequences and scan
folders exported by the simulator giving the bag's trajectory, point files, pcaps without a convert step, clear
errors that name the file."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.core.params import Params
from lego_loam_py.inputs import ImuSample, Scan, SourceError, guess_kind, open_source
from lego_loam_py.inputs.point_files import read_pcd_points, read_ply_points, read_points, write_pcd_points
from lego_loam_py.inputs.sidecars import load_ground_truth
from lego_loam_py.offline import run_bag, run_source
from lego_loam_py.sim.export import export_recording

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / 'bags' / 'campus_8s'
CLI = Path(__import__('sys').executable).parent / 'lego_loam_py'
INDOOR_PCAP = 'real/vlp16_static_indoor_20hz_pcap/vlp-16-test-90deg-1-50-frames.pcap'
SCANS = 12


@pytest.fixture(scope='module')
def exported(tmp_path_factory):
    """The committed campus recording written as a KITTI sequence and as a PCD folder."""
    root = tmp_path_factory.mktemp('exported')
    assert export_recording(BAG, root / 'kitti', 'kitti') == 80
    assert export_recording(BAG, root / 'pcd', 'pcd') == 80
    return root


def test_the_kind_is_guessed_from_the_path(exported, tmp_path, shared_data):
    assert guess_kind(BAG) == 'rosbag' and guess_kind(next(BAG.glob('*.mcap'))) == 'rosbag'
    assert guess_kind(exported / 'kitti') == 'kitti' and guess_kind(exported / 'pcd') == 'scans'
    assert guess_kind(shared_data / INDOOR_PCAP) == 'pcap'
    (tmp_path / 'notes.txt').write_text('no recording')
    with pytest.raises(SourceError, match='notes.txt: not a recording'):
        guess_kind(tmp_path / 'notes.txt')
    with pytest.raises(SourceError, match='no such file'):
        guess_kind(tmp_path / 'nothing')


def test_a_kitti_sequence_holds_the_bags_scans_stamps_and_lidar_ground_truth(exported):
    truth_stamps, truth = load_ground_truth(BAG)
    with open_source(exported / 'kitti') as kitti, open_source(BAG) as bag:
        assert kitti.kind == 'kitti' and kitti.scan_count() == 80
        stamps, poses = kitti.ground_truth()
        # times.txt starts at 0; the differences are the bag's, to the nanosecond.
        assert np.array_equal(stamps - stamps[0], truth_stamps - truth_stamps[0])
        assert np.allclose(poses, truth, atol=1e-8)  # Tr^-1 P Tr undoes the camera frame of poses.txt
        clouds = [item for item in bag.items() if isinstance(item, Scan)]
        for scan, cloud in zip(kitti.items(), clouds[:3]):
            assert set(scan.points.dtype.names) == {'x', 'y', 'z', 'intensity'}  # no ring, no time
            for axis in 'xyz':
                assert np.array_equal(scan.points[axis], cloud.points[axis])


def test_kitti_and_pcd_folders_give_the_trajectory_of_the_bag(exported):
    """The same recording as a bag, a KITTI sequence (rows from the elevations, no point times) and PCD files (every
    field): the same poses bit for bit. The folders have no IMU, so the bag runs without it."""
    expected = run_bag(BAG, Params(), imu_topic='', max_scans=SCANS, progress=False)
    for folder in ('kitti', 'pcd'):
        with open_source(exported / folder) as source:
            result = run_source(source, Params(), max_scans=SCANS, progress=False)
        assert result.counts['scans_processed'] == SCANS and result.counts['mapping_steps'] >= 2
        assert np.array_equal(np.array(result.integrated), np.array(expected.integrated)), folder
        assert np.array_equal(np.array(result.mapped), np.array(expected.mapped)), folder


def test_run_on_a_kitti_folder_reports_the_accuracy_against_poses_txt_and_writes_kitti_poses(exported, tmp_path):
    out = tmp_path / 'out'
    done = subprocess.run(
        [
            str(CLI),
            'run',
            str(exported / 'kitti'),
            '-o',
            str(out),
            '--no-progress',
            '--max-scans',
            '20',
            '--format',
            'kitti',
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert 'reading KITTI sequence' in done.stderr and 'accuracy vs ground truth: ATE RMSE' in done.stdout
    tum = np.loadtxt(out / 'trajectory.tum')
    kitti = np.loadtxt(out / 'trajectory_kitti.txt').reshape(-1, 3, 4)
    assert len(kitti) == len(tum) == 19 and np.allclose(kitti[:, :, 3], tum[:, 1:4], atol=1e-6)


def test_a_scan_folder_is_timed_by_its_rate_without_times_txt(tmp_path, exported):
    folder = tmp_path / 'scans'
    folder.mkdir()
    for k in (1, 2, 10):  # name order counts numbers as numbers: 1, 2, 10
        (folder / f'scan_{k}.pcd').write_bytes((exported / 'pcd' / f'{k:06d}.pcd').read_bytes())
    with open_source(folder, rate_hz=20) as source:
        scans = list(source.items())
        assert [s.stamp_ns for s in scans] == [0, 50_000_000, 100_000_000] and source.ground_truth() is None
        assert np.array_equal(scans[2].points, read_points(exported / 'pcd' / '000010.pcd'))


def test_missing_or_inconsistent_files_are_named(exported, tmp_path):
    import shutil

    broken = tmp_path / 'seq'
    shutil.copytree(exported / 'kitti', broken)
    (broken / 'times.txt').write_text('0.0\n0.1\n')
    with pytest.raises(SourceError, match=r'seq/times.txt lists 2 times for 80 scans'):
        open_source(broken)
    (broken / 'times.txt').unlink()
    (broken / 'poses.txt').write_text((exported / 'kitti' / 'poses.txt').read_text().split('\n', 1)[1])
    with pytest.raises(SourceError, match=r'seq/poses.txt holds 79 poses for 80 scans'):
        open_source(broken)
    (broken / 'poses.txt').unlink()
    (broken / 'calib.txt').write_text('P0: 1 0 0 0 0 1 0 0 0 0 1 0\n')
    (broken / 'poses.txt').write_text((exported / 'kitti' / 'poses.txt').read_text())
    with pytest.raises(SourceError, match=r"seq/calib.txt: no 'Tr:' line"):
        open_source(broken)
    (broken / 'velodyne' / '000005.bin').write_bytes(b'\0' * 10)
    (broken / 'calib.txt').unlink()
    with open_source(broken) as source, pytest.raises(SourceError, match='000005.bin: 10 bytes'):
        list(source.items())
    mixed = tmp_path / 'mixed'
    mixed.mkdir()
    (mixed / 'a.pcd').write_bytes((exported / 'pcd' / '000000.pcd').read_bytes())
    (mixed / 'b.bin').write_bytes((exported / 'kitti' / 'velodyne' / '000000.bin').read_bytes())
    with pytest.raises(SourceError, match='mixes scan formats'):
        open_source(mixed)
    (tmp_path / 'empty').mkdir()
    with pytest.raises(SourceError, match=r'empty: no scan files'):
        open_source(tmp_path / 'empty', 'scans')


def test_point_files_keep_every_field(tmp_path):
    points = np.zeros(
        5, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4'), ('ring', '<u2'), ('time', '<f4')]
    )
    points['x'], points['ring'], points['time'] = np.arange(5) + 0.5, [0, 3, 7, 15, 2], np.linspace(0, 0.1, 5)
    write_pcd_points(tmp_path / 'a.pcd', points)
    assert np.array_equal(read_pcd_points(tmp_path / 'a.pcd'), points)
    ascii_pcd = (
        'VERSION .7\nFIELDS x y z ring\nSIZE 4 4 4 2\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\n'
        'POINTS 2\nDATA ascii\n1.5 2 3 4\n-1 0 0.25 9\n'
    )
    (tmp_path / 'b.pcd').write_text(ascii_pcd)
    cloud = read_pcd_points(tmp_path / 'b.pcd')
    assert cloud.dtype['ring'] == np.dtype('<u2') and cloud['ring'].tolist() == [4, 9] and cloud['x'][0] == 1.5
    header = (
        'ply\nformat {}\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n'
        'property uchar intensity\nend_header\n'
    )
    (tmp_path / 'c.ply').write_text(header.format('ascii 1.0') + '1 2 3 200\n4 5 6 7\n')
    body = np.array(
        [(1, 2, 3, 200), (4, 5, 6, 7)], dtype=[('x', '>f4'), ('y', '>f4'), ('z', '>f4'), ('intensity', 'u1')]
    )
    (tmp_path / 'd.ply').write_bytes(header.format('binary_big_endian 1.0').encode() + body.tobytes())
    little = body.astype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', 'u1')])
    (tmp_path / 'f.ply').write_bytes(header.format('binary_little_endian 1.0').encode() + little.tobytes())
    for name in ('c.ply', 'd.ply', 'f.ply'):
        cloud = read_ply_points(tmp_path / name)
        assert cloud['z'].tolist() == [3, 6] and cloud['intensity'].tolist() == [200, 7], name
        assert cloud.dtype['x'] == np.dtype('<f4') and cloud.flags.writeable, name
    (tmp_path / 'g.ply').write_bytes(header.format('binary_little_endian 1.0').encode() + little.tobytes()[:-3])
    with pytest.raises(SourceError, match='g.ply: truncated: 2 vertices'):
        read_ply_points(tmp_path / 'g.ply')
    (tmp_path / 'e.pcd').write_bytes(ascii_pcd.replace('DATA ascii', 'DATA binary').split('1.5')[0].encode() + b'\0')
    with pytest.raises(SourceError, match='e.pcd: truncated'):
        read_pcd_points(tmp_path / 'e.pcd')
    # Binary records after a header of odd length (misaligned in the file) come back exact, aligned and writable.
    binary = ascii_pcd.replace('DATA ascii\n1.5 2 3 4\n-1 0 0.25 9\n', 'DATA binary\n').replace(
        'VERSION .7', 'VERSION 0.7 '
    )
    records = np.array(
        [(1.5, 2, 3, 4), (-1, 0, 0.25, 9)], dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('ring', '<u2')]
    )
    (tmp_path / 'h.pcd').write_bytes(binary.encode() + records.tobytes())
    cloud = read_pcd_points(tmp_path / 'h.pcd')
    assert (
        len(binary) % 2 == 1 and cloud.tobytes() == records.tobytes() and cloud.flags.aligned and cloud.flags.writeable
    )


def test_a_velodyne_pcap_runs_without_a_convert_step_and_decodes_as_convert_does(shared_data, tmp_path):
    """The real VLP-16 capture (early firmware: its packets claim HDL-32E) read directly gives the rotations
    ``convert --model VLP-16`` writes, and ``run`` goes through all 50 without a convert step."""
    from lego_loam_py.bag.convert import ConvertOptions, convert

    pcap = shared_data / INDOOR_PCAP
    with open_source(pcap) as source, pytest.raises(SourceError, match='--model VLP-16'):
        next(iter(source.items()))
    convert(pcap, tmp_path / 'converted', ConvertOptions(model='VLP-16'))
    with open_source(pcap, model='VLP-16') as direct, open_source(tmp_path / 'converted') as bag:
        ours = [item for item in direct.items() if isinstance(item, Scan)]
        theirs = [item for item in bag.items() if isinstance(item, Scan)]
    assert len(ours) == len(theirs) == 50
    assert [s.stamp_ns for s in ours] == [s.stamp_ns for s in theirs]
    assert all(np.array_equal(a.points, b.points) for a, b in zip(ours, theirs))
    done = subprocess.run(
        [str(CLI), 'run', str(pcap), '--model', 'VLP-16', '-o', str(tmp_path / 'out'), '--no-progress'],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert 'scans in 50, processed 50, dropped 0' in done.stdout
    assert len(np.loadtxt(tmp_path / 'out' / 'trajectory.tum')) == 49


def test_an_ouster_pcap_gives_scans_and_imu_samples_in_time_order(shared_data):
    pcap = shared_data / 'real' / 'ouster_os128_pcaps_with_imu' / 'OS-1-128_v2.3.0_1024x10_lb_n3.pcap'
    with open_source(pcap) as source:
        assert source.metadata.name == 'OS-1-128_v2.3.0_1024x10.json'  # found beside the pcap
        items = list(source.items())
    scans = [i for i in items if isinstance(i, Scan)]
    imu = [i for i in items if isinstance(i, ImuSample)]
    assert len(scans) >= 2 and len(imu) >= 20
    received = [i.received_ns for i in items]
    assert received == sorted(received)
    # The specific force of gravity in m/s^2 (this unit reads 10.6-11.2: a handheld capture, not g units).
    assert all(abs(np.linalg.norm(i.sample[3]) - 9.81) < 2.0 for i in imu)


def test_a_bag_whose_only_cloud_topic_is_not_the_default_is_read(tmp_path, capsys):
    from lego_loam_py.bag.io import BagReader, BagWriter

    bag = tmp_path / 'renamed'
    with BagReader(BAG) as reader, BagWriter(bag) as writer:
        for k, message in enumerate(reader.messages(topics=['/velodyne_points'])):
            if k == 3:
                break
            writer.write_raw('/points', message.msgtype, message.timestamp, message.data)
    with open_source(bag) as source:
        assert source.cloud_topic == '/points' and source.imu_topic is None
        assert source.notes == ['clouds from /points, the only PointCloud2 topic']
        assert sum(isinstance(i, Scan) for i in source.items()) == 3
    from lego_loam_py.bag.io import BagError

    with pytest.raises(BagError, match='no /velodyne_points topic'):  # (a topic asked for is never replaced)
        open_source(bag, cloud_topic='/velodyne_points')
