"""A 2D occupancy grid of the map for a robot's navigation stack (``nav_msgs/OccupancyGrid``), from the keyframes.

Inputs are the keyframes as mapOptimization keeps them (:class:`~lego_loam_py.core.mapping.map_optimization.Keyframe`):
an optimised pose six-vector ``pose6`` (camera_init, LOAM camera axes) and the downsampled ``corner``, ``surf`` and
``outlier`` clouds in the keyframe's sensor frame (camera axes). The grid lies in the ``map`` frame (REP-103: x
forward, y left, z up; camera_init turned into REP-103 axes, as the saved maps are): cell ``(row, col)`` covers
``x in [origin_x + col r, origin_x + (col + 1) r)`` and ``y in [origin_y + row r, ...)``, row 0 at the origin.

**Each keyframe on its own**: its points are sorted into obstacles (``min_height``..``max_height`` above the local
ground) and ground hits by :func:`~lego_loam_py.core.mapping.occupancy_ground.classify_keyframe` (the ground model
and why it is so are there), cached in the keyframe's own sensor frame.

**Into the grid** (:meth:`OccupancyGrid.add_keyframe`): the cells of its obstacle points get ``hit_log_odds``.
Free space is ray casting from the sensor, one ray per azimuth bin of ``angular_resolution_deg``: a bin is free as
far as its rays stay in the height band, i.e. to its obstacle points and to ``1 - min_height / sensor height`` of
the way to its ground hits (past that, a ray to the ground may have passed under an obstacle: a car's body, 0.3 m
above the road), a bin without rays as far as its neighbours', and never closer than ``obstacle_margin`` to the
nearest obstacle of the bin or of its two neighbours (a ray to the top of a car passes over the car's edge below it;
a wall seen at a grazing angle stops the rays of the neighbouring bins too). The bins are filled across their
width by a lookup of every cell's range and bearing from the sensor in one table made for the grid, so the gaps
between the downsampled clouds' rays stay free; free cells get ``miss_log_odds``. Each cell changes at most once
per keyframe (a hit wins over a miss) and its log-odds are clamped to ``min_log_odds``..``max_log_odds``; it is
occupied (100) above ``occupied_threshold``, free (0) below ``free_threshold``, unknown (-1) otherwise or when never
seen (:meth:`OccupancyGrid.ternary`). :meth:`OccupancyGrid.redraw` rebuilds the grid from the keyframes' current
poses (after a loop closure), reusing each keyframe's classification unless its up axis turned by more than
``reclassify_tilt_deg``. :meth:`OccupancyGrid.sync` brings the grid to a list of keyframes as the mapping holds
them: the new ones added, everything redrawn when a pose it was drawn with moved (a loop closure) or a keyframe went.
The parameters are :class:`~lego_loam_py.core.params.types.OccupancyGridParams`. :func:`message_fields` gives what a
``nav_msgs/OccupancyGrid`` holds; :mod:`lego_loam_py.core.mapping.occupancy_files` writes and reads nav2 map_server
files.
"""

from __future__ import annotations

import array
import functools
import math
import threading
from dataclasses import dataclass, field

import numpy as np

from lego_loam_py.core.frames import MAP_FRAME, camera_pose_to_lidar, camera_to_lidar, pose6_to_matrix
from lego_loam_py.core.mapping.occupancy_ground import KeyframeScan, classify_keyframe
from lego_loam_py.core.params.types import OccupancyGridParams

try:  # the disk update in C (native/occupancy_kernels.c); optional, the NumPy version gives the same
    from lego_loam_py.core import _occupancy_kernels
except ImportError:
    _occupancy_kernels = None

__all__ = [
    'KeyframeScan',
    'TernaryGrid',
    'OccupancyGridFields',
    'OccupancyGrid',
    'classify_keyframe',
    'keyframe_lidar_pose',
    'keyframe_points',
    'message_fields',
    'OCCUPIED',
    'FREE',
    'UNKNOWN',
]

