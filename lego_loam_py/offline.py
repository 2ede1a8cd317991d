"""``lego_loam_py run PATH``: the four nodes' cores in one process, without DDS, as fast as the machine goes.

The recording is any :class:`lego_loam_py.inputs.Source`: a ROS bag, a KITTI sequence, a folder of scans or a pcap, its
kind guessed from the path (``--dataloader`` forces it). Messages are taken in recording order, as a replay delivers
them: IMU samples go to featureAssociation and mapOptimization, each cloud goes through imageProjection ->
featureAssociation -> transformFusion, and the 'last' clouds to mapOptimization, whose result corrects the fused poses
of the following scans (in the running system /aft_mapped_to_init of a scan arrives after that scan's
/integrated_to_init). Loop closure, when enabled, runs every ``loop_closure.period`` seconds of bag time. The outputs
are those of the demo: trajectories (TUM, REP-103 and camera_init axes; ``--format kitti`` adds KITTI's), maps (PCD), a
PNG and a summary with the accuracy against the recording's ground truth (beside a simulated bag, a KITTI poses.txt).
``--viewer`` / ``--viewer-save`` show the run in Rerun (:mod:`lego_loam_py.viewer`). With ``--map DIR`` mapOptimization
localizes in the map bundle saved in DIR instead of building a map (``map_optimization.mode: localization``); the
summary says when the first fix came and how much of the run was localized.

The pipeline is :class:`lego_loam_py.core.pipeline.Pipeline`, the one-scan call, in a loop over the recording.
The recording is read and projected in one child process, featureAssociation runs in another and the mapping in
this one (lego_loam_py.front_end_process), or mapOptimization on a worker thread (see :func:`run_source`); the
result is identical to a sequential run, and the ms per mapping step are CPU time.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from collections import deque
from pathlib import Path

from lego_loam_py.allocator import keep_heap_pages
from lego_loam_py.blas import blas_threads_for_run
from lego_loam_py.core.params import Params, SensorParams, load_params, parse_overrides
from lego_loam_py.core.pipeline import Pipeline, RunResult
from lego_loam_py.core.pipeline_events import PipelineListener
from lego_loam_py.front_end_process import can_split, run_split
from lego_loam_py.inputs import SOURCE_KINDS, ImuSample, Scan, Source, open_source
from lego_loam_py.inputs.sidecars import recording_source
from lego_loam_py.outputs import TRAJECTORY_FORMATS, result_lines, write_outputs
from lego_loam_py.results import LocalizationSummary, LoopClosures, OfflineSummary, TimingStats

__all__ = [
    'RunResult',
    'run_bag',
    'run_source',
    'format_summary',
    'loop_closures_of',
    'localization_of',
    'add_arguments',
    'main',
]


# A range image at least this large (64 beams and up) is projected on its own thread: its numpy passes are long
# enough to leave the GIL to featureAssociation most of the time (on the HDL-64E drive, 1.49x -> 1.60x real time,
# medians of 3); a 16-beam scan's short passes only contend for it (4.2x -> 3.6x on the campus).
PROJECTION_THREAD_PIXELS = 64 * 1000


def run_bag(
    bag: str | Path,
    params: Params,
    *,
    cloud_topic: str | None = None,
    imu_topic: str | None = None,
    max_scans: int | None = None,
    progress: bool = True,
    mapping: bool = True,
    mapping_thread: bool = True,
    front_end_process: bool = True,
    listener: PipelineListener | None = None,
) -> RunResult:
    """Run the pipeline over a bag and return what it produced (``mapping=False``: odometry only); the topics
    default to the parameters' (``imu_topic=''``: no IMU). See :func:`run_source`."""
    cloud_topic = cloud_topic or params.sensor.point_cloud_topic
    imu_topic = params.sensor.imu_topic if imu_topic is None else imu_topic
    with open_source(bag, 'rosbag', cloud_topic=cloud_topic, imu_topic=imu_topic) as source:
        return run_source(
            source,
            params,
            max_scans=max_scans,
            progress=progress,
            mapping=mapping,
            mapping_thread=mapping_thread,
            front_end_process=front_end_process,
            listener=listener,
        )


