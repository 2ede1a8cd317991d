"""Scan-to-map registration of mapOptimization (docs/original.md §6.3).

For each downsampled corner point, the 5 nearest map corners must span a line (largest eigenvalue > 3 × the
middle one); for each surface point, the 5 nearest map surface points must fit a plane within 0.2 m. Up to 10
full Gauss-Newton steps with the original's weights, degeneracy projection (eigenvalues of the first
iteration's normal matrix below ``degeneracy_threshold``,
:class:`~lego_loam_py.core.gauss_newton.DegeneracyProjection`) and convergence test (0.05 deg, 0.05 cm). Poses
are world-convention six-vectors in camera axes (:mod:`lego_loam_py.core.frames`).

The rows of the normal matrix are weight × (unit normal or unit line gradient, its moment about the sensor),
so an eigenvalue is the number of full-weight correspondences that hold that direction, a rotation counting
as the displacement it gives 1 m from the sensor: the smallest one (the step's *condition*) says how well the
worst direction was held.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.frames import (
    GENERATOR_X,
    GENERATOR_Y,
    GENERATOR_Z,
    pose6_to_matrix,
    rot_x,
    rot_y,
    rot_z,
    transform_points,
)
from lego_loam_py.core.gauss_newton import DegeneracyProjection, residual_information
from lego_loam_py.core.geometry import GridNeighbours, fit_planes_at, line_coefficients, line_fits_at
from lego_loam_py.core.indexing import select_rows, xyz_columns
from lego_loam_py.core.params.types import Params

try:  # (the C kernels of the correspondences' terms; NumPy without them)
    from lego_loam_py.core import _geometry_kernels
except ImportError:
    _geometry_kernels = None

__all__ = [
    'map_jacobian_rows',
    'edge_correspondences',
    'plane_correspondences',
    'register_scan_to_map',
    'RegistrationCounts',
    'map_trees',
    'registration_information',
]

_F32 = np.float32


def map_jacobian_rows(points: np.ndarray, coeff: np.ndarray, pose6: np.ndarray) -> np.ndarray:
    """Rows ``coeff · d(R p + t)/d(rx, ry, rz, tx, ty, tz)`` with ``R = Ry(ry) Rx(rx) Rz(rz)``."""
    rx, ry, rz = (float(v) for v in pose6[:3])
    Ry, Rx, Rz = rot_y(ry), rot_x(rx), rot_z(rz)
    p = xyz_columns(points)
    c = xyz_columns(coeff)
    rows = np.empty((len(points), 6))
    for k, derivative in enumerate(
        (Ry @ Rx @ GENERATOR_X @ Rz, Ry @ GENERATOR_Y @ Rx @ Rz, Ry @ Rx @ Rz @ GENERATOR_Z)
    ):
        rows[:, k] = np.einsum('ni,ni->n', c, p @ derivative.T)
    rows[:, 3:] = c
    return rows


def edge_correspondences(
    points_world: np.ndarray, tree: GridNeighbours, map_points: np.ndarray, params: Params, native: bool = True
):
    """Point-to-line coefficients: (index of used points, coeff (m, 4) = s·gradient, s·distance). The terms after
    the line fits in one C pass when the extension is built (``_geometry_kernels.map_line_terms``, NumPy's float32
    and float64 operations in its order); ``native=False``: NumPy (the tests compare the two)."""
    mo = params.map_optimization
    if len(points_world) == 0 or tree is None:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4))
    used, index = tree.nearest_within(points_world, mo.knn, mo.knn_max_sq_dist)
    lines, centroid, direction = line_fits_at(map_points, index, mo.edge_eigen_ratio)
    used = used[lines]
    if _terms_in_c(points_world, native):
        line = (np.ascontiguousarray(centroid), np.ascontiguousarray(direction), float(mo.line_half_length))
        return _kernel_terms(_geometry_kernels.map_line_terms, points_world, used, *line, mo=mo)
    a = centroid + mo.line_half_length * direction
    b = centroid - mo.line_half_length * direction
    gradient, dist = line_coefficients(select_rows(points_world, used), a.astype(_F32), b.astype(_F32))
    weight = 1.0 - mo.weight_gain * np.abs(dist.astype(np.float64))
    keep = (weight > mo.min_weight) & np.isfinite(dist) & np.isfinite(gradient).all(axis=1)
    coeff = np.concatenate(
        [select_rows(gradient, keep) * weight[keep, None], (weight[keep] * dist[keep])[:, None]], axis=1
    )
    return used[keep], coeff


def plane_correspondences(
    points_world: np.ndarray, tree: GridNeighbours, map_points: np.ndarray, params: Params, native: bool = True
):
    """Point-to-plane coefficients: (index of used points, coeff (m, 4) = s·normal, s·distance). The terms after
    the plane fits in one C pass when the extension is built (``_geometry_kernels.map_plane_terms``, NumPy's
    operations in its order); ``native=False``: NumPy (the tests compare the two)."""
    mo = params.map_optimization
    if len(points_world) == 0 or tree is None:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4))
    used, index = tree.nearest_within(points_world, mo.knn, mo.knn_max_sq_dist)
    planar, normal, offset = fit_planes_at(map_points, index, mo.plane_max_residual, mo.plane_min_aspect)
    used = used[planar]
    if _terms_in_c(points_world, native):
        plane = (np.ascontiguousarray(normal), np.ascontiguousarray(offset))
        return _kernel_terms(_geometry_kernels.map_plane_terms, points_world, used, *plane, mo=mo)
    p = xyz_columns(select_rows(points_world, used))
    dist = np.einsum('mi,mi->m', p, normal) + offset
    weight = 1.0 - mo.weight_gain * np.abs(dist) / np.sqrt(np.linalg.norm(p, axis=1))
    keep = weight > mo.min_weight
    coeff = np.concatenate(
        [select_rows(normal, keep) * weight[keep, None], (weight[keep] * dist[keep])[:, None]], axis=1
    )
    return used[keep], coeff


def _kernel_terms(kernel, points_world: np.ndarray, used: np.ndarray, *fits, mo) -> tuple[np.ndarray, np.ndarray]:
    """(rows kept, coefficients (m, 4)) of the ``used`` rows of ``points_world`` by a terms kernel of
    ``native/geometry_kernels.c`` (``map_line_terms`` or ``map_plane_terms``) given the fits' arrays and parameters."""
    kept, coeff = np.empty(len(used), dtype=np.int64), np.empty((len(used), 4))
    count = kernel(
        np.ascontiguousarray(points_world),
        points_world.shape[1],
        np.ascontiguousarray(used, dtype=np.int64),
        *fits,
        float(mo.weight_gain),
        float(mo.min_weight),
        kept,
        coeff,
    )
    return kept[:count], coeff[:count]


