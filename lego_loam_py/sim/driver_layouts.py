"""The simulator's clouds in the layouts real lidar drivers publish: the same points and times, other bytes.

Tests and ``benchmarks/driver_layouts.py`` feed these to the pipeline to check that every layout is read into
the points and times of the simulator's own (the ROS 2 velodyne driver's) layout. Each layout follows its
driver's point type and conventions:

==========================  ===================================================================================
``plain``                   as simulated: velodyne PointXYZIRT (32 B), firing order, ``time`` [s, float32]
``velodyne_organized``      the velodyne driver with ``organize_cloud``: one row per firing (height = columns),
                            one column per laser in ring order, NaN x/y/z where a laser had no return
``ouster``                  ouster-ros's legacy point (48 B): organized rows x columns, row-major, row 0 the
                            top beam (``ring`` = row), x = y = z = 0 where a pixel had no return, ``is_dense``
                            true; ``t`` uint32 [ns since the scan start], ``reflectivity``, ``ambient``,
                            ``range`` [mm]
``hesai``                   Hesai's PointXYZIT (48 B): ``timestamp`` float64 absolute [s], ``ring`` counted
                            from the top beam (Hesai numbers its channels from the uppermost)
``robosense``               rslidar_sdk's PointXYZIRT (32 B): ``ring`` (lowest first), ``timestamp`` float64
                            absolute [s]
``livox``                   a Livox-style cloud (24 B): ``tag``, ``line``, ``offset_time`` uint32 [ns from the
                            header stamp]
``float64``                 x/y/z as float64 (other fields as plain)
``xyzi``                    PCL's PointXYZI (32 B): x, y, z, intensity and nothing else
==========================  ===================================================================================

A point's range-image pixel is its ring (row) and its column; the simulator casts every column at azimuth
``-2 pi k / columns`` and each return lies on its beam, so the column follows from the point's azimuth.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from lego_loam_py.core.pointcloud import POINT_XYZI_DTYPE

__all__ = [
    'LAYOUTS',
    'OUSTER_DTYPE',
    'HESAI_DTYPE',
    'ROBOSENSE_DTYPE',
    'LIVOX_DTYPE',
    'FLOAT64_DTYPE',
    'pixels_of',
    'in_layout',
    'rewrite_bag',
    'cached_layout',
]

LAYOUTS = ('plain', 'velodyne_organized', 'ouster', 'hesai', 'robosense', 'livox', 'float64', 'xyzi')

# ouster-ros's legacy point (PCL-aligned): x, y, z float32, intensity float32 at 16, t uint32 [ns] at 20,
# reflectivity uint16 at 24, ring uint16 at 26, ambient uint16 at 28, range uint32 [mm] at 32; 48 bytes.
OUSTER_DTYPE = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 't', 'reflectivity', 'ring', 'ambient', 'range'],
        'formats': ['<f4', '<f4', '<f4', '<f4', '<u4', '<u2', '<u2', '<u2', '<u4'],
        'offsets': [0, 4, 8, 16, 20, 24, 26, 28, 32],
        'itemsize': 48,
    }
)
# Hesai's PointXYZIT (HesaiLidar_General_ROS): intensity at 16, timestamp float64 [s] at 24, ring uint16 at 32.
HESAI_DTYPE = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 'timestamp', 'ring'],
        'formats': ['<f4', '<f4', '<f4', '<f4', '<f8', '<u2'],
        'offsets': [0, 4, 8, 16, 24, 32],
        'itemsize': 48,
    }
)
# rslidar_sdk's PointXYZIRT: intensity at 16, ring uint16 at 20, timestamp float64 [s] at 24.
ROBOSENSE_DTYPE = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 'ring', 'timestamp'],
        'formats': ['<f4', '<f4', '<f4', '<f4', '<u2', '<f8'],
        'offsets': [0, 4, 8, 16, 20, 24],
        'itemsize': 32,
    }
)
# Livox-style point: x, y, z, intensity float32, tag and line uint8, offset_time uint32 [ns from the stamp].
LIVOX_DTYPE = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 'tag', 'line', 'offset_time'],
        'formats': ['<f4', '<f4', '<f4', '<f4', 'u1', 'u1', '<u4'],
        'offsets': [0, 4, 8, 12, 16, 17, 20],
        'itemsize': 24,
    }
)
# float64 coordinates, the rest as the velodyne layout.
FLOAT64_DTYPE = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 'ring', 'time'],
        'formats': ['<f8', '<f8', '<f8', '<f4', '<u2', '<f4'],
        'offsets': [0, 8, 16, 24, 28, 32],
        'itemsize': 40,
    }
)


def pixels_of(points: np.ndarray, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """(ring, column) of every simulated point: its ring field and the column of its azimuth (int64)."""
    x = points['x'].astype(np.float64)
    y = points['y'].astype(np.float64)
    column = np.rint(-np.arctan2(y, x) * columns / (2.0 * np.pi)).astype(np.int64) % columns
    return points['ring'].astype(np.int64), column


def _empty_grid(
    points: np.ndarray, dtype: np.dtype, rows: int, columns: int, empty_xyz: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A (rows, columns) grid of ``dtype`` whose x/y/z hold ``empty_xyz``, and the (ring, column) of the points."""
    ring, column = pixels_of(points, columns)
    if np.unique(ring * columns + column).size != len(points):
        raise ValueError('two points share a pixel: not a single-return simulated sweep')
    grid = np.zeros((rows, columns), dtype=dtype)
    for name in 'xyz':
        grid[name] = empty_xyz
    return grid, ring, column


