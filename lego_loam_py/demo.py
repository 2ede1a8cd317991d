"""``lego_loam_py demo [BAG]``: the whole system on a recording, as it runs on a robot, in one command.

The four nodes run as separate processes talking DDS (:mod:`lego_loam_py.orchestration`), the player
replays the bag with /clock (the nodes use sim time), and the recorder records /integrated_to_init,
/laser_odom_to_init and /aft_mapped_to_init. Once the bag is played and the pipeline drained, every
process is stopped with SIGINT: each node writes its statistics (``LEGO_LOAM_PY_STATS_DIR``) and
mapOptimization saves the map (``map_optimization.file_directory``). The demo then reads all of it back
and writes, into ``OUTDIR`` (default ``output/demo-<bag name>/``):

* ``trajectory.tum`` (REP-103 ``map`` axes) and ``trajectory_camera_init.tum`` (the original's camera_init
  axes): the recorded /integrated_to_init, one pose per scan, the pose = ``odometry_to_pose(msg)``;
* ``map/``: global, corner and surface maps (PCD) and the keyframe trajectory, saved by mapOptimization;
* ``trajectory.png``: the trajectory (and the ground truth) over a top view of the map;
* ``summary.json``: the figures printed at the end (scans in and processed per node, drops, ms per scan,
  trajectory length, accuracy against the ground truth when one sits beside the bag);
* ``recording/`` (mcap), ``stats/<node>.json``, ``logs/<process>.log``.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from lego_loam_py.core.guard import KEYFRAMES, MAPPING_STEPS, SCANS_DROPPED, SCANS_PROCESSED, SCANS_WITH_IMU
from lego_loam_py.core.trajectory import Trajectory
from lego_loam_py.errors import UsageError
from lego_loam_py.orchestration import COMPOSED, DEFAULT_RECORD_TOPICS, NODES, PipelineConfig, run_pipeline
from lego_loam_py.results import DemoSummary, LoopClosures, TimingStats
from lego_loam_py.supervisor import Interrupts, package_file

__all__ = [
    'DemoResult',
    'run_demo',
    'read_trajectory',
    'read_stats',
    'format_demo_summary',
    'default_bag',
    'add_arguments',
    'main',
]

STATS_NODES = tuple(NODES)  # every node writes its statistics when it stops
# Timing entry of each node's statistics that is its work per scan (mapOptimization: per mapping step).
NODE_TIMINGS = {
    'imageProjection': 'scan',
    'featureAssociation': 'scan',
    'mapOptimization': 'step',
    'transformFusion': 'odometry',
}
# Counters that count messages a node received and threw away.
_DROP_COUNTER = re.compile(r'(dropped|failed|rejected|errors)$')
MAP_FILES = (
    'global_map.pcd',
    'corner_map.pcd',
    'surface_map.pcd',
    'trajectory.pcd',
    'trajectory.tum',
    'trajectory_camera_init.tum',
)


def _display(path: Path) -> str:
    """``path`` relative to the working directory when it lies below it (as users type it)."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def default_bag() -> Path:
    """bags/campus_8s of the source tree (the committed recording)."""
    return Path(__file__).resolve().parents[1] / 'bags' / 'campus_8s'


@dataclass
class DemoResult:
    exit_code: int
    summary: DemoSummary
    out_dir: Path


def read_stats(stats_dir: Path) -> dict[str, dict]:
    """Node name -> the statistics it wrote on shutdown (missing nodes are left out)."""
    out = {}
    for name in STATS_NODES:
        path = Path(stats_dir) / f'{name}.json'
        if path.is_file():
            try:
                out[name] = json.loads(path.read_text())
            except (OSError, ValueError):
                continue
    return out


def read_trajectory(recording: Path, topic: str = '/integrated_to_init', offset_ns: int = 0) -> Trajectory:
    """The poses (camera_init frame) of the Odometry messages of ``topic`` in a recorded bag, in the order they
    were published, at their header stamps + ``offset_ns`` [ns]; empty without the topic or the bag."""
    from lego_loam_py.bag.io import BagReader
    from lego_loam_py.ros.conversions import odometry_to_pose

    stamps, poses = [], []
    if not (recording / 'metadata.yaml').is_file():
        return Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)), 'camera_init')
    with BagReader(recording) as reader:
        if topic not in reader.topics():
            return Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)), 'camera_init')
        for message in reader.messages(topics=[topic]):
            msg = reader.deserialize(message)
            try:
                pose = odometry_to_pose(msg)
            except ValueError:
                continue
            stamps.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
            poses.append(pose)
    return Trajectory(np.array(stamps, dtype=np.int64) + offset_ns, np.array(poses).reshape(-1, 4, 4), 'camera_init')


