"""Every lidar driver's cloud read into the same points, rings and times.

:mod:`lego_loam_py.core.pointcloud` views a PointCloud2's bytes as a structured array whatever its fields; this
module decides what the fields mean, so that the pipeline gets the same valid points, rows and times from the
drivers users have (README, "Driver layouts"):

* **Coordinates**: ``x``, ``y``, ``z`` of any numeric type (float64 too), read as float32. Points that are no
  measurement are dropped and counted: NaN or inf (the Velodyne driver's organized clouds hold NaN where a laser
  had no return), beyond ``MAX_COORDINATE``, and exactly at the origin (Ouster's organized clouds hold
  x = y = z = 0 there).
* **Order**: the order the points were measured in. imageProjection takes the sweep's start and end orientation
  from its first and last point, but an organized cloud may be stored beam by beam (ouster-ros: one row per beam),
  so that its first valid point lies anywhere in the sweep. When the first or last valid point is not among the
  earliest or latest by the time field, the points are put in time order (stable sort).
* **Beam**: the ring field, 0 the lowest beam as LeGO-LOAM's range image needs. ouster-ros numbers its rows from
  the top beam and Hesai its channels; which way a cloud counts is read from its points (each ring's mean
  elevation rises or falls with the ring number), and a cloud counted from the top is turned round within
  ``sensor.n_scan`` rows (rings beyond them stay beyond).
* **Time**: the package's convention is seconds since the sweep start (``sensor.time_field``). The field is
  ``sensor.time_field`` when the cloud has it, else the first of ``time`` (Velodyne, s), ``t`` (Ouster, uint32 ns
  since the scan start), ``offset_time`` (Livox, uint32 ns since the header stamp), ``timestamp`` (Hesai,
  RoboSense: absolute float64 s). Its unit is the one of s, ms, us, ns in which the cloud's times span about a
  scan period (:data:`SWEEP_SPAN`); a cloud whose times span too little to tell (a few points) keeps the type's
  unit (float: s, integer: ns). Absolute times (``timestamp``, or values beyond :data:`ABSOLUTE_AFTER`) are
  counted from the sweep's earliest valid point.

A layout that cannot be read raises :class:`~lego_loam_py.core.pointcloud.CloudLayoutError` with one line
naming the field and what was expected.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.pointcloud import CloudLayoutError
from lego_loam_py.core.validation import MAX_COORDINATE

__all__ = [
    'CloudPoints',
    'TimeReading',
    'read_cloud',
    'time_field_of',
    'seconds_since_sweep_start',
    'rings_count_down',
    'KNOWN_TIME_FIELDS',
    'ABSOLUTE_TIME_FIELDS',
    'SWEEP_SPAN',
    'ABSOLUTE_AFTER',
    'TIME_ORDER_TOLERANCE',
]

_F32 = np.float32

# Per-point time fields of the common drivers, in the order they are looked for when the cloud lacks
# sensor.time_field: Velodyne (and this package) 'time' [s since the sweep start], Ouster 't' [uint32 ns since
# the scan start], Livox 'offset_time' [uint32 ns since the header stamp], Hesai and RoboSense 'timestamp'
# [absolute float64 s].
KNOWN_TIME_FIELDS = ('time', 't', 'offset_time', 'timestamp')
ABSOLUTE_TIME_FIELDS = frozenset({'timestamp'})
# A sweep's times span between these multiples of sensor.scan_period (a partial sweep: an azimuth window, a
# sensor spinning faster or slower than configured); 200x apart, so s, ms, us and ns never both fit.
SWEEP_SPAN = (0.05, 10.0)
ABSOLUTE_AFTER = 1e4  # [s] a time this far from the stamp is a clock's, not an offset within the sweep
TIME_UNITS = (('s', 1.0), ('ms', 1e-3), ('us', 1e-6), ('ns', 1e-9))
# The first and last valid points stand for the sweep's start and end when they are within this fraction of
# the scan period of its earliest and latest times (firing offsets within a Velodyne or Hesai block are < 0.06 ms).
TIME_ORDER_TOLERANCE = 0.005
_RING_SAMPLE = 8192  # points looked at to tell which way the rings count


@dataclass(frozen=True)
class TimeReading:
    """How the time field was read: its name, unit ('s', 'ms', 'us', 'ns') and whether it was absolute."""

    field: str
    unit: str
    absolute: bool


@dataclass
class CloudPoints:
    """The valid points of one cloud in measurement order, with their ring and time."""

    xyz: np.ndarray  # float32 (n, 3) [m], finite, none at the origin
    ring: np.ndarray | None  # int64 (n,), 0 = lowest beam; None without a (used) ring field
    time: np.ndarray | None  # float32 (n,) [s since the sweep start]; None without a time field
    source_index: np.ndarray | None  # index in the message of each point (None: all, in message order)
    dropped_non_finite: int = 0  # NaN/inf/beyond MAX_COORDINATE coordinates, ring or time
    dropped_origin: int = 0  # x = y = z = 0 (no return)
    time_reading: TimeReading | None = None
    time_ordered: bool = False  # the points were put in time order
    rings_from_top: bool = False  # the ring field counted from the top beam and was turned round


def time_field_of(names: tuple[str, ...], configured: str) -> str | None:
    """The time field of a cloud with fields ``names``: ``configured`` (sensor.time_field) when present, else the
    first known one; None when there is none or ``configured`` is empty (times switched off)."""
    if not configured:
        return None
    if configured in names:
        return configured
    return next((name for name in KNOWN_TIME_FIELDS if name in names), None)


def seconds_since_sweep_start(values: np.ndarray, field: str, scan_period: float) -> tuple[np.ndarray, TimeReading]:
    """float32 seconds since the sweep start of the valid points' ``values`` of time field ``field``, and how they
    were read. Raises CloudLayoutError when their span is about a scan period in none of s, ms, us, ns."""
    if values.size == 0:
        return np.zeros(0, dtype=_F32), TimeReading(field, 's', False)
    low, high = values.min(), values.max()
    integer = values.dtype.kind in 'iu'
    span = float(int(high) - int(low)) if integer else float(high) - float(low)
    unit, scale = _unit(span, field, values.dtype, scan_period)
    absolute = field in ABSOLUTE_TIME_FIELDS or abs(float(low)) * scale > ABSOLUTE_AFTER
    if absolute:
        offsets = (values - low) if integer else values.astype(np.float64) - float(low)
        seconds = (offsets.astype(np.float64) * scale).astype(_F32)
    elif scale == 1.0:
        seconds = values.astype(_F32)
    else:
        seconds = (values * scale).astype(_F32)
    return seconds, TimeReading(field, unit, absolute)


def _unit(span: float, field: str, dtype: np.dtype, scan_period: float) -> tuple[str, float]:
    low, high = SWEEP_SPAN[0] * scan_period, SWEEP_SPAN[1] * scan_period
    for unit, scale in TIME_UNITS:
        if low <= span * scale <= high:
            return unit, scale
    unit, scale = TIME_UNITS[-1] if dtype.kind in 'iu' else TIME_UNITS[0]
    if span * scale < low:  # too short a span to tell (a few points): the type's usual unit
        return unit, scale
    raise CloudLayoutError(
        f"time field '{field}' ({dtype.name}) spans {span:.6g} within one cloud: expected about "
        f'one scan period (sensor.scan_period {scan_period:g} s) in s, ms, us or ns'
    )


def rings_count_down(ring: np.ndarray, xyz: np.ndarray, n_scan: int) -> bool:
    """Whether ring numbers count from the top beam: the mean elevation of the rings' points falls with the ring
    number over at least 3/4 of the steps between populated rings within ``n_scan`` (a sample of the points)."""
    step = max(1, len(ring) // _RING_SAMPLE)
    rings = ring[::step]
    inside = (rings >= 0) & (rings < n_scan)
    every = bool(inside.all())  # (as a driver's rings are: the columns are then taken without a selection)
    if not every:
        rings = rings[inside]
    # Column by column: a boolean selection of the strided (n, 3) rows, or its float64 copy, costs several times more.
    x, y, z = (xyz[::step, axis] if every else xyz[::step, axis][inside] for axis in range(3))
    horizontal = np.hypot(x.astype(np.float64), y.astype(np.float64))
    slope = z.astype(np.float64) / np.maximum(horizontal, 1e-6)  # tan(elevation), monotone in it
    count = np.bincount(rings, minlength=n_scan)
    populated = np.flatnonzero(count)
    if len(populated) < 2:
        return False
    mean = np.bincount(rings, weights=slope, minlength=n_scan)[populated] / count[populated]
    steps = np.diff(mean)
    return bool(np.count_nonzero(steps < 0) * 4 >= 3 * len(steps))


def read_cloud(
    points: np.ndarray, n_scan: int, ring_field: str | None, time_field: str, scan_period: float
) -> CloudPoints:
    """The valid points of a structured cloud (any shape; organized clouds row-major) as the module says.

    ``ring_field``: the beam index field to use (None: rows from the elevation); ``time_field``:
    sensor.time_field. Raises CloudLayoutError naming the field for a layout that cannot be read.
    """
    names = points.dtype.names or ()
    missing = [name for name in 'xyz' if name not in names]
    if missing:
        raise CloudLayoutError(
            f'the cloud has no {"/".join(missing)} field (fields: {", ".join(names) or "none"}): '
            'expected x, y and z coordinates'
        )
    ring_field = ring_field if ring_field in names else None
    time_name = time_field_of(names, time_field)
    several = [name for name in ('x', 'y', 'z', ring_field, time_name) if name and points.dtype[name].shape != ()]
    if several:
        raise CloudLayoutError(f'field(s) {", ".join(several)} hold several values per point (count > 1): expected one')
    flat = points.reshape(-1)
    xyz = np.empty((flat.size, 3), dtype=_F32)
    with np.errstate(invalid='ignore', over='ignore'):
        xyz[:, 0], xyz[:, 1], xyz[:, 2] = flat['x'], flat['y'], flat['z']
    # NaN and inf fail the bound too; column by column: ~30x faster than reducing (n, 3) along axis 1.
    valid = np.abs(xyz[:, 0]) <= MAX_COORDINATE
    valid &= np.abs(xyz[:, 1]) <= MAX_COORDINATE
    valid &= np.abs(xyz[:, 2]) <= MAX_COORDINATE
    ring = None
    if ring_field is not None:
        ring = flat[ring_field]
        if ring.dtype.kind == 'f':
            valid &= np.isfinite(ring)
            ring = np.where(valid, ring, 0)
        ring = ring.astype(np.int64)
    raw_time = flat[time_name] if time_name is not None else None
    if raw_time is not None and raw_time.dtype.kind == 'f':
        valid &= np.isfinite(raw_time)
    non_finite = int(flat.size - np.count_nonzero(valid))
    at_origin = (xyz[:, 0] == 0) & (xyz[:, 1] == 0) & (xyz[:, 2] == 0) & valid
    origin = int(np.count_nonzero(at_origin))
    if origin:
        valid &= ~at_origin
    index = None
    if non_finite or origin:
        index = np.flatnonzero(valid)
        xyz = xyz[index]
        ring = ring[index] if ring is not None else None
        raw_time = raw_time[index] if raw_time is not None else None
    out = CloudPoints(
        xyz=xyz, ring=ring, time=None, source_index=index, dropped_non_finite=non_finite, dropped_origin=origin
    )
    if raw_time is not None:
        out.time, out.time_reading = seconds_since_sweep_start(raw_time, time_name, scan_period)
        _put_in_time_order(out, scan_period)
    if out.ring is not None and rings_count_down(out.ring, out.xyz, n_scan):
        inside = (out.ring >= 0) & (out.ring < n_scan)  # (rings beyond the image stay there: dropped, warned about)
        out.ring = np.where(inside, (n_scan - 1) - out.ring, out.ring)
        out.rings_from_top = True
    return out


def _put_in_time_order(cloud: CloudPoints, scan_period: float) -> None:
    """Sort the points by time (stable) unless the first and last already are the earliest and latest."""
    time = cloud.time
    if len(time) < 2:
        return
    tolerance = TIME_ORDER_TOLERANCE * scan_period
    if time[0] - time.min() <= tolerance and time.max() - time[-1] <= tolerance:
        return
    order = np.argsort(time, kind='stable')
    cloud.xyz = cloud.xyz[order]
    cloud.time = time[order]
    cloud.ring = cloud.ring[order] if cloud.ring is not None else None
    cloud.source_index = order if cloud.source_index is None else cloud.source_index[order]
    cloud.time_ordered = True
