"""The scan-to-scan correspondence search of featureAssociation (docs/original.md §6.2 step 7, quirk 8.1).

It follows the original: nearest neighbour in the last cloud (KD-tree), then the nearest point on the same ring
and on another ring within ±2.5 rings, scanning the ring-ordered last cloud outwards from the nearest
neighbour; the forward scan is bounded by the *current* feature count (quirk 8.1, kept for parity;
``fix_scan_bound`` removes it). Every scan is done for all queries at once, as index windows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.geometry import GridNeighbours
from lego_loam_py.core.indexing import ragged, ranges, select_rows
from lego_loam_py.core.odometry.sweep import ring_of
from lego_loam_py.core.params.types import Params

try:  # the window search in C (native/feature_kernels.c); optional, the NumPy version gives the same
    from lego_loam_py.core import _feature_kernels
except ImportError:
    _feature_kernels = None

__all__ = [
    'SurfCorrespondences',
    'CornerCorrespondences',
    'LastCloud',
    'find_surf_correspondences',
    'find_corner_correspondences',
]

_F32 = np.float32
# [m] sides of the nearest-point search's cells, the smallest whose grid over the cloud has at most CELLS_PER_POINT
# cells a point: a feature's nearest point mostly lies within a metre, but a sparse cloud's wide, empty grid would
# cost more to lay out than its queries save.
NEAREST_CELLS = (1.0, 2.0, 4.0)
CELLS_PER_POINT = 64


@dataclass
class SurfCorrespondences:
    index1: np.ndarray  # nearest point in the last cloud (or -1), per current flat point
    index2: np.ndarray  # nearest on the same ring (or -1)
    index3: np.ndarray  # nearest on a neighbouring ring (or -1)


@dataclass
class CornerCorrespondences:
    index1: np.ndarray
    index2: np.ndarray


# The original scans the last cloud forwards from the nearest point, then backwards, and tells the points it
# meets apart by ring. Each query's window is cut into four segments, each the candidates of one kind met in
# one direction, in increasing index order: other rings met backwards (below the nearest point's ring), its
# own ring backwards, its own ring forwards, other rings forwards (above). Plane points 2 come from the 'same'
# segments, plane points 3 and line points 2 from the 'other' ones.
_BACK_OTHER, _BACK_SAME, _FORWARD_SAME, _FORWARD_OTHER = range(4)
_SAME, _OTHER = [_BACK_SAME, _FORWARD_SAME], [_BACK_OTHER, _FORWARD_OTHER]
_BACKWARD = np.array([True, True, False, False])


def _next_above(rings: np.ndarray, n_rings: int) -> np.ndarray:
    """(n_rings + 3, N + 1): first index >= j whose ring exceeds r, for thresholds r = -1 .. n_rings + 1."""
    n = len(rings)
    thresholds = np.arange(-1, n_rings + 2)
    above = rings[None, :] > thresholds[:, None]
    index = np.where(above, np.arange(n)[None, :], n)
    out = np.full((len(thresholds), n + 1), n, dtype=np.int64)
    out[:, :n] = np.minimum.accumulate(index[:, ::-1], axis=1)[:, ::-1]
    return out


def _prev_below(rings: np.ndarray, n_rings: int) -> np.ndarray:
    """(n_rings + 3, N + 1): last index <= j - 1 ... stored at j: last index < j whose ring is below r
    (or -1), for thresholds r = -1 .. n_rings + 1."""
    n = len(rings)
    thresholds = np.arange(-1, n_rings + 2)
    below = rings[None, :] < thresholds[:, None]
    index = np.where(below, np.arange(n)[None, :], -1)
    out = np.full((len(thresholds), n + 1), -1, dtype=np.int64)
    out[:, 1:] = np.maximum.accumulate(index, axis=1)
    return out


def _nearest_cell(points: np.ndarray) -> float:
    """The side [m] of the nearest-point search's cells for a cloud (see NEAREST_CELLS)."""
    # (column by column: NumPy reduces an (n, 3) array over its first axis some 20 times slower)
    high = np.array([points[:, axis].max() for axis in range(3)])
    low = np.array([points[:, axis].min() for axis in range(3)])
    span = high.astype(np.float64) - low
    for cell in NEAREST_CELLS:
        if np.prod(span / cell + 2.0) <= CELLS_PER_POINT * len(points):
            return cell
    return NEAREST_CELLS[-1]