def _clear_previous_outputs(out: Path) -> None:
    """Remove what an earlier demo wrote into ``out`` that this run would not overwrite (a stale map or
    statistics file would be taken for this run's). Only our own file names are touched."""
    recording = out / 'recording'
    if recording.exists():
        if recording.is_dir() and ((recording / 'metadata.yaml').is_file() or not any(recording.iterdir())):
            shutil.rmtree(recording)
        else:
            raise UsageError(f'{recording} exists and is not a bag this demo recorded: move it away')
    for name in STATS_NODES:
        (out / 'stats' / f'{name}.json').unlink(missing_ok=True)
    for name in MAP_FILES:
        (out / 'map' / name).unlink(missing_ok=True)
    for name in ('trajectory.tum', 'trajectory_camera_init.tum', 'trajectory.png', 'summary.json'):
        (out / name).unlink(missing_ok=True)


class NodeFigures(NamedTuple):
    """What the nodes' statistics say about a run."""

    processed: dict[str, int]  # node -> scans it processed (mapOptimization: mapping steps)
    drops: dict[str, dict[str, int]]  # node -> its non-zero counters of messages thrown away
    timings: dict[str, TimingStats]  # node -> its time per scan (mapOptimization: per mapping step)


def _node_counters(stats: dict[str, dict]) -> dict[str, dict[str, int]]:
    """Node -> its counters, for every node (empty for a node that wrote no statistics; a counter a node never
    touched is not in its file: read them with ``.get(name, 0)``)."""
    return {name: stats[name].get('counters', {}) if name in stats else {} for name in STATS_NODES}


def _node_summary(stats: dict[str, dict]) -> NodeFigures:
    """Processed scans, drop counters and timings per node from the nodes' statistics."""
    counters = _node_counters(stats)
    processed = {
        'imageProjection': counters['imageProjection'].get('clouds_out', 0),
        'featureAssociation': counters['featureAssociation'].get(SCANS_PROCESSED, 0),
        'mapOptimization': counters['mapOptimization'].get(MAPPING_STEPS, 0),
        'transformFusion': counters['transformFusion'].get('integrated', 0),
    }
    drops = {}
    for name, values in counters.items():
        found = {k: v for k, v in values.items() if _DROP_COUNTER.search(k) and v}
        # featureAssociation's inputs without partners are lost scans; mapOptimization's are mostly the
        # odometry of scans that were not sent to mapping (every other scan), which is by design.
        if name == 'featureAssociation' and values.get('unmatched_inputs'):
            found['unmatched_inputs'] = values['unmatched_inputs']
        if found:
            drops[name] = found
    timings = {}
    for name, key in NODE_TIMINGS.items():
        available = stats[name].get('timings_ms', {}) if name in stats else {}
        entry = available.get(key) or (next(iter(available.values())) if len(available) == 1 else None)
        if entry:
            timings[name] = TimingStats.from_dict(entry)
    return NodeFigures(processed, drops, timings)


