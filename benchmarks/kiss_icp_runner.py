"""KISS-ICP on a list of scans, for benchmarks/real_data.py; run by the Python of the KISS-ICP venv.

    KISS_VENV/bin/python benchmarks/kiss_icp_runner.py MANIFEST OUT_DIR

MANIFEST has one scan a line, ``<stamp ns> <path>``, in recording order; a path is a PCD file (``DATA ascii`` or
``binary``) or a KITTI ``.bin`` (float32 x y z reflectance). The scans go through KISS-ICP's Python API as its
own pipeline feeds it: ``load_config(None)`` (the defaults of ``KISSConfig``, the voxel size derived from the
maximum range), one ``KissICP.register_frame(points, timestamps)`` per scan, ``last_pose`` as the scan's pose.
Per-point timestamps are passed when a PCD has one of the time fields KISS-ICP's generic loader looks for, else
an empty array, as its loaders do for KITTI. Writes OUT_DIR/trajectory.tum (each pose stamped with its scan's
stamp; KISS-ICP's frame: the first scan's sensor frame) and OUT_DIR/info.json (version, configuration, what
deskewing did, time inside register_frame).

Only numpy and kiss_icp are imported, never lego_loam_py: this file runs in KISS-ICP's own environment. The
readers and the TUM writer are plain functions so that the project's tests can check them without KISS-ICP.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

# Per-point time fields, in the order KISS-ICP's generic dataloader tries them.
TIME_FIELDS = ('t', 'timestamp', 'timestamps', 'time', 'stamps')
_PCD_TYPES = {
    ('F', 4): 'f4',
    ('F', 8): 'f8',
    ('U', 1): 'u1',
    ('U', 2): 'u2',
    ('U', 4): 'u4',
    ('U', 8): 'u8',
    ('I', 1): 'i1',
    ('I', 2): 'i2',
    ('I', 4): 'i4',
    ('I', 8): 'i8',
}


def read_pcd(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 x y z and the (N,) float64 per-point times (empty when the file has no time field) of a
    PCD file, ``DATA ascii`` or ``binary``."""
    path = Path(path)
    data = path.read_bytes()
    header, offset = {}, 0
    while True:
        end = data.find(b'\n', offset)
        if end < 0:
            raise ValueError(f'{path}: the PCD header has no DATA line')
        line = data[offset:end].decode('ascii', errors='replace').strip()
        offset = end + 1
        if line and not line.startswith('#'):
            key, _, value = line.partition(' ')
            header[key.upper()] = value.split()
            if key.upper() == 'DATA':
                break
    names = header['FIELDS']
    sizes = [int(v) for v in header['SIZE']]
    kinds = header['TYPE']
    counts = [int(v) for v in header.get('COUNT', ['1'] * len(names))]
    count = (
        int(header['POINTS'][0])
        if 'POINTS' in header
        else int(header['WIDTH'][0]) * int(header.get('HEIGHT', ['1'])[0])
    )
    # Fields with the same name (PCL's '_' padding) get unique names; only x y z and a time field are read.
    unique = [f'{name}#{i}' if names.index(name) != i else name for i, name in enumerate(names)]
    dtype = np.dtype(
        [
            (name, '<' + _PCD_TYPES[(kind, size)], (n,) if n > 1 else ())
            for name, kind, size, n in zip(unique, kinds, sizes, counts)
        ]
    )
    layout = header['DATA'][0].lower()
    if layout == 'binary':
        if len(data) - offset < count * dtype.itemsize:
            raise ValueError(f'{path}: truncated ({count} points of {dtype.itemsize} bytes announced)')
        points = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
        columns = {name: points[name].astype(np.float64) for name in dtype.names}
    elif layout == 'ascii':
        table = np.loadtxt(data[offset:].decode('ascii').splitlines(), dtype=np.float64, ndmin=2)
        if table.shape[0] != count:
            raise ValueError(f'{path}: the header says {count} points, the file holds {table.shape[0]}')
        starts = np.cumsum([0] + counts[:-1])
        columns = {name: table[:, start] for name, start in zip(unique, starts)}
    else:
        raise ValueError(f"{path}: PCD DATA '{layout}' is not read here (ascii or binary)")
    xyz = np.column_stack([columns['x'], columns['y'], columns['z']])
    time_field = next((name for name in TIME_FIELDS if name in columns), None)
    times = columns[time_field] if time_field else np.zeros(0)
    return xyz, times


