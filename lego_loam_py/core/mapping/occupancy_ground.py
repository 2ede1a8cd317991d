"""Which points of a keyframe are obstacles for a 2D occupancy grid, and which hit the ground (the grid itself:
:mod:`lego_loam_py.core.mapping.occupancy_grid`).

A keyframe's points are levelled with the map's up axis (heights along it, distances across it) and sorted using
only the keyframe's own points, so that the result is cached in its frame and reused when its pose moves. Heights
are compared between 0.2 m columns of points, each standing for its lowest point.

* **The local ground plane**: fitted to the lowest points of the ``ground_cell`` (1 m) cells within
  ``ground_plane_radius`` of the sensor, the nearer the heavier; fitted again twice to the cells below the fit (the
  lowest points of walls and cars lie above the ground: in a corridor, where the lowest beam meets the walls near
  the sensor, they outnumber the floor's), then twice to those near it. Its height under the sensor is the
  sensor's height; its ceiling is ``ground_plane_margin`` + twice its RMS residual + ``ground_plane_margin_slope``
  x distance above it (loose where the terrain curves away).
* **Ground hits** are the locally lowest points: none within ``ground_search_radius`` lies lower than the slope
  ``ground_max_slope`` allows (the ground rises no faster), nor within ``ground_far_radius`` (the same bound between
  cells, one cell diagonal looser); they lie under the ceiling; no ray of their azimuth (``see_under_deg``) passed
  under them to a farther point (opaque ground stops every such ray: the underside of a tree crown or of a car's
  body is seen under); and they have ``ground_min_neighbours`` other ground hits within ``ground_search_radius``
  (the ground is a surface: a trunk's foot whose ground lies unseen is a lowest point alone).
* **Obstacles** are points ``min_height``..``max_height`` above the ground under them, where that ground is known:
  the lowest of the ground hits within ``ground_search_radius`` each carried over along the plane's slope, or, nearer
  to the sensor than most ground hits (a VLP-16 at 1.8 m sees no ground nearer than 6.7 m; the top of a car beside
  it is the lowest point there), the ceiling, the plane being surest near the sensor. A locally lowest point is no
  obstacle elsewhere (it may be ground the ceiling rejected), nor is a point with no ground known under it (a
  crown, or a trunk 25 m off in a forest whose floor a sensor 0.75 m up cannot see that far): a keyframe nearer to
  it will tell.

Why not one plane or one sensor height: the terrain is not flat (the simulated campus rolls by +-2 m, the forest by
+-4 m with slopes up to 0.6) and the band's lower edge is only 0.3 m above the ground; why not the lowest point of
a grid cell: on a slope of 0.4 a 1 m cell spans 0.5 m of ground; why not a slope cone for the ground under an
obstacle: its allowance (0.5 x 2 m) lets the underside of a crown 2.5 m up into the band.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.geometry import pairs_within

try:  # the coarse cone in C (native/occupancy_kernels.c); optional, the NumPy version gives the same
    from lego_loam_py.core import _occupancy_kernels
except ImportError:
    _occupancy_kernels = None

__all__ = ['KeyframeScan', 'classify_keyframe']


@dataclass(frozen=True, eq=False)
class KeyframeScan:
    """A keyframe's points sorted for the grid, in its sensor frame (REP-103 lidar axes) [m]."""

    up: np.ndarray  # (3,) the map's up axis in the sensor frame when classified
    obstacles: np.ndarray  # (n, 3) float32: in the height band
    ground: np.ndarray  # (m, 3) float32: ground hits
    sensor_height: float  # [m] above the local ground plane under it (0: unknown)


def _level_axes(up: np.ndarray) -> np.ndarray:
    """(3, 3) rows: two horizontal axes and ``up``, in the sensor frame (depends on ``up`` alone)."""
    up = np.asarray(up, dtype=float) / np.linalg.norm(up)
    reference = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    first = reference - (reference @ up) * up
    first /= np.linalg.norm(first)
    return np.array([first, np.cross(up, first), up])


COLUMN = 0.2  # [m] columns of points for the slope cones


