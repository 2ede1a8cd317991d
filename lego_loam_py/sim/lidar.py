"""Spinning multi-beam lidar model: geometry from the sensor presets, firing order, noise, dropped returns.

Geometry and timing of a sweep (lidar frame, REP-103 axes: x forward, y left, z up):

* Beams: ring ``r`` (0 = lowest) has elevation ``lowest + r * ang_res_y`` with ``ang_res_y`` from
  :data:`lego_loam_py.core.params.SENSOR_PRESETS` and ``lowest`` the real lowest beam of the sensor (the
  presets' ``ang_bottom`` carries LeGO-LOAM's +0.1 deg rounding margin for some sensors). VLP-16: -15, -13,
  ..., +15 deg. A preset with a beam table (HDL-64E: its nominal, unevenly spaced layout) has its beams
  there instead, unless ``uniform_beams`` asks for the even spacing.
* Columns: ``horizon_scan`` of them per sweep. The head spins **clockwise** seen from above, as every
  Velodyne does: column ``k`` looks at azimuth ``atan2(y, x) = -2 pi k / N``. The sweep starts and ends
  straight ahead (+x), where the velodyne driver cuts its clouds, so LeGO-LOAM's start/end orientation
  logic sees a sweep of ~2 pi.
* Timing: column ``k`` fires at ``k * scan_period / N`` after the sweep start; within a column the lasers
  fire one after the other in the sensor's laser-id order (VLP-16 and HDL-32E: interleaved low/high, e.g.
  -15, 1, -13, 3, ... deg, 2.304 us apart for the VLP-16), and points are emitted in firing order.
  All lasers of a column share its azimuth (the driver's per-laser azimuth interpolation, < 0.14 deg, is
  not modelled, so each point falls on its own range-image pixel).
* Motion: every firing has its own time and is cast from the sensor pose *at that time*; the point is the
  measured range along the fixed beam direction of the lidar frame at that time, which is exactly the
  return expressed in the sensor frame at its firing time. Poses at the lasers' firing times are
  interpolated between the exact poses of consecutive columns (55 us apart: error < 1e-8 m, far below
  float32 resolution).

Measurement model (see :class:`LidarModel`): returns beyond ``[min_range, max_range]`` or without a hit
are not emitted (as the real driver does), range noise is Gaussian along the beam and the range is
quantised to the sensor's resolution, a return is detected with a probability that falls with the
received signal (reflectivity x cos(incidence) / range^2: dark surfaces at grazing incidence and long
range get lost), transmissive materials (glass, foliage) lose some returns, and a small fraction of
returns drops at random. Intensity = material reflectivity x incidence factor + noise, 0..255.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lego_loam_py.core.params import SENSOR_PRESETS
from lego_loam_py.core.pointcloud import VELODYNE_POINT_DTYPE
from lego_loam_py.sim.scene import Scene
from lego_loam_py.sim.trajectory import Trajectory

__all__ = ['LidarModel', 'Sweep', 'simulate_sweep', 'column_of_azimuth', 'LIDAR_SPECS', 'VLP16_FIRING_ELEVATIONS']

# The VLP-16's elevation per laser id (= firing order within a column) [deg].
VLP16_FIRING_ELEVATIONS = (-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15)

# Per-sensor facts the presets do not carry: lowest beam [deg], laser firing order ('interleaved':
# laser ids alternate between the lower and the upper half of the beams, as VLP-16 and HDL-32E do;
# 'ascending': ring order), time between two lasers of a column [s] (0: a whole column at once, as Ouster
# does), range limits [m], range noise sigma [m] and range resolution [m] from the data sheets.
LIDAR_SPECS: dict[str, dict] = {
    'VLP-16': dict(
        lowest=-15.0,
        firing='interleaved',
        firing_interval=2.304e-6,
        min_range=0.3,
        max_range=100.0,
        range_noise=0.015,
        range_resolution=0.002,
    ),
    'HDL-32E': dict(
        lowest=-30.67,
        firing='interleaved',
        firing_interval=1.152e-6,
        min_range=1.0,
        max_range=100.0,
        range_noise=0.01,
        range_resolution=0.002,
    ),
    'VLS-128': dict(
        lowest=-25.0,
        firing='ascending',
        firing_interval=0.26e-6,
        min_range=1.0,
        max_range=245.0,
        range_noise=0.015,
        range_resolution=0.004,
    ),
    'HDL-64E': dict(
        lowest=-24.9,
        firing='ascending',
        firing_interval=0.52e-6,
        min_range=0.9,
        max_range=120.0,
        range_noise=0.01,
        range_resolution=0.002,
    ),
    'OS1-16': dict(
        lowest=-16.6,
        firing='ascending',
        firing_interval=0.0,
        min_range=0.8,
        max_range=120.0,
        range_noise=0.015,
        range_resolution=0.001,
    ),
    'OS1-64': dict(
        lowest=-16.6,
        firing='ascending',
        firing_interval=0.0,
        min_range=0.8,
        max_range=120.0,
        range_noise=0.015,
        range_resolution=0.001,
    ),
}
# The presets of core.sensor_presets, with round figures of their kind (approximate: they make plausible clouds,
# the beams are the presets'): Ouster fires a column at once, the others laser after laser within a column.
_OUSTER = dict(firing='ascending', firing_interval=0.0, range_resolution=0.001)
LIDAR_SPECS.update(
    {
        'VLP-32C': dict(
            lowest=-25.0,
            firing='ascending',
            firing_interval=1.152e-6,
            min_range=1.0,
            max_range=200.0,
            range_noise=0.015,
            range_resolution=0.004,
        ),
        **{
            f'OS0-{n}': dict(_OUSTER, lowest=-46.26, min_range=0.5, max_range=50.0, range_noise=0.02)
            for n in (32, 64, 128)
        },
        **{
            f'OS1-{n}': dict(_OUSTER, lowest=-21.82, min_range=0.5, max_range=120.0, range_noise=0.015)
            for n in (32, 128)
        },
        **{
            f'OS2-{n}': dict(_OUSTER, lowest=-11.25, min_range=1.0, max_range=240.0, range_noise=0.025)
            for n in (32, 64, 128)
        },
        'Pandar64': dict(
            lowest=-24.897,
            firing='ascending',
            firing_interval=0.8e-6,
            min_range=0.3,
            max_range=200.0,
            range_noise=0.02,
            range_resolution=0.004,
        ),
        'Pandar40P': dict(
            lowest=-25.0,
            firing='ascending',
            firing_interval=1.3e-6,
            min_range=0.3,
            max_range=200.0,
            range_noise=0.02,
            range_resolution=0.004,
        ),
        'PandarXT-32': dict(
            lowest=-16.0,
            firing='ascending',
            firing_interval=1.5e-6,
            min_range=0.05,
            max_range=120.0,
            range_noise=0.01,
            range_resolution=0.004,
        ),
        'RS-LiDAR-16': dict(
            lowest=-15.0,
            firing='ascending',
            firing_interval=2.8e-6,
            min_range=0.4,
            max_range=150.0,
            range_noise=0.02,
            range_resolution=0.005,
        ),
        'RS-LiDAR-32': dict(
            lowest=-25.0,
            firing='ascending',
            firing_interval=1.44e-6,
            min_range=0.4,
            max_range=200.0,
            range_noise=0.02,
            range_resolution=0.005,
        ),
        'RS-Helios-1615': dict(
            lowest=-16.0,
            firing='ascending',
            firing_interval=1.5e-6,
            min_range=0.2,
            max_range=150.0,
            range_noise=0.02,
            range_resolution=0.0025,
        ),
        'RS-Helios-5515': dict(
            lowest=-55.0,
            firing='ascending',
            firing_interval=1.5e-6,
            min_range=0.2,
            max_range=150.0,
            range_noise=0.02,
            range_resolution=0.0025,
        ),
        'RS-Ruby-128': dict(
            lowest=-25.0,
            firing='ascending',
            firing_interval=0.4e-6,
            min_range=0.4,
            max_range=250.0,
            range_noise=0.03,
            range_resolution=0.005,
        ),
    }
)


@dataclass(frozen=True)
class LidarModel:
    """Geometry, timing and measurement model of a spinning lidar (units: m, s, deg unless stated)."""

    preset: str
    ring_elevations: tuple[float, ...]  # [deg] per ring, ring 0 = lowest
    firing_rings: tuple[int, ...]  # ring of each laser in firing order within a column
    columns: int  # firings per sweep
    scan_period: float = 0.1  # [s]
    firing_interval: float = 2.304e-6  # [s] between consecutive lasers of a column
    min_range: float = 0.3
    max_range: float = 100.0
    range_noise: float = 0.015  # Gaussian sigma along the beam [m]
    range_resolution: float = 0.002  # reported ranges are multiples of this [m] (0: continuous)
    random_dropout: float = 0.006  # fraction of returns lost at random
    detection_reference: float = 5.0  # a 100 %-reflective normal target gives signal 1 at this x max_range
    intensity_noise: float = 1.5  # sigma of the intensity noise [reflectivity units]
    ideal: bool = False  # no noise, no quantisation, every hit in range is returned
    # Every point reads this much lower than its beam really points [deg] (a calibration error common to the
    # beams: KITTI's HDL-64E reads about 0.2 deg low); the returns are cast along the true beams and reported
    # along the calibrated ones.
    elevation_error: float = 0.0

    @staticmethod
    def from_preset(
        preset: str = 'VLP-16',
        scan_period: float = 0.1,
        ideal: bool = False,
        uniform_beams: bool = False,
        elevation_error: float = 0.0,
    ) -> LidarModel:
        """The model of a sensor preset (:data:`SENSOR_PRESETS` geometry + :data:`LIDAR_SPECS`); its beam table
        when it has one, unless ``uniform_beams``."""
        if preset not in SENSOR_PRESETS or preset not in LIDAR_SPECS:
            raise ValueError(f"unknown sensor preset '{preset}' (known: {', '.join(SENSOR_PRESETS)})")
        geometry = SENSOR_PRESETS[preset]
        spec = LIDAR_SPECS[preset]
        n = int(geometry['n_scan'])
        elevations = tuple(round(spec['lowest'] + r * float(geometry['ang_res_y']), 6) for r in range(n))
        if geometry.get('beam_elevations') and not uniform_beams:
            elevations = tuple(float(e) for e in geometry['beam_elevations'])
        if spec['firing'] == 'interleaved':
            half = n // 2
            firing = tuple(i // 2 if i % 2 == 0 else half + i // 2 for i in range(n))
        else:
            firing = tuple(range(n))
        model = LidarModel(
            preset=preset,
            ring_elevations=elevations,
            firing_rings=firing,
            columns=int(geometry['horizon_scan']),
            scan_period=scan_period,
            firing_interval=spec['firing_interval'],
            min_range=spec['min_range'],
            max_range=spec['max_range'],
            range_noise=spec['range_noise'],
            range_resolution=spec['range_resolution'],
            elevation_error=float(elevation_error),
        )
        return model.make_ideal() if ideal else model

    def make_ideal(self) -> LidarModel:
        """The same sensor without noise, quantisation or dropped returns (hits in range are kept)."""
        return replace(self, range_noise=0.0, range_resolution=0.0, random_dropout=0.0, intensity_noise=0.0, ideal=True)

    @property
    def n_rings(self) -> int:
        return len(self.ring_elevations)

    @property
    def column_period(self) -> float:
        return self.scan_period / self.columns

    def column_azimuths(self) -> np.ndarray:
        """(columns,) lidar-frame azimuth atan2(y, x) of each column [rad], decreasing (clockwise)."""
        return -2.0 * np.pi * np.arange(self.columns) / self.columns

    def beam_directions(self, true: bool = False) -> np.ndarray:
        """(columns, lasers, 3) unit beam directions in the lidar frame, lasers in firing order: as calibrated, or
        as the beams really point (``true``: :attr:`elevation_error` higher)."""
        azimuth = self.column_azimuths()[:, None]
        elevation = np.asarray(self.ring_elevations)[list(self.firing_rings)] + (self.elevation_error if true else 0.0)
        elevation = np.radians(elevation)[None, :]
        return np.stack(
            np.broadcast_arrays(
                np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
            ),
            axis=-1,
        )

    def firing_offsets(self) -> np.ndarray:
        """(columns, lasers) firing time of every laser since the sweep start [s]."""
        column = np.arange(self.columns)[:, None] * self.column_period
        return column + np.arange(self.n_rings)[None, :] * self.firing_interval

    def describe(self) -> dict:
        """Plain-data summary for scenario.yaml."""
        return dict(
            preset=self.preset,
            ring_elevations_deg=list(self.ring_elevations),
            firing_order_rings=list(self.firing_rings),
            columns=self.columns,
            scan_period_s=self.scan_period,
            firing_interval_s=self.firing_interval,
            min_range_m=self.min_range,
            max_range_m=self.max_range,
            range_noise_sigma_m=self.range_noise,
            range_resolution_m=self.range_resolution,
            random_dropout=self.random_dropout,
            intensity_noise_sigma=self.intensity_noise,
            ideal=self.ideal,
            **({'elevation_error_deg': self.elevation_error} if self.elevation_error else {}),
        )


@dataclass
class Sweep:
    """One simulated sweep: the cloud in message order and the per-point labels."""

    points: np.ndarray  # structured, velodyne layout (x, y, z, intensity, ring, time), firing order
    labels: np.ndarray  # (N,) uint32: 0 none, 1 ground, >= 2 object instance id
    hits: int  # rays that hit something in range before dropouts (for statistics)


class _SweepGeometry:
    """Per-model constant arrays, computed once."""

    def __init__(self, model: LidarModel):
        self.directions = model.beam_directions().reshape(-1, 3)  # (M, 3) lidar frame, as reported
        self.cast_directions = (
            model.beam_directions(true=True).reshape(-1, 3) if model.elevation_error else self.directions
        )  # ... and as the beams point
        offsets = model.firing_offsets()
        self.time = offsets.reshape(-1)  # (M,) [s]
        self.column_fraction = ((offsets - offsets[:, :1]) / model.column_period).reshape(-1)
        self.column = np.repeat(np.arange(model.columns), model.n_rings)
        self.ring = np.tile(np.asarray(model.firing_rings, dtype=np.uint16), model.columns)


_GEOMETRY_CACHE: dict[LidarModel, _SweepGeometry] = {}


def _geometry(model: LidarModel) -> _SweepGeometry:
    if model not in _GEOMETRY_CACHE:
        _GEOMETRY_CACHE[model] = _SweepGeometry(model)
    return _GEOMETRY_CACHE[model]


def _rotate(vectors: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotate (N, 3) vectors by (N, 3) rotation vectors."""
    angle = np.linalg.norm(rotvec, axis=1, keepdims=True)
    safe = np.where(angle > 0.0, angle, 1.0)
    axis = rotvec / safe
    cos, sin = np.cos(angle), np.sin(angle)
    cross = np.cross(axis, vectors)
    dot = np.sum(axis * vectors, axis=1, keepdims=True)
    return vectors * cos + cross * sin + axis * dot * (1.0 - cos)