class LastCloud:
    """A 'last' feature cloud with its nearest-point search and ring look-ups."""

    def __init__(self, points: np.ndarray, n_rings: int):
        self.points = points
        self.n_rings = n_rings
        self.rings = ring_of(points[:, 3])
        # Features are extracted ring by ring, so the rings normally ascend: every window bound is then a
        # binary search and every segment an index range. Other clouds take the general (slower) path.
        self.ring_ordered = bool(np.all(self.rings[1:] >= self.rings[:-1]))
        # (3, n): one contiguous row per coordinate, the window search gathers all three in one call.
        self.xyz_rows = np.ascontiguousarray(points[:, :3].T)
        # The nearest point on a grid (NEAREST_CELLS) (geometry.GridNeighbours), cKDTree's answer bit for bit.
        # Its tree, asked between points at exactly the same distance, has the layout the search had before:
        # sliding-midpoint splits (balanced_tree=False) and leaves of 32 points without the compaction pass, the
        # fastest to build for the few hundred queries each got; the layout picks between equidistant points.
        self.search = (
            GridNeighbours(points, cell=_nearest_cell(points), leafsize=32, balanced_tree=False, compact_nodes=False)
            if len(points)
            else None
        )
        self._tables = None

    @property
    def tree(self):
        """The cloud's cKDTree (built when first asked for), None for an empty cloud."""
        return None if self.search is None else self.search.tree

    def _window_tables(self):
        if self._tables is None:
            low = int(self.rings.min(initial=0))
            high = int(self.rings.max(initial=0))
            offset = -min(low, 0) + 3
            span = max(high, self.n_rings) + offset + 3
            shifted = self.rings + offset
            self._tables = (offset, _next_above(shifted, span), _prev_below(shifted, span))
        return self._tables

    def window(self, closest: np.ndarray, scan: np.ndarray, window: float, forward_bound: int):
        """Forward [closest+1, hi) and backward (lo, closest-1] index windows of the original's scans."""
        n = len(self.points)
        limit = int(math.floor(window))  # int(ring) > scan + 2.5  <=>  ring > scan + floor(2.5)
        if self.ring_ordered:
            hi = np.searchsorted(self.rings, scan + limit, side='right')  # first ring > scan + limit
            lo = np.minimum(np.searchsorted(self.rings, scan - limit, side='left'), closest) - 1
        else:
            offset, next_above, prev_below = self._window_tables()
            up = np.clip(scan + limit + offset + 1, 0, next_above.shape[0] - 1)
            down = np.clip(scan - limit + offset + 1, 0, prev_below.shape[0] - 1)
            hi = next_above[up, np.minimum(closest + 1, n)]
            lo = prev_below[down, closest]  # last index < closest whose ring < scan - 2
        hi = np.minimum(hi, forward_bound)
        return np.maximum(hi, closest + 1), lo

    def segments(self, closest: np.ndarray, scan: np.ndarray, hi: np.ndarray, lo: np.ndarray, kinds: list[int]):
        """The window segments (see ``_BACK_OTHER``) of every query: (positions back to back, (n, 4) lengths);
        segments not in ``kinds`` are left empty."""
        n_queries = len(closest)
        if self.ring_ordered:
            ring_start = np.searchsorted(self.rings, scan, side='left')
            ring_end = np.searchsorted(self.rings, scan, side='right')
            backward_cut = np.clip(ring_start, lo + 1, closest)
            forward_cut = np.clip(ring_end, closest + 1, hi)
            starts = np.empty((n_queries, 4), dtype=np.int64)
            starts[:, _BACK_OTHER], starts[:, _BACK_SAME] = lo + 1, backward_cut
            starts[:, _FORWARD_SAME], starts[:, _FORWARD_OTHER] = closest + 1, forward_cut
            stops = np.empty((n_queries, 4), dtype=np.int64)
            stops[:, _BACK_OTHER], stops[:, _BACK_SAME] = backward_cut, closest
            stops[:, _FORWARD_SAME], stops[:, _FORWARD_OTHER] = forward_cut, hi
            lengths = np.zeros((n_queries, 4), dtype=np.int64)
            lengths[:, kinds] = stops[:, kinds] - starts[:, kinds]
            return ranges(starts.reshape(-1), lengths.reshape(-1)), lengths
        # General path: class every window point as the original's loops do, then group by query and segment.
        forward_owner, forward = ragged(closest + 1, hi)
        backward_owner, backward = ragged(lo + 1, closest)
        forward_kind = np.where(self.rings[forward] <= scan[forward_owner], _FORWARD_SAME, _FORWARD_OTHER)
        backward_kind = np.where(self.rings[backward] >= scan[backward_owner], _BACK_SAME, _BACK_OTHER)
        key = np.concatenate((backward_owner * 4 + backward_kind, forward_owner * 4 + forward_kind))
        position = np.concatenate((backward, forward))
        wanted = np.isin(key % 4, kinds)
        key, position = key[wanted], position[wanted]
        position = position[np.argsort(key, kind='stable')]
        return position, np.bincount(key, minlength=4 * n_queries).reshape(n_queries, 4)