def run_source(
    source: Source,
    params: Params,
    *,
    max_scans: int | None = None,
    progress: bool = True,
    mapping: bool = True,
    mapping_thread: bool = True,
    front_end_process: bool = True,
    listener: PipelineListener | None = None,
) -> RunResult:
    """Run the pipeline over a recording (any :class:`~lego_loam_py.inputs.Source`) and return what it produced.

    ``mapping_thread``: use the other cores. With ``front_end_process`` (and no listener, on a platform that
    forks) the recording is read and projected (imageProjection) in one child process, featureAssociation runs in
    another, mapOptimization and transformFusion in this one (lego_loam_py.front_end_process). Otherwise
    mapOptimization runs on a worker thread, overlapping the next scans' imageProjection and featureAssociation
    where numpy and scipy release the GIL. Either way, for range images of at least PROJECTION_THREAD_PIXELS, each
    scan's imageProjection runs on a thread of its own from the moment the scan is read, overlapping what comes
    before it in its process (the reading; in one process, the featureAssociation of the scan before it).
    The result is the same as without them: mapOptimization takes the mapping inputs and IMU samples in recording
    order, transformFusion applies each mapping result before the scans that follow it, as the sequential run
    does, and the projection of a scan depends on the scans before it only.
    ``listener`` receives the pipeline's events (a viewer, see core.pipeline_events).
    """
    projection_thread = mapping_thread and params.sensor.n_scan * params.sensor.horizon_scan >= PROJECTION_THREAD_PIXELS
    split = mapping_thread and front_end_process and listener is None and can_split()
    pipeline = Pipeline(
        params,
        mapping=mapping,
        mapping_thread=mapping_thread and not split,
        projection_thread=projection_thread,
        listener=listener,
    )
    pipeline.mo.map_source = recording_source(source.path)  # (noted in the map bundle it saves)
    stages = (pipeline.ip, pipeline.fa, pipeline.mo)  # (mo: the mapping, or the localization in a saved map)
    # What the stages import where they first use it, imported now, as a node does with its first input: before the
    # clock starts, before the front end forks, before the BLAS limit (a library may bring a BLAS of its own).
    for module in dict.fromkeys(module for stage in stages for module in getattr(stage, 'DEFERRED_IMPORTS', ())):
        importlib.import_module(module)
    with blas_threads_for_run():  # (a script that imported NumPy first has a BLAS thread per core)
        result = pipeline.record
        start = time.perf_counter()
        try:
            result.bag_duration = source.duration_s
            bar = None
            if progress:
                from tqdm import tqdm

                total = source.scan_count()
                bar = tqdm(
                    total=None if total is None else min(total, max_scans or total),
                    unit='scan',
                    desc='run',
                    file=sys.stderr,
                    dynamic_ncols=True,
                    mininterval=0.5,
                )
            update = bar.update if bar is not None else (lambda: None)
            items = items_in_turn(source, pipeline, max_scans)
            try:
                if split:
                    cut = run_split(pipeline, items, update)
                else:
                    cut = None
                    for item, projected in items:
                        if item is None:
                            cut = projected
                        elif isinstance(item, ImuSample):
                            pipeline.add_imu(item.sample)
                        else:
                            if isinstance(item, Scan):
                                pipeline.process_scan(item.points, item.stamp_ns, projected)
                            else:  # UnreadableScan
                                pipeline.skip_scan(item.stamp_ns, item.reason)
                            update()
            finally:
                if bar is not None:
                    bar.close()
            if cut is not None:  # (the data processed ends there: the real-time factor is about that part)
                result.bag_duration = cut
            pipeline.finish()
        finally:
            pipeline.close()
        result.wall_time = time.perf_counter() - start
        return result


def items_in_turn(source: Source, pipeline: Pipeline, max_scans: int | None):
    """The recording's items in the order the pipeline takes them, as (item, projected) pairs: each scan's
    projection starts as it is read (:meth:`Pipeline.project`, a future; None for an unreadable scan) and overlaps
    the featureAssociation of the scan before it, everything else keeps the recording's order. When ``max_scans``
    cuts the recording short the last pair is (None, seconds of recording read)."""
    first_ns = None
    scans_read = 0
    waiting: deque = deque()  # items whose turn has not come
    for item in source.items():
        is_scan = not isinstance(item, ImuSample)
        if is_scan and max_scans is not None and scans_read >= max_scans:
            yield from waiting
            yield None, (item.received_ns - first_ns) * 1e-9 if first_ns is not None else 0.0
            return
        first_ns = item.received_ns if first_ns is None else first_ns
        if not is_scan:
            waiting.append((item, None))
            continue
        scans_read += 1
        projected = pipeline.project(item.points) if isinstance(item, Scan) else None
        yield from waiting
        waiting.clear()
        waiting.append((item, projected))
    yield from waiting


def loop_closures_of(result: RunResult, params: Params) -> LoopClosures | None:
    """The loops of a run for its summary (None when loop closure was off or nothing was mapped)."""
    mapper = result.mapper
    if (
        mapper is None
        or not mapper.builds_map
        or not params.loop_closure.loop_closure_enable_flag
        or not mapper.keyframes
    ):
        return None
    return LoopClosures.of(mapper.loops, mapper.keyframes[0].stamp_ns)