def simulate_sweep(
    model: LidarModel,
    scene: Scene,
    trajectory: Trajectory,
    sweep_start: float,
    rng: np.random.Generator | None,
    dtype: np.dtype = VELODYNE_POINT_DTYPE,
) -> Sweep:
    """Cast one sweep starting at ``sweep_start`` [s] (all rays in one call) and measure the returns.

    ``rng`` draws the noise and dropouts (may be None for an ideal model). The cloud is in the lidar frame
    at each point's own firing time; ``time`` = seconds since ``sweep_start``.
    """
    from scipy.spatial.transform import Rotation

    geometry = _geometry(model)
    # Exact poses at every column time and at the start of the next sweep, interpolated per laser.
    column_times = sweep_start + np.arange(model.columns + 1) * model.column_period
    rotations, positions = trajectory.pose(column_times)
    col = geometry.column
    frac = geometry.column_fraction
    if model.firing_interval > 0.0:
        step = (Rotation.from_matrix(rotations[:-1]).inv() * Rotation.from_matrix(rotations[1:])).as_rotvec()
        local = _rotate(geometry.cast_directions, step[col] * frac[:, None])
        origins = positions[col] + frac[:, None] * (positions[col + 1] - positions[col])
    else:
        local = geometry.cast_directions
        origins = positions[col]
    world_dirs = np.einsum('nij,nj->ni', rotations[:-1][col], local)

    distance, triangle, normals = scene.cast(origins, world_dirs)
    in_range = np.isfinite(distance) & (distance >= model.min_range) & (distance <= model.max_range)
    hits = int(in_range.sum())
    idx = np.flatnonzero(in_range)
    distance = distance[idx]
    triangle = triangle[idx]
    cos_incidence = np.clip(np.abs(np.sum(normals[idx] * world_dirs[idx], axis=1)), 0.0, 1.0)
    material = scene.triangle_material[triangle]
    reflectivity = scene.reflectivity[material]
    retro = scene.retroreflective[material]

    # Calibrated reflectivity seen at this incidence: diffuse surfaces darken at grazing angles.
    intensity = np.where(retro, reflectivity * (0.9 + 0.1 * cos_incidence), reflectivity * (0.4 + 0.6 * cos_incidence))
    if model.ideal:
        keep = np.ones(len(idx), dtype=bool)
        measured = distance
    else:
        if rng is None:
            raise ValueError('a noisy lidar model needs a random generator')
        # Received signal relative to the detection threshold; retro-reflectors barely depend on the angle.
        reference = model.detection_reference * model.max_range
        lambert = np.where(retro, 1.0, cos_incidence)
        signal = np.minimum(reflectivity, 100.0) / 100.0 * lambert * (reference / distance) ** 2
        x = np.clip((signal - 0.3) / 1.0, 0.0, 1.0)
        p_detect = x * x * (3.0 - 2.0 * x)
        p_return = p_detect * (1.0 - scene.transmission[material]) * (1.0 - model.random_dropout)
        uniforms = rng.random(len(idx))
        noise = rng.standard_normal(len(idx))
        intensity_noise = rng.standard_normal(len(idx))
        keep = uniforms < p_return
        measured = distance + model.range_noise * noise
        if model.range_resolution > 0.0:
            measured = np.round(measured / model.range_resolution) * model.range_resolution
        keep &= (measured >= model.min_range) & (measured <= model.max_range)
        intensity = intensity + model.intensity_noise * intensity_noise
    intensity = np.clip(np.round(intensity), 0.0, 255.0)

    chosen = idx[keep]
    out = np.zeros(len(chosen), dtype=dtype)
    xyz = geometry.directions[chosen] * measured[keep][:, None]
    out['x'] = xyz[:, 0]
    out['y'] = xyz[:, 1]
    out['z'] = xyz[:, 2]
    out['intensity'] = intensity[keep]
    out['ring'] = geometry.ring[chosen]
    out['time'] = geometry.time[chosen]
    labels = scene.triangle_instance[triangle[keep]]
    return Sweep(points=out, labels=labels.astype(np.uint32), hits=hits)


def column_of_azimuth(azimuth: np.ndarray, columns: int) -> np.ndarray:
    """Column index of lidar-frame azimuths [rad] (inverse of :meth:`LidarModel.column_azimuths`)."""
    return np.mod(np.round(-np.asarray(azimuth) * columns / (2.0 * math.pi)), columns).astype(np.int64)