def _nearest_in_segments(
    query: np.ndarray, last: LastCloud, position: np.ndarray, lengths: np.ndarray, limit: float, native: bool = True
):
    """Per query and segment, the candidate the original's scan keeps: the smallest squared distance below
    ``limit`` (its float32 expression), the first index met on ties (the highest in a backward segment).

    Returns (n, 4) indices (-1: none) and squared distances (inf: none). In C when the extension is built
    (one pass, no (3, m) temporaries); ``native=False`` runs the NumPy version (the tests compare the two).
    """
    if native and _feature_kernels is not None and last.xyz_rows.dtype == _F32 and query.dtype == _F32:
        # (Both float32, as the features are: the NumPy expression is then float32 too.)
        index = np.empty(lengths.size, dtype=np.int64)
        best = np.empty(lengths.size, dtype=_F32)
        _feature_kernels.nearest_in_segments(
            last.xyz_rows,
            np.ascontiguousarray(query[:, :3]),
            np.ascontiguousarray(position, dtype=np.int64),
            np.ascontiguousarray(lengths, dtype=np.int64),
            limit,
            index,
            best,
        )
        return index.reshape(-1, 4), best.reshape(-1, 4)
    flat_lengths = lengths.reshape(-1)
    index = np.full(len(flat_lengths), -1, dtype=np.int64)
    best = np.full(len(flat_lengths), np.inf, dtype=_F32)
    if len(position):
        per_query = lengths.sum(axis=1)
        # (3, m) coordinate differences in one call each; summed x + y + z as the original's float expression.
        delta = last.xyz_rows.take(position, axis=1) - np.repeat(query[:, :3].T, per_query, axis=1)
        delta *= delta
        dist = delta[0] + delta[1]
        dist += delta[2]
        ends = np.cumsum(flat_lengths)
        filled = np.flatnonzero(flat_lengths)
        best[filled] = np.fmin.reduceat(dist, (ends - flat_lengths)[filled])  # fmin: NaN never wins
        at_minimum = np.flatnonzero(dist == np.repeat(best, flat_lengths))
        segment = np.searchsorted(ends, at_minimum, side='right')
        new_segment = segment[1:] != segment[:-1]
        keep = np.where(
            _BACKWARD[segment % 4], np.concatenate((new_segment, [True])), np.concatenate(([True], new_segment))
        )
        index[segment[keep]] = position[at_minimum[keep]]
    outside = ~(best < _F32(limit))
    index[outside] = -1
    best[outside] = np.inf
    return index.reshape(-1, 4), best.reshape(-1, 4)


