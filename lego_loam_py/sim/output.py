"""What the simulator writes beside a bag (the files and where they live: :mod:`lego_loam_py.inputs.sidecars`,
which reads them), and the simulated world a recording's scenario.yaml describes: where the true sensor was
(:func:`true_poses`) and how far a map lies from the scene's surfaces (:func:`map_distance_to_scene`).
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lego_loam_py.formats import tum_lines
from lego_loam_py.inputs.sidecars import load_scenario

__all__ = [
    'relative_poses',
    'write_tum',
    'write_yaml',
    'LabelWriter',
    'map_distance_to_scene',
    'world_of',
    'true_poses',
    'same_scene',
]


def relative_poses(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses expressed relative to the first one (``inv(T_0) T_k``)."""
    first_inverse = np.linalg.inv(poses[0])
    return np.einsum('ij,njk->nik', first_inverse, poses)


def write_tum(path: str | Path, stamps_ns: np.ndarray, poses: np.ndarray) -> None:
    """Ground-truth TUM file: a header line, then ``timestamp tx ty tz qx qy qz qw`` (nm / 1e-12 precision)."""
    Path(path).write_text('# timestamp tx ty tz qx qy qz qw\n' + tum_lines(stamps_ns, poses, 9, 12))


def map_distance_to_scene(
    bag_path: str | Path, map_points: np.ndarray, stamp_ns: int, lidar_pose_in_map: np.ndarray
) -> np.ndarray | None:
    """Distance [m] of each map point (REP-103 axes of the ``map`` frame) to the simulated scene's surfaces,
    or None when no scenario.yaml sits beside the bag.

    ``lidar_pose_in_map`` (4x4) is the estimated lidar pose at ``stamp_ns`` (e.g. the first pose of the
    trajectory); the true pose at that time places ``map`` in the world. (``map`` is not simply the first
    lidar pose: with an IMU the pipeline levels it with the IMU's roll and pitch, as the original does.)
    """
    scenario = load_scenario(bag_path)
    if scenario is None:
        return None
    world = world_of(scenario)
    t = (int(stamp_ns) - int(scenario['recording']['start_stamp_ns'])) / 1e9
    world_from_map = world.trajectory.matrices(np.array([t]))[0] @ np.linalg.inv(lidar_pose_in_map)
    xyz = np.asarray(map_points, dtype=np.float64)[:, :3]
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    return world.scene.distance(xyz @ world_from_map[:3, :3].T + world_from_map[:3, 3])


def world_of(scenario: dict[str, Any]):
    """The simulated world (scene and trajectory) a recording's scenario.yaml (or its 'config' alone) describes."""
    from lego_loam_py.sim.scenarios import build_world

    config = scenario['config']
    route_start = config.get('route_start')
    return build_world(
        config['scenario'],
        int(config['seed']),
        float(config.get('turn_rate', 0.0)),
        None if route_start is None else float(route_start),
        bool(config.get('reverse', False)),
    )


def true_poses(simulated: dict[str, Any], stamps_ns: np.ndarray) -> np.ndarray:
    """(N, 4, 4) true lidar poses in the simulated world (REP-103, z up) at ``stamps_ns``, for a recording
    described by ``simulated`` ({'config': scenario.yaml's config, 'start_stamp_ns': ...})."""
    t = (np.asarray(stamps_ns, dtype=np.int64) - int(simulated['start_stamp_ns'])) * 1e-9
    return world_of(simulated).trajectory.matrices(t)


def same_scene(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two simulated recordings ({'config': ...}) were made in the same world (scenario and seed)."""
    return (a['config']['scenario'], int(a['config']['seed'])) == (b['config']['scenario'], int(b['config']['seed']))


def write_yaml(path: str | Path, data: dict[str, Any]) -> None:
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=110))


# ------------------------------------------------------------------------------------------------ labels

_ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # fixed member dates: identical inputs give identical files


class LabelWriter:
    """Streams per-scan label arrays into an .npz (a zip of .npy members, readable by ``np.load``) without
    holding them all in memory."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._zip = zipfile.ZipFile(self.path, 'w', compression=zipfile.ZIP_DEFLATED, compresslevel=6)
        self._count = 0

    def _write_array(self, name: str, array: np.ndarray) -> None:
        buffer = io.BytesIO()
        array = np.asarray(array)
        np.lib.format.write_array(buffer, array if array.ndim == 0 else np.ascontiguousarray(array), allow_pickle=False)
        info = zipfile.ZipInfo(f'{name}.npy', date_time=_ZIP_DATE)
        info.compress_type = zipfile.ZIP_DEFLATED
        self._zip.writestr(info, buffer.getvalue(), compresslevel=6)

    def add_scan(self, labels: np.ndarray) -> None:
        """Labels of the next scan (key ``s{k}``)."""
        self._write_array(f's{self._count}', np.asarray(labels, dtype=np.uint32))
        self._count += 1

    def close(self, stamps_ns: np.ndarray, classes: list[str] | tuple[str, ...]) -> None:
        self._write_array('stamps', np.asarray(stamps_ns, dtype=np.int64))
        self._write_array('classes', np.array(json.dumps(list(classes))))
        self._zip.close()

    def abort(self) -> None:
        self._zip.close()
