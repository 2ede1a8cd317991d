"""mapOptimization: scan-to-map refinement, keyframes, iSAM2 pose graph, loop closure (docs/original.md §6.3).

Poses are six-vectors ``(rx, ry, rz, tx, ty, tz)`` in LOAM camera axes with the world convention
``R = Ry(ry) Rx(rx) Rz(rz)`` (:mod:`lego_loam_py.core.frames`):

* ``transform_sum``: the latest odometry (featureAssociation's pose of the sweep);
* ``transform_bef`` / ``transform_aft``: the odometry and the optimised pose at the previous mapping step;
* ``transform_tobe``: the pose being optimised, predicted as ``T_aft · T_bef^-1 · T_sum``.

Keyframes (every ``keyframe_distance`` of travel) keep their downsampled corner, surface and outlier
clouds in their own sensor frame and are the nodes of a gtsam iSAM2 graph (prior on the first, between
factors from the optimised poses, the original's noise), expressed in lidar axes as the original does. The
surrounding map is the union of the keyframes within ``surrounding_keyframe_search_radius`` (one per 1 m voxel
of their positions: the latest, or the original's truncated averaged index, quirk 8.5) or, with loop closure
on, the last ``surrounding_keyframe_search_num`` keyframes. The voxel-filtered map is kept in two
:class:`~lego_loam_py.core.voxel.VoxelAccumulator` (corner, surface + outlier): a keyframe's world clouds are
computed and merged in when it enters the set and subtracted when it leaves, so a step costs the change of
the set, not a new filter of some 50 keyframes; a loop closure that moves the poses rebuilds it. Scan-to-map
registration is :mod:`lego_loam_py.core.mapping.scan_to_map`; loop closure :mod:`lego_loam_py.core.loop.closure`; the
saved map bundle :mod:`lego_loam_py.core.mapping.map_bundle`.

Thread safety: :meth:`process`, :meth:`detect_loop`, :meth:`close_loop`, :meth:`global_map` and
:meth:`save` take one lock, so loop closure can run in another thread (as the original's 1 Hz thread).
"""

from __future__ import annotations

import threading
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lego_loam_py.core.frames import (
    camera_pose_to_lidar,
    invert_pose,
    matrix_to_pose6,
    pose6_to_matrix,
    transform_cloud,
)
from lego_loam_py.core.gauss_newton import DegeneracyProjection
from lego_loam_py.core.imu.buffer import ImuBuffer, imu_mounting
from lego_loam_py.core.imu.monitor import MappingImuCheck
from lego_loam_py.core.loop.closure import LoopCandidate, LoopResult
from lego_loam_py.core.loop.methods import make_loop_method
from lego_loam_py.core.mapping.covariance import (
    MAX_REGISTRATION_VARIANCE,
    KeyframeCovariance,
    SweepCovariance,
    mapped_covariance,
    registration_covariance,
)
from lego_loam_py.core.mapping.odometry_continuity import OdometryJump, anchored_transform_bef
from lego_loam_py.core.mapping.pose_graph import PoseGraph
from lego_loam_py.core.mapping.scan_to_map import register_scan_to_map
from lego_loam_py.core.params.types import Params
from lego_loam_py.core.validation import pose6_problem
from lego_loam_py.core.voxel import VoxelAccumulator, voxel_downsample, voxel_indices

if TYPE_CHECKING:
    from lego_loam_py.core.mapping.occupancy_grid import OccupancyGrid

__all__ = ['MapOptimization', 'MappingStep', 'Keyframe']

_F32 = np.float32


@dataclass
class Keyframe:
    index: int
    stamp_ns: int
    pose6: np.ndarray  # optimised pose (world convention, camera axes)
    corner: np.ndarray  # (n, 4) sensor frame, camera axes, downsampled
    surf: np.ndarray
    outlier: np.ndarray


