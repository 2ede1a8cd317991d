"""imageProjection's ground removal (docs/original.md §6.1): which range-image pixels are ground.

The original's pair test (vertical neighbours in the lowest rows whose slope lies within a band around the
sensor's mount angle) in its float32 arithmetic, optionally refined (``image_projection.ground_rule``) by a
vertical-surface test, a plane fit and a walk up each column.

Frames: points are in the sensor frame (REP-103 lidar axes, ``base_link``).
"""

from __future__ import annotations

import math

import numpy as np

from lego_loam_py.core.geometry import affine_fit
from lego_loam_py.core.params.types import Params
from lego_loam_py.core.parity.atan2f_decisions import atan2f_exceeds, first_float32_where
from lego_loam_py.core.parity.libm import float_degrees

try:  # the ground walk in C (native/projection_kernels.c); optional: the NumPy loop gives the same result
    from lego_loam_py.core import _projection_kernels
except ImportError:
    _projection_kernels = None

__all__ = ['GroundRemoval', 'float32_hypot']

_F32 = np.float32


def float32_hypot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``np.hypot`` of float32 arrays, bit for bit where neither is infinite, in a third of its time.

    NumPy's float32 hypot is glibc's hypotf (one call per value), which for finite float32 inputs returns
    (float) sqrt((double) x * x + (double) y * y): the squares are exact in float64, so its FMA build gives the
    same. Here those operations run as whole-array passes. NaN gives NaN either way; an infinite input with a
    NaN gives +inf in glibc and NaN here (both compare false).
    """
    x64, y64 = x.astype(np.float64), y.astype(np.float64)
    x64 *= x64
    y64 *= y64
    x64 += y64
    return np.sqrt(x64, out=x64).astype(_F32)


class GroundRemoval:
    """Ground detection for one sensor configuration; :meth:`ground` handles one scan's range image."""

    def __init__(self, params: Params):
        self.params = params
        s = params.sensor
        self.n_scan = s.n_scan
        self.horizon_scan = s.horizon_scan
        # The original's float constants.
        self._mount_angle = _F32(s.sensor_mount_angle)
        self._slope_threshold = _F32(params.image_projection.ground_slope_threshold)
        # The slope test as angle thresholds: a pair is ground where its libm angle a has band 1, that is
        # a > _slope_above and not a > _slope_at_most (the band is monotone in a, so these are exact).
        band_starts = first_float32_where(lambda a: self._slope_band(a) >= np.array([1, 2]), -math.pi, math.pi, 2)
        self._slope_above, self._slope_at_most = np.nextafter(band_starts, _F32(-np.inf))

    def ground(self, full: np.ndarray, filled: np.ndarray) -> np.ndarray:
        """Ground pixels (the original's groundMat == 1) as a boolean (N_SCAN*H,) mask.

        ``full`` is the (N_SCAN*H, 4) projected cloud, ``filled`` marks non-empty pixels. Pairs of vertically
        adjacent pixels in rows 0..ground_scan_ind are ground when their slope is within the threshold of
        the mount angle; the original's write order is kept (a later empty pair un-marks row i+1).
        """
        n, h = self.n_scan, self.horizon_scan
        g = self.params.sensor.ground_scan_ind
        refined = self.params.image_projection.ground_rule == 'refined'
        # Rows that can hold ground (and, refined, the row above them), as contiguous coordinate planes: strided
        # (n, h, 4) views are slow. The steps between vertical neighbours serve the pair test (rows 0..g) and the
        # refinement (one row more).
        top = min(g + 2, n) if refined else g + 1
        f = filled.reshape(n, h)
        planes = full.reshape(n, h, 4)[:top]
        x, y, z = (np.ascontiguousarray(planes[..., axis]) for axis in range(3))
        with np.errstate(invalid='ignore'):
            dx, dy, dz = x[1:] - x[:-1], y[1:] - y[:-1], z[1:] - z[:-1]
        empty_pair = ~(f[:g] & f[1 : g + 1])
        with np.errstate(invalid='ignore'):
            # The angle of (horizontal, dz) with horizontal >= 0 lies in [-pi/2, pi/2].
            dx_g, dy_g = dx[:g], dy[:g]
            above, beyond = atan2f_exceeds(
                dz[:g],
                np.sqrt(dx_g * dx_g + dy_g * dy_g),
                [self._slope_above, self._slope_at_most],
                (-math.pi / 2, math.pi / 2),
            )
            slope_ok = above & ~beyond
        ground_pair = ~empty_pair & slope_ok
        # Iteration i writes row i (-1 if the pair has an empty pixel, 1 if ground) and row i+1 (1 if
        # ground); iteration i+1 runs later and may overwrite row i+1 with -1. So row i ends ground where its
        # own pair is (never empty then), or the pair below it is and its own pair is not empty; row g where
        # the pair below it is.
        ground = np.zeros((n, h), dtype=bool)
        ground[1 : g + 1] = ground_pair
        ground[:g] &= ~empty_pair
        ground[:g] |= ground_pair
        if refined:
            ground = self._refine_ground((x, y, z), (dx, dy, dz), f, ground)
        return ground.reshape(-1)

    def _slope_band(self, angle: np.ndarray) -> np.ndarray:
        """0 / 1 / 2 where the pair slope [rad] is below / within / above the ground band around the mount
        angle. Band 1 is the original's |deg(angle) - mount| <= threshold; the band index, unlike that test,
        is monotone in the angle, so its changes are two angle thresholds."""
        off = float_degrees(angle) - self._mount_angle
        return (off >= -self._slope_threshold).astype(np.int8) + (off > self._slope_threshold)

    def _refine_ground(
        self, planes: tuple, steps: tuple, f: np.ndarray, ground: np.ndarray, native: bool = True
    ) -> np.ndarray:
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
        x, y, z = planes  # float32 (top, H) [m]: the rows that can hold ground and the one above them
        dx, dy, dz = steps  # float32 (top - 1, H) [m]: each row's step to the row above
        top = len(x)
        ground = ground.copy()
        if native and _projection_kernels is not None:  # the same tests in C, pair by pair
            ratio, max_gap = _F32(ip.ground_vertical_ratio), _F32(ip.ground_vertical_gap)
            ground_rows = ground[:top]  # (rewritten in place)
            _projection_kernels.vertical_pairs(dx, dy, dz, x, y, f, top, self.horizon_scan, ratio, max_gap, ground_rows)
        else:
            both = f[: top - 1] & f[1:top]
            with np.errstate(invalid='ignore'):
                gap = float32_hypot(dx, dy)  # (np.hypot's values; NaN and inf only compare false below, either way)
                rise = np.abs(dz)
                reach = float32_hypot(x[:-1], y[:-1])
                vertical = both & (rise > ip.ground_vertical_ratio * gap) & (gap < ip.ground_vertical_gap * reach)
            ground[: top - 1] &= ~vertical
            ground[1:top] &= ~vertical
        pixels = np.flatnonzero(ground)
        if len(pixels) < 10:
            return ground
        # Ground lies in rows < top only: the planes hold every candidate (float32 values, exact in float64).
        ground_x, ground_y, ground_z = (plane.reshape(-1)[pixels].astype(np.float64) for plane in (x, y, z))
        reach = np.hypot(ground_x, ground_y)
        tolerance = np.maximum(ip.ground_plane_tolerance, ip.ground_plane_tolerance_ratio * reach)
        near = reach <= ip.ground_plane_radius
        fit_near = near.sum() >= 10
        keep = near if fit_near else np.ones(len(pixels), dtype=bool)
        for _ in range(3):
            if keep.sum() < 3:
                break
            slope_x, slope_y, height = affine_fit(ground_x[keep], ground_y[keep], ground_z[keep])
            # (of the last plane fitted, after the loop)
            fits = np.abs(ground_z - (slope_x * ground_x + slope_y * ground_y + height)) <= tolerance
            refit = fits & (near if fit_near else True)
            if np.array_equal(refit, keep):
                break  # the same points give the same plane again: the remaining rounds change nothing
            keep = refit
        on_plane = np.zeros(top * self.horizon_scan, dtype=bool)
        on_plane[pixels] = fits
        far = np.ones(top * self.horizon_scan, dtype=bool)
        far[pixels] = ~near
        on_plane, far = on_plane.reshape(top, -1), far.reshape(top, -1)
        slope = math.tan(math.radians(ip.ground_chain_slope))
        if native and _projection_kernels is not None:  # the same walk in C, column by column
            _projection_kernels.ground_walk(
                x, y, z, top, self.horizon_scan, ground[:top], far, on_plane, slope, ip.ground_chain_tolerance
            )
            return ground
        # The walk up the columns: a loop over the few ground rows, vectorised over the columns.
        points = np.empty((3,) + x.shape)  # float64 (3, top, H): the planes as one array
        points[0], points[1], points[2] = x, y, z
        last = np.full((3, self.horizon_scan), np.nan)  # each column's last ground point
        seeded = np.zeros(self.horizon_scan, dtype=bool)
        # (Few calls a row, into buffers: on 2083-column rows a numpy call's own cost is a large part.)
        step, apart = np.empty(self.horizon_scan), np.empty((3, self.horizon_scan))
        continues, accepted = np.empty(self.horizon_scan, dtype=bool), np.empty(self.horizon_scan, dtype=bool)
        with np.errstate(invalid='ignore'):
            for r in range(top):
                candidate = ground[r]
                if not candidate.any():
                    continue
                np.subtract(points[:, r], last, out=apart)
                np.hypot(apart[0], apart[1], out=step)
                step *= slope
                step += ip.ground_chain_tolerance
                np.abs(apart[2], out=apart[2])
                np.less_equal(apart[2], step, out=continues)
                # Unseeded columns have a NaN last point: no continuation is needed there.
                np.logical_or(continues, ~seeded, out=continues)
                np.logical_and(seeded, far[r], out=accepted)
                accepted |= on_plane[r]
                accepted &= candidate
                accepted &= continues
                ground[r] = accepted
                np.copyto(last, points[:, r], where=accepted)
                seeded |= accepted
        return ground