def localization_of(bag: str | Path, result: RunResult) -> LocalizationSummary | None:
    """How a run localized in its saved map, for its summary (None when it mapped)."""
    from lego_loam_py.evaluation import errors_in_map

    localization = result.mapper
    if localization is None or localization.builds_map:
        return None
    for warning in localization.warnings:
        print(f'warning: {warning}', file=sys.stderr)
    bundle = localization.prior.bundle
    stamps, poses = result.trajectory()
    errors = errors_in_map(bag, bundle.source, bundle.stamps_ns, localization.prior.poses_lidar, stamps, poses)
    return LocalizationSummary.of(
        localization, result.counts.get('scans_in', 0), len(stamps), result.first_scan_ns or 0, errors
    )


def write_optimized_trajectory(out: Path, ground_truth, result: RunResult, summary: OfflineSummary) -> None:
    """``trajectory_optimized.tum`` (REP-103 map axes): the fused trajectory in the pose graph's final frame, and
    its accuracy in the summary against ``ground_truth`` (the recording's trajectory, or None)."""
    from lego_loam_py.evaluation import evaluate
    from lego_loam_py.formats import write_tum_atomic
    from lego_loam_py.outputs import write_summary

    trajectory = result.optimized_trajectory()
    write_tum_atomic(out / 'trajectory_optimized.tum', *trajectory)
    if ground_truth is not None:
        try:
            summary.outputs.accuracy_optimized = evaluate(ground_truth, trajectory)
        except ValueError:
            pass  # (the published trajectory's accuracy_error says why)
    write_summary(out, summary)


def format_summary(summary: OfflineSummary) -> str:
    """The report of ``lego_loam_py run``, as printed at the end of a run."""
    lines = [f'bag: {summary.bag}']
    c = summary.counts  # (a counter the run never touched is 0)
    degenerate = f' ({c["mapping_degenerate"]} degenerate)' if c.get('mapping_degenerate') else ''
    lines.append(
        f'scans in {c.get("scans_in", 0)}, processed {c.get("scans_processed", 0)}, dropped '
        f'{c.get("scans_dropped", 0)}; mapping steps {c.get("mapping_steps", 0)}{degenerate}, keyframes '
        f'{c.get("keyframes", 0)}, IMU used on {c.get("scans_with_imu", 0)} scans'
    )
    for name, t in summary.timings_ms.items():
        lines.append(f'  {name:<20s} median {t.median:7.1f} ms   p95 {t.p95:7.1f} ms   (n={t.count})')
    lines.append(
        f'{summary.bag_duration_s:.1f} s of data in {summary.wall_time_s:.1f} s: '
        f'{summary.realtime_factor:.2f}x real time'
    )
    if summary.loop_closures is not None:
        lines.extend(summary.loop_closures.lines())
    if summary.localization is not None:
        lines.extend(summary.localization.lines())
    lines.extend(result_lines(summary.outputs))
    return '\n'.join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lego_loam_py.cli import add_parameter_arguments

    parser.add_argument(
        'bag',
        metavar='PATH',
        help='a recording: ROS 1 .bag or ROS 2 bag (PointCloud2, optionally Imu), '
        'KITTI odometry sequence folder, folder of .pcd/.ply/.bin scans, or Velodyne/Ouster pcap',
    )
    parser.add_argument('-o', '--output', default=None, help='output directory (default: output/<recording name>)')
    add_parameter_arguments(
        parser, 'ROS 2 parameter file (default: built-in defaults)', 'loop_closure.loop_closure_enable_flag:=false'
    )
    parser.add_argument(
        '--map',
        type=Path,
        default=None,
        metavar='DIR',
        help='localize in the map bundle saved in DIR (by a mapping run: OUT/map, or mapOptimization) '
        'instead of mapping: map_optimization.mode localization',
    )
    parser.add_argument('--no-imu', action='store_true', help='ignore the IMU')
    parser.add_argument('--max-scans', type=_positive_int, default=None, help='stop after this many scans')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    inputs = parser.add_argument_group('recordings other than bags')
    inputs.add_argument(
        '--dataloader',
        choices=SOURCE_KINDS,
        default=None,
        help='the kind of recording (default: guessed from the path)',
    )
    inputs.add_argument(
        '--rate-hz',
        type=_positive_float,
        default=10.0,
        help='scans per second of a folder without times.txt (default 10)',
    )
    inputs.add_argument(
        '--model',
        choices=['auto', 'VLP-16'],
        default='auto',
        help="a Velodyne pcap's model: auto = as its packets claim (must be VLP-16); VLP-16 = decode as "
        'VLP-16 whatever they claim (early VLP-16 firmware reports HDL-32E)',
    )
    inputs.add_argument(
        '--metadata',
        type=Path,
        default=None,
        metavar='JSON',
        help="an Ouster pcap's sensor metadata (default: a .json beside it whose name starts the pcap's)",
    )
    parser.add_argument(
        '--format',
        choices=TRAJECTORY_FORMATS,
        default='tum',
        dest='trajectory_format',
        help='trajectory files: tum (default: trajectory.tum, trajectory_camera_init.tum) or kitti '
        '(those and trajectory_kitti.txt)',
    )
    viewer = parser.add_argument_group('viewer (Rerun, rerun-sdk)')
    viewer.add_argument('--viewer', action='store_true', help='show the run live in a Rerun viewer window')
    viewer.add_argument(
        '--viewer-save',
        type=Path,
        default=None,
        metavar='FILE.rrd',
        help='write what the viewer shows to a Rerun recording (no display needed; open it later with '
        '`rerun FILE.rrd`)',
    )


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f'must be at least 1, got {value}')
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f'must be positive, got {text}')
    return value


