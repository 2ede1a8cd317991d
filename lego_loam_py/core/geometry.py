"""Point-to-plane and point-to-line geometry shared by the odometry and the mapping (docs/original.md §6.2
step 7, §6.3), in float32 where the original computes in float, and the searches for the nearest points both make
(:class:`GridNeighbours`).
"""

from __future__ import annotations

import math

import numpy as np

from lego_loam_py.core.indexing import select_rows

try:  # the plane fits in one pass (native/geometry_kernels.c); optional: fit_planes gives the same values
    from lego_loam_py.core import _geometry_kernels
except ImportError:
    _geometry_kernels = None

__all__ = [
    'plane_through',
    'plane_distance',
    'squared_lengths',
    'plane_coefficients',
    'nearest_within',
    'GridNeighbours',
    'pairs_within',
    'fit_planes',
    'fit_planes_at',
    'line_fits_at',
    'principal_spreads',
    'line_offsets',
    'cross_rows',
    'line_coefficients',
    'affine_fit',
]

_F32 = np.float32


def plane_through(a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Unit normal (n, 3) and offset (n,) of the planes through a, b, c (float32): ``n · p + offset = 0``."""
    ab, ac = (b - a).astype(_F32), (c - a).astype(_F32)
    pa = ab[:, 1] * ac[:, 2] - ac[:, 1] * ab[:, 2]
    pb = ab[:, 2] * ac[:, 0] - ac[:, 2] * ab[:, 0]
    pc = ab[:, 0] * ac[:, 1] - ac[:, 0] * ab[:, 1]
    pd = -(pa * a[:, 0] + pb * a[:, 1] + pc * a[:, 2])
    with np.errstate(invalid='ignore', divide='ignore'):
        ps = np.sqrt(pa * pa + pb * pb + pc * pc)
        normal = np.stack([pa / ps, pb / ps, pc / ps], axis=1)
        pd = pd / ps
    return normal, pd


def squared_lengths(points: np.ndarray) -> np.ndarray:
    """x² + y² + z² [m²] of each row of (n, >= 3) points, in float64: ``(points[:, :3].astype(np.float64) ** 2)
    .sum(axis=1)`` bit for bit (NumPy adds a row's three squares in order to zero), without its reduction over a short
    axis, which costs some 15 ns a row."""
    x, y, z = (points[:, axis].astype(np.float64) for axis in range(3))
    x *= x
    y *= y
    z *= z
    x += y
    x += z
    return x


def plane_distance(normal: np.ndarray, offset: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Signed distances of points p (n, >= 3) to the planes of :func:`plane_through`."""
    return normal[:, 0] * p[:, 0] + normal[:, 1] * p[:, 1] + normal[:, 2] * p[:, 2] + offset


def plane_coefficients(p_start: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Unit normal (n, 3) and signed distance (n,) of points to the planes through a, b, c (float32)."""
    normal, offset = plane_through(a, b, c)
    return normal, plane_distance(normal, offset, p_start)


def nearest_within(tree, points: np.ndarray, k: int, max_sq_dist: float):
    """(indices of the ``points`` whose ``k`` nearest neighbours in ``tree`` (a cKDTree) all lie within
    ``sqrt(max_sq_dist)`` [m], those neighbours' indices (m, k)). The tree search stops at the gate, which
    spares most of the walk for points far from the tree's cloud; the neighbours of the points that pass are
    the exact k nearest."""
    distance, index = tree.query(points, k=k, distance_upper_bound=_search_bound(max_sq_dist))
    used = np.flatnonzero(distance[:, -1] ** 2 < max_sq_dist)
    return used, index[used]


class GridNeighbours:
    """The points (n, >= 3) float32 [m] of a map, for many :func:`nearest_within` searches within one radius
    (``sqrt(max_sq_dist)``) and nearest-point searches: sorted by cubic cell of that side, or of ``cell``
    (``native/geometry_kernels.c``, a counting sort, a fraction of a kd-tree's build), and searched over the 27 cells
    around each query, the candidates of three cells side by side in memory (the nearest point: shell by shell of
    cells outwards). The answers are cKDTree's, bit for bit: the same squared distances by the same operations, the
    same neighbours, nearest first. Two candidates at exactly the same distance, whose order the kd-tree decides by
    its walk, are left to a cKDTree built then, as is everything without the extension, other float types, or
    points spread over more than MAX_CELLS cells. ``query`` is that cKDTree's.
    """

    MAX_CELLS = 1 << 23  # (32 MiB of cell starts: a map some 200 x 200 x 200 search radii across)

    def __init__(self, points: np.ndarray, max_sq_dist: float | None = None, cell: float | None = None, **tree_options):
        """``cell`` [m]: the cells' side; by default the radius of ``max_sq_dist`` [m^2], which
        :meth:`nearest_within` needs (with smaller cells it asks the kd-tree); :meth:`nearest_one` takes any.
        ``tree_options``: the cKDTree's (its layout picks between points at exactly the same distance); by default
        ``balanced_tree=False``."""
        if cell is None and max_sq_dist is None:
            raise ValueError('GridNeighbours needs a cell size or the squared radius it spans')
        self.points = points
        self._tree_options = tree_options or {'balanced_tree': False}
        self._tree = None
        self._grid = None
        n = len(points)
        if not (
            _geometry_kernels is not None
            and n
            and points.dtype == _F32
            and points.ndim == 2
            and points.shape[1] >= 3
            and points.flags.c_contiguous
        ):
            return
        if cell is None:
            cell = _search_bound(max_sq_dist) * (1.0 + 1e-6)  # (a cell spanning the search radius)
        extent = _geometry_kernels.grid_extent(points, points.shape[1], cell)
        if extent is None:
            return
        low, high = extent
        size = tuple(h - lo + 1 for lo, h in zip(low, high))
        if size[0] * size[1] * size[2] > self.MAX_CELLS:
            return
        starts = np.empty(size[0] * size[1] * size[2] + 1, np.int32)
        sorted_xyz, sorted_rows = np.empty((n, 3)), np.empty(n, np.int64)
        _geometry_kernels.grid_fill(
            points, points.shape[1], cell, low, size, starts, sorted_xyz, sorted_rows, np.empty(n, np.int64)
        )
        self._grid = (cell, low, size, starts, sorted_xyz, sorted_rows)

    @property
    def tree(self):
        """The cKDTree of the points' float64 coordinates (built when first asked for)."""
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.points[:, :3].astype(np.float64), **self._tree_options)
        return self._tree

    def query(self, *args, **kwargs):
        """cKDTree.query on the points."""
        return self.tree.query(*args, **kwargs)

    def nearest_within(self, queries: np.ndarray, k: int, max_sq_dist: float) -> tuple[np.ndarray, np.ndarray]:
        """:func:`nearest_within` of the (m, >= 3) ``queries`` [m] in these points (on the grid when its cells span
        the radius)."""
        on_grid = self._grid is not None and self._grid[0] >= _search_bound(max_sq_dist)  # (27 cells hold it)
        if not on_grid or queries.dtype != _F32 or queries.ndim != 2 or not 1 < k <= 64:
            return nearest_within(self.tree, queries[:, :3], k, max_sq_dist)
        queries = np.ascontiguousarray(queries)
        status, index = np.empty(len(queries), np.uint8), np.empty((len(queries), k), np.int64)
        bound = _search_bound(max_sq_dist)
        _geometry_kernels.grid_nearest(
            *self._grid, queries, queries.shape[1], k, bound * bound, max_sq_dist, status, index
        )
        tied = np.flatnonzero(status == 2)
        if len(tied):  # equal distances: the kd-tree's order
            near, tied_index = nearest_within(self.tree, queries[tied, :3], k, max_sq_dist)
            status[tied] = 0
            status[tied[near]] = 1
            index[tied[near]] = tied_index
        used = np.flatnonzero(status)
        return used, select_rows(index, used)

    def nearest_one(self, queries: np.ndarray, max_sq_dist: float) -> tuple[np.ndarray, np.ndarray]:
        """(indices of the (m, >= 3) ``queries`` [m] whose nearest point, as cKDTree's ``query(k=1)`` finds it,
        lies closer than ``sqrt(max_sq_dist)`` (its distance squared, as there), that point's row (int64)). The
        shells of cells go out as far as the radius needs, for any cell size."""
        if self._grid is None or queries.dtype != _F32 or queries.ndim != 2:
            distance, nearest = self.tree.query(queries[:, :3].astype(np.float64), k=1)
            near = np.flatnonzero(distance.astype(np.float64) ** 2 < max_sq_dist)
            return near, nearest[near]
        queries = np.ascontiguousarray(queries)
        status, index = np.empty(len(queries), np.uint8), np.empty(len(queries), np.int64)
        max_shell = math.ceil(_search_bound(max_sq_dist) / self._grid[0]) + 1
        _geometry_kernels.grid_nearest_one(
            *self._grid, queries, queries.shape[1], max_shell, max_sq_dist, status, index
        )
        tied = np.flatnonzero(status == 2)
        if len(tied):  # two at the nearest distance: the kd-tree's choice
            distance, nearest = self.tree.query(queries[tied, :3].astype(np.float64), k=1)
            status[tied] = distance.astype(np.float64) ** 2 < max_sq_dist
            index[tied] = nearest
        near = np.flatnonzero(status)
        return near, index[near]


def pairs_within(xy: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of the (n, 2) points ``xy`` [m] within ``radius`` [m] of each other, as ``cKDTree(xy).query_pairs``
    finds them (the same set: dx^2 + dy^2 <= radius^2), each once as (i, j) with i < j: (first, second) int64. On a
    grid of the radius in C (``native/geometry_kernels.c``), ordered by first; by cKDTree without the extension or
    for points the grid cannot hold."""
    xy = np.asarray(xy)
    if _geometry_kernels is not None and xy.dtype == np.float64 and xy.ndim == 2 and xy.shape[1] == 2 and radius > 0:
        xy = np.ascontiguousarray(xy)
        capacity = 32 * len(xy) + 16
        while True:
            first, second = np.empty(capacity, np.int64), np.empty(capacity, np.int64)
            count = _geometry_kernels.pairs_within(xy, float(radius), first, second)
            if count < 0 or count <= capacity:
                break
            capacity = count  # (more pairs than room: once more with room for all)
        if count >= 0:
            return first[:count], second[:count]
    from scipy.spatial import cKDTree

    found = cKDTree(xy).query_pairs(radius, output_type='ndarray')
    return found[:, 0].astype(np.int64), found[:, 1].astype(np.int64)


def _search_bound(max_sq_dist: float) -> float:
    """The radius [m] a search for neighbours within ``sqrt(max_sq_dist)`` stops at (see nearest_within)."""
    return math.sqrt(max_sq_dist) * (1.0 + 1e-9)


def fit_planes(neighbours: np.ndarray, max_residual: float, min_aspect: float = 0.0):
    """Least-squares planes ``n · x + offset = 0`` through (m, k, 3) float64 neighbourhoods: (indices of the
    neighbourhoods whose every point lies within ``max_residual`` [m] of their plane, and, with ``min_aspect``
    > 0, that spread across their main direction at least that fraction of their spread along it (see
    :func:`principal_spreads`), unit normals (j, 3), offsets (j,)).

    The plane is fitted as ``n · x = -1`` through the normal equations ``(A^T A) n = -A^T 1``, solved in closed
    form (Cramer's rule on the symmetric 3x3 systems, vectorised); it cannot pass through the origin, which
    the sensor never sees.
    """
    xx, yy, zz = (np.einsum('mk,mk->m', neighbours[..., i], neighbours[..., i]) for i in range(3))
    xy = np.einsum('mk,mk->m', neighbours[..., 0], neighbours[..., 1])
    xz = np.einsum('mk,mk->m', neighbours[..., 0], neighbours[..., 2])
    yz = np.einsum('mk,mk->m', neighbours[..., 1], neighbours[..., 2])
    b = -neighbours.sum(axis=1)
    c00, c01, c02 = yy * zz - yz * yz, xz * yz - xy * zz, xy * yz - xz * yy
    c11, c12, c22 = xx * zz - xz * xz, xy * xz - xx * yz, xx * yy - xy * xy
    det = xx * c00 + xy * c01 + xz * c02
    solvable = np.flatnonzero(np.abs(det) > 1e-12)
    with np.errstate(divide='ignore', invalid='ignore'):
        normal = (
            np.stack(
                [
                    c00 * b[:, 0] + c01 * b[:, 1] + c02 * b[:, 2],
                    c01 * b[:, 0] + c11 * b[:, 1] + c12 * b[:, 2],
                    c02 * b[:, 0] + c12 * b[:, 1] + c22 * b[:, 2],
                ],
                axis=1,
            )
            / det[:, None]
        )
    neighbours, normal = neighbours[solvable], normal[solvable]
    norm = np.linalg.norm(normal, axis=1)
    with np.errstate(divide='ignore', invalid='ignore'):  # (a zero normal: NaN residuals, no plane)
        normal /= norm[:, None]
        offset = 1.0 / norm
        residuals = np.abs(np.einsum('mki,mi->mk', neighbours, normal) + offset[:, None])
    valid = (residuals <= max_residual).all(axis=1)
    if min_aspect > 0.0:  # (from the sums above; solvable rows only)
        k = neighbours.shape[1]
        along, across = _principal_spreads(-b[solvable] / k, *(m[solvable] / k for m in (xx, yy, zz, xy, xz, yz)))
        valid &= across >= min_aspect * along
    return solvable[valid], normal[valid], offset[valid]


def fit_planes_at(
    points: np.ndarray, index: np.ndarray, max_residual: float, min_aspect: float = 0.0, native: bool = True
):
    """:func:`fit_planes` of the neighbourhoods ``points[index, :3]`` ((n, >= 3) points [m], (m, k) indices into
    them), the same values bit for bit: in one C pass over the neighbours (``native/geometry_kernels.c``) when
    it is built and the points are float32, without the (m, k, 3) float64 copy; else by :func:`fit_planes`."""
    index = np.asarray(index)
    if not _neighbourhoods_in_c(points, index, native):
        return fit_planes(points[index, :3].astype(np.float64), max_residual, min_aspect)
    m, k = index.shape
    normal, offset = np.empty((m, 3)), np.empty(m)
    moments, status = np.empty((m, 9)), np.empty(m, dtype=np.uint8)
    _geometry_kernels.plane_fits(
        np.ascontiguousarray(points),
        points.shape[1],
        np.ascontiguousarray(index, dtype=np.int64),
        k,
        float(max_residual),
        normal,
        offset,
        moments,
        status,
    )
    undecided = np.flatnonzero(status == 2)
    if len(undecided):  # a distance within 1e-9 m of the bound: NumPy's own sum decides, as in fit_planes
        near = points[index[undecided], :3].astype(np.float64)
        residuals = np.abs(np.einsum('mki,mi->mk', near, normal[undecided]) + offset[undecided, None])
        status[undecided] = (residuals <= max_residual).all(axis=1)
    rows = np.flatnonzero(status)
    if min_aspect > 0.0:  # (element by element: the same values on these rows as on all solvable ones)
        xx, yy, zz, xy, xz, yz = (moments[rows, i] / k for i in range(6))
        along, across = _principal_spreads(select_rows(moments, rows)[:, 6:] / k, xx, yy, zz, xy, xz, yz)
        rows = rows[across >= min_aspect * along]
    return rows, select_rows(normal, rows), offset[rows]


def line_fits_at(points: np.ndarray, index: np.ndarray, eigen_ratio: float, native: bool = True):
    """The neighbourhoods ``points[index, :3]`` ((n, >= 3) points [m], (m, k) indices into them) that lie along a
    line: (their indices (j,), centroids (j, 3) [m], unit directions (j, 3), each with an arbitrary sign), a
    neighbourhood's largest covariance eigenvalue exceeding ``eigen_ratio`` times its middle one.

    In one C pass over the neighbours (``native/geometry_kernels.c``, its own 3x3 eigen decomposition) when it is
    built and the points are float32, without the (m, k, 3) float64 copy: the centroids bit for bit, the
    directions LAPACK's to rounding; else with NumPy (``np.linalg.eigh``, some 1.2 us a neighbourhood)."""
    index = np.asarray(index)
    if not _neighbourhoods_in_c(points, index, native):
        neighbours = select_rows(points, index)[..., :3].astype(np.float64)
        centroid = neighbours.mean(axis=1)
        centred = neighbours - centroid[:, None, :]
        values, vectors = np.linalg.eigh(np.einsum('mki,mkj->mij', centred, centred) / index.shape[1])  # ascending
        rows = np.flatnonzero(values[:, 2] > eigen_ratio * values[:, 1])
        return rows, centroid[rows], vectors[rows, :, 2]
    m, k = index.shape
    centroid, direction, status = np.empty((m, 3)), np.empty((m, 3)), np.empty(m, dtype=np.uint8)
    _geometry_kernels.line_fits(
        np.ascontiguousarray(points),
        points.shape[1],
        np.ascontiguousarray(index, dtype=np.int64),
        k,
        float(eigen_ratio),
        centroid,
        direction,
        status,
    )
    rows = np.flatnonzero(status)
    return rows, select_rows(centroid, rows), select_rows(direction, rows)


def _neighbourhoods_in_c(points: np.ndarray, index: np.ndarray, native: bool) -> bool:
    """Whether the C kernels of :func:`fit_planes_at` and :func:`line_fits_at` take these neighbourhoods: the
    extension is built (and asked for), the points are (n, >= 3) float32 and there is at least one (m, k) row."""
    return (
        native
        and _geometry_kernels is not None
        and points.dtype == _F32
        and points.ndim == 2
        and points.shape[1] >= 3
        and index.ndim == 2
        and len(index) > 0
    )


def principal_spreads(neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RMS spreads [m] of each (m, k, 3) neighbourhood along its first and second principal directions (the
    square roots of the largest and middle eigenvalues of its covariance). Points along a line, such as the
    nearest points of one lidar ring, spread along it only: any plane about the line fits them."""
    k = neighbours.shape[1]
    moments = [
        np.einsum('mk,mk->m', neighbours[..., i], neighbours[..., j]) / k
        for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
    ]
    return _principal_spreads(neighbours.sum(axis=1) / k, *moments)


def _principal_spreads(mean, xx, yy, zz, xy, xz, yz) -> tuple[np.ndarray, np.ndarray]:
    """:func:`principal_spreads` from the mean (m, 3) and the raw second moments (each (m,), divided by k), by
    the closed form for the eigenvalues of symmetric 3x3 matrices, vectorised."""
    mx, my, mz = mean[:, 0], mean[:, 1], mean[:, 2]
    a, b, c = xx - mx * mx, yy - my * my, zz - mz * mz
    e, f, g = xy - mx * my, xz - mx * mz, yz - my * mz
    q = (a + b + c) / 3.0
    p = np.sqrt(np.maximum(((a - q) ** 2 + (b - q) ** 2 + (c - q) ** 2 + 2.0 * (e * e + f * f + g * g)) / 6.0, 0.0))
    safe = np.where(p > 1e-12, p, 1.0)
    a, b, c, e, f, g = (a - q) / safe, (b - q) / safe, (c - q) / safe, e / safe, f / safe, g / safe
    det = a * (b * c - g * g) - e * (e * c - g * f) + f * (e * g - b * f)
    phi = np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0
    largest = np.where(p > 1e-12, q + 2.0 * p * np.cos(phi), q)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    middle = np.where(p > 1e-12, 3.0 * q - largest - smallest, q)
    return np.sqrt(np.maximum(largest, 0.0)), np.sqrt(np.maximum(middle, 0.0))


def line_offsets(p: np.ndarray, anchor: np.ndarray, along: np.ndarray) -> np.ndarray:
    """(n, 3) perpendicular offsets of points from the lines through ``anchor`` with unit direction ``along``."""
    d = p - anchor
    return d - np.einsum('ni,ni->n', d, along)[:, None] * along


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays, the same operations as ``np.cross`` without its overhead."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def line_coefficients(p: np.ndarray, a: np.ndarray, b: np.ndarray):
    """Unit direction (n, 3) from the line through a, b towards p, and the distance (n,) (float32)."""
    p, a, b = (v[:, :3].astype(_F32) for v in (p, a, b))
    pa, pb, ab = p - a, p - b, a - b
    # Cross product (p - a) x (p - b): its norm is twice the triangle area.
    cross = cross_rows(pa, pb)
    area = np.linalg.norm(cross, axis=1)
    length = np.linalg.norm(ab, axis=1)
    with np.errstate(invalid='ignore', divide='ignore'):
        # The gradient of the distance w.r.t. p: (a - b) x (pa x pb) / (|pa x pb| |a - b|).
        gradient = cross_rows(ab, cross) / (area * length)[:, None]
        distance = area / length
    return gradient.astype(_F32), distance.astype(_F32)


# ----------------------------------------------------------------------------------------- the solver


# Below this 1 - (correlation of u and v)², the two are too nearly dependent for the closed form: lstsq decides.
_AFFINE_MIN_INDEPENDENCE = 1e-10


def affine_fit(u: np.ndarray, v: np.ndarray, z: np.ndarray) -> tuple[float, float, float]:
    """Least-squares ``(c_u, c_v, c_0)`` of ``z ≈ c_u u + c_v v + c_0`` over float64 samples (n >= 3; units of z
    per unit of u and v, and of z).

    Solved on the centred samples by Cramer's rule on the 2x2 normal equations: the same solution as
    ``np.linalg.lstsq`` of ``[u, v, 1]`` to within a few units of the last place on well-spread samples (centring
    keeps the system's condition that of the samples' spread, not of their distance from the origin), in a tenth
    of its time on thousands of samples. Nearly collinear ``u`` and ``v`` go to lstsq (its minimum-norm answer).
    """
    mean_u, mean_v, mean_z = u.mean(), v.mean(), z.mean()
    du, dv, dz = u - mean_u, v - mean_v, z - mean_z
    suu, svv, suv = float(du @ du), float(dv @ dv), float(du @ dv)
    determinant = suu * svv - suv * suv
    if not determinant > _AFFINE_MIN_INDEPENDENCE * suu * svv:
        design = np.stack([u, v, np.ones(len(u))], axis=1)
        c_u, c_v, c_0 = np.linalg.lstsq(design, z, rcond=None)[0]
        return float(c_u), float(c_v), float(c_0)
    suz, svz = float(du @ dz), float(dv @ dz)
    c_u = (suz * svv - svz * suv) / determinant
    c_v = (svz * suu - suz * suv) / determinant
    return c_u, c_v, float(mean_z) - c_u * float(mean_u) - c_v * float(mean_v)
