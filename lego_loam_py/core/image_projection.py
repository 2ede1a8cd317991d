"""imageProjection: range image, ground removal and segmentation (reference/LEGO_LOAM.md §3, §6.1, §8).

Everything is vectorised over points and pixels. The arithmetic follows the C++ original step by step,
in float32 where it uses floats and with libm's ``atan2f`` (see :mod:`lego_loam_py.core.libm`), so on the
same input the clouds and CloudInfo arrays equal the original's point for point.

The breadth-first segmentation of the original is computed as connected components of the graph whose
nodes are the non-ground, non-empty pixels and whose edges join 4-neighbours (columns wrap around) that
satisfy the angle criterion β > segment_theta. The criterion is symmetric in the two pixels, so components
equal the BFS's clusters; labels are numbered as the BFS numbers them (by the row-major index of each
cluster's first pixel, invalid clusters consuming no number).

Frames: every input and output point is in the sensor frame (REP-103 lidar axes, ``base_link``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from lego_loam_py.core.libm import atan2f, cosf, sinf
from lego_loam_py.core.params import Params

__all__ = ['CloudInfo', 'SegmentationResult', 'ImageProjection', 'ProjectionInput', 'OUTLIER_LABEL',
           'NO_LABEL', 'prepare_input', 'InputError']

OUTLIER_LABEL = 999999   # the original's label of points in clusters that are too small
MAX_COORDINATE = 1e4     # [m] points further out on any axis are dropped as invalid (input validation)
NO_LABEL = -1            # ground or empty pixel (labelMat == -1)
_F32 = np.float32


class InputError(ValueError):
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
        # 4-neighbour pairs of the range image (column wrap-around, no row wrap), row-major pixel indices.
        n, h = self.n_scan, self.horizon_scan
        index = np.arange(n * h).reshape(n, h)
        self._h_pairs = (index.reshape(-1), np.roll(index, -1, axis=1).reshape(-1))
        self._v_pairs = (index[:-1].reshape(-1), index[1:].reshape(-1))
        self._rows = np.repeat(np.arange(n), h)
        self._cols = np.tile(np.arange(h), n)

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
            vertical = _deg(atan2f(z, np.sqrt(x * x + y * y)))
            value = (vertical + self._ang_bottom) / self._ang_res_y
            # C++ converts to size_t: truncation toward zero; below -1 wraps to a huge value (dropped).
            row = np.where(value > -1, np.trunc(value), -1).astype(np.int64)
        row[(row < 0) | (row >= self.n_scan)] = -1
        horizon = _deg(atan2f(x, y)).astype(np.float64)
        col = -_round_half_away(
            (horizon - 90.0) / np.float64(self._ang_res_x)) + self.horizon_scan // 2
        col = col.astype(np.int64)
        col[col >= self.horizon_scan] -= self.horizon_scan
        col[(col < 0) | (col >= self.horizon_scan)] = -1
        return row, col

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
        pixel = np.flatnonzero(winner_of_pixel >= 0)
        winner = winner_of_pixel[pixel]
        self._winner_of_pixel = winner_of_pixel

        range_image = np.full(n * h, np.finfo(np.float32).max, dtype=_F32)
        range_image[pixel] = rng[winner]
        full = np.full((n * h, 4), np.nan, dtype=_F32)
        full[:, 3] = -1.0
        full[pixel, :3] = xyz[winner]
        full[pixel, 3] = (self._rows[pixel] + self._cols[pixel] / 10000.0).astype(_F32)
        full_info = full.copy()
        full_info[pixel, 3] = rng[winner]
        filled = np.zeros(n * h, dtype=bool)
        filled[pixel] = True
        self._time_image = None
        if data.time is not None:
            self._time_image = np.zeros(n * h, dtype=_F32)
            self._time_image[pixel] = data.time[winner]

        ground = self.ground(full, filled)
        labels = self.segment(range_image, filled, ground)
        return self._assemble(full, full_info, range_image, filled, ground, labels, start, end, diff, data,
                              dropped_outside=int(np.count_nonzero((row < 0) | (col < 0))),
                              dropped_close=int(np.count_nonzero((row >= 0) & (col >= 0) & ~keep)),
                              overwritten=int(len(kept) - len(pixel)))

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
            angle = _deg(atan2f(dz, np.sqrt(dx * dx + dy * dy)))
            slope_ok = np.abs(angle - self._mount_angle) <= _F32(self.params.image_projection.ground_slope_threshold)
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
        lower, upper = p[:top - 1], p[1:top]
        both = f[:top - 1] & f[1:top]
        with np.errstate(invalid='ignore'):
            gap = np.hypot(upper[..., 0] - lower[..., 0], upper[..., 1] - lower[..., 1])
            rise = np.abs(upper[..., 2] - lower[..., 2])
            reach = np.hypot(lower[..., 0], lower[..., 1])
            vertical = both & (rise > ip.ground_vertical_ratio * gap) & (gap < ip.ground_vertical_gap * reach)
        ground = ground.copy()
        ground[:top - 1] &= ~vertical
        ground[1:top] &= ~vertical
        rows, cols = np.nonzero(ground)
        if len(rows) < 10:
            return ground
        xyz = p[rows, cols, :3].astype(np.float64)
        reach = np.hypot(xyz[:, 0], xyz[:, 1])
        tolerance = np.maximum(ip.ground_plane_tolerance, ip.ground_plane_tolerance_ratio * reach)
        near = reach <= ip.ground_plane_radius
        keep = near if near.sum() >= 10 else np.ones(len(xyz), dtype=bool)
        design = np.column_stack([xyz[:, 0], xyz[:, 1], np.ones(len(xyz))])
        for _ in range(3):
            if keep.sum() < 3:
                break
            coef, *_ = np.linalg.lstsq(design[keep], xyz[keep, 2], rcond=None)
            keep = (np.abs(xyz[:, 2] - design @ coef) <= tolerance) & (near if near.sum() >= 10 else True)
        on_plane = np.zeros_like(ground)
        on_plane[rows, cols] = np.abs(xyz[:, 2] - design @ coef) <= tolerance
        near_image = np.zeros_like(ground)
        near_image[rows, cols] = near
        # The walk up the columns: a loop over the few ground rows, vectorised over the columns.
        slope = math.tan(math.radians(ip.ground_chain_slope))
        last = np.full((self.horizon_scan, 3), np.nan)
        for r in range(top):
            candidate = ground[r]
            if not candidate.any():
                continue
            xyz_r = p[r, :, :3].astype(np.float64)
            with np.errstate(invalid='ignore'):
                step = np.hypot(xyz_r[:, 0] - last[:, 0], xyz_r[:, 1] - last[:, 1])
                continues = np.abs(xyz_r[:, 2] - last[:, 2]) <= slope * step + ip.ground_chain_tolerance
            seeded = ~np.isnan(last[:, 0])
            accepted = candidate & np.where(seeded, continues, True) & (on_plane[r] | (seeded & ~near_image[r]))
            ground[r] = accepted
            last[accepted] = xyz_r[accepted]
        return ground

    # ------------------------------------------------------------------------------- segmentation
    def segment(self, range_image: np.ndarray, filled: np.ndarray, ground: np.ndarray) -> np.ndarray:
        """The original's labelMat as int32 (N_SCAN*H,): -1 ground or empty, 999999 pixels of clusters that
        are too small, 1, 2, ... valid segments numbered in the BFS's order.

        ``range_image`` is (N_SCAN*H,) float32 [m], ``filled`` marks non-empty pixels, ``ground`` the ground.
        """
        n, h = self.n_scan, self.horizon_scan
        ip = self.params.image_projection
        labels = np.full(n * h, NO_LABEL, dtype=np.int32)
        candidate = filled & ~ground
        if not candidate.any():
            return labels
        heads, tails = [], []
        for direction, (a, b) in enumerate((self._h_pairs, self._v_pairs)):
            both = candidate[a] & candidate[b]
            a, b = a[both], b[both]
            ra, rb = range_image[a], range_image[b]
            d1, d2 = np.maximum(ra, rb), np.minimum(ra, rb)
            beta = atan2f(d2 * self._sin_alpha[direction], d1 - d2 * self._cos_alpha[direction])
            join = beta > self._theta
            heads.append(a[join])
            tails.append(b[join])
        nodes = np.flatnonzero(candidate)
        node_of_pixel = np.full(n * h, -1, dtype=np.int64)
        node_of_pixel[nodes] = np.arange(len(nodes))
        head = node_of_pixel[np.concatenate(heads)]
        tail = node_of_pixel[np.concatenate(tails)]
        graph = coo_matrix((np.ones(len(head), dtype=np.int8), (head, tail)), shape=(len(nodes), len(nodes)))
        count, component = connected_components(graph, directed=False)

        size = np.bincount(component, minlength=count)
        # The BFS seed is the component's first pixel in row-major order; its row counts only if another
        # pixel of the component lies in the same row (quirk 13).
        seed = np.full(count, np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(seed, component, nodes)
        non_seed = nodes != seed[component]
        row_seen = np.zeros((count, n), dtype=bool)
        row_seen[component[non_seed], self._rows[nodes[non_seed]]] = True
        line_count = row_seen.sum(axis=1)
        valid = (size >= ip.segment_min_cluster_size) | (
            (size >= ip.segment_valid_point_num) & (line_count >= ip.segment_valid_line_num))
        # Label numbers in the order the BFS finds the clusters (row-major seed order), valid ones only.
        number = np.zeros(count, dtype=np.int32)
        valid_ids = np.flatnonzero(valid)
        number[valid_ids[np.argsort(seed[valid_ids])]] = np.arange(1, len(valid_ids) + 1, dtype=np.int32)
        number[~valid] = OUTLIER_LABEL
        labels[nodes] = number[component]
        return labels

    # --------------------------------------------------------------------------------- assembling
    def _assemble(self, full, full_info, range_image, filled, ground, labels, start, end, diff, data,
                  **stats) -> SegmentationResult:
        n, h = self.n_scan, self.horizon_scan
        ip = self.params.image_projection
        g = self.params.sensor.ground_scan_ind
        rows, cols = self._rows, self._cols
        # Pixels in row-major order, as the original walks them.
        outlier = labels == OUTLIER_LABEL
        thinned_ground = ground & ((cols % ip.ground_column_stride == 0) | (cols <= ip.ground_edge_columns) |
                                   (cols >= h - ip.ground_edge_columns))
        segmented = ((labels > 0) & ~outlier) | thinned_ground
        segmented_index = np.flatnonzero(segmented)
        outlier_index = np.flatnonzero(outlier & (rows > g) & (cols % ip.outlier_column_stride == 0))

        count_before_row = np.concatenate(([0], np.cumsum(np.bincount(rows[segmented_index], minlength=n))))
        margin = ip.ring_index_margin
        start_ring = (count_before_row[:-1] - 1 + margin).astype(np.int32)
        end_ring = (count_before_row[1:] - 1 - margin).astype(np.int32)

        info = CloudInfo(
            start_ring_index=start_ring, end_ring_index=end_ring,
            start_orientation=start, end_orientation=end, orientation_diff=diff,
            segmented_cloud_ground_flag=ground[segmented_index].copy(),
            segmented_cloud_col_ind=cols[segmented_index].astype(np.uint32),
            segmented_cloud_range=range_image[segmented_index].copy())
        ground_index = np.flatnonzero(ground & (rows <= g))
        pure_index = np.flatnonzero((labels > 0) & ~outlier)
        pure = full[pure_index].copy()
        pure[:, 3] = labels[pure_index]
        stats.update(
            input_points=int(data.xyz.shape[0] + data.dropped_non_finite),
            non_finite=data.dropped_non_finite, projected=int(np.count_nonzero(filled)),
            ground=int(np.count_nonzero(ground)), segments=int(labels[pure_index].max(initial=0)),
            segmented=len(segmented_index), outliers=len(outlier_index))
        segmented_time = self._time_image[segmented_index] if self._time_image is not None else None
        return SegmentationResult(
            segmented_time=segmented_time, pixel_point=self._winner_of_pixel,
            segmented_cloud=full[segmented_index], cloud_info=info, outlier_cloud=full[outlier_index],
            ground_cloud=full[ground_index], segmented_cloud_pure=pure, full_cloud=full,
            full_info_cloud=full_info, range_image=range_image.reshape(n, h),
            ground_mask=ground.reshape(n, h), label_image=labels.reshape(n, h), stats=stats)


def _deg(angle_rad: np.ndarray) -> np.ndarray:
    """``angle * 180 / M_PI`` as the original evaluates it on a float: float32 product, double division."""
    return ((angle_rad * _F32(180.0)).astype(np.float64) / math.pi).astype(_F32)


def _round_half_away(value: np.ndarray) -> np.ndarray:
    """C ``round``: halves away from zero (NumPy rounds halves to even)."""
    return np.sign(value) * np.floor(np.abs(value) + 0.5)
