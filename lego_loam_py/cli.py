"""The ``lego_loam_py`` command: bag tools, simulator, offline runs and evaluation.

Each command lives in its own module with ``add_arguments(parser)`` and ``main(args) -> int``; the table
below lists them. ROS arguments (remappings, parameters) go after ``--ros-args``, as for any ROS 2
executable.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from lego_loam_py import __version__
from lego_loam_py.blas import one_blas_thread
from lego_loam_py.errors import LegoLoamError

one_blas_thread()  # (before any command imports NumPy)

__all__ = ['main', 'build_parser', 'run_command', 'add_parameter_arguments', 'COMMANDS']

# (command, module, one-line help, description)
COMMANDS = [
    (
        'play',
        'lego_loam_py.bag.player',
        'replay a ROS 1 or ROS 2 bag over DDS, publishing /clock',
        'Replay a ROS 1 (.bag) or ROS 2 (.db3/.mcap) bag over DDS, publishing /clock. ROS 1 messages are converted '
        'to their ROS 2 types.',
    ),
    (
        'record',
        'lego_loam_py.bag.recorder',
        'record topics into a ROS 2 bag (mcap by default)',
        'Record topics into a ROS 2 bag, custom message types (CloudInfo) included. Ctrl-C finishes the bag cleanly.',
    ),
    (
        'simulate',
        'lego_loam_py.sim.cli',
        'simulate a lidar + IMU recording of a scenario, with ground truth',
        'Simulate a VLP-16 (or another preset) and a 9-axis IMU in a procedural world by ray casting: campus loop, '
        'forest trail, indoor corridor or aggressive drive. Writes a ROS 2 (mcap/db3) or ROS 1 bag with '
        '/velodyne_points and /imu/data, plus ground truth (TUM), per-point labels and the parameters beside it. '
        'Seeded and reproducible.',
    ),
    (
        'view',
        'lego_loam_py.sim.render',
        'top-down PNG of one scan of a bag',
        'Render one PointCloud2 scan of any bag (simulated or real) as a top-down PNG, coloured by height, intensity, '
        'ring or (simulated bags) per-point label.',
    ),
    (
        'convert',
        'lego_loam_py.bag.convert',
        'convert Velodyne/Ouster pcaps or raw-packet bags into PointCloud2 bags',
        'Convert a real recording (Velodyne VLP-16 pcap, single or dual return; Ouster pcap + metadata JSON; ROS 1/2 '
        'bag of velodyne_msgs/VelodyneScan raw packets) into a bag of PointCloud2 sweeps with ring and per-point time.',
    ),
    (
        'run',
        'lego_loam_py.offline',
        'run the pipeline on a recording in one process, without DDS (offline mode)',
        'Run imageProjection, featureAssociation, mapOptimization and transformFusion on a recording (a ROS bag, a '
        'KITTI sequence, a folder of PCD/PLY/BIN scans or a Velodyne/Ouster pcap) in one process, as fast as the '
        'machine goes; writes the trajectory (TUM, REP-103 and camera_init axes; KITTI with --format kitti), the map '
        "(PCD), a PNG and a summary with the accuracy against the recording's ground truth when it has one.",
    ),
    (
        'launch',
        'lego_loam_py.launch',
        'start the four nodes as supervised processes (optionally player, recorder)',
        'Start imageProjection, featureAssociation, mapOptimization and transformFusion as separate processes with one '
        'parameter file (ros2 launch is not installable from PyPI), optionally replaying a bag with /clock '
        '(use_sim_time) and recording topics. Ctrl-C, SIGTERM or the end of the bag (after a drain) stop every process '
        'cleanly in reverse order; the exit code is non-zero when any process failed.',
    ),
    (
        'demo',
        'lego_loam_py.demo',
        'one command: the pipeline over DDS on a bag, with summary, trajectory, map, PNG',
        'Run the four nodes as separate processes over DDS on a bag (default: bags/campus_8s) with the player and the '
        'recorder, then print a summary (scans in and processed per node, drops, trajectory length, accuracy against '
        'the ground truth beside the bag, ms per scan per node) and write the trajectory (TUM), the map (PCD), a PNG '
        'and summary.json.',
    ),
    (
        'batch',
        'lego_loam_py.batch.cli',
        'many recordings x parameter sets through the offline pipeline, on Dask',
        'Run every recording x parameter set (a grid from -p NAME:=V1,V2 and repeated --params-file; x IMU on/off) '
        'through the offline pipeline, each run in its own worker process of a Dask cluster (local on 127.0.0.1 by '
        'default, or --scheduler). Every run gets a directory (trajectory, map, summary, parameters, code version, '
        'command, log); running again resumes: finished runs are kept, failed ones retried. Writes report.md, '
        'report.csv and plots.',
    ),
    (
        'viewer',
        'lego_loam_py.ros.viewer_node',
        'show the running nodes in Rerun (or save it as .rrd)',
        'Subscribe to the standard topics of the running nodes (scan by label, features, map, keyframes, the three '
        'odometries, /diagnostics) and show them live in a Rerun viewer, or save them with --save FILE.rrd. Needs '
        'rerun-sdk.',
    ),
    (
        'calibrate',
        'lego_loam_py.calibration',
        'estimate the IMU-to-lidar rotation and time offset from a recording',
        'Estimate how the IMU is mounted on the lidar (the rotation of its axes, imu.rotation_rpy) and how its clock '
        "relates to the lidar's (imu.time_offset) from a recording with motion: the lidar-only odometry's turns "
        "against the gyro's (hand-eye). Prints the values with their uncertainty as a parameter block to paste, or "
        'refuses when the motion cannot tell them (too short, or not turning about every axis).',
    ),
    (
        'eval',
        'lego_loam_py.evaluation',
        'accuracy of a trajectory against ground truth (ATE, RPE, drift) with evo',
        'Compare an estimated TUM trajectory with a ground truth (a TUM file, or the ground_truth.tum beside a '
        'bag): ATE after SE(3) alignment, RPE over segments, end-point error and drift; optional plot.',
    ),
]


def _split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """(our arguments, rclpy arguments); rclpy gets '--ros-args ...' up to a closing '--'."""
    if '--ros-args' not in argv:
        return argv, []
    i = argv.index('--ros-args')
    rest = argv[i:]
    end = rest.index('--') if '--' in rest else len(rest)
    return argv[:i] + rest[end + 1 :], rest[:end]


def add_parameter_arguments(parser: argparse.ArgumentParser, params_file_help: str, param_example: str) -> None:
    """``--params-file FILE`` and ``-p NAME:=VALUE`` (repeatable; see core.params.parse_overrides), the same
    for every command that runs the pipeline."""
    parser.add_argument('--params-file', type=Path, default=None, help=params_file_help)
    parser.add_argument(
        '-p',
        '--param',
        action='append',
        default=[],
        metavar='NAME:=VALUE',
        help=f'override one parameter, e.g. -p {param_example}',
    )


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser; with ``command``, only that command's module is imported and given its arguments
    (the others keep their help line; '' for none): each module brings its own dependencies (rclpy, scipy,
    matplotlib, ...), half a second of start-up for all of them."""
    parser = argparse.ArgumentParser(
        prog='lego_loam_py',
        description='LeGO-LOAM for ROS 2 in Python: tools around the four nodes.',
        epilog='ROS arguments go after --ros-args. Nodes: ros2 run lego_loam_py <imageProjection|'
        'featureAssociation|mapOptimization|transformFusion>.',
    )
    parser.add_argument('--version', action='version', version=f'lego_loam_py {__version__}')
    commands = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for name, module_name, summary, description in COMMANDS:
        sub = commands.add_parser(name, help=summary, description=description)
        if command is None or name == command:
            module = importlib.import_module(module_name)
            module.add_arguments(sub)
            sub.set_defaults(handler=module.main)
    return parser


def run_command(handler, args: argparse.Namespace) -> int:
    """A command's exit code: what ``handler(args)`` returns, or for a :class:`LegoLoamError` it raised its
    ``exit_code`` after one ``error: ...`` line (the one place where errors become messages and codes); 130
    after Ctrl-C."""
    try:
        return int(handler(args) or 0)
    except LegoLoamError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, ros_args = _split_ros_args(argv)
    # (the command is the first word: the program's own options, --help and --version, take no value; without a
    # known one, argparse's help or error needs no command's module)
    command = next((word for word in ours if not word.startswith('-')), None)
    known = command in {name for name, *_ in COMMANDS}
    args = build_parser(command if known else '').parse_args(ours)
    args.ros_args = ['lego_loam_py', *ros_args]
    code = run_command(args.handler, args)
    if 'lego_loam_py.ros.runtime' in sys.modules and sys.modules['lego_loam_py.ros.runtime'].stuck_teardowns():
        # A DDS teardown is stuck on a thread of ours: interpreter exit would wait for it forever.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


if __name__ == '__main__':
    sys.exit(main())
