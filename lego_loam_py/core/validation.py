"""What a sensor and the pipeline can physically produce, and the checks of inputs and state against it.

One home for the bounds that keep a node serving whatever it is sent:

* Inputs are checked before anything is allocated for them or any state is touched. A failed check raises
  :class:`InputRejected`, whose message names the field, the value and the bound, e.g.
  ``/segmented_cloud_info.orientation_diff = 1e-30, outside [3.1406, 9.4258] rad (a sweep's angle)``.
* Each core checks its own state after every step against the same bounds (``health_problem()`` of
  featureAssociation, mapOptimization and transformFusion); a node resets only what is poisoned.

Units: metres, radians, seconds. Clouds are float32 ``(n, 4)`` arrays (x, y, z, intensity).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lego_loam_py.errors import LegoLoamError

__all__ = [
    'InputRejected',
    'MAX_COORDINATE',
    'MAX_POSITION',
    'MAX_ANGULAR_VELOCITY',
    'MAX_ACCELERATION',
    'MAX_SWEEP_TRANSLATION',
    'MAX_SPEED',
    'ORIENTATION_TOLERANCE',
    'check_count',
    'derived_points_limit',
    'raw_points_limit',
    'check_cloud',
    'check_cloud_info',
    'check_pose',
    'pose6_problem',
    'cloud_problem',
    'vector_problem',
]

MAX_COORDINATE = 1e4  # [m] a point further out on any axis is garbage (lidars reach a few hundred m)
MAX_POSITION = 1e6  # [m] a pose further from its origin than 1000 km is garbage, not a map
MAX_ANGULAR_VELOCITY = 100.0  # [rad/s] anything faster is garbage (gyros saturate at 35-70 rad/s)
MAX_ACCELERATION = 1000.0  # [m/s^2] about 100 g (accelerometers saturate at 16-200 g)
MAX_SWEEP_TRANSLATION = 100.0  # [m] between two sweeps (0.1 s): 1000 m/s is no vehicle
MAX_SPEED = 1000.0  # [m/s] an integrated velocity beyond this is garbage
MAX_ANGLE = 100.0  # [rad] Euler angles of a pose six-vector beyond this are garbage
ORIENTATION_TOLERANCE = 1e-3  # [rad] float32 rounding of the sweep orientations, with margin


class InputRejected(LegoLoamError, ValueError):
    """An input outside what the sensor or the pipeline can produce: ``field = value, bound``."""

    def __init__(self, field: str, value: Any, bound: str):
        self.field, self.value, self.bound = field, value, bound
        super().__init__(f'{field} = {_show(value)}, {bound}')


def _show(value: Any) -> str:
    if isinstance(value, (float, np.floating)):
        return f'{float(value):.6g}'
    return str(value)


# ---------------------------------------------------------------------------------------------- inputs


def derived_points_limit(params) -> int:
    """Most points a cloud derived from the range image can hold: one per pixel (rings x columns)."""
    return int(params.sensor.n_scan) * int(params.sensor.horizon_scan)


def raw_points_limit(params) -> int:
    """Most points a raw sensor cloud may hold: ``reliability.max_points_per_pixel`` per range-image pixel (a
    dual-return VLP-16 has 2)."""
    return int(params.reliability.max_points_per_pixel * derived_points_limit(params))


def check_count(field: str, count: int, limit: int, what: str) -> None:
    """Reject ``count`` items beyond ``limit`` (checked on the message header, before anything is decoded)."""
    if count < 0 or count > limit:
        raise InputRejected(field, count, f'more than the {limit} {what}')


def check_cloud(field: str, cloud: np.ndarray, n_scan: int | None = None) -> None:
    """Finite points within :data:`MAX_COORDINATE` on every axis; with ``n_scan``, intensities
    ``row + column / 10000`` of imageProjection's clouds (rows ``0 .. n_scan - 1``)."""
    if len(cloud) == 0:
        return
    xyz = cloud[:, :3]
    finite = np.isfinite(cloud)
    if not finite.all():
        raise InputRejected(field, f'{int((~finite).any(axis=1).sum())} points with NaN or inf', 'must be finite')
    largest = _largest_magnitude(xyz)
    if largest > MAX_COORDINATE:
        raise InputRejected(f'{field} coordinate', largest, f'beyond {MAX_COORDINATE:g} m')
    if n_scan is not None:
        low, high = float(cloud[:, 3].min()), float(cloud[:, 3].max())
        if low < 0 or high >= n_scan:
            value = low if low < 0 else high
            raise InputRejected(
                f'{field} intensity', value, f'outside [0, {n_scan}) (row + column / 10000, rows 0..{n_scan - 1})'
            )


