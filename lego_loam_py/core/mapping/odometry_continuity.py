"""Odometry restarts as mapping sees them, and re-anchoring the mapper at its last pose.

mapOptimization predicts each scan's map pose from the odometry: ``T_aft · T_bef^-1 · T_sum`` (the optimised
pose and the odometry pose of its last step, the new odometry pose; all 4x4 in LOAM camera axes). When the
odometry restarts (featureAssociation restarted or reset, so its frame starts again at about the identity),
that prediction would drag the map to the odometry's new origin. :class:`OdometryContinuity` tells such a
restart from motion, and :func:`anchored_transform_bef` gives the ``T_bef`` that makes the prediction continue
from the last mapped pose instead, moved on at the last speed over the gap. Used by the mapOptimization node
and by the offline mode alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.frames import invert_pose, matrix_to_pose6, pose6_to_matrix, scaled_motion

__all__ = [
    'OdometryJump',
    'OdometryContinuity',
    'anchored_transform_bef',
    'JUMP_M',
    'JUMP_M_PER_S',
    'JUMP_RAD',
    'JUMP_RAD_PER_S',
    'MAX_EXTRAPOLATION_S',
]

# Further than any vehicle moves between two odometry poses dt seconds apart: JUMP_M + JUMP_M_PER_S * dt [m],
# or JUMP_RAD + JUMP_RAD_PER_S * dt [rad].
JUMP_M, JUMP_M_PER_S = 5.0, 30.0
JUMP_RAD, JUMP_RAD_PER_S = 1.0, 6.0
MAX_EXTRAPOLATION_S = 10.0  # over a longer gap the vehicle is assumed to have stopped


def _angle(rotation: np.ndarray) -> float:
    """Angle of a 3x3 rotation [rad]."""
    return float(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)))


@dataclass(frozen=True)
class OdometryJump:
    """An odometry pose that does not continue the ones before: by how much, over what time, and why."""

    distance_m: float
    angle_rad: float
    dt_s: float
    new_publisher: bool  # another process publishes the odometry now
    previous: tuple[int, np.ndarray]  # (stamp [ns], 4x4 pose) of the last pose before the jump
    older: tuple[int, np.ndarray] | None  # the one before it (for the speed over the gap), if any

    def describe(self) -> str:
        why = 'featureAssociation restarted' if self.new_publisher else 'featureAssociation restarted?'
        return (
            f'the odometry jumped by {self.distance_m:.1f} m and {np.degrees(self.angle_rad):.0f} deg in '
            f'{self.dt_s:.1f} s ({why}): re-anchored at the last mapped pose, moved on at the last speed '
            'over the gap'
        )


class OdometryContinuity:
    """The last two odometry poses a mapper took; :meth:`check` says whether the next one continues them."""

    def __init__(self):
        self._last: tuple[int, np.ndarray, object] | None = None  # (stamp [ns], 4x4, publisher)
        self._older: tuple[int, np.ndarray, object] | None = None

    def forget(self) -> None:
        """Start afresh (the mapping was reset): the next pose continues nothing."""
        self._last = self._older = None

    def check(self, stamp_ns: int, pose: np.ndarray, publisher=None) -> OdometryJump | None:
        """Take the odometry pose ``pose`` (4x4, camera axes) of ``stamp_ns``, from ``publisher`` (any id; None:
        unknown). Returns the jump when it does not continue the last one: it comes from another publisher and
        moved, or it moved further than any vehicle, or it is back at the origin after moving."""
        previous, self._last = self._last, (stamp_ns, pose, publisher)
        if previous is None:
            return None
        self._older, older = previous, self._older
        dt = max((stamp_ns - previous[0]) * 1e-9, 0.0)
        step = invert_pose(previous[1]) @ pose
        distance = float(np.linalg.norm(step[:3, 3]))
        angle = _angle(step[:3, :3])
        implausible = distance > JUMP_M + JUMP_M_PER_S * dt or angle > JUMP_RAD + JUMP_RAD_PER_S * dt
        # A restarted featureAssociation starts again at (about) the identity, usually after a gap in time.
        back_at_origin = (
            (distance > 2.0 or angle > 0.5) and np.linalg.norm(pose[:3, 3]) < 1.5 and _angle(pose[:3, :3]) < 0.35
        )
        new_publisher = (
            publisher is not None
            and previous[2] is not None
            and publisher != previous[2]
            and (distance > 0.5 or angle > 0.1)
        )
        if not (implausible or back_at_origin or new_publisher):
            return None
        self._older = None  # the one before belongs to the old odometry frame
        return OdometryJump(distance, angle, dt, new_publisher, previous[:2], older[:2] if older else None)


def anchored_transform_bef(
    jump: OdometryJump, pose: np.ndarray, transform_aft: np.ndarray, transform_bef: np.ndarray
) -> np.ndarray:
    """The mapper's new ``T_bef`` (six-vector) after ``jump``: with it, ``T_aft · T_bef^-1 · pose`` is the map
    pose of the last odometry before the jump (as the old ``transform_aft`` / ``transform_bef`` predicted it),
    moved on at the speed before it over the gap, up to MAX_EXTRAPOLATION_S."""
    aft = pose6_to_matrix(transform_aft)
    predicted = aft @ invert_pose(pose6_to_matrix(transform_bef)) @ jump.previous[1]
    older = jump.older
    if older is not None and jump.previous[0] > older[0] and jump.dt_s <= MAX_EXTRAPOLATION_S:
        # Constant velocity over the gap (the vehicle did not stop while the odometry was away).
        motion = invert_pose(older[1]) @ jump.previous[1]
        predicted = predicted @ scaled_motion(motion, jump.dt_s / ((jump.previous[0] - older[0]) * 1e-9))
    return matrix_to_pose6(pose @ invert_pose(predicted) @ aft)
