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

:func:`sidecar_path` and the loaders find these beside any bag (the demo, the evaluation, the map bundle's
``source`` and the benchmarks read them); the simulator (:mod:`lego_loam_py.sim.output`) writes them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lego_loam_py.core.trajectory import Trajectory
from lego_loam_py.formats import read_tum

__all__ = [
    'GROUND_TRUTH',
    'GROUND_TRUTH_DENSE',
    'LABELS',
    'SCENARIO',
    'NOTE',
    'sidecar_path',
    'load_ground_truth',
    'load_scenario',
    'recording_source',
    'Labels',
    'load_labels',
]

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


def load_ground_truth(bag_path: str | Path, dense: bool = False) -> Trajectory | None:
    """Ground truth beside a bag: the lidar's trajectory (stamps [ns], poses relative to the first, REP-103 axes:
    frame 'map'), or None when the bag has none. ``dense`` selects the IMU-rate file."""
    path = sidecar_path(bag_path, GROUND_TRUTH_DENSE if dense else GROUND_TRUTH)
    if not path.is_file():
        return None
    return Trajectory(*read_tum(path), 'map')


def load_scenario(bag_path: str | Path) -> dict[str, Any] | None:
    """The scenario.yaml beside a bag, or None."""
    path = sidecar_path(bag_path, SCENARIO)
    if not path.is_file():
        return None
    return yaml.safe_load(path.read_text())


def recording_source(bag_path: str | Path) -> dict[str, Any]:
    """What a saved map notes about the recording it was made from (its bundle's ``source``): the bag, and for a
    simulated one its configuration and start stamp, from which :func:`true_poses` gives the true sensor poses."""
    source: dict[str, Any] = {'bag': str(Path(bag_path).expanduser().resolve())}
    scenario = load_scenario(bag_path)
    if scenario is not None:
        source['simulated'] = {
            'config': scenario['config'],
            'start_stamp_ns': int(scenario['recording']['start_stamp_ns']),
        }
    return source


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
