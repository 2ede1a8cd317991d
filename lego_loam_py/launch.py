"""``lego_loam_py launch``: the four nodes as separate, supervised processes (ros2 launch without launch).

ros2 launch is not installable from PyPI, so this module does for lego_loam_py what ``ros2 launch`` does
with the original's ``run.launch``: it starts imageProjection, featureAssociation, mapOptimization and
transformFusion as separate processes with one parameter file, optionally the bag player (``-p
use_sim_time:=true`` for every node then), the recorder and rviz2, and stops all of them cleanly. With a
full ROS 2 install, ``launch/lego_loam.launch.py`` does the same through ``ros2 launch``.

This module is the command line only: the life of a run (start, ready, run, drain, stop) is
:func:`lego_loam_py.orchestration.run_pipeline`, the processes are :mod:`lego_loam_py.supervisor`'s.

The exit code is 0 when every process started, ran and stopped cleanly (a Ctrl-C included) and 1 when any
did not (a crash, a non-zero exit, a process that had to be killed, the pipeline not becoming ready), 2
for invalid arguments or parameters.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from lego_loam_py.errors import UsageError
from lego_loam_py.orchestration import DEFAULT_RECORD_TOPICS, NODES, PipelineConfig, run_pipeline
from lego_loam_py.supervisor import Interrupts, package_file

__all__ = ['add_arguments', 'main', 'build_parser', 'main_argv']


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lego_loam_py.cli import add_parameter_arguments

    parser.add_argument(
        '--bag',
        type=Path,
        default=None,
        help='replay this bag (ROS 1 .bag or ROS 2 directory) with /clock; the nodes get '
        'use_sim_time:=true and everything stops once the bag is played and drained',
    )
    parser.add_argument('-r', '--rate', type=float, default=1.0, help='playback rate factor (default 1)')
    parser.add_argument('--start-offset', type=float, default=0.0, metavar='SEC', help="skip the bag's first SEC s")
    parser.add_argument('--progress', action='store_true', help="show the player's progress bar")
    parser.add_argument(
        '--keep-alive',
        action='store_true',
        help='keep the nodes running after the bag ended (stop with Ctrl-C), e.g. to look at RViz',
    )
    add_parameter_arguments(
        parser,
        'ROS 2 parameter file for all four nodes (default: config/params.yaml of the package)',
        'map_optimization.file_directory:=/tmp/maps',
    )
    parser.add_argument(
        '--use-sim-time',
        choices=['auto', 'true', 'false'],
        default='auto',
        help='use_sim_time of the nodes (auto: true when replaying a bag)',
    )
    parser.add_argument(
        '--nodes',
        nargs='+',
        choices=list(NODES),
        default=list(NODES),
        metavar='NODE',
        help=f'start only these nodes (default: all: {" ".join(NODES)})',
    )
    parser.add_argument(
        '--composed',
        action='store_true',
        help='the four nodes in one process (legoLoam): their messages to each other in memory, not over DDS; '
        'the same topics, frames and results, less CPU',
    )
    parser.add_argument(
        '--record',
        nargs='*',
        default=None,
        metavar='TOPIC',
        help='record these topics (no topic: /integrated_to_init /laser_odom_to_init '
        '/aft_mapped_to_init) into a ROS 2 bag (see -o)',
    )
    parser.add_argument('--record-all', action='store_true', help='record every topic')
    parser.add_argument(
        '-o',
        '--record-output',
        type=Path,
        default=None,
        help='bag directory the recorder creates (default: rosbag2_<date>-<time>)',
    )
    parser.add_argument(
        '--stats-dir',
        type=Path,
        default=None,
        help='each node writes <dir>/<node>.json (counters, timings) when it stops',
    )
    parser.add_argument(
        '--log-dir', type=Path, default=None, help="also write every process's output to <dir>/<name>.log"
    )
    parser.add_argument(
        '--quiet-nodes', action='store_true', help="nodes' output only into --log-dir files, not on the terminal"
    )
    parser.add_argument(
        '--rviz', action='store_true', help='start rviz2 with config/lego_loam.rviz (full ROS 2 installs)'
    )
    parser.add_argument('--rviz-config', type=Path, default=None, help='another .rviz file')
    parser.add_argument(
        '--ready-timeout',
        type=float,
        default=60.0,
        metavar='SEC',
        help='give up when the nodes are not up within SEC s (default 60)',
    )
    parser.add_argument(
        '--drain-quiet',
        type=float,
        default=2.0,
        metavar='SEC',
        help='after the bag: stop once no /integrated_to_init came for SEC s (default 2)',
    )
    parser.add_argument(
        '--drain-timeout',
        type=float,
        default=30.0,
        metavar='SEC',
        help='after the bag: stop after SEC s at most (default 30)',
    )
    parser.add_argument(
        '--stop-timeout',
        type=float,
        default=30.0,
        metavar='SEC',
        help='SIGKILL a process that has not exited SEC s after SIGINT (default 30)',
    )


def main(args: argparse.Namespace) -> int:
    if args.quiet_nodes and args.log_dir is None:
        raise UsageError('--quiet-nodes needs --log-dir')
    record_topics = list(DEFAULT_RECORD_TOPICS) if args.record == [] else list(args.record or [])
    ros_args = list(getattr(args, 'ros_args', None) or [])[1:]  # [program name, '--ros-args', ...]
    config = PipelineConfig(
        nodes=args.nodes,
        composed=args.composed,
        params_file=args.params_file or package_file('config', 'params.yaml'),
        overrides=args.param,
        ros_args=ros_args,
        use_sim_time=None if args.use_sim_time == 'auto' else args.use_sim_time == 'true',
        bag=args.bag,
        rate=args.rate,
        start_offset=args.start_offset,
        player_progress=args.progress,
        record_topics=record_topics,
        record_all=args.record_all,
        record_output=args.record_output,
        stats_dir=args.stats_dir,
        rviz=args.rviz,
        rviz_config=args.rviz_config,
        keep_alive=args.keep_alive,
        ready_timeout=args.ready_timeout,
        drain_quiet=args.drain_quiet,
        drain_timeout=args.drain_timeout,
        stop_timeout=args.stop_timeout,
        output='log' if args.quiet_nodes else 'screen',
        log_dir=args.log_dir,
    )
    with Interrupts() as interrupts:
        outcome = run_pipeline(config, stop=interrupts.stop, hurry=interrupts.hurry)
    if outcome.failures:
        print('[launch] FAILED: ' + '; '.join(outcome.failures), file=sys.stderr, flush=True)
    else:
        print(
            f'[launch] done: every process stopped cleanly ({outcome.wall_time_s:.1f} s)', file=sys.stderr, flush=True
        )
    return outcome.exit_code


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='lego_loam.py',
        description=__doc__.split('\n\n')[1].replace('\n', ' '),
        epilog='ROS arguments for every node go after --ros-args (e.g. --ros-args -r /velodyne_points:=/points).',
    )
    add_arguments(parser)
    return parser


def main_argv(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``launch_scripts/lego_loam.py``: the ``launch`` command with its own parser."""
    from lego_loam_py.cli import _split_ros_args, run_command

    ours, ros_args = _split_ros_args(list(sys.argv[1:] if argv is None else argv))
    args = build_parser().parse_args(ours)
    args.ros_args = ['lego_loam.py', *ros_args]
    return run_command(main, args)