OCCUPIED, FREE, UNKNOWN = 100, 0, -1


@dataclass(frozen=True, eq=False)
class TernaryGrid:
    """A finished grid: ``cells[row, col]`` int8 100 / 0 / -1, row 0 at the origin (lowest y), column 0 lowest x."""

    resolution: float  # [m]
    origin: tuple[float, float]  # [m] the lower-left corner of cell (0, 0) in the map frame
    cells: np.ndarray  # (height, width) int8
    origin_yaw: float = 0.0  # [rad] rotation of the grid about the origin (nav2 ignores it)
    frame_id: str = MAP_FRAME

    @property
    def width(self) -> int:
        return int(self.cells.shape[1])

    @property
    def height(self) -> int:
        return int(self.cells.shape[0])

    def counts(self) -> dict[str, int]:
        """Cells occupied, free and unknown."""
        return {
            'occupied': int(np.count_nonzero(self.cells == OCCUPIED)),
            'free': int(np.count_nonzero(self.cells == FREE)),
            'unknown': int(np.count_nonzero(self.cells == UNKNOWN)),
        }

    def cell_centres(self, which: int = OCCUPIED) -> np.ndarray:
        """(k, 2) map-frame x, y [m] of the centres of the cells holding ``which`` (yaw 0 assumed)."""
        rows, cols = np.nonzero(self.cells == which)
        return np.column_stack(
            [self.origin[0] + (cols + 0.5) * self.resolution, self.origin[1] + (rows + 0.5) * self.resolution]
        )


@dataclass(frozen=True, eq=False)
class OccupancyGridFields:
    """The fields of a ``nav_msgs/OccupancyGrid`` (the node adds the stamp): ``msg.info.resolution = resolution``,
    ``msg.info.origin.position`` x, y, z = ``origin_position``, ``.orientation`` x, y, z, w = ``origin_orientation``,
    ``msg.data = data`` (int8 row-major, row 0 at the origin; an array.array('b'), which the message takes as is)."""

    frame_id: str
    resolution: float
    width: int
    height: int
    origin_position: tuple[float, float, float]
    origin_orientation: tuple[float, float, float, float]
    data: array.array


def message_fields(grid: TernaryGrid) -> OccupancyGridFields:
    """What a ``nav_msgs/OccupancyGrid`` of ``grid`` holds, as plain data."""
    data = array.array('b')
    data.frombytes(np.ascontiguousarray(grid.cells, dtype=np.int8).tobytes())
    half = 0.5 * grid.origin_yaw
    return OccupancyGridFields(
        grid.frame_id,
        float(grid.resolution),
        grid.width,
        grid.height,
        (float(grid.origin[0]), float(grid.origin[1]), 0.0),
        (0.0, 0.0, math.sin(half), math.cos(half)),
        data,
    )


def keyframe_lidar_pose(pose6: np.ndarray) -> np.ndarray:
    """4x4 pose of a keyframe's sensor (REP-103 lidar axes) in the map frame, from its camera_init six-vector."""
    return camera_pose_to_lidar(pose6_to_matrix(pose6))


def keyframe_points(keyframe) -> np.ndarray:
    """(n, 3) float32: a keyframe's corner, surf and outlier points ((n, >= 3) arrays, camera axes) in its sensor
    frame, REP-103 lidar axes; non-finite points dropped."""
    clouds = [np.asarray(c, dtype=np.float32) for c in (keyframe.corner, keyframe.surf, keyframe.outlier)]
    points = camera_to_lidar(
        np.concatenate(
            [c[:, :3] for c in clouds if c.ndim == 2 and c.shape[1] >= 3 and len(c)] or [np.zeros((0, 3), np.float32)]
        )
    )
    if np.isfinite(points).all():  # (the usual case, in one pass: a row-wise test over (n, 3) costs 30 times more)
        return np.ascontiguousarray(points)
    finite = np.isfinite(points[:, 0]) & np.isfinite(points[:, 1]) & np.isfinite(points[:, 2])
    return np.ascontiguousarray(points[finite])


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@dataclass
class _Disk:
    """Range [m] and azimuth bin of every cell within the ray-casting range, relative to the sensor's cell."""

    reach: int  # cells from the centre to the edge
    ranges: np.ndarray = field(repr=False)  # (2 reach + 1, 2 reach + 1) float32
    bins: np.ndarray = field(repr=False)  # same shape, int32; outside the range: the sentinel bin ``count``
    count: int = 0