def _pick(index: np.ndarray, best: np.ndarray, backward: int, forward: int) -> np.ndarray:
    """The original's choice between its forward and backward scans: backward only when strictly closer."""
    return np.where(best[:, backward] < best[:, forward], index[:, backward], index[:, forward])


def _window_search(
    points_start: np.ndarray, last: LastCloud, params: Params, forward_bound: int, kinds: list[int], native: bool = True
):
    """The search both correspondence kinds make: the queries whose nearest point in the last cloud lies within the
    gate (indices ``q``), that point, and per query the nearest point of each window segment of ``kinds`` with its
    squared distance (:func:`_nearest_in_segments`). A ring-ordered cloud is searched in C in one pass when the
    extension is built (the index arrays of the windows are never built: per-call costs dominate the small scans);
    ``native=False`` runs the NumPy version (the tests compare the two)."""
    fa = params.feature_association
    limit = fa.nearest_feature_search_sq_dist
    q, closest = last.search.nearest_one(points_start, limit)
    if (
        native
        and hasattr(_feature_kernels, 'nearest_in_windows')  # (None, or an extension built before it: NumPy)
        and last.ring_ordered
        and last.xyz_rows.dtype == _F32
        and points_start.dtype == _F32
    ):
        index = np.empty((len(q), 4), dtype=np.int64)
        best = np.empty((len(q), 4), dtype=_F32)
        _feature_kernels.nearest_in_windows(
            last.xyz_rows,
            last.rings,
            np.ascontiguousarray(select_rows(points_start, q)[:, :3]),
            np.ascontiguousarray(closest, dtype=np.int64),
            int(math.floor(fa.ring_search_window)),
            int(forward_bound),
            sum(1 << kind for kind in kinds),
            limit,
            index,
            best,
        )
        return q, closest, index, best
    scan = last.rings[closest]
    hi, lo = last.window(closest, scan, fa.ring_search_window, forward_bound)
    position, lengths = last.segments(closest, scan, hi, lo, kinds)
    index, best = _nearest_in_segments(points_start[q], last, position, lengths, limit, native)
    return q, closest, index, best


def find_surf_correspondences(
    points_start: np.ndarray, last: LastCloud, params: Params, forward_bound: int
) -> SurfCorrespondences:
    """The original's plane correspondences for flat points already mapped to the sweep start."""
    n = len(points_start)
    index1 = np.full(n, -1, dtype=np.int64)
    index2, index3 = index1.copy(), index1.copy()
    if n == 0 or last.search is None:
        return SurfCorrespondences(index1, index2, index3)
    q, closest, index, best = _window_search(points_start, last, params, forward_bound, _SAME + _OTHER)
    index1[q] = closest
    index2[q] = _pick(index, best, _BACK_SAME, _FORWARD_SAME)
    index3[q] = _pick(index, best, _BACK_OTHER, _FORWARD_OTHER)
    return SurfCorrespondences(index1, index2, index3)


def find_corner_correspondences(
    points_start: np.ndarray, last: LastCloud, params: Params, forward_bound: int
) -> CornerCorrespondences:
    """The original's line correspondences for sharp points already mapped to the sweep start."""
    n = len(points_start)
    index1 = np.full(n, -1, dtype=np.int64)
    index2 = index1.copy()
    if n == 0 or last.search is None:
        return CornerCorrespondences(index1, index2)
    q, closest, index, best = _window_search(points_start, last, params, forward_bound, _OTHER)
    index1[q] = closest
    index2[q] = _pick(index, best, _BACK_OTHER, _FORWARD_OTHER)
    return CornerCorrespondences(index1, index2)