def check_cloud_info(field: str, info, params, n_points: int | None = None) -> None:
    """imageProjection's CloudInfo (a core :class:`~lego_loam_py.core.projection.image_projection.CloudInfo` with array
    fields) on its own and, with ``n_points``, for a segmented cloud of that many points."""
    n_scan, columns = params.sensor.n_scan, params.sensor.horizon_scan
    limit = derived_points_limit(params)
    for name in ('segmented_cloud_range', 'segmented_cloud_col_ind', 'segmented_cloud_ground_flag'):
        length = len(getattr(info, name))
        if length > limit:
            raise InputRejected(f'{field}.{name} length', length, f'more than the {limit} pixels of the range image')
    for name in ('start_ring_index', 'end_ring_index'):
        values = np.asarray(getattr(info, name))
        if len(values) != n_scan:
            raise InputRejected(f'{field}.{name} length', len(values), f'must equal sensor.n_scan ({n_scan})')
        if len(values) and (values.min() < -10 or values.max() > limit + 10):
            bad = int(values.min()) if values.min() < -10 else int(values.max())
            raise InputRejected(f'{field}.{name}', bad, f'outside [-10, {limit + 10}] (pixels of the range image)')
    # The ring indices point into the per-point arrays (end_ring_index of the last ring: the cloud's last point
    # minus the margin): arrays shorter than that cannot belong to any cloud.
    covered = int(np.asarray(info.end_ring_index).max(initial=-1)) + 1
    for name in ('segmented_cloud_range', 'segmented_cloud_col_ind', 'segmented_cloud_ground_flag'):
        length = len(getattr(info, name))
        if length < covered:
            raise InputRejected(
                f'{field}.{name} length', length, f'shorter than the end_ring_index it carries ({covered - 1})'
            )
    start, end, diff = (float(info.start_orientation), float(info.end_orientation), float(info.orientation_diff))
    tolerance = ORIENTATION_TOLERANCE
    # imageProjection: start = -atan2 of the first point, end = start + diff with diff wrapped into [pi, 3 pi].
    if not (math.isfinite(start) and abs(start) <= math.pi + tolerance):
        raise InputRejected(
            f'{field}.start_orientation', start, f'outside [{-math.pi - tolerance:.4f}, {math.pi + tolerance:.4f}] rad'
        )
    if not (math.isfinite(diff) and math.pi - tolerance <= diff <= 3 * math.pi + tolerance):
        raise InputRejected(
            f'{field}.orientation_diff',
            diff,
            f"outside [{math.pi - tolerance:.4f}, {3 * math.pi + tolerance:.4f}] rad (a sweep's angle)",
        )
    if not (math.isfinite(end) and abs(end - start - diff) <= 4 * tolerance):
        raise InputRejected(
            f'{field}.end_orientation', end, f'must equal start_orientation + orientation_diff ({start + diff:.4f} rad)'
        )
    if n_points is None:
        return
    for name in ('segmented_cloud_range', 'segmented_cloud_col_ind', 'segmented_cloud_ground_flag'):
        length = len(getattr(info, name))
        # The original publishes 28800-long arrays whatever the cloud holds: only the first n_points matter.
        if length < n_points:
            raise InputRejected(
                f'{field}.{name} length', length, f'shorter than the segmented cloud ({n_points} points)'
            )
    # (A ring's feature regions run from its start index to its end index; imageProjection's margins put the
    # start up to 10 past the end when a ring holds (almost) nothing, never the end past the cloud.)
    for name, bound in (('start_ring_index', n_points + 10), ('end_ring_index', n_points)):
        values = np.asarray(getattr(info, name))
        if len(values) and values.max() > bound:
            raise InputRejected(f'{field}.{name}', int(values.max()), f'beyond {bound} (the segmented cloud)')
    ranges = np.asarray(info.segmented_cloud_range[:n_points], dtype=np.float64)
    if len(ranges) and not (np.isfinite(ranges).all() and np.abs(ranges).max() <= 2 * MAX_COORDINATE):
        bad = ranges[~np.isfinite(ranges) | (np.abs(ranges) > 2 * MAX_COORDINATE)][0]
        raise InputRejected(
            f'{field}.segmented_cloud_range', float(bad), f'not finite or beyond {2 * MAX_COORDINATE:g} m'
        )
    columns_used = np.asarray(info.segmented_cloud_col_ind[:n_points])
    if len(columns_used) and int(columns_used.max()) >= columns:
        raise InputRejected(
            f'{field}.segmented_cloud_col_ind',
            int(columns_used.max()),
            f'beyond the {columns} columns of the range image',
        )


