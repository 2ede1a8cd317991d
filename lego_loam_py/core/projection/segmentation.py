"""imageProjection's segmentation (docs/original.md §6.1): the label of every range-image pixel.

The original's breadth-first segmentation runs in C when the extension is built (native/projection_kernels.c).
Its NumPy version computes the clusters as connected components of the graph whose nodes are the non-ground,
non-empty pixels and whose edges join 4-neighbours (columns wrap around) that satisfy the angle criterion
β > segment_theta. The criterion is symmetric in the two pixels, so components equal the BFS's clusters; labels
are numbered as the BFS numbers them (by the row-major index of each cluster's first pixel, invalid clusters
consuming no number). The components are found on a smaller graph with the same connectivity: the vertically
joined runs of each column are its nodes (SciPy's connected components).
"""

from __future__ import annotations

import math

import numpy as np

from lego_loam_py.core.params.types import Params
from lego_loam_py.core.parity.atan2f_decisions import atan2f_exceeds, exceeding_tests
from lego_loam_py.core.parity.libm import cosf, sinf

try:  # the segmentation in C (native/projection_kernels.c); optional: the NumPy version gives the same labels
    from lego_loam_py.core import _projection_kernels
except ImportError:
    _projection_kernels = None
# What the first scan imports: SciPy's connected components, without the C kernel.
SEGMENTATION_IMPORTS = ('scipy.sparse.csgraph',) if _projection_kernels is None else ()

__all__ = ['Segmentation', 'OUTLIER_LABEL', 'NO_LABEL', 'SEGMENTATION_IMPORTS', 'run_components']

OUTLIER_LABEL = 999999  # the original's label of points in clusters that are too small
NO_LABEL = -1  # ground or empty pixel (labelMat == -1)
_F32 = np.float32