def _make_disk(params: OccupancyGridParams) -> _Disk:
    reach = int(math.ceil(params.max_range / params.resolution))
    offsets = np.arange(-reach, reach + 1, dtype=np.float64) * params.resolution
    dy, dx = np.meshgrid(offsets, offsets, indexing='ij')
    ranges = np.hypot(dx, dy)
    count = int(math.ceil(360.0 / params.angular_resolution_deg))
    bins = (np.floor((np.arctan2(dy, dx) + math.pi) / (2 * math.pi) * count).astype(np.int32)) % count
    bins[ranges > params.max_range] = count
    return _Disk(reach, ranges.astype(np.float32), bins, count)


def _update_window(
    log_odds: np.ndarray,
    observed: np.ndarray,
    corner: tuple[int, int],
    disk: _Disk,
    free_range: np.ndarray,
    hit: np.ndarray,
    params: OccupancyGridParams,
    native: bool = True,
) -> None:
    """One keyframe's update, in place, of the disk's window of the grid's arrays ``log_odds`` (float32) and
    ``observed`` (bool); ``corner``: the window's first (column, row) in them. ``free_range`` (disk.count + 1,)
    float32 [m]: how far each azimuth bin is free (the last, 0: outside the disk); ``hit`` (the disk's shape) bool:
    the obstacles' cells. Each cell of the window gets + hit_log_odds where hit, else + miss_log_odds where free
    (nearer than its bin's free range), else + 0 (float32 sums), then np.clip's clamp (its bounds float32), and is
    observed where hit or free. In C when the extension is built, the same values bit for bit; ``native=False``
    runs the NumPy version (the tests compare the two)."""
    p = params
    x0, y0 = int(corner[0]), int(corner[1])
    size = 2 * disk.reach + 1
    if (
        native
        and _occupancy_kernels is not None
        and log_odds.dtype == np.float32
        and observed.dtype == np.bool_
        and log_odds.ndim == 2
        and observed.shape == log_odds.shape
        and log_odds.flags.c_contiguous
        and observed.flags.c_contiguous
        and free_range.dtype == np.float32
        and hit.dtype == np.bool_
    ):
        _occupancy_kernels.update_disk(
            log_odds,
            observed,
            log_odds.shape[1],
            x0,
            y0,
            size,
            disk.ranges,
            disk.bins,
            np.ascontiguousarray(free_range),
            np.ascontiguousarray(hit),
            # (what NumPy makes of the Python floats next to float32 arrays: float32, rounded to nearest)
            *(float(np.float32(v)) for v in (p.hit_log_odds, p.miss_log_odds, p.min_log_odds, p.max_log_odds)),
        )
        return
    free = disk.ranges < free_range[disk.bins]
    window = log_odds[y0 : y0 + size, x0 : x0 + size]
    window += np.where(hit, np.float32(p.hit_log_odds), np.where(free, np.float32(p.miss_log_odds), np.float32(0.0)))
    np.clip(window, p.min_log_odds, p.max_log_odds, out=window)
    observed[y0 : y0 + size, x0 : x0 + size] |= hit | free


