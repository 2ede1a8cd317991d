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
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from lego_loam_py.core.frames import rpy_to_matrix
from lego_loam_py.sim.trajectory import Trajectory

__all__ = ['GRAVITY', 'ImuNoise', 'ImuBiases', 'ImuModel', 'ImuSamples']

GRAVITY = 9.81  # [m/s^2], LeGO-LOAM's value


@dataclass(frozen=True)
class ImuNoise:
    """White-noise densities and bias magnitudes (1 sigma, per axis)."""

    gyro_noise_density: float = math.radians(0.01)    # [rad/s/sqrt(Hz)]  (0.01 deg/s/sqrt(Hz))
    gyro_bias_sigma: float = math.radians(0.02)       # [rad/s]           (0.02 deg/s)
    accel_noise_density: float = 60e-6 * GRAVITY       # [m/s^2/sqrt(Hz)]  (60 ug/sqrt(Hz))
    accel_bias_sigma: float = 0.02                     # [m/s^2]           (~2 mg)
    orientation_noise: float = math.radians(0.05)     # white noise on each axis [rad]
    tilt_bias_sigma: float = math.radians(0.1)        # constant roll/pitch error [rad]
    heading_bias_sigma: float = math.radians(0.5)     # constant yaw error [rad]

    @staticmethod
    def none() -> 'ImuNoise':
        return ImuNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ImuBiases:
    """The constant errors of one simulated unit (drawn once per simulation)."""

    gyro: tuple[float, float, float] = (0.0, 0.0, 0.0)          # [rad/s], IMU frame
    accel: tuple[float, float, float] = (0.0, 0.0, 0.0)         # [m/s^2], IMU frame
    orientation: tuple[float, float, float] = (0.0, 0.0, 0.0)   # rotation vector in the world [rad]


@dataclass
class ImuSamples:
    """IMU measurements at ``times``."""

    times: np.ndarray                 # (N,) [s]
    orientation: np.ndarray           # (N, 4) quaternion (x, y, z, w), world <- imu
    angular_velocity: np.ndarray      # (N, 3) [rad/s], IMU frame
    linear_acceleration: np.ndarray   # (N, 3) [m/s^2], IMU frame, specific force


@dataclass(frozen=True)
class ImuModel:
    """Rate, noise and mounting of the simulated IMU."""

    rate: float = 200.0                                               # [Hz]
    noise: ImuNoise = field(default_factory=ImuNoise)
    extrinsic_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)   # IMU axes in the lidar frame [deg]
    gravity: float = GRAVITY
    lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0)           # IMU origin in the lidar frame [m]
    orientation_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # orientation frame in the IMU frame [deg]
    time_offset: float = 0.0                                          # IMU stamp - lidar stamp [s]

    def ideal(self) -> 'ImuModel':
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

    def covariances(self) -> dict[str, np.ndarray]:
        """Diagonal 3x3 covariances (row-major, 9 values) for the Imu message fields."""
        n = self.noise
        orientation = np.diag([n.orientation_noise ** 2 + n.tilt_bias_sigma ** 2] * 2
                              + [n.orientation_noise ** 2 + n.heading_bias_sigma ** 2])
        return dict(orientation=orientation.ravel(), angular_velocity=np.eye(3).ravel() * self.gyro_sigma ** 2,
                    linear_acceleration=np.eye(3).ravel() * self.accel_sigma ** 2)

    def draw_biases(self, rng: np.random.Generator) -> ImuBiases:
        n = self.noise
        gyro = rng.standard_normal(3) * n.gyro_bias_sigma
        accel = rng.standard_normal(3) * n.accel_bias_sigma
        orientation = rng.standard_normal(3) * [n.tilt_bias_sigma, n.tilt_bias_sigma, n.heading_bias_sigma]
        return ImuBiases(tuple(float(v) for v in gyro), tuple(float(v) for v in accel),
                         tuple(float(v) for v in orientation))

    def measure(self, trajectory: Trajectory, times: np.ndarray, biases: ImuBiases,
                rng: np.random.Generator | None) -> ImuSamples:
        """Measurements at ``times`` [s]; ``rng`` draws the white noise (None: noise-free samples)."""
        times = np.asarray(times, dtype=float)
        rotation, _ = trajectory.pose(times)
        omega_lidar = trajectory.angular_velocity(times)
        lever_arm = np.asarray(self.lever_arm, dtype=float)
        accel_world = trajectory.acceleration(times, lever_arm if lever_arm.any() else None)
        r_li = self.rotation_lidar_imu
        gravity = np.array([0.0, 0.0, -self.gravity])
        specific_lidar = np.einsum('nji,nj->ni', rotation, accel_world - gravity)
        gyro = omega_lidar @ r_li + np.asarray(biases.gyro)          # R_li^T omega for each row
        accel = specific_lidar @ r_li + np.asarray(biases.accel)
        world_imu = Rotation.from_matrix(rotation @ (r_li @ self.rotation_imu_orientation
                                                     if any(self.orientation_rpy_deg) else r_li))
        error = np.broadcast_to(np.asarray(biases.orientation), (len(times), 3)).copy()
        if rng is not None:
            n = len(times)
            gyro = gyro + rng.standard_normal((n, 3)) * self.gyro_sigma
            accel = accel + rng.standard_normal((n, 3)) * self.accel_sigma
            error = error + rng.standard_normal((n, 3)) * self.noise.orientation_noise
        quaternion = (Rotation.from_rotvec(error) * world_imu).as_quat()
        quaternion[quaternion[:, 3] < 0] *= -1.0
        return ImuSamples(times, quaternion, gyro, accel)

    def describe(self, biases: ImuBiases) -> dict:
        """Plain-data summary for scenario.yaml (SI units; the drawn biases included)."""
        mounting = {}
        if any(self.lever_arm):   # (only when set: the sidecars of recordings without them stay as they were)
            mounting['lever_arm_m'] = list(self.lever_arm)
        if any(self.orientation_rpy_deg):
            mounting['orientation_rpy_deg'] = list(self.orientation_rpy_deg)
            mounting['rotation_imu_orientation'] = (self.rotation_imu_orientation.round(12) + 0.0).tolist()
        if self.time_offset:
            mounting['time_offset_s'] = self.time_offset
        return dict(rate_hz=self.rate, gravity=self.gravity, extrinsic_rpy_deg=list(self.extrinsic_rpy_deg),
                    rotation_lidar_imu=(self.rotation_lidar_imu.round(12) + 0.0).tolist(), **mounting,
                    noise={k: float(v) for k, v in asdict(self.noise).items()},
                    gyro_sigma_per_sample=self.gyro_sigma, accel_sigma_per_sample=self.accel_sigma,
                    biases=dict(gyro=list(biases.gyro), accel=list(biases.accel),
                                orientation_rotvec=list(biases.orientation)))
