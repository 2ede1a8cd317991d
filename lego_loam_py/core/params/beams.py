"""Per-beam elevation tables: the rows of a range image for sensors whose beams are not evenly spaced.

A spinning lidar's lasers sit at fixed elevation angles. The original LeGO-LOAM assumes they are evenly spaced
(``ang_bottom`` + row x ``ang_res_y``), which holds for the VLP-16 (-15 to +15 deg, 2 deg apart) but not for the
HDL-64E, whose two blocks of lasers have different spacings. A table lists every beam's elevation [deg], lowest
first: row ``r`` of the range image is the ``r``-th lowest beam (the ``ring`` convention of the velodyne driver).
Without a ring field, each point goes to the row of the beam nearest to its elevation (:class:`BeamRows`).

Tables come from a sensor preset (the tables below, as their makers publish them), from ``sensor.beam_elevations``
or from a Velodyne calibration file (``sensor.beam_calibration``, :func:`read_velodyne_calibration`). A unit's own
calibration differs from its model's table by up to a few tenths of a degree; give it when you have it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = [
    'HDL64E_NOMINAL_ELEVATIONS',
    'VLP32C_ELEVATIONS',
    'PANDAR64_ELEVATIONS',
    'PANDAR40P_ELEVATIONS',
    'OS1_128_UNIT_ELEVATIONS',
    'OS0_128_UNIT_ELEVATIONS',
    'BeamRows',
    'read_velodyne_calibration',
    'table_problem',
]

# The HDL-64E's nominal beam layout [deg], lowest beam first, from Velodyne's HDL-64E S2 user's manual and data sheet:
# a vertical field of view from +2.0 to -24.33 deg in two blocks of 32 lasers, the upper block from +2.0 down to
# -8.33 deg at 1/3 deg spacing and the lower block from -8.83 down to -24.33 deg at 1/2 deg spacing. Each unit's own
# calibration (db.xml / a velodyne_pointcloud YAML) differs from it by a few tenths of a degree; give that with
# sensor.beam_calibration when you have it.
HDL64E_NOMINAL_ELEVATIONS: tuple[float, ...] = tuple(
    [round(-24.33 + 0.5 * k, 6) for k in range(32)] + [round(2.0 - (31 - k) / 3.0, 6) for k in range(32)]
)


# The VLP-32C's laser elevations [deg], lowest first: Velodyne's VLP-32C user manual (63-9325 Rev C, table 9-6,
# "VLP-32C Azimuth Offsets by Elevation"), from -25 to +15 deg, densest (1/3 deg) around the horizon.
VLP32C_ELEVATIONS: tuple[float, ...] = (
    -25.0,
    -15.639,
    -11.31,
    -8.843,
    -7.254,
    -6.148,
    -5.333,
    -4.667,
    -4.0,
    -3.667,
    -3.333,
    -3.0,
    -2.667,
    -2.333,
    -2.0,
    -1.667,
    -1.333,
    -1.0,
    -0.667,
    -0.333,
    0.0,
    0.333,
    0.667,
    1.0,
    1.333,
    1.667,
    2.333,
    3.333,
    4.667,
    7.0,
    10.333,
    15.0,
)

# Hesai's design elevations [deg], lowest first (Hesai numbers its channels from the top: channel 1 is the last
# entry), as Hesai's HesaiLidar_General_SDK uses them when it is given no calibration file. Pandar64: -24.897 to
# +14.882 deg, 1/6 deg apart from -6.061 to +1.86 deg. Pandar40P: -25 to +15 deg, 1/3 deg apart from -6 to +2 deg
# (its manual's channel table lists the same angles to two decimals).
PANDAR64_ELEVATIONS: tuple[float, ...] = (
    -24.897,
    -18.889,
    -13.93,
    -12.974,
    -12.006,
    -11.032,
    -9.885,
    -9.06,
    -8.059,
    -7.063,
    -6.061,
    -5.898,
    -5.726,
    -5.565,
    -5.391,
    -5.229,
    -5.057,
    -4.892,
    -4.72,
    -4.558,
    -4.385,
    -4.221,
    -4.05,
    -3.884,
    -3.712,
    -3.548,
    -3.375,
    -3.21,
    -3.04,
    -2.873,
    -2.7,
    -2.536,
    -2.365,
    -2.198,
    -2.028,
    -1.86,
    -1.688,
    -1.522,
    -1.351,
    -1.184,
    -1.013,
    -0.845,
    -0.675,
    -0.508,
    -0.337,
    -0.169,
    0.0,
    0.169,
    0.337,
    0.508,
    0.675,
    0.846,
    1.013,
    1.184,
    1.351,
    1.522,
    1.688,
    1.86,
    2.028,
    3.04,
    5.057,
    8.059,
    11.032,
    14.882,
)
PANDAR40P_ELEVATIONS: tuple[float, ...] = (
    -25.0,
    -19.0,
    -14.0,
    -13.0,
    -12.0,
    -11.0,
    -10.0,
    -9.0,
    -8.0,
    -7.0,
    -6.0,
    -5.67,
    -5.33,
    -5.0,
    -4.67,
    -4.33,
    -4.0,
    -3.67,
    -3.33,
    -3.0,
    -2.67,
    -2.33,
    -2.0,
    -1.66,
    -1.33,
    -1.0,
    -0.67,
    -0.33,
    0.0,
    0.33,
    0.67,
    1.0,
    1.33,
    1.67,
    2.0,
    3.0,
    5.0,
    8.0,
    11.0,
    15.0,
)

# Two real Ouster units' beam_altitude_angles [deg], lowest first (Ouster lists them from the top), from the
# metadata of the OS1-128 and OS0-128 captures in Ouster's SDK test data (firmware 2.3, ../shared/data/real/
# ouster_os128_pcaps_with_imu). Ouster publishes no nominal table: each unit's is in its metadata. The spacing
# is not even (OS1-128 0.28-0.37 deg, OS0-128 0.43-1.05 deg). The angles are seen from the optical centre, 36.18 mm
# above the origin of os_sensor, the frame of ouster-ros's clouds: there, rows come from the ring field.
OS1_128_UNIT_ELEVATIONS: tuple[float, ...] = (
    -21.82,
    -21.54,
    -21.22,
    -20.92,
    -20.57,
    -20.27,
    -19.99,
    -19.67,
    -19.32,
    -19.02,
    -18.72,
    -18.39,
    -18.06,
    -17.74,
    -17.44,
    -17.11,
    -16.76,
    -16.45,
    -16.12,
    -15.79,
    -15.46,
    -15.11,
    -14.79,
    -14.48,
    -14.12,
    -13.8,
    -13.46,
    -13.15,
    -12.78,
    -12.46,
    -12.12,
    -11.78,
    -11.43,
    -11.09,
    -10.76,
    -10.42,
    -10.07,
    -9.71,
    -9.38,
    -9.05,
    -8.69,
    -8.35,
    -8.01,
    -7.67,
    -7.3,
    -6.97,
    -6.61,
    -6.27,
    -5.9,
    -5.57,
    -5.22,
    -4.86,
    -4.5,
    -4.15,
    -3.81,
    -3.46,
    -3.11,
    -2.75,
    -2.4,
    -2.07,
    -1.7,
    -1.35,
    -0.99,
    -0.64,
    -0.28,
    0.07,
    0.41,
    0.78,
    1.12,
    1.47,
    1.82,
    2.17,
    2.53,
    2.88,
    3.24,
    3.58,
    3.93,
    4.29,
    4.64,
    4.98,
    5.34,
    5.7,
    6.04,
    6.39,
    6.74,
    7.08,
    7.43,
    7.78,
    8.11,
    8.47,
    8.81,
    9.15,
    9.51,
    9.84,
    10.18,
    10.54,
    10.87,
    11.2,
    11.55,
    11.9,
    12.22,
    12.57,
    12.91,
    13.25,
    13.57,
    13.9,
    14.23,
    14.57,
    14.9,
    15.23,
    15.56,
    15.89,
    16.2,
    16.53,
    16.86,
    17.19,
    17.5,
    17.82,
    18.14,
    18.47,
    18.76,
    19.11,
    19.41,
    19.73,
    20.03,
    20.36,
    20.67,
    20.95,
)
OS0_128_UNIT_ELEVATIONS: tuple[float, ...] = (
    -46.26,
    -45.24,
    -44.52,
    -44.09,
    -43.22,
    -42.23,
    -41.51,
    -41.08,
    -40.21,
    -39.24,
    -38.55,
    -38.11,
    -37.24,
    -36.29,
    -35.6,
    -35.14,
    -34.29,
    -33.37,
    -32.68,
    -32.21,
    -31.36,
    -30.47,
    -29.78,
    -29.29,
    -28.46,
    -27.57,
    -26.9,
    -26.39,
    -25.56,
    -24.7,
    -24.02,
    -23.5,
    -22.68,
    -21.84,
    -21.17,
    -20.62,
    -19.8,
    -18.99,
    -18.32,
    -17.77,
    -16.95,
    -16.16,
    -15.48,
    -14.91,
    -14.1,
    -13.34,
    -12.65,
    -12.07,
    -11.28,
    -10.51,
    -9.85,
    -9.24,
    -8.43,
    -7.71,
    -7.05,
    -6.43,
    -5.6,
    -4.9,
    -4.23,
    -3.6,
    -2.77,
    -2.09,
    -1.43,
    -0.77,
    0.04,
    0.71,
    1.37,
    2.06,
    2.86,
    3.5,
    4.17,
    4.87,
    5.68,
    6.31,
    6.99,
    7.71,
    8.51,
    9.13,
    9.81,
    10.55,
    11.34,
    11.94,
    12.62,
    13.41,
    14.19,
    14.76,
    15.45,
    16.27,
    17.04,
    17.6,
    18.3,
    19.13,
    19.91,
    20.46,
    21.16,
    22.03,
    22.79,
    23.33,
    24.03,
    24.93,
    25.7,
    26.23,
    26.93,
    27.86,
    28.62,
    29.13,
    29.85,
    30.8,
    31.56,
    32.06,
    32.78,
    33.74,
    34.51,
    35.0,
    35.72,
    36.71,
    37.47,
    37.95,
    38.69,
    39.7,
    40.46,
    40.94,
    41.68,
    42.72,
    43.47,
    43.93,
    44.7,
    45.75,
)


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
        self.lowest = table[0] - 0.5 * (table[1] - table[0])  # [rad]
        self.highest = table[-1] + 0.5 * (table[-1] - table[-2])  # [rad]
        self._boundaries = middles
        self.elevations = table  # [rad]
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
        raise ValueError(
            f"the Velodyne calibration {path}: every laser needs a numeric 'vert_correction' [rad]"
        ) from None
    declared = document.get('num_lasers')
    if declared is not None and int(declared) != len(lasers):
        raise ValueError(
            f'the Velodyne calibration {path} declares num_lasers {declared} but lists {len(lasers)} lasers'
        )
    return tuple(round(float(v), 9) for v in np.sort(elevations))
