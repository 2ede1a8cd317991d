"""transformFusion: the 10 Hz odometry corrected by the latest mapping result (docs/original.md §6.4).

``T_mapped = T_aft · T_bef^-1 · T_sum``: the odometry pose ``T_sum`` of every scan, moved by the correction
the last mapping step found (``T_aft`` is the optimised pose of the odometry pose ``T_bef``). Poses are
4x4 matrices in camera_init (LOAM camera axes).

In localization (``max_correction_age_ns`` given) a pose is published only while the correction comes from a
mapping step at most that long before it: before the first fix in the saved map the odometry is in a frame of
its own, and once tracking is lost the old correction soon no longer holds.

The fused pose's covariance (:attr:`TransformFusion.covariance`; conventions of :mod:`lego_loam_py.core.frames`: in
camera_init, position [m²] in its axes, rotation [rad²] about them, ROS order) is the mapped pose's compounded with
what the odometry's covariance grew by since the odometry pose that mapping step started from
(:func:`~lego_loam_py.core.frames.relative_covariance` of the two odometry covariances along its chain).
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from lego_loam_py.core.frames import compound_covariance, invert_pose, relative_covariance
from lego_loam_py.core.validation import MAX_POSITION, vector_problem

__all__ = ['TransformFusion']


def _frozen(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


class TransformFusion:
    def __init__(self, max_correction_age_ns: int | None = None):
        self.correction = _frozen(np.eye(4))  # T_aft · T_bef^-1 (replaced, never changed in place: see health_problem)
        self.mapped_steps = 0
        self.max_correction_age_ns = max_correction_age_ns
        self.correction_stamp_ns: int | None = None  # of the mapping step the correction comes from
        self.covariance = np.zeros((6, 6))  # of the last fused pose (see the module docstring)
        # The recent odometry poses and covariances by stamp (a mapping result refers to one of them), and the
        # mapped pose, its covariance, the odometry pose it came from and that one's covariance.
        self._odometry: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._mapped: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._checked: tuple[np.ndarray, str | None] | None = None  # (the correction, its health_problem)

    # (Mapping lags the odometry by a few scans, at most a few seconds when loop closure holds it up.)
    HISTORY = 400

    def on_mapped(
        self, aft: np.ndarray, bef: np.ndarray, stamp_ns: int | None = None, aft_covariance: np.ndarray | None = None
    ) -> None:
        """A mapping result of the scan stamped ``stamp_ns``: the optimised pose ``aft`` of the odometry pose
        ``bef`` (4x4 each), ``aft``'s covariance (6x6, camera_init) if known."""
        self.correction = _frozen(aft @ invert_pose(bef))
        self.mapped_steps += 1
        self.correction_stamp_ns = stamp_ns
        bef_covariance = self._odometry_covariance(stamp_ns)
        if aft_covariance is not None and bef_covariance is not None:
            self._mapped = (np.asarray(aft, float), np.asarray(aft_covariance, float), bef, bef_covariance)

    def _odometry_covariance(self, stamp_ns: int | None) -> np.ndarray | None:
        """The covariance of the odometry pose stamped ``stamp_ns`` (the nearest stamp kept), or None."""
        if stamp_ns is None or not self._odometry:
            return None
        exact = self._odometry.get(stamp_ns)  # (the usual case: the mapping step of a scan fused here)
        if exact is not None:
            return exact[1]
        nearest = min(self._odometry, key=lambda stamp: abs(stamp - stamp_ns))
        return self._odometry[nearest][1]

    def integrate(
        self, odometry: np.ndarray, covariance: np.ndarray | None = None, stamp_ns: int | None = None
    ) -> np.ndarray:
        """The map-corrected pose of an odometry pose (4x4); with the odometry's ``covariance`` (6x6, camera_init)
        and its stamp, :attr:`covariance` becomes the fused pose's."""
        if covariance is not None:
            covariance = np.asarray(covariance, dtype=float)
            if stamp_ns is not None:
                self._odometry[stamp_ns] = (odometry, covariance)
                while len(self._odometry) > self.HISTORY:
                    self._odometry.popitem(last=False)
            if self._mapped is None:  # no mapped pose yet: the odometry's, moved by the correction
                self.covariance = compound_covariance(self.correction, np.zeros((6, 6)), odometry, covariance)
            else:
                aft, aft_covariance, bef, bef_covariance = self._mapped
                since = relative_covariance(bef, bef_covariance, odometry, covariance)
                self.covariance = compound_covariance(aft, aft_covariance, invert_pose(bef) @ odometry, since)
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
        checked = self._checked
        if checked is not None and checked[0] is self.correction:  # (asked for every scan; set once per mapping step)
            return checked[1]
        problem = vector_problem('the map correction', self.correction, MAX_POSITION, 'm')
        if problem is None and np.abs(self.correction[:3, :3] @ self.correction[:3, :3].T - np.eye(3)).max() > 1e-3:
            problem = 'the map correction is not a rigid transform'
        self._checked = (self.correction, problem)
        return problem