@dataclass
class MappingStep:
    """Result of one mapping step (what /aft_mapped_to_init publishes)."""

    stamp_ns: int
    transform_aft: np.ndarray  # optimised pose of aft_mapped in camera_init
    transform_bef: np.ndarray  # the odometry pose it was computed from
    keyframe_added: bool
    keyframes: int
    correspondences: int = 0
    iterations: int = 0
    degenerate: bool = False
    condition: float = float('nan')  # the registration's, see core.scan_to_map (NaN: none)
    optimised: bool = False
    corner_map_points: int = 0
    surf_map_points: int = 0
    timings_ms: dict = field(default_factory=dict)
    imu_alignment: object = None  # what the IMU check decided at this step (core.imu_monitor.AlignmentEvent)
    # 6x6 covariance of transform_aft in camera_init (position [m²] in its axes, rotation [rad²] about them; ROS
    # order x, y, z, rot x, rot y, rot z; core.mapping.covariance); None: no covariance known.
    pose_covariance: np.ndarray | None = None
    registration_covariance: np.ndarray | None = None  # of transform_aft relative to the map (None: not registered)


class MapOptimization:
    """The mapOptimization algorithm; :meth:`process` is called with each synchronised input set."""

    builds_map = True  # (a core.mapping.mapper.Mapper with keyframes, loops and a map to save)
    # Imported by the first mapping step, not with this module (a node imports them ahead with its first input).
    # The map's neighbour searches are grids: scipy.spatial comes only with a search's rare tie or a loop closure.
    DEFERRED_IMPORTS = ('gtsam',)

    def __init__(self, params: Params):
        self.params = params
        mo = params.map_optimization
        self.transform_sum = np.zeros(6)
        self.transform_bef = np.zeros(6)
        self.transform_aft = np.zeros(6)
        self.transform_tobe = np.zeros(6)
        self.transform_last = np.zeros(6)
        self.keyframes: list[Keyframe] = []
        self._positions = np.zeros((0, 3))
        self._corner_accumulator = VoxelAccumulator(mo.corner_leaf_size)
        self._surf_accumulator = VoxelAccumulator(mo.surf_leaf_size)
        self.current_position = np.zeros(3)
        self._previous_keyframe_position: np.ndarray | None = None
        self.graph = PoseGraph(mo)
        self.imu = ImuBuffer(
            params.feature_association.imu_que_length,
            params.feature_association.gravity,
            params.sensor.scan_period,
            imu_mounting(params),
        )
        self.imu_check = MappingImuCheck(params, lambda: self.imu)  # is the IMU mounted as the parameters say?
        self._degeneracy = DegeneracyProjection(6)
        # The keyframes' uncertainty (a graph of its own, core.mapping.covariance), the last registration's
        # information and the mapped pose's covariance.
        self.keyframe_covariance = KeyframeCovariance()
        self._registration_information: np.ndarray | None = None
        self.pose_covariance = np.zeros((6, 6))
        self.sweep_covariance = SweepCovariance()  # the motion's since the last input, from the odometry's covariance
        self._last_processing_ns: int | None = None
        self.latest_odometry_ns = 0
        self.loop_closed = False
        self.loops: list[LoopResult] = []  # every loop verified, accepted or not
        self.loop_method = make_loop_method(params.loop_closure)  # (chosen once: loop_closure.method)
        self.lock = threading.RLock()
        self.last_maps: tuple[np.ndarray, np.ndarray] = (np.zeros((0, 4), _F32), np.zeros((0, 4), _F32))
        self.last_scan: tuple[np.ndarray, np.ndarray] = (np.zeros((0, 4), _F32), np.zeros((0, 4), _F32))
        self.map_source: dict = {}  # where the data came from (a bag), noted in the saved map bundle
        self.occupancy_problem: str | None = None  # why the last save wrote no occupancy grid (None: it did)

    # --------------------------------------------------------------------------------- self-checks
    def health_problem(self) -> str | None:
        """Why the mapping state is poisoned (non-finite or absurd poses, optimizer solution or IMU), or None.
        Checked after every step; :meth:`heal` repairs it."""
        with self.lock:
            return (
                pose6_problem('the mapped pose', self.transform_aft)
                or pose6_problem('the pose being optimised', self.transform_tobe)
                or pose6_problem('the odometry of the last step', self.transform_bef)
                or pose6_problem('the latest odometry', self.transform_sum)
                or pose6_problem('the last keyframe pose', self.transform_last)
                or (
                    pose6_problem('the newest keyframe (optimizer solution)', self.keyframes[-1].pose6)
                    if self.keyframes
                    else None
                )
                or self.imu.health_problem()
            )

    def reanchor(self, jump: OdometryJump, pose: np.ndarray, transform_sum: np.ndarray) -> None:
        """The odometry restarted (``jump``, see :mod:`lego_loam_py.core.mapping.odometry_continuity`) and is now at
        ``pose`` (4x4) = ``transform_sum`` (six-vector): the next step starts from the last mapped pose, moved on
        at the last speed over the gap, instead of the odometry's new origin."""
        with self.lock:
            self.transform_bef = anchored_transform_bef(jump, pose, self.transform_aft, self.transform_bef)
            self.transform_sum = np.asarray(transform_sum, dtype=float).copy()
            self.sweep_covariance.reset()

    def heal(self) -> str:
        """Reset what :meth:`health_problem` found poisoned and keep the map and the trajectory built so far:
        keyframes whose optimised pose is not sane are dropped (the pose graph is then rebuilt from the kept
        poses, loop constraints included in them), and mapping goes on from the newest sane keyframe, where the
        next odometry is re-anchored. Returns what was done, for the log."""
        with self.lock:
            done = []
            good = [kf for kf in self.keyframes if pose6_problem('', kf.pose6) is None]
            if len(good) < len(self.keyframes):
                done.append(f'{len(self.keyframes) - len(good)} keyframe(s) with a poisoned pose dropped')
                self.keyframe_covariance = self.keyframe_covariance.kept(
                    [kf.index for kf in good], [pose6_to_matrix(kf.pose6) for kf in good]
                )
                self.keyframes = [
                    Keyframe(i, kf.stamp_ns, kf.pose6, kf.corner, kf.surf, kf.outlier) for i, kf in enumerate(good)
                ]
                self.graph.rebuild([kf.pose6 for kf in self.keyframes])
            self._positions = np.array([kf.pose6[3:] for kf in self.keyframes]).reshape(-1, 3)
            anchor = self.keyframes[-1].pose6.copy() if self.keyframes else np.zeros(6)
            self.transform_aft, self.transform_tobe, self.transform_last = anchor.copy(), anchor.copy(), anchor.copy()
            if pose6_problem('', self.transform_sum) is not None:
                self.transform_sum = np.zeros(6)
            # T_aft · T_bef^-1 · T_sum predicts the anchor for the latest odometry: mapping resumes there.
            self.transform_bef = self.transform_sum.copy()
            self.sweep_covariance.reset()
            self.current_position = anchor[3:].copy()
            self._previous_keyframe_position = anchor[3:].copy() if self.keyframes else None
            self._corner_accumulator.clear()
            self._surf_accumulator.clear()
            if self.imu.health_problem() is not None:
                self.imu.clear()
                done.append('IMU samples dropped')
            done.append(
                f'mapping resumes from keyframe {len(self.keyframes) - 1}' if self.keyframes else 'mapping starts again'
            )
            return ', '.join(done) + f'; {len(self.keyframes)} keyframes kept'

    # ------------------------------------------------------------------------------------------ steps
    def process(
        self,
        stamp_ns: int,
        transform_sum: np.ndarray,
        corner_last: np.ndarray,
        surf_last: np.ndarray,
        outlier_last: np.ndarray,
        odometry_covariance: np.ndarray | None = None,
    ) -> MappingStep | None:
        """One mapping step, or None when less than ``mapping_process_interval`` passed since the last one.
        ``odometry_covariance``: the 6x6 covariance of the odometry pose ``transform_sum`` (that of
        /laser_odom_to_init, camera_init; None: unknown), read for the deskewing's error
        (:class:`~lego_loam_py.core.mapping.covariance.SweepCovariance`)."""
        mo = self.params.map_optimization
        interval_ns = int(round(mo.mapping_process_interval * 1e9))
        with self.lock:
            self.latest_odometry_ns = stamp_ns
            self.transform_sum = np.asarray(transform_sum, dtype=float).copy()
            self.sweep_covariance.add(pose6_to_matrix(self.transform_sum), odometry_covariance)
            # (An input stamped before the last step comes after a wrong stamp was found out, see StampOrder's
            # resync: the interval counts from the inputs on the right timeline.)
            if self._last_processing_ns is not None and 0 <= stamp_ns - self._last_processing_ns < interval_ns:
                return None
            self._last_processing_ns = stamp_ns
            timings = {}
            t0 = _time.perf_counter()
            self._associate_to_map()
            corner_map, surf_map = self._surrounding_map()
            t1 = _time.perf_counter()
            corner_ds = voxel_downsample(corner_last, mo.corner_leaf_size)
            surf_ds = voxel_downsample(surf_last, mo.surf_leaf_size)
            outlier_ds = voxel_downsample(outlier_last, mo.outlier_leaf_size)
            surf_total_ds = voxel_downsample(np.concatenate([surf_ds, outlier_ds]), mo.surf_leaf_size)
            step = MappingStep(
                stamp_ns,
                self.transform_aft,
                self.transform_bef,
                False,
                len(self.keyframes),
                corner_map_points=len(corner_map),
                surf_map_points=len(surf_map),
            )
            registration = None
            if len(corner_map) > mo.min_corner_map_points and len(surf_map) > mo.min_surf_map_points:
                self._scan_to_map(corner_map, surf_map, corner_ds, surf_total_ds, step)
                # As in the original, the poses only move on when a map was there to register against: the
                # first step (no map yet) keeps transform_aft/bef at their previous values.
                self._transform_update(stamp_ns, step)
                registration = registration_covariance(
                    self.transform_aft, self._registration_information, mo.covariance_scale
                )
            t2 = _time.perf_counter()
            step.keyframe_added = self._save_keyframe(stamp_ns, corner_ds, surf_ds, outlier_ds, registration)
            self._correct_poses()
            # The scan was deskewed with the odometry's motion estimate: its error is the mapped pose's too, unseen
            # by the registration (core.mapping.covariance.SweepCovariance).
            deskewing = self.sweep_covariance.deskewing(pose6_to_matrix(self.transform_aft), mo.covariance_deskew)
            step.pose_covariance = self._mapped_covariance(step.keyframe_added, registration) + deskewing
            step.registration_covariance = registration
            t3 = _time.perf_counter()
            timings.update(
                map=(t1 - t0) * 1e3, registration=(t2 - t1) * 1e3, graph=(t3 - t2) * 1e3, total=(t3 - t0) * 1e3
            )
            step.timings_ms = timings
            step.transform_aft = self.transform_aft.copy()
            step.transform_bef = self.transform_bef.copy()
            step.keyframes = len(self.keyframes)
            self.last_maps = (corner_map, surf_map)
            self.last_scan = (corner_ds, surf_total_ds)
            return step

    def _associate_to_map(self) -> None:
        """Prediction of the map-frame pose from the odometry: ``T_aft · T_bef^-1 · T_sum``."""
        predicted = (
            pose6_to_matrix(self.transform_aft)
            @ invert_pose(pose6_to_matrix(self.transform_bef))
            @ pose6_to_matrix(self.transform_sum)
        )
        self.transform_tobe = matrix_to_pose6(predicted)

    def _surrounding_ids(self) -> list[int]:
        mo, lc = self.params.map_optimization, self.params.loop_closure
        n = len(self.keyframes)
        if n == 0:
            return []
        if lc.loop_closure_enable_flag and self.loop_method.recent_keyframes_as_map:
            return list(range(max(0, n - mo.surrounding_keyframe_search_num), n))
        near = np.flatnonzero(
            np.linalg.norm(self._positions - self.current_position, axis=1) <= mo.surrounding_keyframe_search_radius
        )
        return self._one_keyframe_per_voxel(near, mo.surrounding_keypose_leaf_size)

    def _one_keyframe_per_voxel(self, ids: np.ndarray, leaf_size: float) -> list[int]:
        """Sorted keyframe indices, one per ``leaf_size`` voxel of the positions of keyframes ``ids``.

        'latest' keeps each voxel's most recent keyframe. 'averaged_index' is the original's (quirk 8.5): PCL
        averages the indices in a voxel and the mean is truncated, which on a second pass over a place picks a
        keyframe from between the two passes, far from the voxel."""
        if len(ids) == 0:
            return []
        if self.params.map_optimization.keypose_pick == 'averaged_index':
            poses = np.concatenate([self._positions[ids], ids[:, None].astype(float)], axis=1)
            picked = np.unique(np.trunc(voxel_downsample(poses, leaf_size)[:, 3]).astype(np.int64))
            return [int(i) for i in picked if 0 <= i < len(self.keyframes)]
        voxel = voxel_indices(self._positions[ids].astype(np.float32), leaf_size)
        order = np.lexsort((ids, voxel))  # by voxel, then by keyframe index
        last_of_voxel = np.append(voxel[order][1:] != voxel[order][:-1], True)
        return sorted(int(i) for i in ids[order][last_of_voxel])

    def _surrounding_map(self) -> tuple[np.ndarray, np.ndarray]:
        """The voxel-filtered corner and surface(+outlier) maps of the surrounding keyframes (world, camera
        axes). Between steps the set changes by a keyframe or two, so the accumulators merge those in and out
        instead of filtering every point again; a keyframe's world clouds are computed once, when it enters."""
        ids = self._surrounding_ids()
        present = self._corner_accumulator.ids()
        entering = [i for i in ids if i not in present]
        leaving = present - set(ids)
        if len(entering) + len(leaving) > max(4, len(ids) // 2):
            # Most of the map changed (start, loop correction, a jump): one grouping beats many merges.
            clouds = {i: self._world_clouds(i) for i in ids}
            self._corner_accumulator.rebuild({i: c for i, (c, _) in clouds.items()})
            self._surf_accumulator.rebuild({i: s for i, (_, s) in clouds.items()})
        else:
            for i in leaving:
                self._corner_accumulator.remove(i)
                self._surf_accumulator.remove(i)
            for i in entering:
                corner, surf = self._world_clouds(i)
                self._corner_accumulator.add(i, corner)
                self._surf_accumulator.add(i, surf)
        return self._corner_accumulator.centroids(), self._surf_accumulator.centroids()

    def _world_clouds(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        kf = self.keyframes[index]
        return (transform_cloud(kf.corner, kf.pose6), transform_cloud(np.concatenate([kf.surf, kf.outlier]), kf.pose6))

    def _scan_to_map(self, corner_map, surf_map, corner_ds, surf_ds, step: MappingStep) -> None:
        self.transform_tobe = self.register_to_map(corner_map, surf_map, corner_ds, surf_ds, self.transform_tobe, step)

    def register_to_map(
        self,
        corner_map: np.ndarray,
        surf_map: np.ndarray,
        corner_ds: np.ndarray,
        surf_ds: np.ndarray,
        initial: np.ndarray,
        step: MappingStep | None = None,
    ) -> np.ndarray:
        """Scan-to-map registration from ``initial``
        (:func:`~lego_loam_py.core.mapping.scan_to_map.register_scan_to_map`) with this mapper's degeneracy state;
        returns the optimised pose. ``step`` (optional) receives iteration and correspondence counts."""
        pose, counts = register_scan_to_map(
            corner_map, surf_map, corner_ds, surf_ds, initial, self.params, self._degeneracy
        )
        self._registration_information = counts.information
        if step is not None:
            step.optimised = True
            step.iterations, step.correspondences = counts.iterations, counts.correspondences
            step.degenerate, step.condition = counts.degenerate, counts.condition
        return pose

    def _transform_update(self, stamp_ns: int, step: MappingStep) -> None:
        # The IMU's roll and pitch, blended in by the IMU check (which compares the mapped turn with the IMU's first).
        step.imu_alignment = self.imu_check.update(stamp_ns, self.transform_tobe)
        self.transform_bef = self.transform_sum.copy()
        self.transform_aft = self.transform_tobe.copy()

    # ------------------------------------------------------------------------------------- the graph
    def _mapped_covariance(self, keyframe_added: bool, registration: np.ndarray | None) -> np.ndarray:
        """The covariance of transform_aft (see :class:`MappingStep`): a new keyframe's marginal when it is that
        keyframe, else the registration's on top of the latest keyframe's (the map's); without a registration (no map
        to register against yet) transform_aft is not a mapped pose: every direction at the registration's bound
        on top of the latest keyframe's."""
        if len(self.keyframe_covariance) and len(self.keyframe_covariance) == len(self.keyframes):
            anchor, anchor_covariance = self.keyframe_pose(-1), self.keyframe_covariance.covariance()
            aft = pose6_to_matrix(self.transform_aft)
            if keyframe_added and registration is not None:
                self.pose_covariance = anchor_covariance
            else:
                if registration is None:
                    registration = np.eye(6) * MAX_REGISTRATION_VARIANCE
                self.pose_covariance = mapped_covariance(anchor, anchor_covariance, aft, registration)
        return self.pose_covariance.copy()

    def _save_keyframe(
        self, stamp_ns: int, corner_ds, surf_ds, outlier_ds, registration: np.ndarray | None = None
    ) -> bool:
        mo = self.params.map_optimization
        self.current_position = self.transform_aft[3:].copy()
        if (
            self.keyframes
            and np.linalg.norm(self.current_position - self._previous_keyframe_position) < mo.keyframe_distance
        ):
            return False
        self._previous_keyframe_position = self.current_position.copy()
        k = len(self.keyframes)
        if k == 0:
            latest = self.graph.add_keyframe(0, self.transform_tobe)
            self.transform_last = self.transform_tobe.copy()
        else:
            latest = self.graph.add_keyframe(k, self.transform_aft, previous6=self.transform_last)
        self.keyframes.append(Keyframe(k, stamp_ns, latest, corner_ds, surf_ds, outlier_ds))
        self._positions = np.vstack([self._positions, latest[3:]])
        if len(self.keyframe_covariance) == k:  # (its keyframes are these, added as they come)
            if k and registration is None:  # (not registered: no map to register against)
                registration = np.eye(6) * MAX_REGISTRATION_VARIANCE
            self.keyframe_covariance.add_keyframe(pose6_to_matrix(latest), registration if k else None)
        if k > 0:
            self.transform_aft = latest.copy()
            self.transform_last = latest.copy()
            self.transform_tobe = latest.copy()
        return True

    def _correct_poses(self) -> None:
        if not self.loop_closed:
            return
        for kf, pose6 in zip(self.keyframes, self.graph.poses([kf.index for kf in self.keyframes])):
            kf.pose6 = pose6
        self._positions = np.array([kf.pose6[3:] for kf in self.keyframes])
        self._corner_accumulator.clear()  # every keyframe moved: the map is rebuilt at the next step
        self._surf_accumulator.clear()
        self.loop_closed = False

    # ------------------------------------------------------------------------------------ loop closure
    def detect_loop(self) -> LoopCandidate | None:
        """A loop candidate for the newest keyframe (:mod:`lego_loam_py.core.loop.closure`), or None."""
        with self.lock:
            return self.loop_method.detect(self)

    def close_loop(self, candidate: LoopCandidate) -> LoopResult:
        """Verify the candidate (without the lock: it takes a while); its constraint goes into the graph if it
        passes."""
        return self.loop_method.close(self, candidate)

    @property
    def keyframe_positions(self) -> np.ndarray:
        """(n, 3) positions of the keyframes (world, camera axes)."""
        return self._positions

    def keyframe_pose(self, index: int) -> np.ndarray:
        """4x4 pose of keyframe ``index`` (world, camera axes)."""
        return pose6_to_matrix(self.keyframes[index].pose6)

    def add_verified_loops(self, loops) -> None:
        """Constraints of verified loops into the graph; every keyframe and the pose being mapped follow."""
        lc = self.params.loop_closure
        newest = pose6_to_matrix(self.keyframes[-1].pose6)
        index = {kf.stamp_ns: kf.index for kf in self.keyframes}
        for pending in loops:
            latest, candidate = index[pending.latest_stamp_ns], index[pending.candidate_stamp_ns]
            self.graph.add_loop_constraint(
                candidate,
                latest,
                pending.relative_lidar,
                pending.result.information,
                lc.robust_kernel,
                lc.robust_kernel_width,
            )
            self.keyframe_covariance.add_loop(candidate, latest, pending.relative_lidar, self.graph.last_loop_noise)
        self.loop_closed = True
        self._correct_poses()
        # The pose being mapped moves with the newest keyframe, so that the next step starts where the corrected
        # map is (the original waits for the next keyframe and registers the old pose against the moved map).
        moved = pose6_to_matrix(self.keyframes[-1].pose6) @ invert_pose(newest)
        loops[-1].result.applied_m = float(np.linalg.norm(self.keyframes[-1].pose6[3:] - newest[:3, 3]))
        self.transform_aft = matrix_to_pose6(moved @ pose6_to_matrix(self.transform_aft))
        self.transform_tobe = matrix_to_pose6(moved @ pose6_to_matrix(self.transform_tobe))
        self.transform_last = self.keyframes[-1].pose6.copy()
        self.current_position = self.transform_aft[3:].copy()
        self._previous_keyframe_position = self.transform_last[3:].copy()

    def add_loop_factor(self, latest: int, candidate: int, relative: np.ndarray, variances: np.ndarray) -> None:
        """Add the constraint 'keyframe ``candidate`` seen from keyframe ``latest`` is ``relative``' (4x4,
        camera axes) with diagonal variances (rot, rot, rot, x, y, z in lidar axes, as the original), update
        iSAM2 and move every keyframe to the new estimate."""
        with self.lock:
            self.graph.add_loop(latest, candidate, relative, variances)
            self.keyframe_covariance.add_loop(
                latest, candidate, camera_pose_to_lidar(relative), self.graph.last_loop_noise
            )
            self.loop_closed = True
            self._correct_poses()

    # ------------------------------------------------------------------------------- maps and saving
    def keyframe_poses(self) -> np.ndarray:
        """(K, 6) keyframe poses (world convention, camera axes)."""
        with self.lock:
            return np.array([kf.pose6 for kf in self.keyframes]).reshape(-1, 6)

    def global_map(self, radius: float | None = None) -> np.ndarray:
        """The original's /laser_cloud_surround: keyframes within ``radius`` of the current position (through a
        1 m voxel grid of positions), corner + surface + outlier in the world, voxel-filtered (camera axes)."""
        mo = self.params.map_optimization
        radius = mo.global_map_visualization_search_radius if radius is None else radius
        with self.lock:
            if not self.keyframes:
                return np.zeros((0, 4), _F32)
            near = np.flatnonzero(np.linalg.norm(self._positions - self.current_position, axis=1) <= radius)
            ids = self._one_keyframe_per_voxel(near, mo.global_map_keypose_leaf_size)
            clouds = [
                transform_cloud(
                    np.concatenate([self.keyframes[i].corner, self.keyframes[i].surf, self.keyframes[i].outlier]),
                    self.keyframes[i].pose6,
                )
                for i in ids
            ]
        if not clouds:  # (the robot is beyond ``radius`` of every keyframe)
            return np.zeros((0, 4), _F32)
        return voxel_downsample(np.concatenate(clouds), mo.global_map_leaf_size)

    def maps(self) -> dict[str, np.ndarray]:
        """Full maps over every keyframe (camera axes): 'corner' (0.2 m voxels), 'surface' (surface + outliers,
        0.4 m), 'global' (everything, 0.4 m)."""
        mo = self.params.map_optimization
        with self.lock:
            corner = [transform_cloud(kf.corner, kf.pose6) for kf in self.keyframes]
            surface = [transform_cloud(np.concatenate([kf.surf, kf.outlier]), kf.pose6) for kf in self.keyframes]
        if not corner:
            empty = np.zeros((0, 4), _F32)
            return dict(corner=empty, surface=empty, global_map=empty)
        corner_map = voxel_downsample(np.concatenate(corner), mo.corner_leaf_size)
        surface_map = voxel_downsample(np.concatenate(surface), mo.surf_leaf_size)
        return dict(
            corner=corner_map,
            surface=surface_map,
            global_map=voxel_downsample(np.concatenate([corner_map, surface_map]), mo.global_map_leaf_size),
        )

    def keyframes_now(self) -> list[Keyframe]:
        """The keyframes as they stand, each with a copy of its pose (a loop closure replaces the poses later on;
        the clouds are never changed): what the occupancy grid is drawn from on another thread."""
        with self.lock:
            return [
                Keyframe(kf.index, kf.stamp_ns, kf.pose6.copy(), kf.corner, kf.surf, kf.outlier)
                for kf in self.keyframes
            ]

    def save(
        self, directory: str | Path, grid: OccupancyGrid | None = None, maps: dict[str, np.ndarray] | None = None
    ) -> dict[str, Path]:
        """Write the maps (PCD, REP-103 ``map`` axes), the keyframe trajectory (PCD, TUM), the map bundle that
        localization loads and, with ``occupancy_grid.enabled``, the occupancy grid (nav2 map_server files), each
        atomically (see :mod:`lego_loam_py.core.mapping.map_files`). ``grid``: a
        :class:`~lego_loam_py.core.mapping.occupancy_grid.OccupancyGrid` kept up to date meanwhile (the node's),
        brought to the saved keyframes; without it the grid is drawn from them here. A grid that cannot be made
        (a pose it refuses, more than ``occupancy_grid.max_cells``) leaves the rest of the save as it is and says why
        in :attr:`occupancy_problem` (None after a save with its grid). ``maps``: :meth:`maps` as it stands, when the
        caller made it already."""
        from lego_loam_py.core.mapping.map_bundle import MapBundle
        from lego_loam_py.core.mapping.map_files import write_map_files
        from lego_loam_py.core.mapping.occupancy_grid import OccupancyGrid

        maps = self.maps() if maps is None else maps
        with self.lock:  # (one consistent set of keyframes and factors)
            keyframes = self.keyframes_now()
            bundle = MapBundle.of(
                keyframes, list(self.graph.factors), self.params, maps['corner'], maps['surface'], self.map_source
            )
        occupancy, self.occupancy_problem = None, None
        if self.params.occupancy_grid.enabled:
            grid = grid if grid is not None else OccupancyGrid(self.params.occupancy_grid)
            try:
                with grid.lock:  # (the grid of exactly the saved keyframes)
                    grid.sync(keyframes)
                    occupancy = grid.ternary()
            except Exception as exc:  # (the map is saved all the same, without its grid; the caller is told)
                self.occupancy_problem = f'the occupancy grid was not saved: {exc}'
        return write_map_files(directory, maps, bundle, occupancy)
