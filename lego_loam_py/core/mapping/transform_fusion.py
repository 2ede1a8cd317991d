"""transformFusion: the 10 Hz odometry corrected by the latest mapping result (docs/original.md §6.4).

``T_mapped = T_aft · T_bef^-1 · T_sum``: the odometry pose ``T_sum`` of every scan, moved by the correction
the last mapping step found (``T_aft`` is the optimised pose of the odometry pose ``T_bef``). Poses are
4x4 matrices in camera_init (LOAM camera axes).

In localization (``max_correction_age_ns`` given) a pose is published only while the correction comes from a
mapping step at most that long before it: before the first fix in the saved map the odometry is in a frame of
its own, and once tracking is lost the old correction soon no longer holds.
"""

from __future__ import annotations

import numpy as np

from lego_loam_py.core.frames import invert_pose
from lego_loam_py.core.validation import MAX_POSITION, vector_problem

__all__ = ['TransformFusion']


class TransformFusion:
    def __init__(self, max_correction_age_ns: int | None = None):
        self.correction = np.eye(4)  # T_aft · T_bef^-1
        self.mapped_steps = 0
        self.max_correction_age_ns = max_correction_age_ns
        self.correction_stamp_ns: int | None = None  # of the mapping step the correction comes from

    def on_mapped(self, aft: np.ndarray, bef: np.ndarray, stamp_ns: int | None = None) -> None:
        """A mapping result of the scan stamped ``stamp_ns``: the optimised pose ``aft`` of the odometry pose
        ``bef`` (4x4 each)."""
        self.correction = aft @ invert_pose(bef)
        self.mapped_steps += 1
        self.correction_stamp_ns = stamp_ns

    def integrate(self, odometry: np.ndarray) -> np.ndarray:
        """The map-corrected pose of an odometry pose (4x4)."""
        return self.correction @ odometry

    def publishable(self, stamp_ns: int) -> bool:
        """Whether the fused pose of the scan stamped ``stamp_ns`` goes out: always, unless a maximum age of the
        correction was given (localization) and the correction is older or there is none yet."""
        if self.max_correction_age_ns is None:
            return True
        return (
            self.correction_stamp_ns is not None
            and abs(stamp_ns - self.correction_stamp_ns) <= self.max_correction_age_ns
        )

    def reset(self) -> None:
        self.__init__(self.max_correction_age_ns)

    def health_problem(self) -> str | None:
        """Why the map correction is poisoned (non-finite, absurd, or not a rigid transform), or None."""
        problem = vector_problem('the map correction', self.correction, MAX_POSITION, 'm')
        if problem is None and np.abs(self.correction[:3, :3] @ self.correction[:3, :3].T - np.eye(3)).max() > 1e-3:
            problem = 'the map correction is not a rigid transform'
        return problem
