"""``lego_loam_py run BAG``: the four nodes' cores in one process, without DDS, as fast as the machine goes.

Messages are taken in recording order, as a replay delivers them: IMU samples go to featureAssociation and
mapOptimization, each cloud goes through imageProjection -> featureAssociation -> transformFusion, and the
'last' clouds to mapOptimization, whose result corrects the fused poses of the following scans (in the
running system /aft_mapped_to_init of a scan arrives after that scan's /integrated_to_init). Loop closure,
when enabled, runs every ``loop_closure.period`` seconds of bag time. The outputs are those of the demo:
trajectories (TUM, REP-103 and camera_init axes), maps (PCD), a PNG and a summary with the accuracy against
the ground truth found beside the bag.

The pipeline is :class:`lego_loam_py.core.pipeline.Pipeline`, the one-scan call, in a loop over the bag.
mapOptimization runs on its worker thread beside imageProjection and featureAssociation (see :func:`run_bag`);
the result is identical to a sequential run, and its ms per mapping step are the worker's CPU time.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from lego_loam_py.allocator import keep_heap_pages
from lego_loam_py.bag.io import BagError, BagReader, cloud_msg_to_array
from lego_loam_py.core.imu import imu_sample
from lego_loam_py.core.params import Params, load_params, parse_overrides
from lego_loam_py.core.pipeline import Pipeline, RunResult
from lego_loam_py.core.pointcloud import CloudLayoutError
from lego_loam_py.outputs import result_lines, write_outputs
from lego_loam_py.results import LoopClosures, OfflineSummary, TimingStats

__all__ = ['RunResult', 'run_bag', 'format_summary', 'loop_closures_of', 'add_arguments', 'main']


def run_bag(bag: str | Path, params: Params, *, cloud_topic: str | None = None, imu_topic: str | None = None,
            max_scans: int | None = None, progress: bool = True, mapping: bool = True,
            mapping_thread: bool = True) -> RunResult:
    """Run the pipeline over a bag and return what it produced (``mapping=False``: odometry only).

    ``mapping_thread``: mapOptimization runs on a worker thread, overlapping the next scans' imageProjection
    and featureAssociation (it spends most of its time in numpy and scipy, which release the GIL). The result
    is the same as without it: the worker takes the mapping inputs and IMU samples in recording order, and
    transformFusion applies each mapping result before the scans that follow it, as the sequential run does.
    """
    cloud_topic = cloud_topic or params.sensor.point_cloud_topic
    imu_topic = params.sensor.imu_topic if imu_topic is None else imu_topic
    pipeline = Pipeline(params, mapping=mapping, mapping_thread=mapping_thread)
    result = pipeline.record
    start = time.perf_counter()
    try:
        with BagReader(bag) as reader:
            topics = reader.topics()
            if cloud_topic not in topics:
                raise BagError(f'{bag}: no {cloud_topic} topic (topics: {", ".join(sorted(topics)) or "none"})')
            wanted = [cloud_topic] + ([imu_topic] if imu_topic and imu_topic in topics else [])
            total = reader.topic_counts().get(cloud_topic, 0)
            result.bag_duration = reader.duration
            bar = None
            if progress:
                from tqdm import tqdm
                bar = tqdm(total=min(total, max_scans or total), unit='scan', desc='run', file=sys.stderr,
                           dynamic_ncols=True, mininterval=0.5)
            first_ns = None
            try:
                for message in reader.messages(topics=wanted):
                    if message.topic == cloud_topic and max_scans is not None and \
                            result.counts.get('scans_in', 0) >= max_scans:
                        # The data processed ends here: the real-time factor is about that part of the bag.
                        result.bag_duration = (message.timestamp - first_ns) * 1e-9 if first_ns is not None else 0.0
                        break
                    first_ns = message.timestamp if first_ns is None else first_ns
                    msg = reader.deserialize(message)
                    stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
                    if message.topic != cloud_topic:
                        pipeline.add_imu(imu_sample(msg))
                        continue
                    try:
                        points = cloud_msg_to_array(msg)
                    except CloudLayoutError as exc:
                        pipeline.skip_scan(stamp, str(exc))
                    else:
                        pipeline.process_scan(points, stamp)
                    if bar is not None:
                        bar.update(1)
            finally:
                if bar is not None:
                    bar.close()
            pipeline.finish()
    finally:
        pipeline.close()
    result.wall_time = time.perf_counter() - start
    return result


def loop_closures_of(result: RunResult, params: Params) -> LoopClosures | None:
    """The loops of a run for its summary (None when loop closure was off or nothing was mapped)."""
    mapper = result.mapper
    if mapper is None or not params.loop_closure.loop_closure_enable_flag or not mapper.keyframes:
        return None
    return LoopClosures.of(mapper.loops, mapper.keyframes[0].stamp_ns)


def write_optimized_trajectory(out: Path, bag: str | Path, result: RunResult, summary: OfflineSummary) -> None:
    """``trajectory_optimized.tum`` (REP-103 map axes): the fused trajectory in the pose graph's final frame, and
    its accuracy in the summary when a ground truth is beside the bag."""
    from lego_loam_py.core.io import write_tum_atomic
    from lego_loam_py.evaluation import evaluate
    from lego_loam_py.outputs import write_summary
    from lego_loam_py.sim.output import load_ground_truth

    stamps, poses = result.optimized_trajectory()
    write_tum_atomic(out / 'trajectory_optimized.tum', stamps, poses)
    ground_truth = load_ground_truth(bag)
    if ground_truth is not None:
        try:
            summary.outputs.accuracy_optimized = evaluate(ground_truth, (stamps, poses))
        except ValueError:
            pass   # (the published trajectory's accuracy_error says why)
    write_summary(out, summary)


def format_summary(summary: OfflineSummary) -> str:
    """The report of ``lego_loam_py run``, as printed at the end of a run."""
    lines = [f"bag: {summary.bag}"]
    c = summary.counts   # (a counter the run never touched is 0)
    lines.append(f"scans in {c.get('scans_in', 0)}, processed {c.get('scans_processed', 0)}, dropped "
                 f"{c.get('scans_dropped', 0)}; mapping steps {c.get('mapping_steps', 0)}, keyframes "
                 f"{c.get('keyframes', 0)}, IMU used on {c.get('scans_with_imu', 0)} scans")
    for name, t in summary.timings_ms.items():
        lines.append(f"  {name:<20s} median {t.median:7.1f} ms   p95 {t.p95:7.1f} ms   (n={t.count})")
    lines.append(f"{summary.bag_duration_s:.1f} s of data in {summary.wall_time_s:.1f} s: "
                 f"{summary.realtime_factor:.2f}x real time")
    if summary.loop_closures is not None:
        lines.extend(summary.loop_closures.lines())
    lines.extend(result_lines(summary.outputs))
    return '\n'.join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lego_loam_py.cli import add_parameter_arguments

    parser.add_argument('bag', help='ROS 1 .bag or ROS 2 bag directory with PointCloud2 (and optionally Imu)')
    parser.add_argument('-o', '--output', default=None, help='output directory (default: output/<bag name>)')
    add_parameter_arguments(parser, 'ROS 2 parameter file (default: built-in defaults)',
                            'loop_closure.loop_closure_enable_flag:=true')
    parser.add_argument('--no-imu', action='store_true', help='ignore the IMU topic')
    parser.add_argument('--max-scans', type=_positive_int, default=None, help='stop after this many scans')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f'must be at least 1, got {value}')
    return value


def main(args: argparse.Namespace) -> int:
    keep_heap_pages()   # as the nodes do (see lego_loam_py.allocator)
    params = load_params(args.params_file, parse_overrides(args.param))
    out = Path(args.output or Path('output') / Path(args.bag).resolve().name)
    result = run_bag(args.bag, params, imu_topic='' if args.no_imu else None, max_scans=args.max_scans,
                     progress=not args.no_progress)
    stamps, _ = result.trajectory()
    summary = OfflineSummary(bag=str(args.bag), counts=result.counts,
                             timings_ms={name: TimingStats.of(v) for name, v in result.timings_ms.items() if v},
                             wall_time_s=result.wall_time, bag_duration_s=result.bag_duration,
                             loop_closures=loop_closures_of(result, params))
    write_outputs(out, args.bag, stamps, np.array(result.integrated), result.mapper, summary, params)
    if summary.loop_closures is not None and summary.loop_closures.accepted and len(stamps) >= 3:
        write_optimized_trajectory(out, args.bag, result, summary)
    print(format_summary(summary))
    written = sorted(p.name + ('/' if p.is_dir() else '') for p in out.iterdir() if not p.name.startswith('.'))
    print(f'outputs in {out}/: {", ".join(written)}')
    return 0
