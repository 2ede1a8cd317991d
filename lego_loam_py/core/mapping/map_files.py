"""The files a mapping run's save writes into one directory: what users view and what localization loads.

* ``global_map.pcd``, ``corner_map.pcd``, ``surface_map.pcd``: the maps in REP-103 ``map`` axes, intensity kept;
* ``trajectory.pcd`` (keyframe positions, intensity = index), ``trajectory.tum`` (REP-103 ``map`` axes) and
  ``trajectory_camera_init.tum`` (the original's camera_init axes): the keyframe poses;
* the map bundle (:mod:`lego_loam_py.core.mapping.map_bundle`);
* ``occupancy.yaml`` and ``occupancy.pgm``: the 2D occupancy grid in the ``map`` frame, as nav2's map_server reads
  it (:mod:`lego_loam_py.core.mapping.occupancy_files`), when one is given.

Each file is written under a temporary name and renamed, so a crash never leaves a half-written file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lego_loam_py.core.frames import camera_pose_to_lidar, camera_to_lidar, pose6_to_matrix
from lego_loam_py.core.mapping.map_bundle import MapBundle, write_bundle
from lego_loam_py.core.mapping.occupancy_files import write_occupancy_files
from lego_loam_py.core.mapping.occupancy_grid import TernaryGrid
from lego_loam_py.formats import write_pcd_atomic, write_tum_atomic

__all__ = ['write_map_files', 'in_map_axes']


def in_map_axes(cloud: np.ndarray) -> np.ndarray:
    """A map cloud (N, 3+) in camera axes, as MapOptimization.maps gives it, in REP-103 ``map`` axes with its other
    columns kept: the points its PCD file holds."""
    return np.concatenate([camera_to_lidar(cloud[:, :3]), cloud[:, 3:]], axis=1)


def write_map_files(
    directory: str | Path, maps: dict[str, np.ndarray], bundle: MapBundle, occupancy: TernaryGrid | None = None
) -> dict[str, Path]:
    """Write ``maps`` ('global_map', 'corner', 'surface': (N, 4) camera axes, as MapOptimization.maps gives them),
    the keyframe trajectory of ``bundle``, ``bundle`` itself and the ``occupancy`` grid (when given and not empty:
    'occupancy_yaml', 'occupancy_image') into ``directory``; returns the paths by name."""
    from lego_loam_py import __version__

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    poses, stamps = bundle.poses6, bundle.stamps_ns
    camera_matrices = np.array([pose6_to_matrix(p) for p in poses]).reshape(-1, 4, 4)
    lidar_matrices = camera_pose_to_lidar(np.asarray(camera_matrices).reshape(-1, 4, 4))  # (the whole stack)
    written = {}
    for name, cloud in (
        ('global_map', maps['global_map']),
        ('corner_map', maps['corner']),
        ('surface_map', maps['surface']),
    ):
        written[name] = write_pcd_atomic(directory / f'{name}.pcd', in_map_axes(cloud))
    trajectory = np.concatenate([lidar_matrices[:, :3, 3], np.arange(len(poses))[:, None]], axis=1)
    written['trajectory'] = write_pcd_atomic(directory / 'trajectory.pcd', trajectory.astype(np.float32))
    written['trajectory_tum'] = write_tum_atomic(directory / 'trajectory.tum', stamps, lidar_matrices)
    written['trajectory_camera_init_tum'] = write_tum_atomic(
        directory / 'trajectory_camera_init.tum', stamps, camera_matrices
    )
    written.update(write_bundle(directory, bundle, f'lego_loam_py {__version__}'))
    if occupancy is not None and occupancy.width and occupancy.height:
        files = write_occupancy_files(directory, occupancy)
        written.update(occupancy_yaml=files['yaml'], occupancy_image=files['image'])
    return written
