"""Feature extraction of featureAssociation (docs/original.md §6.2 steps 2-4, quirks 8.2 and 8.7).

Input: the segmented cloud of one scan in LOAM camera axes (after deskewing), with the CloudInfo arrays
(ground flags, columns, ranges, ring index bounds). Output: sharp (edge), less-sharp, flat (ground plane)
and less-flat features, exactly as the original selects them:

* curvature ``c_i = (sum_{k=+-1..+-5} r_{i+k} - 10 r_i)^2`` over the 1-D segmented array (float32, as the C++);
* occluded and parallel-beam points are excluded from selection;
* each ring is cut into ``sections_total`` sub-regions; per region the ``edge_feature_num`` sharpest
  non-ground points are sharp, up to ``less_edge_feature_num`` are less sharp, and the
  ``surf_feature_num`` flattest ground points are flat; every pick suppresses its +-5 neighbours unless the
  column jumps by more than 10;
* less-flat = every non-edge point of the region, voxel-filtered per ring (0.2 m).

Two quirks of the original are kept because they change which points are picked: ``std::sort`` over
``[sp, ep)`` leaves element ``ep`` unsorted (it is visited first for edges and last for flats), and the
smoothness entry at position 4 is never written, so the first region of ring 0 holds a phantom candidate
for point 0 with curvature 0 whose neighbour marks persist across scans.

The per-region selection is a short loop over the candidates that pass the vectorised thresholds (it stops
after 20 edges / 4 flats), never over all points.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lego_loam_py.core.indexing import ragged, select_rows
from lego_loam_py.core.params.types import Params
from lego_loam_py.core.projection.cloud_info import CloudInfo
from lego_loam_py.core.voxel import voxel_downsample_groups

try:  # the greedy selection in C (native/feature_kernels.c); optional, as the Python loop gives the same
    from lego_loam_py.core import _feature_kernels
except ImportError:
    _feature_kernels = None

__all__ = ['ScanFeatures', 'FeatureExtractor', 'smoothness', 'occluded_mask']

_F32 = np.float32


@dataclass
class ScanFeatures:
    """Features of one scan; clouds are float32 (k, 4) = x, y, z (camera axes), intensity (ring + 0.1 s)."""

    sharp: np.ndarray
    less_sharp: np.ndarray
    flat: np.ndarray
    less_flat: np.ndarray
    sharp_index: np.ndarray  # indices into the scan's points
    less_sharp_index: np.ndarray
    flat_index: np.ndarray
    # Selects the wall points (below) when first asked for: only a stage short of matches needs them.
    select_walls: Callable[[], np.ndarray] | None = field(default=None, repr=False, compare=False)
    # The scan's points (n, 4), which the wall indices refer to (read, never written).
    scan_points: np.ndarray | None = field(default=None, repr=False, compare=False)

    @functools.cached_property
    def wall_index(self) -> np.ndarray:
        """Indices of the flat non-ground points (walls, ceilings, facades) that back up a sweep-start odometry
        stage short of matches; empty when ``wall_feature_num`` is 0 (the original has none)."""
        return np.zeros(0, np.int64) if self.select_walls is None else self.select_walls()

    @functools.cached_property
    def wall(self) -> np.ndarray:
        """The wall points (k, 4) float32, as the other clouds."""
        return self.scan_points[self.wall_index] if self.select_walls is not None else np.zeros((0, 4), _F32)


def smoothness(ranges: np.ndarray, half_window: int = 5) -> np.ndarray:
    """Curvature of every point; 0 for the first and last ``half_window`` points (never computed there).

    Summed left to right in float32 exactly as the original's expression
    ``r[i-5] + ... + r[i-1] - r[i]*10 + r[i+1] + ... + r[i+5]``.
    """
    r = np.asarray(ranges, dtype=_F32)
    n, w = len(r), half_window
    out = np.zeros(n, dtype=_F32)
    if n <= 2 * w:
        return out
    m = n - 2 * w
    acc = r[0:m].copy()
    for k in range(1, w):
        acc += r[k : k + m]
    acc -= r[w : w + m] * _F32(2 * w)
    for k in range(w + 1, 2 * w + 1):
        acc += r[k : k + m]
    out[w : n - w] = acc * acc
    return out


def occluded_mask(ranges: np.ndarray, columns: np.ndarray, params: Params, native: bool = True) -> np.ndarray:
    """Points excluded from selection: the near side of occlusion boundaries and parallel beams. In C when the
    extension is built (one pass instead of some thirty NumPy calls over the scan); ``native=False`` runs the NumPy
    version (the tests compare the two)."""
    fa = params.feature_association
    r = np.asarray(ranges, dtype=_F32)
    n = len(r)
    picked = np.zeros(n, dtype=bool)
    w = fa.smoothness_half_window
    if native and hasattr(_feature_kernels, 'occluded') and w >= 0:
        _feature_kernels.occluded(
            np.ascontiguousarray(r),
            np.ascontiguousarray(columns, dtype=np.int64),
            int(w),
            float(fa.occlusion_column_gap),
            float(fa.occlusion_depth_jump),
            float(fa.parallel_beam_ratio),
            picked,
        )
        return picked
    i = np.arange(w, n - w - 1)
    if len(i) == 0:
        return picked
    # Points i and i + 1 as slices (i runs over one contiguous range); i - 1 indexed, it wraps when w = 0.
    here, after = slice(w, n - w - 1), slice(w + 1, n - w)
    col = columns.astype(np.int64)
    near = np.abs(col[after] - col[here]) < fa.occlusion_column_gap
    d1, d2 = r[here], r[after]
    jump = _F32(fa.occlusion_depth_jump)
    farther_behind = near & (d1.astype(np.float64) - d2 > jump)  # i is the far side: mark i-5..i
    farther_ahead = near & ~farther_behind & (d2.astype(np.float64) - d1 > jump)  # mark i+1..i+6
    behind, ahead = i[farther_behind], i[farther_ahead] + 1
    for offset in range(w + 1):
        picked[behind - offset] = True
        picked[ahead + offset] = True
    diff1 = np.abs(r[i - 1] - d1)
    diff2 = np.abs(d2 - d1)
    ratio = fa.parallel_beam_ratio * d1.astype(np.float64)
    picked[i[(diff1 > ratio) & (diff2 > ratio)]] = True
    return picked


class FeatureExtractor:
    """Selects features scan by scan; keeps the few array entries the original never resets."""

    def __init__(self, params: Params):
        self.params = params
        w = params.feature_association.smoothness_half_window
        self._stale_picked = np.zeros(w, dtype=bool)  # picked flags of points 0..w-1 carry over

    def extract(self, points: np.ndarray, info: CloudInfo) -> ScanFeatures:
        """Features of a scan: ``points`` (n, 4) float32 in camera axes, ``info`` its CloudInfo."""
        fa = self.params.feature_association
        n = len(points)
        w = fa.smoothness_half_window
        ranges = info.segmented_cloud_range[:n]
        columns = info.segmented_cloud_col_ind[:n].astype(np.int64)
        ground = info.segmented_cloud_ground_flag[:n].astype(bool)
        curvature = smoothness(ranges, w)
        picked = occluded_mask(ranges, columns, self.params)
        head = min(w, n)
        picked[:head] |= self._stale_picked[:head]
        # Points picked already (occluded, parallel beams, stale) are never selected: left out of the candidates.
        is_edge_candidate = (curvature > _F32(fa.edge_threshold)) & ~ground & ~picked
        is_flat_candidate = (curvature < _F32(fa.surf_threshold)) & ground & ~picked

        # Every sub-region [sp, ep] of every ring at once, ring by ring (C++ integer division truncates toward
        # zero); empty ones (sp >= ep) are skipped.
        sections = fa.sections_total
        j = np.arange(sections)
        s = info.start_ring_index.astype(np.int64)[:, None]
        e = info.end_ring_index.astype(np.int64)[:, None]
        sp = np.trunc((s * (sections - j) + e * j) / sections).astype(np.int64).reshape(-1)
        ep = (np.trunc((s * (sections - 1 - j) + e * (j + 1)) / sections).astype(np.int64) - 1).reshape(-1)
        region_ring = np.repeat(np.arange(len(s)), sections)
        valid = sp < ep
        sp, ep, region_ring = sp[valid], ep[valid], region_ring[valid]
        regions = len(sp)

        # Per region, the candidates of [sp, ep) sorted by curvature (stable): edges from the unsorted element ep, then
        # the largest curvature down; flats from the smallest up, ep last. Positions below w were never written: a
        # phantom entry for point 0, whose curvature was never computed either (0), so it is sorted as point 0.
        entry_region, entry = ragged(sp, ep)
        entry[entry < w] = 0
        edge_list, edge_bounds = _visiting_order(
            *_by_curvature(entry_region, entry, curvature, is_edge_candidate), ep, is_edge_candidate, True
        )
        flat_list, flat_bounds = _visiting_order(
            *_by_curvature(entry_region, entry, curvature, is_flat_candidate), ep, is_flat_candidate, False
        )

        # The greedy selection is sequential (each pick suppresses its neighbours for the later ones, up to a
        # column jump): in C when the extension is built.
        taken = bytearray(picked.tobytes())
        sharp_index, less_sharp_index, flat_index, less_sharp_region = greedy_selection(
            edge_list,
            edge_bounds,
            flat_list,
            flat_bounds,
            _column_jumps(columns, fa.suppress_column_jump),
            fa.suppress_half_window,
            taken,
            regions,
            fa.edge_feature_num,
            fa.less_edge_feature_num,
            fa.surf_feature_num,
        )
        self._stale_picked[:head] = np.frombuffer(taken, dtype=bool)[:head]

        # Less flat: the points of each region [sp, ep] not picked as edges by the end of that region (only the
        # phantom point 0 can be picked from another region), voxel-filtered ring by ring (one grouped filter
        # gives the same points in the same order).
        edge_region = np.full(n, regions, dtype=np.int64)
        edge_region[less_sharp_index] = less_sharp_region
        region_of, position = ragged(sp, ep + 1)
        kept = edge_region[position] > region_of
        if kept.any():
            less_flat = voxel_downsample_groups(
                select_rows(points, position[kept]), region_ring[region_of[kept]], fa.less_flat_leaf_size
            )
        else:
            less_flat = np.zeros((0, 4), _F32)
        # Wall points cost a pass over every region: selected only if a stage asks for them (corridors).
        select_walls = functools.partial(_wall_points, entry_region, entry, curvature, ground, taken, fa)
        return ScanFeatures(
            sharp=select_rows(points, sharp_index),
            less_sharp=select_rows(points, less_sharp_index),
            flat=select_rows(points, flat_index),
            less_flat=less_flat,
            sharp_index=sharp_index,
            less_sharp_index=less_sharp_index,
            flat_index=flat_index,
            select_walls=select_walls,
            scan_points=points,
        )


def _by_curvature(region_of: np.ndarray, position: np.ndarray, curvature: np.ndarray, usable: np.ndarray):
    """(positions, regions) of the entries (``region_of``, ``position``: by region, ascending) whose point is
    ``usable``, sorted by region, then curvature, ties in entry order: what a stable sort of all entries keeps of
    them, in one sort of the few. The curvature is a square, and the bits of a non-negative float32 order as the
    values do."""
    chosen = usable[position]
    region, position = region_of[chosen], position[chosen]
    order = np.argsort((region << 32) | curvature[position].view(np.uint32).astype(np.int64), kind='stable')
    return position[order], region[order]


def _visiting_order(position: np.ndarray, region: np.ndarray, ep: np.ndarray, usable: np.ndarray, edges: bool):
    """The candidates in the order the original visits them and, per region, where they start and end in that
    list (region r: [bounds[r], bounds[r + 1])). ``position``, ``region``: the region's sorted candidates
    (:func:`_by_curvature`); ``ep``: each region's last point, a candidate if ``usable``. Edges: ep first, then the
    sorted ones from the end; flats: the sorted ones, then ep."""
    regions = len(ep)
    with_end = usable[ep]
    count = np.bincount(region, minlength=regions)
    bounds = np.concatenate(([0], np.cumsum(count + with_end)))
    first = np.cumsum(count) - count  # each region's first entry in the sorted candidates
    rank = np.arange(len(position)) - first[region]
    out = np.empty(bounds[-1], dtype=np.int64)
    start = bounds[:-1]
    if edges:
        out[start[with_end]] = ep[with_end]
        out[(start + with_end + count - 1)[region] - rank] = position
    else:
        out[start[region] + rank] = position
        out[(start + count)[with_end]] = ep[with_end]
    return out, bounds


def _wall_points(
    region_of: np.ndarray, position: np.ndarray, curvature: np.ndarray, ground: np.ndarray, taken: bytearray, fa
) -> np.ndarray:
    """Up to ``wall_feature_num`` flattest non-ground points of each sub-region that no edge or flat pick
    took or suppressed (``region_of``, ``position``: the regions' entries, as :func:`_by_curvature` takes them).

    In a corridor the floor is hardly seen; walls and ceiling then hold the odometry's plane stage (see
    :class:`~lego_loam_py.core.odometry.laser_odometry.SweepStartOdometry`)."""
    if fa.wall_feature_num <= 0 or not len(position):
        return np.zeros(0, np.int64)
    is_wall = (curvature < _F32(fa.surf_threshold)) & ~ground & ~np.frombuffer(taken, dtype=bool)
    chosen, chosen_region = _by_curvature(region_of, position, curvature, is_wall)
    # Rank within the region: position in the candidate list minus the region's first candidate.
    first = np.flatnonzero(np.r_[True, chosen_region[1:] != chosen_region[:-1]])
    rank = np.arange(len(chosen)) - np.repeat(first, np.diff(np.r_[first, len(chosen)]))
    return np.unique(chosen[rank < fa.wall_feature_num])  # (the phantom point 0 may appear twice)


def _column_jumps(columns: np.ndarray, column_jump: int) -> np.ndarray:
    """Sorted j in [0, n] where the column jumps by more than ``column_jump`` between points j - 1 and j; the
    array ends (0 and n) count as jumps, they stop a suppression walk too."""
    inner = np.flatnonzero(np.abs(np.diff(columns)) > column_jump) + 1
    return np.concatenate(([0], inner, [len(columns)]))


def _suppression_slices(index: np.ndarray, jumps: np.ndarray, half_window: int):
    """(start, stop) arrays of the slice a pick at each ``index`` marks, as the original walks l = 1..w (and
    -1..-w) and stops at the first column jump; 0 <= start < stop <= n for indices in [0, n)."""
    n = int(jumps[-1])
    negative = len(index) > 0 and index.min() < 0
    k = np.where(index < 0, index + n, index) if negative else index  # the point a negative index reads
    forward = np.minimum(half_window, jumps[np.searchsorted(jumps, np.minimum(k + 1, n))] - k - 1)
    backward = np.minimum(half_window, k - jumps[np.searchsorted(jumps, k, side='right') - 1])
    start = index - backward
    stop = index + forward + 1
    if negative:  # normalised as Python slices are, so that stop - start stays the slice's length
        start = np.clip(np.where(start < 0, start + n, start), 0, n)
        stop = np.maximum(np.clip(np.where(stop < 0, stop + n, stop), 0, n), start)
    return start.astype(np.int64, copy=False), stop.astype(np.int64, copy=False)


def greedy_selection(
    edges: np.ndarray,
    edge_bounds: np.ndarray,
    flats: np.ndarray,
    flat_bounds: np.ndarray,
    jumps: np.ndarray,
    half_window: int,
    taken: bytearray,
    regions: int,
    edge_num: int,
    less_edge_num: int,
    surf_num: int,
    native: bool = True,
):
    """The original's sequential picks, region by region: up to ``edge_num`` sharp and ``less_edge_num`` less
    sharp points from ``edges`` (largest curvature first), then up to ``surf_num`` flat points from ``flats``
    (smallest first), skipping points already ``taken`` and marking each pick's suppression slice in ``taken``,
    which is updated in place: up to ``half_window`` points on each side, stopping at the column ``jumps``
    (:func:`_column_jumps`, :func:`_suppression_slices`).

    ``*_bounds``: region r's candidates are entries [bounds[r], bounds[r + 1]). Returns the sharp, less sharp,
    flat point indices and the region of each less sharp point (int64 arrays). ``native=False`` runs the Python
    loop even when the C extension is there (the tests compare the two)."""
    edges, flats = np.ascontiguousarray(edges, np.int64), np.ascontiguousarray(flats, np.int64)
    edge_bounds = np.ascontiguousarray(edge_bounds, np.int64)
    flat_bounds = np.ascontiguousarray(flat_bounds, np.int64)
    jumps = np.ascontiguousarray(jumps, np.int64)
    if native and hasattr(_feature_kernels, 'select_features'):  # (None, or an extension built before it)
        sharp = np.empty(regions * edge_num, np.int64)
        less_sharp = np.empty(regions * less_edge_num, np.int64)
        less_sharp_region = np.empty_like(less_sharp)
        flat = np.empty(regions * surf_num, np.int64)
        n_sharp, n_less, n_flat = _feature_kernels.select_features(
            edges,
            edge_bounds,
            flats,
            flat_bounds,
            jumps,
            half_window,
            taken,
            edge_num,
            less_edge_num,
            surf_num,
            sharp,
            less_sharp,
            less_sharp_region,
            flat,
        )
        return sharp[:n_sharp], less_sharp[:n_less], flat[:n_flat], less_sharp_region[:n_less]
    edge_slices = _suppression_slices(edges, jumps, half_window)
    flat_slices = _suppression_slices(flats, jumps, half_window)
    edge_list, flat_list = edges.tolist(), flats.tolist()
    edge_bounds, flat_bounds = edge_bounds.tolist(), flat_bounds.tolist()
    edge_low, edge_high = (np.asarray(a).tolist() for a in edge_slices)
    flat_low, flat_high = (np.asarray(a).tolist() for a in flat_slices)
    sharp, less_sharp, less_sharp_region, flat = [], [], [], []
    for region in range(regions):
        count = 0
        for i in range(edge_bounds[region], edge_bounds[region + 1]):
            k = edge_list[i]
            if taken[k]:
                continue
            count += 1
            if count <= edge_num:
                sharp.append(k)
            elif count > less_edge_num:
                break
            less_sharp.append(k)
            less_sharp_region.append(region)
            taken[edge_low[i] : edge_high[i]] = b'\x01' * (edge_high[i] - edge_low[i])
        count = 0
        for i in range(flat_bounds[region], flat_bounds[region + 1]):
            k = flat_list[i]
            if taken[k]:
                continue
            flat.append(k)
            count += 1
            if count >= surf_num:
                break
            taken[flat_low[i] : flat_high[i]] = b'\x01' * (flat_high[i] - flat_low[i])
    return tuple(np.asarray(a, dtype=np.int64) for a in (sharp, less_sharp, flat, less_sharp_region))
