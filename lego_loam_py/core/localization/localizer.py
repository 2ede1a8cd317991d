"""mapOptimization in localization mode: each scan registered against a saved map, never building a new one.

``map_optimization.mode: localization`` replaces :class:`~lego_loam_py.core.mapping.map_optimization.MapOptimization` by
:class:`Localization`, with the same interface and the same output: a :class:`MappingStep` per step, whose
``transform_aft`` is the sensor's pose in the saved map's frame (LOAM camera axes of its ``camera_init``) and whose
``transform_bef`` is the odometry pose it was computed from. transformFusion and every consumer work unchanged,
and /aft_mapped_to_init and /integrated_to_init come out in the saved map's frame.

States (:attr:`Localization.state`):

* ``relocalizing``: no fix yet. Each step is a relocalization attempt
  (:mod:`lego_loam_py.core.localization.relocalization`), near the initial pose when one was given
  (``localization.initial_pose``, /initialpose), else anywhere in the map. Nothing is published.
* ``confirming``: an attempt verified a place; tracking from it must hold for ``confirm_steps`` steps (each
  registered within ``max_correction`` of what the odometry predicts, with ``min_tracking_overlap`` of the scan on
  the map) before it becomes the fix. Nothing is published; a step that fails sends it back to searching.
* ``localized``: tracking. The pose predicted from the odometry (``T_aft · T_bef^-1 · T_sum``, as the mapping
  predicts it) is refined by the mapping's scan-to-map registration (:mod:`lego_loam_py.core.mapping.scan_to_map`)
  against the saved map around it, and published. A step that fails the tracking gates is not published and keeps the
  last correction; ``lost_after_steps`` in a row, or a gap in the data longer than ``max_gap`` (a kidnapped robot, a
  sensor that stopped), and it is lost.
* ``lost``: as relocalizing, after a fix.

The saved map is never modified; localization adds no keyframe (it builds no map: nothing to save,
writes nothing). Poses and clouds are in LOAM camera axes as in the mapping; the relocalization works in REP-103
axes, as the map bundle's descriptors and the place recognition do.
"""

from __future__ import annotations

import math
import threading
import time as _time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from lego_loam_py.core.frames import (
    camera_pose_to_lidar,
    invert_pose,
    lidar_pose_to_camera,
    matrix_to_pose6,
    pose6_to_matrix,
    rot_x,
    rot_y,
    rot_z,
    transform_cloud,
    transform_points,
)
from lego_loam_py.core.gauss_newton import DegeneracyProjection
from lego_loam_py.core.imu.buffer import ImuBuffer, imu_mounting
from lego_loam_py.core.localization.prior_map import PriorMap, levelling
from lego_loam_py.core.localization.relocalization import Attempt, Hint, Relocalizer, Verification, scan_points_lidar
from lego_loam_py.core.mapping.covariance import MAX_REGISTRATION_VARIANCE, registration_covariance
from lego_loam_py.core.mapping.map_bundle import check_compatible, read_bundle
from lego_loam_py.core.mapping.map_optimization import MappingStep
from lego_loam_py.core.mapping.odometry_continuity import OdometryJump, anchored_transform_bef
from lego_loam_py.core.mapping.scan_to_map import register_scan_to_map
from lego_loam_py.core.params.types import Params
from lego_loam_py.core.validation import pose6_problem
from lego_loam_py.core.voxel import voxel_downsample

__all__ = ['Localization', 'LocalizationEvent', 'LocalizationStatus', 'STATES', 'HINT_ATTEMPTS']

STATES = ('relocalizing', 'confirming', 'localized', 'lost')
HINT_ATTEMPTS = 10  # failed attempts near an initial pose before the search widens to the whole map
_RECENT_INPUTS = 3  # mapping inputs joined for a relocalization attempt (a denser view of the place)
OVERLAP_SAMPLE = 1000  # surface points at most a tracking step's overlap is measured on (an even sample)
_F32 = np.float32


@dataclass(frozen=True)
class LocalizationEvent:
    """A fix, a loss or a hint, for the log and the run's summary."""

    stamp_ns: int
    kind: str  # 'fix', 'lost', 'rejected' (a verified place that tracking did not confirm), 'hint'
    detail: str


@dataclass(frozen=True)
class LocalizationStatus:
    """What the node says on /localization_status and in its throttled log line."""

    state: str
    localized: bool
    message: str
    values: dict = field(default_factory=dict)