def in_layout(
    points: np.ndarray, layout: str, stamp_ns: int, rows: int, columns: int, scan_period: float = 0.1
) -> np.ndarray:
    """A simulated sweep (velodyne layout, ``time`` [s] since the header stamp ``stamp_ns``) in ``layout``:
    a 1-D array (unorganized) or a 2-D (height, width) one (organized)."""
    time = points['time'].astype(np.float64)
    if layout == 'plain':
        return points
    if layout in ('hesai', 'robosense', 'livox', 'float64', 'xyzi'):
        dtype = {
            'hesai': HESAI_DTYPE,
            'robosense': ROBOSENSE_DTYPE,
            'livox': LIVOX_DTYPE,
            'float64': FLOAT64_DTYPE,
            'xyzi': POINT_XYZI_DTYPE,
        }[layout]
        out = np.zeros(len(points), dtype=dtype)
        for name in ('x', 'y', 'z', 'intensity'):
            out[name] = points[name]
        if layout == 'hesai':
            out['ring'] = rows - 1 - points['ring'].astype(np.int64)
        elif layout in ('robosense', 'float64'):
            out['ring'] = points['ring']
        if layout in ('hesai', 'robosense'):
            out['timestamp'] = stamp_ns * 1e-9 + time
        elif layout == 'livox':
            out['offset_time'] = np.rint(time * 1e9).astype(np.uint32)
            out['line'] = points['ring']
        elif layout == 'float64':
            out['time'] = points['time']
        return out
    column_time = np.arange(columns) * (scan_period / columns)
    if layout == 'velodyne_organized':
        grid, ring, column = _empty_grid(points, points.dtype, rows, columns, np.nan)
        grid['ring'] = np.arange(rows)[:, None]
        grid['time'] = column_time[None, :]
        grid[ring, column] = points
        return np.ascontiguousarray(grid.T)  # one row per firing, one column per laser
    if layout == 'ouster':
        grid, ring, column = _empty_grid(points, OUSTER_DTYPE, rows, columns, 0.0)
        grid['ring'] = np.arange(rows)[:, None]
        grid['t'] = np.rint(column_time * 1e9).astype(np.uint32)[None, :]
        row = rows - 1 - ring  # row 0 is the top beam
        cell = grid[row, column]
        for name in ('x', 'y', 'z', 'intensity'):
            cell[name] = points[name]
        cell['t'] = np.rint(time * 1e9).astype(np.uint32)
        cell['reflectivity'] = np.clip(points['intensity'], 0, 255).astype(np.uint16)
        cell['ring'] = row
        xyz = np.stack([points['x'], points['y'], points['z']], axis=1).astype(np.float64)
        cell['range'] = np.rint(np.linalg.norm(xyz, axis=1) * 1000.0).astype(np.uint32)
        grid[row, column] = cell
        return grid
    raise ValueError(f"unknown layout '{layout}' (known: {', '.join(LAYOUTS)})")


SIDECARS = ('ground_truth.tum', 'ground_truth_dense.tum', 'scenario.yaml')


def rewrite_bag(source: str | Path, output: str | Path, layout: str, max_scans: int | None = None) -> Path:
    """Copy the simulated bag ``source`` to ``output`` (a new ROS 2 bag) with its clouds in ``layout``; the IMU
    messages and the ground truth are copied as they are. Returns ``output``."""
    from lego_loam_py.bag.io import BagReader, BagWriter, cloud_msg_to_array, make_cloud_msg
    from lego_loam_py.inputs.sidecars import load_scenario, sidecar_path
    from lego_loam_py.sim.simulator import CLOUD_TOPIC

    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout '{layout}' (known: {', '.join(LAYOUTS)})")
    lidar = load_scenario(source)['lidar']
    rows, columns = len(lidar['ring_elevations_deg']), int(lidar['columns'])
    period = float(lidar['scan_period_s'])
    output = Path(output)
    scans = 0
    with BagReader(source) as reader, BagWriter(output) as writer:
        topics = reader.topics()
        for message in reader.messages():
            if message.topic != CLOUD_TOPIC:
                writer.write_raw(message.topic, topics[message.topic], message.timestamp, message.data)
                continue
            if max_scans is not None and scans >= max_scans:
                continue
            scans += 1
            msg = reader.deserialize(message)
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            points = in_layout(cloud_msg_to_array(msg).copy(), layout, stamp, rows, columns, period)
            header = writer.header(stamp, msg.header.frame_id)
            writer.write_msg(CLOUD_TOPIC, message.timestamp, make_cloud_msg(writer.types, header, points))
    for name in SIDECARS:
        if sidecar_path(source, name).is_file():
            shutil.copyfile(sidecar_path(source, name), sidecar_path(output, name))
    return output


def cached_layout(source: str | Path, layout: str) -> Path:
    """``source`` (a cached simulated bag) rewritten into ``layout``, kept in the cache beside it and reused."""
    source = Path(source)
    entry = source.parent / 'layouts' / f'{source.name}-{layout}'
    if (entry / 'ground_truth.tum').is_file():
        return entry
    temporary = entry.with_name(f'.{entry.name}.tmp{os.getpid()}')
    if temporary.exists():
        shutil.rmtree(temporary)
    entry.parent.mkdir(parents=True, exist_ok=True)
    try:
        rewrite_bag(source, temporary, layout)
        try:
            os.rename(temporary, entry)
        except OSError:
            if not (entry / 'ground_truth.tum').is_file():  # (another process finished first otherwise)
                raise
    finally:
        if temporary.exists():
            shutil.rmtree(temporary, ignore_errors=True)
    return entry
