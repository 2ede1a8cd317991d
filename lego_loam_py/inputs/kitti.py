"""KITTI odometry sequences as a source, and the files of the format (read here, written for the simulator).

A sequence folder (``dataset/sequences/NN`` of the KITTI odometry benchmark) holds::

    velodyne/000000.bin ...   one HDL-64E scan per file: float32 x y z reflectance, sensor frame (REP-103 axes)
    times.txt                 one time per scan [s since the first], optional (else 10 Hz)
    calib.txt                 the cameras' projections and ``Tr``: velodyne -> left camera (cam0), 3x4, optional
    poses.txt                 ground truth, optional: cam0's pose of every scan in the first one's frame, 12
                              numbers a line (also found at ``dataset/poses/NN.txt``, where KITTI ships it)

The ground truth is the lidar's: ``Tr^-1 P_k Tr`` with ``P_k`` the camera pose of scan k (without calib.txt the
poses are taken as the lidar's). KITTI's scans have no ring and no per-point time: rows come from the beams'
elevations (``sensor.preset: HDL-64E`` carries the sensor's table) and point times from the azimuth.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from lego_loam_py.core.trajectory import Trajectory
from lego_loam_py.formats import read_kitti_poses, write_kitti_poses_atomic
from lego_loam_py.inputs.point_files import read_bin_points
from lego_loam_py.inputs.source import Scan, Source, SourceError, SourceItem

__all__ = [
    'KittiSource',
    'is_kitti_sequence',
    'read_times',
    'write_times',
    'read_calibration',
    'write_kitti_sequence_files',
    'lidar_ground_truth',
    'KITTI_VELO_TO_CAM',
]

# The axes KITTI's cam0 has relative to its velodyne (x right, y down, z forward vs x forward, y left, z up):
# the rotation of Tr without KITTI's small mounting offsets, for sequences made here.
KITTI_VELO_TO_CAM = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def is_kitti_sequence(path: Path) -> bool:
    """A folder with a ``velodyne/`` folder of ``.bin`` scans."""
    return path.is_dir() and (path / 'velodyne').is_dir() and any((path / 'velodyne').glob('*.bin'))


def read_times(path: Path, expected: int, what: str = 'scans') -> np.ndarray:
    """int64 stamps [ns] of a ``times.txt`` (one time [s] a line), checked: ``expected`` lines, increasing."""
    try:
        seconds = np.loadtxt(path, dtype=np.float64, ndmin=1)
    except ValueError as exc:
        raise SourceError(f'{path}: not one time [s] a line ({exc})') from None
    if len(seconds) != expected:
        raise SourceError(f'{path} lists {len(seconds)} times for {expected} {what}')
    stamps = np.round(seconds * 1e9).astype(np.int64)
    if len(stamps) > 1 and np.any(np.diff(stamps) <= 0):
        bad = int(np.flatnonzero(np.diff(stamps) <= 0)[0]) + 2
        raise SourceError(f'{path}: times must increase (line {bad} is not after the line before it)')
    return stamps


def read_calibration(path: Path) -> np.ndarray:
    """``Tr`` (velodyne -> cam0, 4x4) of a KITTI ``calib.txt``."""
    for line in path.read_text().splitlines():
        key, _, values = line.partition(':')
        if key.strip() in ('Tr', 'Tr_velo_to_cam'):
            numbers = values.split()
            if len(numbers) != 12:
                raise SourceError(f'{path}: {key.strip()} has {len(numbers)} numbers, a 3x4 matrix has 12')
            matrix = np.eye(4)
            matrix[:3, :] = np.array(numbers, dtype=float).reshape(3, 4)
            return matrix
    raise SourceError(f"{path}: no 'Tr:' line (the velodyne -> camera transform)")


def _poses_file(folder: Path) -> Path | None:
    beside = folder / 'poses.txt'
    if beside.is_file():
        return beside
    shipped = folder.parent.parent / 'poses' / f'{folder.name}.txt'  # dataset/poses/NN.txt
    return shipped if shipped.is_file() else None


def lidar_ground_truth(folder: Path, stamps: np.ndarray) -> Trajectory | None:
    """The lidar trajectory of a folder's ``poses.txt`` (camera poses with ``calib.txt``, else the lidar's),
    stamped with ``stamps``, relative to the first pose; None without poses.txt."""
    path = _poses_file(folder)
    if path is None:
        return None
    try:
        poses = read_kitti_poses(path)
    except ValueError as exc:
        raise SourceError(str(exc)) from None
    if len(poses) != len(stamps):
        raise SourceError(f'{path} holds {len(poses)} poses for {len(stamps)} scans')
    calib = folder / 'calib.txt'
    if calib.is_file():
        tr = read_calibration(calib)
        poses = np.linalg.inv(tr)[None] @ poses @ tr[None]
    poses = np.linalg.inv(poses[0])[None] @ poses if len(poses) else poses
    return Trajectory(stamps.copy(), poses, 'map')


class KittiSource(Source):
    """A KITTI odometry sequence folder (see the module docstring); ``rate_hz`` times scans without times.txt."""

    kind = 'kitti'

    def __init__(self, path: str | Path, rate_hz: float = 10.0):
        self.path = Path(path)
        self.name = self.path.resolve().name
        if not is_kitti_sequence(self.path):
            raise SourceError(f'{self.path}: not a KITTI sequence (no velodyne/*.bin files in it)')
        self.scan_files = sorted((self.path / 'velodyne').glob('*.bin'))
        times = self.path / 'times.txt'
        if times.is_file():
            self.stamps = read_times(times, len(self.scan_files))
            self.timed_by = str(times)
        else:
            self.stamps = np.round(np.arange(len(self.scan_files)) * 1e9 / rate_hz).astype(np.int64)
            self.timed_by = f'{rate_hz:g} Hz (no times.txt)'
        self._ground_truth = lidar_ground_truth(self.path, self.stamps)

    @property
    def duration_s(self) -> float:
        return float(self.stamps[-1] - self.stamps[0]) * 1e-9 if len(self.stamps) else 0.0

    def scan_count(self) -> int:
        return len(self.scan_files)

    def ground_truth(self) -> Trajectory | None:
        return self._ground_truth

    def describe(self) -> str:
        truth = 'poses.txt as ground truth' if self._ground_truth is not None else 'no ground truth'
        return f'KITTI sequence {self.path}: {len(self.scan_files)} scans timed by {self.timed_by}, {truth}'

    def items(self) -> Iterator[SourceItem]:
        for stamp, path in zip(self.stamps, self.scan_files):
            yield Scan(int(stamp), read_bin_points(path), int(stamp))


def write_times(path: Path, stamps_ns: np.ndarray) -> None:
    """A ``times.txt``: each stamp in seconds since the first, with nanosecond digits (read back exactly)."""
    relative = np.asarray(stamps_ns, dtype=np.int64) - int(stamps_ns[0])
    path.write_text(''.join(f'{t // 1_000_000_000}.{t % 1_000_000_000:09d}\n' for t in relative.tolist()))


def write_kitti_sequence_files(folder: Path, stamps_ns: np.ndarray, lidar_poses: np.ndarray) -> None:
    """``times.txt`` (seconds since the first stamp, ns digits), ``calib.txt`` (``Tr`` =
    :data:`KITTI_VELO_TO_CAM`) and ``poses.txt`` (the camera's poses, ``Tr P Tr^-1``) of a sequence folder
    whose lidar poses (relative to the first, REP-103 axes) are ``lidar_poses``."""
    write_times(folder / 'times.txt', stamps_ns)
    tr = KITTI_VELO_TO_CAM
    (folder / 'calib.txt').write_text('Tr: ' + ' '.join(f'{v:.12e}' for v in tr[:3, :].reshape(-1)) + '\n')
    write_kitti_poses_atomic(folder / 'poses.txt', tr[None] @ lidar_poses @ np.linalg.inv(tr)[None])
