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

try:  # the passes over the points in C (native/projection_kernels.c); NumPy's where it is not built
    from lego_loam_py.core import _projection_kernels
except ImportError:  # pragma: no cover
    _projection_kernels = None

__all__ = ['rows_from_laser_order', 'MIN_STEP_DEG', 'median']

TWO_PI = 2.0 * math.pi
_DEG_PER_RAD = 180.0 / math.pi  # np.degrees multiplies by this constant (in a scalar loop: a product is ~6x faster)
MIN_STEP_DEG = 0.15  # an elevation step at least this large [deg] may be a change of laser
_CUT_BIN_DEG = 1.0  # histogram bin of the steps' azimuths, and the window refining the most common one
_RESTART_DEG = 10.0  # the angle from the cut falling back by more than this begins a laser
_CUT_CANDIDATES = 4  # most common azimuths of the elevation steps tried as the cut
_DECIDED_RAD = 1e-9  # an elevation decision this far from its threshold holds for any rounding of the range


def _mod(values: np.ndarray, period: float, bounds: tuple[float, float] | None = None) -> np.ndarray:
    """``np.mod(values, period)`` bit for bit, for float64 ``values`` and a positive ``period``, in a few cheap
    passes where ``np.mod`` (fmod, then a sign fix) costs about 10 ns a value.

    On [-period, 2 period) numpy's result is exact arithmetic: fmod is ``v`` itself below ``period`` in size, or
    ``v - period`` (exact, Sterbenz) above it; a negative remainder then gets ``period`` added (rounded, as here);
    a zero one is +0.0. Anything else (a value out of that range, NaN) goes to ``np.mod``.

    ``bounds``: (low, high) that the caller knows every value lies within (then ``values``, which must hold no
    -0.0, is overwritten with the result); None to find them (``values`` is left alone).
    """
    if bounds is None:
        low, high = (float(values.min()), float(values.max())) if len(values) else (0.0, 0.0)
        out = None
    else:
        (low, high), out = bounds, values
    if not (-period <= low and high < 2.0 * period):
        return np.mod(values, period)
    if out is None:
        out = values + 0.0  # a copy with -0.0 made +0.0 (np.mod's zero is +0.0); every other value as it was
    # (Masks from the values before the first change; the sum may round up to period itself, as np.mod's does.)
    negative, beyond = values < 0.0, values >= period
    np.add(out, period, out=out, where=negative)
    np.subtract(out, period, out=out, where=beyond)
    return out


