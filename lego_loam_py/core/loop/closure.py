"""Loop closure of mapOptimization: finding a place visited before, verifying it, and deciding whether its
constraint may enter the pose graph (:class:`LoopCloser`, driven by :meth:`MapOptimization.detect_loop
<lego_loam_py.core.mapping.map_optimization.MapOptimization.detect_loop>` and ``close_loop``).

Two methods (``loop_closure.method``):

* ``'original'`` (docs/original.md §6.3): the nearest keyframe within ``history_keyframe_search_radius`` older
  than ``time_gap``, point-to-point ICP from the drifted poses, accepted when its fitness is at most
  ``history_keyframe_fitness_score``; :func:`find_loop_candidate` and :func:`align_loop`.
* ``'verified'`` (default): candidates from the same radius search *and* a Scan Context descriptor
  (:mod:`lego_loam_py.core.loop.place_recognition`), which finds a place however far the drift has carried the
  estimate; each verified by a point-to-plane registration (:mod:`lego_loam_py.core.loop.registration`) with
  gates on overlap, residual and how well every direction is constrained, a gate on the correction against the
  drift the mapping can have built up since, and a pairwise consistency check: a loop enters the graph once
  another loop agrees with it (the cycle through both loops and the odometry between them closes).

Keyframe clouds and poses of the mapper are in the world, camera axes (:mod:`lego_loam_py.core.frames`); the
verified method works in lidar axes, as the pose graph does.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from lego_loam_py.core.frames import (
    camera_pose_to_lidar,
    camera_to_lidar,
    invert_pose,
    lidar_pose_to_camera,
    pose6_to_matrix,
    rotation_vector,
    transform_cloud,
    transform_points,
)
from lego_loam_py.core.loop.place_recognition import PlaceDatabase, ScanContextConfig, scan_context
from lego_loam_py.core.loop.registration import Registration, register
from lego_loam_py.core.params.types import LoopClosureParams
from lego_loam_py.core.voxel import voxel_downsample

__all__ = ['LoopCandidate', 'LoopResult', 'LoopCloser', 'find_loop_candidate', 'align_loop', 'rotation_angle_deg']


def rotation_angle_deg(pose: np.ndarray) -> float:
    """Angle [deg] of the rotation of a 4x4 pose."""
    return float(np.degrees(np.linalg.norm(rotation_vector(pose[:3, :3]))))


@dataclass
class LoopCandidate:
    latest: int
    candidate: int
    source: np.ndarray  # ('original': world points, camera axes) 'verified': the latest keyframes' points in
    #                        the latest keyframe's frame, lidar axes
    target: np.ndarray  # ('original': world points, camera axes) 'verified': the candidate's neighbourhood in
    #                        the candidate's frame, lidar axes, downsampled
    detector: str = 'radius'  # 'radius' or 'scan_context'
    score: float = float('nan')  # Scan Context distance (0 same .. 1 unrelated)
    initial: np.ndarray | None = None  # 4x4 guess of the latest keyframe in the candidate's frame (lidar axes)
    graph_relative: np.ndarray | None = None  # the graph's pose of the latest in the candidate's frame (lidar)
    path_m: float = 0.0  # path travelled between the two keyframes (graph) [m]
    latest_stamp_ns: int = 0
    candidate_stamp_ns: int = 0
    candidate_pose: np.ndarray | None = None  # 4x4 world pose of the candidate (camera axes), for display
    source_latest: np.ndarray | None = None  # 'verified': which source points are mostly the latest keyframe's


@dataclass(eq=False)
class LoopResult:
    latest: int
    candidate: int
    fitness: float  # 'original': mean squared NN distance [m^2]; 'verified': RMS residual [m]
    converged: bool
    accepted: bool
    correction: np.ndarray  # 4x4 world-frame correction (camera axes) the fit implies for the latest keyframe
    relative: np.ndarray | None = None  # 4x4 constraint: candidate seen from latest (camera axes)
    relative_before: np.ndarray | None = None  # the same as the graph had it before the constraint
    variances: np.ndarray | None = None  # 'original': of the loop factor (rot x3, trans x3; lidar axes)
    information: np.ndarray | None = None  # 'verified': 6x6 information of the constraint (lidar axes)
    detector: str = 'radius'
    score: float = float('nan')
    overlap: float = float('nan')
    constraint: float = float('nan')
    reason: str = ''  # why it was rejected, or 'accepted' / 'pending' (waiting for a second loop)
    latest_stamp_ns: int = 0
    candidate_stamp_ns: int = 0
    correction_m: float = 0.0  # how far the constraint moves the latest keyframe against the graph [m]
    correction_deg: float = 0.0  # ... and turns it [deg]
    applied_m: float = float('nan')  # how far the latest keyframe actually moved when the loop went in [m]
    cpu_ms: float = 0.0  # CPU of the verifying registration and its gates (the process's) [ms]
    source_shift_m: float = 0.0  # how far the latest keyframe alone would move the fit [m] (see verify)
    source_shift_deg: float = 0.0  # ... and turn it [deg]

    def constrain(self, latest_pose: np.ndarray, candidate_pose: np.ndarray) -> None:
        """The original's constraint from its ICP correction, given both keyframes' world poses (4x4, camera
        axes): the candidate seen from the corrected latest keyframe, variances = fitness on every axis."""
        self.relative = invert_pose(self.correction @ latest_pose) @ candidate_pose
        self.relative_before = invert_pose(latest_pose) @ candidate_pose
        self.variances = np.full(6, max(self.fitness, 1e-12))

    def summary(self) -> dict:
        """The loop as the run's summary lists it."""
        return dict(
            latest=self.latest,
            candidate=self.candidate,
            latest_stamp_ns=self.latest_stamp_ns,
            candidate_stamp_ns=self.candidate_stamp_ns,
            detector=self.detector,
            score=None if math.isnan(self.score) else round(self.score, 4),
            rmse_m=round(self.fitness, 4),
            overlap=None if math.isnan(self.overlap) else round(self.overlap, 3),
            correction_m=round(self.correction_m, 3),
            correction_deg=round(self.correction_deg, 3),
            applied_m=None if math.isnan(self.applied_m) else round(self.applied_m, 3),
            accepted=self.accepted,
            reason=self.reason,
        )


