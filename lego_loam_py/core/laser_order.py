"""Range-image rows of a cloud without a ring field whose points are stored laser by laser.

Some recordings keep each laser's points together, one whole turn after the other, and drop the ring field:
KITTI's scans (the HDL-64E's lasers from the top one down, each starting as the laser faces forward), and an
organised cloud whose rows are beams. The point order then says which laser measured a point, where the
elevation angle cannot: a laser's elevation seen from the sensor origin changes with range by its vertical
offset in the head (tenths of a degree at 10 m), and a real unit's beams sit off the published table by about
as much, so on KITTI's scans the nearest beam of the nominal table names another laser for most points of the
lower block.

Such a cloud is recognised by its azimuth, unwrapped along the point order, turning about once per laser
(a driver's cloud in firing order turns once). Lasers change where the turns are cut: the azimuth at which
the elevation steps from one laser to the next, the most common azimuth of such steps. Every point gets the
count of cuts before it; rows run from the lowest laser up (row 0 is the lowest beam, as the ring field's),
counted from the first laser in the order (KITTI's last scan of a drive is cut short at its lower lasers).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ['rows_from_laser_order', 'MIN_STEP_DEG']

TWO_PI = 2.0 * math.pi
MIN_STEP_DEG = 0.15       # an elevation step at least this large [deg] may be a change of laser
_CUT_BIN_DEG = 1.0        # histogram bin of the steps' azimuths, and the window refining the most common one


def rows_from_laser_order(x: np.ndarray, y: np.ndarray, z: np.ndarray, n_scan: int) -> np.ndarray | None:
    """int64 row of every point (sensor-frame coordinates [m], in the cloud's order) when the cloud is stored
    laser by laser with at most ``n_scan`` lasers; None when it is not (e.g. in firing order)."""
    if len(x) < 4 * n_scan or n_scan < 2:
        return None
    azimuth = np.arctan2(y, x, dtype=np.float64)
    unwrapped = np.unwrap(azimuth)
    total = float(unwrapped[-1] - unwrapped[0])
    turns = abs(total) / TWO_PI
    if not max(2.0, 0.5 * n_scan) <= turns <= n_scan + 0.5:
        return None
    phase = math.copysign(1.0, total) * (unwrapped - unwrapped[0])   # grows by a turn per laser
    elevation = np.arctan2(z, np.hypot(x, y), dtype=np.float64)
    head = max(1, len(x) // 20)
    top_first = float(np.median(elevation[:head])) > float(np.median(elevation[-head:]))
    step = np.diff(elevation) * (-1.0 if top_first else 1.0)     # positive where the next laser begins
    starts = np.flatnonzero(step > math.radians(MIN_STEP_DEG)) + 1
    if len(starts) < turns / 2:
        return None
    start_phase = np.degrees(np.mod(phase[starts], TWO_PI))
    counts = np.bincount((start_phase // _CUT_BIN_DEG).astype(np.int64), minlength=int(360 / _CUT_BIN_DEG) + 1)
    mode = (int(np.argmax(counts)) + 0.5) * _CUT_BIN_DEG
    near = start_phase[np.abs((start_phase - mode + 180.0) % 360.0 - 180.0) <= 2 * _CUT_BIN_DEG]
    offset = (float(np.median((near - mode + 180.0) % 360.0 - 180.0)) + mode) % 360.0
    # Cut half a point spacing before the steps (a laser's first point lies at the cut or just after it); the
    # first cut at or before the first point: a point's laser is the number of cuts after it up to the point.
    spacing = float(np.median(np.diff(phase)))
    cut = math.radians(offset) - 0.5 * spacing - TWO_PI
    laser = np.floor((phase - cut) / TWO_PI).astype(np.int64)
    laser -= laser[0]
    lasers = int(laser[-1]) + 1
    if lasers > n_scan or np.any(np.diff(laser) < 0):
        return None
    return (n_scan - 1 - laser) if top_first else laser
