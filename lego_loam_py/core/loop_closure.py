"""Loop closure of mapOptimization (docs/original.md §6.3): the candidate search, and the ICP that
checks a candidate before the pose graph gets its constraint (:meth:`MapOptimization.close_loop
<lego_loam_py.core.map_optimization.MapOptimization.close_loop>`).

Keyframe clouds and poses are in the world, camera axes (:mod:`lego_loam_py.core.frames`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from lego_loam_py.core.frames import transform_cloud, transform_points
from lego_loam_py.core.param_types import LoopClosureParams
from lego_loam_py.core.voxel import voxel_downsample

__all__ = ['LoopCandidate', 'LoopResult', 'find_loop_candidate', 'align_loop']


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


def find_loop_candidate(keyframes: Sequence, positions: np.ndarray, current_position: np.ndarray, latest_ns: int,
                        lc: LoopClosureParams) -> LoopCandidate | None:
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
    near = range(max(0, candidate - lc.history_keyframe_search_num),
                 min(latest, candidate + lc.history_keyframe_search_num) + 1)
    target = np.concatenate([transform_cloud(np.concatenate([keyframes[j].corner, keyframes[j].surf]),
                                             keyframes[j].pose6) for j in near])
    target = voxel_downsample(target, lc.history_keyframe_leaf_size)
    return LoopCandidate(latest, candidate, source, target)


def align_loop(candidate: LoopCandidate, lc: LoopClosureParams) -> LoopResult:
    """ICP (point to point, open3d) of the latest keyframe against the candidate's neighbourhood, judged as the
    original: accepted when it converged and its fitness is at most ``history_keyframe_fitness_score``."""
    import open3d as o3d

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
    return LoopResult(candidate.latest, candidate.candidate, fitness, converged, accepted, correction)