class OccupancyGrid:
    """The map's occupancy grid, updated keyframe by keyframe and redrawn after the poses change.

    Thread safety: every public method takes :attr:`lock`, so one thread may update the grid while another
    reads :meth:`ternary`; :attr:`version` changes with every change of the grid. ``native=False``: NumPy only, no C
    kernels (the same grid bit for bit; the tests compare the two)."""

    def __init__(self, params: OccupancyGridParams | None = None, native: bool = True):
        self.params = params or OccupancyGridParams()
        self.native = native
        self._scans: dict[object, KeyframeScan] = {}
        self.keyframes_added = 0
        self.classified = 0  # keyframes classified (cache misses), for the record
        self.redraws = 0  # redraws of every keyframe (after loop closures), for the record
        self.version = 0
        self.lock = threading.RLock()
        self._clear()

    @functools.cached_property
    def _disk(self) -> _Disk:
        """The ray-casting disk, made with the first keyframe (10 ms: not a node's start-up)."""
        return _make_disk(self.params)

    def _clear(self) -> None:
        self._log_odds = np.zeros((0, 0), np.float32)
        self._observed = np.zeros((0, 0), bool)
        self._corner = np.zeros(2, np.int64)  # lattice index (x, y) of cell (0, 0) of the arrays
        self._drawn: list[tuple[object, bytes]] = []  # (key, pose6 bytes) of each keyframe drawn, in order
        self.keyframes_added = 0

    # ------------------------------------------------------------------------------------------------ updates

    def add_keyframe(self, keyframe) -> None:
        """Add one keyframe's observations (any object with ``pose6``, ``corner``, ``surf``, ``outlier``; its
        ``index`` and ``stamp_ns``, when it has them, key the cache :meth:`redraw` reuses). A ValueError for a pose
        that is not finite or would stretch the grid past ``max_cells``; the grid is then unchanged."""
        with self.lock:
            pose = _checked_pose(keyframe)
            self._cover(pose[:2, 3], pose[:2, 3])
            self._render(self._scan_of(keyframe, pose), pose)
            self._drawn.append(_identity(keyframe))
            self.version += 1

    def redraw(self, keyframes) -> None:
        """Rebuild the grid from ``keyframes`` (all of them, in order) at their current poses."""
        with self.lock:
            self._redraw(list(keyframes))

    def sync(self, keyframes) -> str:
        """Bring the grid to ``keyframes`` (all of the map's, in order, each as in :meth:`add_keyframe`): when the
        keyframes it was drawn from are the first of them at the same poses, the others are added ('added', or
        'unchanged' when there are none); otherwise (a loop closure moved the poses, keyframes were dropped) it is
        redrawn from all of them ('redrawn'). Costs the new keyframes, or a redraw."""
        keyframes = list(keyframes)
        with self.lock:
            drawn = len(self._drawn)
            if drawn <= len(keyframes) and all(
                _identity(kf) == seen for kf, seen in zip(keyframes[:drawn], self._drawn)
            ):
                for keyframe in keyframes[drawn:]:
                    self.add_keyframe(keyframe)
                return 'added' if len(keyframes) > drawn else 'unchanged'
            self._redraw(keyframes)
            return 'redrawn'

    def _redraw(self, keyframes: list) -> None:
        poses = [_checked_pose(kf) for kf in keyframes]
        if poses:
            sensors = np.array([p[:2, 3] for p in poses])
            self._cells_needed(sensors.min(axis=0), sensors.max(axis=0), grown=False)
        self._clear()
        if poses:
            self._cover(sensors.min(axis=0), sensors.max(axis=0))
        scans = {}
        for keyframe, pose in zip(keyframes, poses):
            scan = self._scan_of(keyframe, pose)
            if _key(keyframe) is not None:
                scans[_key(keyframe)] = scan
            self._render(scan, pose)
            self._drawn.append(_identity(keyframe))
        self._scans = scans  # (keyframes no longer in the map are forgotten)
        self.redraws += 1
        self.version += 1

    def _scan_of(self, keyframe, pose: np.ndarray) -> KeyframeScan:
        up = pose[2, :3]  # the map's z axis in the sensor frame: the third row of R_map_sensor
        key = _key(keyframe)
        scan = None if key is None else self._scans.get(key)
        tilt = math.radians(self.params.reclassify_tilt_deg)
        if scan is None or float(np.dot(scan.up, up)) < math.cos(tilt):
            scan = classify_keyframe(keyframe_points(keyframe), up, self.params, self.native)
            if key is not None:
                self._scans[key] = scan
            self.classified += 1
        return scan

    def _cells_needed(self, low_xy: np.ndarray, high_xy: np.ndarray, grown: bool = True):
        """(low, high) lattice indices (x, y) of the arrays that hold every cell within range of sensors between
        ``low_xy`` and ``high_xy`` (``grown``: and what the arrays hold now, with room to grow); a ValueError past
        ``max_cells``."""
        reach = self._disk.reach + 1
        low = np.floor(np.asarray(low_xy) / self.params.resolution).astype(np.int64) - reach
        high = np.floor(np.asarray(high_xy) / self.params.resolution).astype(np.int64) + reach + 1
        if grown and self._log_odds.size:  # at least half the size more on a side that grows: amortised copies
            shape = np.array(self._log_odds.shape[::-1], dtype=np.int64)  # (x, y)
            end = self._corner + shape
            low = np.minimum(low, np.where(low < self._corner, self._corner - shape // 2, self._corner))
            high = np.maximum(high, np.where(high > end, end + shape // 2, end))
        cells = int(np.prod(high - low))
        if cells > self.params.max_cells:
            r = self.params.resolution
            raise ValueError(
                f'occupancy grid: {(high - low)[0] * r:.0f} x {(high - low)[1] * r:.0f} m at {r:g} m '
                f'would take {cells} cells, more than max_cells {self.params.max_cells}'
            )
        return low, high

    def _cover(self, low_xy: np.ndarray, high_xy: np.ndarray) -> None:
        """Grow the arrays to hold every cell within the range of sensors between ``low_xy`` and ``high_xy``."""
        low, high = self._cells_needed(low_xy, high_xy, grown=False)
        shape = np.array(self._log_odds.shape[::-1], dtype=np.int64)  # (x, y)
        if self._log_odds.size and (low >= self._corner).all() and (high <= self._corner + shape).all():
            return
        low, high = self._cells_needed(low_xy, high_xy)
        size = high - low
        log_odds = np.zeros((size[1], size[0]), np.float32)
        observed = np.zeros((size[1], size[0]), bool)
        if self._log_odds.size:
            x0, y0 = self._corner - low
            log_odds[y0 : y0 + shape[1], x0 : x0 + shape[0]] = self._log_odds
            observed[y0 : y0 + shape[1], x0 : x0 + shape[0]] = self._observed
        self._log_odds, self._observed, self._corner = log_odds, observed, low

    def _render(self, scan: KeyframeScan, pose: np.ndarray) -> None:
        p, disk = self.params, self._disk
        sensor = pose[:2, 3]
        rotation, translation = pose[:2, :3], pose[:2, 3]
        obstacles = scan.obstacles.astype(np.float64) @ rotation.T + translation
        ground = scan.ground.astype(np.float64) @ rotation.T + translation
        # Free range of each azimuth bin: as far as its rays stay in the height band (gaps of one bin filled from the
        # neighbours), stopping obstacle_margin short of the nearest obstacle of the bin or its neighbours. A ray to
        # an obstacle stays in the band; one to the ground leaves it min_height above the ground, at the share
        # 1 - min_height / sensor_height of its length whatever the slope (the ground under a straight ray is taken
        # as straight): beyond, it may have passed under an obstacle (a car's body, 0.3 m above the road). The
        # last bin is the sentinel: outside the disk.
        in_band = max(0.0, 1.0 - p.min_height / scan.sensor_height) if scan.sensor_height > 0 else 0.0
        nearest = np.full(disk.count, np.inf)
        farthest = np.zeros(disk.count)
        for xy, is_obstacle in ((obstacles, True), (ground, False)):
            offset = xy - sensor
            distance = np.hypot(offset[:, 0], offset[:, 1])
            bins = (
                np.floor((np.arctan2(offset[:, 1], offset[:, 0]) + math.pi) / (2 * math.pi) * disk.count).astype(
                    np.int64
                )
            ) % disk.count
            np.maximum.at(farthest, bins, distance if is_obstacle else distance * in_band)
            if is_obstacle:
                np.minimum.at(nearest, bins, distance)
        nearest = np.minimum(np.minimum(nearest, np.roll(nearest, 1)), np.roll(nearest, -1)) - p.obstacle_margin
        farthest = np.maximum(np.maximum(farthest, np.roll(farthest, 1)), np.roll(farthest, -1))
        free_range = np.append(np.minimum(nearest, farthest), 0.0).astype(np.float32)
        # The window of the disk around the sensor's cell, in the arrays.
        centre = np.floor(sensor / p.resolution).astype(np.int64) - self._corner
        x0, y0 = centre - disk.reach
        size = 2 * disk.reach + 1
        hit = np.zeros(disk.ranges.shape, bool)
        cells = np.floor(obstacles / p.resolution).astype(np.int64) - self._corner - (x0, y0)
        inside = (cells[:, 0] >= 0) & (cells[:, 0] < size) & (cells[:, 1] >= 0) & (cells[:, 1] < size)
        hit[cells[inside, 1], cells[inside, 0]] = True
        _update_window(self._log_odds, self._observed, (x0, y0), disk, free_range, hit, p, self.native)
        self.keyframes_added += 1

    # ----------------------------------------------------------------------------------------------- results

    def ternary(self) -> TernaryGrid:
        """The grid as it stands, cut to the cells ever observed (an empty 0 x 0 grid before any)."""
        with self.lock:
            return self._ternary()

    def _ternary(self) -> TernaryGrid:
        rows = np.flatnonzero(self._observed.any(axis=1))
        cols = np.flatnonzero(self._observed.any(axis=0))
        r = self.params.resolution
        if not len(rows):
            return TernaryGrid(r, (0.0, 0.0), np.zeros((0, 0), np.int8))
        window = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        log_odds, observed = self._log_odds[window], self._observed[window]
        cells = np.full(log_odds.shape, UNKNOWN, np.int8)
        cells[observed & (log_odds < _logit(self.params.free_threshold))] = FREE
        cells[observed & (log_odds > _logit(self.params.occupied_threshold))] = OCCUPIED
        origin = ((self._corner[0] + cols[0]) * r, (self._corner[1] + rows[0]) * r)
        return TernaryGrid(r, (float(origin[0]), float(origin[1])), cells)


def _key(keyframe) -> tuple[int, int] | None:
    """What identifies a keyframe across calls: (index, stamp) when it has them (else it is never cached)."""
    index, stamp = getattr(keyframe, 'index', None), getattr(keyframe, 'stamp_ns', None)
    return (int(index), int(stamp)) if index is not None and stamp is not None else None


def _identity(keyframe) -> tuple[object, bytes]:
    """What :meth:`OccupancyGrid.sync` compares: the keyframe's key and the exact pose it is drawn at."""
    return _key(keyframe), np.asarray(keyframe.pose6, dtype=np.float64).tobytes()


def _checked_pose(keyframe) -> np.ndarray:
    """The keyframe's sensor pose in the map (lidar axes), or a ValueError when it is not finite."""
    pose6 = np.asarray(keyframe.pose6, dtype=float)
    if pose6.shape != (6,) or not np.isfinite(pose6).all():
        raise ValueError(f'occupancy grid: keyframe {getattr(keyframe, "index", "?")} has no finite pose: {pose6}')
    return keyframe_lidar_pose(pose6)