def _cells(
    xy: np.ndarray, z: np.ndarray, size: float, native: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The square cells of edge ``size`` holding points: (lattice indices (k, 2), each point's cell (n,), each
    cell's lowest height (k,), the index of that lowest point (k,)); cells in the order of their keys below, the
    first of equal heights the lowest. ``native``: in C when the extension is built (the same values)."""
    lattice = np.floor(xy / size).astype(np.int64)
    low = lattice.min()
    span = int(lattice.max()) - int(low) + 1
    keys = (lattice[:, 0] - low) * span + (lattice[:, 1] - low)
    if native and _occupancy_kernels is not None and hasattr(_occupancy_kernels, 'lowest_in_cells'):
        cell_of, lowest = np.empty(len(z), np.int64), np.empty(len(z), np.int64)
        count = _occupancy_kernels.lowest_in_cells(keys, np.ascontiguousarray(z, dtype=np.float64), cell_of, lowest)
        if count >= 0:  # (else keys past 2^31 or a NaN height: NumPy's sort)
            lowest_point = lowest[:count]
            return lattice[lowest_point], cell_of, z[lowest_point], lowest_point
    order = np.lexsort((z, keys))  # by cell, then height: each cell's first is its lowest
    first = np.flatnonzero(np.concatenate([[True], keys[order][1:] != keys[order][:-1]]))
    starts = np.zeros(len(z), np.int64)
    starts[first] = 1
    cell_of = np.empty(len(z), np.int64)
    cell_of[order] = np.cumsum(starts) - 1
    lowest_point = order[first]
    return lattice[lowest_point], cell_of, z[lowest_point], lowest_point


class _Neighbours:
    """The pairs of points within a horizontal radius of each other, once: slope cones and counts over them. The
    passes over the pairs in C when the extension is built (``native``), the same values bit for bit."""

    def __init__(self, xy: np.ndarray, radius: float, native: bool = True):
        self.xy = xy
        self.first, self.second = pairs_within(xy, radius)
        # xy[first] - xy[second] as (m, 2) rows (for the products with a gradient), and their lengths.
        x, y = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1])
        self.native = native and _occupancy_kernels is not None and hasattr(_occupancy_kernels, 'pairs_min')
        self.offset = np.empty((len(self.first), 2))
        if self.native:
            self.distance = np.empty(len(self.first))
            _occupancy_kernels.pair_offsets(x, y, self.first, self.second, self.offset, self.distance)
        else:
            # a coordinate at a time: gathers and element-wise passes over (m, 2) rows cost several times more on
            # the hundred thousand pairs of a 64-beam keyframe
            self.offset[:, 0] = np.subtract(x[self.first], x[self.second])
            self.offset[:, 1] = np.subtract(y[self.first], y[self.second])
            self.distance = np.hypot(self.offset[:, 0], self.offset[:, 1])

    def _minimum(self, bound: np.ndarray, z: np.ndarray, add: np.ndarray, backward_sign: float, base) -> None:
        """In place: bound[first] = min(bound[first], z[second] + add) over the pairs whose second point is in
        ``base`` (all without it), then bound[second] = min(bound[second], z[first] + backward_sign * add) over
        those whose first point is."""
        if self.native:
            mask = b'' if base is None else np.ascontiguousarray(base, dtype=np.bool_)
            _occupancy_kernels.pairs_min(
                bound, self.first, self.second, np.ascontiguousarray(z), add, backward_sign, mask
            )
            return
        for to, source, sign in ((self.first, self.second, 1.0), (self.second, self.first, backward_sign)):
            take = slice(None) if base is None else np.flatnonzero(base[source])
            np.minimum.at(bound, to[take], z[source[take]] + sign * add[take])

    def cone(self, z: np.ndarray, slope: float, base: np.ndarray | None = None) -> np.ndarray:
        """Per point: min over the base points among its neighbours and itself (all without ``base``, a mask) of
        ``z + slope x horizontal distance``; inf where none."""
        bound = z.copy() if base is None else np.where(base, z, np.inf)
        self._minimum(bound, z, slope * self.distance, 1.0, base)
        return bound

    def ground_under(self, z: np.ndarray, base: np.ndarray, gradient: np.ndarray) -> np.ndarray:
        """Per point: the ground under it from the base points among its neighbours and itself, each carried over
        along the ground plane's ``gradient`` (dz/dx, dz/dy), the lowest of them; inf where none."""
        bound = np.where(base, z, np.inf)
        # The rise from the second point to the first; the other way round its negation (exactly: a product's
        # rounding is symmetric), so one product of all the pairs (NumPy's, as BLAS rounds it; a row's value does not
        # depend on the rows beside it) serves both directions.
        self._minimum(bound, z, self.offset @ gradient, -1.0, base)
        return bound

    def count(self, mask: np.ndarray) -> np.ndarray:
        """Per point: how many of its neighbours (itself not) are in ``mask``."""
        n = len(mask)
        if self.native:
            out = np.empty(n, np.int64)
            _occupancy_kernels.pairs_count(self.first, self.second, np.ascontiguousarray(mask, dtype=np.bool_), out)
            return out
        both = mask[self.first] & mask[self.second]
        return np.bincount(self.first[both], minlength=n) + np.bincount(self.second[both], minlength=n)


@functools.lru_cache(maxsize=16)
def _cone_offsets(cell: float, slope: float, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cell offsets (di, dj) (m,) int64 within ``radius`` [m] of a cell of edge ``cell`` [m], and what each adds
    to the cone, ``slope (distance + one cell diagonal)`` [m] (m,) float64, in Python's floats (math.hypot: C's
    hypot may round differently) and in the order both versions of :func:`_coarse_cone` take them. Read-only."""
    reach = int(radius // cell)
    di, dj, terms = [], [], []
    for i in range(-reach, reach + 1):
        for j in range(-reach, reach + 1):
            distance = cell * math.hypot(i, j)
            if distance <= radius:
                di.append(i)
                dj.append(j)
                terms.append(slope * (distance + math.sqrt(2.0) * cell))
    table = np.array(di, np.int64), np.array(dj, np.int64), np.array(terms, np.float64)
    for column in table:
        column.setflags(write=False)
    return table


def _coarse_cone(
    cells: np.ndarray, lowest: np.ndarray, cell: float, slope: float, radius: float, native: bool = True
) -> np.ndarray:
    """Per cell (``cells`` (k, 2) lattice indices, ``lowest`` their lowest points [m]): min over the cells within
    ``radius`` [m] of ``lowest + slope (distance + one cell diagonal)``, a bound of the cone wherever in the two cells
    the points are (inf: none). In C when the extension is built, the same values bit for bit; ``native=False``
    runs the NumPy version (the tests compare the two)."""
    corner = cells.min(axis=0)
    shape = tuple(cells.max(axis=0) - corner + 1)
    local = cells - corner
    grid = np.full(shape, np.inf)
    grid[local[:, 0], local[:, 1]] = lowest
    di, dj, terms = _cone_offsets(float(cell), float(slope), float(radius))
    # (A term of -0.0, from a slope of -0.0, could make +0.0 and -0.0 tie, which NumPy's SIMD and scalar minimum
    # break differently: NumPy decides those.)
    if native and _occupancy_kernels is not None and not np.signbit(terms).any():
        bound = np.empty(len(local))
        _occupancy_kernels.coarse_cone(grid, shape[1], di, dj, terms, np.ascontiguousarray(local, np.int64), bound)
        return bound
    bound = np.full(shape, np.inf)
    n0, n1 = shape
    for i, j, term in zip(di.tolist(), dj.tolist(), terms.tolist()):
        if abs(i) >= n0 or abs(j) >= n1:
            continue
        target = bound[max(i, 0) : n0 + min(i, 0), max(j, 0) : n1 + min(j, 0)]
        source = grid[max(-i, 0) : n0 + min(-i, 0), max(-j, 0) : n1 + min(-j, 0)]
        np.minimum(target, source + term, out=target)
    return bound[local[:, 0], local[:, 1]]


def _seen_under(xy: np.ndarray, z: np.ndarray, horizontal: np.ndarray, bin_deg: float, clearance: float) -> np.ndarray:
    """Per point: whether a ray to a farther point of its azimuth bin passed more than ``clearance`` under it: the
    ground cannot be such a point (opaque ground stops every ray that would pass under it)."""
    bins = np.floor((np.arctan2(xy[:, 1], xy[:, 0]) + math.pi) / math.radians(bin_deg)).astype(np.int64)
    order = np.lexsort((-horizontal, -bins))  # bins descending, each from its farthest point in
    slope = z / np.maximum(horizontal, 1e-6)  # the ray's height per metre
    # min of the slopes of the points farther out in the same bin: a running min, kept inside each bin by an
    # offset that grows with the bin (the bins come in descending order, so a new bin starts below the last)
    offset = bins[order] * (2.0 * (np.abs(slope).max() + 1.0))
    farther = np.minimum.accumulate(slope[order] + offset) - offset
    lowest_beyond = np.empty(len(z))
    lowest_beyond[order] = np.concatenate([[np.inf], farther[:-1]])
    same_bin = np.empty(len(z), bool)
    same_bin[order] = np.concatenate([[False], bins[order][1:] == bins[order][:-1]])
    return same_bin & (lowest_beyond * horizontal < z - clearance)


def _ground_plane(xy: np.ndarray, z: np.ndarray, radius: float) -> tuple[np.ndarray, float] | None:
    """(a, b, c) of the plane ``z = a x + b y + c`` under the cells' lowest points (at ``xy``, heights ``z``)
    within ``radius`` of the sensor, and the RMS residual of the cells it was fitted to; None with too few."""
    distance = np.hypot(xy[:, 0], xy[:, 1])
    near = distance <= radius
    xy, z, weight = xy[near], z[near], 1.0 / (1.0 + distance[near] / 5.0)
    design = np.column_stack([xy, np.ones(len(xy))])
    keep, coefficients = np.ones(len(z), bool), None
    for above in (np.inf, 0.02, 0.02, 0.25, 0.15):  # from the cells below the fits (walls are above), then near
        if coefficients is not None:
            keep = z - design @ coefficients < above
        if keep.sum() < 10:
            return None
        coefficients = np.linalg.lstsq(design[keep] * weight[keep, None], z[keep] * weight[keep], rcond=None)[0]
    residual = z[keep] - design[keep] @ coefficients
    return coefficients, float(np.sqrt(np.average(residual**2, weights=weight[keep])))


def classify_keyframe(points: np.ndarray, up: np.ndarray, params, native: bool = True) -> KeyframeScan:
    """Sort a keyframe's points ((n, 3) sensor frame, REP-103 lidar axes) into obstacles and ground hits (module
    docstring); ``up``: the map's up axis in the sensor frame; ``params``: an
    :class:`~lego_loam_py.core.params.types.OccupancyGridParams`; ``native=False``: NumPy only (the same result)."""
    p = params
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    axes = _level_axes(up)
    levelled = points.astype(np.float64) @ axes.T
    horizontal = np.hypot(levelled[:, 0], levelled[:, 1])
    near = (horizontal >= p.min_range) & (horizontal <= p.max_range)
    points, levelled, horizontal = points[near], levelled[near], horizontal[near]
    empty = np.zeros((0, 3), np.float32)
    if not len(points):
        return KeyframeScan(axes[2].copy(), empty, empty, 0.0)
    xy, z = levelled[:, :2], levelled[:, 2]
    cells, cell_of, cell_lowest, cell_point = _cells(xy, z, p.ground_cell, native)
    # The slope cones between columns of points (the lowest point of each 0.2 m column stands for it): a wall's
    # points stack in a few columns, so this is several times fewer pairs than between the points.
    _, column_of, column_lowest, column_point = _cells(xy, z, COLUMN, native)
    neighbours = _Neighbours(xy[column_point], p.ground_search_radius, native)
    lower_bound = np.minimum(
        neighbours.cone(column_lowest, p.ground_max_slope)[column_of],
        _coarse_cone(cells, cell_lowest, p.ground_cell, p.ground_max_slope, p.ground_far_radius, native)[cell_of],
    )
    lowest_around = z - lower_bound <= p.ground_tolerance
    ground_hit = lowest_around.copy()
    fit = _ground_plane(xy[cell_point], cell_lowest, p.ground_plane_radius)
    ceiling = np.full(len(z), np.inf)
    sensor_height, gradient = 0.0, np.zeros(2)
    if fit is not None:
        plane, spread = fit
        gradient = plane[:2]
        sensor_height = max(0.0, -float(plane[2]))
        ceiling = (
            xy @ plane[:2] + plane[2] + p.ground_plane_margin + 2.0 * spread + p.ground_plane_margin_slope * horizontal
        )
        ground_hit &= z <= ceiling
    ground_hit &= ~_seen_under(xy, z, horizontal, p.see_under_deg, p.ground_tolerance)
    # The ground is a surface: a lowest point alone (the foot of a trunk whose ground lies unseen) is no ground hit.
    ground_column = ground_hit[column_point]
    ground_column &= neighbours.count(ground_column) >= p.ground_min_neighbours
    ground_hit &= ground_column[column_of]
    ground = neighbours.ground_under(column_lowest, ground_column, gradient)[column_of]
    # A locally lowest point that is no ground hit may be ground all the same (on terrain that curves away from the
    # plane): no obstacle. Except nearer than most ground hits, where the lidar sees no ground (a car's top beside
    # it is the lowest point there): the plane, surest near the sensor, tells.
    candidate = ~lowest_around
    if ground_hit.any():
        blind = horizontal < np.percentile(horizontal[ground_hit], 10)
        ground[blind] = np.minimum(ground[blind], ceiling[blind])
        candidate |= blind
    height = z - ground
    band = candidate & (height >= p.min_height) & (height <= p.max_height)
    return KeyframeScan(
        axes[2].copy(), np.ascontiguousarray(points[band]), np.ascontiguousarray(points[ground_hit]), sensor_height
    )
