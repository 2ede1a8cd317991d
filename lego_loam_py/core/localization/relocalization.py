"""Where in the saved map is the robot? Candidate places and their verification (localization, issue 18).

A relocalization attempt takes the latest scans (the last few mapping inputs, joined by the odometry into the
sensor frame of the newest, REP-103 lidar axes) and:

1. **Candidates.** The Scan Context descriptor of those points, levelled by the odometry's roll and pitch, is
   looked up among the map's keyframes (:class:`~lego_loam_py.core.loop.place_recognition.PlaceDatabase`): the best
   ``relocalization_candidates`` places under ``relocalization_threshold``, each with the yaw between the two
   views. With a hint (an initial pose, /initialpose, the pose before the odometry restarted) only keyframes within
   its radius count, and the hint itself is tried first as it is.
2. **Verification.** Each candidate is registered to the map around it (point-to-plane ICP, coarse to fine,
   :func:`~lego_loam_py.core.loop.registration.register`) from the keyframe's position and the descriptor's
   heading. It passes when enough of the scan lies on the map (``min_overlap``), the fit is tight (``max_rmse``),
   every direction is constrained (``min_constraint``: the ground alone fixes only height, roll and pitch) and the
   scan's edge points (poles, corners, trunks) lie on the map's edges (``min_edge_overlap``): another place that
   shares only its road and a wall with this one fails the last.
3. **Ambiguity.** Two places that both pass but lie more than ``ambiguity_distance`` apart: no fix (look-alike
   places, e.g. a row of identical buildings); the next attempt, a few metres on, may tell them apart.

The winner is a hypothesis only: :class:`~lego_loam_py.core.localization.localizer.Localization` tracks from it for
``confirm_steps`` before anything is published.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.frames import camera_to_lidar, invert_pose, rot_z, transform_points
from lego_loam_py.core.localization.prior_map import PriorMap, heading, levelling, thinned
from lego_loam_py.core.loop.registration import register
from lego_loam_py.core.params.types import Params

__all__ = ['Hint', 'Verification', 'Attempt', 'Relocalizer', 'scan_points_lidar']

_MAX_SOURCE_POINTS = 6000  # the scan side of a verifying registration (as the loop closure's)


@dataclass(frozen=True)
class Hint:
    """Where the robot probably is: ``pose`` (4x4, map frame, REP-103) at the odometry pose ``odometry`` (4x4,
    the odometry's frame, REP-103), within ``radius`` [m]; ``origin`` says who gave it."""

    pose: np.ndarray
    odometry: np.ndarray
    radius: float
    origin: str = 'initial pose'

    def now(self, odometry: np.ndarray) -> np.ndarray:
        """The hinted pose moved on by the odometry since the hint was given."""
        return self.pose @ invert_pose(self.odometry) @ odometry


@dataclass(frozen=True)
class Verification:
    """A candidate place and what its registration said."""

    keyframe: int  # the map keyframe it was found at (-1: the hint itself)
    score: float  # Scan Context distance (nan for the hint)
    pose: np.ndarray  # 4x4 sensor pose in the map (REP-103) the registration found
    overlap: float
    rmse: float  # [m]
    constraint: float
    edge_overlap: float
    accepted: bool
    reason: str  # 'verified' or why not
    cpu_ms: float


@dataclass(frozen=True)
class Attempt:
    """One relocalization attempt: the hypothesis (4x4 sensor pose in the map, REP-103) or None, and why."""

    pose: np.ndarray | None
    verifications: tuple[Verification, ...]
    reason: str  # 'verified', 'no candidate place', 'ambiguous: ...', or the best rejection


class Relocalizer:
    """Relocalization attempts in one :class:`~lego_loam_py.core.localization.prior_map.PriorMap`."""

    def __init__(self, prior: PriorMap, params: Params):
        self.prior = prior
        self.params = params
        import open3d  # noqa: F401  (its first import costs about 0.5 s of CPU: when the map loads, not in an attempt)

    def attempt(
        self, source_lidar: np.ndarray, edges_lidar: np.ndarray, odometry_lidar: np.ndarray, hint: Hint | None = None
    ) -> Attempt:
        """Look for the place of the newest scan: ``source_lidar`` (N, 3) its points (and the few before it) in its
        sensor frame, ``edges_lidar`` (M, 3) the edge points among them, ``odometry_lidar`` (4x4) its odometry pose
        (only its roll and pitch are used, to level the descriptor), REP-103 axes."""
        lo = self.params.localization
        prior = self.prior
        query = prior.descriptor(source_lidar, odometry_lidar)
        guesses: list[tuple[int, float, np.ndarray]] = []  # (keyframe, score, initial pose)
        allowed = None
        if hint is not None:
            hinted = hint.now(odometry_lidar)
            guesses.append((-1, float('nan'), hinted))
            allowed = np.linalg.norm(prior.poses_lidar[:, :2, 3] - hinted[:2, 3], axis=1) <= hint.radius
        tilt = levelling(odometry_lidar)
        for match in prior.places.query(query, allowed, count=lo.relocalization_candidates):
            if match.distance > lo.relocalization_threshold:
                continue
            keyframe = prior.poses_lidar[match.key]
            initial = np.eye(4)
            initial[:3, :3] = rot_z(heading(keyframe) + match.yaw) @ tilt
            initial[:3, 3] = keyframe[:3, 3]
            guesses.append((match.key, match.distance, initial))
        if not guesses:
            return Attempt(None, (), 'no candidate place (no keyframe looks like the scan)')
        source = thinned(source_lidar, self.params.loop_closure.history_keyframe_leaf_size, _MAX_SOURCE_POINTS)
        verifications = tuple(
            self.verify(source, edges_lidar, initial, keyframe, score) for keyframe, score, initial in guesses
        )
        accepted = [v for v in verifications if v.accepted]
        if hint is not None:  # a place far from the hint contradicts it
            hinted = hint.now(odometry_lidar)
            accepted = [v for v in accepted if np.linalg.norm(v.pose[:2, 3] - hinted[:2, 3]) <= hint.radius + 2.0]
        if not accepted:
            best = min(verifications, key=lambda v: (not math.isfinite(v.rmse), -v.overlap))
            return Attempt(None, verifications, best.reason)
        for a in accepted:
            for b in accepted:
                apart = float(np.linalg.norm(a.pose[:3, 3] - b.pose[:3, 3]))
                if apart > lo.ambiguity_distance:
                    return Attempt(None, verifications, f'ambiguous: two places {apart:.0f} m apart both fit')
        best = max(accepted, key=lambda v: (v.edge_overlap, v.overlap))
        return Attempt(best.pose, verifications, 'verified')

    def verify(
        self, source: np.ndarray, edges: np.ndarray, initial: np.ndarray, keyframe: int, score: float
    ) -> Verification:
        """Register ``source`` (sensor frame, lidar axes) to the map around ``initial`` (4x4 guess of the sensor in
        the map) and judge the fit by the gates of the module docstring."""
        lo, lc = self.params.localization, self.params.loop_closure
        start = time.process_time()
        target = self.prior.region(initial[:3, 3], lc.history_keyframe_leaf_size)
        if len(target) < 100:
            return Verification(
                keyframe,
                score,
                initial,
                0.0,
                float('inf'),
                0.0,
                0.0,
                False,
                'no map there',
                (time.process_time() - start) * 1e3,
            )
        fit = register(
            source,
            target,
            initial,
            lc.registration_distances,
            lc.registration_iterations,
            lo.tracking_inlier_distance,
            lc.registration_points,
            lc.min_registration_sigma,
        )
        edge_overlap = 0.0
        if len(edges):
            gap, _ = self.prior.edge_tree().query(
                transform_points(fit.pose, edges[:, :3]), distance_upper_bound=lo.tracking_inlier_distance
            )
            edge_overlap = float(np.isfinite(gap).mean())
        reason = fit.gate_failure(lo.min_overlap, lo.max_rmse, lo.min_constraint)
        if not reason and edge_overlap < lo.min_edge_overlap:
            reason = f'edge overlap {edge_overlap:.2f} < {lo.min_edge_overlap:g}'
        reason = reason or 'verified'
        return Verification(
            keyframe,
            score,
            fit.pose,
            fit.overlap,
            fit.rmse,
            fit.constraint,
            edge_overlap,
            reason == 'verified',
            reason,
            (time.process_time() - start) * 1e3,
        )


def scan_points_lidar(recent: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """The points of the ``recent`` mapping inputs ((odometry 4x4 camera axes, corner, surface) each, clouds in their
    sensor frames, camera axes) in the sensor frame of the newest, REP-103 axes: (all points, edge points)."""
    newest = recent[-1][0]
    to_newest = [invert_pose(newest) @ odometry for odometry, _, _ in recent]
    points = np.concatenate(
        [
            transform_points(m, np.concatenate([c, s])[:, :3].astype(np.float64))
            for m, (_, c, s) in zip(to_newest, recent)
        ]
    )
    edges = np.concatenate(
        [transform_points(m, c[:, :3].astype(np.float64)) for m, (_, c, _) in zip(to_newest, recent)]
    )
    return camera_to_lidar(points), camera_to_lidar(edges)
