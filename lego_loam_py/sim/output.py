"""Files beside a bag: ground truth, per-point labels, the generating parameters and a note.

For a ROS 2 bag directory ``P`` the sidecar files live inside it (``P/ground_truth.tum``); for a ROS 1 bag
file ``P.bag`` they sit next to it with the bag's stem as prefix (``P.ground_truth.tum``):

==========================  ======================================================================================
``ground_truth.tum``        lidar pose at every sweep start (= the cloud's header stamp), relative to the first
                            one (first pose = identity), REP-103 axes (x forward, y left, z up). TUM format:
                            ``timestamp tx ty tz qx qy qz qw``, timestamp in seconds with nanosecond digits.
``ground_truth_dense.tum``  the same trajectory at every IMU stamp (for deskewing and IMU checks).
``labels.npz``              ``s{k}``: uint32 label of every point of scan k, in message order (0 none,
                            1 ground, >= 2 object id); ``stamps``: int64 header stamps [ns]; ``classes``: JSON
                            array, ``classes[id]`` = class name of each id.
``scenario.yaml``           every parameter (scenario, seed, sensor, noise, drawn biases, layout, ...), the
                            world pose of the first ground-truth pose, statistics.
``README.md``               how the bag was produced, with the exact command.
==========================  ======================================================================================

:func:`sidecar_path` and :func:`load_ground_truth` find these beside any bag; the pipeline's demo and
evaluation use them.
"""
from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lego_loam_py.formats import read_tum, tum_lines

__all__ = ['map_distance_to_scene', 'GROUND_TRUTH', 'GROUND_TRUTH_DENSE', 'LABELS', 'SCENARIO', 'NOTE', 'sidecar_path', 'write_tum',
           'read_tum', 'load_ground_truth', 'relative_poses', 'LabelWriter', 'Labels', 'load_labels',
           'load_scenario', 'write_yaml', 'world_of', 'recording_source', 'true_poses', 'same_scene']

GROUND_TRUTH = 'ground_truth.tum'
GROUND_TRUTH_DENSE = 'ground_truth_dense.tum'
LABELS = 'labels.npz'
SCENARIO = 'scenario.yaml'
NOTE = 'README.md'


def sidecar_path(bag_path: str | Path, name: str) -> Path:
    """Where the sidecar ``name`` of a bag lives: inside a ROS 2 bag directory, or ``<stem>.<name>`` next
    to a ROS 1 ``.bag`` file. A ``.db3``/``.mcap`` file inside a ROS 2 bag directory stands for that
    directory. The bag need not exist yet."""
    path = Path(bag_path).expanduser()
    if path.suffix == '.bag':
        return path.with_name(f'{path.stem}.{name}')
    if path.suffix in ('.db3', '.mcap') and (path.parent / 'metadata.yaml').is_file():
        return path.parent / name
    return path / name


def relative_poses(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses expressed relative to the first one (``inv(T_0) T_k``)."""
    first_inverse = np.linalg.inv(poses[0])
    return np.einsum('ij,njk->nik', first_inverse, poses)


def write_tum(path: str | Path, stamps_ns: np.ndarray, poses: np.ndarray) -> None:
    """Ground-truth TUM file: a header line, then ``timestamp tx ty tz qx qy qz qw`` (nm / 1e-12 precision)."""
    Path(path).write_text('# timestamp tx ty tz qx qy qz qw\n' + tum_lines(stamps_ns, poses, 9, 12))


def load_ground_truth(bag_path: str | Path, dense: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
    """Ground truth beside a bag: (stamps [ns] int64 (N,), lidar poses (N, 4, 4) relative to the first),
    or None when the bag has none. ``dense`` selects the IMU-rate file."""
    path = sidecar_path(bag_path, GROUND_TRUTH_DENSE if dense else GROUND_TRUTH)
    if not path.is_file():
        return None
    return read_tum(path)


def load_scenario(bag_path: str | Path) -> dict[str, Any] | None:
    """The scenario.yaml beside a bag, or None."""
    path = sidecar_path(bag_path, SCENARIO)
    if not path.is_file():
        return None
    return yaml.safe_load(path.read_text())


def map_distance_to_scene(bag_path: str | Path, map_points: np.ndarray, stamp_ns: int,
                          lidar_pose_in_map: np.ndarray) -> np.ndarray | None:
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
    return build_world(config['scenario'], int(config['seed']), float(config.get('turn_rate', 0.0)),
                       None if route_start is None else float(route_start), bool(config.get('reverse', False)))


def recording_source(bag_path: str | Path) -> dict[str, Any]:
    """What a saved map notes about the recording it was made from (its bundle's ``source``): the bag, and for a
    simulated one its configuration and start stamp, from which :func:`true_poses` gives the true sensor poses."""
    source: dict[str, Any] = {'bag': str(Path(bag_path).expanduser().resolve())}
    scenario = load_scenario(bag_path)
    if scenario is not None:
        source['simulated'] = {'config': scenario['config'],
                               'start_stamp_ns': int(scenario['recording']['start_stamp_ns'])}
    return source


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

_ZIP_DATE = (1980, 1, 1, 0, 0, 0)   # fixed member dates: identical inputs give identical files


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
        np.lib.format.write_array(buffer, array if array.ndim == 0 else np.ascontiguousarray(array),
                                  allow_pickle=False)
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


class Labels:
    """Read access to a labels.npz: ``labels[k]`` is scan k's uint32 array."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._npz = np.load(self.path, allow_pickle=False)
        self.stamps = self._npz['stamps']
        self.classes: list[str] = json.loads(str(self._npz['classes'].reshape(-1)[0]))

    def __len__(self) -> int:
        return len(self.stamps)

    def __getitem__(self, scan: int) -> np.ndarray:
        if not 0 <= scan < len(self):
            raise IndexError(f'scan {scan} out of range (0..{len(self) - 1})')
        return self._npz[f's{scan}']

    def class_names(self, labels: np.ndarray) -> np.ndarray:
        """Class name of each label value."""
        return np.asarray(self.classes, dtype=object)[labels]

    def close(self) -> None:
        self._npz.close()


def load_labels(bag_path: str | Path) -> Labels | None:
    """The labels.npz beside a bag, or None."""
    path = sidecar_path(bag_path, LABELS)
    return Labels(path) if path.is_file() else None
