"""Range-image rows of a cloud without a ring field whose points are stored laser by laser.

Some recordings keep each laser's points together, one whole turn after the other, and drop the ring field:
KITTI's scans (the HDL-64E's lasers from the top one down, each starting as the laser faces forward), and an
organised cloud whose rows are beams. The point order then says which laser measured a point, where the
elevation angle cannot: a laser's elevation seen from the sensor origin changes with range by its vertical
offset in the head (tenths of a degree at 10 m), and a real unit's beams sit off the published table by about
as much, so on KITTI's scans the nearest beam of the nominal table names another laser for most points of the
lower block.

Lasers are cut at one azimuth: the most common azimuth at which the elevation steps from one point to the
next by a beam spacing. Along one laser the angle turned from that cut only grows; it falls back where the
next laser begins, whether the lasers make whole turns or only arcs (a laser seeing nothing but a wall ahead).
A cloud is taken to be stored laser by laser when that gives between half of ``n_scan`` and ``n_scan`` lasers (a
driver's cloud in firing order falls back once). Rows run from the lowest laser up (row 0 is the lowest beam, as
the ring field's), counted from the first laser in the order (KITTI's last scan of a drive is cut short at its
lower lasers).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ['rows_from_laser_order', 'MIN_STEP_DEG']

TWO_PI = 2.0 * math.pi
MIN_STEP_DEG = 0.15  # an elevation step at least this large [deg] may be a change of laser
_CUT_BIN_DEG = 1.0  # histogram bin of the steps' azimuths, and the window refining the most common one
_RESTART_DEG = 10.0  # the angle from the cut falling back by more than this begins a laser
_CUT_CANDIDATES = 4  # most common azimuths of the elevation steps tried as the cut


def rows_from_laser_order(x: np.ndarray, y: np.ndarray, z: np.ndarray, n_scan: int) -> np.ndarray | None:
    """int64 row of every point (sensor-frame coordinates [m], in the cloud's order) when the cloud is stored
    laser by laser with at most ``n_scan`` lasers; None when it is not (e.g. in firing order)."""
    if len(x) < 4 * n_scan or n_scan < 2:
        return None
    azimuth = np.arctan2(y, x, dtype=np.float64)
    step = np.diff(azimuth)
    step = np.mod(step + math.pi, TWO_PI) - math.pi
    direction = 1.0 if float(np.median(step)) >= 0.0 else -1.0  # the way the order turns
    elevation = np.arctan2(z, np.hypot(x, y), dtype=np.float64)
    head = max(1, len(x) // 20)
    top_first = float(np.median(elevation[:head])) > float(np.median(elevation[-head:]))
    rise = np.diff(elevation) * (-1.0 if top_first else 1.0)  # positive where the next laser begins
    starts = np.flatnonzero(rise > math.radians(MIN_STEP_DEG)) + 1
    if len(starts) < n_scan // 4:
        return None
    # The cut: an azimuth (in the order's sense of turning) at which lasers begin; of the few most common ones,
    # the one that leaves the fewest restarts (a wrong one also restarts every whole turn that crosses it).
    turned = np.degrees(np.mod(direction * azimuth, TWO_PI))
    counts = np.bincount((turned[starts] // _CUT_BIN_DEG).astype(np.int64), minlength=int(360 / _CUT_BIN_DEG) + 1)
    spacing = math.degrees(float(np.median(np.abs(step))))
    begins = None
    for peak in np.argsort(counts)[::-1][:_CUT_CANDIDATES]:
        if counts[peak] == 0:
            break
        mode = (int(peak) + 0.5) * _CUT_BIN_DEG
        near = (turned[starts] - mode + 180.0) % 360.0 - 180.0
        cut = mode + float(np.median(near[np.abs(near) <= 2 * _CUT_BIN_DEG]))
        # Half a point spacing before it, so that a laser's first point (at the cut or just after) falls after it.
        from_cut = np.mod(turned - cut + 0.5 * spacing, 360.0)
        # Along a laser the angle from the cut only grows; it falls back where the next laser begins.
        candidate = np.flatnonzero(np.diff(from_cut) < -_RESTART_DEG) + 1
        if begins is None or len(candidate) < len(begins):
            begins = candidate
    if begins is None:
        return None
    lasers = len(begins) + 1
    if not max(2.0, 0.5 * n_scan) <= lasers <= n_scan:
        return None
    laser = np.zeros(len(x), dtype=np.int64)
    laser[begins] = 1
    np.cumsum(laser, out=laser)
    return (n_scan - 1 - laser) if top_first else laser
