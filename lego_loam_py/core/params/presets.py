"""Range-image geometry of every sensor ``sensor.preset`` names (:data:`SENSOR_PRESETS`): the original's
``utility.h`` blocks and the lidars users have beyond them (:data:`MORE_SENSOR_PRESETS`).

Each of the latter gives ``n_scan``, ``horizon_scan`` and ``ang_res_x`` (the sensor's columns per sweep at 10 Hz;
Ouster: the 1024x10 mode), ``ang_res_y`` and ``ang_bottom`` (its beams' span evenly divided, ``ang_bottom`` with the
original's 0.1 deg margin below the lowest beam), ``ground_scan_ind`` (the highest beam at or below -1 deg, as the
VLP-16's 7) and, where the maker publishes one, ``beam_elevations`` (core.beam_table). Without a table the geometry is
the even one: rows come from the ring field, which every one of these drivers sends, and the segmentation takes
``ang_res_y`` for the angle between rows; give a unit's own table (``sensor.beam_elevations``) when its beams are not
evenly spaced."""

from __future__ import annotations

from typing import Any

from lego_loam_py.core.params.beams import (
    HDL64E_NOMINAL_ELEVATIONS,
    OS0_128_UNIT_ELEVATIONS,
    OS1_128_UNIT_ELEVATIONS,
    PANDAR40P_ELEVATIONS,
    PANDAR64_ELEVATIONS,
    VLP32C_ELEVATIONS,
)

__all__ = ['SENSOR_PRESETS', 'MORE_SENSOR_PRESETS', 'PRESET_FIELDS']


def _preset(
    n_scan: int,
    columns: int,
    lowest: float,
    highest: float,
    ground_scan_ind: int,
    beam_elevations: tuple[float, ...] = (),
) -> dict[str, Any]:
    """The geometry of ``n_scan`` beams from ``lowest`` to ``highest`` [deg] and ``columns`` per sweep."""
    out = dict(
        n_scan=n_scan,
        horizon_scan=columns,
        ang_res_x=360.0 / columns,
        ang_res_y=(highest - lowest) / (n_scan - 1),
        ang_bottom=round(-lowest + 0.1, 6),
        ground_scan_ind=ground_scan_ind,
    )
    if beam_elevations:
        out['beam_elevations'] = beam_elevations
    return out


MORE_SENSOR_PRESETS: dict[str, dict[str, Any]] = {
    # Velodyne VLP-32C: -25 to +15 deg, unevenly (core.beam_table), 0.2 deg at 10 Hz.
    'VLP-32C': _preset(32, 1800, -25.0, 15.0, 17, VLP32C_ELEVATIONS),
    # Ouster (the 1024x10 mode; 512 or 2048 columns: set horizon_scan and ang_res_x). The OS1-128 and OS0-128
    # carry a real unit's table (core.beam_table); their 32- and 64-beam kin are the same span evenly divided.
    # The OS2 spans 22.5 deg (+-11.25 deg) as Ouster publishes it: no unit was at hand, even spacing.
    # (OS1-16 and OS1-64 are the original's, for the first OS1's 33.2 deg; a later OS1-64 spans about 42.8 deg.)
    'OS0-32': _preset(32, 1024, -46.26, 45.75, 15),
    'OS0-64': _preset(64, 1024, -46.26, 45.75, 30),
    'OS0-128': _preset(128, 1024, -46.26, 45.75, 62, OS0_128_UNIT_ELEVATIONS),
    'OS1-32': _preset(32, 1024, -21.82, 20.95, 15),
    'OS1-128': _preset(128, 1024, -21.82, 20.95, 61, OS1_128_UNIT_ELEVATIONS),
    'OS2-32': _preset(32, 1024, -11.25, 11.25, 14),
    'OS2-64': _preset(64, 1024, -11.25, 11.25, 28),
    'OS2-128': _preset(128, 1024, -11.25, 11.25, 57),
    # Hesai: Pandar64 and Pandar40P with their design tables (core.beam_table), 0.2 deg at 10 Hz; PandarXT-32
    # evenly 1 deg from -16 to +15 deg (its design table is even), 0.18 deg at 10 Hz.
    'Pandar64': _preset(64, 1800, -24.897, 14.882, 40, PANDAR64_ELEVATIONS),
    'Pandar40P': _preset(40, 1800, -25.0, 15.0, 25, PANDAR40P_ELEVATIONS),
    'PandarXT-32': _preset(32, 2000, -16.0, 15.0, 15),
    # RoboSense, 0.2 deg at 10 Hz. RS-LiDAR-16: evenly 2 deg from -15 to +15 deg. The RS-LiDAR-32 (-25 to +15 deg),
    # RS-Helios-5515 (-55 to +15 deg) and RS-Ruby-128 (-25 to +15 deg) space their beams unevenly, densest around
    # the horizon, but no table of them was found published (each unit reports its own: rslidar_sdk reads it from
    # the sensor; give it as sensor.beam_elevations): even geometry. RS-Helios-1615: 32 beams from -16 to +15 deg.
    'RS-LiDAR-16': _preset(16, 1800, -15.0, 15.0, 7),
    'RS-LiDAR-32': _preset(32, 1800, -25.0, 15.0, 18),
    'RS-Helios-1615': _preset(32, 1800, -16.0, 15.0, 15),
    'RS-Helios-5515': _preset(32, 1800, -55.0, 15.0, 23),
    'RS-Ruby-128': _preset(128, 1800, -25.0, 15.0, 76),
}


