"""imageProjection: range image, ground removal and segmentation (docs/original.md §3, §6.1, §8).

Everything is vectorised over points and pixels. The arithmetic follows the C++ original step by step,
in float32 where it uses floats and with libm's ``atan2f`` (see :mod:`lego_loam_py.core.libm`), so on the
same input the clouds and CloudInfo arrays equal the original's point for point. libm's atan2f is slow, so
:func:`_of_atan2f` calls it only for the few angles whose last bits decide a column, a ground pair or a join.

The breadth-first segmentation of the original is computed as connected components of the graph whose
nodes are the non-ground, non-empty pixels and whose edges join 4-neighbours (columns wrap around) that
satisfy the angle criterion β > segment_theta. The criterion is symmetric in the two pixels, so components
equal the BFS's clusters; labels are numbered as the BFS numbers them (by the row-major index of each
cluster's first pixel, invalid clusters consuming no number). The components are found on a smaller graph
with the same connectivity: the vertically joined runs of each column are its nodes.

Frames: every input and output point is in the sensor frame (REP-103 lidar axes, ``base_link``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from lego_loam_py.core.libm import atan2f, cosf, sinf
from lego_loam_py.core.params import Params
from lego_loam_py.core.validation import MAX_COORDINATE
from lego_loam_py.errors import LegoLoamError

__all__ = ['CloudInfo', 'SegmentationResult', 'ImageProjection', 'ProjectionInput', 'OUTLIER_LABEL',
           'NO_LABEL', 'prepare_input', 'InputError']

OUTLIER_LABEL = 999999   # the original's label of points in clusters that are too small
NO_LABEL = -1            # ground or empty pixel (labelMat == -1)
_F32 = np.float32


class InputError(LegoLoamError, ValueError):
    """The cloud cannot be projected at all (no x/y/z, no valid point)."""


@dataclass
class CloudInfo:
    """Content of cloud_msgs/CloudInfo for one scan. Arrays are as long as the segmented cloud."""

    start_ring_index: np.ndarray       # int32 (N_SCAN,)
    end_ring_index: np.ndarray         # int32 (N_SCAN,)
    start_orientation: np.float32      # [rad]
    end_orientation: np.float32        # [rad]
    orientation_diff: np.float32       # [rad]
    segmented_cloud_ground_flag: np.ndarray  # bool (M,)
    segmented_cloud_col_ind: np.ndarray      # uint32 (M,)
    segmented_cloud_range: np.ndarray        # float32 (M,) [m]


@dataclass
class ProjectionInput:
    """Valid points of one cloud, in message order: sensor-frame coordinates and optional ring."""

    xyz: np.ndarray               # float32 (n, 3) [m], all finite
    ring: np.ndarray | None       # int64 (n,) or None (rows from the elevation angle)
    dropped_non_finite: int = 0   # points removed because x, y or z was NaN/inf or beyond MAX_COORDINATE
    time: np.ndarray | None = None  # float32 (n,) [s since the sweep start] when the cloud has it
    source_index: np.ndarray | None = None  # index in the message of each kept point (None: all were kept)


@dataclass
class SegmentationResult:
    """What imageProjection publishes for one scan; clouds are float32 (k, 4) = x, y, z, intensity."""

    segmented_cloud: np.ndarray       # intensity = row + col / 10000
    cloud_info: CloudInfo
    outlier_cloud: np.ndarray         # intensity = row + col / 10000
    ground_cloud: np.ndarray          # intensity = row + col / 10000
    segmented_cloud_pure: np.ndarray  # intensity = segment label (1, 2, ...)
    full_cloud: np.ndarray            # (N_SCAN*H, 4) row-major range image; empty cells NaN, intensity -1
    full_info_cloud: np.ndarray       # same cells, intensity = range [m]
    range_image: np.ndarray           # float32 (N_SCAN, H) [m], FLT_MAX where empty
    ground_mask: np.ndarray           # bool (N_SCAN, H)
    label_image: np.ndarray           # int32 (N_SCAN, H): -1 ground/empty, 999999 outlier, >= 1 segment
    stats: dict = field(default_factory=dict)
    segmented_time: np.ndarray | None = None  # float32 (M,) per-point time of the segmented cloud [s]
    pixel_point: np.ndarray | None = None     # int64 (N_SCAN*H,): index of the input point in each pixel, -1 empty


def prepare_input(points: np.ndarray, params: Params) -> ProjectionInput:
    """Valid (finite) points of a structured cloud, with the ring field when it exists and is used.

    Mirrors the original's ``removeNaNFromPointCloud``; inf is dropped as well, and so are coordinates
    beyond ``MAX_COORDINATE`` (10 km: no lidar measures that; such values would overflow float32 squares).
    Unlike the original, which shuts down on a non-dense cloud in ring mode, the ring is filtered together
    with the coordinates.
    """
    names = points.dtype.names or ()
    missing = [n for n in 'xyz' if n not in names]
    if missing:
        raise InputError(f'the cloud has no {"/".join(missing)} field (fields: {", ".join(names) or "none"})')
    used = ['x', 'y', 'z'] + ([params.sensor.ring_field] if params.sensor.use_cloud_ring and
                              params.sensor.ring_field in names else [])
    several = [n for n in used if points.dtype[n].shape != ()]
    if several:
        raise InputError(f'field(s) {", ".join(several)} hold several values per point (count > 1)')
    flat = points.reshape(-1)
    xyz = np.empty((flat.size, 3), dtype=_F32)
    with np.errstate(invalid='ignore', over='ignore'):
        xyz[:, 0], xyz[:, 1], xyz[:, 2] = flat['x'], flat['y'], flat['z']
    finite = np.isfinite(xyz).all(axis=1) & (np.abs(xyz) <= MAX_COORDINATE).all(axis=1)
    ring = None
    ring_field = params.sensor.ring_field
    if params.sensor.use_cloud_ring and ring_field in names:
        ring = flat[ring_field]
        if ring.dtype.kind == 'f':
            finite &= np.isfinite(ring)
            ring = np.where(finite, ring, 0)
        ring = ring.astype(np.int64)
    time = None
    time_field = params.sensor.time_field
    if time_field and time_field in names and flat[time_field].ndim == 1:
        time = flat[time_field].astype(_F32)
        if time_field == 't' and np.issubdtype(flat[time_field].dtype, np.integer):
            time = (flat[time_field] * 1e-9).astype(_F32)  # Ouster: ns since the scan start
        finite &= np.isfinite(time)
    dropped = int(flat.size - np.count_nonzero(finite))
    if dropped:
        xyz = xyz[finite]
        ring = ring[finite] if ring is not None else None
        time = time[finite] if time is not None else None
    return ProjectionInput(xyz=xyz, ring=ring, dropped_non_finite=dropped, time=time,
                           source_index=np.flatnonzero(finite) if dropped else None)


class ImageProjection:
    """The imageProjection algorithm for one sensor configuration; :meth:`process` handles one scan."""

    def __init__(self, params: Params):
        self.params = params
        s = params.sensor
        self.n_scan = s.n_scan
        self.horizon_scan = s.horizon_scan
        # The original's float constants.
        self._ang_res_x = _F32(s.ang_res_x)
        self._ang_res_y = _F32(s.ang_res_y)
        self._ang_bottom = _F32(s.ang_bottom)
        self._min_range = _F32(s.sensor_minimum_range)
        self._mount_angle = _F32(s.sensor_mount_angle)
        alpha_x = _F32(s.ang_res_x / 180.0 * math.pi)
        alpha_y = _F32(s.ang_res_y / 180.0 * math.pi)
        self._sin_alpha = (sinf(alpha_x), sinf(alpha_y))
        self._cos_alpha = (cosf(alpha_x), cosf(alpha_y))
        self._theta = _F32(params.image_projection.segment_theta)
        self._slope_threshold = _F32(params.image_projection.ground_slope_threshold)
        # Per-pixel constants of the range image (row-major pixel indices).
        n, h = self.n_scan, self.horizon_scan
        ip, g = params.image_projection, s.ground_scan_ind
        self._rows = np.repeat(np.arange(n), h)
        self._cols = np.tile(np.arange(h), n)
        self._pixel_intensity = (self._rows + self._cols / 10000.0).astype(_F32)
        cols = self._cols
        self._ground_kept_column = ((cols % ip.ground_column_stride == 0) | (cols <= ip.ground_edge_columns) |
                                    (cols >= h - ip.ground_edge_columns))
        self._outlier_kept_pixel = (self._rows > g) & (cols % ip.outlier_column_stride == 0)
        self._ground_row_pixel = self._rows <= g

    # ------------------------------------------------------------------------------------ projection
    def orientation(self, xyz: np.ndarray) -> tuple[np.float32, np.float32, np.float32]:
        """(start, end, diff) orientation [rad] from the first and last point, as the original computes it."""
        a = atan2f(xyz[[0, -1], 1], xyz[[0, -1], 0])
        start = _F32(-a[0])
        end = _F32(float(-a[1]) + 2 * math.pi)
        if float(_F32(end - start)) > 3 * math.pi:
            end = _F32(float(end) - 2 * math.pi)
        elif float(_F32(end - start)) < math.pi:
            end = _F32(float(end) + 2 * math.pi)
        return start, end, _F32(end - start)

    def rows_and_columns(self, data: ProjectionInput) -> tuple[np.ndarray, np.ndarray]:
        """Range-image row and column of every point (int64; -1 where outside the image)."""
        x, y, z = data.xyz[:, 0], data.xyz[:, 1], data.xyz[:, 2]
        if data.ring is not None:
            row = data.ring.copy()
        else:
            row = _of_atan2f(z, np.sqrt(x * x + y * y), self._row_of_elevation).astype(np.int64)
        row[(row < 0) | (row >= self.n_scan)] = -1
        col = _of_atan2f(x, y, self._column_of_azimuth).astype(np.int64)
        col[col >= self.horizon_scan] -= self.horizon_scan
        col[(col < 0) | (col >= self.horizon_scan)] = -1
        return row, col

    def _row_of_elevation(self, vertical: np.ndarray) -> np.ndarray:
        """Row (float; -1 below the image) of elevation angles [rad], monotone in the angle."""
        value = (_deg(vertical) + self._ang_bottom) / self._ang_res_y
        # C++ converts to size_t: truncation toward zero; below -1 wraps to a huge value (dropped).
        return np.where(value > -1, np.trunc(value), -1)

    def _column_of_azimuth(self, azimuth: np.ndarray) -> np.ndarray:
        """Column (float, before wrapping into the image) of atan2(x, y) angles [rad], monotone in the angle."""
        value = _deg(azimuth).astype(np.float64)
        value -= 90.0
        value /= np.float64(self._ang_res_x)
        return (self.horizon_scan // 2) - _round_half_away(value)

    def process(self, data: ProjectionInput) -> SegmentationResult:
        """Project, remove ground, segment and assemble the published clouds for one scan."""
        if data.xyz.shape[0] == 0:
            raise InputError('the cloud has no valid point')
        n, h = self.n_scan, self.horizon_scan
        xyz = data.xyz
        x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        start, end, diff = self.orientation(xyz)
        row, col = self.rows_and_columns(data)
        rng = np.sqrt(x * x + y * y + z * z)  # float32, as sqrt(x*x + y*y + z*z) on floats
        keep = (row >= 0) & (col >= 0) & (rng >= self._min_range)
        pixel_of_point = (col + row * h)[keep]
        kept = np.flatnonzero(keep)
        # Later points overwrite earlier ones in the same pixel: the largest point index wins.
        winner_of_pixel = np.full(n * h, -1, dtype=np.int64)
        np.maximum.at(winner_of_pixel, pixel_of_point, kept)
        filled = winner_of_pixel >= 0
        self._winner_of_pixel = winner_of_pixel

        # Every per-pixel image is one row gather from a per-point table whose extra last row (index -1)
        # holds the empty pixel's values; np.take is ~10x faster than fancy indexing on 2-D rows.
        table = np.empty((len(xyz) + 1, 4), dtype=_F32)
        for axis in range(3):   # column by column: ~3x faster than one (n, 3) -> (n, 4) strided copy
            table[:-1, axis] = xyz[:, axis]
        table[:-1, 3] = rng
        table[-1] = (np.nan, np.nan, np.nan, np.finfo(np.float32).max)
        full_info = np.take(table, winner_of_pixel, axis=0)
        range_image = full_info[:, 3].copy()
        full_info[:, 3] = np.where(filled, range_image, _F32(-1.0))
        full = full_info.copy()
        full[:, 3] = np.where(filled, self._pixel_intensity, _F32(-1.0))
        self._time_image = None
        if data.time is not None:
            self._time_image = np.append(data.time.astype(_F32, copy=False), _F32(0.0))[winner_of_pixel]

        ground = self.ground(full, filled)
        labels = self.segment(range_image, filled, ground)
        return self._assemble(full, full_info, range_image, filled, ground, labels, start, end, diff, data,
                              dropped_outside=int(np.count_nonzero((row < 0) | (col < 0))),
                              dropped_close=int(np.count_nonzero((row >= 0) & (col >= 0) & ~keep)),
                              overwritten=int(len(kept) - np.count_nonzero(filled)))

    # ------------------------------------------------------------------------------------- ground
    def ground(self, full: np.ndarray, filled: np.ndarray) -> np.ndarray:
        """Ground pixels (the original's groundMat == 1) as a boolean (N_SCAN*H,) mask.

        ``full`` is the (N_SCAN*H, 4) projected cloud, ``filled`` marks non-empty pixels. Pairs of vertically
        adjacent pixels in rows 0..ground_scan_ind are ground when their slope is within the threshold of
        the mount angle; the original's write order is kept (a later empty pair un-marks row i+1).
        """
        n, h = self.n_scan, self.horizon_scan
        g = self.params.sensor.ground_scan_ind
        p = full.reshape(n, h, 4)
        f = filled.reshape(n, h)
        lower, upper = p[:g], p[1:g + 1]
        empty_pair = ~(f[:g] & f[1:g + 1])
        with np.errstate(invalid='ignore'):
            dx = upper[..., 0] - lower[..., 0]
            dy = upper[..., 1] - lower[..., 1]
            dz = upper[..., 2] - lower[..., 2]
            slope_ok = _of_atan2f(dz, np.sqrt(dx * dx + dy * dy), self._slope_band) == 1
        ground_pair = ~empty_pair & slope_ok
        # Iteration i writes row i (-1 if the pair has an empty pixel, 1 if ground) and row i+1 (1 if
        # ground); iteration i+1 runs later and may overwrite row i+1 with -1.
        mat = np.zeros((n, h), dtype=np.int8)
        mat[1:g + 1][ground_pair] = 1
        rows_i = mat[:g]
        rows_i[ground_pair] = 1
        rows_i[empty_pair] = -1
        ground = mat == 1
        if self.params.image_projection.ground_rule == 'refined':
            ground = self._refine_ground(p, f, ground)
        return ground.reshape(-1)

    def _slope_band(self, angle: np.ndarray) -> np.ndarray:
        """0 / 1 / 2 where the pair slope [rad] is below / within / above the ground band around the mount
        angle. Band 1 is the original's |deg(angle) - mount| <= threshold; the band index, unlike that test,
        is monotone in the angle (as :func:`_of_atan2f` needs)."""
        off = _deg(angle) - self._mount_angle
        return (off >= -self._slope_threshold).astype(np.int8) + (off > self._slope_threshold)

    def _refine_ground(self, p: np.ndarray, f: np.ndarray, ground: np.ndarray) -> np.ndarray:
        """Remove from the original's ground what a pair test over a 2-degree gap cannot see.

        * A pixel that forms a vertical pair with the pixel above or below it (height step > ratio x horizontal
          gap, gap < a fraction of the range) lies on a vertical surface: the first ring on a wall's base or a
          car's side pairs with distant ground at a shallow slope, and the original marks it ground.
        * Candidates within the plane radius, and the first candidate of every column wherever it lies, must
          lie within max(tolerance, ratio x range) of a plane fitted (least squares, refitted without the
          rejects, three rounds) to the candidates within that radius: car hoods and roofs, benches.
        * Each column is walked upward from the lowest ring: every candidate after the column's first must
          continue the column's last accepted ground point, a height change of at most tan(chain slope) x the
          horizontal gap + the chain tolerance. Raised surfaces far out break that chain, while ground that
          bends away from any single plane, as a forest's uneven terrain does, continues it. (A plane fitted
          to the whole scan instead dropped up to 77 % of the ground of single forest scans.)
        """
        ip = self.params.image_projection
        g = self.params.sensor.ground_scan_ind
        top = min(g + 2, self.n_scan)
        # Contiguous coordinate planes of the rows that can hold ground (strided (n, h, 4) views are slow).
        x, y, z = (np.ascontiguousarray(p[:top, :, axis]) for axis in range(3))
        both = f[:top - 1] & f[1:top]
        with np.errstate(invalid='ignore'):
            gap = np.hypot(x[1:] - x[:-1], y[1:] - y[:-1])
            rise = np.abs(z[1:] - z[:-1])
            reach = np.hypot(x[:-1], y[:-1])
            vertical = both & (rise > ip.ground_vertical_ratio * gap) & (gap < ip.ground_vertical_gap * reach)
        ground = ground.copy()
        ground[:top - 1] &= ~vertical
        ground[1:top] &= ~vertical
        pixels = np.flatnonzero(ground)
        if len(pixels) < 10:
            return ground
        # Ground lies in rows < top only: the planes hold every candidate.
        x, y, z = x.astype(np.float64), y.astype(np.float64), z.astype(np.float64)
        ground_x, ground_y, ground_z = (plane.reshape(-1)[pixels] for plane in (x, y, z))
        reach = np.hypot(ground_x, ground_y)
        tolerance = np.maximum(ip.ground_plane_tolerance, ip.ground_plane_tolerance_ratio * reach)
        near = reach <= ip.ground_plane_radius
        fit_near = near.sum() >= 10
        keep = near if fit_near else np.ones(len(pixels), dtype=bool)
        design = np.empty((len(pixels), 3))
        design[:, 0], design[:, 1], design[:, 2] = ground_x, ground_y, 1.0
        for _ in range(3):
            if keep.sum() < 3:
                break
            # np.compress: the same rows as design[keep], several times faster on a 2-D array.
            coef, *_ = np.linalg.lstsq(np.compress(keep, design, axis=0), ground_z[keep], rcond=None)
            refit = (np.abs(ground_z - design @ coef) <= tolerance) & (near if fit_near else True)
            if np.array_equal(refit, keep):
                break   # the same points give the same plane again: the remaining rounds change nothing
            keep = refit
        on_plane = np.zeros(top * self.horizon_scan, dtype=bool)
        on_plane[pixels] = np.abs(ground_z - design @ coef) <= tolerance
        far = np.ones(top * self.horizon_scan, dtype=bool)
        far[pixels] = ~near
        on_plane, far = on_plane.reshape(top, -1), far.reshape(top, -1)
        # The walk up the columns: a loop over the few ground rows, vectorised over the columns.
        slope = math.tan(math.radians(ip.ground_chain_slope))
        last_x, last_y, last_z = (np.full(self.horizon_scan, np.nan) for _ in range(3))
        seeded = np.zeros(self.horizon_scan, dtype=bool)
        for r in range(top):
            candidate = ground[r]
            if not candidate.any():
                continue
            with np.errstate(invalid='ignore'):
                step = np.hypot(x[r] - last_x, y[r] - last_y)
                # Unseeded columns have a NaN last point: no continuation is needed there.
                continues = (np.abs(z[r] - last_z) <= slope * step + ip.ground_chain_tolerance) | ~seeded
            accepted = candidate & continues & (on_plane[r] | (seeded & far[r]))
            ground[r] = accepted
            for last, now in ((last_x, x[r]), (last_y, y[r]), (last_z, z[r])):
                np.copyto(last, now, where=accepted)
            seeded |= accepted
        return ground

    # ------------------------------------------------------------------------------- segmentation
    def segment(self, range_image: np.ndarray, filled: np.ndarray, ground: np.ndarray) -> np.ndarray:
        """The original's labelMat as int32 (N_SCAN*H,): -1 ground or empty, 999999 pixels of clusters that
        are too small, 1, 2, ... valid segments numbered in the BFS's order.

        ``range_image`` is (N_SCAN*H,) float32 [m], ``filled`` marks non-empty pixels, ``ground`` the ground.
        """
        n, h = self.n_scan, self.horizon_scan
        ip = self.params.image_projection
        candidate = filled & ~ground
        if not candidate.any():
            return np.full(n * h, NO_LABEL, dtype=np.int32)
        # Work in column-major order, (h, n): a column's pixels bottom to top, then the next column.
        # Vertical joins chain the pixels of a column into runs (poles and walls give long ones, while the
        # horizontal criterion often fails on surfaces seen obliquely); the graph's nodes are these runs and
        # its edges the horizontal joins: a quarter of the pixels' nodes and edges, so the components cost
        # much less.
        node = np.ascontiguousarray(candidate.reshape(n, h).T)
        depth = np.ascontiguousarray(range_image.reshape(n, h).T)
        joined_up = np.zeros((h, n), dtype=bool)   # joined to the pixel above (row n-1 has none)
        joined_up[:, :-1] = node[:, :-1] & node[:, 1:] & self._joins(depth[:, :-1], depth[:, 1:], 1)
        depth_right = np.roll(depth, -1, axis=0)   # columns wrap around
        joined_right = node & np.roll(node, -1, axis=0) & self._joins(depth, depth_right, 0)
        node, joined_up = node.reshape(-1), joined_up.reshape(-1)

        joined_below = np.zeros(n * h, dtype=bool)
        joined_below[1:] = joined_up[:-1]
        starts_run = node & ~joined_below
        first = np.flatnonzero(starts_run)   # runs are ranges of the column-major order
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
        indptr = np.zeros(runs + 1, dtype=np.int32)
        np.cumsum(np.bincount(lower, minlength=runs), out=indptr[1:])
        graph = csr_matrix((np.ones(len(upper)), upper, indptr), shape=(runs, runs))
        count, component_of_run = connected_components(graph, directed=False)

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
        labels = np.where(node, number[component_of_run][run_of_pixel], np.int32(NO_LABEL))
        return labels.reshape(h, n).T.reshape(-1)

    def _joins(self, range_a: np.ndarray, range_b: np.ndarray, direction: int) -> np.ndarray:
        """The segmentation criterion beta > theta for neighbour pairs (direction 0: horizontal, 1: vertical).

        Computed for every pixel, pair or not (empty pixels' FLT_MAX ranges give finite angles far from theta):
        cheaper than gathering the pairs.
        """
        d1, d2 = np.maximum(range_a, range_b), np.minimum(range_a, range_b)
        return _of_atan2f(d2 * self._sin_alpha[direction], d1 - d2 * self._cos_alpha[direction],
                          self._beyond_theta)

    def _beyond_theta(self, beta: np.ndarray) -> np.ndarray:
        """beta [rad] > segment_theta: the pair lies on one object."""
        return beta > self._theta

    # --------------------------------------------------------------------------------- assembling
    def _assemble(self, full, full_info, range_image, filled, ground, labels, start, end, diff, data,
                  **stats) -> SegmentationResult:
        n, h = self.n_scan, self.horizon_scan
        # Pixels in row-major order, as the original walks them.
        outlier = labels == OUTLIER_LABEL
        in_segment = (labels > 0) & ~outlier
        segmented = in_segment | (ground & self._ground_kept_column)
        segmented_index = np.flatnonzero(segmented)
        outlier_index = np.flatnonzero(outlier & self._outlier_kept_pixel)

        count_before_row = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.count_nonzero(segmented.reshape(n, h), axis=1), out=count_before_row[1:])
        margin = self.params.image_projection.ring_index_margin
        start_ring = (count_before_row[:-1] - 1 + margin).astype(np.int32)
        end_ring = (count_before_row[1:] - 1 - margin).astype(np.int32)

        info = CloudInfo(
            start_ring_index=start_ring, end_ring_index=end_ring,
            start_orientation=start, end_orientation=end, orientation_diff=diff,
            segmented_cloud_ground_flag=ground[segmented_index],
            segmented_cloud_col_ind=self._cols[segmented_index].astype(np.uint32),
            segmented_cloud_range=range_image[segmented_index])
        ground_index = np.flatnonzero(ground & self._ground_row_pixel)
        pure_index = np.flatnonzero(in_segment)
        pure = np.take(full, pure_index, axis=0)
        pure_labels = labels[pure_index]
        pure[:, 3] = pure_labels
        stats.update(
            input_points=int(data.xyz.shape[0] + data.dropped_non_finite),
            non_finite=data.dropped_non_finite, projected=int(np.count_nonzero(filled)),
            ground=int(np.count_nonzero(ground)), segments=int(pure_labels.max(initial=0)),
            segmented=len(segmented_index), outliers=len(outlier_index))
        segmented_time = self._time_image[segmented_index] if self._time_image is not None else None
        return SegmentationResult(
            segmented_time=segmented_time, pixel_point=self._winner_of_pixel,
            segmented_cloud=np.take(full, segmented_index, axis=0), cloud_info=info,
            outlier_cloud=np.take(full, outlier_index, axis=0), ground_cloud=np.take(full, ground_index, axis=0),
            segmented_cloud_pure=pure, full_cloud=full, full_info_cloud=full_info,
            range_image=range_image.reshape(n, h), ground_mask=ground.reshape(n, h),
            label_image=labels.reshape(n, h), stats=stats)


def _of_atan2f(y: np.ndarray, x: np.ndarray, decide) -> np.ndarray:
    """``decide(atan2f(y, x))`` for float32 ``y``, ``x`` and an element-wise ``decide`` that is monotone in
    the angle, calling libm's atan2f (~40 ns a value, the most expensive step of a scan) only where the
    result depends on the angle's last bits.

    float64 arctan2 is within ~1e-16 of the exact angle and libm's atan2f within 2 ulp of it, so the libm
    value lies within |angle| * 2**-19 (>= 16 ulp; the constant term covers subnormal angles) of the rounded
    float64 angle. Where ``decide`` agrees at both ends of that bracket it agrees on the libm value too (NaN
    inputs give NaN at both ends and in libm alike).
    """
    with np.errstate(invalid='ignore'):
        angle = np.arctan2(y, x, dtype=np.float64).astype(_F32)
        margin = np.abs(angle)
        margin *= _F32(2.0 ** -19)
        margin += _F32(2.0 ** -140)
        result = decide(angle - margin)
        unsure = result != decide(angle + margin)
    if unsure.any():
        result[unsure] = decide(atan2f(y[unsure], x[unsure]))
    return result


def _deg(angle_rad: np.ndarray) -> np.ndarray:
    """``angle * 180 / M_PI`` as the original evaluates it on a float: float32 product, double division."""
    return ((angle_rad * _F32(180.0)).astype(np.float64) / math.pi).astype(_F32)


def _round_half_away(value: np.ndarray) -> np.ndarray:
    """C ``round``: halves away from zero (NumPy rounds halves to even)."""
    # Rounding to nearest is symmetric, so this equals sign(v) * floor(|v| + 0.5) bit for bit, in 3 passes.
    return np.trunc(value + np.copysign(0.5, value))
