"""The mapper: what mapOptimization's node and the offline pipeline drive, whether it builds a map
(:class:`~lego_loam_py.core.mapping.map_optimization.MapOptimization`) or tracks the robot in a saved one
(:class:`~lego_loam_py.core.localization.localizer.Localization`).

Both take each scan's odometry and clouds (:meth:`Mapper.process`), say whether their state is poisoned and heal it,
follow an odometry that restarted, and give the map around the robot for display. Only a mapper that
``builds_map`` has keyframes, loops and a map to save; the callers ask that, not the class.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ['Mapper']


@runtime_checkable
class Mapper(Protocol):
    """See the module docstring. Poses are camera_init's (camera axes); ``lock`` guards the state between the
    node's threads."""

    builds_map: bool  # keyframes, loops, ``detect_loop``/``close_loop`` and ``save`` exist
    lock: object
    imu: object  # its IMU buffer (core.imu.ImuBuffer), for the roll and pitch blend and the IMU check

    def process(
        self,
        stamp_ns: int,
        transform_sum: np.ndarray,
        corner_last: np.ndarray,
        surf_last: np.ndarray,
        outlier_last: np.ndarray,
        odometry_covariance: np.ndarray | None = None,
    ):
        """One mapping input; the step (core.mapping.map_optimization.MappingStep) or None when none was due.
        ``odometry_covariance``: the odometry pose's 6x6 covariance (camera_init; None: unknown)."""

    def health_problem(self) -> str | None:
        """Why the state is poisoned (non-finite or impossible values), or None."""

    def heal(self) -> str:
        """Reset what is poisoned, keep what is sound; says what was done."""

    def reanchor(self, jump, pose: np.ndarray, transform_sum: np.ndarray) -> None:
        """The odometry restarted (core.mapping.odometry_continuity): carry on from the last mapped pose."""

    def keyframe_poses(self) -> np.ndarray:
        """(K, 6) the map's keyframe poses."""

    def global_map(self, radius: float | None = None) -> np.ndarray:
        """The map around the robot, for display."""

    def registered_scan(self) -> np.ndarray:
        """The last scan's features where the last step put them."""
