"""imageProjection's first step: the valid points of a cloud and their range image (docs/original.md §6.1).

:func:`prepare_input` keeps the valid points of a structured cloud; :class:`RangeImageProjection` puts each
one in its range-image pixel (row from the ring or the elevation, column from the azimuth) as the C++
original does, in float32 where it uses floats and with libm's ``atan2f`` where the last bit decides.

Frames: every input and output point is in the sensor frame (REP-103 lidar axes, ``base_link``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.params.beams import BeamRows
from lego_loam_py.core.params.types import Params
from lego_loam_py.core.parity.atan2f_decisions import Atan2fSteps, decide_on_atan2f, first_float32_where
from lego_loam_py.core.parity.libm import atan2f, float_degrees, round_half_away
from lego_loam_py.core.projection.driver_layouts import read_cloud
from lego_loam_py.core.projection.laser_order import rows_from_laser_order
from lego_loam_py.errors import LegoLoamError

try:  # the pixels of a scan in one C pass (native/projection_kernels.c); NumPy's where it is not built
    from lego_loam_py.core import _projection_kernels
except ImportError:  # pragma: no cover
    _projection_kernels = None

__all__ = ['InputError', 'ProjectionInput', 'prepare_input', 'RangeImage', 'RangeImageProjection']

_F32 = np.float32


class InputError(LegoLoamError, ValueError):
    """The cloud cannot be projected at all (no valid point)."""


@dataclass
class ProjectionInput:
    """Valid points of one cloud, in measurement order: sensor-frame coordinates and optional ring and time."""

    xyz: np.ndarray  # float32 (n, 3) [m], all finite
    ring: np.ndarray | None  # int64 (n,) or None (rows from the elevation angle)
    dropped_non_finite: int = 0  # points removed because x, y or z was NaN/inf or beyond MAX_COORDINATE
    time: np.ndarray | None = None  # float32 (n,) [s since the sweep start] when the cloud has it
    source_index: np.ndarray | None = None  # index in the message of each kept point (None: all, in order)
    dropped_origin: int = 0  # points removed because x = y = z = 0 (no return: Ouster's organized clouds)
    time_ordered: bool = False  # the points were put in time order (the cloud was stored beam by beam)
    rings_from_top: bool = False  # the ring field counted from the top beam and was turned round


def prepare_input(points: np.ndarray, params: Params) -> ProjectionInput:
    """The valid points of a structured cloud in any driver's layout, in measurement order: coordinates, the ring
    counted from the lowest beam, the time in seconds since the sweep start
    (:mod:`lego_loam_py.core.projection.driver_layouts`).

    Mirrors the original's ``removeNaNFromPointCloud``; inf is dropped as well, and so are coordinates beyond
    ``MAX_COORDINATE`` (10 km: no lidar measures that; such values would overflow float32 squares) and points at
    the origin (no return). The sweep's start and end orientation thus come from measured points. Unlike the
    original, which shuts down on a non-dense cloud in ring mode, the ring is filtered together with the
    coordinates. Raises CloudLayoutError for a layout that cannot be read.
    """
    s = params.sensor
    cloud = read_cloud(points, s.n_scan, s.ring_field if s.use_cloud_ring else None, s.time_field, s.scan_period)
    return ProjectionInput(
        xyz=cloud.xyz,
        ring=cloud.ring,
        dropped_non_finite=cloud.dropped_non_finite,
        time=cloud.time,
        source_index=cloud.source_index,
        dropped_origin=cloud.dropped_origin,
        time_ordered=cloud.time_ordered,
        rings_from_top=cloud.rings_from_top,
    )


@dataclass
class RangeImage:
    """One scan in the (N_SCAN, H) range image. Per-pixel arrays are flat (N_SCAN*H,), row-major."""

    full_cloud: np.ndarray  # float32 (N_SCAN*H, 4): x, y, z [m], row + col / 10000; empty cells NaN, -1
    full_info_cloud: np.ndarray  # same cells, intensity = range [m]
    range: np.ndarray  # float32 [m], FLT_MAX where empty
    filled: np.ndarray  # bool: the pixel holds a point
    point_of_pixel: np.ndarray  # int64: index of the input point in each pixel, -1 where empty
    time: np.ndarray | None  # float32 [s since the sweep start] of each pixel's point, 0 where empty
    start_orientation: np.float32  # [rad]
    end_orientation: np.float32  # [rad]
    orientation_diff: np.float32  # [rad]
    stats: dict  # points dropped outside the image or too close, overwritten in a pixel


class RangeImageProjection:
    """The projection of one sensor configuration; :meth:`project` handles one scan."""

    def __init__(self, params: Params):
        s = params.sensor
        self.n_scan = s.n_scan
        self.horizon_scan = s.horizon_scan
        # The original's float constants.
        self._ang_res_x = _F32(s.ang_res_x)
        self._ang_res_y = _F32(s.ang_res_y)
        self._ang_bottom = _F32(s.ang_bottom)
        self._min_range = _F32(s.sensor_minimum_range)
        # Unevenly spaced beams: rows without a ring field from the nearest beam of the table.
        self._beam_rows = BeamRows(s.beam_elevations) if s.beam_elevations else None
        self._rows_from_order = s.use_cloud_ring  # (without a ring field: see core.laser_order)
        n, h = self.n_scan, self.horizon_scan
        rows, cols = np.repeat(np.arange(n), h), np.tile(np.arange(h), n)
        self._pixel_intensity = (rows + cols / 10000.0).astype(_F32)
        # The column before wrapping falls from _top_column at atan2f = -pi to its value at +pi, one step at
        # each threshold angle: the staircase that Atan2fSteps reads mostly without computing angles.
        ends = self._column_of_azimuth(np.array([-math.pi, math.pi], dtype=_F32))
        self._top_column = int(ends[0])
        levels = np.arange(self._top_column - 1, int(ends[1]) - 1, -1)
        thresholds = first_float32_where(lambda a: self._column_of_azimuth(a) <= levels, -math.pi, math.pi, len(levels))
        self._azimuth_steps = Atan2fSteps(thresholds)

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

    def rows_and_columns(
        self, ring: np.ndarray | None, x: np.ndarray, y: np.ndarray, z: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Range-image row and column of every point (int64; -1 where outside the image) from its ring (or
        None) and float32 sensor-frame coordinates [m]."""
        row = ring.copy() if ring is not None else None
        if row is None and self._rows_from_order:  # a cloud stored laser by laser (KITTI's) tells its lasers
            row = rows_from_laser_order(x, y, z, self.n_scan)
        if row is None and self._beam_rows is not None:
            row = self._beam_rows.rows(z, np.sqrt(x * x + y * y))
        elif row is None:
            row = decide_on_atan2f(z, np.sqrt(x * x + y * y), self._row_of_elevation).astype(np.int64)
        row[(row < 0) | (row >= self.n_scan)] = -1
        col = self._columns(x, y)
        col[col >= self.horizon_scan] -= self.horizon_scan
        col[(col < 0) | (col >= self.horizon_scan)] = -1
        return row, col

    def _columns(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Column (int64, before wrapping into the image) of points at sensor-frame x, y [m]."""
        steps, confirmed = self._azimuth_steps.count(x, y)  # of atan2f(x, y)
        col = self._top_column - steps
        unconfirmed = ~confirmed
        if unconfirmed.any():
            col[unconfirmed] = decide_on_atan2f(x[unconfirmed], y[unconfirmed], self._column_of_azimuth)
        return col

    def _row_of_elevation(self, vertical: np.ndarray) -> np.ndarray:
        """Row (float; -1 below the image) of elevation angles [rad], monotone in the angle."""
        value = (float_degrees(vertical) + self._ang_bottom) / self._ang_res_y
        # C++ converts to size_t: truncation toward zero; below -1 wraps to a huge value (dropped).
        return np.where(value > -1, np.trunc(value), -1)

    def _column_of_azimuth(self, azimuth: np.ndarray) -> np.ndarray:
        """Column (float, before wrapping into the image) of atan2(x, y) angles [rad], monotone in the angle."""
        value = float_degrees(azimuth).astype(np.float64)
        value -= 90.0
        value /= np.float64(self._ang_res_x)
        return (self.horizon_scan // 2) - round_half_away(value)

    def project(self, data: ProjectionInput, native: bool = True) -> RangeImage:
        """The range image of one scan's valid points (at least one). The pixels in one C pass when the extension
        is built (the same values); ``native=False``: NumPy's passes (the tests compare the two)."""
        xyz = data.xyz
        # Contiguous copies: every pass over a strided column of xyz costs about twice as much.
        x, y, z = (np.ascontiguousarray(xyz[:, axis]) for axis in range(3))
        start, end, diff = self.orientation(xyz)
        row, col = self.rows_and_columns(data.ring, x, y, z)
        time = None if data.time is None else np.ascontiguousarray(data.time, dtype=_F32)
        pixels = self._pixels_in_c if native and _projection_kernels is not None else self._pixels
        full, full_info, range_image, winner_of_pixel, time_image, stats = pixels(x, y, z, row, col, time)
        return RangeImage(
            full_cloud=full,
            full_info_cloud=full_info,
            range=range_image,
            filled=winner_of_pixel >= 0,
            point_of_pixel=winner_of_pixel,
            time=time_image,
            start_orientation=start,
            end_orientation=end,
            orientation_diff=diff,
            stats=stats,
        )

    def _pixels(self, x, y, z, row, col, time) -> tuple:
        """(full cloud, full info cloud, range image, winner of each pixel, pixel times or None, stats) of the
        points x, y, z (float32) at their row and column (int64, -1 outside), with their times (float32) or
        None: the fields of :class:`RangeImage`."""
        h = self.horizon_scan
        rng = np.sqrt(x * x + y * y + z * z)  # float32, as sqrt(x*x + y*y + z*z) on floats
        keep = (row >= 0) & (col >= 0) & (rng >= self._min_range)
        pixel_of_point = (col + row * h)[keep]
        kept = np.flatnonzero(keep)
        # Later points overwrite earlier ones in the same pixel: the largest point index wins.
        winner_of_pixel = np.full(self.n_scan * h, -1, dtype=np.int64)
        np.maximum.at(winner_of_pixel, pixel_of_point, kept)
        filled = winner_of_pixel >= 0

        # Every per-pixel image is one row gather from a per-point table whose extra last row (index -1)
        # holds the empty pixel's values; np.take is ~10x faster than fancy indexing on 2-D rows.
        table = np.empty((len(x) + 1, 4), dtype=_F32)
        for axis, values in enumerate((x, y, z)):  # column by column: ~3x faster than one (n, 3) -> (n, 4) copy
            table[:-1, axis] = values
        table[:-1, 3] = rng
        table[-1] = (np.nan, np.nan, np.nan, -1.0)  # an empty pixel's intensity is -1 in both clouds
        full_info = np.take(table, winner_of_pixel, axis=0)
        range_image = np.take(np.append(rng, np.finfo(np.float32).max), winner_of_pixel)  # FLT_MAX where empty
        full = full_info.copy()
        np.copyto(full[:, 3], self._pixel_intensity, where=filled)
        time_image = None if time is None else np.append(time, _F32(0.0))[winner_of_pixel]
        stats = dict(
            dropped_outside=int(np.count_nonzero((row < 0) | (col < 0))),
            dropped_close=int(np.count_nonzero((row >= 0) & (col >= 0) & ~keep)),
            overwritten=int(len(kept) - np.count_nonzero(filled)),
        )
        return full, full_info, range_image, winner_of_pixel, time_image, stats

    def _pixels_in_c(self, x, y, z, row, col, time) -> tuple:
        """:meth:`_pixels` in one C pass (native/projection_kernels.c), the same values."""
        pixels = self.n_scan * self.horizon_scan
        winner_of_pixel, range_image = np.empty(pixels, dtype=np.int64), np.empty(pixels, dtype=_F32)
        full_info, full = np.empty((pixels, 4), dtype=_F32), np.empty((pixels, 4), dtype=_F32)
        time_image = None if time is None else np.empty(pixels, dtype=_F32)
        no_time = np.empty(0, _F32)
        outside, close, kept, filled = _projection_kernels.range_image(
            x,
            y,
            z,
            np.ascontiguousarray(row, dtype=np.int64),
            np.ascontiguousarray(col, dtype=np.int64),
            self._min_range,
            self.n_scan,
            self.horizon_scan,
            self._pixel_intensity,
            no_time if time is None else time,
            winner_of_pixel,
            range_image,
            full_info,
            full,
            no_time if time_image is None else time_image,
        )
        stats = dict(dropped_outside=outside, dropped_close=close, overwritten=kept - filled)
        return full, full_info, range_image, winner_of_pixel, time_image, stats
