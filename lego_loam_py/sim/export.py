"""A simulated recording written again as the datasets others publish: a KITTI sequence or a folder of PCD scans.

Both hold the bag's clouds in order (the same points, float32) with ``times.txt`` (the clouds' header stamps, in
seconds since the first, nanosecond digits) and ``poses.txt`` (the ground truth, 12 numbers a line):

* ``kitti``: ``velodyne/NNNNNN.bin`` (x y z intensity, float32: no ring, no point time, as KITTI's scans),
  ``calib.txt`` with ``Tr`` and ``poses.txt`` as the camera's poses (``Tr P Tr^-1``), as KITTI ships them;
* ``pcd``: ``NNNNNN.pcd`` with every field of the cloud (x y z intensity ring time) and ``poses.txt`` as the
  lidar's poses.

``lego_loam_py run`` reads either (:mod:`lego_loam_py.inputs`); no IMU is exported, so compare with the bag run
``--no-imu``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

__all__ = ['export_recording', 'EXPORT_KINDS']

EXPORT_KINDS = ('kitti', 'pcd')


def export_recording(bag: str | Path, folder: str | Path, kind: str) -> int:
    """Write the clouds and ground truth of the simulated ``bag`` into ``folder`` (must not exist) as ``kind``;
    returns the number of scans written."""
    from lego_loam_py.bag.io import BagReader, cloud_msg_to_array
    from lego_loam_py.formats import write_kitti_poses_atomic
    from lego_loam_py.inputs.kitti import write_kitti_sequence_files, write_times
    from lego_loam_py.inputs.point_files import write_bin_points, write_pcd_points
    from lego_loam_py.inputs.sidecars import load_ground_truth
    from lego_loam_py.sim.simulator import CLOUD_TOPIC

    if kind not in EXPORT_KINDS:
        raise ValueError(f"unknown export '{kind}' (use {' or '.join(EXPORT_KINDS)})")
    folder = Path(folder)
    if folder.exists():
        raise FileExistsError(f'{folder} exists already; choose another folder')
    truth = load_ground_truth(bag)
    if truth is None:
        raise ValueError(f'{bag} has no ground truth beside it: not a simulated recording')
    scans = folder / 'velodyne' if kind == 'kitti' else folder
    scans.mkdir(parents=True)
    stamps = []
    try:
        with BagReader(bag) as reader:
            for k, message in enumerate(reader.messages(topics=[CLOUD_TOPIC])):
                msg = reader.deserialize(message)
                points = cloud_msg_to_array(msg)
                stamps.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
                if kind == 'kitti':
                    write_bin_points(scans / f'{k:06d}.bin', points)
                else:
                    write_pcd_points(scans / f'{k:06d}.pcd', points)
        truth_stamps, poses = truth
        index = np.searchsorted(truth_stamps, stamps)
        if np.any(index >= len(truth_stamps)) or np.any(
            truth_stamps[np.minimum(index, len(truth_stamps) - 1)] != stamps
        ):
            raise ValueError(f'{bag}: the ground truth does not list every cloud stamp')
        poses = poses[index]
        if kind == 'kitti':
            write_kitti_sequence_files(folder, np.array(stamps), poses)
        else:
            write_times(folder / 'times.txt', np.array(stamps, dtype=np.int64))
            write_kitti_poses_atomic(folder / 'poses.txt', poses)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return len(stamps)
