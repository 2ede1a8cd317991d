"""``lego_loam_py simulate``: generate a lidar + IMU recording of a scenario, with ground truth and labels.

lego_loam_py simulate campus -o campus_run --duration 60 --seed 1
lego_loam_py simulate aggressive -o fast.bag --ros1 --layout packed
lego_loam_py simulate forest --cached          # prints the cached bag, generating it on first use
lego_loam_py simulate --list
"""

from __future__ import annotations

import argparse
import sys

from lego_loam_py.errors import LegoLoamError, UsageError

__all__ = ['add_arguments', 'main']


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = (
        'Scenarios: campus (outdoor loop, returns to its start), forest (uneven trail), corridor (indoor '
        'walk), aggressive (yaw rates up to 90 deg/s); see --list. Beside the bag: ground_truth.tum, '
        'ground_truth_dense.tum, labels.npz, scenario.yaml, README.md (inside a ROS 2 bag directory, '
        'or <stem>.<name> next to a ROS 1 .bag).'
    )
    parser.add_argument('scenario', nargs='?', help='campus, forest, corridor or aggressive')
    parser.add_argument('-o', '--output', help='ROS 2 bag directory to create (a .bag file with --ros1)')
    parser.add_argument('--duration', type=float, help='simulated time [s] (default: one full lap of the scenario)')
    parser.add_argument('--seed', type=int, default=0, help='scenery and noise seed (default 0)')
    parser.add_argument(
        '--preset',
        default='VLP-16',
        help='sensor preset: VLP-16 (default), HDL-32E, VLS-128, '
        'HDL-64E, OS1-64, VLP-32C, OS1-128, Pandar64, RS-LiDAR-32, ... (--list shows them all)',
    )
    parser.add_argument('--imu-rate', type=float, default=200.0, help='IMU rate [Hz] (default 200)')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap', help='ROS 2 storage (default mcap)')
    parser.add_argument('--ros1', action='store_true', help='write a ROS 1 .bag instead of a ROS 2 bag')
    parser.add_argument(
        '--layout',
        choices=('driver', 'packed'),
        default='driver',
        help="point layout: 'driver' = ROS 2 velodyne driver PointXYZIRT, 32 bytes (default); "
        "'packed' = ROS 1 driver's packed XYZIRT, 22 bytes",
    )
    parser.add_argument('--compress', action='store_true', help='zstd-compress the bag (ROS 2 only)')
    parser.add_argument(
        '--imu-extrinsic-rpy',
        type=float,
        nargs=3,
        metavar=('R', 'P', 'Y'),
        default=(0.0, 0.0, 0.0),
        help='rotate the IMU axes relative to the lidar: roll pitch yaw [deg] (default 0 0 0)',
    )
    parser.add_argument(
        '--imu-lever-arm',
        type=float,
        nargs=3,
        metavar=('X', 'Y', 'Z'),
        default=(0.0, 0.0, 0.0),
        help='IMU origin in the lidar frame [m] (default 0 0 0): its accelerometer then feels the '
        'centripetal and tangential acceleration of the rotation',
    )
    parser.add_argument(
        '--imu-orientation-rpy',
        type=float,
        nargs=3,
        metavar=('R', 'P', 'Y'),
        default=(0.0, 0.0, 0.0),
        help='rotate the frame whose attitude the orientation field reports, '
        "relative to the IMU axes: roll pitch yaw [deg] (default 0 0 0: the IMU's own)",
    )
    parser.add_argument(
        '--imu-time-offset',
        type=float,
        default=0.0,
        metavar='S',
        help='IMU stamps run this far ahead of the lidar clock [s] (default 0; negative: behind)',
    )
    imu = parser.add_argument_group("IMU errors (each replaces the profile's own, and applies with --ideal too)")
    imu.add_argument(
        '--imu-profile',
        default='default',
        metavar='NAME',
        help='the IMU unit: default (a good MEMS unit, as before), consumer (a BNO055 / MPU-9250 class '
        '9-axis module), industrial (an Xsens MTi / VectorNav VN-100 class AHRS); see the README',
    )
    imu.add_argument(
        '--imu-gyro-bias',
        type=float,
        nargs=2,
        metavar=('LOW', 'HIGH'),
        default=None,
        help='constant gyro bias per axis: magnitude drawn in LOW..HIGH [deg/s], random sign',
    )
    imu.add_argument(
        '--imu-gyro-bias-walk',
        type=float,
        nargs=2,
        metavar=('SIGMA', 'TAU'),
        default=None,
        help='wandering gyro bias per axis: Gauss-Markov, stationary SIGMA [deg/s], correlation time TAU [s]',
    )
    imu.add_argument(
        '--imu-accel-bias',
        type=float,
        nargs=2,
        metavar=('LOW', 'HIGH'),
        default=None,
        help='constant accelerometer bias per axis: magnitude in LOW..HIGH [m/s^2], random sign',
    )
    imu.add_argument(
        '--imu-accel-bias-walk',
        type=float,
        nargs=2,
        metavar=('SIGMA', 'TAU'),
        default=None,
        help='wandering accelerometer bias per axis: SIGMA [m/s^2], TAU [s]',
    )
    imu.add_argument(
        '--imu-gyro-scale-error',
        type=float,
        default=None,
        metavar='PERCENT',
        help='scale-factor error of each gyro axis, drawn within +-PERCENT',
    )
    imu.add_argument(
        '--imu-accel-scale-error',
        type=float,
        default=None,
        metavar='PERCENT',
        help='scale-factor error of each accelerometer axis, drawn within +-PERCENT',
    )
    imu.add_argument(
        '--imu-misalignment',
        type=float,
        default=None,
        metavar='DEG',
        help='cross-axis terms of gyro and accelerometer, each drawn within +-DEG',
    )
    imu.add_argument(
        '--imu-tilt-error',
        type=float,
        nargs=2,
        metavar=('LOW', 'HIGH'),
        default=None,
        help='constant roll/pitch error of the orientation: magnitude in LOW..HIGH [deg], random direction',
    )
    imu.add_argument(
        '--imu-yaw-offset',
        type=float,
        default=None,
        metavar='DEG',
        help='constant yaw offset of the orientation [deg] (profiles other than default: drawn in -180..180)',
    )
    imu.add_argument(
        '--imu-orientation-noise',
        type=float,
        default=None,
        metavar='DEG',
        help='white noise of the orientation per axis [deg]',
    )
    imu.add_argument(
        '--imu-heading-drift',
        type=float,
        nargs=2,
        metavar=('SIGMA', 'TAU'),
        default=None,
        help='wandering heading error of the orientation: Gauss-Markov, SIGMA [deg], TAU [s]',
    )
    imu.add_argument(
        '--imu-stamp-jitter',
        type=float,
        default=0.0,
        metavar='S',
        help='Gaussian jitter of the IMU stamps, sigma [s] (at most a sixth of the sample period)',
    )
    imu.add_argument(
        '--imu-record-late',
        action='store_true',
        help='record each IMU message at its stamp, as a late driver delivers it (with --imu-time-offset: '
        'after the lidar sweep it belongs to), not when it was measured',
    )
    parser.add_argument(
        '--ideal', action='store_true', help='noise-free sensors: no range/IMU noise, no biases, no dropped returns'
    )
    parser.add_argument(
        '--turn-rate',
        type=float,
        default=0.0,
        metavar='DEG_S',
        help='stop for whole in-place turns (at 10 s, then every 30 s) peaking at this yaw rate '
        '[deg/s] (default 0: none)',
    )
    parser.add_argument(
        '--uniform-beams',
        action='store_true',
        help='evenly spaced beams even for a preset with a '
        'beam table (HDL-64E: its nominal, unevenly spaced layout by default)',
    )
    parser.add_argument(
        '--kitti',
        metavar='DIR',
        default=None,
        help='also write the recording as a KITTI odometry '
        'sequence folder (velodyne/*.bin, times.txt, calib.txt, poses.txt)',
    )
    parser.add_argument(
        '--pcd',
        metavar='DIR',
        default=None,
        help='also write the recording as a folder of PCD scans (every field) with times.txt and poses.txt',
    )
    parser.add_argument(
        '--route-start',
        type=float,
        default=None,
        metavar='M',
        help='drive another route through the same scene: start at this arc length [m] along the '
        "scenario's path (default: the scenario's own start)",
    )
    parser.add_argument('--reverse', action='store_true', help="drive the scenario's path the other way round")
    parser.add_argument(
        '--beam-elevation-error',
        type=float,
        default=0.0,
        metavar='DEG',
        help='every point reads this much lower than its beam really points, as a miscalibrated '
        "unit's (KITTI's HDL-64E: about 0.2; default 0)",
    )
    parser.add_argument(
        '--cached',
        action='store_true',
        help='generate into the cache (~/.cache/lego_loam_py/sim, $LEGO_LOAM_CACHE) unless present; print the bag path',
    )
    parser.add_argument('--list', action='store_true', help='list the scenarios and sensor presets, then exit')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')