# ------------------------------------------------------------------------------------------ the original


def find_loop_candidate(
    keyframes: Sequence, positions: np.ndarray, current_position: np.ndarray, latest_ns: int, lc: LoopClosureParams
) -> LoopCandidate | None:
    """The original's candidate search: the nearest keyframe within the search radius of ``current_position``
    [m] that is older than ``time_gap`` from ``latest_ns``, with the clouds the ICP aligns (the latest keyframe's
    corners and surfaces; the candidate's neighbours' downsampled). ``keyframes`` have ``stamp_ns``,
    ``pose6``, ``corner`` and ``surf``; ``positions`` (K, 3) are theirs."""
    if not keyframes:
        return None
    distance = np.linalg.norm(positions - current_position, axis=1)
    order = np.argsort(distance, kind='stable')
    order = order[distance[order] <= lc.history_keyframe_search_radius]
    times = np.array([kf.stamp_ns for kf in keyframes])
    old = np.abs(times[order] - latest_ns) > lc.time_gap * 1e9
    if not old.any():
        return None
    candidate = int(order[np.argmax(old)])
    latest = len(keyframes) - 1
    kf = keyframes[latest]
    source = transform_cloud(np.concatenate([kf.corner, kf.surf]), kf.pose6)
    source = source[np.trunc(source[:, 3]) >= 0]
    near = range(
        max(0, candidate - lc.history_keyframe_search_num), min(latest, candidate + lc.history_keyframe_search_num) + 1
    )
    target = np.concatenate(
        [transform_cloud(np.concatenate([keyframes[j].corner, keyframes[j].surf]), keyframes[j].pose6) for j in near]
    )
    target = voxel_downsample(target, lc.history_keyframe_leaf_size)
    return LoopCandidate(
        latest,
        candidate,
        source,
        target,
        detector='radius',
        latest_stamp_ns=kf.stamp_ns,
        candidate_stamp_ns=keyframes[candidate].stamp_ns,
        candidate_pose=np.eye(4),
    )