def median(values: np.ndarray) -> float:
    """``float(np.median(values))`` bit for bit for a 1-D float64 array, several times faster (np.median's NaN check
    and general-axis handling cost more than the selection on a few thousand values).

    The middle order statistics are picked by ``np.partition``; on long arrays out of the values between two bounds
    taken from a sorted sample, which hold them in all but rare cases (then, as for NaN, np.median itself).
    np.median's mean of the two middle values of an even count is taken the same way, with np.mean of the two in
    order.
    """
    n = len(values)
    if n == 0:
        return float(np.median(values))
    upper_mid = n // 2  # the (n // 2)-th smallest value; with an even count also the one before it
    ranks = [upper_mid - 1, upper_mid] if n % 2 == 0 else [upper_mid]
    if n < 4096:
        if np.isnan(values).any():
            return float(np.median(values))
        below, band = 0, values
    else:
        sample = np.sort(values[:: n // 1024])
        at = upper_mid * len(sample) // n
        low = sample[max(at - 64, 0)]
        high = sample[min(at + 64, len(sample) - 1)]
        below = np.count_nonzero(values < low)
        band = values[(values >= low) & (values <= high)]
        above = np.count_nonzero(values > high)
        if below + len(band) + above != n or ranks[0] < below or ranks[-1] >= below + len(band):
            return float(np.median(values))  # NaN, or the middle is outside the band
    local = [r - below for r in ranks]
    middle = np.partition(band, local)[local]
    if not middle.all():
        return float(np.median(values))  # a zero: which of -0.0 and +0.0 np.median picks is its partition's choice
    return float(np.mean(middle))


def _median_is_not_negative(values: np.ndarray) -> bool:
    """``float(np.median(values)) >= 0.0`` for a 1-D float64 array, from a count where the two middle values of
    an even count have the same sign; np.median's mean of the two when they straddle zero."""
    n = len(values)
    negative = int(np.count_nonzero(values < 0.0))
    if n == 0 or np.count_nonzero(values >= 0.0) != n - negative:
        return float(np.median(values)) >= 0.0  # (empty or NaN: np.median's NaN is not >= 0)
    upper_mid = n // 2  # the (n // 2)-th smallest value; with an even count also the one before it
    if n % 2 or negative != upper_mid:
        return bool(negative <= upper_mid if n % 2 else negative < upper_mid)
    # The largest negative value and the smallest other one are the middle pair: np.median's mean of the two.
    pair = np.array([values[values < 0.0].max(), values[values >= 0.0].min()])
    return float(np.mean(pair)) >= 0.0


def _abs_median(values: np.ndarray, kernels) -> float:
    """``median(np.abs(values))`` (float64): by the C module ``kernels``, or NumPy for None, NaN and zero middles."""
    found = kernels.abs_median(values) if kernels is not None else None
    return median(np.abs(values)) if found is None else found


def _laser_starts(x: np.ndarray, y: np.ndarray, z: np.ndarray, single: bool, kernels=None) -> tuple[bool, np.ndarray]:
    """(whether the order runs from the top laser down, indices where the elevation steps to the next laser)
    from float64 coordinates [m]: the elevation is arctan2(z, hypot(x, y)), the step a difference of two.

    Only decisions come out, so where the coordinates are float32 values (``single``) the horizontal range is
    taken as sqrt(x * x + y * y) first, a quarter of np.hypot's time (glibc's hypot, one call a value): the
    squares are exact in float64 and cannot overflow or underflow, so it is within 2**-51 of the exact range
    relatively, as np.hypot (< 1 ulp) is; arctan2 moves by at most half of that [rad] (its derivative in the range
    is at most 1 / (2 range)), plus a few ulps of its own at either range. The elevations agree to within 1e-14
    rad, their differences to within 3e-14. Every decision taken at least _DECIDED_RAD (1e-9 rad) from its
    threshold is therefore the same with np.hypot; otherwise (or with NaN) all is recomputed with np.hypot.
    ``kernels``: the C module to take the steps with (the same decisions), or None for NumPy.
    """
    threshold = math.radians(MIN_STEP_DEG)
    head = max(1, len(x) // 20)
    for exact in (False, True) if single else (True,):
        if exact:
            elevation = np.arctan2(z, np.hypot(x, y))
        else:
            squares = x * x
            squares += y * y
            elevation = np.arctan2(z, np.sqrt(squares, out=squares))
        first, last = float(np.median(elevation[:head])), float(np.median(elevation[-head:]))
        top_first = first > last
        # The elevation rises (falls, from the top laser down) by more than a step where the next laser begins.
        bound = -threshold if top_first else threshold
        if kernels is not None:
            if exact or abs(first - last) > _DECIDED_RAD:
                starts = np.empty(max(len(elevation) - 1, 0), dtype=np.int64)
                count = kernels.elevation_steps(elevation, bound, top_first, 0.0 if exact else _DECIDED_RAD, starts)
                if count >= 0:
                    return top_first, starts[:count]
            continue  # a decision too close to call (or NaN): the exact elevations
        rise = np.diff(elevation)
        if not exact:
            rise -= bound
            np.abs(rise, out=rise)
            if not (abs(first - last) > _DECIDED_RAD and np.all(rise > _DECIDED_RAD)):
                continue  # a decision too close to call (or NaN): the exact elevations
            rise = np.diff(elevation)
        return top_first, np.flatnonzero(rise < bound if top_first else rise > bound) + 1
    raise AssertionError('unreachable')  # (the exact pass always returns)


def rows_from_laser_order(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, n_scan: int, native: bool = True
) -> np.ndarray | None:
    """int64 row of every point (sensor-frame coordinates [m], in the cloud's order) when the cloud is stored
    laser by laser with at most ``n_scan`` lasers; None when it is not (e.g. in firing order). The passes over the
    points run in C when the extension is built (the same values: the arctangents stay NumPy's); ``native=False``
    runs NumPy's alone (the tests compare the two)."""
    if len(x) < 4 * n_scan or n_scan < 2:
        return None
    single = all(np.asarray(c).dtype == np.float32 for c in (x, y, z))
    # float64 copies made once: the ufuncs' own casting (dtype=np.float64) feeds the same loops in buffers, slower.
    x, y, z = (np.asarray(c, dtype=np.float64) for c in (x, y, z))
    kernels = _projection_kernels if native else None
    azimuth = np.arctan2(y, x)
    step = np.diff(azimuth)
    step = _mod(step + math.pi, TWO_PI) - math.pi
    direction = 1.0 if _median_is_not_negative(step) else -1.0  # the way the order turns
    top_first, starts = _laser_starts(x, y, z, single, kernels)
    if len(starts) < n_scan // 4:
        return None
    # The cut: an azimuth (in the order's sense of turning) at which lasers begin; of the few most common ones,
    # the one that leaves the fewest restarts (a wrong one also restarts every whole turn that crosses it).
    turned = _mod(direction * azimuth, TWO_PI) * _DEG_PER_RAD  # [deg]; np.mod's zeros are +0.0
    turned_low, turned_high = float(turned.min()), float(turned.max())
    counts = np.bincount((turned[starts] // _CUT_BIN_DEG).astype(np.int64), minlength=int(360 / _CUT_BIN_DEG) + 1)
    spacing = math.degrees(_abs_median(step, kernels))
    begins = None
    for peak in np.argsort(counts)[::-1][:_CUT_CANDIDATES]:
        if counts[peak] == 0:
            break
        mode = (int(peak) + 0.5) * _CUT_BIN_DEG
        near = (turned[starts] - mode + 180.0) % 360.0 - 180.0
        cut = mode + float(np.median(near[np.abs(near) <= 2 * _CUT_BIN_DEG]))
        # Half a point spacing before it, so that a laser's first point (at the cut or just after) falls after it.
        # Rounding is monotone: the ends of turned, shifted by the same operations, bound every value (none is
        # -0.0: u - cut is +0.0 where they are equal, and turned holds no -0.0).
        bounds = ((turned_low - cut) + 0.5 * spacing, (turned_high - cut) + 0.5 * spacing)
        if kernels is not None and -360.0 <= bounds[0] and bounds[1] < 720.0:  # (_mod's fast range)
            candidate = np.empty(max(len(turned) - 1, 0), dtype=np.int64)
            candidate = candidate[: kernels.restarts(turned, cut, 0.5 * spacing, _RESTART_DEG, candidate)]
        else:
            from_cut = turned - cut
            from_cut += 0.5 * spacing
            from_cut = _mod(from_cut, 360.0, bounds)
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