class Localization:
    """Localization in a saved map (see the module docstring); built by :meth:`load` from the parameters. A
    :class:`~lego_loam_py.core.mapping.mapper.Mapper` that builds no map: the saved one is never changed."""

    builds_map = False

    def __init__(self, params: Params, prior: PriorMap, warnings: list[str] | None = None):
        self.params = params
        self.prior = prior
        self.warnings = list(warnings or [])  # what differs between the map's parameters and these
        self.relocalizer = Relocalizer(prior, params)
        self.imu = ImuBuffer(
            params.feature_association.imu_que_length,
            params.feature_association.gravity,
            params.sensor.scan_period,
            imu_mounting(params),
        )
        self.lock = threading.RLock()
        self.map_source: dict = {}
        self.last_maps = (np.zeros((0, 4), _F32), np.zeros((0, 4), _F32))
        self.last_scan = (np.zeros((0, 4), _F32), np.zeros((0, 4), _F32))
        self.events: deque[LocalizationEvent] = deque(maxlen=1000)  # the latest
        self.event_count = 0  # events recorded in all
        self.verifications: deque[tuple[int, Verification]] = deque(maxlen=1000)  # the latest (stamp, result)
        self.counters: dict[str, int] = {}
        self._degeneracy = DegeneracyProjection(6)
        self.first_input_ns: int | None = None
        self.first_fix_ns: int | None = None
        self.restart()

    @classmethod
    def load(cls, params: Params) -> Localization:
        """Localization in the bundle of ``map_optimization.map_path`` (MapBundleError when it cannot be used)."""
        bundle = read_bundle(params.map_optimization.map_path)
        warnings = check_compatible(bundle, params)
        return cls(params, PriorMap(bundle, params), warnings)

    def restart(self, from_the_start: bool = True) -> None:
        """Forget where the robot is and relocalize from the next input: ``from_the_start`` (a new timeline, a bag
        played again) with ``localization.initial_pose`` when there is one, else (a poisoned state) anywhere."""
        with self.lock:
            self.transform_sum, self.transform_bef, self.transform_aft = np.zeros(6), np.zeros(6), np.zeros(6)
            self.state = 'relocalizing'
            self.hint: Hint | None = None
            self._pending_hint: tuple | None = None
            self._hint_attempts = 0
            self._recent: deque = deque(maxlen=_RECENT_INPUTS)
            self._last_processing_ns: int | None = None
            self._bad_steps = self._confirmed = self.attempts_since_fix = 0
            self.withheld = False  # the last step gave no output (no fix)
            self.last_reason = 'no scan yet'
            self.last_overlap = float('nan')
            self.latest_odometry_ns = 0
            self._searching = 'relocalizing'
            pose = self.params.localization.initial_pose
            if pose and from_the_start:  # [x, y, yaw] or [x, y, z, roll, pitch, yaw]
                self.set_initial_pose(
                    pose[0],
                    pose[1],
                    pose[2] if len(pose) == 6 else None,
                    pose[-1],
                    *(pose[3:5] if len(pose) == 6 else (None, None)),
                    origin='initial_pose parameter',
                )

    # ------------------------------------------------------------------------------------- initial pose
    def set_initial_pose(
        self,
        x: float,
        y: float,
        z: float | None,
        yaw_deg: float,
        roll_deg: float | None = None,
        pitch_deg: float | None = None,
        radius: float | None = None,
        origin: str = 'initial pose',
    ) -> None:
        """Where the robot is now, in the saved map's ``map`` frame (REP-103 axes; metres, degrees), within
        ``radius`` [m] (default ``localization.initial_pose_radius``): the next attempts look there, and what they
        verify near it becomes the fix (a tracked robot relocalizes too: the user said it is elsewhere). Without z
        the nearest keyframe's height is taken, without roll and pitch the odometry's."""
        with self.lock:
            radius = self.params.localization.initial_pose_radius if radius is None else float(radius)
            self._pending_hint = (float(x), float(y), z, math.radians(yaw_deg), roll_deg, pitch_deg, radius, origin)
            self._record(
                'hint',
                self.latest_odometry_ns,
                f'{origin}: x {x:.2f} m, y {y:.2f} m, yaw {yaw_deg:.1f} deg (within {radius:.1f} m)',
            )

    def _take_hint(self, odometry_lidar: np.ndarray) -> None:
        x, y, z, yaw, roll, pitch, radius, origin = self._pending_hint
        self._pending_hint = None
        if z is None:
            nearest = int(np.argmin(np.linalg.norm(self.prior.poses_lidar[:, :2, 3] - [x, y], axis=1)))
            z = float(self.prior.poses_lidar[nearest, 2, 3])
        if roll is None or pitch is None:
            tilt = levelling(odometry_lidar)
        else:
            tilt = rot_y(math.radians(pitch)) @ rot_x(math.radians(roll))
        pose = np.eye(4)
        pose[:3, :3] = rot_z(yaw) @ tilt
        pose[:3, 3] = (x, y, z)
        self.hint = Hint(pose, odometry_lidar, radius, origin)
        self._hint_attempts = 0
        if self.state != 'relocalizing':
            self.state = 'lost' if self.first_fix_ns is not None else 'relocalizing'

    # ---------------------------------------------------------------------------------------- steps
    def process(
        self,
        stamp_ns: int,
        transform_sum: np.ndarray,
        corner_last: np.ndarray,
        surf_last: np.ndarray,
        outlier_last: np.ndarray,
        odometry_covariance: np.ndarray | None = None,
    ) -> MappingStep | None:
        """One step: the pose in the saved map, or None when none is published (not due, no fix, a bad step).
        ``odometry_covariance`` (the odometry pose's) is not used here."""
        mo, lo = self.params.map_optimization, self.params.localization
        with self.lock:
            self.latest_odometry_ns = stamp_ns
            self.transform_sum = np.asarray(transform_sum, dtype=float).copy()
            self.withheld = False
            last = self._last_processing_ns
            if last is not None and 0 <= stamp_ns - last < int(round(mo.mapping_process_interval * 1e9)):
                return None
            self._last_processing_ns = stamp_ns
            self.first_input_ns = stamp_ns if self.first_input_ns is None else self.first_input_ns
            self._count('steps')
            t0 = _time.perf_counter()
            corner_ds = voxel_downsample(corner_last, mo.corner_leaf_size)
            surf_ds = voxel_downsample(surf_last, mo.surf_leaf_size)
            outlier_ds = voxel_downsample(outlier_last, mo.outlier_leaf_size)
            surf_total_ds = voxel_downsample(np.concatenate([surf_ds, outlier_ds]), mo.surf_leaf_size)
            odometry = pose6_to_matrix(self.transform_sum)
            if last is not None and abs(stamp_ns - last) > lo.max_gap * 1e9:
                self._recent.clear()  # (the odometry across a gap is not to be trusted)
                if self.state in ('localized', 'confirming'):
                    self._lose(stamp_ns, f'a gap of {abs(stamp_ns - last) * 1e-9:.1f} s in the data')
            self._recent.append((odometry, corner_ds, surf_total_ds))
            if self._pending_hint is not None:
                self._take_hint(camera_pose_to_lidar(odometry))
            step = MappingStep(stamp_ns, self.transform_aft, self.transform_bef, False, 0)
            published = False
            if self.state in ('localized', 'confirming'):
                published = self._track(stamp_ns, odometry, corner_ds, surf_total_ds, step)
            else:
                published = self._relocalize(stamp_ns, odometry)
            step.timings_ms = dict(total=(_time.perf_counter() - t0) * 1e3)
            step.transform_aft, step.transform_bef = self.transform_aft.copy(), self.transform_bef.copy()
            self.last_scan = (corner_ds, surf_total_ds)
            self.withheld = not published
            if published:
                self._count('steps_localized')
                if step.pose_covariance is None:  # (a fix found by relocalization, not by a tracking registration)
                    step.pose_covariance = np.eye(6) * MAX_REGISTRATION_VARIANCE
                return step
            return None

    def _track(
        self, stamp_ns: int, odometry: np.ndarray, corner_ds: np.ndarray, surf_ds: np.ndarray, step: MappingStep
    ) -> bool:
        """A tracking step from the odometry's prediction; True when it is published."""
        mo, lo = self.params.map_optimization, self.params.localization
        predicted = pose6_to_matrix(self.transform_aft) @ invert_pose(pose6_to_matrix(self.transform_bef)) @ odometry
        local = self.prior.local(predicted[:3, 3])
        self.last_maps = (local.corner, local.surf)
        step.corner_map_points, step.surf_map_points = len(local.corner), len(local.surf)
        problem = None
        if len(local.corner) <= mo.min_corner_map_points or len(local.surf) <= mo.min_surf_map_points:
            problem, pose, overlap = 'the saved map has nothing here', predicted, 0.0
        else:
            pose6, counts = register_scan_to_map(
                local.corner,
                local.surf,
                corner_ds,
                surf_ds,
                matrix_to_pose6(predicted),
                self.params,
                self._degeneracy,
                local.trees,
            )
            step.optimised, step.iterations, step.correspondences = True, counts.iterations, counts.correspondences
            step.degenerate = counts.degenerate
            # In the saved map, whose keyframes are fixed: the registration's alone (core.mapping.covariance).
            step.pose_covariance = registration_covariance(pose6, counts.information, mo.covariance_scale)
            pose = pose6_to_matrix(pose6)
            # The share of the scan on the map from an even sample of its points (a share, not a fit: 1000 tell
            # it to a couple of percent, at a third of the cost of all of them).
            sample = surf_ds[:: max(1, -(-len(surf_ds) // OVERLAP_SAMPLE)), :3].astype(np.float64)
            gap, _ = local.trees[1].query(
                transform_points(pose, sample), distance_upper_bound=lo.tracking_inlier_distance
            )
            overlap = float(np.isfinite(gap).mean()) if len(gap) else 0.0
            correction = invert_pose(predicted) @ pose
            moved, turned = float(np.linalg.norm(correction[:3, 3])), _angle_deg(correction)
            if overlap < lo.min_tracking_overlap:
                problem = f'only {overlap:.0%} of the scan lies on the map'
            elif moved > lo.max_correction or turned > lo.max_correction_rotation:
                problem = f'the map moved the odometry by {moved:.2f} m / {turned:.1f} deg'
        self.last_overlap = overlap
        if problem is None:
            self.transform_aft, self.transform_bef = matrix_to_pose6(pose), self.transform_sum.copy()
            self._bad_steps = 0
        else:
            self._bad_steps += 1
            self._count('bad_steps')
        if self.state == 'confirming':
            if problem is not None:
                self.state = self._searching
                self.last_reason = f'a verified place was not confirmed: {problem}'
                self._count('hypotheses_rejected')
                self._record('rejected', stamp_ns, self.last_reason)
                return False
            self._confirmed += 1
            if self._confirmed < lo.confirm_steps:
                return False
            self._fixed(stamp_ns, pose)
            return True
        if problem is not None:
            self.last_reason = problem
            if self._bad_steps >= lo.lost_after_steps:
                self._lose(stamp_ns, f'{self._bad_steps} tracking steps in a row failed: {problem}')
            return False
        return True

    def _relocalize(self, stamp_ns: int, odometry: np.ndarray) -> bool:
        """A relocalization attempt; True when its place becomes the fix at once (confirm_steps 0)."""
        lo = self.params.localization
        self._count('attempts')
        self.attempts_since_fix += 1
        points, edges = scan_points_lidar(self._recent)
        attempt: Attempt = self.relocalizer.attempt(points, edges, camera_pose_to_lidar(odometry), self.hint)
        for verification in attempt.verifications:
            self._count('places_verified' if verification.accepted else 'places_rejected')
            self.verifications.append((stamp_ns, verification))
        self.last_reason = attempt.reason
        if attempt.pose is None:
            if self.hint is not None:
                self._hint_attempts += 1
                if self._hint_attempts >= HINT_ATTEMPTS:
                    self._record(
                        'hint',
                        stamp_ns,
                        f'{self.hint.origin} not verified in {HINT_ATTEMPTS} attempts: looking in the whole map',
                    )
                    self.hint = None
            return False
        hypothesis = lidar_pose_to_camera(attempt.pose)
        self.transform_aft, self.transform_bef = matrix_to_pose6(hypothesis), self.transform_sum.copy()
        self._searching, self.state, self._confirmed, self._bad_steps = self.state, 'confirming', 0, 0
        if lo.confirm_steps == 0:
            self._fixed(stamp_ns, hypothesis)
            return True
        return False

    def _fixed(self, stamp_ns: int, pose: np.ndarray) -> None:
        keyframe, distance = self.prior.nearest_keyframe(pose[:3, 3])
        how = f'near the {self.hint.origin}' if self.hint is not None else 'anywhere in the map'
        self._record(
            'fix',
            stamp_ns,
            f'verified {how} in {self.attempts_since_fix} attempt(s), {distance:.1f} m from keyframe {keyframe}',
        )
        self.first_fix_ns = stamp_ns if self.first_fix_ns is None else self.first_fix_ns
        self.state, self.hint, self.attempts_since_fix = 'localized', None, 0
        self._count('fixes')

    def _lose(self, stamp_ns: int, reason: str) -> None:
        self.state = 'lost' if self.first_fix_ns is not None else 'relocalizing'
        self.last_reason = reason
        self._bad_steps = 0
        self._count('losses')
        self._record('lost', stamp_ns, reason)

    def _record(self, kind: str, stamp_ns: int, detail: str) -> None:
        self.events.append(LocalizationEvent(stamp_ns, kind, detail))
        self.event_count += 1

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    # ------------------------------------------------------------------------------------------ status
    def status(self) -> LocalizationStatus:
        """The state in words and values (for /localization_status, the log, the summary)."""
        with self.lock:
            lo = self.params.localization
            values = dict(
                state=self.state,
                attempts=self.counters.get('attempts', 0),
                fixes=self.counters.get('fixes', 0),
                losses=self.counters.get('losses', 0),
                map_keyframes=len(self.prior),
            )
            if self.first_fix_ns is not None and self.first_input_ns is not None:
                values['time_to_first_fix_s'] = round((self.first_fix_ns - self.first_input_ns) * 1e-9, 3)
            if self.state == 'localized':
                values['overlap'] = round(self.last_overlap, 3)
                return LocalizationStatus(
                    self.state, True, f'localized in the map ({self.last_overlap:.0%} of the scan on it)', values
                )
            where = f'near the {self.hint.origin}' if self.hint is not None else 'in the whole map'
            if self.state == 'confirming':
                message = (
                    f'no pose yet: confirming a verified place ({self._confirmed} of {lo.confirm_steps} tracking steps)'
                )
            elif self.state == 'lost':
                message = (
                    f'lost, no pose published: relocalizing {where} ({self.attempts_since_fix} attempts; '
                    f'last: {self.last_reason})'
                )
            else:
                message = (
                    f'no pose yet: relocalizing {where} ({self.attempts_since_fix} attempts; last: {self.last_reason})'
                )
            return LocalizationStatus(self.state, False, message, values)

    # ----------------------------------------------------------------- the mapper's interface, as far as it goes
    def health_problem(self) -> str | None:
        with self.lock:
            return (
                pose6_problem('the localized pose', self.transform_aft)
                or pose6_problem('the odometry of the last step', self.transform_bef)
                or pose6_problem('the latest odometry', self.transform_sum)
                or self.imu.health_problem()
            )

    def heal(self) -> str:
        with self.lock:
            self.restart(from_the_start=False)
            if self.imu.health_problem() is not None:
                self.imu.clear()
            return 'localization starts again (relocalizing); the saved map is kept'

    def reanchor(self, jump: OdometryJump, pose: np.ndarray, transform_sum: np.ndarray) -> None:
        """The odometry restarted: the prediction continues from the last localized pose (as the mapping does);
        tracking verifies it at the next step."""
        with self.lock:
            self.transform_bef = anchored_transform_bef(jump, pose, self.transform_aft, self.transform_bef)
            self.transform_sum = np.asarray(transform_sum, dtype=float).copy()
            self._recent.clear()

    def keyframe_poses(self) -> np.ndarray:
        """(K, 6) the saved map's keyframe poses (map frame, camera axes)."""
        return self.prior.bundle.poses6.copy()

    def global_map(self, radius: float | None = None) -> np.ndarray:
        """The saved map (corner, surface and outliers; map frame, camera axes), for /laser_cloud_surround."""
        radius = self.params.map_optimization.global_map_visualization_search_radius if radius is None else radius
        cloud = np.concatenate([self.prior.corner_map, self.prior.surface_map])
        position = pose6_to_matrix(self.transform_aft)[:3, 3]
        return cloud[np.linalg.norm(cloud[:, :3] - position, axis=1) <= radius]

    def registered_scan(self) -> np.ndarray:
        """The last scan's features where the last step put them (map frame, camera axes)."""
        return transform_cloud(np.concatenate(self.last_scan), self.transform_aft)


def _angle_deg(pose: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(pose[:3, :3])) - 1.0) / 2.0))))
