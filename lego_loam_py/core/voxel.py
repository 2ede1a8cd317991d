"""Voxel-grid downsampling with PCL's ``VoxelGrid`` semantics (the one place the project voxel-filters).

PCL's filter, which the original uses everywhere (less-flat features, mapping clouds, key poses):

* the grid is anchored at ``floor(min(p) / leaf)`` of the input's bounding box;
* a point's voxel is ``floor(p * (1/leaf)) - min_b`` per axis (float32 arithmetic), flattened x-fastest;
* one output point per occupied voxel, in increasing voxel index: the mean of every field of its points
  (x, y, z and, e.g., intensity; PCL averages all fields when ``downsample_all_data`` is on, its default).

Points with a non-finite coordinate are ignored, as PCL does. Fully vectorised: a sort and segment sums.
"""
from __future__ import annotations

import numpy as np

__all__ = ['voxel_downsample', 'voxel_downsample_groups', 'voxel_indices']


def voxel_indices(xyz: np.ndarray, leaf_size: float) -> np.ndarray:
    """PCL's flattened voxel index (int64) of every point of a finite (N, 3) float32 array."""
    inverse = np.float32(1.0) / np.float32(leaf_size)
    scaled = np.floor(xyz.astype(np.float32, copy=False) * inverse)
    min_b = np.floor(xyz.min(axis=0) * inverse)
    max_b = np.floor(xyz.max(axis=0) * inverse)
    div = (max_b - min_b).astype(np.int64) + 1
    ijk = (scaled - min_b.astype(np.float32)).astype(np.int64)
    return ijk[:, 0] + ijk[:, 1] * div[0] + ijk[:, 2] * div[0] * div[1]


def voxel_downsample(points: np.ndarray, leaf_size: float, return_counts: bool = False):
    """Voxel centroids of (N, k) points whose first three columns are x, y, z [m].

    Every column is averaged per voxel (float32 accumulation, like PCL). Returns an (M, k) float32 array
    ordered by voxel index, and with ``return_counts`` also the number of points in each voxel.
    """
    if leaf_size <= 0:
        raise ValueError(f'voxel leaf size must be positive, got {leaf_size}')
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f'expected (N, k>=3) points, got shape {points.shape}')
    finite = np.isfinite(points[:, :3]).all(axis=1)
    if not finite.all():
        points = points[finite]
    if len(points) == 0:
        empty = np.zeros((0, points.shape[1]), dtype=np.float32)
        return (empty, np.zeros(0, dtype=np.int64)) if return_counts else empty
    index = voxel_indices(points[:, :3], leaf_size)
    order = np.argsort(index, kind='stable')
    sorted_index = index[order]
    starts = np.flatnonzero(np.concatenate(([True], sorted_index[1:] != sorted_index[:-1])))
    counts = np.diff(np.append(starts, len(sorted_index)))
    sums = np.add.reduceat(points[order], starts, axis=0)
    centroids = (sums / counts[:, None].astype(np.float32)).astype(np.float32)
    return (centroids, counts) if return_counts else centroids


def voxel_downsample_groups(points: np.ndarray, groups: np.ndarray, leaf_size: float) -> np.ndarray:
    """``voxel_downsample`` of each group of points on its own grid (anchored at the group's bounding box),
    concatenated in increasing group order: what a filter per ring gives, in one sort instead of one per ring.

    ``points`` (N, k) with x, y, z first; ``groups`` (N,) non-negative integers.
    """
    if leaf_size <= 0:
        raise ValueError(f'voxel leaf size must be positive, got {leaf_size}')
    points = np.asarray(points, dtype=np.float32)
    groups = np.asarray(groups, dtype=np.int64)
    finite = np.isfinite(points[:, :3]).all(axis=1)
    if not finite.all():
        points, groups = points[finite], groups[finite]
    if len(points) == 0:
        return np.zeros((0, points.shape[1]), dtype=np.float32)
    by_group = np.argsort(groups, kind='stable')
    points, groups = points[by_group], groups[by_group]
    group_starts = np.flatnonzero(np.concatenate(([True], groups[1:] != groups[:-1])))
    group_of = np.cumsum(np.concatenate(([False], groups[1:] != groups[:-1])))   # 0..G-1 per point
    inverse = np.float32(1.0) / np.float32(leaf_size)
    # floor(min(p) / leaf) == min(floor(p / leaf)): the product and floor are monotonic in float32 too.
    scaled = np.floor(points[:, :3] * inverse)
    min_b = np.minimum.reduceat(scaled, group_starts, axis=0)
    max_b = np.maximum.reduceat(scaled, group_starts, axis=0)
    div = (max_b - min_b).astype(np.int64) + 1
    ijk = (scaled - min_b[group_of]).astype(np.int64)
    local = ijk[:, 0] + ijk[:, 1] * div[group_of, 0] + ijk[:, 2] * (div[:, 0] * div[:, 1])[group_of]
    span = int((div[:, 0] * div[:, 1] * div[:, 2]).max())
    index = group_of * span + local
    order = np.argsort(index, kind='stable')
    sorted_index = index[order]
    starts = np.flatnonzero(np.concatenate(([True], sorted_index[1:] != sorted_index[:-1])))
    counts = np.diff(np.append(starts, len(sorted_index)))
    sums = np.add.reduceat(points[order], starts, axis=0)
    return (sums / counts[:, None].astype(np.float32)).astype(np.float32)