def run_components(runs: int, lower: np.ndarray, upper: np.ndarray) -> tuple[int, np.ndarray]:
    """(count, component of each run) of the undirected graph of ``runs`` nodes whose edges join ``lower[k]`` and
    ``upper[k]`` (``lower`` ascending): SciPy's connected components (only which runs share a component matters to
    the labels, not its number)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    indptr = np.zeros(runs + 1, dtype=np.int32)
    np.cumsum(np.bincount(lower, minlength=runs), out=indptr[1:])
    graph = csr_matrix((np.ones(len(upper)), upper, indptr), shape=(runs, runs))
    return connected_components(graph, directed=False)


class Segmentation:
    """The segmentation of one sensor configuration; :meth:`labels` handles one scan's range image."""

    def __init__(self, params: Params):
        s, self._settings = params.sensor, params.image_projection
        self.n_scan, self.horizon_scan = s.n_scan, s.horizon_scan
        # The original's float constants: the angle between neighbouring columns (0) and rows (1).
        alpha_x = _F32(s.ang_res_x / 180.0 * math.pi)
        alpha_y = _F32(s.ang_res_y / 180.0 * math.pi)
        self._sin_alpha = (sinf(alpha_x), sinf(alpha_y))
        self._cos_alpha = (cosf(alpha_x), cosf(alpha_y))
        if s.beam_elevations:  # unevenly spaced beams: each row and the row above it have their own angle
            rows_apart = np.diff(np.radians(np.asarray(s.beam_elevations, dtype=np.float64)))  # (n_scan - 1,)
            # (n_scan - 1, 1): vertical pairs are (rows - 1, columns) arrays
            self._sin_alpha = (self._sin_alpha[0], np.sin(rows_apart).astype(_F32)[:, None])
            self._cos_alpha = (self._cos_alpha[0], np.cos(rows_apart).astype(_F32)[:, None])
        self._theta = _F32(self._settings.segment_theta)
        # The C kernel's view of the same constants: an angle per pair of rows, theta's tested directions.
        self._row_sin, self._row_cos = (
            np.ascontiguousarray(np.broadcast_to(v, (self.n_scan - 1, 1)).reshape(-1), dtype=_F32)
            for v in (self._sin_alpha[1], self._cos_alpha[1])
        )
        tests = exceeding_tests(self._theta, (0.0, math.pi))  # (beta lies in [0, pi]: y >= 0)
        self._directions = (
            np.empty(0, _F32)
            if tests is None
            else np.array([f(phi) for phi in tests for f in (math.cos, math.sin)], dtype=_F32)
        )

    def labels(
        self, range_image: np.ndarray, filled: np.ndarray, ground: np.ndarray, native: bool = True
    ) -> np.ndarray:
        """The original's labelMat as int32 (N_SCAN*H,): -1 ground or empty, 999999 pixels of clusters that
        are too small, 1, 2, ... valid segments numbered in the BFS's order.

        ``range_image`` is (N_SCAN*H,) float32 [m], ``filled`` marks non-empty pixels, ``ground`` the ground.
        The BFS itself in C when the extension is built (native/projection_kernels.c, the same labels);
        ``native=False``: the components of the joined runs, in NumPy (the tests compare the two).
        """
        n, h = self.n_scan, self.horizon_scan
        ip = self._settings
        candidate = filled & ~ground
        if native and _projection_kernels is not None and range_image.dtype == _F32:
            labels = np.empty(n * h, dtype=np.int32)
            _projection_kernels.segment_labels(
                np.ascontiguousarray(range_image),
                np.ascontiguousarray(candidate),
                n,
                h,
                self._row_sin,
                self._row_cos,
                self._sin_alpha[0],
                self._cos_alpha[0],
                self._theta,
                self._directions,
                ip.segment_min_cluster_size,
                ip.segment_valid_point_num,
                ip.segment_valid_line_num,
                labels,
            )
            return labels
        if not candidate.any():
            return np.full(n * h, NO_LABEL, dtype=np.int32)
        # Work in column-major order, (h, n): a column's pixels bottom to top, then the next column.
        # Vertical joins chain the pixels of a column into runs (poles and walls give long ones, while the
        # horizontal criterion often fails on surfaces seen obliquely); the graph's nodes are these runs and
        # its edges the horizontal joins: a quarter of the pixels' nodes and edges, so the components cost
        # much less.
        # The joins are found in the images' row-major order and only the boolean results transposed (a float
        # image's transposed copy costs more).
        node_rows = candidate.reshape(n, h)
        depth = range_image.reshape(n, h)
        joined_up = np.zeros((n, h), dtype=bool)  # joined to the pixel above (row n-1 has none)
        joined_up[:-1] = node_rows[:-1] & node_rows[1:] & self._joins(depth[:-1], depth[1:], 1)
        depth_right = np.roll(depth, -1, axis=1)  # columns wrap around
        joined_right = node_rows & np.roll(node_rows, -1, axis=1) & self._joins(depth, depth_right, 0)
        node, joined_up, joined_right = (
            np.ascontiguousarray(a.T).reshape(-1) for a in (node_rows, joined_up, joined_right)
        )

        joined_below = np.zeros(n * h, dtype=bool)
        joined_below[1:] = joined_up[:-1]
        starts_run = node & ~joined_below
        first = np.flatnonzero(starts_run)  # runs are ranges of the column-major order
        last = np.flatnonzero(node & ~joined_up)
        runs = len(first)
        run_length = last - first + 1
        run_of_pixel = np.cumsum(starts_run, dtype=np.int32) - 1
        # Horizontal edges, in column-major order of their left pixel, come sorted by its run (the wrap-around
        # ones, from column h-1, last). Pixels side by side in two runs give repeats, one after the other.
        left = np.flatnonzero(joined_right)
        right = left + n
        right[right >= n * h] -= n * h
        lower, upper = run_of_pixel[left], run_of_pixel[right]
        repeat = np.zeros(len(lower), dtype=bool)
        repeat[1:] = (lower[1:] == lower[:-1]) & (upper[1:] == upper[:-1])
        lower, upper = lower[~repeat], upper[~repeat]
        count, component_of_run = run_components(runs, lower, upper)

        size = np.bincount(component_of_run, weights=run_length, minlength=count)
        # The BFS seed is the component's first pixel in row-major order: the lowest pixel of one of its runs.
        first_row_major = (first % n) * h + first // n
        seed = np.full(count, np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(seed, component_of_run, first_row_major)
        valid = size >= ip.segment_min_cluster_size
        # The line count decides only for the mid-sized clusters. It counts the rows of the pixels other
        # than the seed: the seed's row only if another pixel of the component lies in it (quirk 8.13). Each
        # run covers an interval of rows, the seed's run from the row above the seed (its lowest pixel).
        mid_sized = (size >= ip.segment_valid_point_num) & ~valid
        if mid_sized.any():
            run = np.flatnonzero(mid_sized[component_of_run])
            component = component_of_run[run]
            low = first[run] % n + (first_row_major[run] == seed[component])
            high = last[run] % n
            spans = low <= high
            # Rows covered per mid-sized cluster: +1 where an interval starts, -1 after it ends, summed up.
            clusters = int(np.count_nonzero(mid_sized))
            cell = (np.cumsum(mid_sized)[component[spans]] - 1) * (n + 1)
            bounds = np.bincount(cell + low[spans], minlength=clusters * (n + 1))
            bounds -= np.bincount(cell + high[spans] + 1, minlength=clusters * (n + 1))
            covered = np.cumsum(bounds.reshape(clusters, n + 1), axis=1)[:, :n] > 0
            line_count = np.zeros(count, dtype=np.int64)
            line_count[mid_sized] = np.count_nonzero(covered, axis=1)
            valid |= mid_sized & (line_count >= ip.segment_valid_line_num)
        # Label numbers in the order the BFS finds the clusters (row-major seed order), valid ones only.
        number = np.full(count, OUTLIER_LABEL, dtype=np.int32)
        valid_ids = np.flatnonzero(valid)
        number[valid_ids[np.argsort(seed[valid_ids])]] = np.arange(1, len(valid_ids) + 1, dtype=np.int32)
        # The column-major order is runs and the gaps between them, one after the other: the labels are each
        # segment's value repeated over its length (the gaps', maybe empty, NO_LABEL).
        value = np.full(2 * runs + 1, NO_LABEL, dtype=np.int32)
        value[1::2] = number[component_of_run]
        length = np.empty(2 * runs + 1, dtype=np.int64)
        length[1::2] = run_length
        length[0:-1:2] = first
        length[2:-1:2] -= last[:-1] + 1
        length[-1] = n * h - 1 - last[-1]
        return np.repeat(value, length).reshape(h, n).T.reshape(-1)

    def _joins(self, range_a: np.ndarray, range_b: np.ndarray, direction: int) -> np.ndarray:
        """The segmentation criterion beta > theta for neighbour pairs (direction 0: horizontal, 1: vertical;
        vertical pairs are (rows - 1, columns) arrays, so a beam table's per-row angles broadcast along columns).

        Computed for every pixel, pair or not (empty pixels' FLT_MAX ranges give finite angles far from theta):
        cheaper than gathering the pairs. beta is libm's atan2f(y, x) with y >= 0, so it lies in [0, pi].
        """
        d1, d2 = np.maximum(range_a, range_b), np.minimum(range_a, range_b)
        y = d2 * self._sin_alpha[direction]
        x = d2 * self._cos_alpha[direction]
        np.subtract(d1, x, out=x)
        return atan2f_exceeds(y, x, [self._theta], (0.0, math.pi))[0]
