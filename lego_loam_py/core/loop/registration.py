"""Verification of a loop candidate by registration: where the latest keyframe sits in the candidate's
neighbourhood, how well that fit holds (overlap, residual, how well it constrains each direction), and the
information of the resulting constraint for the pose graph.

Clouds and poses are in REP-103 lidar axes (x forward, y left, z up), as the pose graph keeps them, so the
information matrix is directly that of a gtsam ``BetweenFactorPose3(candidate, latest, pose)``: ordered
(rotation x, y, z [rad]; translation x, y, z [m]) in the tangent space of ``pose`` on the latest keyframe's side
(gtsam's ``pose * Expmap(delta)``).

The fit is open3d's point-to-plane ICP, coarse to fine over a few correspondence distances, so a start a metre
or two off (a place recognised by its descriptor, whose translation is unknown) still converges; the
statistics that judge it are computed here from the final pose with one nearest-neighbour query.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.frames import transform_points

__all__ = ['Registration', 'register']


@dataclass(frozen=True)
class Registration:
    """The result of :func:`register`."""

    pose: np.ndarray  # 4x4 source (latest keyframe) in the target's (candidate's) frame
    overlap: float  # share of source points with a target point within the inlier distance
    rmse: float  # point-to-plane RMS residual of those inliers [m]
    inliers: int
    constraint: float  # smallest eigenvalue of the per-inlier translational information (0..1/3; 0: a
    #                           direction the fit does not constrain, e.g. along a featureless corridor)
    information: np.ndarray  # 6x6 (rot, trans) information of the constraint (see the module docstring)
    # How far the points of ``subset`` (see :func:`register`) would move the pose on their own: one Gauss-Newton
    # step from the fit with their inliers alone, translation [m] and rotation [deg] (0: no subset given).
    subset_shift_m: float = 0.0
    subset_shift_deg: float = 0.0

    def gate_failure(self, min_overlap: float, max_rmse: float, min_constraint: float) -> str:
        """Why the fit fails the gates every verification applies ('' when it passes them): too little of the
        source on the target, too large a residual, or a direction left unconstrained."""
        if self.overlap < min_overlap:
            return f'overlap {self.overlap:.2f} < {min_overlap:g}'
        if self.rmse > max_rmse:
            return f'rmse {self.rmse:.3f} m > {max_rmse:g}'
        if self.constraint < min_constraint:
            return f'constraint {self.constraint:.3f} < {min_constraint:g}'
        return ''


def _normals(target: np.ndarray, radius: float, neighbours: int) -> np.ndarray:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=neighbours))
    return np.asarray(cloud.normals)


def register(
    source: np.ndarray,
    target: np.ndarray,
    initial: np.ndarray,
    distances: Sequence[float],
    iterations: int,
    inlier_distance: float,
    independent_points: float,
    min_sigma: float,
    normal_radius: float = 1.0,
    subset: np.ndarray | None = None,
) -> Registration:
    """Register ``source`` (N, 3) points of the latest keyframe(s), in the latest keyframe's frame, to ``target``
    (M, 3), in the candidate's frame, from ``initial`` (4x4, source in target frame) by point-to-plane ICP with
    the correspondence ``distances`` [m] in turn (``iterations`` each).

    The statistics use the source points within ``inlier_distance`` [m] of the target after the fit. The
    information is ``H * independent_points / N / sigma^2``: ``H`` the point-to-plane Gauss-Newton matrix of the
    N inliers, ``sigma`` their RMS residual (at least ``min_sigma`` [m]). Neighbouring residuals are not
    independent (a map's error is smooth), so the fit counts as ``independent_points`` measurements, whatever
    the number of points.

    ``subset`` (N booleans) marks source points whose own view of the fit is checked: the step they would take
    alone is in :attr:`Registration.subset_shift_m` / ``_deg`` (a source stacked from several keyframes whose
    poses disagree gives a compromise that none of them agrees with)."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    source = np.ascontiguousarray(source[:, :3], dtype=np.float64)
    target = np.ascontiguousarray(target[:, :3], dtype=np.float64)
    normals = _normals(target, normal_radius, 15)
    source_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    target_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    target_cloud.normals = o3d.utility.Vector3dVector(normals)
    pose = np.asarray(initial, dtype=np.float64).copy()
    for distance in distances:
        result = o3d.pipelines.registration.registration_icp(
            source_cloud,
            target_cloud,
            float(distance),
            pose,
            o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=int(iterations)),
        )
        pose = np.asarray(result.transformation).copy()
    moved = transform_points(pose, source)
    gap, nearest = cKDTree(target).query(moved, distance_upper_bound=inlier_distance)
    inside = np.isfinite(gap)
    count = int(inside.sum())
    if count < 6 or not np.isfinite(pose).all():
        return Registration(pose, count / max(len(source), 1), float('inf'), count, 0.0, np.zeros((6, 6)))
    normal = normals[nearest[inside]]
    residual = np.einsum('ij,ij->i', moved[inside] - target[nearest[inside]], normal)
    rmse = float(np.sqrt(np.mean(residual**2)))
    # d residual / d delta for source points p moved by pose * Expmap(delta): [p x m, m], m = R^T n (the normal in
    # the source frame).
    m = normal @ pose[:3, :3]
    p = source[inside]
    jacobian = np.concatenate([np.cross(p, m), m], axis=1)
    hessian = jacobian.T @ jacobian
    constraint = float(np.linalg.eigvalsh(hessian[3:, 3:] / count)[0])
    sigma = max(rmse, min_sigma)
    information = hessian * (independent_points / count) / sigma**2
    shift_m, shift_deg = _subset_step(jacobian, residual, subset[inside]) if subset is not None else (0.0, 0.0)
    return Registration(pose, count / len(source), rmse, count, constraint, information, shift_m, shift_deg)


def _subset_step(jacobian: np.ndarray, residual: np.ndarray, chosen: np.ndarray) -> tuple[float, float]:
    """The Gauss-Newton step (translation [m], rotation [deg]) of the ``chosen`` rows alone, over the directions
    they constrain (eigenvalues above 1 % of the largest: a direction they leave open is no disagreement)."""
    if chosen.sum() < 6:
        return 0.0, 0.0
    rows, r = jacobian[chosen], residual[chosen]
    # Rotations scaled to metres at the points' RMS range, so that both kinds of direction compare.
    arm = max(float(np.sqrt(np.mean(np.sum(rows[:, :3] ** 2, axis=1)))), 1e-6)
    scale = np.array([1.0 / arm] * 3 + [1.0] * 3)
    rows = rows * scale
    values, vectors = np.linalg.eigh(rows.T @ rows)
    keep = values > 0.01 * values[-1]
    step = -vectors[:, keep] @ ((vectors[:, keep].T @ (rows.T @ r)) / values[keep]) * scale
    return float(np.linalg.norm(step[3:])), float(np.degrees(np.linalg.norm(step[:3])))
