"""featureAssociation: deskew, feature extraction and scan-to-scan odometry for one scan at a time.

Per scan (docs/original.md §6.2): the segmented cloud (lidar axes, intensity row + col/10000) is turned into LOAM
camera axes and every point gets its relative time in the sweep; with an IMU it is deskewed to the sweep
start; features are extracted; the first scan initialises the 'last' clouds; later scans are registered
against them (:mod:`~lego_loam_py.core.odometry.laser_odometry`), the motion is accumulated into
``transform_sum`` and the less-sharp / less-flat features re-projected to the sweep end become the next
'last' clouds, handed to mapOptimization every ``skip_frame_num + 1`` scans.

Relative time (``feature_association.relative_time_source``): from each point's azimuth, clockwise from the sweep's
start orientation (default), the cloud's time field (``point_time``), or the original's unwrapping bit for bit
(``original``, for parity checks: it times the first quarter of most rings as the sweep's end). Outputs refer to the
header stamp's instant in the sweep (``sensor.stamp_position``,
:class:`~lego_loam_py.core.odometry.sweep.StampInstant`).

IMU (deliberate deviation, documented in the README): points are deskewed with the IMU attitude, so the
odometry then estimates only the rotation the IMU did not explain; its initial rotation guess is
therefore zero, not the gyro rotation of the previous sweep the original uses (which counts the rotation
twice). Translation keeps the original's constant-velocity guess corrected by the IMU velocity change.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np

from lego_loam_py.core.frames import (
    CAMERA_TO_LIDAR,
    LIDAR_TO_CAMERA_COLUMNS,
    euler_to_matrix,
    invert_pose,
    make_pose,
    matrix_to_euler,
    matrix_to_pose6,
)
from lego_loam_py.core.imu.agreement import ImuAgreement
from lego_loam_py.core.imu.buffer import ImuBuffer, ImuSweep, SweepAttitude, imu_mounting, imu_world_rotation
from lego_loam_py.core.imu.monitor import SweepImuCheck
from lego_loam_py.core.imu.sweep import deskew_with_imu, rotate_at_points, sweep_attitude
from lego_loam_py.core.indexing import copy_columns
from lego_loam_py.core.odometry.covariance import (
    OdometryCovariance,
    motion_covariance,
    sweep_motion,
    unmodelled_covariance,
)
from lego_loam_py.core.odometry.features import FeatureExtractor, ScanFeatures
from lego_loam_py.core.odometry.laser_odometry import OdometryStats, make_laser_odometry
from lego_loam_py.core.odometry.sweep import (
    StampInstant,
    accumulate,
    imu_free_motion,
    motion_to_theta,
    relative_time,
    relative_time_from_azimuth,
    sweep_rotation,
    transform_to_end,
    transform_to_start,
)
from lego_loam_py.core.params.types import Params
from lego_loam_py.core.projection.cloud_info import CloudInfo
from lego_loam_py.core.validation import (
    MAX_POSITION,
    MAX_SWEEP_TRANSLATION,
    cloud_problem,
    pose6_problem,
    vector_problem,
)

__all__ = ['FeatureAssociation', 'FeatureAssociationResult', 'ScanInput']

_F32 = np.float32


@dataclass
class ScanInput:
    """What featureAssociation receives for one scan (imageProjection's three messages)."""

    stamp_ns: int  # header stamp = sweep start [ns]
    segmented: np.ndarray  # (n, 4) float32 lidar axes, intensity = row + col / 10000
    info: CloudInfo
    outlier: np.ndarray  # (m, 4) float32 lidar axes
    point_time: np.ndarray | None = None  # (n,) seconds since the sweep start, when the cloud carries it

    @classmethod
    def from_segmentation(cls, stamp_ns: int, segmentation, point_time: bool = True) -> ScanInput:
        """The input of a scan that imageProjection segmented (its SegmentationResult), as its three messages
        carry it; ``point_time=False`` leaves the per-point times out, as a cloud without a time field."""
        return cls(
            stamp_ns,
            segmentation.segmented_cloud,
            segmentation.cloud_info,
            segmentation.outlier_cloud,
            segmentation.segmented_time if point_time else None,
        )


@dataclass
class FeatureAssociationResult:
    stamp_ns: int
    features: ScanFeatures  # camera axes; intensity ring + 0.1 * relative time
    transform_sum: np.ndarray  # (rx, ry, rz, tx, ty, tz): laser_odom in camera_init
    corner_last: np.ndarray | None  # set when published to mapOptimization (camera axes)
    surf_last: np.ndarray | None
    outlier_last: np.ndarray | None
    initialized: bool  # this scan initialised the odometry
    imu_used: bool
    odometry: OdometryStats | None = None
    timings_ms: dict = field(default_factory=dict)
    resumed: bool = False  # initialised again after a restart, at the pose reached before it
    imu_alignment: object = None  # what the IMU check decided on this scan (core.imu_monitor.AlignmentEvent)
    imu_uncovered: str | None = None  # why the IMU samples could not cover this sweep (core.imu.UNCOVERED)
    # 6x6 covariance of ``pose`` in camera_init (position [m²] in camera_init axes, rotation [rad²] about them; ROS
    # order x, y, z, rot x, rot y, rot z; core.odometry.covariance) and of the last sweep's motion (in the previous
    # sweep start's axes). Unbounded: zero at the first pose (core.frames.bounded_covariance for a message).
    pose_covariance: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    motion_covariance: np.ndarray | None = None

    @property
    def pose(self) -> np.ndarray:
        """4x4 pose of laser_odom in camera_init (camera axes)."""
        return make_pose(euler_to_matrix(*self.transform_sum[:3]), self.transform_sum[3:])


class FeatureAssociation:
    """The featureAssociation algorithm; feed scans (and IMU samples) in time order."""

    # Imported by the first scan, not with this module (a node imports them ahead with its first input): none, the
    # neighbour searches are grids and the rotations core.frames', with an IMU too.
    DEFERRED_IMPORTS = ()

    def __init__(self, params: Params, fix_scan_bound: bool = False):
        self.params = params
        fa = params.feature_association
        self.extractor = FeatureExtractor(params)
        # The sweep-start model minimises R((1+s)θ)^T (p - (1+s) t) and needs its exact derivative; the original
        # model keeps the original's rows (derivative at the full θ). The scan path is chosen with it, once.
        self.odometry = make_laser_odometry(params, fix_scan_bound)
        self._process = self._process_original if fa.odometry_model == 'original' else self._process_sweep_start
        gyro = fa.imu_attitude == 'gyro' and fa.odometry_model == 'sweep_start'
        self.imu = ImuBuffer(
            fa.imu_que_length, fa.gravity, params.sensor.scan_period, imu_mounting(params), gyro_attitude=gyro
        )
        self.imu_agreement = ImuAgreement(params.sensor.scan_period) if gyro else None
        self._period = params.sensor.scan_period
        self._imu_uncovered: str | None = None  # why the IMU did not cover this scan's sweep
        self.transform_sum = np.zeros(6)
        self.covariance = OdometryCovariance()  # of the accumulated pose (and the last sweep's motion)
        self.initialized = False
        self.frame_count = fa.skip_frame_num
        self._previous_used_imu = False
        self._last_full_motion = np.zeros(6)  # sweep motion as a full (IMU-free) six-vector
        self._world_pose = np.eye(4)  # sweep-start model: pose of the current sweep start
        self.stamp_instant = StampInstant(params)  # ... and its outputs at the header stamp's instant
        self._previous_attitude: SweepAttitude | None = None
        self._previous_start: float | None = None  # [s] the last sweep's start
        self.imu_check = SweepImuCheck(params, lambda: self.imu)  # is the IMU mounted as the parameters say?
        self._imu_event = None  # what the check decided on this scan (an AlignmentEvent), for the result
        self._first_features = None
        self._resumed = False  # restarted after a poisoned state: the first scan keeps transform_sum as it is
        self.scans = 0
        self._imu_given = False  # (see takes_mapped_poses)

    @property
    def takes_mapped_poses(self) -> bool:
        """Whether :meth:`add_mapped_pose` can change anything: only once an IMU sample was given (since the start or
        the last reset). Both its users, the IMU check and the gyro-bias agreement, take a mapped pose only beside
        the IMU's state at that scan, which only a scan the IMU covered has; a pose without one only ends the
        check's pair, as having none does. A front end in another process need not wait for the poses before."""
        return self._imu_given

    def reset(self, keep_imu: bool = False) -> None:
        """Forget everything (a bag restarted or time jumped back); ``keep_imu``: but the IMU samples and what
        its check found (they follow their own timeline)."""
        imu, check, agreement, imu_given = self.imu, self.imu_check, self.imu_agreement, self._imu_given
        self.__init__(self.params, self.odometry.fix_scan_bound)
        if keep_imu:
            self.imu, self.imu_check, self.imu_agreement, self._imu_given = imu, check, agreement, imu_given

    def health_problem(self) -> str | None:
        """Why the odometry state is poisoned (non-finite or beyond what a sensor can produce), or None.

        Checked after every scan: the accumulated pose, the sweep motion being estimated, the 'last' clouds the
        next scan registers against (coordinates, and intensities ``ring + 0.1 s`` below ``n_scan + 1``) and the
        IMU integration."""
        odometry = self.odometry
        last_bound = self.params.sensor.n_scan + 1.0
        return (
            pose6_problem('the odometry pose', self.transform_sum)
            or pose6_problem('the sweep motion', odometry.transform_cur, MAX_SWEEP_TRANSLATION)
            or pose6_problem('the previous sweep motion', self._last_full_motion, MAX_SWEEP_TRANSLATION)
            or vector_problem('the sweep-start pose', self._world_pose, MAX_POSITION, 'm')
            or (
                cloud_problem('the last corner cloud', odometry.last_corner.points, last_bound)
                if odometry.last_corner is not None
                else None
            )
            or (
                cloud_problem('the last surface cloud', odometry.last_surf.points, last_bound)
                if odometry.last_surf is not None
                else None
            )
            or self.imu.health_problem()
        )

    def restart(self) -> None:
        """Start the odometry again from the next scan, after its state was poisoned (:meth:`health_problem`).

        The pose reached so far is kept when it is sane, so /laser_odom_to_init carries on from there instead of
        jumping back to the origin; the IMU samples are kept when they are sane, else they are dropped too.
        """
        pose = self.transform_sum.copy() if pose6_problem('pose', self.transform_sum) is None else np.zeros(6)
        instant, covariance = self.stamp_instant, self.covariance
        self.reset(keep_imu=self.imu.health_problem() is None)
        self.transform_sum, self.stamp_instant = pose, instant
        if pose.any():  # carrying on from the pose reached: so does its uncertainty
            self.covariance = covariance
        self._resumed = bool(np.any(pose != 0.0))

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
        copy_columns(out, seg, LIDAR_TO_CAMERA_COLUMNS)
        # int(intensity) + 0.1 * relTime, computed in double and stored as float as the original does. The
        # factor is 0.1 whatever the scan period, so that 10 * fraction is always the relative time.
        out[:, 3] = (np.trunc(seg[:, 3]).astype(np.float64) + 0.1 * rel.astype(np.float64)).astype(_F32)
        return out

    def process(self, scan: ScanInput) -> FeatureAssociationResult:
        """Features and odometry of one scan (see the module docstring)."""
        return self._process(scan)

    def _prepare_scan(self, scan: ScanInput, imu_step):
        """What both models do first: the prepared points (:meth:`prepare_points`), ``imu_step(points, rel,
        stamp_ns)`` (the model's use of the IMU over the sweep, ``rel`` the points' relative times; None for a
        scan without points), the features, and the timings of the two [ms]."""
        t0 = time.perf_counter()
        points = self.prepare_points(scan)
        rel = 10.0 * (points[:, 3].astype(np.float64) - np.trunc(points[:, 3]))
        imu = imu_step(points, rel, scan.stamp_ns) if len(points) else None
        t1 = time.perf_counter()
        features = self.extractor.extract(points, scan.info)
        self.scans += 1
        return points, imu, features, {'deskew': (t1 - t0) * 1e3, 'features': (time.perf_counter() - t1) * 1e3}

    def _motion_covariance(self, theta, stats, shift, turn, motion: np.ndarray) -> np.ndarray:
        """The sweep's motion covariance (start-frame axes): the registration's information (``stats``) and what it
        cannot see (the deskewing's errors, core.odometry.covariance); ``turn`` is the gyro's share of the turn
        (None: no gyro)."""
        fa = self.params.feature_association
        seen = motion_covariance(theta, stats.information, shift, turn, fa.covariance_scale, stats.prior_information)
        unseen = unmodelled_covariance(
            motion,
            self.covariance.last_motion,
            turn is not None,
            self.params.sensor.scan_period,
            fa.covariance_turn,
            fa.covariance_change,
            fa.covariance_stamp_jitter,
        )
        return seen + unseen

    def _finish(
        self,
        scan: ScanInput,
        features,
        corner_last,
        surf_last,
        outlier_last,
        initialized,
        imu_used,
        stats,
        timings,
        pose6: np.ndarray | None = None,
    ) -> FeatureAssociationResult:
        """Publication decision (every skip_frame_num + 1 scans after the first) and the result; the 'last' clouds
        may be functions making them, called only for a scan that is published (only mapOptimization uses them);
        ``pose6``: the published pose when it is not ``transform_sum`` (:class:`StampInstant`)."""
        fa = self.params.feature_association
        event, self._imu_event = self._imu_event, None
        uncovered, self._imu_uncovered = self._imu_uncovered, None
        covariance = {'pose_covariance': self.covariance.pose.copy()}
        if initialized:
            return FeatureAssociationResult(
                scan.stamp_ns,
                features,
                self.transform_sum.copy(),
                corner_last,
                surf_last,
                None,
                True,
                imu_used,
                None,
                timings,
                resumed=self._resumed,
                imu_alignment=event,
                imu_uncovered=uncovered,
                **covariance,
            )
        self.frame_count += 1
        publish = self.frame_count >= fa.skip_frame_num + 1
        if publish:
            self.frame_count = 0
        if publish:
            corner_last, surf_last, outlier_last = (
                c() if callable(c) else c for c in (corner_last, surf_last, outlier_last)
            )
        return FeatureAssociationResult(
            scan.stamp_ns,
            features,
            self.transform_sum.copy() if pose6 is None else pose6,
            corner_last if publish else None,
            surf_last if publish else None,
            outlier_last if publish else None,
            False,
            imu_used,
            stats,
            timings,
            imu_alignment=event,
            imu_uncovered=uncovered,
            motion_covariance=self.covariance.motion.copy(),
            **covariance,
        )

    def _process_sweep_start(self, scan: ScanInput) -> FeatureAssociationResult:
        """The default model: poses and 'last' clouds at the sweep start (header stamp).

        The previous sweep's less-sharp / less-flat features, deskewed to its start, are the reference. The
        current sweep's sharp / flat points are mapped into that frame with ``(1 + s) θ`` (constant motion
        over both sweeps; ``θ`` = motion over one sweep in the original's six-vector convention), so the whole
        displacement between the sweep starts is observed, not only the distortion within a sweep. With an
        IMU, points are first rotated into the reference orientation with its attitude and ``θ`` keeps only
        the rotation the IMU missed.
        """
        t0 = time.perf_counter()
        points, attitude, features, timings = self._prepare_scan(
            scan, lambda prepared, rel, stamp_ns: self._covered(sweep_attitude(self.imu, rel, *self._sweep(stamp_ns)))
        )
        t2 = time.perf_counter()
        odometry, check = self.odometry, self.imu_check
        self._imu_event = check.scan(
            scan.stamp_ns, lambda: self._ground(scan, points), None if attitude is None else attitude.r_start
        )
        if attitude is not None and self.imu_agreement is not None:  # (its pose time is its stamp)
            self.imu_agreement.keep(
                scan.stamp_ns, scan.stamp_ns * 1e-9, imu_world_rotation(*self.imu.attitude([scan.stamp_ns * 1e-9]))[0]
            )
        attitude = attitude if check.trusted else None  # an IMU that disagrees with the lidar is not used
        # On probation a fast-turning sweep is registered without the IMU and compared with it (core.imu_monitor).
        previous = self._previous_attitude
        if previous is None and attitude is not None and self._previous_start is not None:
            # The last sweep went without the IMU (a gap, late samples): its start may be covered by now.
            previous = self._covered(sweep_attitude(self.imu, attitude.rel[:0], self._previous_start, 0.0))
        imu_attitude, attitude = attitude, None if attitude and check.on_probation(attitude, previous) else attitude
        if not self.initialized:
            if imu_attitude is not None and not self._resumed:
                self.transform_sum[0] += imu_attitude.pitch_start
                self.transform_sum[2] += imu_attitude.roll_start
            self._world_pose = make_pose(euler_to_matrix(*self.transform_sum[:3]), self.transform_sum[3:])
            self.stamp_instant.begin(self._world_pose, scan.stamp_ns)
            motion = np.eye(4)
            corner_last = self._deskew_to_start(
                features.less_sharp, features.less_sharp_index, motion, attitude, points
            )
            surf_last = self._deskew_to_start(features.less_flat, None, motion, attitude, points)
            odometry.set_last(corner_last, surf_last)
            self._previous_attitude, self._previous_start = imu_attitude, self._sweep(scan.stamp_ns)[0]
            self._first_features = (features, points, attitude)  # re-deskewed once the motion is known
            self.initialized = True
            return self._finish(scan, features, corner_last, surf_last, None, True, attitude is not None, None, timings)
        use_imu = attitude is not None and previous is not None
        to_reference = previous.r_start.T if use_imu else None
        sharp = self._registration_input(features.sharp, features.sharp_index, to_reference, attitude)
        flat = self._registration_input(features.flat, features.flat_index, to_reference, attitude)
        # Walls are needed only where a stage is short of matches (corridors): prepared on first use.
        wall = functools.cache(
            lambda: self._registration_input(features.wall, features.wall_index, to_reference, attitude)
        )
        if use_imu:
            odometry.transform_cur[:3] = 0.0  # the IMU explains the rotation; only what it missed is left
        largest = self.params.feature_association.imu_rotation_prior
        odometry.rotation_prior = (
            (largest if self.imu_agreement is None else self.imu_agreement.prior_weight(largest)) if use_imu else 0.0
        )
        stats = odometry.register(sharp, flat, wall)
        if self._first_features is not None:
            # The first reference was deskewed without knowing the motion (the sensor may already be moving):
            # deskew it with the motion just found and register again, twice (once the motion is known).
            first, first_points, first_attitude = self._first_features
            self._first_features = None
            for _ in range(2):
                guess = odometry.transform_cur.copy()
                first_motion = invert_pose(make_pose(sweep_rotation(*guess[:3]), guess[3:]))
                if use_imu:
                    first_motion = first_motion @ make_pose(previous.r_start.T @ attitude.r_start)
                odometry.set_last(
                    self._deskew_to_start(
                        first.less_sharp, first.less_sharp_index, first_motion, first_attitude, first_points
                    ),
                    self._deskew_to_start(first.less_flat, None, first_motion, first_attitude, first_points),
                )
                stats = odometry.register(sharp, flat, wall)
        t3 = time.perf_counter()
        timings['odometry'] = (t3 - t2) * 1e3
        theta = odometry.transform_cur
        motion = invert_pose(make_pose(sweep_rotation(*theta[:3]), theta[3:]))
        if use_imu:
            motion = motion @ make_pose(previous.r_start.T @ attitude.r_start)
        elif imu_attitude is not None and previous is not None:  # on probation
            self._imu_event = check.compare(previous, imu_attitude, motion[:3, :3]) or self._imu_event
        imu_turn = previous.r_start.T @ attitude.r_start if use_imu else None
        covariance = self._motion_covariance(theta, stats, None, imu_turn, motion)
        self.covariance.add(self._world_pose, motion, covariance)
        self._world_pose = self._world_pose @ motion
        self.transform_sum = matrix_to_pose6(self._world_pose)
        corner_last = self._deskew_to_start(features.less_sharp, features.less_sharp_index, motion, attitude, points)
        surf_last = self._deskew_to_start(features.less_flat, None, motion, attitude, points)
        odometry.set_last(corner_last, surf_last)
        self._previous_attitude, self._previous_start = imu_attitude, self._sweep(scan.stamp_ns)[0]
        instant = self.stamp_instant
        share = instant.share(scan.stamp_ns) if instant.active else 1.0
        at_stamp = (lambda cloud: instant.cloud(cloud, motion, share)) if instant.active else (lambda cloud: cloud)
        result = self._finish(
            scan,
            features,
            lambda: at_stamp(corner_last),
            lambda: at_stamp(surf_last),
            lambda: at_stamp(self._outlier_at_start(scan, motion, attitude)),
            False,
            use_imu,
            stats,
            timings,
            matrix_to_pose6(instant.pose(self._world_pose, motion, share)) if instant.active else None,
        )
        result.timings_ms['total'] = (time.perf_counter() - t0) * 1e3
        return result

    @staticmethod
    def _ground(scan: ScanInput, points: np.ndarray) -> np.ndarray:
        """The scan's ground points (camera axes), for the IMU check's look at gravity."""
        return points[np.asarray(scan.info.segmented_cloud_ground_flag[: len(points)], dtype=bool)]

    def _registration_input(
        self, cloud: np.ndarray, index: np.ndarray, to_reference: np.ndarray | None, attitude: SweepAttitude | None
    ) -> np.ndarray:
        """Current-sweep points for the registration: rotated into the reference orientation with the IMU
        (when used) and timed ``1 + s`` (the reference is the previous sweep's start)."""
        out = cloud.copy()
        if to_reference is not None:
            copy_columns(out, rotate_at_points(self.imu, to_reference, attitude, index, cloud, self._period))
        ring = np.trunc(cloud[:, 3]).astype(np.float64)
        s = 10.0 * (cloud[:, 3].astype(np.float64) - ring)
        out[:, 3] = (ring + 0.1 * (1.0 + s)).astype(_F32)
        return out

    def _deskew_to_start(
        self,
        cloud: np.ndarray,
        index: np.ndarray | None,
        motion: np.ndarray,
        attitude: SweepAttitude | None,
        points: np.ndarray,
    ) -> np.ndarray:
        """Features of this sweep in its start frame, assuming the sweep moved by ``motion`` (4x4, pose of the
        next sweep start): the IMU rotation (when there is one) and ``s`` times the translation, else the
        original's interpolation of the six-vector. The intensity becomes the ring."""
        ring = np.trunc(cloud[:, 3]).astype(np.float64)
        out = np.empty_like(cloud)
        out[:, 3] = ring.astype(_F32)
        if attitude is None:
            copy_columns(out, transform_to_start(cloud, motion_to_theta(motion)))
            return out
        s = 10.0 * (cloud[:, 3].astype(np.float64) - ring)  # (the IMU's deskewing only)
        if index is not None:
            rotated = rotate_at_points(self.imu, attitude.r_start.T, attitude, index, cloud, self._period)
        else:  # voxel centroids (less-flat): attitude at each point's own time
            times = attitude.t_start + s * self.params.sensor.scan_period
            rotated = self.imu.rotate_at(times, attitude.r_start.T, cloud)
        copy_columns(out, rotated + s[:, None] * motion[:3, 3][None, :])
        return out

    def _outlier_at_start(self, scan: ScanInput, motion: np.ndarray, attitude: SweepAttitude | None) -> np.ndarray:
        """The outlier cloud in camera axes, deskewed to the sweep start like the features."""
        outlier = np.empty_like(scan.outlier)
        copy_columns(outlier, scan.outlier, LIDAR_TO_CAMERA_COLUMNS)
        if len(outlier) == 0:
            outlier[:, 3] = scan.outlier[:, 3]
            return outlier
        rel = relative_time_from_azimuth(scan.outlier, scan.info).astype(np.float64)
        timed = outlier.copy()
        timed[:, 3] = (np.trunc(scan.outlier[:, 3]) + 0.1 * rel).astype(_F32)
        deskewed = self._deskew_to_start(timed, None, motion, attitude, timed)
        deskewed[:, 3] = scan.outlier[:, 3]
        return deskewed

    def _sweep(self, stamp_ns: int) -> tuple[float, float]:
        """(start [s], period [s]) of the sweep stamped ``stamp_ns``."""
        return self.stamp_instant.sweep_start(stamp_ns), self._period

    def _covered(self, imu):
        """The IMU's part of a sweep (core.sweep_imu), or None with the reason noted when it did not cover it (none
        for a lidar without IMU: no sample has ever come)."""
        if isinstance(imu, str):
            self._imu_uncovered, imu = (imu if imu != 'no_samples' or self.imu.accepted else None), None
        return imu

    def _process_original(self, scan: ScanInput) -> FeatureAssociationResult:
        """The original's model: registration against the previous features moved to that sweep's end."""
        t0 = time.perf_counter()
        check = self.imu_check
        points, imu, features, timings = self._prepare_scan(
            scan,
            lambda prepared, rel, stamp_ns: (
                self._covered(deskew_with_imu(self.imu, prepared, rel, *self._sweep(stamp_ns)))
                if check.trusted
                else None
            ),
        )
        self._imu_event = check.scan(scan.stamp_ns, lambda: self._ground(scan, points))
        t2 = time.perf_counter()
        if not self.initialized:
            self.odometry.set_last(features.less_sharp, features.less_flat)
            if imu is not None and not self._resumed and check.trusted:
                self.transform_sum[0] += imu.pitch_start
                self.transform_sum[2] += imu.roll_start
            self.initialized = True
            return self._finish(
                scan, features, features.less_sharp, features.less_flat, None, True, imu is not None, None, timings
            )
        self._initial_guess(imu)
        stats = self.odometry.register(features.sharp, features.flat)
        t3 = time.perf_counter()
        timings['odometry'] = (t3 - t2) * 1e3
        theta = self.odometry.transform_cur.copy()
        shift_end = imu.shift_end if imu is not None else None
        turn = imu.delta_end if imu is not None else None
        motion = sweep_motion(theta, shift_end, turn)
        self.covariance.add(
            make_pose(euler_to_matrix(*self.transform_sum[:3]), self.transform_sum[3:]),
            motion,
            self._motion_covariance(theta, stats, shift_end, turn, motion),
        )
        self.transform_sum = accumulate(self.transform_sum, theta, shift_end)
        if imu is not None:
            rotation = euler_to_matrix(*self.transform_sum[:3]) @ imu.delta_end
            self.transform_sum[:3] = matrix_to_euler(rotation)
        self._remember_motion(theta, imu)
        correction = imu.delta_end.T if imu is not None else None
        corner_last = transform_to_end(features.less_sharp, theta, correction, shift_end)
        surf_last = transform_to_end(features.less_flat, theta, correction, shift_end)
        self.odometry.set_last(corner_last, surf_last)
        outlier_last = np.empty_like(scan.outlier)  # the original does not deskew the outliers (quirk 8.9)
        copy_columns(outlier_last, scan.outlier, LIDAR_TO_CAMERA_COLUMNS)
        outlier_last[:, 3] = scan.outlier[:, 3]
        timings['total'] = (time.perf_counter() - t0) * 1e3
        return self._finish(
            scan, features, corner_last, surf_last, outlier_last, False, imu is not None, stats, timings
        )

    # ----------------------------------------------------------------------------------------- IMU
    def add_mapped_pose(self, stamp_ns: int, pose: np.ndarray):
        """mapOptimization's pose (4x4, camera_init) of the scan stamped ``stamp_ns``, for the IMU check; returns
        what the check decided (a :class:`~lego_loam_py.core.imu.monitor.AlignmentEvent`) or None."""
        if self.imu_agreement is not None:  # the gyro's bias, and how far to trust it (core.imu_agreement)
            self.imu_agreement.mapped(stamp_ns, np.asarray(pose, dtype=float)[:3, :3])
            self.imu.gyro.bias = CAMERA_TO_LIDAR @ self.imu_agreement.bias
        return self.imu_check.mapped_pose(stamp_ns, np.asarray(pose, dtype=float)[:3, :3])

    def add_imu(self, stamp_s: float, orientation_xyzw, angular_velocity, linear_acceleration) -> str | None:
        """Feed one IMU sample (REP-103 body axes); returns the rejection reason or None."""
        self._imu_given = True
        return self.imu.add(stamp_s, orientation_xyzw, angular_velocity, linear_acceleration)

    def _initial_guess(self, imu: ImuSweep | None) -> None:
        """Constant-velocity prior (``transform_cur`` kept), adapted when the IMU use changes."""
        cur = self.odometry.transform_cur
        period = self.params.sensor.scan_period
        if imu is not None:
            cur[:3] = 0.0  # deskewed points: only the rotation the IMU missed remains
            # The previous sweep's full translation, expressed for this sweep's IMU-deskewed points.
            cur[3:] = imu.delta_end @ self._last_full_motion[3:] + imu.shift_end - imu.velocity_change * period
        elif self._previous_used_imu:
            cur[:] = self._last_full_motion

    def _remember_motion(self, theta: np.ndarray, imu: ImuSweep | None) -> None:
        """Store the sweep motion as an IMU-free six-vector (sweep convention) for the next prior."""
        self._previous_used_imu = imu is not None
        self._last_full_motion = theta.copy() if imu is None else imu_free_motion(theta, imu.delta_end, imu.shift_end)
