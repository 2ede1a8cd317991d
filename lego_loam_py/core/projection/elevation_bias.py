"""A common error of every beam's elevation, found from the ground ahead of and behind the lidar, and corrected.

A lidar whose beams all point a little lower than its calibration says sees flat ground as a shallow cone:
ground at horizontal range ``rho`` reads ``rho tan(delta)`` low. Driving forward, the ground ahead then seems to
rise by ``tan(delta)`` per metre travelled, and the odometry and the map sink and pitch with it. KITTI's HDL-64E
reads about 0.2 deg low (its scans sink 0.8 m and pitch 0.8 deg over the 107 m of the shared city drive).

Each scan's ground pixels ahead and behind (azimuth within :data:`SECTOR_DEG` of the x axis, horizontal range
:data:`MIN_RANGE`..:data:`MAX_RANGE`) are fitted with ``z = a + b x + c rho`` (trimmed least squares): a slope
along the path goes to ``b``, the cone to ``c = -tan(delta)``. The sides are left out (kerbs and pavements
rise there). A hill's crest or dip under the lidar bends the ground like a cone, but not scan after scan by the
same amount: the correction is taken only once :data:`MIN_SCANS` scans agree (their median absolute deviation
within :data:`MAX_SPREAD_DEG`) on an error of at least :data:`MIN_OFFSET_DEG` and at most
:data:`MAX_OFFSET_DEG`; it is then fixed (a calibration does not change) and every later scan is corrected:
``z += rho tan(delta)``, the first-order change of the elevation (x and y move by ``delta^2 / 2`` of the range).
The simulated scenarios' rolling ground never agrees (spread 1.1 deg), so they are not touched.
"""

from __future__ import annotations

import math

import numpy as np

from lego_loam_py.core.geometry import affine_fit
from lego_loam_py.core.projection.ground import float32_hypot
from lego_loam_py.core.projection.laser_order import median

__all__ = ['ElevationBias', 'apply_elevation_offset', 'ground_cone_deg', 'elevation_note']

SECTOR_DEG = 30.0  # ground within this azimuth of straight ahead or behind
MIN_RANGE, MAX_RANGE = 5.0, 35.0  # [m] horizontal range of the fitted ground
MIN_GROUND_POINTS = 100
MIN_SCANS = 20  # scans that must agree before a correction is taken
MAX_SPREAD_DEG = 0.1  # ... their estimates' median absolute deviation at most this
MIN_OFFSET_DEG = 0.05  # an error smaller than this is left alone
MAX_OFFSET_DEG = 0.5  # ... and one larger than this is not a calibration error but the ground's shape
GIVE_UP_SCANS = 600  # no agreement after this many scans: stop looking (the ground is not flat enough)


def apply_elevation_offset(xyz: np.ndarray, offset_deg: float) -> None:
    """Raise every point's elevation by ``offset_deg`` [deg], in place on (n, 3) float32 sensor-frame points."""
    if offset_deg:
        rho = float32_hypot(xyz[:, 0], xyz[:, 1])  # np.hypot's float32 values, in a third of its time
        xyz[:, 2] += np.float32(math.tan(math.radians(offset_deg))) * rho


def elevation_note(offset_deg: float, stamp_ns: int) -> str:
    """What a run tells its user when it found the correction (once)."""
    return (
        f'scan at {stamp_ns * 1e-9:.3f} s: the ground ahead and behind says every point reads {abs(offset_deg):.2f} '
        f'deg {"low" if offset_deg > 0 else "high"}; scans are corrected from here on (set '
        f'sensor.elevation_offset: {offset_deg:g} to correct them from the first one)'
    )


def ground_cone_deg(ground_xyz: np.ndarray) -> float | None:
    """The elevation error [deg] the ground points ahead and behind say (positive: the beams read low), or None
    when there are too few of them."""
    x, y, z = (ground_xyz[:, axis].astype(np.float64) for axis in range(3))
    rho = np.hypot(x, y)
    cos_sector = math.cos(math.radians(SECTOR_DEG))
    keep = (rho > MIN_RANGE) & (rho < MAX_RANGE) & (np.abs(x) > cos_sector * rho)
    ahead = np.count_nonzero(keep & (x > 0))
    if (
        min(ahead, np.count_nonzero(keep) - ahead) < MIN_GROUND_POINTS // 4
        or np.count_nonzero(keep) < MIN_GROUND_POINTS
    ):
        return None  # (a slope and a cone are told apart only by ground on both sides)
    x, rho, z = x[keep], rho[keep], z[keep]
    used = np.ones(len(z), dtype=bool)
    for _ in range(4):  # trimmed: points beyond three robust deviations of the fit are left out
        if np.count_nonzero(used) < 3:
            break
        slope, cone, height = affine_fit(x[used], rho[used], z[used])
        residual = np.abs(z - (slope * x + cone * rho + height))
        scale = 1.5 * median(residual) + 1e-3
        used = residual < 3.0 * scale
    return -math.degrees(math.atan(cone))


class ElevationBias:
    """The elevation correction of one sensor: ``fixed`` [deg] from the parameters, or found from the ground when
    ``estimate`` (and nothing is fixed); see the module docstring."""

    def __init__(self, fixed: float = 0.0, estimate: bool = True):
        self.offset_deg = float(fixed)
        self.found = False  # the estimate was taken (the offset came from the ground)
        self._looking = bool(estimate) and fixed == 0.0
        self._estimates: list[float] = []
        self._scans = 0

    @property
    def looking(self) -> bool:
        return self._looking

    def correct(self, xyz: np.ndarray) -> None:
        """Correct a scan's points (in place) with the offset known so far."""
        apply_elevation_offset(xyz, self.offset_deg)

    def observe(self, ground_xyz: np.ndarray) -> float | None:
        """A scan's ground points (sensor frame, as corrected); returns the offset [deg] when it was just found."""
        if not self._looking:
            return None
        self._scans += 1
        estimate = ground_cone_deg(ground_xyz)
        if estimate is not None:
            self._estimates.append(estimate)
            recent = np.array(self._estimates[-2 * MIN_SCANS :])
            if len(recent) >= MIN_SCANS:
                median = float(np.median(recent))
                spread = float(np.median(np.abs(recent - median)))
                if spread <= MAX_SPREAD_DEG and MIN_OFFSET_DEG <= abs(median) <= MAX_OFFSET_DEG:
                    self.offset_deg, self.found, self._looking = round(median, 3), True, False
                    return self.offset_deg
        if self._scans >= GIVE_UP_SCANS:
            self._looking = False
        return None
