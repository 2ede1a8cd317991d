"""The pure helpers of benchmarks/real_data.py and its KISS-ICP runner, without KISS-ICP or the network: the
runner's PCD reader and TUM writer, and the time-shift diagnostic on synthetic trajectories."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lego_loam_py.formats import read_tum
from lego_loam_py.inputs.point_files import read_pcd_points

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'benchmarks'))
import kiss_icp_runner  # noqa: E402
import real_data  # noqa: E402


def tiny_points() -> np.ndarray:
    """Five points with a field before x, a two-value field, intensity and a float64 time."""
    dtype = np.dtype(
        [
            ('ring', '<u2'),
            ('x', '<f4'),
            ('y', '<f4'),
            ('z', '<f4'),
            ('normal', '<f4', (2,)),
            ('intensity', '<f4'),
            ('time', '<f8'),
        ]
    )
    points = np.zeros(5, dtype=dtype)
    points['ring'] = [3, 1, 4, 1, 5]
    points['x'], points['y'], points['z'] = [1.5, -2.25, 3, 0.125, 7], [0, 1, -1, 2.5, 9], [-0.5, 0.25, 4, 8, -3]
    points['normal'] = [[0.1, 0.2]] * 5
    points['intensity'] = [10, 20, 30, 40, 50]
    points['time'] = [0.0, 0.01, 0.02, 0.05, 0.0999]
    return points


def pcd_header(points: np.ndarray, data: str) -> bytes:
    return (
        '# .PCD v0.7\nVERSION 0.7\nFIELDS ring x y z normal intensity time\nSIZE 2 4 4 4 4 4 8\n'
        'TYPE U F F F F F F\nCOUNT 1 1 1 1 2 1 1\n'
        f'WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA {data}\n'
    ).encode()


def test_the_runner_reads_x_y_z_and_the_time_of_binary_and_ascii_pcd(tmp_path):
    points = tiny_points()
    binary = tmp_path / 'binary.pcd'
    binary.write_bytes(pcd_header(points, 'binary') + points.tobytes())
    ascii_file = tmp_path / 'ascii.pcd'
    rows = [
        f'{p["ring"]} {p["x"]} {p["y"]} {p["z"]} {p["normal"][0]} {p["normal"][1]} {p["intensity"]} '
        f'{float(p["time"])!r}'
        for p in points
    ]
    ascii_file.write_bytes(pcd_header(points, 'ascii') + ('\n'.join(rows) + '\n').encode())
    expected = np.column_stack([points['x'], points['y'], points['z']]).astype(np.float64)
    for path in (binary, ascii_file):
        xyz, times = kiss_icp_runner.read_scan(path)
        assert xyz.dtype == np.float64 and xyz.shape == (5, 3)
        assert np.array_equal(xyz, expected), path
        assert np.allclose(times, points['time'], rtol=0, atol=1e-12), path
    # Without a time field: no per-point times, as KISS-ICP's loaders give for KITTI scans.
    plain = tmp_path / 'plain.pcd'
    kiss_icp_runner.write_pcd(plain, expected)
    xyz, times = kiss_icp_runner.read_pcd(plain)
    assert np.array_equal(xyz, expected) and times.shape == (0,)


def test_pcd_written_for_kiss_icp_reads_the_same_in_lego_loam_py(tmp_path):
    """The scans written out for KISS-ICP (recordings it cannot read directly) hold what the project's reader
    sees: the same x y z and time."""
    points = tiny_points()
    path = tmp_path / 'out.pcd'
    kiss_icp_runner.write_pcd(path, np.column_stack([points['x'], points['y'], points['z']]), points['time'])
    ours = read_pcd_points(path)
    for name in ('x', 'y', 'z', 'time'):
        assert np.array_equal(ours[name], points[name]), name


def test_a_pcd_the_runner_cannot_read_is_an_error(tmp_path):
    points = tiny_points()
    path = tmp_path / 'compressed.pcd'
    path.write_bytes(pcd_header(points, 'binary_compressed') + b'\0' * 16)
    with pytest.raises(ValueError, match='binary_compressed'):
        kiss_icp_runner.read_pcd(path)
    short = tmp_path / 'short.pcd'
    short.write_bytes(pcd_header(points, 'binary') + points.tobytes()[:-3])
    with pytest.raises(ValueError, match='truncated'):
        kiss_icp_runner.read_pcd(short)


def test_the_tum_writer_keeps_stamps_exact_and_poses_to_a_micrometre():
    rotations = Rotation.random(200, random_state=3).as_matrix()
    # Half turns (w = 0) and the identity, where a quaternion from a matrix is easiest to get wrong.
    rotations[:4] = [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)]
    poses = np.tile(np.eye(4), (len(rotations), 1, 1))
    poses[:, :3, :3] = rotations
    poses[:, :3, 3] = np.random.default_rng(3).uniform(-500, 500, (len(rotations), 3))
    stamps = 1317042145964000000 + np.arange(len(rotations), dtype=np.int64) * 103_000_001
    stamps[1] = 1317042146074000000
    text = kiss_icp_runner.tum_text(stamps, poses)
    assert text.splitlines()[1].startswith('1317042146.074000000 ')
    quats = np.array([line.split()[4:] for line in text.splitlines()], dtype=float)
    assert (quats[:, 3] >= 0).all() and np.allclose(np.linalg.norm(quats, axis=1), 1.0, atol=1e-8)
    with_stamps, read = read_tum_text(text)
    assert np.array_equal(with_stamps, stamps)
    assert np.abs(read[:, :3, 3] - poses[:, :3, 3]).max() <= 5e-7
    assert np.abs(read[:, :3, :3] - rotations).max() < 1e-8


def read_tum_text(text: str):
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / 'trajectory.tum'
        path.write_text(text)
        return read_tum(path)


def wavy_drive(times_s: np.ndarray) -> np.ndarray:
    """Poses of a drive at ``times_s``: forward speed between 3 and 13 m/s, weaving left and right, the vehicle
    facing where it goes; nothing a rigid alignment could turn into a time shift."""
    x = 8.0 * times_s - 5.0 * np.sin(0.9 * times_s) / 0.9
    y = 12.0 * np.sin(0.35 * times_s)
    z = 0.4 * np.sin(0.5 * times_s)
    heading = np.arctan2(12.0 * 0.35 * np.cos(0.35 * times_s), 8.0 - 5.0 * np.cos(0.9 * times_s))
    poses = np.tile(np.eye(4), (len(times_s), 1, 1))
    poses[:, :3, :3] = Rotation.from_euler('z', heading[:, None]).as_matrix()
    poses[:, :3, 3] = np.column_stack([x, y, z])
    return poses


def test_a_trajectory_stamped_late_is_found_at_the_opposite_shift():
    """Poses that describe instants 0.05 s before their stamps (and sit in another frame) are best at -0.05 s;
    an exact estimate is best at 0."""
    truth_stamps = np.arange(0, 300, dtype=np.int64) * 100_000_000 + 1_000_000_000_000
    truth = (truth_stamps, wavy_drive((truth_stamps - truth_stamps[0]) * 1e-9))
    instants = truth_stamps[5:-5] + 37_000_000  # the estimate's own instants, between the reference's
    frame = np.eye(4)
    frame[:3, :3] = Rotation.from_euler('xyz', [0.02, -0.01, 1.2]).as_matrix()
    frame[:3, 3] = [4.0, -7.0, 0.5]
    poses = frame @ wavy_drive((instants - truth_stamps[0]) * 1e-9)

    late = real_data.time_shift_scan(truth, (instants + 50_000_000, poses))
    assert late['best_shift_s'] == pytest.approx(-0.05, abs=0.0101)
    assert late['best_ate_m'] < 0.2 * late['ate_at_zero_m']
    assert late['poses'] == len(instants)
    assert late['shifts_s'][0] == -0.12 and late['shifts_s'][-1] == 0.12 and len(late['shifts_s']) == 25

    exact = real_data.time_shift_scan(truth, (instants, poses))
    assert exact['best_shift_s'] == pytest.approx(0.0, abs=0.0101)
    assert exact['ate_at_zero_m'] < 0.02


def test_poses_are_interpolated_linearly_and_by_slerp():
    stamps = np.array([0, 1_000_000_000], dtype=np.int64)
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[1, :3, :3] = Rotation.from_euler('z', 90, degrees=True).as_matrix()
    poses[1, :3, 3] = [2.0, -4.0, 1.0]
    middle = real_data.interpolate_poses(stamps, poses, np.array([250_000_000]))[0]
    assert np.allclose(middle[:3, 3], [0.5, -1.0, 0.25])
    assert np.allclose(Rotation.from_matrix(middle[:3, :3]).as_euler('xyz', degrees=True), [0, 0, 22.5])


def test_the_readme_row_holds_the_median_figures():
    runs = [
        dict(run=k, ate_m=a, rpe_percent=r, cpu_ms_per_scan=c, x_realtime=x, note='text')
        for k, a, r, c, x in ((1, 0.07, 0.8, 120.0, 0.8), (2, 0.05, 0.6, 100.0, 1.0), (3, 0.06, 0.7, 300.0, 0.2))
    ]
    median = real_data.median_summary(runs)
    assert median == {'ate_m': 0.06, 'rpe_percent': 0.7, 'cpu_ms_per_scan': 120.0, 'x_realtime': 0.8}
    row = real_data.markdown_row('drive', 105.54, median, dict(median, ate_m=0.142, cpu_ms_per_scan=104.2))
    assert row == ('| drive | 105.5 m | 0.060 m / 0.70 % | 0.142 m / 0.70 % | 120 ms / 104 ms | 0.80x / 0.80x |')
    assert row.count('|') == real_data.MARKDOWN_HEADER.splitlines()[0].count('|')
