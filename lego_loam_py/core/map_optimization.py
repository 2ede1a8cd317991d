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
the set, not a new filter of some 50 keyframes; a loop closure that moves the poses rebuilds it.

Scan-to-map registration: for each downsampled corner point, the 5 nearest map corners must span a line
(largest eigenvalue > 3 × the middle one); for each surface point, the 5 nearest map surface points must
fit a plane within 0.2 m. Up to 10 full Gauss-Newton steps with the original's weights, degeneracy
projection (eigenvalues < 100 on the first iteration) and convergence test (0.05 deg, 0.05 cm).

Thread safety: :meth:`process`, :meth:`detect_loop`, :meth:`close_loop`, :meth:`global_map` and
:meth:`save` take one lock, so loop closure can run in another thread (as the original's 1 Hz thread).
"""
from __future__ import annotations

import math
import threading
import time as _time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lego_loam_py.core.frames import (camera_pose_to_lidar, camera_to_lidar, invert_pose, lidar_pose_to_camera,
                                      matrix_to_pose6, pose6_to_matrix, rot_x, rot_y, rot_z, transform_points)
from lego_loam_py.core.imu import ImuBuffer
from lego_loam_py.core.laser_odometry import line_coefficients
from lego_loam_py.core.odometry_continuity import OdometryJump, anchored_transform_bef
from lego_loam_py.core.params import Params
from lego_loam_py.core.validation import pose6_problem
from lego_loam_py.core.voxel import VoxelAccumulator, voxel_downsample, voxel_indices

__all__ = ['MapOptimization', 'MappingStep', 'LoopCandidate', 'LoopResult', 'map_jacobian_rows',
           'edge_correspondences', 'plane_correspondences', 'transform_cloud']

_F32 = np.float32
_GX = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_GY = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
_GZ = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


def transform_cloud(points: np.ndarray, pose6: np.ndarray) -> np.ndarray:
    """(n, 4) points (camera axes, intensity kept) mapped with a world-convention pose six-vector."""
    out = np.empty_like(points, dtype=_F32)
    out[:, :3] = transform_points(pose6_to_matrix(pose6), points[:, :3].astype(np.float64))
    out[:, 3] = points[:, 3]
    return out


def map_jacobian_rows(points: np.ndarray, coeff: np.ndarray, pose6: np.ndarray) -> np.ndarray:
    """Rows ``coeff · d(R p + t)/d(rx, ry, rz, tx, ty, tz)`` with ``R = Ry(ry) Rx(rx) Rz(rz)``."""
    rx, ry, rz = (float(v) for v in pose6[:3])
    Ry, Rx, Rz = rot_y(ry), rot_x(rx), rot_z(rz)
    p = points[:, :3].astype(np.float64)
    c = coeff[:, :3].astype(np.float64)
    rows = np.empty((len(points), 6))
    for k, derivative in enumerate((Ry @ Rx @ _GX @ Rz, Ry @ _GY @ Rx @ Rz, Ry @ Rx @ Rz @ _GZ)):
        rows[:, k] = np.einsum('ni,ni->n', c, p @ derivative.T)
    rows[:, 3:] = c
    return rows


def _neighbourhoods(points_world: np.ndarray, tree: cKDTree, map_points: np.ndarray, mo):
    """(indices of the points whose ``knn`` nearest map points all lie within the gate, those neighbours
    (m, k, 3) float64). The tree search stops at the gate, which spares most of the walk for points off the
    map; the neighbours of the points that pass are the exact k nearest."""
    bound = math.sqrt(mo.knn_max_sq_dist) * (1.0 + 1e-9)
    distance, index = tree.query(points_world[:, :3], k=mo.knn, distance_upper_bound=bound)
    used = np.flatnonzero(distance[:, -1] ** 2 < mo.knn_max_sq_dist)
    return used, map_points[index[used], :3].astype(np.float64)


def edge_correspondences(points_world: np.ndarray, tree: cKDTree, map_points: np.ndarray, params: Params):
    """Point-to-line coefficients: (index of used points, coeff (m, 4) = s·gradient, s·distance)."""
    mo = params.map_optimization
    if len(points_world) == 0 or tree is None:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4))
    used, neighbours = _neighbourhoods(points_world, tree, map_points, mo)
    centroid = neighbours.mean(axis=1)
    centred = neighbours - centroid[:, None, :]
    covariance = np.einsum('mki,mkj->mij', centred, centred) / mo.knn
    values, vectors = np.linalg.eigh(covariance)                         # ascending
    is_line = values[:, 2] > mo.edge_eigen_ratio * values[:, 1]
    used, centroid, direction = used[is_line], centroid[is_line], vectors[is_line, :, 2]
    a = centroid + mo.line_half_length * direction
    b = centroid - mo.line_half_length * direction
    gradient, dist = line_coefficients(points_world[used], a.astype(_F32), b.astype(_F32))
    weight = 1.0 - mo.weight_gain * np.abs(dist.astype(np.float64))
    keep = (weight > mo.min_weight) & np.isfinite(dist) & np.isfinite(gradient).all(axis=1)
    coeff = np.concatenate([gradient[keep] * weight[keep, None], (weight[keep] * dist[keep])[:, None]], axis=1)
    return used[keep], coeff


def plane_correspondences(points_world: np.ndarray, tree: cKDTree, map_points: np.ndarray, params: Params):
    """Point-to-plane coefficients: (index of used points, coeff (m, 4) = s·normal, s·distance)."""
    mo = params.map_optimization
    if len(points_world) == 0 or tree is None:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4))
    used, neighbours = _neighbourhoods(points_world, tree, map_points, mo)
    # Least-squares plane n·x = -1 through the neighbours: the normal equations (A^T A) n = -A^T 1, solved in
    # closed form (Cramer's rule on the symmetric 3x3 systems, vectorised over all points).
    xx, yy, zz = (np.einsum('mk,mk->m', neighbours[..., i], neighbours[..., i]) for i in range(3))
    xy = np.einsum('mk,mk->m', neighbours[..., 0], neighbours[..., 1])
    xz = np.einsum('mk,mk->m', neighbours[..., 0], neighbours[..., 2])
    yz = np.einsum('mk,mk->m', neighbours[..., 1], neighbours[..., 2])
    b = -neighbours.sum(axis=1)
    c00, c01, c02 = yy * zz - yz * yz, xz * yz - xy * zz, xy * yz - xz * yy
    c11, c12, c22 = xx * zz - xz * xz, xy * xz - xx * yz, xx * yy - xy * xy
    det = xx * c00 + xy * c01 + xz * c02
    solvable = np.abs(det) > 1e-12
    with np.errstate(divide='ignore', invalid='ignore'):
        normal = np.stack([c00 * b[:, 0] + c01 * b[:, 1] + c02 * b[:, 2],
                           c01 * b[:, 0] + c11 * b[:, 1] + c12 * b[:, 2],
                           c02 * b[:, 0] + c12 * b[:, 1] + c22 * b[:, 2]], axis=1) / det[:, None]
    used, neighbours, normal = used[solvable], neighbours[solvable], normal[solvable]
    norm = np.linalg.norm(normal, axis=1)
    normal /= norm[:, None]
    offset = 1.0 / norm
    residuals = np.abs(np.einsum('mki,mi->mk', neighbours, normal) + offset[:, None])
    valid = (residuals <= mo.plane_max_residual).all(axis=1)
    used, normal, offset = used[valid], normal[valid], offset[valid]
    p = points_world[used, :3].astype(np.float64)
    dist = np.einsum('mi,mi->m', p, normal) + offset
    weight = 1.0 - mo.weight_gain * np.abs(dist) / np.sqrt(np.linalg.norm(p, axis=1))
    keep = weight > mo.min_weight
    coeff = np.concatenate([normal[keep] * weight[keep, None], (weight[keep] * dist[keep])[:, None]], axis=1)
    return used[keep], coeff


@dataclass
class Keyframe:
    index: int
    stamp_ns: int
    pose6: np.ndarray        # optimised pose (world convention, camera axes)
    corner: np.ndarray       # (n, 4) sensor frame, camera axes, downsampled
    surf: np.ndarray
    outlier: np.ndarray


@dataclass
class MappingStep:
    """Result of one mapping step (what /aft_mapped_to_init publishes)."""

    stamp_ns: int
    transform_aft: np.ndarray         # optimised pose of aft_mapped in camera_init
    transform_bef: np.ndarray         # the odometry pose it was computed from
    keyframe_added: bool
    keyframes: int
    correspondences: int = 0
    iterations: int = 0
    degenerate: bool = False
    optimised: bool = False
    corner_map_points: int = 0
    surf_map_points: int = 0
    timings_ms: dict = field(default_factory=dict)


@dataclass
class LoopCandidate:
    latest: int
    candidate: int
    source: np.ndarray     # world points (camera axes) of the latest keyframe
    target: np.ndarray     # world points of the candidate's neighbourhood, downsampled


@dataclass
class LoopResult:
    latest: int
    candidate: int
    fitness: float         # PCL-style: mean squared distance to the nearest target point [m^2]
    converged: bool
    accepted: bool
    correction: np.ndarray  # 4x4 world-frame correction (camera axes) applied to the latest keyframe


class _Degeneracy:
    def __init__(self):
        self.projection = np.eye(6)
        self.degenerate = False

    def update(self, ata: np.ndarray, threshold: float) -> None:
        values, vectors = np.linalg.eigh(ata)
        keep = np.ones(6, dtype=bool)
        self.degenerate = False
        for i in range(6):
            if values[i] < threshold:
                keep[i] = False
                self.degenerate = True
            else:
                break
        self.projection = vectors @ np.diag(keep.astype(float)) @ vectors.T


class MapOptimization:
    """The mapOptimization algorithm; :meth:`process` is called with each synchronised input set."""

    def __init__(self, params: Params):
        import gtsam

        self._gtsam = gtsam
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
        self._prior_noise = gtsam.noiseModel.Diagonal.Variances(np.asarray(mo.prior_noise_variances, dtype=float))
        self._odometry_noise = gtsam.noiseModel.Diagonal.Variances(np.asarray(mo.odometry_noise_variances, dtype=float))
        self._rebuild_graph()   # (empty)
        self.imu = ImuBuffer(params.feature_association.imu_que_length, params.feature_association.gravity,
                             params.sensor.scan_period)
        self._degeneracy = _Degeneracy()
        self._last_processing_ns: int | None = None
        self.latest_odometry_ns = 0
        self.loop_closed = False
        self.loops: list[LoopResult] = []
        self.lock = threading.RLock()
        self.last_maps: tuple[np.ndarray, np.ndarray] = (np.zeros((0, 4), _F32), np.zeros((0, 4), _F32))
        self.last_scan: tuple[np.ndarray, np.ndarray] = (np.zeros((0, 4), _F32), np.zeros((0, 4), _F32))

    # --------------------------------------------------------------------------------- self-checks
    def health_problem(self) -> str | None:
        """Why the mapping state is poisoned (non-finite or absurd poses, optimizer solution or IMU), or None.
        Checked after every step; :meth:`heal` repairs it."""
        with self.lock:
            return (pose6_problem('the mapped pose', self.transform_aft)
                    or pose6_problem('the pose being optimised', self.transform_tobe)
                    or pose6_problem('the odometry of the last step', self.transform_bef)
                    or pose6_problem('the latest odometry', self.transform_sum)
                    or pose6_problem('the last keyframe pose', self.transform_last)
                    or (pose6_problem('the newest keyframe (optimizer solution)', self.keyframes[-1].pose6)
                        if self.keyframes else None)
                    or self.imu.health_problem())

    def reanchor(self, jump: OdometryJump, pose: np.ndarray, transform_sum: np.ndarray) -> None:
        """The odometry restarted (``jump``, see :mod:`lego_loam_py.core.odometry_continuity`) and is now at
        ``pose`` (4x4) = ``transform_sum`` (six-vector): the next step starts from the last mapped pose, moved on
        at the last speed over the gap, instead of the odometry's new origin."""
        with self.lock:
            self.transform_bef = anchored_transform_bef(jump, pose, self.transform_aft, self.transform_bef)
            self.transform_sum = np.asarray(transform_sum, dtype=float).copy()

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
                self.keyframes = [Keyframe(i, kf.stamp_ns, kf.pose6, kf.corner, kf.surf, kf.outlier)
                                  for i, kf in enumerate(good)]
                self._rebuild_graph()
            self._positions = np.array([kf.pose6[3:] for kf in self.keyframes]).reshape(-1, 3)
            anchor = self.keyframes[-1].pose6.copy() if self.keyframes else np.zeros(6)
            self.transform_aft, self.transform_tobe, self.transform_last = anchor.copy(), anchor.copy(), anchor.copy()
            if pose6_problem('', self.transform_sum) is not None:
                self.transform_sum = np.zeros(6)
            # T_aft · T_bef^-1 · T_sum predicts the anchor for the latest odometry: mapping resumes there.
            self.transform_bef = self.transform_sum.copy()
            self.current_position = anchor[3:].copy()
            self._previous_keyframe_position = anchor[3:].copy() if self.keyframes else None
            self._corner_accumulator.clear()
            self._surf_accumulator.clear()
            if self.imu.health_problem() is not None:
                self.imu.clear()
                done.append('IMU samples dropped')
            done.append(f'mapping resumes from keyframe {len(self.keyframes) - 1}' if self.keyframes
                        else 'mapping starts again')
            return ', '.join(done) + f'; {len(self.keyframes)} keyframes kept'

    def _rebuild_graph(self) -> None:
        """A new iSAM2 graph over the keyframes' current poses: a prior on the first, between factors along."""
        gtsam = self._gtsam
        mo = self.params.map_optimization
        isam_params = gtsam.ISAM2Params()
        isam_params.setRelinearizeThreshold(mo.isam_relinearize_threshold)
        isam_params.relinearizeSkip = mo.isam_relinearize_skip
        # QR, not gtsam's default Cholesky: with the original's tiny variances (1e-8 m^2) Cholesky declares the
        # system indeterminate once the keyframes are some 50 m from the origin; QR stays well-conditioned.
        isam_params.setFactorization('QR')
        self.isam = gtsam.ISAM2(isam_params)
        if not self.keyframes:
            return
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        poses = [self._gtsam_pose(kf.pose6) for kf in self.keyframes]
        graph.add(gtsam.PriorFactorPose3(0, poses[0], self._prior_noise))
        values.insert(0, poses[0])
        for k in range(1, len(poses)):
            graph.add(gtsam.BetweenFactorPose3(k - 1, k, poses[k - 1].between(poses[k]), self._odometry_noise))
            values.insert(k, poses[k])
        self.isam.update(graph, values)
        self.isam.update()

    # ------------------------------------------------------------------------------------------ steps
    def process(self, stamp_ns: int, transform_sum: np.ndarray, corner_last: np.ndarray, surf_last: np.ndarray,
                outlier_last: np.ndarray) -> MappingStep | None:
        """One mapping step, or None when less than ``mapping_process_interval`` passed since the last one."""
        mo = self.params.map_optimization
        interval_ns = int(round(mo.mapping_process_interval * 1e9))
        with self.lock:
            self.latest_odometry_ns = stamp_ns
            self.transform_sum = np.asarray(transform_sum, dtype=float).copy()
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
            step = MappingStep(stamp_ns, self.transform_aft, self.transform_bef, False, len(self.keyframes),
                               corner_map_points=len(corner_map), surf_map_points=len(surf_map))
            if len(corner_map) > mo.min_corner_map_points and len(surf_map) > mo.min_surf_map_points:
                self._scan_to_map(corner_map, surf_map, corner_ds, surf_total_ds, step)
                # As in the original, the poses only move on when a map was there to register against: the
                # first step (no map yet) keeps transform_aft/bef at their previous values.
                self._transform_update(stamp_ns)
            t2 = _time.perf_counter()
            step.keyframe_added = self._save_keyframe(stamp_ns, corner_ds, surf_ds, outlier_ds)
            self._correct_poses()
            t3 = _time.perf_counter()
            timings.update(map=(t1 - t0) * 1e3, registration=(t2 - t1) * 1e3, graph=(t3 - t2) * 1e3,
                           total=(t3 - t0) * 1e3)
            step.timings_ms = timings
            step.transform_aft = self.transform_aft.copy()
            step.transform_bef = self.transform_bef.copy()
            step.keyframes = len(self.keyframes)
            self.last_maps = (corner_map, surf_map)
            self.last_scan = (corner_ds, surf_total_ds)
            return step

    def _associate_to_map(self) -> None:
        """Prediction of the map-frame pose from the odometry: ``T_aft · T_bef^-1 · T_sum``."""
        predicted = pose6_to_matrix(self.transform_aft) @ invert_pose(pose6_to_matrix(self.transform_bef)) @ \
            pose6_to_matrix(self.transform_sum)
        self.transform_tobe = matrix_to_pose6(predicted)

    def _surrounding_ids(self) -> list[int]:
        mo, lc = self.params.map_optimization, self.params.loop_closure
        n = len(self.keyframes)
        if n == 0:
            return []
        if lc.loop_closure_enable_flag:
            return list(range(max(0, n - mo.surrounding_keyframe_search_num), n))
        near = np.flatnonzero(np.linalg.norm(self._positions - self.current_position, axis=1)
                              <= mo.surrounding_keyframe_search_radius)
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
        order = np.lexsort((ids, voxel))                     # by voxel, then by keyframe index
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
        return (transform_cloud(kf.corner, kf.pose6),
                transform_cloud(np.concatenate([kf.surf, kf.outlier]), kf.pose6))

    def _scan_to_map(self, corner_map, surf_map, corner_ds, surf_ds, step: MappingStep) -> None:
        self.transform_tobe = self.register_to_map(corner_map, surf_map, corner_ds, surf_ds, self.transform_tobe, step)

    def register_to_map(self, corner_map: np.ndarray, surf_map: np.ndarray, corner_ds: np.ndarray,
                        surf_ds: np.ndarray, initial: np.ndarray, step: MappingStep | None = None) -> np.ndarray:
        """Scan-to-map Gauss-Newton from ``initial`` (pose six-vector); returns the optimised pose.

        ``corner_ds`` / ``surf_ds`` are the scan's downsampled features in its sensor frame, the maps are in the
        world (camera axes). ``step`` (optional) receives iteration and correspondence counts.
        """
        mo = self.params.map_optimization
        step = step if step is not None else MappingStep(0, initial, initial, False, 0)
        pose = np.asarray(initial, dtype=float).copy()
        corner_tree = cKDTree(corner_map[:, :3].astype(np.float64), balanced_tree=False)
        surf_tree = cKDTree(surf_map[:, :3].astype(np.float64), balanced_tree=False)
        step.optimised = True
        for iteration in range(mo.max_iterations):
            step.iterations = iteration + 1
            world = pose6_to_matrix(pose)
            corner_world = transform_points(world, corner_ds[:, :3].astype(np.float64)).astype(_F32)
            surf_world = transform_points(world, surf_ds[:, :3].astype(np.float64)).astype(_F32)
            ci, cc = edge_correspondences(corner_world, corner_tree, corner_map, self.params)
            si, sc = plane_correspondences(surf_world, surf_tree, surf_map, self.params)
            points = np.concatenate([corner_ds[ci], surf_ds[si]])
            coeff = np.concatenate([cc, sc])
            step.correspondences = len(coeff)
            if len(coeff) < mo.min_correspondences:
                break  # nothing would change in the next iterations
            a = map_jacobian_rows(points, coeff, pose)
            b = -coeff[:, 3]
            ata, atb = a.T @ a, a.T @ b
            try:
                x = np.linalg.solve(ata, atb)
            except np.linalg.LinAlgError:
                x = np.linalg.lstsq(ata, atb, rcond=None)[0]
            if iteration == 0:
                self._degeneracy.update(ata, mo.degeneracy_threshold)
            step.degenerate = self._degeneracy.degenerate
            if self._degeneracy.degenerate:
                x = self._degeneracy.projection @ x
            if not np.isfinite(x).all():
                break
            pose = pose + x
            delta_r = math.degrees(math.sqrt(float(x[0] ** 2 + x[1] ** 2 + x[2] ** 2)))
            delta_t = math.sqrt(float(((x[3:] * 100.0) ** 2).sum()))
            if delta_r < mo.convergence_rotation and delta_t < mo.convergence_translation:
                break
        return pose

    def _transform_update(self, stamp_ns: int) -> None:
        mo = self.params.map_optimization
        if len(self.imu):
            state = self.imu.interpolate([stamp_ns * 1e-9 + self.params.sensor.scan_period])
            w = mo.imu_blend_weight
            self.transform_tobe[0] = (1 - w) * self.transform_tobe[0] + w * float(state.pitch[0])
            self.transform_tobe[2] = (1 - w) * self.transform_tobe[2] + w * float(state.roll[0])
        self.transform_bef = self.transform_sum.copy()
        self.transform_aft = self.transform_tobe.copy()

    # ------------------------------------------------------------------------------------- the graph
    def _gtsam_pose(self, pose6: np.ndarray):
        lidar = camera_pose_to_lidar(pose6_to_matrix(pose6))
        return self._gtsam.Pose3(self._gtsam.Rot3(lidar[:3, :3]), lidar[:3, 3].copy())

    @staticmethod
    def _pose6_of(gtsam_pose) -> np.ndarray:
        return matrix_to_pose6(lidar_pose_to_camera(gtsam_pose.matrix()))

    def _save_keyframe(self, stamp_ns: int, corner_ds, surf_ds, outlier_ds) -> bool:
        mo = self.params.map_optimization
        gtsam = self._gtsam
        self.current_position = self.transform_aft[3:].copy()
        if self.keyframes and np.linalg.norm(self.current_position - self._previous_keyframe_position) < \
                mo.keyframe_distance:
            return False
        self._previous_keyframe_position = self.current_position.copy()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        k = len(self.keyframes)
        if k == 0:
            pose = self._gtsam_pose(self.transform_tobe)
            graph.add(gtsam.PriorFactorPose3(0, pose, self._prior_noise))
            values.insert(0, pose)
            self.transform_last = self.transform_tobe.copy()
        else:
            pose_from = self._gtsam_pose(self.transform_last)
            pose_to = self._gtsam_pose(self.transform_aft)
            graph.add(gtsam.BetweenFactorPose3(k - 1, k, pose_from.between(pose_to), self._odometry_noise))
            values.insert(k, pose_to)
        self.isam.update(graph, values)
        self.isam.update()
        latest = self._pose6_of(self.isam.calculateEstimatePose3(k))
        self.keyframes.append(Keyframe(k, stamp_ns, latest, corner_ds, surf_ds, outlier_ds))
        self._positions = np.vstack([self._positions, latest[3:]])
        if k > 0:
            self.transform_aft = latest.copy()
            self.transform_last = latest.copy()
            self.transform_tobe = latest.copy()
        return True

    def _correct_poses(self) -> None:
        if not self.loop_closed:
            return
        estimate = self.isam.calculateEstimate()
        for kf in self.keyframes:
            kf.pose6 = self._pose6_of(estimate.atPose3(kf.index))
        self._positions = np.array([kf.pose6[3:] for kf in self.keyframes])
        self._corner_accumulator.clear()   # every keyframe moved: the map is rebuilt at the next step
        self._surf_accumulator.clear()
        self.loop_closed = False

    # ------------------------------------------------------------------------------------ loop closure
    def detect_loop(self) -> LoopCandidate | None:
        """The original's candidate search: the nearest keyframe within the radius that is old enough."""
        lc = self.params.loop_closure
        with self.lock:
            if not self.keyframes:
                return None
            distance = np.linalg.norm(self._positions - self.current_position, axis=1)
            order = np.argsort(distance, kind='stable')
            order = order[distance[order] <= lc.history_keyframe_search_radius]
            times = np.array([kf.stamp_ns for kf in self.keyframes])
            old = np.abs(times[order] - self.latest_odometry_ns) > lc.time_gap * 1e9
            if not old.any():
                return None
            candidate = int(order[np.argmax(old)])
            latest = len(self.keyframes) - 1
            kf = self.keyframes[latest]
            source = transform_cloud(np.concatenate([kf.corner, kf.surf]), kf.pose6)
            source = source[np.trunc(source[:, 3]) >= 0]
            near = range(max(0, candidate - lc.history_keyframe_search_num),
                         min(latest, candidate + lc.history_keyframe_search_num) + 1)
            target = np.concatenate([transform_cloud(np.concatenate([self.keyframes[j].corner, self.keyframes[j].surf]),
                                                     self.keyframes[j].pose6) for j in near])
            target = voxel_downsample(target, lc.history_keyframe_leaf_size)
            return LoopCandidate(latest, candidate, source, target)

    def close_loop(self, candidate: LoopCandidate) -> LoopResult:
        """ICP of the latest keyframe against the candidate's neighbourhood; adds a loop factor when the fit
        is good enough. The ICP runs without the lock (it can take a while)."""
        import open3d as o3d

        lc = self.params.loop_closure
        source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(candidate.source[:, :3].astype(np.float64)))
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(candidate.target[:, :3].astype(np.float64)))
        criteria = o3d.pipelines.registration.ICPConvergenceCriteria(
            relative_fitness=lc.icp_euclidean_fitness_epsilon, relative_rmse=lc.icp_transformation_epsilon,
            max_iteration=lc.icp_max_iterations)
        result = o3d.pipelines.registration.registration_icp(
            source, target, lc.icp_max_correspondence_distance, np.eye(4),
            o3d.pipelines.registration.TransformationEstimationPointToPoint(), criteria)
        correction = np.asarray(result.transformation)
        aligned = transform_points(correction, candidate.source[:, :3].astype(np.float64))
        distance, _ = cKDTree(candidate.target[:, :3].astype(np.float64)).query(aligned)
        inside = distance <= lc.icp_max_correspondence_distance
        fitness = float(np.mean(distance[inside] ** 2)) if inside.any() else float('inf')
        converged = bool(np.isfinite(correction).all() and len(result.correspondence_set) > 0)
        accepted = converged and fitness <= lc.history_keyframe_fitness_score
        loop = LoopResult(candidate.latest, candidate.candidate, fitness, converged, accepted, correction)
        if accepted:
            with self.lock:
                latest_pose = pose6_to_matrix(self.keyframes[candidate.latest].pose6)
                corrected = correction @ latest_pose
                target_pose = pose6_to_matrix(self.keyframes[candidate.candidate].pose6)
                self.add_loop_factor(candidate.latest, candidate.candidate, invert_pose(corrected) @ target_pose,
                                     np.full(6, max(fitness, 1e-12)))
        self.loops.append(loop)
        return loop

    def add_loop_factor(self, latest: int, candidate: int, relative: np.ndarray, variances: np.ndarray) -> None:
        """Add the constraint 'keyframe ``candidate`` seen from keyframe ``latest`` is ``relative``' (4x4,
        camera axes) with diagonal variances (rot, rot, rot, x, y, z in lidar axes, as the original), update
        iSAM2 and move every keyframe to the new estimate."""
        gtsam = self._gtsam
        with self.lock:
            lidar = camera_pose_to_lidar(relative)
            between = gtsam.Pose3(gtsam.Rot3(lidar[:3, :3]), lidar[:3, 3].copy())
            graph = gtsam.NonlinearFactorGraph()
            graph.add(gtsam.BetweenFactorPose3(latest, candidate, between,
                                               gtsam.noiseModel.Diagonal.Variances(np.asarray(variances, float))))
            self.isam.update(graph, gtsam.Values())
            self.isam.update()
            self.loop_closed = True
            self._correct_poses()

    # ------------------------------------------------------------------------------- maps and saving
    def keyframe_poses(self) -> np.ndarray:
        """(K, 6) keyframe poses (world convention, camera axes)."""
        with self.lock:
            return np.array([kf.pose6 for kf in self.keyframes]).reshape(-1, 6)

    def keyframe_stamps(self) -> np.ndarray:
        with self.lock:
            return np.array([kf.stamp_ns for kf in self.keyframes], dtype=np.int64)

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
            clouds = [transform_cloud(np.concatenate([self.keyframes[i].corner, self.keyframes[i].surf,
                                                      self.keyframes[i].outlier]), self.keyframes[i].pose6)
                      for i in ids]
        if not clouds:   # (the robot is beyond ``radius`` of every keyframe)
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
        return dict(corner=corner_map, surface=surface_map,
                    global_map=voxel_downsample(np.concatenate([corner_map, surface_map]), mo.global_map_leaf_size))

    def save(self, directory: str | Path) -> dict[str, Path]:
        """Write the maps (PCD, REP-103 ``map`` axes, intensity kept) and the keyframe trajectory (PCD of
        positions, and TUM in both REP-103 map axes and the original's camera_init axes). Each file is
        written under a temporary name and renamed, so a crash never leaves a half-written file."""
        from lego_loam_py.core.io import write_pcd_atomic, write_tum_atomic

        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        maps = self.maps()
        poses = self.keyframe_poses()
        stamps = self.keyframe_stamps()
        camera_matrices = np.array([pose6_to_matrix(p) for p in poses]).reshape(-1, 4, 4)
        lidar_matrices = np.array([camera_pose_to_lidar(m) for m in camera_matrices]).reshape(-1, 4, 4)
        written = {}
        for name, cloud in (('global_map', maps['global_map']), ('corner_map', maps['corner']),
                            ('surface_map', maps['surface'])):
            in_map = np.concatenate([camera_to_lidar(cloud[:, :3]), cloud[:, 3:]], axis=1)
            written[name] = write_pcd_atomic(directory / f'{name}.pcd', in_map)
        trajectory = np.concatenate([lidar_matrices[:, :3, 3], np.arange(len(poses))[:, None]], axis=1)
        written['trajectory'] = write_pcd_atomic(directory / 'trajectory.pcd', trajectory.astype(_F32))
        written['trajectory_tum'] = write_tum_atomic(directory / 'trajectory.tum', stamps, lidar_matrices)
        written['trajectory_camera_init_tum'] = write_tum_atomic(directory / 'trajectory_camera_init.tum', stamps,
                                                                 camera_matrices)
        return written