def _list() -> int:
    from lego_loam_py.sim.lidar import LIDAR_SPECS, LidarModel
    from lego_loam_py.sim.scenarios import SCENARIOS

    print('scenarios:')
    for name, info in SCENARIOS.items():
        print(f'  {name:<11s} {info.description}')
    print('sensor presets (--preset):')
    for name in LIDAR_SPECS:
        model = LidarModel.from_preset(name)
        print(
            f'  {name:<14s} {model.n_rings:3d} beams {model.ring_elevations[0]:+.2f}..{model.ring_elevations[-1]:+.2f} '
            f'deg, {model.columns} columns, range {model.min_range:g}-{model.max_range:g} m, '
            f'noise {100 * model.range_noise:.1f} cm'
        )
    from lego_loam_py.sim.imu import PROFILE_SOURCES

    print('IMU profiles (--imu-profile):')
    for name, source in PROFILE_SOURCES.items():
        print(f'  {name:<11s} {source}')
    return 0


def main(args: argparse.Namespace) -> int:
    if args.list:
        return _list()
    if not args.scenario:
        raise UsageError('name a scenario (campus, forest, corridor, aggressive) or use --list')
    if args.compress and args.ros1:
        raise UsageError('--compress applies to ROS 2 bags only')
    if args.cached and (args.kitti or args.pcd):
        raise UsageError('--kitti and --pcd write beside a bag given with -o, not with --cached')
    if args.cached and args.output:
        raise UsageError('--cached chooses the output itself; drop -o')
    if not args.cached and not args.output:
        raise UsageError('give the output bag with -o (or use --cached)')
    from lego_loam_py.sim.simulator import SimConfig, cached_scenario, simulate

    options = dict(
        duration=args.duration,
        seed=args.seed,
        preset=args.preset,
        imu_rate=args.imu_rate,
        storage=args.storage,
        ros1=args.ros1,
        layout=args.layout,
        compress=args.compress,
        imu_extrinsic_rpy=tuple(args.imu_extrinsic_rpy),
        ideal=args.ideal,
        turn_rate=args.turn_rate,
        uniform_beams=args.uniform_beams,
        imu_lever_arm=tuple(args.imu_lever_arm),
        imu_orientation_rpy=tuple(args.imu_orientation_rpy),
        imu_time_offset=args.imu_time_offset,
        route_start=args.route_start,
        reverse=args.reverse,
        beam_elevation_error=args.beam_elevation_error,
        **_imu_errors(args),
    )
    try:
        if args.cached:
            print(cached_scenario(args.scenario, progress=not args.no_progress, **options))
            return 0
        result = simulate(SimConfig(scenario=args.scenario, **options), args.output, progress=not args.no_progress)
    except (ValueError, FileExistsError) as exc:  # an unknown scenario, a value out of range, an existing bag
        raise LegoLoamError(str(exc)) from None
    print(
        f'wrote {result.bag_path}: {result.scans} scans, {result.imu_messages} IMU messages, {result.points} points '
        f'({result.duration:.1f} s); ground truth and labels beside it',
        file=sys.stderr,
    )
    _export(result.bag_path, args)
    return 0


