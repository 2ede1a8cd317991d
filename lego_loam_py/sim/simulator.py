"""The simulator's driver: a scenario -> a bag with /velodyne_points and /imu/data, plus its sidecar files.

Timing: simulation time t = 0 is header stamp :data:`START_STAMP_NS`. Sweep k starts at ``k * scan_period`` (its cloud's
header stamp, or that much later for a preset whose drivers stamp later in the sweep: ``sensor.stamp_position``, the
HDL-64E's at its end) and is recorded at its end (bag time = sweep start + scan_period, as a driver publishes it); IMU
sample j is stamped and recorded at ``j / imu_rate``, from t = 0 to the end of the last sweep, so every sweep is covered
by IMU data recorded before its cloud. (``imu_time_offset`` and ``imu_stamp_jitter`` move the IMU's stamps, not its bag
times; ``imu_record_late`` records each sample at its stamp, so that a late IMU's last samples of a sweep come after its
cloud, as from a late driver.)

Determinism: every random draw comes from a generator seeded by (seed, purpose, index) -- the scenery, the
IMU biases, each sweep's lidar noise, each sweep's IMU noise (and bias wander), the IMU stamps' jitter -- and
nothing depends on the wall clock, so the same configuration always gives byte-identical messages and sidecar
files.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lego_loam_py import __version__

if TYPE_CHECKING:
    from lego_loam_py.sim.imu import ImuModel

__all__ = [
    'SimConfig',
    'SimResult',
    'simulate',
    'cached_scenario',
    'cache_root',
    'START_STAMP_NS',
    'SIM_VERSION',
    'LAYOUTS',
    'CLOUD_TOPIC',
    'IMU_TOPIC',
    'LIDAR_FRAME',
    'IMU_FRAME',
]

SIM_VERSION = 1  # bump whenever the same configuration would give other data
START_STAMP_NS = 1_700_000_000_000_000_000  # header stamp of t = 0 (2023-11-14T22:13:20Z)
CLOUD_TOPIC, IMU_TOPIC = '/velodyne_points', '/imu/data'
LIDAR_FRAME, IMU_FRAME = 'velodyne', 'imu_link'
LAYOUTS = ('driver', 'packed')  # VELODYNE_POINT_DTYPE (ROS 2 driver, 32 B) / VELODYNE_PACKED_DTYPE (22 B)
STORAGES = ('mcap', 'sqlite3')


@dataclass(frozen=True)
class SimConfig:
    """Everything that determines a simulated recording."""

    scenario: str
    duration: float | None = None  # [s]; None: the scenario's default (one full lap)
    seed: int = 0
    preset: str = 'VLP-16'
    imu_rate: float = 200.0  # [Hz]
    storage: str = 'mcap'  # ROS 2 storage: mcap or sqlite3
    ros1: bool = False  # write a ROS 1 .bag instead
    layout: str = 'driver'  # point layout: driver (32 B) or packed (22 B)
    compress: bool = False  # zstd chunks (ROS 2 mcap / sqlite3 file)
    imu_extrinsic_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU axes in the lidar frame [deg]
    ideal: bool = False  # no noise, no bias, no dropped returns
    turn_rate: float = 0.0  # peak yaw rate of inserted in-place turns [deg/s]; 0: none
    uniform_beams: bool = False  # evenly spaced beams even where the preset has a beam table
    imu_lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU origin in the lidar frame [m]
    imu_orientation_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)  # orientation frame in the IMU frame [deg]
    imu_time_offset: float = 0.0  # IMU stamp - lidar stamp of the same instant [s]
    # Another route through the same scene: start at this arc length [m] along the scenario's path (None: the
    # scenario's own start), and drive it the other way round (see scenarios.build_world).
    route_start: float | None = None
    reverse: bool = False
    beam_elevation_error: float = 0.0  # every point reads this much lower than its beam points [deg]
    # The IMU's errors (issue 34): a named unit (sim.imu.IMU_PROFILES), and each error of it replaced when set
    # (None: the profile's). Bias and tilt ranges are magnitudes (each axis' sign, the tilt's direction drawn);
    # walks and drift are (stationary sigma, correlation time [s]) of a Gauss-Markov process.
    imu_profile: str = 'default'
    imu_gyro_bias: tuple[float, float] | None = None  # [deg/s] |constant bias| range per axis
    imu_gyro_bias_walk: tuple[float, float] | None = None  # ([deg/s], [s]) wandering bias
    imu_accel_bias: tuple[float, float] | None = None  # [m/s^2] |constant bias| range per axis
    imu_accel_bias_walk: tuple[float, float] | None = None  # ([m/s^2], [s])
    imu_gyro_scale_error: float | None = None  # [%] bound of each axis' scale-factor error
    imu_accel_scale_error: float | None = None  # [%]
    imu_misalignment: float | None = None  # [deg] bound of each cross-axis term
    imu_tilt_error: tuple[float, float] | None = None  # [deg] |constant roll/pitch error| of the orientation
    imu_yaw_offset: float | None = None  # [deg] constant yaw offset of the orientation
    imu_orientation_noise: float | None = None  # [deg] its white noise per axis
    imu_heading_drift: tuple[float, float] | None = None  # ([deg], [s]) its wandering heading error
    imu_stamp_jitter: float = 0.0  # [s] sigma of the stamps' Gaussian jitter
    imu_record_late: bool = False  # record each IMU message at its stamp, not when measured

    # Options added after recordings were cached: left out of to_dict (and so of the cache key) at their defaults.
    _OPTIONAL = {
        'turn_rate': 0.0,
        'imu_lever_arm': (0.0, 0.0, 0.0),
        'imu_orientation_rpy': (0.0, 0.0, 0.0),
        'imu_time_offset': 0.0,
        'route_start': None,
        'reverse': False,
        'beam_elevation_error': 0.0,
        'imu_profile': 'default',
        'imu_gyro_bias': None,
        'imu_gyro_bias_walk': None,
        'imu_accel_bias': None,
        'imu_accel_bias_walk': None,
        'imu_gyro_scale_error': None,
        'imu_accel_scale_error': None,
        'imu_misalignment': None,
        'imu_tilt_error': None,
        'imu_yaw_offset': None,
        'imu_orientation_noise': None,
        'imu_heading_drift': None,
        'imu_stamp_jitter': 0.0,
        'imu_record_late': False,
    }
    _IMU_PAIRS = (
        'imu_gyro_bias',
        'imu_gyro_bias_walk',
        'imu_accel_bias',
        'imu_accel_bias_walk',
        'imu_tilt_error',
        'imu_heading_drift',
    )
    _IMU_VALUES = (
        'imu_gyro_scale_error',
        'imu_accel_scale_error',
        'imu_misalignment',
        'imu_yaw_offset',
        'imu_orientation_noise',
    )

    def validate(self) -> SimConfig:
        from lego_loam_py.core.params import SENSOR_PRESETS
        from lego_loam_py.sim.scenarios import SCENARIOS

        if self.scenario not in SCENARIOS:
            raise ValueError(f"unknown scenario '{self.scenario}' (known: {', '.join(SCENARIOS)})")
        if self.preset not in SENSOR_PRESETS:
            raise ValueError(f"unknown sensor preset '{self.preset}' (known: {', '.join(SENSOR_PRESETS)})")
        if self.layout not in LAYOUTS:
            raise ValueError(f"unknown layout '{self.layout}' (use {' or '.join(LAYOUTS)})")
        if self.storage not in STORAGES:
            raise ValueError(f"unknown storage '{self.storage}' (use {' or '.join(STORAGES)})")
        if self.duration is not None and not self.duration > 0:
            raise ValueError(f'duration must be positive, got {self.duration}')
        if not 1.0 <= self.imu_rate <= 2000.0:
            raise ValueError(f'imu rate must be within 1..2000 Hz, got {self.imu_rate}')
        if not 0.0 <= self.turn_rate <= 720.0:
            raise ValueError(f'turn rate must be within 0..720 deg/s, got {self.turn_rate}')
        for name, what in (
            ('imu_extrinsic_rpy', 'roll, pitch and yaw'),
            ('imu_orientation_rpy', 'roll, pitch and yaw'),
            ('imu_lever_arm', 'x, y and z'),
        ):
            value = getattr(self, name)
            if len(value) != 3 or not all(math.isfinite(float(v)) for v in value):
                raise ValueError(f'{name.replace("_", " ")} needs {what} (finite numbers)')
        if any(abs(float(v)) > 10.0 for v in self.imu_lever_arm):
            raise ValueError(f'the IMU lever arm must be within 10 m of the lidar, got {tuple(self.imu_lever_arm)}')
        if not abs(float(self.imu_time_offset)) <= 1.0:
            raise ValueError(f'the IMU time offset must be within 1 s, got {self.imu_time_offset}')
        if not abs(float(self.beam_elevation_error)) <= 2.0:
            raise ValueError(f'the beam elevation error must be within 2 deg, got {self.beam_elevation_error}')
        if self.route_start is not None and not math.isfinite(self.route_start):
            raise ValueError(f'route start must be a finite arc length [m], got {self.route_start}')
        imu = self._validate_imu_errors()
        return replace(
            self,
            **imu,
            imu_extrinsic_rpy=tuple(float(a) for a in self.imu_extrinsic_rpy),
            imu_orientation_rpy=tuple(float(a) for a in self.imu_orientation_rpy),
            imu_lever_arm=tuple(float(a) for a in self.imu_lever_arm),
            imu_time_offset=float(self.imu_time_offset),
            seed=int(self.seed),
            imu_rate=float(self.imu_rate),
            turn_rate=float(self.turn_rate),
            route_start=None if self.route_start is None else float(self.route_start),
            reverse=bool(self.reverse),
            beam_elevation_error=float(self.beam_elevation_error),
        )

    def _validate_imu_errors(self) -> dict[str, Any]:
        """The IMU error options checked and converted to plain numbers (returned for ``replace``)."""
        from lego_loam_py.sim.imu import IMU_PROFILES

        if self.imu_profile not in IMU_PROFILES:
            raise ValueError(f"unknown IMU profile '{self.imu_profile}' (known: {', '.join(IMU_PROFILES)})")
        out: dict[str, Any] = {}
        limits = {'imu_gyro_bias': 10.0, 'imu_accel_bias': 5.0, 'imu_tilt_error': 10.0}  # deg/s, m/s^2, deg
        for name in self._IMU_PAIRS:
            value = getattr(self, name)
            if value is None:
                continue
            if len(value) != 2 or not all(math.isfinite(float(v)) and float(v) >= 0.0 for v in value):
                raise ValueError(f'{name.replace("_", " ")} needs two non-negative finite numbers, got {value}')
            first, second = (float(v) for v in value)
            if name in limits:
                if not first <= second <= limits[name]:
                    raise ValueError(
                        f'{name.replace("_", " ")} needs a range low <= high <= {limits[name]:g}, '
                        f'got {first:g} {second:g}'
                    )
            elif not second > 0.0:
                raise ValueError(f'{name.replace("_", " ")} needs a positive correlation time [s], got {second:g}')
            out[name] = (first, second)
        for name in self._IMU_VALUES:
            value = getattr(self, name)
            if value is None:
                continue
            value = float(value)
            bound = {'imu_yaw_offset': 360.0, 'imu_gyro_scale_error': 50.0, 'imu_accel_scale_error': 50.0}.get(
                name, 10.0
            )  # (deg, %, deg)
            if not (math.isfinite(value) and (value >= 0.0 or name == 'imu_yaw_offset') and abs(value) <= bound):
                raise ValueError(
                    f'{name.replace("_", " ")} must be within {"-" if name == "imu_yaw_offset" else "0"}'
                    f'..{bound:g}, got {value:g}'
                )
            out[name] = value
        period = 1.0 / float(self.imu_rate)
        if not (math.isfinite(float(self.imu_stamp_jitter)) and 0.0 <= float(self.imu_stamp_jitter) <= period / 6):
            raise ValueError(
                f'the IMU stamp jitter must be within 0..{period / 6:g} s (a sixth of the sample '
                f'period, so that clipping it to keep the stamps increasing hardly shows), '
                f'got {self.imu_stamp_jitter}'
            )
        out.update(imu_stamp_jitter=float(self.imu_stamp_jitter), imu_record_late=bool(self.imu_record_late))
        return out

    def imu_model(self) -> ImuModel:
        """The simulated IMU: the profile's unit (no errors with ``ideal``) with the errors given here replacing
        its own (so ``ideal`` and one option give an IMU with that error alone)."""
        from lego_loam_py.sim.imu import IMU_PROFILES, ImuModel, ImuNoise

        noise = ImuNoise.none() if self.ideal else IMU_PROFILES[self.imu_profile]
        deg = math.radians
        changes: dict[str, Any] = {}
        if self.imu_gyro_bias is not None:
            changes.update(gyro_bias_sigma=0.0, gyro_bias_range=tuple(deg(v) for v in self.imu_gyro_bias))
        if self.imu_accel_bias is not None:
            changes.update(accel_bias_sigma=0.0, accel_bias_range=tuple(float(v) for v in self.imu_accel_bias))
        if self.imu_gyro_bias_walk is not None:
            changes.update(
                gyro_bias_instability=deg(self.imu_gyro_bias_walk[0]), gyro_bias_time=float(self.imu_gyro_bias_walk[1])
            )
        if self.imu_accel_bias_walk is not None:
            changes.update(
                accel_bias_instability=float(self.imu_accel_bias_walk[0]),
                accel_bias_time=float(self.imu_accel_bias_walk[1]),
            )
        if self.imu_gyro_scale_error is not None:
            changes.update(gyro_scale_error=self.imu_gyro_scale_error / 100.0)
        if self.imu_accel_scale_error is not None:
            changes.update(accel_scale_error=self.imu_accel_scale_error / 100.0)
        if self.imu_misalignment is not None:
            changes.update(misalignment=deg(self.imu_misalignment))
        if self.imu_tilt_error is not None:
            changes.update(tilt_bias_sigma=0.0, tilt_range=tuple(deg(v) for v in self.imu_tilt_error))
        if self.imu_yaw_offset is not None:  # exactly this offset
            changes.update(heading_bias_sigma=0.0, yaw_offset_range=(deg(self.imu_yaw_offset),) * 2)
        if self.imu_orientation_noise is not None:
            changes.update(orientation_noise=deg(self.imu_orientation_noise))
        if self.imu_heading_drift is not None:
            changes.update(
                heading_drift=deg(self.imu_heading_drift[0]), heading_drift_time=float(self.imu_heading_drift[1])
            )
        return ImuModel(
            rate=self.imu_rate,
            noise=replace(noise, **changes) if changes else noise,
            extrinsic_rpy_deg=self.imu_extrinsic_rpy,
            lever_arm=self.imu_lever_arm,
            orientation_rpy_deg=self.imu_orientation_rpy,
            time_offset=self.imu_time_offset,
            stamp_jitter=self.imu_stamp_jitter,
            record_late=self.imu_record_late,
            profile=self.imu_profile,
        )

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        for name, default in self._OPTIONAL.items():
            # Recordings without the option keep the cache keys (and scenario.yaml) they had before it.
            value = (
                tuple(out[name]) if isinstance(default, tuple) or isinstance(out[name], (tuple, list)) else out[name]
            )
            if value == default:
                del out[name]
            elif isinstance(value, tuple):
                out[name] = list(value)
        out['imu_extrinsic_rpy'] = list(self.imu_extrinsic_rpy)
        del out['uniform_beams']
        if self._has_beam_table():  # (a preset whose beams moved to a table gets new cache keys, no other)
            out['beams'] = 'uniform' if self.uniform_beams else 'table'
        if self.stamp_position():  # (likewise a preset whose clouds are stamped later than their sweep start)
            out['stamp_position'] = self.stamp_position()
        return out

    def stamp_position(self) -> float:
        """Where in the sweep the clouds' header stamps are taken, as the preset's drivers do
        (``sensor.stamp_position``: 0 the sweep start, 1 its end)."""
        from lego_loam_py.core.params import SENSOR_PRESETS

        return float(SENSOR_PRESETS.get(self.preset, {}).get('stamp_position', 0.0))

    def _has_beam_table(self) -> bool:
        from lego_loam_py.core.params import SENSOR_PRESETS

        return bool(SENSOR_PRESETS.get(self.preset, {}).get('beam_elevations'))

    def command(self, output: str | Path) -> str:
        """The ``lego_loam_py simulate`` command line that reproduces this configuration."""
        parts = ['lego_loam_py', 'simulate', self.scenario, '-o', str(output)]
        if self.duration is not None:
            parts += ['--duration', f'{self.duration:g}']
        parts += ['--seed', str(self.seed)]
        if self.preset != 'VLP-16':
            parts += ['--preset', self.preset]
        if self.imu_rate != 200.0:
            parts += ['--imu-rate', f'{self.imu_rate:g}']
        if self.ros1:
            parts.append('--ros1')
        elif self.storage != 'mcap':
            parts += ['--storage', self.storage]
        if self.layout != 'driver':
            parts += ['--layout', self.layout]
        if self.compress:
            parts.append('--compress')
        if any(self.imu_extrinsic_rpy):
            parts += ['--imu-extrinsic-rpy', *(f'{a:g}' for a in self.imu_extrinsic_rpy)]
        if self.ideal:
            parts.append('--ideal')
        if self.turn_rate:
            parts += ['--turn-rate', f'{self.turn_rate:g}']
        if self.uniform_beams and self._has_beam_table():
            parts.append('--uniform-beams')
        if any(self.imu_lever_arm):
            parts += ['--imu-lever-arm', *(f'{a:g}' for a in self.imu_lever_arm)]
        if any(self.imu_orientation_rpy):
            parts += ['--imu-orientation-rpy', *(f'{a:g}' for a in self.imu_orientation_rpy)]
        if self.imu_time_offset:
            parts += ['--imu-time-offset', f'{self.imu_time_offset:g}']
        if self.route_start is not None:
            parts += ['--route-start', f'{self.route_start:g}']
        if self.reverse:
            parts.append('--reverse')
        if self.beam_elevation_error:
            parts += ['--beam-elevation-error', f'{self.beam_elevation_error:g}']
        if self.imu_profile != 'default':
            parts += ['--imu-profile', self.imu_profile]
        for name in (*self._IMU_PAIRS, *self._IMU_VALUES):
            value = getattr(self, name)
            if value is not None:
                values = value if isinstance(value, (tuple, list)) else (value,)
                parts += ['--' + name.replace('_', '-'), *(f'{float(v):g}' for v in values)]
        if self.imu_stamp_jitter:
            parts += ['--imu-stamp-jitter', f'{self.imu_stamp_jitter:g}']
        if self.imu_record_late:
            parts.append('--imu-record-late')
        return ' '.join(parts)

    def cache_key(self) -> str:
        """Hash of the configuration and the simulator version (names the cache entry)."""
        text = json.dumps({'sim_version': SIM_VERSION, **self.to_dict()}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:12]


@dataclass
class SimResult:
    """What :func:`simulate` wrote."""

    bag_path: Path
    scans: int
    imu_messages: int
    points: int
    duration: float  # [s] simulated (scans x scan period)
    facts: dict = field(default_factory=dict)


def _point_dtype(layout: str) -> np.dtype:
    from lego_loam_py.core.pointcloud import VELODYNE_PACKED_DTYPE, VELODYNE_POINT_DTYPE

    return VELODYNE_PACKED_DTYPE if layout == 'packed' else VELODYNE_POINT_DTYPE


def _bag_output_path(config: SimConfig, output: str | Path) -> Path:
    path = Path(output).expanduser()
    if config.ros1 and path.suffix != '.bag':
        path = path.with_name(path.name + '.bag')
    return path


def _imu_message(types: dict, header: Any, sample: tuple, covariances: dict) -> Any:
    orientation, gyro, accel = sample
    vector = types['geometry_msgs/msg/Vector3']
    return types['sensor_msgs/msg/Imu'](
        header=header,
        orientation=types['geometry_msgs/msg/Quaternion'](
            x=float(orientation[0]), y=float(orientation[1]), z=float(orientation[2]), w=float(orientation[3])
        ),
        orientation_covariance=covariances['orientation'],
        angular_velocity=vector(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
        angular_velocity_covariance=covariances['angular_velocity'],
        linear_acceleration=vector(x=float(accel[0]), y=float(accel[1]), z=float(accel[2])),
        linear_acceleration_covariance=covariances['linear_acceleration'],
    )


def _note(config: SimConfig, bag_name: str, result: SimResult, description: str) -> str:
    command = config.command(bag_name)
    kind = (
        'ROS 1 bag' if config.ros1 else f'ROS 2 bag ({config.storage}{", zstd-compressed" if config.compress else ""})'
    )
    layout = (
        "the ROS 1 velodyne driver's packed XYZIRT layout (22 bytes)"
        if config.layout == 'packed'
        else "the ROS 2 velodyne driver's PointXYZIRT layout (32 bytes)"
    )
    ideal = ' Ideal sensors: no noise, no bias, no dropped returns.' if config.ideal else ''
    return f"""# {bag_name}: simulated `{config.scenario}` scenario