def run_demo(
    bag: str | Path,
    out_dir: str | Path,
    *,
    rate: float = 1.0,
    params_file: Path | None = None,
    overrides: list[str] | None = None,
    progress: bool = False,
    stop: threading.Event | None = None,
    hurry: threading.Event | None = None,
    announce: Callable[[str], None] | None = None,
    ready_timeout: float = 60.0,
    viewer: bool = False,
    viewer_save: Path | None = None,
    composed: bool = False,
) -> DemoResult:
    """Run the pipeline over DDS on ``bag`` and write the outputs into ``out_dir`` (see the module
    docstring). Raises ``BagError``, ``ParameterError`` or ``UsageError`` before starting anything when the
    bag, the parameters or the output directory cannot be used."""
    from lego_loam_py.bag.io import BagReader
    from lego_loam_py.core.params import load_params, parse_overrides
    from lego_loam_py.outputs import pose_time_offset_ns, write_outputs, write_summary

    out = Path(out_dir).resolve()
    params_file = params_file or package_file('config', 'params.yaml')
    map_dir = out / 'map'
    node_overrides = list(overrides or []) + [f'map_optimization.file_directory:={map_dir}']
    params = load_params(params_file, parse_overrides(node_overrides), node_name='imageProjection')
    with BagReader(bag) as reader:
        scans_in = reader.topic_counts().get(params.sensor.point_cloud_topic, 0)
        bag_duration = reader.duration
    out.mkdir(parents=True, exist_ok=True)
    _clear_previous_outputs(out)

    config = PipelineConfig(
        composed=composed,
        params_file=params_file,
        overrides=node_overrides,
        bag=Path(bag),
        rate=rate,
        player_progress=progress,
        record_topics=DEFAULT_RECORD_TOPICS,
        record_output=out / 'recording',
        stats_dir=out / 'stats',
        output='log',
        log_dir=out / 'logs',
        ready_timeout=ready_timeout,
        viewer=viewer,
        viewer_save=Path(viewer_save).resolve() if viewer_save is not None else None,
    )
    outcome = run_pipeline(config, stop=stop, hurry=hurry, announce=announce)

    stats = read_stats(out / 'stats')
    figures = _node_summary(stats)
    counters = _node_counters(stats)
    recording = out / 'recording'
    trajectory = read_trajectory(recording, offset_ns=pose_time_offset_ns(params))
    stamps = trajectory.stamps_ns
    fa = counters['featureAssociation']
    # Scans imageProjection published that featureAssociation neither processed nor rejected: overwritten in
    # its depth-1 input queues while it was busy (the original's queue semantics), when it is not real time.
    # (A scan with one part overwritten leaves its other parts in featureAssociation's unmatched_inputs.)
    fa_handled = fa.get(SCANS_PROCESSED, 0) + fa.get(SCANS_DROPPED, 0)
    overwritten = max(0, figures.processed['imageProjection'] - fa_handled) if 'featureAssociation' in stats else 0
    summary = DemoSummary(
        bag=_display(bag),
        rate=rate,
        bag_duration_s=bag_duration,
        wall_time_s=outcome.wall_time_s,
        scans_in=scans_in,
        processed=figures.processed,
        integrated=len(stamps),
        not_received=(
            max(0, scans_in - counters['imageProjection'].get('clouds_in', 0))
            if 'imageProjection' in stats
            else scans_in
        ),
        drop_counters=figures.drops,
        queue_overwritten=overwritten,
        keyframes=counters['mapOptimization'].get(KEYFRAMES, 0),
        scans_with_imu=fa.get(SCANS_WITH_IMU, 0),
        timings_ms=figures.timings,
        processes=list(outcome.processes),
        failures=list(outcome.failures),
        interrupted=outcome.interrupted,
        ready_after_s=outcome.ready_after_s,
        loop_closures=_loop_closures(stats),
    )
    if len(stamps):
        write_outputs(out, bag, trajectory, None, summary, params, map_dir=map_dir)
    else:  # no pose, no trajectory file, picture or accuracy: the summary says 0 m
        write_summary(out, summary)
    exit_code = outcome.exit_code
    if exit_code == 0 and not len(stamps) and not outcome.interrupted:
        summary.failures.append(f'no /integrated_to_init was recorded from {scans_in} scans')
        write_summary(out, summary)
        exit_code = 1
    return DemoResult(exit_code, summary, out)


def _loop_closures(stats: dict[str, dict]) -> LoopClosures | None:
    """The loops mapOptimization wrote into its statistics (None when it wrote none: loop closure off)."""
    entry = stats.get('mapOptimization', {}).get('loop_closures')
    return LoopClosures(**entry) if isinstance(entry, dict) else None


