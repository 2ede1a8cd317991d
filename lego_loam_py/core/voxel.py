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

try:  # the filter in one pass (native/voxel_kernels.c); optional: the NumPy code below gives the same values
    from lego_loam_py.core import _voxel_kernels
except ImportError:
    _voxel_kernels = None

__all__ = ['VoxelAccumulator', 'voxel_downsample', 'voxel_downsample_groups', 'voxel_indices']


def voxel_indices(xyz: np.ndarray, leaf_size: float) -> np.ndarray:
    """PCL's flattened voxel index (int64) of every point of a finite (N, 3) float32 array."""
    inverse = np.float32(1.0) / np.float32(leaf_size)
    scaled = np.floor(xyz.astype(np.float32, copy=False) * inverse)
    min_b = np.floor(xyz.min(axis=0) * inverse)
    max_b = np.floor(xyz.max(axis=0) * inverse)
    div = (max_b - min_b).astype(np.int64) + 1
    ijk = (scaled - min_b.astype(np.float32)).astype(np.int64)
    return ijk[:, 0] + ijk[:, 1] * div[0] + ijk[:, 2] * div[0] * div[1]


def voxel_downsample(points: np.ndarray, leaf_size: float, return_counts: bool = False, native: bool = True):
    """Voxel centroids of (N, k) points whose first three columns are x, y, z [m].

    Every column is averaged per voxel (float32 accumulation, like PCL). Returns an (M, k) float32 array
    ordered by voxel index, and with ``return_counts`` also the number of points in each voxel. In one pass in C
    where the extension is built (the same values; ``native=False``: the NumPy version, which the tests compare).
    """
    if leaf_size <= 0:
        raise ValueError(f'voxel leaf size must be positive, got {leaf_size}')
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f'expected (N, k>=3) points, got shape {points.shape}')
    if not np.isfinite(points[:, :3]).all():  # (one whole-array test first: a test per row costs 20 ns a row)
        points = points[np.isfinite(points[:, :3]).all(axis=1)]
    if len(points) == 0:
        empty = np.zeros((0, points.shape[1]), dtype=np.float32)
        return (empty, np.zeros(0, dtype=np.int64)) if return_counts else empty
    filtered = _voxel_groups(points, np.zeros(1, dtype=np.int64), leaf_size) if native else None
    if filtered is not None:
        return filtered if return_counts else filtered[0]
    index = voxel_indices(points[:, :3], leaf_size)
    order = np.argsort(index, kind='stable')
    sorted_index = index[order]
    starts = np.flatnonzero(np.concatenate(([True], sorted_index[1:] != sorted_index[:-1])))
    counts = np.diff(np.append(starts, len(sorted_index)))
    sums = np.add.reduceat(points[order], starts, axis=0)
    centroids = (sums / counts[:, None].astype(np.float32)).astype(np.float32)
    return (centroids, counts) if return_counts else centroids


