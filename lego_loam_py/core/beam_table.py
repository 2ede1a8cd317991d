"""Per-beam elevation tables: the rows of a range image for sensors whose beams are not evenly spaced.

A spinning lidar's lasers sit at fixed elevation angles. The original LeGO-LOAM assumes they are evenly spaced
(``ang_bottom`` + row x ``ang_res_y``), which holds for the VLP-16 (-15 to +15 deg, 2 deg apart) but not for the
HDL-64E, whose two blocks of lasers have different spacings. A table lists every beam's elevation [deg], lowest
first: row ``r`` of the range image is the ``r``-th lowest beam (the ``ring`` convention of the velodyne driver).
Without a ring field, each point goes to the row of the beam nearest to its elevation (:class:`BeamRows`).

Tables come from a sensor preset (:data:`HDL64E_NOMINAL_ELEVATIONS`), from ``sensor.beam_elevations`` or from a
Velodyne calibration file (``sensor.beam_calibration``, :func:`read_velodyne_calibration`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ['HDL64E_NOMINAL_ELEVATIONS', 'BeamRows', 'read_velodyne_calibration', 'table_problem']

# The HDL-64E's nominal beam layout [deg], lowest beam first, from Velodyne's HDL-64E S2 user's manual and data sheet:
# a vertical field of view from +2.0 to -24.33 deg in two blocks of 32 lasers, the upper block from +2.0 down to
# -8.33 deg at 1/3 deg spacing and the lower block from -8.83 down to -24.33 deg at 1/2 deg spacing. Each unit's own
# calibration (db.xml / a velodyne_pointcloud YAML) differs from it by a few tenths of a degree; give that with
# sensor.beam_calibration when you have it.
HDL64E_NOMINAL_ELEVATIONS: tuple[float, ...] = tuple(
    [round(-24.33 + 0.5 * k, 6) for k in range(32)] + [round(2.0 - (31 - k) / 3.0, 6) for k in range(32)])


def table_problem(elevations: tuple[float, ...], n_scan: int) -> str | None:
    """Why ``elevations`` [deg] cannot be the beam table of an ``n_scan``-row image, or None."""
    table = np.asarray(elevations, dtype=np.float64)
    if len(table) != n_scan:
        return f'lists {len(table)} beams but the range image has {n_scan} rows (sensor.n_scan)'
    if not np.all(np.isfinite(table)) or np.any(np.abs(table) >= 90.0):
        return 'must hold finite elevations within (-90, 90) degrees'
    if np.any(np.diff(table) <= 0.0):
        return 'must list the beams from the lowest to the highest, each above the one before'
    return None


class BeamRows:
    """Row of each point from its elevation with a table of beam elevations [deg], lowest first: the nearest beam.

    The decision boundaries are the midpoints between neighbouring beams; a point more than half the outermost
    spacing below the lowest or above the highest beam belongs to none (row -1), as a point outside the
    uniform image's rows does.
    """

    def __init__(self, elevations_deg: tuple[float, ...]):
        table = np.radians(np.asarray(elevations_deg, dtype=np.float64))
        if len(table) < 2:
            raise ValueError('a beam table needs at least two beams')
        middles = 0.5 * (table[1:] + table[:-1])
        self.lowest = table[0] - 0.5 * (table[1] - table[0])       # [rad]
        self.highest = table[-1] + 0.5 * (table[-1] - table[-2])  # [rad]
        self._boundaries = middles
        self.elevations = table                                     # [rad]
        self.n_rows = len(table)

    def rows(self, z: np.ndarray, horizontal: np.ndarray) -> np.ndarray:
        """int64 row of every point from its sensor-frame height ``z`` and horizontal distance [m]; -1 outside."""
        elevation = np.arctan2(np.asarray(z, dtype=np.float64), np.asarray(horizontal, dtype=np.float64))
        row = np.searchsorted(self._boundaries, elevation).astype(np.int64)
        row[(elevation < self.lowest) | (elevation > self.highest)] = -1
        return row

    def spacing(self) -> np.ndarray:
        """(n_rows - 1,) angle [rad] between each row and the row above it."""
        return np.diff(self.elevations)


def read_velodyne_calibration(path: str | Path) -> tuple[float, ...]:
    """The beam table [deg, lowest first] of a Velodyne calibration file in the velodyne_pointcloud YAML layout
    (``lasers:`` entries with ``laser_id`` and ``vert_correction`` [rad], as the ROS driver's ``*db.yaml`` files
    and its ``gen_calibration.py`` output have them). Raises ValueError naming the file and what is wrong."""
    import yaml

    path = Path(path).expanduser()
    try:
        document = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ValueError(f'cannot read the Velodyne calibration {path}: {exc.strerror or exc}') from None
    except yaml.YAMLError as exc:
        raise ValueError(f'the Velodyne calibration {path} is not valid YAML: {exc}') from None
    lasers = document.get('lasers') if isinstance(document, dict) else None
    if not isinstance(lasers, list) or not lasers:
        raise ValueError(f"the Velodyne calibration {path} has no 'lasers' list")
    try:
        elevations = np.degrees([float(laser['vert_correction']) for laser in lasers])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"the Velodyne calibration {path}: every laser needs a numeric 'vert_correction' "
                         '[rad]') from None
    declared = document.get('num_lasers')
    if declared is not None and int(declared) != len(lasers):
        raise ValueError(f'the Velodyne calibration {path} declares num_lasers {declared} but lists '
                         f'{len(lasers)} lasers')
    return tuple(round(float(v), 9) for v in np.sort(elevations))
