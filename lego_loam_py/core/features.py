"""Feature extraction of featureAssociation (reference §6.2 steps 2-4, quirks §8.2 and §8.7).

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

from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.image_projection import CloudInfo
from lego_loam_py.core.params import Params
from lego_loam_py.core.voxel import voxel_downsample_groups

__all__ = ['ScanFeatures', 'FeatureExtractor', 'smoothness', 'occluded_mask']

_F32 = np.float32


@dataclass
class ScanFeatures:
    """Features of one scan; clouds are float32 (k, 4) = x, y, z (camera axes), intensity (ring + 0.1 s)."""

    sharp: np.ndarray
    less_sharp: np.ndarray
    flat: np.ndarray
    less_flat: np.ndarray
    sharp_index: np.ndarray        # indices into the scan's points
    less_sharp_index: np.ndarray
    flat_index: np.ndarray


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
        acc += r[k:k + m]
    acc -= r[w:w + m] * _F32(2 * w)
    for k in range(w + 1, 2 * w + 1):
        acc += r[k:k + m]
    out[w:n - w] = acc * acc
    return out


def occluded_mask(ranges: np.ndarray, columns: np.ndarray, params: Params) -> np.ndarray:
    """Points excluded from selection: the near side of occlusion boundaries and parallel beams."""
    fa = params.feature_association
    r = np.asarray(ranges, dtype=_F32)
    n = len(r)
    picked = np.zeros(n, dtype=bool)
    w = fa.smoothness_half_window
    i = np.arange(w, n - w - 1)
    if len(i) == 0:
        return picked
    col = columns.astype(np.int64)
    near = np.abs(col[i + 1] - col[i]) < fa.occlusion_column_gap
    d1, d2 = r[i], r[i + 1]
    jump = _F32(fa.occlusion_depth_jump)
    farther_behind = near & (d1.astype(np.float64) - d2 > jump)        # i is the far side: mark i-5..i
    farther_ahead = near & ~farther_behind & (d2.astype(np.float64) - d1 > jump)  # mark i+1..i+6
    for offset in range(w + 1):
        picked[i[farther_behind] - offset] = True
        picked[i[farther_ahead] + 1 + offset] = True
    diff1 = np.abs(r[i - 1] - r[i])
    diff2 = np.abs(r[i + 1] - r[i])
    ratio = fa.parallel_beam_ratio * r[i].astype(np.float64)
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
        label = np.zeros(n, dtype=np.int8)
        edge_thr, surf_thr = _F32(fa.edge_threshold), _F32(fa.surf_threshold)
        is_edge_candidate = (curvature > edge_thr) & ~ground
        is_flat_candidate = (curvature < surf_thr) & ground
        sharp, less_sharp, flat = [], [], []
        less_flat_parts, less_flat_rings = [], []
        sections = fa.sections_total
        start_ring = info.start_ring_index.astype(np.int64)
        end_ring = info.end_ring_index.astype(np.int64)

        # How far a pick suppresses its neighbours: up to suppress_half_window points each way, stopping
        # before the first column jump larger than suppress_column_jump (precomputed for every point).
        forward, backward = _suppression_extents(columns, fa.suppress_half_window, fa.suppress_column_jump)

        def suppress(index: int) -> None:
            picked[index - backward[index]:index + forward[index] + 1] = True

        for ring in range(len(start_ring)):
            ring_less_flat = []
            s, e = int(start_ring[ring]), int(end_ring[ring])
            for j in range(sections):
                # C++ integer division truncates toward zero.
                sp = int((s * (sections - j) + e * j) / sections)
                ep = int((s * (sections - 1 - j) + e * (j + 1)) / sections) - 1
                if sp >= ep:
                    continue
                positions = np.arange(sp, ep)
                ind = positions.copy()
                # Positions below w were never written: a phantom entry for point 0, whose curvature was
                # never computed either (0), so the candidate tests below treat it as point 0.
                ind[positions < w] = 0
                order = ind[np.argsort(curvature[ind], kind='stable')]
                # Edges: the unsorted element ep first, then from the largest curvature down.
                edge_order = np.concatenate(([ep], order[::-1]))
                edge_order = edge_order[is_edge_candidate[edge_order]].tolist()
                count = 0
                for k in edge_order:
                    if picked[k]:
                        continue
                    count += 1
                    if count <= fa.edge_feature_num:
                        label[k] = 2
                        sharp.append(k)
                        less_sharp.append(k)
                    elif count <= fa.less_edge_feature_num:
                        label[k] = 1
                        less_sharp.append(k)
                    else:
                        break
                    suppress(k)
                # Flats: from the smallest curvature up, the unsorted element ep last.
                flat_order = np.concatenate((order, [ep]))
                flat_order = flat_order[is_flat_candidate[flat_order]].tolist()
                count = 0
                for k in flat_order:
                    if picked[k]:
                        continue
                    label[k] = -1
                    flat.append(k)
                    count += 1
                    if count >= fa.surf_feature_num:
                        break
                    suppress(k)
                region = np.arange(sp, ep + 1)
                ring_less_flat.append(region[label[region] <= 0])
            if ring_less_flat:
                idx = np.concatenate(ring_less_flat)
                less_flat_parts.append(idx)
                less_flat_rings.append(np.full(len(idx), ring))
        self._stale_picked[:head] = picked[:head]
        sharp_index = np.asarray(sharp, dtype=np.int64)
        less_sharp_index = np.asarray(less_sharp, dtype=np.int64)
        flat_index = np.asarray(flat, dtype=np.int64)
        if less_flat_parts:
            # The original filters ring by ring; one grouped filter gives the same points in the same order.
            less_flat = voxel_downsample_groups(points[np.concatenate(less_flat_parts)], np.concatenate(less_flat_rings),
                                                fa.less_flat_leaf_size)
        else:
            less_flat = np.zeros((0, 4), _F32)
        return ScanFeatures(sharp=points[sharp_index], less_sharp=points[less_sharp_index], flat=points[flat_index],
                            less_flat=less_flat, sharp_index=sharp_index, less_sharp_index=less_sharp_index,
                            flat_index=flat_index)



def _suppression_extents(columns: np.ndarray, half_window: int, column_jump: int) -> tuple[np.ndarray, np.ndarray]:
    """(forward, backward) numbers of neighbours a pick at each index marks: the original walks l = 1..w
    (and -1..-w) and stops at the first |col[k+l] - col[k+l-1]| > jump."""
    n = len(columns)
    jump = np.zeros(n + 1, dtype=bool)          # jump[j]: between point j-1 and j
    jump[1:n] = np.abs(np.diff(columns)) > column_jump
    jump[0] = jump[n] = True                    # the array ends stop the walk too
    index = np.arange(n + 1)
    next_jump = np.minimum.accumulate(np.where(jump, index, n + 1)[::-1])[::-1]   # first jump at >= j
    last_jump = np.maximum.accumulate(np.where(jump, index, -1))                  # last jump at <= j
    k = np.arange(n)
    forward = np.minimum(half_window, next_jump[np.minimum(k + 1, n)] - k - 1)
    backward = np.minimum(half_window, k - last_jump[k])
    return forward.astype(np.int64), backward.astype(np.int64)