def check_pose(field: str, pose: np.ndarray) -> None:
    """A 4x4 rigid transform: finite, position within :data:`MAX_POSITION`, a rotation."""
    if not np.isfinite(pose).all():
        raise InputRejected(field, 'NaN or inf', 'must be finite')
    distance = float(np.abs(pose[:3, 3]).max())
    if distance > MAX_POSITION:
        raise InputRejected(f'{field} position', distance, f'beyond {MAX_POSITION:g} m')
    error = float(np.abs(pose[:3, :3] @ pose[:3, :3].T - np.eye(3)).max())
    if error > 1e-3:
        raise InputRejected(f'{field} rotation', f'R R^T - I up to {error:.3g}', 'must be a rotation')


# ----------------------------------------------------------------------------------------------- state


def _largest_magnitude(values: np.ndarray) -> float:
    """max |v| over ``values`` (float32 or float64, non-empty) as a float, NaN when any is NaN. Column by column for
    the rows of a cloud ((n, k) views with a few columns, e.g. a cloud's x, y, z): NumPy reduces such a view a row
    of k at a time, several times slower, and ``np.abs`` would make a copy first."""
    columns = [values[:, j] for j in range(values.shape[1])] if values.ndim == 2 and values.shape[1] <= 8 else [values]
    extremes = [float(v) for column in columns for v in (column.max(), column.min())]  # (NaN propagates in both)
    if not all(math.isfinite(v) for v in extremes):
        return math.nan if any(math.isnan(v) for v in extremes) else math.inf
    return max(abs(v) for v in extremes)


def vector_problem(name: str, values: np.ndarray, bound: float, unit: str) -> str | None:
    """Why ``values`` are not a sane state (non-finite, or beyond ``bound``), or None."""
    values = np.asarray(values)
    if values.dtype != np.float32 and values.dtype != np.float64:
        values = values.astype(np.float64)
    if not values.size:
        return None
    largest = _largest_magnitude(values)
    if not math.isfinite(largest):
        return f'{name} is not finite'
    if largest > bound:
        unit = f' {unit}' if unit else ''
        return f'{name} reach {largest:.3g}{unit} (bound {bound:g}{unit})'
    return None


def pose6_problem(name: str, pose6: np.ndarray, position_bound: float = MAX_POSITION) -> str | None:
    """Why a pose six-vector (rx, ry, rz, tx, ty, tz) is not a sane state, or None."""
    pose6 = np.asarray(pose6, dtype=np.float64)
    return vector_problem(f'{name} angles', pose6[:3], MAX_ANGLE, 'rad') or vector_problem(
        f'{name} position', pose6[3:], position_bound, 'm'
    )


def cloud_problem(name: str, cloud: np.ndarray | None, intensity_bound: float | None = None) -> str | None:
    """Why a cloud held as state is not sane (non-finite, beyond :data:`MAX_COORDINATE`, or intensities beyond
    ``intensity_bound``), or None."""
    if cloud is None or len(cloud) == 0:
        return None
    problem = vector_problem(f'{name} points', cloud[:, :3], 2 * MAX_COORDINATE, 'm')
    if problem is None and intensity_bound is not None:
        problem = vector_problem(f'{name} intensities', cloud[:, 3], intensity_bound, '')
    return problem