def read_bin(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 x y z of a KITTI velodyne ``.bin`` (float32 x y z reflectance); no per-point times."""
    return np.fromfile(path, dtype='<f4').reshape(-1, 4)[:, :3].astype(np.float64), np.zeros(0)


def read_scan(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    suffix = Path(path).suffix.lower()
    if suffix == '.pcd':
        return read_pcd(path)
    if suffix == '.bin':
        return read_bin(path)
    raise ValueError(f'{path}: not a .pcd or .bin scan')


def write_pcd(path: str | Path, xyz: np.ndarray, times: np.ndarray | None = None) -> None:
    """A binary PCD with float32 x y z and, when given, float64 ``time`` per point."""
    xyz = np.asarray(xyz)
    fields = [('x', '<f4'), ('y', '<f4'), ('z', '<f4')] + ([('time', '<f8')] if times is not None else [])
    points = np.zeros(len(xyz), dtype=fields)
    points['x'], points['y'], points['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if times is not None:
        points['time'] = times
    names = ' '.join(name for name, _ in fields)
    header = (
        f'VERSION 0.7\nFIELDS {names}\nSIZE {" ".join(kind[-1] for _, kind in fields)}\n'
        f'TYPE {" ".join("F" for _ in fields)}\nCOUNT {" ".join("1" for _ in fields)}\n'
        f'WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA binary\n'
    )
    Path(path).write_bytes(header.encode('ascii') + points.tobytes())


def read_manifest(path: str | Path) -> tuple[np.ndarray, list[Path]]:
    """(stamps [ns] int64, scan paths) of a manifest (``<stamp ns> <path>`` a line)."""
    stamps, files = [], []
    for line in Path(path).read_text().splitlines():
        if line.strip():
            stamp, _, name = line.strip().partition(' ')
            stamps.append(int(stamp))
            files.append(Path(name))
    return np.array(stamps, dtype=np.int64), files


def quaternions_xyzw(rotations: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions x y z w, w >= 0, of (N, 3, 3) rotation matrices (the largest of the four
    components computed first, for accuracy)."""
    m = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    squares = np.stack([1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22, 1 + m00 + m11 + m22], 1)
    largest = np.argmax(squares, axis=1)
    big = np.sqrt(np.maximum(squares[np.arange(len(m)), largest], 1e-300)) / 2  # that component's value
    s12, d21 = m[:, 1, 2] + m[:, 2, 1], m[:, 2, 1] - m[:, 1, 2]
    s02, d02 = m[:, 0, 2] + m[:, 2, 0], m[:, 0, 2] - m[:, 2, 0]
    s01, d10 = m[:, 0, 1] + m[:, 1, 0], m[:, 1, 0] - m[:, 0, 1]
    # 4 * (product of that component with each of the others), by which component is the largest (rows x y z w)
    products = np.stack(
        [
            np.stack([4 * big**2, s01, s02, d21], 1),
            np.stack([s01, 4 * big**2, s12, d02], 1),
            np.stack([s02, s12, 4 * big**2, d10], 1),
            np.stack([d21, d02, d10, 4 * big**2], 1),
        ],
        1,
    )
    quats = products[np.arange(len(m)), largest] / (4 * big)[:, None]
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    quats[quats[:, 3] < 0] *= -1.0
    return quats


def tum_text(stamps_ns: np.ndarray, poses: np.ndarray) -> str:
    """TUM lines ``stamp x y z qx qy qz qw`` with the stamps written exactly from integer nanoseconds."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    quats = quaternions_xyzw(poses[:, :3, :3]) if len(poses) else np.zeros((0, 4))
    lines = []
    for stamp, t, q in zip(np.asarray(stamps_ns, dtype=np.int64), poses[:, :3, 3], quats):
        seconds, nanoseconds = divmod(int(stamp), 1_000_000_000)
        lines.append(
            f'{seconds}.{nanoseconds:09d} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}'
        )
    return ''.join(line + '\n' for line in lines)


def run(manifest: Path, out: Path) -> dict:
    from importlib.metadata import version

    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    stamps, files = read_manifest(manifest)
    config = load_config(None)  # what KISS-ICP's pipeline does without a config file
    odometry = KissICP(config=config)
    poses = np.empty((len(files), 4, 4))
    register_s = np.empty(len(files))
    timed_scans, probe_shift_m = 0, None
    for index, path in enumerate(files):
        points, times = read_scan(path)
        timed_scans += bool(len(times))
        if probe_shift_m is None and not len(times):
            # What the preprocessor does to a scan without per-point times under a 1 m, 10 deg motion: with
            # deskewing on it would move the points; 0 means the scan is registered as it is.
            motion, yaw = np.eye(4), np.radians(10.0)
            motion[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
            motion[0, 3] = 1.0
            sample = points[:1000]
            kept = sample[
                (np.linalg.norm(sample, axis=1) < config.data.max_range)
                & (np.linalg.norm(sample, axis=1) > config.data.min_range)
            ]
            moved = odometry.preprocessor.preprocess(sample, np.zeros(0), motion)
            probe_shift_m = float(np.abs(moved - kept).max()) if moved.shape == kept.shape else float('nan')
        start = time.perf_counter()
        odometry.register_frame(points, times)
        register_s[index] = time.perf_counter() - start
        poses[index] = odometry.last_pose
    out.mkdir(parents=True, exist_ok=True)
    (out / 'trajectory.tum').write_text(tum_text(stamps, poses))
    info = {
        'kiss_icp_version': version('kiss-icp'),
        'config': config.model_dump(),
        'scans': len(files),
        'scans_with_point_times': timed_scans,
        'deskew_enabled': bool(config.data.deskew),
        'deskew_probe_shift_m': probe_shift_m,
        'register_frame_ms_median': float(np.median(register_s) * 1e3) if len(files) else float('nan'),
        'register_frame_ms_mean': float(np.mean(register_s) * 1e3) if len(files) else float('nan'),
    }
    (out / 'info.json').write_text(json.dumps(info, indent=2) + '\n')
    return info


if __name__ == '__main__':
    if len(sys.argv) != 3:
        sys.exit(__doc__.split('\n\n')[1])
    run(Path(sys.argv[1]), Path(sys.argv[2]))