# Geometry of the sensor blocks of utility.h (docs/original.md §2.3) plus the HDL-64E values the original's
# author suggested (issue #12, ang_res_y as 26.9/63) but its real azimuth step (0.1728 deg at 10 Hz: 2083 columns;
# the suggested 1800 dropped 16 % of a real KITTI scan's points on shared pixels), the sensor's nominal beam
# table (rows without a ring field come from it; see core.beam_table) and its stamp at the sweep's end (both
# sources of HDL-64E clouds stamp there: the Velodyne driver, with its last packet, and KITTI). Keys are the
# values accepted by ``sensor.preset``.
SENSOR_PRESETS: dict[str, dict[str, Any]] = {
    'VLP-16': dict(
        n_scan=16, horizon_scan=1800, ang_res_x=0.2, ang_res_y=2.0, ang_bottom=15.0 + 0.1, ground_scan_ind=7
    ),
    'HDL-32E': dict(
        n_scan=32, horizon_scan=1800, ang_res_x=360.0 / 1800, ang_res_y=41.33 / 31, ang_bottom=30.67, ground_scan_ind=20
    ),
    'VLS-128': dict(n_scan=128, horizon_scan=1800, ang_res_x=0.2, ang_res_y=0.3, ang_bottom=25.0, ground_scan_ind=10),
    'HDL-64E': dict(
        n_scan=64,
        horizon_scan=2083,
        ang_res_x=360.0 / 2083,
        ang_res_y=26.9 / 63,
        ang_bottom=24.9,
        ground_scan_ind=50,
        beam_elevations=HDL64E_NOMINAL_ELEVATIONS,
        stamp_position=1.0,
    ),
    'OS1-16': dict(
        n_scan=16,
        horizon_scan=1024,
        ang_res_x=360.0 / 1024,
        ang_res_y=33.2 / 15,
        ang_bottom=16.6 + 0.1,
        ground_scan_ind=7,
    ),
    'OS1-64': dict(
        n_scan=64,
        horizon_scan=1024,
        ang_res_x=360.0 / 1024,
        ang_res_y=33.2 / 63,
        ang_bottom=16.6 + 0.1,
        ground_scan_ind=15,
    ),
    **MORE_SENSOR_PRESETS,  # VLP-32C, Ouster OS0/OS1/OS2, Hesai Pandar, RoboSense (above)
}
PRESET_FIELDS = (
    'n_scan',
    'horizon_scan',
    'ang_res_x',
    'ang_res_y',
    'ang_bottom',
    'ground_scan_ind',
    'beam_elevations',
    'stamp_position',
)