def format_demo_summary(summary: DemoSummary, out_dir: Path | None = None) -> str:
    """The demo's report, as printed at the end of a run."""
    scans_in = summary.scans_in
    p = summary.processed
    composed = any(process.name == COMPOSED[0] for process in summary.processes)
    layout = 'the four nodes in one process' if composed else 'four nodes as separate processes'
    lines = [
        f'LeGO-LOAM over DDS: {summary.bag} at {summary.rate:g}x, {layout}'
        + (' (INTERRUPTED)' if summary.interrupted else '')
    ]
    lines.append(
        f'scans in {scans_in} ({summary.bag_duration_s:.1f} s of data); processed: imageProjection '
        f'{p["imageProjection"]}, featureAssociation {p["featureAssociation"]} (IMU on '
        f'{summary.scans_with_imu}), mapOptimization {p["mapOptimization"]} mapping steps '
        f'({summary.keyframes} keyframes), transformFusion {p["transformFusion"]}'
    )
    fraction = summary.integrated_fraction
    lines.append(
        f'/integrated_to_init for {summary.integrated} of {scans_in} scans ({fraction:.1%}; the first '
        f'scan only initialises the odometry)'
    )
    detail = [f'{summary.not_received} never reached imageProjection']
    for node, counters in summary.drop_counters.items():
        detail.append(f'{node} ' + ', '.join(f'{k} {v}' for k, v in counters.items()))
    lines.append(f'dropped messages {summary.dropped}: ' + '; '.join(detail))
    if summary.queue_overwritten:
        lines.append(
            f'  + {summary.queue_overwritten} scans featureAssociation never got: overwritten in its '
            'depth-1 input queues while it was busy (as in the original: the latest scan wins)'
        )
    if summary.timings_ms:
        lines.append(f'{"ms per scan":<22s}{"median":>8s}{"p95":>9s}{"n":>7s}')
        for node, t in summary.timings_ms.items():
            unit = '  (per mapping step)' if node == 'mapOptimization' else ''
            lines.append(f'  {node:<20s}{t.median:8.1f}{t.p95:9.1f}{t.count:7d}{unit}')
    from lego_loam_py.outputs import result_lines

    if summary.loop_closures is not None:
        lines.extend(summary.loop_closures.lines())
    lines.extend(result_lines(summary.outputs))
    if out_dir is not None:
        lines.append(
            f'outputs in {_display(out_dir)}/: trajectory.tum (REP-103 map axes), trajectory_camera_init.tum, '
            f'map/*.pcd, trajectory.png, summary.json, recording/ (mcap), stats/, logs/'
        )
    for failure in summary.failures:
        lines.append(f'FAILED: {failure}')
    return '\n'.join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lego_loam_py.cli import add_parameter_arguments

    parser.add_argument(
        'bag',
        nargs='?',
        default=None,
        help='ROS 1 .bag or ROS 2 bag directory (default: bags/campus_8s of the repository)',
    )
    parser.add_argument('-o', '--output', default=None, help='output directory (default: output/demo-<bag name>)')
    parser.add_argument('-r', '--rate', type=float, default=1.0, help='playback rate factor (default 1)')
    add_parameter_arguments(
        parser, 'ROS 2 parameter file for the nodes (default: config/params.yaml)', 'sensor.imu_topic:=""'
    )
    parser.add_argument('--no-progress', action='store_true', help='no progress bar while the bag plays')
    parser.add_argument('--viewer', action='store_true', help='show the run live in Rerun (lego_loam_py viewer)')
    parser.add_argument(
        '--composed', action='store_true', help='the four nodes in one process (legoLoam) instead of four'
    )
    parser.add_argument(
        '--viewer-save',
        type=Path,
        default=None,
        metavar='FILE.rrd',
        help='save what the viewer shows to a Rerun recording (no display needed)',
    )


def main(args: argparse.Namespace) -> int:
    bag = Path(args.bag) if args.bag else default_bag()
    if args.bag is None and not bag.exists():
        raise UsageError(f'the default recording {bag} is not there (a source checkout has it): give a BAG')
    name = bag.resolve().name if bag.suffix != '.bag' else bag.stem
    out = Path(args.output) if args.output else Path('output') / f'demo-{name}'
    progress = not args.no_progress and sys.stderr.isatty()
    print(
        f'demo: {_display(bag)} at {args.rate:g}x through imageProjection, featureAssociation, mapOptimization and '
        f'transformFusion ({"one process" if args.composed else "separate processes, DDS"}); logs in {out}/logs/',
        file=sys.stderr,
        flush=True,
    )
    with Interrupts() as interrupts:
        result = run_demo(
            bag,
            out,
            rate=args.rate,
            params_file=args.params_file,
            overrides=args.param,
            progress=progress,
            stop=interrupts.stop,
            hurry=interrupts.hurry,
            viewer=args.viewer,
            viewer_save=args.viewer_save,
            composed=args.composed,
        )
    print(format_demo_summary(result.summary, result.out_dir))
    if result.summary.interrupted:
        return 130
    return result.exit_code