def _imu_errors(args: argparse.Namespace) -> dict:
    """The IMU error options (SimConfig's imu_* fields of issue 34) as given."""
    pairs = (
        'imu_gyro_bias',
        'imu_gyro_bias_walk',
        'imu_accel_bias',
        'imu_accel_bias_walk',
        'imu_tilt_error',
        'imu_heading_drift',
    )
    out = {name: None if getattr(args, name) is None else tuple(getattr(args, name)) for name in pairs}
    for name in (
        'imu_profile',
        'imu_gyro_scale_error',
        'imu_accel_scale_error',
        'imu_misalignment',
        'imu_yaw_offset',
        'imu_orientation_noise',
        'imu_stamp_jitter',
        'imu_record_late',
    ):
        out[name] = getattr(args, name)
    return out


def _export(bag, args: argparse.Namespace) -> None:
    """--kitti / --pcd: the recording again as dataset folders (lego_loam_py.sim.export)."""
    from lego_loam_py.sim.export import export_recording

    for kind, folder in (('kitti', args.kitti), ('pcd', args.pcd)):
        if folder:
            try:
                scans = export_recording(bag, folder, kind)
            except (ValueError, FileExistsError) as exc:
                raise LegoLoamError(str(exc)) from None
            print(f'wrote {folder}: {scans} scans as a {kind} folder', file=sys.stderr)