{description[0].upper() + description[1:]}.

Produced by the lego_loam_py simulator (lego_loam_py {__version__}, simulator version {SIM_VERSION}) with

```bash
{command}
```

The same command always produces byte-identical messages (seeded; no wall-clock input).

* {kind}, {result.duration:.1f} s: `{CLOUD_TOPIC}` (sensor_msgs/PointCloud2, frame `{LIDAR_FRAME}`,
  {config.preset}, {result.scans} sweeps at 10 Hz, {result.points} points; fields x y z intensity ring time in
  {layout}; header stamp = sweep start) and `{IMU_TOPIC}` (sensor_msgs/Imu, frame `{IMU_FRAME}`,
  {config.imu_rate:g} Hz, {result.imu_messages} messages).{ideal}
* `ground_truth.tum`: lidar pose at each sweep start relative to the first (TUM, REP-103 axes);
  `ground_truth_dense.tum`: the same at every IMU stamp.
* `labels.npz`: per-point labels of every scan (0 none, 1 ground, >= 2 object id; `classes` names them).
* `scenario.yaml`: every parameter, the drawn IMU biases, the world pose of the first ground-truth pose,
  statistics.
"""


def simulate(config: SimConfig, output: str | Path, progress: bool = False) -> SimResult:
    """Run the simulation ``config`` and write the bag ``output`` with its sidecar files.

    ``output`` is a ROS 2 bag directory (must not exist) or, with ``config.ros1``, a ``.bag`` file (the
    suffix is added when missing). Returns what was written.
    """
    from tqdm import tqdm

    from lego_loam_py.bag.io import BagWriter, make_cloud_msg
    from lego_loam_py.inputs import sidecars
    from lego_loam_py.sim import output as sim_output
    from lego_loam_py.sim.lidar import LidarModel, simulate_sweep
    from lego_loam_py.sim.scenarios import build_world, scenario_rng

    config = config.validate()
    bag_path = _bag_output_path(config, output)
    if bag_path.exists():
        raise FileExistsError(f'{bag_path} exists already; choose another output (bags are never overwritten)')
    world = build_world(config.scenario, config.seed, config.turn_rate, config.route_start, config.reverse)
    lidar = LidarModel.from_preset(
        config.preset,
        ideal=config.ideal,
        uniform_beams=config.uniform_beams,
        elevation_error=config.beam_elevation_error,
    )
    imu = config.imu_model()
    period_ns = int(round(lidar.scan_period * 1e9))
    stamp_offset_ns = int(round(config.stamp_position() * period_ns))  # sweep start -> header stamp
    duration = world.default_duration if config.duration is None else config.duration
    n_scans = max(1, int(math.floor(duration / lidar.scan_period + 1e-9)))
    end_ns = n_scans * period_ns
    imu_period = 1e9 / imu.rate
    imu_offsets_ns = np.round(np.arange(int(math.floor(end_ns / imu_period + 1e-9)) + 1) * imu_period).astype(np.int64)
    biases = imu.draw_biases(scenario_rng(config.seed, 'imu-bias'))
    covariances = imu.covariances()
    # The IMU's clock runs imu_time_offset ahead of the lidar's (and jitters): its stamps say so, while the bag
    # records each sample when it was measured (as a recorder receives it), or, for a late driver, at its stamp.
    imu_stamps_ns = imu.stamps_ns(imu_offsets_ns, scenario_rng(config.seed, 'imu-jitter') if imu.stamp_jitter else None)
    imu_recorded_ns = imu_stamps_ns if imu.record_late else imu_offsets_ns
    # Samples are measured sweep by sweep (sweep k's noise generator draws those measured during it, up to its end)
    # and written once their recording time has come: before the cloud of the sweep that ends after it.
    chunk_stops = np.searchsorted(imu_offsets_ns, (np.arange(n_scans, dtype=np.int64) + 1) * period_ns, side='right')
    chunk_stops[-1] = len(imu_offsets_ns)  # (the samples reach the end of the last sweep, no further)
    dtype = _point_dtype(config.layout)

    bag_path.parent.mkdir(parents=True, exist_ok=True)
    sweep_offsets_ns = np.arange(n_scans, dtype=np.int64) * period_ns
    total_points = 0
    labels_path = sidecars.sidecar_path(bag_path, sidecars.LABELS)
    label_writer = None
    with BagWriter(bag_path, storage=config.storage, ros1=config.ros1, compress=config.compress) as bag:
        types = bag.types
        bag.add_topic(CLOUD_TOPIC, 'sensor_msgs/msg/PointCloud2')
        bag.add_topic(IMU_TOPIC, 'sensor_msgs/msg/Imu')
        label_writer = sim_output.LabelWriter(labels_path)
        n_imu = len(imu_offsets_ns)
        measured = (np.zeros((n_imu, 4)), np.zeros((n_imu, 3)), np.zeros((n_imu, 3)))  # orientation, gyro, accel
        state = {'measured': 0, 'written': 0, 'chunk': 0, 'wander': None}

        def measure_until(count: int) -> None:
            """Measure sweep by sweep until the first ``count`` samples are."""
            while state['measured'] < count:
                chunk, start = state['chunk'], state['measured']
                stop = int(chunk_stops[chunk])
                if stop > start:
                    wander = None
                    if imu.noise.wanders:
                        wander = imu.wander(
                            stop - start, scenario_rng(config.seed, 'imu-wander', chunk), state['wander']
                        )
                        state['wander'] = wander[-1]
                    noise = scenario_rng(config.seed, 'imu-noise', chunk) if imu.has_white_noise else None
                    samples = imu.measure(world.trajectory, imu_offsets_ns[start:stop] / 1e9, biases, noise, wander)
                    for array, values in zip(
                        measured, (samples.orientation, samples.angular_velocity, samples.linear_acceleration)
                    ):
                        array[start:stop] = values
                state['measured'], state['chunk'] = stop, chunk + 1

        def write_imu_until(count: int) -> None:
            """Write the first ``count`` IMU messages (those not written yet)."""
            measure_until(count)
            for j in range(state['written'], count):
                header = bag.header(START_STAMP_NS + int(imu_stamps_ns[j]), IMU_FRAME, seq=j)
                message = _imu_message(types, header, (measured[0][j], measured[1][j], measured[2][j]), covariances)
                bag.write_msg(IMU_TOPIC, START_STAMP_NS + int(imu_recorded_ns[j]), message)
            state['written'] = max(state['written'], count)

        try:
            with tqdm(
                total=n_scans, unit='scan', disable=not progress, file=sys.stderr, desc=f'simulate {config.scenario}'
            ) as bar:
                for k in range(n_scans):
                    sweep_end = int(sweep_offsets_ns[k] + period_ns)
                    # IMU samples recorded up to and including the end of this sweep, before its cloud.
                    write_imu_until(int(np.searchsorted(imu_recorded_ns, sweep_end, side='right')))
                    sweep = simulate_sweep(
                        lidar,
                        world.scene,
                        world.trajectory,
                        sweep_offsets_ns[k] / 1e9,
                        None if config.ideal else scenario_rng(config.seed, 'lidar', k),
                        dtype,
                    )
                    header = bag.header(START_STAMP_NS + int(sweep_offsets_ns[k]) + stamp_offset_ns, LIDAR_FRAME, seq=k)
                    bag.write_msg(CLOUD_TOPIC, START_STAMP_NS + sweep_end, make_cloud_msg(types, header, sweep.points))
                    label_writer.add_scan(sweep.labels)
                    total_points += len(sweep.points)
                    bar.update(1)
                write_imu_until(n_imu)  # a late IMU's last messages, after the last cloud
        except BaseException:
            label_writer.abort()
            raise

    label_writer.close(START_STAMP_NS + sweep_offsets_ns + stamp_offset_ns, world.scene.classes)
    # Ground truth: lidar poses at the header stamps relative to the first one (the first sweep start, t = 0, also
    # the first IMU stamp, unless the preset stamps its sweeps later).
    poses = world.trajectory.matrices((sweep_offsets_ns + stamp_offset_ns) / 1e9)
    dense = world.trajectory.matrices(imu_offsets_ns / 1e9)
    first = poses[0].copy()
    sim_output.write_tum(
        sidecars.sidecar_path(bag_path, sidecars.GROUND_TRUTH),
        START_STAMP_NS + sweep_offsets_ns + stamp_offset_ns,
        sim_output.relative_poses(poses),
    )
    dense_relative = np.einsum('ij,njk->nik', np.linalg.inv(first), dense)
    sim_output.write_tum(
        sidecars.sidecar_path(bag_path, sidecars.GROUND_TRUTH_DENSE), START_STAMP_NS + imu_offsets_ns, dense_relative
    )
    result = SimResult(
        bag_path, n_scans, len(imu_offsets_ns), total_points, n_scans * lidar.scan_period, dict(world.facts)
    )
    from scipy.spatial.transform import Rotation

    first_quaternion = Rotation.from_matrix(first[:3, :3]).as_quat()
    if first_quaternion[3] < 0:
        first_quaternion = -first_quaternion
    travelled = np.linalg.norm(np.diff(dense[:, :3, 3], axis=0), axis=1).sum()
    sim_output.write_yaml(
        sidecars.sidecar_path(bag_path, sidecars.SCENARIO),
        {
            'generator': f'lego_loam_py {__version__} simulator version {SIM_VERSION}',
            'command': config.command(bag_path.name),
            'config': config.to_dict(),
            'scenario': {
                'name': world.name,
                'description': world.description,
                'seed': config.seed,
                'default_duration_s': world.default_duration,
                **world.facts,
            },
            'recording': {
                'scans': n_scans,
                'duration_s': round(n_scans * lidar.scan_period, 6),
                'imu_messages': len(imu_offsets_ns),
                'points': total_points,
                'mean_points_per_scan': round(total_points / n_scans, 1),
                'distance_travelled_m': round(float(travelled), 3),
                'start_stamp_ns': START_STAMP_NS,
                'topics': {
                    CLOUD_TOPIC: {
                        'type': 'sensor_msgs/msg/PointCloud2',
                        'frame_id': LIDAR_FRAME,
                        'layout': config.layout,
                        'point_step': int(dtype.itemsize),
                    },
                    IMU_TOPIC: {'type': 'sensor_msgs/msg/Imu', 'frame_id': IMU_FRAME},
                },
                'bag_time': 'clouds at sweep end (stamp + scan period), IMU at its stamp',
            },
            'lidar': lidar.describe(),
            'imu': imu.describe(biases),
            'ground_truth': {
                'file': sidecars.GROUND_TRUTH,
                'dense_file': sidecars.GROUND_TRUTH_DENSE,
                'frame': 'lidar (REP-103: x forward, y left, z up) relative to its pose at the first sweep start',
                'world': 'gravity-aligned simulator world, z up',
                'world_T_first': {
                    'translation': [round(float(v), 9) for v in first[:3, 3]],
                    'quaternion_xyzw': [round(float(v), 12) for v in first_quaternion],
                },
            },
            'labels': {
                'file': sidecars.LABELS,
                'values': '0 none (clutter, unlabeled), 1 ground, >= 2 object id',
                'objects': len(world.scene.classes) - 2,
                'classes': sorted(set(world.scene.classes[2:])),
            },
        },
    )
    sidecars.sidecar_path(bag_path, sidecars.NOTE).write_text(_note(config, bag_path.name, result, world.description))
    return result


# ------------------------------------------------------------------------------------------------- cache


def cache_root() -> Path:
    """Base of lego_loam_py's caches: ``$LEGO_LOAM_CACHE``, else ``$XDG_CACHE_HOME/lego_loam_py``, else
    ``~/.cache/lego_loam_py``. Simulated scenarios go to its ``sim/`` folder."""
    if os.environ.get('LEGO_LOAM_CACHE'):
        return Path(os.environ['LEGO_LOAM_CACHE']).expanduser()
    base = os.environ.get('XDG_CACHE_HOME') or str(Path.home() / '.cache')
    return Path(base).expanduser() / 'lego_loam_py'


def cached_scenario(
    name: str, duration: float | None = None, seed: int = 0, progress: bool = False, **options: Any
) -> Path:
    """Path of the bag of scenario ``name`` (``duration`` [s], ``seed``, further :class:`SimConfig` fields in
    ``options``), generated into the cache on first use and reused afterwards.

    The entry is ``<cache_root()>/sim/<name>-<hash of the configuration>``: the ROS 2 bag directory itself
    (or, for ``ros1=True``, a folder holding ``<name>.bag``). Generation writes to a temporary folder that
    is renamed when complete, so an interrupted run never leaves a half-written entry behind.
    """
    config = SimConfig(scenario=name, duration=duration, seed=seed, **options).validate()
    folder = cache_root() / 'sim'
    entry = folder / f'{name}-{config.cache_key()}'

    def bag_in(directory: Path) -> Path:
        return directory / f'{name}.bag' if config.ros1 else directory

    if (entry / 'README.md').is_file() or (config.ros1 and bag_in(entry).is_file()):
        return bag_in(entry)
    folder.mkdir(parents=True, exist_ok=True)
    temporary = folder / f'.{entry.name}.tmp{os.getpid()}'
    if temporary.exists():
        shutil.rmtree(temporary)
    try:
        if config.ros1:
            temporary.mkdir()
        simulate(config, bag_in(temporary), progress=progress)
        try:
            os.rename(temporary, entry)
        except OSError:
            if not entry.exists():  # another process finished first otherwise
                raise
    finally:
        if temporary.exists():
            shutil.rmtree(temporary, ignore_errors=True)
    return bag_in(entry)