def align_loop(candidate: LoopCandidate, lc: LoopClosureParams) -> LoopResult:
    """ICP (point to point, open3d) of the latest keyframe against the candidate's neighbourhood, judged as the
    original: accepted when it converged and its fitness is at most ``history_keyframe_fitness_score``."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(candidate.source[:, :3].astype(np.float64)))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(candidate.target[:, :3].astype(np.float64)))
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(
        relative_fitness=lc.icp_euclidean_fitness_epsilon,
        relative_rmse=lc.icp_transformation_epsilon,
        max_iteration=lc.icp_max_iterations,
    )
    result = o3d.pipelines.registration.registration_icp(
        source,
        target,
        lc.icp_max_correspondence_distance,
        np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPoint(),
        criteria,
    )
    correction = np.asarray(result.transformation)
    aligned = transform_points(correction, candidate.source[:, :3].astype(np.float64))
    distance, _ = cKDTree(candidate.target[:, :3].astype(np.float64)).query(aligned)
    inside = distance <= lc.icp_max_correspondence_distance
    fitness = float(np.mean(distance[inside] ** 2)) if inside.any() else float('inf')
    converged = bool(np.isfinite(correction).all() and len(result.correspondence_set) > 0)
    accepted = converged and fitness <= lc.history_keyframe_fitness_score
    return LoopResult(
        candidate.latest,
        candidate.candidate,
        fitness,
        converged,
        accepted,
        correction,
        reason='accepted' if accepted else 'fitness',
        latest_stamp_ns=candidate.latest_stamp_ns,
        candidate_stamp_ns=candidate.candidate_stamp_ns,
    )


# ------------------------------------------------------------------------------------------ verified


def _levelling(pose_lidar: np.ndarray) -> np.ndarray:
    """The 3x3 rotation that levels a keyframe's points (its roll and pitch in the world), keeping its yaw."""
    yaw = math.atan2(pose_lidar[1, 0], pose_lidar[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ pose_lidar[:3, :3]


# A registration's cost grows with its clouds: keyframes far apart (a fast drive) give more points per keyframe
# span, so the leaf grows until the clouds are at most this large (a 21k-point target costs about 100 ms).
_MAX_SOURCE_POINTS, _MAX_TARGET_POINTS = 6000, 20000


def _thinned(points: np.ndarray, leaf: float, max_points: int, marked: np.ndarray | None = None):
    """(N, 3) points voxel-filtered with ``leaf`` [m], coarser (x1.25 at a time) until at most ``max_points``.
    With ``marked`` (N booleans) also which of the thinned points come mostly from marked points."""
    cloud = np.column_stack([points, np.zeros(len(points)) if marked is None else marked]).astype(np.float32)
    thinned = voxel_downsample(cloud, leaf)
    while len(thinned) > max_points:
        leaf *= 1.25
        thinned = voxel_downsample(cloud, leaf)
    xyz = thinned[:, :3].astype(np.float64)
    return xyz if marked is None else (xyz, thinned[:, 3] > 0.5)


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    return out


@dataclass(eq=False)
class _Pending:
    """A verified loop waiting for a second one that agrees with it."""

    result: LoopResult
    relative_lidar: np.ndarray  # latest in candidate's frame (lidar axes), as registered
    latest_stamp_ns: int
    candidate_stamp_ns: int


@dataclass
class LoopCloser:
    """The 'verified' method's state: descriptors of the keyframes (keyed by stamp, so keyframes dropped by a
    self-repair do not confuse it), the loops waiting for confirmation and every loop tried."""

    params: LoopClosureParams
    places: PlaceDatabase = field(init=False)
    pending: list[_Pending] = field(default_factory=list)  # verified, waiting for a loop that agrees
    confirmed: list[_Pending] = field(default_factory=list)  # in the graph, within the consistency window
    _tried: dict[int, int] = field(default_factory=dict)  # candidate stamp -> latest stamp when last tried
    _last_verified_ns: int | None = None  # latest keyframe of the last verification
    _last_detected_ns: int | None = None  # latest keyframe of the last detection
    too_far: int = 0  # descriptor matches beyond the drift bound of the graph's estimate, never registered

    def __post_init__(self):
        lc = self.params
        self.places = PlaceDatabase(
            ScanContextConfig(
                rings=lc.scan_context_rings, sectors=lc.scan_context_sectors, max_radius=lc.scan_context_max_radius
            )
        )
        self._described: set[int] = set()
        # open3d is imported by the first ICP (on the loop-closure thread), not here: its import costs a node 0.5-1 s
        # of CPU (it loads plotly and dash for its viewers), paid at start-up by every run, most of which never
        # verify a loop in their first minutes; the one mapping step that import may delay comes with a loop.

    def describe(self, keyframes: Sequence) -> None:
        """Descriptors for the keyframes that have none yet (their clouds levelled by their poses)."""
        for kf in keyframes:
            if kf.stamp_ns in self._described:
                continue
            pose = camera_pose_to_lidar(pose6_to_matrix(kf.pose6))
            points = camera_to_lidar(np.concatenate([kf.corner, kf.surf, kf.outlier])[:, :3].astype(np.float64))
            self.places.add(kf.stamp_ns, scan_context(points @ _levelling(pose).T, self.places.config))
            self._described.add(kf.stamp_ns)

    def detect(self, keyframes: Sequence, positions: np.ndarray) -> LoopCandidate | None:
        """The candidate to verify for the newest keyframe, or None: the Scan Context match when one is below the
        threshold, else the nearest keyframe within the search radius; pairs tried in the last ``period`` of
        travel near the same place are not tried again."""
        lc = self.params
        if len(keyframes) < 2:
            return None
        self.describe(keyframes)
        latest = len(keyframes) - 1
        latest_kf = keyframes[latest]
        if latest_kf.stamp_ns == self._last_detected_ns and not self.pending:
            return None  # no new keyframe since the last look: nothing new to find
        self._last_detected_ns = latest_kf.stamp_ns
        stamps = np.array([kf.stamp_ns for kf in keyframes], dtype=np.int64)
        old = np.abs(stamps - latest_kf.stamp_ns) > lc.time_gap * 1e9
        # Not the first keyframes: the mapping's attitude settles over them (on the simulated campus the 5th
        # keyframe is pitched 1 deg against the 1st as seen from those after it), which a constraint to them would
        # carry into the graph.
        old[: lc.skip_first_keyframes] = False
        if not old.any():
            return None
        index_of = {int(s): i for i, s in enumerate(stamps)}
        place_keys = np.array(self.places._keys, dtype=np.int64)
        allowed = np.isin(place_keys, stamps[old])
        choices = []
        distance = np.linalg.norm(positions - positions[latest], axis=1)
        path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
        for match in self.places.query(self.places.descriptor(latest_kf.stamp_ns), allowed, count=3):
            if match.distance > lc.scan_context_threshold or match.key not in index_of:
                continue
            candidate = index_of[match.key]
            # A place that looks the same but lies farther from the graph's estimate than the drift over the path
            # between them (and the registration's reach) allows is another place alike: not worth a registration.
            reach = (
                lc.max_drift_base + lc.max_drift_ratio * (path[latest] - path[candidate]) + lc.registration_distances[0]
            )
            if distance[candidate] > reach:
                self.too_far += 1
                continue
            choices.append(('scan_context', candidate, match.distance, match.yaw))
            break
        near = np.flatnonzero(old & (distance <= lc.history_keyframe_search_radius))
        if len(near):
            choices.append(('radius', int(near[np.argmin(distance[near])]), float('nan'), None))
        recently_closed = any(
            latest_kf.stamp_ns - p.latest_stamp_ns <= lc.consistency_window * 1e9 for p in self.confirmed
        )
        if choices and (recently_closed or not self.pending) and self._last_verified_ns in index_of:
            # Verifications are spaced along the path (they cost a registration each), unless a first loop waits
            # for its confirmation; wider once loops went in here (a loop still pending then disagreed with them).
            spacing = lc.closed_verification_spacing if recently_closed else lc.verification_spacing
            steps = np.linalg.norm(np.diff(positions[index_of[self._last_verified_ns] :], axis=0), axis=1)
            if steps.sum() < spacing:
                return None
        for detector, candidate, score, yaw in choices:
            previous = self._tried.get(int(stamps[candidate]))
            if (
                previous is not None
                and previous in index_of
                and np.linalg.norm(positions[index_of[previous]] - positions[latest]) < 1.0
            ):
                continue  # the same pair, hardly moved since: its verdict would be the same
            self._tried[int(stamps[candidate])] = int(latest_kf.stamp_ns)
            self._last_verified_ns = int(latest_kf.stamp_ns)
            return self._candidate(keyframes, positions, latest, candidate, detector, score, yaw)
        return None

    def _candidate(
        self, keyframes, positions, latest: int, candidate: int, detector: str, score: float, yaw: float | None
    ) -> LoopCandidate:
        lc = self.params
        poses = {
            i: camera_pose_to_lidar(pose6_to_matrix(keyframes[i].pose6))
            for i in set(range(max(0, latest - lc.source_keyframes), latest + 1))
            | set(range(max(0, candidate - lc.target_keyframes), min(latest, candidate + lc.target_keyframes + 1)))
        }

        def cloud_in(frame: int, ids) -> np.ndarray:
            to_frame = invert_pose(poses[frame])
            parts = [
                transform_points(
                    to_frame @ poses[j],
                    camera_to_lidar(
                        np.concatenate([keyframes[j].corner, keyframes[j].surf, keyframes[j].outlier])[:, :3].astype(
                            np.float64
                        )
                    ),
                )
                for j in ids
            ]
            return np.concatenate(parts) if parts else np.zeros((0, 3))

        before = cloud_in(latest, range(max(0, latest - lc.source_keyframes), latest))
        newest = cloud_in(latest, [latest])
        source, source_latest = _thinned(
            np.concatenate([before, newest]),
            lc.history_keyframe_leaf_size,
            _MAX_SOURCE_POINTS,
            marked=np.arange(len(before) + len(newest)) >= len(before),
        )
        target = _thinned(
            cloud_in(
                candidate,
                range(max(0, candidate - lc.target_keyframes), min(latest, candidate + lc.target_keyframes + 1)),
            ),
            lc.history_keyframe_leaf_size,
            _MAX_TARGET_POINTS,
        )
        graph_relative = invert_pose(poses[candidate]) @ poses[latest]
        if yaw is None:
            initial = graph_relative
        else:  # same place, turned by the descriptor's yaw: levelled frames differ by a rotation about z
            level_l, level_c = np.eye(4), np.eye(4)
            level_l[:3, :3], level_c[:3, :3] = _levelling(poses[latest]), _levelling(poses[candidate])
            initial = level_c.T @ _rot_z(yaw) @ level_l
        steps = np.linalg.norm(np.diff(positions[min(candidate, latest) : max(candidate, latest) + 1], axis=0), axis=1)
        return LoopCandidate(
            latest,
            candidate,
            source,
            target,
            detector=detector,
            score=score,
            initial=initial,
            graph_relative=graph_relative,
            path_m=float(steps.sum()),
            latest_stamp_ns=keyframes[latest].stamp_ns,
            candidate_stamp_ns=keyframes[candidate].stamp_ns,
            candidate_pose=pose6_to_matrix(keyframes[candidate].pose6),
            source_latest=source_latest,
        )

    def verify(self, candidate: LoopCandidate) -> tuple[LoopResult, Registration]:
        """Register the candidate and judge it by the registration and drift gates (no lock needed)."""
        lc = self.params
        start = time.process_time()
        fit = register(
            candidate.source,
            candidate.target,
            candidate.initial,
            lc.registration_distances,
            lc.registration_iterations,
            lc.inlier_distance,
            lc.registration_points,
            lc.min_registration_sigma,
            subset=candidate.source_latest if lc.source_keyframes else None,
        )
        change = invert_pose(candidate.graph_relative) @ fit.pose  # the graph's view -> the registration's
        correction_m, correction_deg = float(np.linalg.norm(change[:3, 3])), rotation_angle_deg(change)
        reason = fit.gate_failure(lc.min_overlap, lc.max_rmse, lc.min_constraint)
        if not reason and (fit.subset_shift_m > lc.max_source_shift or fit.subset_shift_deg > lc.max_source_shift_deg):
            reason = (
                f'source inconsistent: the newest keyframe alone moves the fit {fit.subset_shift_m:.2f} m '
                f'{fit.subset_shift_deg:.2f} deg (its mapped pose disagrees with the keyframes before it)'
            )
        if not reason and correction_m > lc.max_drift_base + lc.max_drift_ratio * candidate.path_m:
            reason = f'correction {correction_m:.2f} m beyond the drift possible over {candidate.path_m:.0f} m'
        if not reason and correction_deg > lc.max_drift_rotation_base + lc.max_drift_rotation_ratio * candidate.path_m:
            reason = f'correction {correction_deg:.2f} deg beyond the drift possible over {candidate.path_m:.0f} m'
        result = LoopResult(
            candidate.latest,
            candidate.candidate,
            fit.rmse,
            True,
            False,
            np.eye(4),
            detector=candidate.detector,
            score=candidate.score,
            overlap=fit.overlap,
            constraint=fit.constraint,
            reason=reason or 'verified',
            latest_stamp_ns=candidate.latest_stamp_ns,
            candidate_stamp_ns=candidate.candidate_stamp_ns,
            correction_m=correction_m,
            correction_deg=correction_deg,
            information=fit.information,
            relative=lidar_pose_to_camera(invert_pose(fit.pose)),
            relative_before=lidar_pose_to_camera(invert_pose(candidate.graph_relative)),
            cpu_ms=(time.process_time() - start) * 1e3,
            source_shift_m=fit.subset_shift_m,
            source_shift_deg=fit.subset_shift_deg,
        )
        return result, fit

    def admit(self, result: LoopResult, fit: Registration, keyframes: Sequence, now_ns: int) -> list[_Pending]:
        """The loops to put into the graph now that ``result`` was verified (see :meth:`consistent`); sets its
        ``reason`` ('accepted', 'pending', or why not). Called with the mapper's lock held."""
        if result.reason != 'verified':
            return []
        poses = {kf.stamp_ns: camera_pose_to_lidar(pose6_to_matrix(kf.pose6)) for kf in keyframes}
        if result.latest_stamp_ns not in poses or result.candidate_stamp_ns not in poses:
            result.reason = 'keyframes dropped meanwhile'
            return []
        ready = self.consistent(result, fit, poses, now_ns)
        result.reason = 'accepted' if ready else 'pending'
        for loop in ready:
            loop.result.accepted = True
            loop.result.reason = 'accepted'
        return ready

    def consistent(
        self, result: LoopResult, fit: Registration, poses_by_stamp: dict[int, np.ndarray], now_ns: int
    ) -> list[_Pending]:
        """The verified loops that may go into the graph now, given the new one: [] while it waits for a second
        loop to agree with it (or with an accepted one), else it and the pending loops that agree with it.
        ``poses_by_stamp``: the graph's current keyframe poses (4x4, lidar axes)."""
        lc = self.params
        new = _Pending(result, fit.pose, result.latest_stamp_ns, result.candidate_stamp_ns)
        window = lc.consistency_window * 1e9

        def recent(loops: list[_Pending]) -> list[_Pending]:
            return [
                p
                for p in loops
                if now_ns - p.latest_stamp_ns <= window
                and p.latest_stamp_ns in poses_by_stamp
                and p.candidate_stamp_ns in poses_by_stamp
            ]

        self.pending, self.confirmed = recent(self.pending), recent(self.confirmed)
        if lc.min_consistent_loops <= 1 or any(self._agree(new, p, poses_by_stamp) for p in self.confirmed):
            self.confirmed.append(new)
            return [new]
        agreeing = [p for p in self.pending if self._agree(new, p, poses_by_stamp)]
        if len(agreeing) + 1 >= lc.min_consistent_loops:
            self.pending = [p for p in self.pending if p not in agreeing]
            self.confirmed.extend(agreeing + [new])
            return agreeing + [new]
        self.pending.append(new)
        return []

    def _agree(self, a: _Pending, b: _Pending, poses: dict[int, np.ndarray]) -> bool:
        """The cycle a.latest -> a.candidate (loop a) -> b.candidate (odometry) -> b.latest (loop b) ->
        a.latest (odometry) closes within the consistency bounds."""
        lc = self.params
        odometry_candidates = invert_pose(poses[a.candidate_stamp_ns]) @ poses[b.candidate_stamp_ns]
        odometry_latest = invert_pose(poses[b.latest_stamp_ns]) @ poses[a.latest_stamp_ns]
        # a.relative: latest_a in candidate_a's frame; cycle: candidate_a -> latest_a should equal
        # candidate_a -> candidate_b -> latest_b -> latest_a.
        cycle = invert_pose(a.relative_lidar) @ odometry_candidates @ b.relative_lidar @ odometry_latest
        return bool(
            np.linalg.norm(cycle[:3, 3]) <= lc.consistency_translation
            and rotation_angle_deg(cycle) <= lc.consistency_rotation
        )
