"""``lego_loam_py calibrate BAG``: the IMU-to-lidar rotation and the lidar-IMU time offset from a recording.

Hand-eye calibration of the rotation (:mod:`lego_loam_py.core.imu.alignment`): the lidar's turn between
sweeps comes from the pipeline run on the lidar alone (``lego_loam_py run --no-imu``: scan-to-scan odometry
corrected by the scan-to-map registration), the IMU's from its gyro integrated over the same intervals on its
own clock. The rotation that maps the gyro's turns onto the lidar's (over 1, 2 and 4 sweeps), and the clock
offset that lines them up (over 1 and 2 s), are the calibration. A second pass runs the pipeline again with
the sweeps deskewed by the IMU as first found, every rotation still the lidar's own, and estimates again: the
lidar-only odometry's poses lag the sensor where it shakes (bumps: 37 ms per sweep on the simulated forest
trail), which the first offset partly inherits. The orientation field, when the IMU has one, is checked
against the gyro the same way (``imu.orientation_rpy``).

Uncertainty: the 1-sigma of each value from a block jackknife over ten stretches of the recording (each left
out in turn), which holds whatever the noise is like; the least-squares figure, which assumes independent
intervals, is given beside it. The command refuses, with the reason, when the recording cannot tell: too
short, no gyro, a lidar odometry that no rotation reconciles with the gyro, or motion that does not turn about
all three axes (a straight drive) or never changes its rate of turn (the clock offset).

The lever arm (``imu.translation``) is not estimated: the rotation and the clock do not depend on it, and an
accelerometer-based estimate needs far stronger motion than a vehicle drives. Measure it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lego_loam_py.core.frames import matrix_to_rpy
from lego_loam_py.core.imu.alignment import GyroTrack, OrientationTrack, fit_alignment
from lego_loam_py.errors import LegoLoamError

__all__ = [
    'Calibration',
    'CalibrationRefused',
    'calibrate_bag',
    'calibrate',
    'refine_calibration',
    'read_imu',
    'add_arguments',
    'main',
]

MIN_DURATION = 10.0  # [s] of lidar odometry with IMU data
MAX_ROTATION_SIGMA = 1.0  # [deg] about any axis, 1 sigma: beyond it the motion did not excite that axis
MAX_OFFSET_SIGMA = 0.004  # [s], 1 sigma
MAX_RESIDUAL = 2.0  # [deg per sweep] left after the fit: beyond it lidar and gyro do not agree at all
MIN_TURN_ACROSS = 5.0  # [deg/s] RMS turn across an axis that should show the rotation about it
ROTATION_SPANS = (1, 2, 4)  # interval lengths [sweeps] the rotation is fitted over ...
OFFSET_SPANS = (10, 20)  # ... and the clock offset
BLOCKS = 10  # stretches of the jackknife
OFFSETS = np.round(np.arange(-0.2, 0.2 + 1e-9, 0.002), 6)  # clock offsets searched [s]


class CalibrationRefused(LegoLoamError):
    """The recording cannot tell the rotation or the offset (the message says why)."""

    exit_code = 1


@dataclass
class Calibration:
    """What :func:`calibrate` found. Rotations are ``R_lidar_imu`` (IMU axes in lidar axes, as
    ``imu.rotation_rpy``); sigmas are 1-sigma, from the block jackknife."""

    rotation: np.ndarray  # (3, 3)
    time_offset: float  # [s], as imu.time_offset
    rotation_sigma_deg: np.ndarray  # (3,) about the lidar's x, y, z axes
    time_offset_sigma: float  # [s]
    formal_rotation_sigma_deg: np.ndarray  # (3,) the least-squares figures (independent intervals assumed)
    formal_time_offset_sigma: float  # [s]
    intervals: int
    duration: float  # [s] of data used
    residual_deg: float  # per interval, after the fit
    rates_rms_deg_s: np.ndarray  # (3,) the lidar's turn rate, RMS about its x, y, z axes
    orientation_rotation: np.ndarray | None = None  # R_imu_orientation, when the IMU reports an orientation
    orientation_sigma_deg: np.ndarray | None = None
    refused: str | None = None  # why the values cannot be trusted (they are still given)
    notes: list[str] = field(default_factory=list)

    @property
    def rotation_rpy(self) -> np.ndarray:
        return matrix_to_rpy(self.rotation)

    def to_dict(self) -> dict:
        out = dict(
            rotation_rpy_deg=self.rotation_rpy.tolist(),
            rotation_matrix=self.rotation.tolist(),
            rotation_sigma_deg=self.rotation_sigma_deg.tolist(),
            time_offset_s=self.time_offset,
            time_offset_sigma_s=self.time_offset_sigma,
            formal_rotation_sigma_deg=self.formal_rotation_sigma_deg.tolist(),
            formal_time_offset_sigma_s=self.formal_time_offset_sigma,
            intervals=self.intervals,
            duration_s=self.duration,
            residual_deg=self.residual_deg,
            rates_rms_deg_s=self.rates_rms_deg_s.tolist(),
            refused=self.refused,
            notes=self.notes,
        )
        if self.orientation_rotation is not None:
            out['orientation_rpy_deg'] = matrix_to_rpy(self.orientation_rotation).tolist()
            out['orientation_sigma_deg'] = self.orientation_sigma_deg.tolist()
        return out

    def parameter_block(self) -> str:
        """The ``imu`` section of a ROS 2 parameter file, ready to paste (with the figures as comments)."""
        rpy = ', '.join(f'{a:.2f}' for a in np.round(self.rotation_rpy, 2) + 0.0)
        sigma = ', '.join(f'{a:.2f}' for a in self.rotation_sigma_deg)
        lines = [
            '/**:',
            '  ros__parameters:',
            '    imu:',
            f'      rotation_rpy: [{rpy}]   # deg; 1 sigma about the lidar x, y, z axes: {sigma} deg',
            f'      time_offset: {self.time_offset:.4f}   # s; 1 sigma {1e3 * self.time_offset_sigma:.1f} ms',
        ]
        if self.orientation_rotation is not None:
            angles = matrix_to_rpy(self.orientation_rotation)
            if np.degrees(np.linalg.norm(Rotation.from_matrix(self.orientation_rotation).as_rotvec())) > 1.0:
                values = ', '.join(f'{a:.2f}' for a in np.round(angles, 2) + 0.0)
                lines.append(
                    f'      orientation_rpy: [{values}]   # deg: the orientation field reports another frame '
                    'than the gyro'
                )
        lines.append('      # translation: [x, y, z]   # m: the lever arm is not estimated, measure it')
        return '\n'.join(lines)


def read_imu(bag: str | Path, topic: str) -> dict:
    """The IMU messages of ``topic``: stamps [s] (header), angular velocity [rad/s], orientation (x, y, z, w; rows
    of NaN when the message says it has none: covariance[0] = -1, or a zero quaternion)."""
    from lego_loam_py.bag.io import BagReader

    stamps, rates, orientations = [], [], []
    with BagReader(bag) as reader:
        if topic not in reader.topics():
            raise CalibrationRefused(
                f'{bag}: no IMU topic {topic} (topics: {", ".join(sorted(reader.topics()))}); name it with --imu-topic'
            )
        for message in reader.messages(topics=[topic]):
            msg = reader.deserialize(message)
            stamps.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
            w, o = msg.angular_velocity, msg.orientation
            rates.append((w.x, w.y, w.z))
            known = float(msg.orientation_covariance[0]) != -1.0 and (o.x, o.y, o.z, o.w) != (0.0, 0.0, 0.0, 0.0)
            orientations.append((o.x, o.y, o.z, o.w) if known else (math.nan,) * 4)
    order = np.argsort(stamps, kind='stable')
    return dict(
        stamps=np.asarray(stamps, dtype=np.int64)[order] * 1e-9,
        rates=np.asarray(rates, float)[order],
        orientations=np.asarray(orientations, float)[order],
    )


def calibrate(stamps: np.ndarray, lidar_rotations: np.ndarray, imu: dict) -> Calibration:
    """The calibration from lidar poses (``stamps`` [s], (n, 3, 3) rotations of the lidar in its odometry frame,
    REP-103 axes) and the IMU's data (:func:`read_imu`). Raises :class:`CalibrationRefused` when there is nothing
    to estimate from; returns a result with ``refused`` set when the estimate is not good enough.

    The rotation comes from turns over 1, 2 and 4 sweeps (:data:`ROTATION_SPANS`), the clock offset from turns
    over 1 and 2 s (:data:`OFFSET_SPANS`): a lidar odometry's pose lags the sensor where the motion shakes faster
    than its deskewing follows (bumps), up to 40 ms per sweep on the simulated forest trail, much less over
    seconds, where the turns that show the offset are the slow ones."""
    stamps = np.asarray(stamps, dtype=float)
    gyro = imu['rates']
    if len(gyro) < 10 or not np.isfinite(gyro).all():
        raise CalibrationRefused('the IMU has no usable angular velocity (fewer than 10 finite samples)')
    track = GyroTrack(imu['stamps'], gyro)
    margin = float(np.abs(OFFSETS).max()) + 0.01
    covered = (stamps - margin >= track.times[0]) & (stamps + margin <= track.times[-1])
    stamps, lidar_rotations = stamps[covered], np.asarray(lidar_rotations)[covered]
    duration = float(stamps[-1] - stamps[0]) if len(stamps) > 1 else 0.0
    if duration < MIN_DURATION:
        raise CalibrationRefused(
            f'too short: {duration:.1f} s of lidar odometry within the IMU data '
            f'({len(stamps)} sweeps); the calibration needs {MIN_DURATION:g} s or more of motion'
        )
    poses = Rotation.from_matrix(lidar_rotations)
    rotation, rotation_covariance, rotation_fit, pairs = _jackknifed(stamps, poses, track, ROTATION_SPANS, duration)
    _, offset_covariance, offset_fit, _ = _jackknifed(stamps, poses, track, OFFSET_SPANS, duration)
    offset = offset_fit.offset
    single = pairs[: len(stamps) - 1] / np.diff(stamps)[:, None]  # the lidar's turn rates (one sweep)
    result = Calibration(
        rotation=rotation,
        time_offset=offset,
        time_offset_sigma=math.sqrt(offset_covariance[3, 3]),
        rotation_sigma_deg=np.degrees(np.sqrt(np.diag(rotation_covariance)[:3])),
        formal_rotation_sigma_deg=np.degrees(np.sqrt(np.maximum(np.diag(rotation_fit.rotation_covariance), 0.0))),
        formal_time_offset_sigma=offset_fit.offset_sigma,
        intervals=int(len(pairs)),
        duration=duration,
        residual_deg=rotation_fit.rms_after_deg,
        rates_rms_deg_s=np.degrees(np.sqrt(np.square(single).mean(axis=0))),
    )
    result.refused = _refusal(result, offset_fit, rotation_covariance, np.degrees(single))
    _orientation(result, imu, stamps)
    return result


def _jackknifed(stamps: np.ndarray, poses: Rotation, track: GyroTrack, spans, duration: float):
    """(rotation, covariance of (rotation vector, offset) from the block jackknife, the fit of all of it, the
    lidar's turns) over the intervals of ``spans`` sweeps."""
    start = np.concatenate([np.arange(len(stamps) - span) for span in spans if span < len(stamps)])
    end = np.concatenate([np.arange(len(stamps) - span) + span for span in spans if span < len(stamps)])
    lidar = (poses[start].inv() * poses[end]).as_rotvec()

    def fit(keep: np.ndarray, offsets: np.ndarray = OFFSETS):
        a, b = stamps[start[keep]], stamps[end[keep]]
        return fit_alignment(lidar[keep], lambda trial: track.increments(a, b, trial), offsets)

    best = fit(np.ones(len(start), dtype=bool))
    # Leave out each tenth of the recording in turn.
    block = np.minimum((stamps[start] - stamps[0]) / duration * BLOCKS, BLOCKS - 1).astype(int)
    estimates = []
    for k in range(BLOCKS):
        partial = fit(block != k, np.linspace(best.offset - 0.02, best.offset + 0.02, 21))
        estimates.append(
            np.concatenate([Rotation.from_matrix(partial.rotation @ best.rotation.T).as_rotvec(), [partial.offset]])
        )
    spread = np.array(estimates) - np.mean(estimates, axis=0)
    return best.rotation, (BLOCKS - 1) / BLOCKS * spread.T @ spread, best, lidar


def _refusal(result: Calibration, fit, covariance: np.ndarray, rates: np.ndarray) -> str | None:
    """Why the estimate cannot be trusted, or None (``rates``: the lidar's turn rates [deg/s], (n, 3))."""
    if result.residual_deg > MAX_RESIDUAL:
        return (
            f'the lidar odometry and the gyro disagree by {result.residual_deg:.2f} deg per interval under the '
            'best rotation: the lidar odometry failed, or the gyro is not rigidly fixed to the lidar'
        )
    eigenvalues, axes = np.linalg.eigh(covariance[:3, :3])
    weakest = float(np.degrees(math.sqrt(max(eigenvalues[-1], 0.0))))
    if weakest > MAX_ROTATION_SIGMA:
        axis = axes[:, -1]
        name = (
            'xyz'[int(np.argmax(np.abs(axis)))]
            if np.abs(axis).max() > 0.9
            else '(' + ', '.join(f'{v:.2f}' for v in axis) + ')'
        )
        rms = ', '.join(f'{r:.1f}' for r in result.rates_rms_deg_s)
        # The rotation about an axis shows in the turns about the two others.
        across = float(np.sqrt(np.square(np.cross(rates, axis)).sum(axis=1).mean()))
        if across >= MIN_TURN_ACROSS:
            return (
                f"the rotation about the lidar's {name} axis is known to {weakest:.1f} deg only (1 sigma, "
                f'{MAX_ROTATION_SIGMA:g} needed) although the lidar turned about the other axes at {across:.1f} '
                f'deg/s RMS: the lidar odometry is too noisy here ({result.residual_deg:.2f} deg per interval left '
                'against the gyro); a recording with more structure around the sensor will do better'
            )
        return (
            f"the motion does not show the rotation about the lidar's {name} axis (1 sigma {weakest:.1f} deg, "
            f'{MAX_ROTATION_SIGMA:g} needed): the lidar turned at {rms} deg/s RMS about its x, y, z axes. The '
            'rotation about an axis shows only in turns about the other two: record a drive that turns left and '
            'right and goes over bumps or slopes (or tilt and turn the sensor by hand)'
        )
    if result.time_offset_sigma > MAX_OFFSET_SIGMA or fit.offset_at_edge:
        return (
            f'the motion does not show the time offset (1 sigma {1e3 * result.time_offset_sigma:.1f} ms, '
            f'{1e3 * MAX_OFFSET_SIGMA:g} needed'
            + (', best at the end of the +-0.2 s searched' if fit.offset_at_edge else '')
            + '): the offset shows only when the rate of turn changes; record turns that start and stop'
        )
    return None


def _orientation(result: Calibration, imu: dict, stamps: np.ndarray) -> None:
    """The orientation field's frame in the IMU frame (``R_imu_orientation``): its turns against the gyro's over
    the sweeps, on the IMU's own clock."""
    start, end = np.arange(len(stamps) - 1), np.arange(1, len(stamps))
    known = np.isfinite(imu['orientations']).all(axis=1)
    if known.sum() < 10:
        result.notes.append('the IMU reports no orientation (the pipeline needs one: a 9-axis unit)')
        return
    orientation = OrientationTrack(imu['stamps'][known], imu['orientations'][known])
    gyro = GyroTrack(imu['stamps'], imu['rates'])
    inside = (stamps[start] >= orientation.times[0]) & (stamps[end] <= orientation.times[-1])
    if inside.sum() < 10:
        return
    a, b = stamps[start[inside]] + result.time_offset, stamps[end[inside]] + result.time_offset
    fit = fit_alignment(
        gyro.increments(a, b, [0.0])[0], lambda trial: orientation.increments(a, b, trial), np.array([0.0])
    )
    result.orientation_rotation = fit.rotation.T  # the gyro's turn = R_imu_orientation @ the orientation's turn
    result.orientation_sigma_deg = np.degrees(np.sqrt(np.maximum(np.diag(fit.rotation_covariance), 0.0)))


def calibrate_bag(
    bag: str | Path, params, trajectory: str | Path | None = None, progress: bool = False, refine: bool = True
) -> Calibration:
    """:func:`calibrate` on a bag: the lidar-only poses from the offline pipeline on it (or a TUM ``trajectory``
    of them, REP-103 axes, stamped with the scans), the IMU from ``params.sensor.imu_topic``. With ``refine`` (and
    no ``trajectory``), a second pass deskews the sweeps with the IMU as first found and estimates again."""
    imu_topic = params.sensor.imu_topic or '/imu/data'
    imu = read_imu(bag, imu_topic)
    imu_span = (
        f'{imu["stamps"][-1] - imu["stamps"][0]:.2f} s of IMU ({len(imu["stamps"])} samples)'
        if len(imu['stamps'])
        else 'no IMU sample'
    )
    if trajectory is not None:
        table = np.loadtxt(trajectory, ndmin=2)
        if table.shape[1] != 8:
            raise CalibrationRefused(f'{trajectory}: not a TUM trajectory (8 columns: t x y z qx qy qz qw)')
        stamps, rotations = table[:, 0], Rotation.from_quat(table[:, 4:8]).as_matrix()
        scans = len(stamps)
    else:
        from lego_loam_py.offline import run_bag

        result = run_bag(bag, params, imu_topic='', progress=progress)  # the lidar alone
        stamps_ns, poses = result.trajectory(axes='map')
        stamps, rotations = stamps_ns * 1e-9, poses[:, :3, :3]
        scans = result.counts.get('scans_in', 0)
    if len(stamps) < 3 or stamps[-1] - stamps[0] < MIN_DURATION:
        span = f'{stamps[-1] - stamps[0]:.2f} s' if len(stamps) > 1 else 'no motion'
        sweeps = f'{scans} scan' if scans == 1 else f'{scans} scans'
        raise CalibrationRefused(
            f'too short: {sweeps} ({len(stamps)} lidar odometry poses, {span}) and '
            f'{imu_span}; the calibration needs {MIN_DURATION:g} s or more of motion'
        )
    first = calibrate(stamps, rotations, imu)
    if trajectory is not None or not refine:
        return first
    return refine_calibration(bag, params, first, imu, progress)


def refine_calibration(bag: str | Path, params, first: Calibration, imu: dict, progress: bool = False) -> Calibration:
    """The second pass: the lidar odometry again, its sweeps deskewed with the IMU as ``first`` found it (no more
    lag where the motion shakes), every rotation still the lidar's own (no IMU prior) and the IMU check off; then
    :func:`calibrate` on its poses. Returns ``first`` (with a note) when that IMU did not cover the sweeps."""
    from lego_loam_py.offline import run_bag

    imu_topic = params.sensor.imu_topic or '/imu/data'
    deskewed = params.replace(
        imu__rotation_rpy=first.rotation_rpy.tolist(),
        imu__time_offset=first.time_offset,
        imu__translation=[0.0, 0.0, 0.0],
        imu__orientation_rpy=[0.0, 0.0, 0.0],
        imu__alignment_check=False,
        feature_association__imu_rotation_prior=0.0,
    )
    result = run_bag(bag, deskewed, imu_topic=imu_topic, progress=progress)
    if result.counts.get('scans_with_imu', 0) < 0.5 * max(1, result.counts.get('scans_processed', 0)):
        first.notes.append('one pass only: the IMU did not cover the sweeps with the offset first found')
        return first
    stamps_ns, poses = result.trajectory(axes='map')
    second = calibrate(stamps_ns * 1e-9, poses[:, :3, :3], imu)
    second.notes.append(
        f'second pass (sweeps deskewed with the IMU as first found: rotation_rpy '
        f'[{", ".join(f"{a:.2f}" for a in np.round(first.rotation_rpy, 2) + 0.0)}], time_offset '
        f'{first.time_offset:.4f})'
    )
    return second


def format_calibration(calibration: Calibration, bag: str) -> str:
    c = calibration
    rpy = ', '.join(f'{a:.2f}' for a in np.round(c.rotation_rpy, 2) + 0.0)
    lines = [
        f'# lego_loam_py calibrate {bag}',
        f'# {c.duration:.1f} s, {c.intervals} intervals of lidar-only odometry against the gyro; the lidar '
        f'turned at {", ".join(f"{r:.1f}" for r in c.rates_rms_deg_s)} deg/s RMS about its x, y, z axes',
        f'# rotation_rpy [{rpy}] deg (IMU axes in the lidar frame), 1 sigma about the lidar x, y, z axes '
        f'{", ".join(f"{s:.2f}" for s in c.rotation_sigma_deg)} deg (block jackknife; least squares '
        f'{", ".join(f"{s:.2f}" for s in c.formal_rotation_sigma_deg)})',
        f'# time_offset {1e3 * c.time_offset:.1f} ms (IMU stamp - lidar stamp), 1 sigma '
        f'{1e3 * c.time_offset_sigma:.1f} ms (least squares {1e3 * c.formal_time_offset_sigma:.1f})',
        f'# {c.residual_deg:.3f} deg per interval left between the lidar and the gyro',
    ]
    lines += [f'# note: {note}' for note in c.notes]
    return '\n'.join(lines) + '\n' + c.parameter_block()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lego_loam_py.cli import add_parameter_arguments

    parser.add_argument('bag', help='ROS 1 .bag or ROS 2 bag with PointCloud2 and Imu (angular velocity), moving')
    parser.add_argument(
        '--trajectory',
        type=Path,
        default=None,
        help='lidar-only poses as TUM (REP-103 axes, e.g. trajectory.tum of lego_loam_py run --no-imu) '
        'instead of running the pipeline on the lidar alone',
    )
    add_parameter_arguments(
        parser, 'ROS 2 parameter file for the lidar-only run (sensor, topics)', 'sensor.imu_topic:=/os_cloud_node/imu'
    )
    parser.add_argument(
        '--single-pass',
        action='store_true',
        help='estimate once, from the lidar-only odometry (default: again from a second pass whose '
        'sweeps are deskewed with the IMU as first found; halves the time)',
    )
    parser.add_argument('--json', type=Path, default=None, help='also write the figures as JSON here')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')


def main(args: argparse.Namespace) -> int:
    from lego_loam_py.core.params import load_params, parse_overrides

    params = load_params(args.params_file, parse_overrides(args.param))
    calibration = calibrate_bag(
        args.bag, params, args.trajectory, progress=not args.no_progress, refine=not args.single_pass
    )
    if args.json is not None:
        args.json.write_text(json.dumps(calibration.to_dict(), indent=2) + '\n')
    if calibration.refused is not None:
        print(format_calibration(calibration, args.bag), file=sys.stderr)
        raise CalibrationRefused(f'{args.bag}: {calibration.refused}')
    print(format_calibration(calibration, args.bag))
    return 0