def voxel_downsample_groups(
    points: np.ndarray, groups: np.ndarray, leaf_size: float, native: bool = True
) -> np.ndarray:
    """``voxel_downsample`` of each group of points on its own grid (anchored at the group's bounding box),
    concatenated in increasing group order: what a filter per ring gives, in one sort instead of one per ring.

    ``points`` (N, k) with x, y, z first; ``groups`` (N,) non-negative integers. ``native=False``: the NumPy
    version even where the C kernel is built (the tests compare the two).
    """
    if leaf_size <= 0:
        raise ValueError(f'voxel leaf size must be positive, got {leaf_size}')
    points = np.asarray(points, dtype=np.float32)
    groups = np.asarray(groups, dtype=np.int64)
    if not np.isfinite(points[:, :3]).all():  # one whole-array test first: non-finite points are rare
        finite = np.isfinite(points[:, :3]).all(axis=1)
        points, groups = points[finite], groups[finite]
    if len(points) == 0:
        return np.zeros((0, points.shape[1]), dtype=np.float32)
    if (groups[1:] < groups[:-1]).any():  # the features come ring by ring: usually in group order already
        by_group = np.argsort(groups, kind='stable')
        points, groups = points[by_group], groups[by_group]
    group_starts = np.flatnonzero(np.concatenate(([True], groups[1:] != groups[:-1])))
    filtered = _voxel_groups(points, group_starts, leaf_size) if native else None
    if filtered is not None:
        return filtered[0]
    group_sizes = np.diff(np.append(group_starts, len(groups)))  # per-group values reach the points by repeat
    inverse = np.float32(1.0) / np.float32(leaf_size)
    # floor(min(p) / leaf) == min(floor(p / leaf)): the product and floor are monotonic in float32 too.
    scaled = np.floor(points[:, :3] * inverse)
    min_b = np.minimum.reduceat(scaled, group_starts, axis=0)
    max_b = np.maximum.reduceat(scaled, group_starts, axis=0)
    div = (max_b - min_b).astype(np.int64) + 1
    ijk = (scaled - np.repeat(min_b, group_sizes, axis=0)).astype(np.int64)
    local = (
        ijk[:, 0]
        + ijk[:, 1] * np.repeat(div[:, 0], group_sizes)
        + ijk[:, 2] * np.repeat(div[:, 0] * div[:, 1], group_sizes)
    )
    span = int((div[:, 0] * div[:, 1] * div[:, 2]).max())
    index = np.repeat(np.arange(len(group_starts)) * span, group_sizes) + local
    order = np.argsort(index, kind='stable')
    sorted_index = index[order]
    starts = np.flatnonzero(np.concatenate(([True], sorted_index[1:] != sorted_index[:-1])))
    counts = np.diff(np.append(starts, len(sorted_index)))
    sums = np.add.reduceat(points[order], starts, axis=0)
    return (sums / counts[:, None].astype(np.float32)).astype(np.float32)