def _topic_asked_for(value: str, default: str) -> str | None:
    """A topic parameter as the user set it, or None when it is the default (the source may then choose)."""
    return None if value == default else value


def _open_viewer(args: argparse.Namespace, source: Source):
    """The pipeline listener showing the run, or None without --viewer / --viewer-save."""
    if not args.viewer and args.viewer_save is None:
        return None
    from lego_loam_py.viewer.pipeline_view import PipelineView
    from lego_loam_py.viewer.scene import SceneLog

    scene = SceneLog(source.name, save=args.viewer_save, spawn=args.viewer)
    return PipelineView(scene, source.ground_truth())


def main(args: argparse.Namespace) -> int:
    keep_heap_pages()  # as the nodes do (see lego_loam_py.allocator)
    overrides = parse_overrides(args.param)
    if args.map is not None:
        overrides.update({'map_optimization.mode': 'localization', 'map_optimization.map_path': str(args.map)})
    params = load_params(args.params_file, overrides)
    defaults = SensorParams()
    imu_topic = '' if args.no_imu else _topic_asked_for(params.sensor.imu_topic, defaults.imu_topic)
    with open_source(
        args.bag,
        args.dataloader,
        rate_hz=args.rate_hz,
        model=args.model,
        metadata=args.metadata,
        cloud_topic=_topic_asked_for(params.sensor.point_cloud_topic, defaults.point_cloud_topic),
        imu_topic=imu_topic,
    ) as source:
        for note in getattr(source, 'notes', ()):
            print(f'note: {note}', file=sys.stderr)
        if source.kind != 'rosbag':
            print(f'reading {source.describe()}', file=sys.stderr)
        out = Path(args.output or Path('output') / source.name)
        view = _open_viewer(args, source)
        try:
            result = run_source(source, params, max_scans=args.max_scans, progress=not args.no_progress, listener=view)
        finally:
            if view is not None:
                view.finish()
        ground_truth = source.ground_truth()
    trajectory = result.trajectory(axes='camera_init')
    stamps = trajectory.stamps_ns
    summary = OfflineSummary(
        bag=str(args.bag),
        counts=result.counts,
        timings_ms={name: TimingStats.of(v) for name, v in result.timings_ms.items() if v},
        wall_time_s=result.wall_time,
        bag_duration_s=result.bag_duration,
        loop_closures=loop_closures_of(result, params),
        localization=localization_of(args.bag, result),
    )
    localized = summary.localization is not None
    write_outputs(
        out,
        args.bag,
        trajectory,
        result.mapper,
        summary,
        params,
        map_dir=result.mapper.prior.bundle.path if localized else None,
        in_saved_map=localized,
        ground_truth=ground_truth,
        trajectory_format=args.trajectory_format,
        parallel=view is None,  # (a viewer's threads may still be sending: no fork)
    )
    if summary.loop_closures is not None and summary.loop_closures.accepted and len(stamps) >= 3:
        write_optimized_trajectory(out, ground_truth, result, summary)
    print(format_summary(summary))
    written = sorted(p.name + ('/' if p.is_dir() else '') for p in out.iterdir() if not p.name.startswith('.'))
    print(f'outputs in {out}/: {", ".join(written)}')
    if args.viewer_save is not None:
        print(f'viewer recording: {args.viewer_save} (open it with: rerun {args.viewer_save})')
    return 0
