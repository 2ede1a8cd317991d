"""A trajectory: stamps, poses, and the frame they are in, as the outputs, the evaluation, localization and the viewer
pass it around.

Two frames (:mod:`lego_loam_py.core.frames`): ``'map'``, the lidar's poses (REP-103 axes: x forward, y left, z up)
in the map frame, as files and the evaluation want them; ``'camera_init'``, the LOAM camera axes the pipeline
works in (x left, y up, z forward). :meth:`Trajectory.to` changes between them for the whole stack at once (the
axis change is a permutation: exact). A trajectory unpacks as ``stamps, poses = trajectory``, the pair the
evaluation functions take.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

__all__ = ['Trajectory', 'FRAMES']

FRAMES = ('map', 'camera_init')


@dataclass(frozen=True)
class Trajectory:
    """``stamps_ns`` (n,) int64 [ns], ``poses`` (n, 4, 4) of the sensor in ``frame`` (one of :data:`FRAMES`)."""

    stamps_ns: np.ndarray
    poses: np.ndarray
    frame: str = 'map'

    def __post_init__(self):
        stamps = np.asarray(self.stamps_ns, dtype=np.int64).reshape(-1)
        poses = np.asarray(self.poses, dtype=float).reshape(-1, 4, 4)
        if len(stamps) != len(poses):
            raise ValueError(f'{len(stamps)} stamps for {len(poses)} poses')
        if self.frame not in FRAMES:
            raise ValueError(f'frame must be one of {FRAMES}, got {self.frame!r}')
        object.__setattr__(self, 'stamps_ns', stamps)
        object.__setattr__(self, 'poses', poses)

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def __iter__(self) -> Iterator[np.ndarray]:
        """``stamps, poses = trajectory``."""
        return iter((self.stamps_ns, self.poses))

    def to(self, frame: str) -> Trajectory:
        """The same poses in ``frame``."""
        if frame == self.frame:
            return self
        from lego_loam_py.core.frames import camera_pose_to_lidar, lidar_pose_to_camera

        change = camera_pose_to_lidar if frame == 'map' else lidar_pose_to_camera
        return Trajectory(self.stamps_ns, change(self.poses), frame)

    def select(self, keep: np.ndarray) -> Trajectory:
        """The poses where ``keep`` (boolean or index array) says."""
        return Trajectory(self.stamps_ns[keep], self.poses[keep], self.frame)

    @property
    def positions(self) -> np.ndarray:
        """(n, 3) positions [m]."""
        return self.poses[:, :3, 3]
