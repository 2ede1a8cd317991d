"""IMU model: a 9-axis unit (orientation + gyroscope + accelerometer) rigidly attached to the lidar.

Frames (the conventions of :class:`lego_loam_py.core.frames.ImuMounting`, which the pipeline's ``imu.*``
parameters undo): by default the IMU sits at the lidar origin with the lidar's axes (x forward, y left, z up),
as LeGO-LOAM assumes. ``extrinsic_rpy_deg`` rotates its axes: ``R_lidar_imu = Rz(yaw) Ry(pitch) Rx(roll)``
maps IMU coordinates into lidar coordinates (``p_lidar = R_lidar_imu p_imu``); ``lever_arm`` [m] is the IMU
origin in the lidar frame; ``orientation_rpy_deg`` rotates the frame whose attitude the orientation field
reports (``R_imu_orientation``, as a 9-axis unit whose orientation output uses other axes than its rates);
``time_offset`` [s] is added to the stamps (the IMU clock runs that far ahead of the lidar's).

Measurements at time t (all from the very trajectory functions that place the lidar):

* ``angular_velocity`` = R_lidar_imu^T omega_lidar(t) + b_g + n_g [rad/s], body (IMU) frame;
* ``linear_acceleration`` = R_lidar_imu^T R_world_lidar^T (a_world(t, lever_arm) - g_world) + b_a + n_a
  [m/s^2]: the specific force at the IMU's own position (on a lever arm the rotation adds centripetal and
  tangential acceleration), gravity included as a real accelerometer reports it (+9.81 on z when level at
  rest); ``g_world = (0, 0, -9.81)`` (LeGO-LOAM's constant);
* ``orientation`` = Exp(e_bias + e_noise) R_world_lidar(t) R_lidar_imu R_imu_orientation, as (x, y, z, w):
  in a gravity-aligned world frame (z up; the yaw reference is the simulator world's), like an AHRS output.

Noise (:class:`ImuNoise`, defaults of a good MEMS unit such as an Xsens MTi-300 after turn-on): white
noise given as a density and discretised as ``sigma = density * sqrt(rate)``; constant biases drawn once
per simulation from N(0, bias_sigma^2) per axis (seeded, recorded in scenario.yaml).

The errors of real 9-axis units (issue 34; all off by default, named sets of them in :data:`IMU_PROFILES`):

* constant biases drawn with a magnitude in a given range and a random sign per axis (a unit known to lie
  there), and a wandering part per axis, a first-order Gauss-Markov process that starts at 0 with stationary
  sigma ``*_bias_instability`` and correlation time ``*_bias_time``:
  ``b[k+1] = a b[k] + sigma sqrt(1 - a^2) w[k]``, ``a = exp(-dt / time)``, so ``Var(b(t)) = sigma^2 (1 -
  exp(-2 t / time))``: a random walk of density ``sigma sqrt(2 / time)`` over times much shorter than ``time``;
* scale-factor errors and axis misalignment: ``angular_velocity = M_g R_lidar_imu^T omega + ...`` with
  ``M = I + diag(scale errors) + cross-axis terms``, each drawn uniformly within its bound (likewise ``M_a``
  for the specific force, gravity included);
* the orientation field: a constant tilt (roll/pitch error about a random horizontal axis, magnitude in a
  range), a constant yaw offset about the world z axis (the yaw reference of a magnetometer-aided unit is its
  own: anything in -180..180 deg), white noise, and a slowly wandering heading error (Gauss-Markov, as a
  magnetometer-referenced heading wanders with the local field):
  ``orientation = Rz(yaw_offset + h(t)) Exp(e_bias + e_noise) R_world_imu``;
* stamps: ``time_offset`` plus Gaussian jitter (``stamp_jitter``, clipped at 0.49 of the sample period so
  that stamps stay increasing), and ``record_late``: the recorder receives each sample at its stamp rather
  than when it was measured (see the simulator).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from lego_loam_py.core.frames import rpy_to_matrix
from lego_loam_py.sim.trajectory import Trajectory

__all__ = ['GRAVITY', 'ImuNoise', 'ImuBiases', 'ImuModel', 'ImuSamples', 'IMU_PROFILES', 'PROFILE_SOURCES']

GRAVITY = 9.81  # [m/s^2], LeGO-LOAM's value


@dataclass(frozen=True)
class ImuNoise:
    """White-noise densities and bias magnitudes (1 sigma, per axis)."""

    gyro_noise_density: float = math.radians(0.01)  # [rad/s/sqrt(Hz)]  (0.01 deg/s/sqrt(Hz))
    gyro_bias_sigma: float = math.radians(0.02)  # [rad/s]           (0.02 deg/s)
    accel_noise_density: float = 60e-6 * GRAVITY  # [m/s^2/sqrt(Hz)]  (60 ug/sqrt(Hz))
    accel_bias_sigma: float = 0.02  # [m/s^2]           (~2 mg)
    orientation_noise: float = math.radians(0.05)  # white noise on each axis [rad]
    tilt_bias_sigma: float = math.radians(0.1)  # constant roll/pitch error [rad]
    heading_bias_sigma: float = math.radians(0.5)  # constant yaw error [rad]
    # The errors below came later (issue 34). At their defaults they draw nothing and change nothing: the unit
    # above, and every recording made with it, stays as it was.
    gyro_bias_range: tuple[float, float] | None = None  # [rad/s] |constant bias| per axis, uniform, random sign
    accel_bias_range: tuple[float, float] | None = None  # [m/s^2] (both replace the *_bias_sigma draw)
    gyro_bias_instability: float = 0.0  # [rad/s] stationary sigma of the wandering bias
    gyro_bias_time: float = 100.0  # [s] its correlation time
    accel_bias_instability: float = 0.0  # [m/s^2]
    accel_bias_time: float = 100.0  # [s]
    gyro_scale_error: float = 0.0  # bound of each axis' scale-factor error (fraction)
    accel_scale_error: float = 0.0
    misalignment: float = 0.0  # [rad] bound of each cross-axis term (gyro and accel)
    tilt_range: tuple[float, float] | None = None  # [rad] |constant roll/pitch error| (replaces tilt_bias_sigma)
    yaw_offset_range: tuple[float, float] | None = None  # [rad] constant yaw offset, uniform in the range
    heading_drift: float = 0.0  # [rad] stationary sigma of the wandering heading error
    heading_drift_time: float = 60.0  # [s] its correlation time

    @staticmethod
    def none() -> ImuNoise:
        return ImuNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def wanders(self) -> bool:
        """True when a bias or the heading wanders (a Gauss-Markov process to carry from sample to sample)."""
        return bool(self.gyro_bias_instability or self.accel_bias_instability or self.heading_drift)

    def changed(self) -> dict:
        """The fields added for issue 34 that differ from their defaults, as plain data (scenario.yaml)."""
        out = {}
        for f in fields(self)[7:]:
            value = getattr(self, f.name)
            if value != f.default:
                out[f.name] = [float(v) for v in value] if isinstance(value, tuple) else float(value)
        return out


_UG = 1e-6 * GRAVITY  # [m/s^2] per micro-g
_DEG_H = math.radians(1.0) / 3600.0  # [rad/s] per deg/h

# Named units (``lego_loam_py simulate --imu-profile``). Where each number comes from is said beside it;
# "assumed" marks what no data sheet states (the correlation times of the bias wander, residual biases after a
# unit's own calibration) -- take those as plausible, not as measured.
IMU_PROFILES: dict[str, ImuNoise] = {
    # The simulator's unit since its first version (an Xsens MTi-300 after turn-on): its noise densities are
    # the MTi-300 data sheet's (gyro 0.01 deg/s/sqrt(Hz), accel 60 ug/sqrt(Hz)); its constant errors were
    # chosen small (0.02 deg/s, 0.02 m/s^2, 0.1 deg tilt, 0.5 deg heading). Kept as the default.
    'default': ImuNoise(),
    # A consumer 9-axis module of the BNO055 / MPU-9250 class, as measured on the unit of issue 34.
    'consumer': ImuNoise(
        # BNO055 data sheet (BST-BNO055-DS000, Table 0-2, its BMG160-class gyro): 0.014 deg/s/sqrt(Hz); the
        # MPU-9250 product specification gives 0.01. (The BNO055 figures are as recalled, not re-read here.)
        gyro_noise_density=math.radians(0.014),
        gyro_bias_sigma=0.0,
        # BNO055 data sheet: 150 ug/sqrt(Hz) (MPU-9250: 300 ug/sqrt(Hz)).
        accel_noise_density=150.0 * _UG,
        accel_bias_sigma=0.0,
        # Its AHRS output: 0.05 deg white (the BNO055 reports Euler angles in 1/16 deg steps); assumed.
        orientation_noise=math.radians(0.05),
        tilt_bias_sigma=0.0,
        heading_bias_sigma=0.0,
        # Measured on the unit of issue 34 after the module's own calibration: 1-3 mrad/s and 0.02-0.07 m/s^2.
        # (The data sheets' untrimmed zero-rate and zero-g offsets are far wider: BNO055 +-1 deg/s and
        # +-80 mg, MPU-9250 +-5 deg/s and +-60-80 mg.)
        gyro_bias_range=(1e-3, 3e-3),
        accel_bias_range=(0.02, 0.07),
        # Neither data sheet states an in-run bias instability: assumed 20 deg/h and 1 mg wander, 100 s.
        gyro_bias_instability=20.0 * _DEG_H,
        gyro_bias_time=100.0,
        accel_bias_instability=1000.0 * _UG,
        accel_bias_time=100.0,
        # The MPU-9250 product specification allows +-3 % sensitivity (gyro and accel) and +-2 % cross-axis
        # sensitivity per part; a 2 % cross-axis term would put 0.2 m/s^2 on a level unit's x and y, more than
        # the 0.02-0.07 m/s^2 measured, so this trimmed module is taken at 1 % and 0.1 deg: assumed.
        gyro_scale_error=0.01,
        accel_scale_error=0.01,
        misalignment=math.radians(0.1),
        # Measured (issue 34): the orientation tilted by a constant 0.1-0.3 deg, its yaw offset arbitrary (the
        # module's heading is magnetic). Its heading wanders with the local field: assumed 1 deg over 60 s.
        tilt_range=(math.radians(0.1), math.radians(0.3)),
        yaw_offset_range=(-math.pi, math.pi),
        heading_drift=math.radians(1.0),
        heading_drift_time=60.0,
    ),
    # An industrial MEMS AHRS of the Xsens MTi (1-series / 300) and VectorNav VN-100 class.
    'industrial': ImuNoise(
        # Xsens MTi-1 series data sheet: gyro 0.007 deg/s/sqrt(Hz), in-run bias stability 10 deg/h; accel
        # 120 ug/sqrt(Hz), 0.03 mg (the MTi-300's: 0.01 deg/s/sqrt(Hz), 10 deg/h, 60 ug/sqrt(Hz), 15 ug).
        # VectorNav's VN-100 is of the same order (not re-read here). Correlation times assumed.
        gyro_noise_density=math.radians(0.007),
        gyro_bias_sigma=0.0,
        accel_noise_density=120.0 * _UG,
        accel_bias_sigma=0.0,
        gyro_bias_instability=10.0 * _DEG_H,
        gyro_bias_time=100.0,
        accel_bias_instability=30.0 * _UG,
        accel_bias_time=100.0,
        # What is left after the unit's on-line bias estimation: no data sheet states it; assumed a tenth of the
        # consumer module's (0.1-0.5 mrad/s, 0.5-2 mg).
        gyro_bias_range=(1e-4, 5e-4),
        accel_bias_range=(0.005, 0.02),
        # Factory-calibrated scale and alignment: assumed 0.1 % and 0.05 deg (the MTi data sheets give 0.1 %
        # of full scale as the gyro's non-linearity).
        gyro_scale_error=0.001,
        accel_scale_error=0.001,
        misalignment=math.radians(0.05),
        # MTi-300 data sheet: roll/pitch 0.2 deg RMS, heading 1 deg RMS: a tilt of 0.05-0.2 deg, a heading that
        # wanders 1 deg (over an assumed 60 s), 0.02 deg white (assumed); the yaw reference is magnetic north.
        orientation_noise=math.radians(0.02),
        tilt_bias_sigma=0.0,
        heading_bias_sigma=0.0,
        tilt_range=(math.radians(0.05), math.radians(0.2)),
        yaw_offset_range=(-math.pi, math.pi),
        heading_drift=math.radians(1.0),
        heading_drift_time=60.0,
    ),
}
PROFILE_SOURCES = {
    'default': "the simulator's unit since its first version (Xsens MTi-300 noise densities)",
    'consumer': 'BNO055 / MPU-9250 data sheets; biases and orientation errors as measured in issue 34',
    'industrial': 'Xsens MTi-1 series and MTi-300 data sheets (VectorNav VN-100 class)',
}


@dataclass(frozen=True)
class ImuBiases:
    """The constant errors of one simulated unit (drawn once per simulation)."""

    gyro: tuple[float, float, float] = (0.0, 0.0, 0.0)  # [rad/s], IMU frame
    accel: tuple[float, float, float] = (0.0, 0.0, 0.0)  # [m/s^2], IMU frame
    orientation: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rotation vector in the world [rad]
    yaw_offset: float = 0.0  # [rad] about the world z axis, after ``orientation``
    gyro_matrix: tuple | None = None  # 3x3 rows, I + scale errors + cross-axis terms (None: the identity)
    accel_matrix: tuple | None = None


@dataclass
class ImuSamples:
    """IMU measurements at ``times``."""

    times: np.ndarray  # (N,) [s]
    orientation: np.ndarray  # (N, 4) quaternion (x, y, z, w), world <- imu
    angular_velocity: np.ndarray  # (N, 3) [rad/s], IMU frame
    linear_acceleration: np.ndarray  # (N, 3) [m/s^2], IMU frame, specific force


@dataclass(frozen=True)
class ImuModel:
    """Rate, noise, mounting and stamping of the simulated IMU."""

    rate: float = 200.0  # [Hz]
    noise: ImuNoise = field(default_factory=ImuNoise)
    extrinsic_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU axes in the lidar frame [deg]
    gravity: float = GRAVITY
    lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU origin in the lidar frame [m]
    orientation_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # orientation frame in the IMU frame [deg]
    time_offset: float = 0.0  # IMU stamp - lidar stamp [s]
    stamp_jitter: float = 0.0  # [s] sigma of Gaussian stamp noise (clipped at 0.49 sample periods)
    record_late: bool = False  # the recorder receives each sample at its stamp, not when measured
    profile: str = 'default'  # name of the noise's profile (IMU_PROFILES), for the record

    def ideal(self) -> ImuModel:
        return replace(self, noise=ImuNoise.none())

    @property
    def rotation_lidar_imu(self) -> np.ndarray:
        """3x3 ``R_lidar_imu`` (p_lidar = R p_imu)."""
        return rpy_to_matrix(self.extrinsic_rpy_deg)

    @property
    def rotation_imu_orientation(self) -> np.ndarray:
        """3x3 ``R_imu_orientation``: the axes of the frame the orientation field reports, in IMU axes."""
        return rpy_to_matrix(self.orientation_rpy_deg)

    @property
    def gyro_sigma(self) -> float:
        """Per-sample white-noise sigma of the gyroscope [rad/s]."""
        return self.noise.gyro_noise_density * math.sqrt(self.rate)

    @property
    def accel_sigma(self) -> float:
        """Per-sample white-noise sigma of the accelerometer [m/s^2]."""
        return self.noise.accel_noise_density * math.sqrt(self.rate)

    @property
    def has_white_noise(self) -> bool:
        n = self.noise
        return bool(n.gyro_noise_density or n.accel_noise_density or n.orientation_noise)

    def covariances(self) -> dict[str, np.ndarray]:
        """Diagonal 3x3 covariances (row-major, 9 values) for the Imu message fields. The orientation's: its
        white noise, constant tilt (the range's upper end) and heading errors, without the yaw offset (the
        unit's yaw reference is its own, which a 9-axis driver does not count as an error either)."""
        n = self.noise
        tilt = n.tilt_bias_sigma if n.tilt_range is None else n.tilt_range[1]
        heading = n.orientation_noise**2 + n.heading_bias_sigma**2
        if n.heading_drift:
            heading += n.heading_drift**2
        orientation = np.diag([n.orientation_noise**2 + tilt**2] * 2 + [heading])
        return dict(
            orientation=orientation.ravel(),
            angular_velocity=np.eye(3).ravel() * self.gyro_sigma**2,
            linear_acceleration=np.eye(3).ravel() * self.accel_sigma**2,
        )

    def draw_biases(self, rng: np.random.Generator) -> ImuBiases:
        """The constant errors of one unit. The first three draws are the original unit's, in its order (so
        its recordings keep their biases); the errors added since are drawn after them, only when set."""
        n = self.noise
        gyro = rng.standard_normal(3) * n.gyro_bias_sigma
        accel = rng.standard_normal(3) * n.accel_bias_sigma
        orientation = rng.standard_normal(3) * [n.tilt_bias_sigma, n.tilt_bias_sigma, n.heading_bias_sigma]
        if n.gyro_bias_range is not None:
            gyro = _signed_magnitudes(rng, n.gyro_bias_range)
        if n.accel_bias_range is not None:
            accel = _signed_magnitudes(rng, n.accel_bias_range)
        if n.tilt_range is not None:  # about a horizontal axis in a random direction
            magnitude, azimuth = rng.uniform(*n.tilt_range), rng.uniform(-math.pi, math.pi)
            orientation = np.array([magnitude * math.cos(azimuth), magnitude * math.sin(azimuth), orientation[2] + 0.0])
        yaw_offset = float(rng.uniform(*n.yaw_offset_range)) if n.yaw_offset_range is not None else 0.0
        matrices = [
            _sensitivity(rng, scale, n.misalignment) if scale or n.misalignment else None
            for scale in (n.gyro_scale_error, n.accel_scale_error)
        ]
        return ImuBiases(
            tuple(float(v) for v in gyro),
            tuple(float(v) for v in accel),
            tuple(float(v) for v in orientation),
            yaw_offset,
            *matrices,
        )

    def wander(self, count: int, rng: np.random.Generator, previous: np.ndarray | None = None) -> np.ndarray:
        """The next ``count`` samples (count, 7) of the wandering errors: gyro bias (3, rad/s), accelerometer
        bias (3, m/s^2), heading (rad), each a first-order Gauss-Markov process at the IMU rate that carries on
        from ``previous`` (the last sample of the previous call, (7,); None: 0, the start)."""
        n = self.noise
        sigma = np.array([n.gyro_bias_instability] * 3 + [n.accel_bias_instability] * 3 + [n.heading_drift])
        times = np.array([n.gyro_bias_time] * 3 + [n.accel_bias_time] * 3 + [n.heading_drift_time])
        decay = np.exp(-1.0 / (self.rate * times))
        gain = sigma * np.sqrt(1.0 - decay**2)
        previous = np.zeros(7) if previous is None else np.asarray(previous, dtype=float)
        drive = rng.standard_normal((count, 7))
        out = np.zeros((count, 7))
        for axis in np.flatnonzero(sigma):  # x[k] = decay x[k-1] + gain w[k], as a filter (7 axes, no samples)
            out[:, axis] = lfilter(
                [gain[axis]], [1.0, -decay[axis]], drive[:, axis], zi=[decay[axis] * previous[axis]]
            )[0]
        return out

    def stamps_ns(self, measured_ns: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """Header stamps [ns] of samples measured at ``measured_ns`` (the lidar's clock): ``time_offset`` later,
        plus the jitter (``rng`` draws it; clipped so that stamps stay increasing)."""
        stamps = np.asarray(measured_ns, dtype=np.int64) + int(round(self.time_offset * 1e9))
        if self.stamp_jitter and rng is not None:
            bound = 0.49 / self.rate
            jitter = np.clip(rng.standard_normal(len(stamps)) * self.stamp_jitter, -bound, bound)
            stamps = stamps + np.round(jitter * 1e9).astype(np.int64)
        return stamps

    def measure(
        self,
        trajectory: Trajectory,
        times: np.ndarray,
        biases: ImuBiases,
        rng: np.random.Generator | None,
        wander: np.ndarray | None = None,
    ) -> ImuSamples:
        """Measurements at ``times`` [s]; ``rng`` draws the white noise (None: noise-free samples); ``wander``
        (len(times), 7) the wandering errors at those times (:meth:`wander`; None: none)."""
        times = np.asarray(times, dtype=float)
        rotation, _ = trajectory.pose(times)
        omega_lidar = trajectory.angular_velocity(times)
        lever_arm = np.asarray(self.lever_arm, dtype=float)
        accel_world = trajectory.acceleration(times, lever_arm if lever_arm.any() else None)
        r_li = self.rotation_lidar_imu
        gravity = np.array([0.0, 0.0, -self.gravity])
        specific_lidar = np.einsum('nji,nj->ni', rotation, accel_world - gravity)
        gyro = omega_lidar @ r_li  # R_li^T omega for each row
        accel = specific_lidar @ r_li
        if biases.gyro_matrix is not None:  # scale errors and misalignment: M v for each row
            gyro = gyro @ np.asarray(biases.gyro_matrix).T
        if biases.accel_matrix is not None:
            accel = accel @ np.asarray(biases.accel_matrix).T
        gyro = gyro + np.asarray(biases.gyro)
        accel = accel + np.asarray(biases.accel)
        if wander is not None:
            gyro = gyro + wander[:, :3]
            accel = accel + wander[:, 3:6]
        world_imu = Rotation.from_matrix(
            rotation @ (r_li @ self.rotation_imu_orientation if any(self.orientation_rpy_deg) else r_li)
        )
        error = np.broadcast_to(np.asarray(biases.orientation), (len(times), 3)).copy()
        if rng is not None:
            n = len(times)
            gyro = gyro + rng.standard_normal((n, 3)) * self.gyro_sigma
            accel = accel + rng.standard_normal((n, 3)) * self.accel_sigma
            error = error + rng.standard_normal((n, 3)) * self.noise.orientation_noise
        orientation_error = Rotation.from_rotvec(error)
        if biases.yaw_offset or (wander is not None and wander[:, 6].any()):
            heading = biases.yaw_offset + (wander[:, 6] if wander is not None else np.zeros(len(times)))
            orientation_error = Rotation.from_rotvec(np.outer(heading, [0.0, 0.0, 1.0])) * orientation_error
        quaternion = (orientation_error * world_imu).as_quat()
        quaternion[quaternion[:, 3] < 0] *= -1.0
        return ImuSamples(times, quaternion, gyro, accel)

    def describe(self, biases: ImuBiases) -> dict:
        """Plain-data summary for scenario.yaml (SI units; the drawn biases included)."""
        mounting = {}
        if any(self.lever_arm):  # (only when set: the sidecars of recordings without them stay as they were)
            mounting['lever_arm_m'] = list(self.lever_arm)
        if any(self.orientation_rpy_deg):
            mounting['orientation_rpy_deg'] = list(self.orientation_rpy_deg)
            mounting['rotation_imu_orientation'] = (self.rotation_imu_orientation.round(12) + 0.0).tolist()
        if self.time_offset:
            mounting['time_offset_s'] = self.time_offset
        if self.stamp_jitter:
            mounting['stamp_jitter_s'] = self.stamp_jitter
        if self.record_late:
            mounting['recorded'] = 'at its stamp, as a late driver delivers it (not when measured)'
        if self.profile != 'default':
            mounting['profile'] = self.profile
        noise = {k: float(v) for k, v in asdict(self.noise).items() if k in _ORIGINAL_NOISE_FIELDS}
        drawn = dict(gyro=list(biases.gyro), accel=list(biases.accel), orientation_rotvec=list(biases.orientation))
        if biases.yaw_offset:
            drawn['yaw_offset_rad'] = biases.yaw_offset
        for name in ('gyro_matrix', 'accel_matrix'):
            if getattr(biases, name) is not None:
                drawn[name] = [list(row) for row in getattr(biases, name)]
        return dict(
            rate_hz=self.rate,
            gravity=self.gravity,
            extrinsic_rpy_deg=list(self.extrinsic_rpy_deg),
            rotation_lidar_imu=(self.rotation_lidar_imu.round(12) + 0.0).tolist(),
            **mounting,
            noise={**noise, **self.noise.changed()},
            gyro_sigma_per_sample=self.gyro_sigma,
            accel_sigma_per_sample=self.accel_sigma,
            biases=drawn,
        )


_ORIGINAL_NOISE_FIELDS = [f.name for f in fields(ImuNoise)][:7]


def _signed_magnitudes(rng: np.random.Generator, bounds: tuple[float, float]) -> np.ndarray:
    """Three values with magnitudes uniform in ``bounds`` and random signs."""
    magnitude = rng.uniform(bounds[0], bounds[1], 3)
    return np.where(rng.random(3) < 0.5, -magnitude, magnitude)


def _sensitivity(rng: np.random.Generator, scale_error: float, misalignment: float) -> tuple:
    """I + diag(scale errors) + cross-axis terms, each uniform within its bound, as rows (tuple of tuples)."""
    matrix = np.eye(3) + np.diag(rng.uniform(-scale_error, scale_error, 3))
    off_diagonal = ~np.eye(3, dtype=bool)
    matrix[off_diagonal] = rng.uniform(-misalignment, misalignment, 6)
    return tuple(tuple(float(v) for v in row) for row in matrix)
