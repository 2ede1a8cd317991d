"""featureAssociation: deskew, feature extraction and scan-to-scan odometry for one scan at a time.

Per scan (reference §6.2): the segmented cloud (lidar axes, intensity row + col/10000) is turned into LOAM
camera axes and every point gets its relative time in the sweep; with an IMU it is deskewed to the sweep
start; features are extracted; the first scan initialises the 'last' clouds; later scans are registered
against them (:class:`~lego_loam_py.core.laser_odometry.LaserOdometry`), the motion is accumulated into
``transform_sum`` and the less-sharp / less-flat features re-projected to the sweep end become the next
'last' clouds, handed to mapOptimization every ``skip_frame_num + 1`` scans.

Relative time (``feature_association.relative_time_source``): by default from each point's azimuth,
measured clockwise from the sweep's start orientation (``azimuth``): it needs no per-point time field, does
not depend on how a driver encodes time, and is right for every spinning lidar whose sweep starts at the
cut. ``point_time`` uses the cloud's own time field instead (exact for any firing pattern; needs a driver
whose time field matches ``scan_period``). ``original`` reproduces the original's unwrapping bit for bit:
it switches from the start to the end rule once per cloud, but the segmented cloud is ordered by ring and
column, so from then on the first quarter of the sweep of every ring is timed as the sweep's end (1 + s). It exists for parity
checks; it degrades deskewing, see the README.

IMU (deliberate deviation, documented in the README): points are deskewed with the IMU attitude, so the
odometry then estimates only the rotation the IMU did not explain; its initial rotation guess is
therefore zero, not the gyro rotation of the previous sweep the original uses (which counts the rotation
twice). Translation keeps the original's constant-velocity guess corrected by the IMU velocity change.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lego_loam_py.core.features import FeatureExtractor, ScanFeatures
from lego_loam_py.core.frames import euler_to_matrix, lidar_to_camera, make_pose, matrix_to_euler
from lego_loam_py.core.image_projection import CloudInfo
from lego_loam_py.core.imu import ImuBuffer, imu_world_rotation
from lego_loam_py.core.laser_odometry import (LaserOdometry, OdometryStats, accumulate, sweep_angles,
                                              sweep_rotation, transform_to_end)
from lego_loam_py.core.libm import atan2f
from lego_loam_py.core.params import Params

__all__ = ['FeatureAssociation', 'FeatureAssociationResult', 'relative_time', 'relative_time_from_azimuth',
           'ScanInput']

_F32 = np.float32
TWO_PI = 2 * math.pi


@dataclass
class ScanInput:
    """What featureAssociation receives for one scan (imageProjection's three messages)."""

    stamp_ns: int                      # header stamp = sweep start [ns]
    segmented: np.ndarray              # (n, 4) float32 lidar axes, intensity = row + col / 10000
    info: CloudInfo
    outlier: np.ndarray                # (m, 4) float32 lidar axes
    point_time: np.ndarray | None = None  # (n,) seconds since the sweep start, when the cloud carries it


@dataclass
class FeatureAssociationResult:
    stamp_ns: int
    features: ScanFeatures               # camera axes; intensity ring + 0.1 * relative time
    transform_sum: np.ndarray            # (rx, ry, rz, tx, ty, tz): laser_odom in camera_init
    corner_last: np.ndarray | None       # set when published to mapOptimization (camera axes)
    surf_last: np.ndarray | None
    outlier_last: np.ndarray | None
    initialized: bool                    # this scan initialised the odometry
    imu_used: bool
    odometry: OdometryStats | None = None
    timings_ms: dict = field(default_factory=dict)

    @property
    def pose(self) -> np.ndarray:
        """4x4 pose of laser_odom in camera_init (camera axes)."""
        return make_pose(euler_to_matrix(*self.transform_sum[:3]), self.transform_sum[3:])


def relative_time_from_azimuth(points_lidar: np.ndarray, info: CloudInfo) -> np.ndarray:
    """Relative time in [0, 1) of each point: its clockwise angle from the start orientation, modulo a turn,
    over the sweep's orientation difference."""
    ori = -atan2f(points_lidar[:, 1], points_lidar[:, 0]).astype(np.float64)
    angle = np.mod(ori - float(info.start_orientation), TWO_PI)
    return (angle / float(info.orientation_diff)).astype(_F32)


def relative_time(points_lidar: np.ndarray, info: CloudInfo) -> np.ndarray:
    """Relative time in [about -0.25, 1.25] of each point from its azimuth, as the original computes it.

    The orientation ``-atan2(y, x)`` is unwrapped against the sweep's start orientation until it passes
    half a turn and against the end orientation afterwards; the switch happens once per cloud (the cloud is
    ordered by ring, so later rings use the end rule throughout and their first quarter gets 1 + s).
    """
    ori = -atan2f(points_lidar[:, 1], points_lidar[:, 0]).astype(np.float64)
    start = float(info.start_orientation)
    end = float(info.end_orientation)
    first = np.where(ori < start - math.pi / 2, ori + TWO_PI, np.where(ori > start + 3 * math.pi / 2, ori - TWO_PI, ori))
    first = first.astype(_F32)
    passed = (first - _F32(start)).astype(np.float64) > math.pi
    switch = int(np.argmax(passed)) if passed.any() else len(ori)
    second = (ori + TWO_PI).astype(_F32).astype(np.float64)
    second = np.where(second < end - 3 * math.pi / 2, second + TWO_PI,
                      np.where(second > end + math.pi / 2, second - TWO_PI, second)).astype(_F32)
    final = np.where(np.arange(len(ori)) <= switch, first, second)
    return ((final - _F32(start)) / _F32(info.orientation_diff)).astype(_F32)


class FeatureAssociation:
    """The featureAssociation algorithm; feed scans (and IMU samples) in time order."""

    def __init__(self, params: Params, fix_scan_bound: bool = False):
        self.params = params
        fa = params.feature_association
        self.extractor = FeatureExtractor(params)
        self.odometry = LaserOdometry(params, fix_scan_bound=fix_scan_bound)
        self.imu = ImuBuffer(fa.imu_que_length, fa.gravity, params.sensor.scan_period)
        self.transform_sum = np.zeros(6)
        self.initialized = False
        self.frame_count = fa.skip_frame_num
        self._previous_used_imu = False
        self._last_full_motion = np.zeros(6)   # sweep motion as a full (IMU-free) six-vector
        self.scans = 0

    def reset(self) -> None:
        """Forget everything (a bag restarted or time jumped back)."""
        self.__init__(self.params, self.odometry.fix_scan_bound)

    # ------------------------------------------------------------------------------------- per scan
    def prepare_points(self, scan: ScanInput) -> np.ndarray:
        """(n, 4) camera-axes points with intensity ``ring + 0.1 * relative time`` (before deskewing)."""
        seg = scan.segmented
        source = self.params.feature_association.relative_time_source
        if source == 'point_time' and scan.point_time is not None:
            rel = (np.asarray(scan.point_time, dtype=np.float64) / self.params.sensor.scan_period).astype(_F32)
        elif source == 'original':
            rel = relative_time(seg, scan.info)
        else:
            rel = relative_time_from_azimuth(seg, scan.info)
        out = np.empty((len(seg), 4), dtype=_F32)
        out[:, :3] = lidar_to_camera(seg[:, :3])
        # int(intensity) + 0.1 * relTime, computed in double and stored as float as the original does. The
        # factor is 0.1 whatever the scan period, so that 10 * fraction is always the relative time.
        out[:, 3] = (np.trunc(seg[:, 3]).astype(np.float64) + 0.1 * rel.astype(np.float64)).astype(_F32)
        return out

    def process(self, scan: ScanInput) -> FeatureAssociationResult:
        import time as _time

        timings = {}
        t0 = _time.perf_counter()
        points = self.prepare_points(scan)
        rel = 10.0 * (points[:, 3].astype(np.float64) - np.trunc(points[:, 3]))
        imu = self._imu_deskew(points, rel, scan.stamp_ns) if len(points) else None
        t1 = _time.perf_counter()
        features = self.extractor.extract(points, scan.info)
        t2 = _time.perf_counter()
        timings['deskew'] = (t1 - t0) * 1e3
        timings['features'] = (t2 - t1) * 1e3
        self.scans += 1
        fa = self.params.feature_association
        if not self.initialized:
            self.odometry.set_last(features.less_sharp, features.less_flat)
            if imu is not None:
                self.transform_sum[0] += imu['pitch_start']
                self.transform_sum[2] += imu['roll_start']
            self.initialized = True
            return FeatureAssociationResult(scan.stamp_ns, features, self.transform_sum.copy(), features.less_sharp,
                                            features.less_flat, None, True, imu is not None, None, timings)
        self._initial_guess(imu)
        stats = self.odometry.register(features.sharp, features.flat)
        t3 = _time.perf_counter()
        timings['odometry'] = (t3 - t2) * 1e3
        theta = self.odometry.transform_cur.copy()
        shift_end = imu['shift_end'] if imu is not None else None
        self.transform_sum = accumulate(self.transform_sum, theta, shift_end)
        if imu is not None:
            rotation = euler_to_matrix(*self.transform_sum[:3]) @ imu['delta_end']
            self.transform_sum[:3] = matrix_to_euler(rotation)
        self._remember_motion(theta, imu)
        correction = imu['delta_end'].T if imu is not None else None
        corner_last = transform_to_end(features.less_sharp, theta, correction, shift_end)
        surf_last = transform_to_end(features.less_flat, theta, correction, shift_end)
        self.odometry.set_last(corner_last, surf_last)
        self.frame_count += 1
        publish = self.frame_count >= fa.skip_frame_num + 1
        outlier_last = None
        if publish:
            self.frame_count = 0
            outlier_last = np.empty_like(scan.outlier)
            outlier_last[:, :3] = lidar_to_camera(scan.outlier[:, :3])
            outlier_last[:, 3] = scan.outlier[:, 3]
        timings['total'] = (_time.perf_counter() - t0) * 1e3
        return FeatureAssociationResult(scan.stamp_ns, features, self.transform_sum.copy(),
                                        corner_last if publish else None, surf_last if publish else None,
                                        outlier_last, False, imu is not None, stats, timings)

    # ----------------------------------------------------------------------------------------- IMU
    def add_imu(self, stamp_s: float, orientation_xyzw, angular_velocity, linear_acceleration) -> str | None:
        """Feed one IMU sample (REP-103 body axes); returns the rejection reason or None."""
        return self.imu.add(stamp_s, orientation_xyzw, angular_velocity, linear_acceleration)

    def _imu_deskew(self, points: np.ndarray, rel: np.ndarray, stamp_ns: int) -> dict | None:
        """Rotate every point into the sweep-start frame with the IMU attitude and remove the IMU's non-linear
        shift; returns the sweep's IMU quantities, or None when the IMU does not cover the sweep."""
        period = self.params.sensor.scan_period
        t_start = stamp_ns * 1e-9
        t_end = t_start + period
        if not self.imu.covers(t_start, t_end):
            return None
        point_times = t_start + rel * period
        state = self.imu.interpolate(np.concatenate(([point_times[0], t_end], point_times)))
        rotations = imu_world_rotation(state.roll, state.pitch, state.yaw)
        r_start, r_end, r_points = rotations[0], rotations[1], rotations[2:]
        v_start = state.velocity[0]
        dt = point_times - point_times[0]
        shift = (state.shift[2:] - state.shift[0] - v_start[None, :] * dt[:, None]) @ r_start   # R_S^T (.)
        relative = np.einsum('ij,njk->nik', r_start.T, r_points)
        points[:, :3] = (np.einsum('nij,nj->ni', relative, points[:, :3].astype(np.float64)) + shift).astype(_F32)
        shift_end = r_start.T @ (state.shift[1] - state.shift[0] - v_start * (t_end - point_times[0]))
        velocity_change = r_start.T @ (state.velocity[1] - v_start)
        return dict(roll_start=float(state.roll[0]), pitch_start=float(state.pitch[0]), delta_end=r_start.T @ r_end,
                    shift_end=shift_end, velocity_change=velocity_change)

    def _initial_guess(self, imu: dict | None) -> None:
        """Constant-velocity prior (``transform_cur`` kept), adapted when the IMU use changes."""
        cur = self.odometry.transform_cur
        period = self.params.sensor.scan_period
        if imu is not None:
            cur[:3] = 0.0   # deskewed points: only the rotation the IMU missed remains
            # The previous sweep's full translation, expressed for this sweep's IMU-deskewed points.
            cur[3:] = imu['delta_end'] @ self._last_full_motion[3:] + imu['shift_end'] - imu['velocity_change'] * period
        elif self._previous_used_imu:
            cur[:] = self._last_full_motion

    def _remember_motion(self, theta: np.ndarray, imu: dict | None) -> None:
        """Store the sweep motion as an IMU-free six-vector (sweep convention) for the next prior."""
        self._previous_used_imu = imu is not None
        if imu is None:
            self._last_full_motion = theta.copy()
            return
        # Sweep end in the start frame: T(θ)^-1 · [ΔR, shift]; its inverse is the full T.
        full_rotation = imu['delta_end'].T @ sweep_rotation(*theta[:3])
        full_translation = imu['delta_end'].T @ (theta[3:] - imu['shift_end'])
        self._last_full_motion = np.array([*sweep_angles(full_rotation), *full_translation])