def _terms_in_c(points_world: np.ndarray, native: bool) -> bool:
    """Whether the C kernels make the correspondences' terms: built (and asked for), float32 (n, >= 3) points."""
    return (
        native
        and hasattr(_geometry_kernels, 'map_plane_terms')  # (None, or an extension built before them)
        and points_world.dtype == _F32
        and points_world.ndim == 2
        and points_world.shape[1] >= 3
    )


@dataclass
class RegistrationCounts:
    """What one scan-to-map registration did."""

    iterations: int = 0
    correspondences: int = 0  # point-to-line and point-to-plane pairs of the last iteration
    degenerate: bool = False  # a direction was projected out (found on the first iteration)
    # Smallest eigenvalue of the first iteration's normal matrix [full-weight correspondences], NaN when too
    # few correspondences were found to register.
    condition: float = float('nan')
    # 6x6 Fisher information of the pose six-vector (rx, ry, rz [rad], tx, ty, tz [m]; world convention, camera
    # axes) from the last iteration's rows: the point-to-line and the point-to-plane residuals each with the
    # variance of their own weighted residuals (:func:`registration_information`); None: not registered.
    information: np.ndarray | None = None


# Smallest residual standard deviation the variance estimate may give [m] (see core.odometry.laser_odometry).
MIN_RESIDUAL_SIGMA = 0.005