def _voxel_groups(
    points: np.ndarray, group_starts: np.ndarray, leaf_size: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """(centroids, counts) of finite float32 points whose groups start at ``group_starts`` (int64, from 0), by
    the C kernel: voxel_downsample_groups' values and order (native/voxel_kernels.c); None without the extension,
    or for a grid too large for its sort keys (the NumPy code then filters)."""
    if _voxel_kernels is None:
        return None
    points = np.ascontiguousarray(points, dtype=np.float32)
    out = np.empty_like(points)
    counts = np.empty(len(points), dtype=np.int64)
    inverse = np.float32(1.0) / np.float32(leaf_size)
    m = _voxel_kernels.voxel_groups(
        points, points.shape[1], np.ascontiguousarray(group_starts, dtype=np.int64), float(inverse), out, counts
    )
    return (out[:m].copy(), counts[:m].copy()) if m >= 0 else None


_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def _global_voxel_keys(xyz: np.ndarray, leaf_size: float) -> np.ndarray:
    """Key of each point's cell of the global grid ``floor(p * (1/leaf))`` (float32, as PCL), packed so that
    key order is PCL's output order (z, then y, then x): PCL anchors its grid at ``floor(min / leaf)``, an
    integer cell, so its cells are the global grid's and only their flattened numbering is relative."""
    inverse = np.float32(1.0) / np.float32(leaf_size)
    ijk = np.floor(xyz.astype(np.float32, copy=False) * inverse).astype(np.int64) + _KEY_OFFSET
    if len(ijk) and (ijk.min() < 0 or ijk.max() >= (1 << _KEY_BITS)):
        raise ValueError(f'points beyond +-{_KEY_OFFSET * leaf_size:.0f} m cannot be keyed on a {leaf_size} m grid')
    return (ijk[:, 2] << (2 * _KEY_BITS)) | (ijk[:, 1] << _KEY_BITS) | ijk[:, 0]


class VoxelAccumulator:
    """``voxel_downsample`` of a union of clouds that changes a few clouds at a time.

    Each cloud is reduced once to per-voxel sums (float64) and counts; the union keeps the summed voxels in
    key order, so adding or removing a cloud costs a merge of its voxels instead of a new filter of every
    point. :meth:`centroids` equals ``voxel_downsample(np.concatenate(clouds), leaf_size)`` up to the float32
    rounding of the means (the sums here are float64, PCL's float32) and is in the same order.
    """

    def __init__(self, leaf_size: float, columns: int = 4):
        if leaf_size <= 0:
            raise ValueError(f'voxel leaf size must be positive, got {leaf_size}')
        self.leaf_size = float(leaf_size)
        self.columns = int(columns)
        self._parts: dict[object, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._keys = np.zeros(0, dtype=np.int64)
        self._sums = np.zeros((0, self.columns))
        self._counts = np.zeros(0, dtype=np.int64)
        self._centroids: np.ndarray | None = None

    def __contains__(self, cloud_id) -> bool:
        return cloud_id in self._parts

    def __len__(self) -> int:
        return len(self._keys)

    def ids(self) -> set:
        return set(self._parts)

    def _reduce(self, points: np.ndarray):
        points = np.asarray(points, dtype=np.float32)
        if points.ndim != 2 or points.shape[1] != self.columns:
            raise ValueError(f'expected (N, {self.columns}) points, got shape {points.shape}')
        if not np.isfinite(points[:, :3]).all():
            points = points[np.isfinite(points[:, :3]).all(axis=1)]
        keys = _global_voxel_keys(points[:, :3], self.leaf_size)
        return _group_sums(keys, points.astype(np.float64), np.ones(len(keys), dtype=np.int64))

    def add(self, cloud_id, points: np.ndarray) -> None:
        """Add the (N, columns) cloud ``points`` (x, y, z first) under ``cloud_id`` (replacing an older one)."""
        if cloud_id in self._parts:
            self.remove(cloud_id)
        part = self._reduce(points)
        self._parts[cloud_id] = part
        keys, sums, counts = part
        if len(keys) == 0:
            return
        position = np.searchsorted(self._keys, keys)
        found = position < len(self._keys)
        found[found] = self._keys[position[found]] == keys[found]
        self._sums[position[found]] += sums[found]
        self._counts[position[found]] += counts[found]
        new = ~found
        if new.any():
            self._keys = np.insert(self._keys, position[new], keys[new])
            self._sums = np.insert(self._sums, position[new], sums[new], axis=0)
            self._counts = np.insert(self._counts, position[new], counts[new])
        self._centroids = None

    def remove(self, cloud_id) -> None:
        """Take the cloud added under ``cloud_id`` out of the union (nothing if it is not there)."""
        part = self._parts.pop(cloud_id, None)
        if part is None or len(part[0]) == 0:
            return
        keys, sums, counts = part
        position = np.searchsorted(self._keys, keys)
        self._sums[position] -= sums
        self._counts[position] -= counts
        empty = self._counts[position] == 0
        if empty.any():
            keep = np.ones(len(self._keys), dtype=bool)
            keep[position[empty]] = False
            self._keys, self._sums, self._counts = self._keys[keep], self._sums[keep], self._counts[keep]
        self._centroids = None

    def rebuild(self, clouds: dict) -> None:
        """Replace the union by ``clouds`` ({cloud_id: points}) in one grouping (cheaper than many adds)."""
        self._parts = {cloud_id: self._reduce(points) for cloud_id, points in clouds.items()}
        if self._parts:
            keys, sums, counts = (np.concatenate(column) for column in zip(*self._parts.values()))
            self._keys, self._sums, self._counts = _group_sums(keys, sums, counts)
        else:
            self.clear()
        self._centroids = None

    def clear(self) -> None:
        self._parts.clear()
        self._keys = np.zeros(0, dtype=np.int64)
        self._sums = np.zeros((0, self.columns))
        self._counts = np.zeros(0, dtype=np.int64)
        self._centroids = None

    def centroids(self) -> np.ndarray:
        """(M, columns) float32 voxel means of the union, in PCL's output order."""
        if self._centroids is None:
            self._centroids = (self._sums / self._counts[:, None]).astype(np.float32)
        return self._centroids


def _group_sums(keys: np.ndarray, sums: np.ndarray, counts: np.ndarray):
    """(unique sorted keys, summed rows, summed counts) of rows grouped by key."""
    if len(keys) == 0:
        return keys.astype(np.int64), sums.reshape(0, sums.shape[1]).astype(np.float64), counts.astype(np.int64)
    order = np.argsort(keys)
    keys = keys[order]
    starts = np.flatnonzero(np.concatenate(([True], keys[1:] != keys[:-1])))
    return keys[starts], np.add.reduceat(sums[order], starts, axis=0), np.add.reduceat(counts[order], starts)