def registration_information(rows: np.ndarray, residuals: np.ndarray, corners: int) -> np.ndarray:
    """The information of a scan-to-map registration from its (n, 6) rows and weighted residuals, the first
    ``corners`` point-to-line, the rest point-to-plane, each kind with its own residual variance."""
    out = np.zeros((6, 6))
    for part in (slice(0, corners), slice(corners, None)):
        a, r = rows[part], residuals[part]
        if len(r) > 6:
            out += residual_information(a.T @ a, float(r @ r), len(r), 6, MIN_RESIDUAL_SIGMA)
    return out


def map_trees(
    corner_map: np.ndarray, surf_map: np.ndarray, max_sq_dist: float
) -> tuple[GridNeighbours, GridNeighbours]:
    """The neighbour searches :func:`register_scan_to_map` makes in a corner and a surface map, within
    ``sqrt(max_sq_dist)`` [m] (``map_optimization.knn_max_sq_dist``); each also answers cKDTree's ``query``."""
    return GridNeighbours(corner_map, max_sq_dist), GridNeighbours(surf_map, max_sq_dist)


def register_scan_to_map(
    corner_map: np.ndarray,
    surf_map: np.ndarray,
    corner_ds: np.ndarray,
    surf_ds: np.ndarray,
    initial: np.ndarray,
    params: Params,
    degeneracy: DegeneracyProjection,
    trees: tuple[GridNeighbours, GridNeighbours] | None = None,
) -> tuple[np.ndarray, RegistrationCounts]:
    """Scan-to-map Gauss-Newton from ``initial`` (pose six-vector): (the optimised pose, what it did).

    ``corner_ds`` / ``surf_ds`` are the scan's downsampled features in its sensor frame, the maps are in the
    world (camera axes). ``degeneracy`` is the mapper's, kept across steps as the original does. ``trees``: the
    maps' :func:`map_trees` when the caller keeps them across steps (a map that does not change), else built here.
    """
    mo = params.map_optimization
    counts = RegistrationCounts()
    pose = np.asarray(initial, dtype=float).copy()
    corner_tree, surf_tree = map_trees(corner_map, surf_map, mo.knn_max_sq_dist) if trees is None else trees
    last_rows = None  # (rows, weighted residuals, point-to-line count) of the last iteration that had them
    for iteration in range(mo.max_iterations):
        counts.iterations = iteration + 1
        world = pose6_to_matrix(pose)
        corner_world = transform_points(world, xyz_columns(corner_ds)).astype(_F32)
        surf_world = transform_points(world, xyz_columns(surf_ds)).astype(_F32)
        ci, cc = edge_correspondences(corner_world, corner_tree, corner_map, params)
        si, sc = plane_correspondences(surf_world, surf_tree, surf_map, params)
        points = np.concatenate([select_rows(corner_ds, ci), select_rows(surf_ds, si)])
        coeff = np.concatenate([cc, sc])
        counts.correspondences = len(coeff)
        if len(coeff) < mo.min_correspondences:
            break  # nothing would change in the next iterations
        a = map_jacobian_rows(points, coeff, pose)
        last_rows = a, coeff, len(cc)
        x = degeneracy.step(a, -coeff[:, 3], iteration == 0, mo.degeneracy_threshold)
        counts.degenerate = degeneracy.degenerate
        counts.condition = degeneracy.smallest_eigenvalue
        if not np.isfinite(x).all():
            break
        pose = pose + x
        delta_r = math.degrees(math.sqrt(float(x[0] ** 2 + x[1] ** 2 + x[2] ** 2)))
        delta_t = math.sqrt(float(((x[3:] * 100.0) ** 2).sum()))
        if delta_r < mo.convergence_rotation and delta_t < mo.convergence_translation:
            break
    if last_rows is not None:  # (only the last iteration's information is kept: computed once, here)
        a, coeff, corners = last_rows
        counts.information = registration_information(a, coeff[:, 3].astype(np.float64), corners)
    return pose, counts
