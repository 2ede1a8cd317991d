"""``lego_loam_py run BAG``: the four nodes' cores in one process, without DDS, as fast as the machine goes.

Messages are taken in recording order, as a replay delivers them: IMU samples go to featureAssociation and
mapOptimization, each cloud goes through imageProjection -> featureAssociation -> transformFusion, and the
'last' clouds to mapOptimization, whose result corrects the fused poses of the following scans (in the
running system /aft_mapped_to_init of a scan arrives after that scan's /integrated_to_init). Loop closure,
when enabled, runs every ``loop_closure.period`` seconds of bag time. The outputs are those of the demo:
trajectories (TUM, REP-103 and camera_init axes), maps (PCD), a PNG and a summary with the accuracy against
the ground truth found beside the bag.

mapOptimization runs on a worker thread beside imageProjection and featureAssociation (see :func:`run_bag`);
the result is identical to a sequential run, and its ms per mapping step are the worker's CPU time.
"""
from __future__ import annotations

import argparse
import sys
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lego_loam_py.bag.io import BagError, BagReader, cloud_msg_to_array
from lego_loam_py.core.feature_association import FeatureAssociation, ScanInput
from lego_loam_py.core.frames import camera_pose_to_lidar, pose6_to_matrix
from lego_loam_py.core.image_projection import ImageProjection, InputError, prepare_input
from lego_loam_py.core.imu import imu_sample
from lego_loam_py.core.map_optimization import MapOptimization
from lego_loam_py.core.odometry_continuity import OdometryContinuity
from lego_loam_py.core.params import Params, load_params, parse_overrides
from lego_loam_py.core.pointcloud import CloudLayoutError
from lego_loam_py.core.transform_fusion import TransformFusion
from lego_loam_py.outputs import pose_time_offset_ns, result_lines, write_outputs

__all__ = ['RunResult', 'run_bag', 'format_summary', 'add_arguments', 'main']


@dataclass
class RunResult:
    """Everything a run produced; poses are 4x4 in camera_init (LOAM camera axes)."""

    stamps: list[int] = field(default_factory=list)            # scans with an odometry pose
    integrated: list[np.ndarray] = field(default_factory=list)  # /integrated_to_init
    odometry: list[np.ndarray] = field(default_factory=list)    # /laser_odom_to_init
    mapped_stamps: list[int] = field(default_factory=list)
    mapped: list[np.ndarray] = field(default_factory=list)      # /aft_mapped_to_init
    timings_ms: dict[str, list[float]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    wall_time: float = 0.0
    bag_duration: float = 0.0
    mapper: MapOptimization | None = None
    pose_time_offset_ns: int = 0   # the original odometry model's pose of scan k is the sensor's at k + one sweep

    def count(self, name: str, amount: int = 1) -> None:
        self.counts[name] = self.counts.get(name, 0) + amount

    def time(self, name: str, ms: float) -> None:
        self.timings_ms.setdefault(name, []).append(ms)

    def trajectory(self, axes: str = 'map', which: str = 'integrated') -> tuple[np.ndarray, np.ndarray]:
        """(stamps [ns] of the sensor poses, poses) of the fused ('integrated') or odometry ('odometry')
        trajectory; ``axes`` 'map' (REP-103) or 'camera_init'. Stamps include the model's pose time offset."""
        poses = np.array(self.integrated if which == 'integrated' else self.odometry).reshape(-1, 4, 4)
        if axes == 'map':
            poses = np.array([camera_pose_to_lidar(p) for p in poses]).reshape(-1, 4, 4)
        return np.array(self.stamps, dtype=np.int64) + self.pose_time_offset_ns, poses


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
    ip, fa = ImageProjection(params), FeatureAssociation(params)
    mo, fusion = MapOptimization(params), TransformFusion()
    result = RunResult(mapper=mo if mapping else None)
    result.pose_time_offset_ns = pose_time_offset_ns(params)
    back_end = _BackEnd(mo if mapping else None, fusion, result, threaded=mapping and mapping_thread)
    lc = params.loop_closure
    next_loop_check = None
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
                        sample = imu_sample(msg)
                        if fa.add_imu(*sample) is not None:
                            result.count('imu_rejected')
                        back_end.add_imu(sample)
                        continue
                    result.count('scans_in')
                    _one_scan(msg, stamp, params, ip, fa, back_end, result)
                    if mapping and lc.loop_closure_enable_flag:
                        if next_loop_check is None:
                            next_loop_check = stamp + int(lc.period * 1e9)
                        elif stamp >= next_loop_check:
                            next_loop_check = stamp + int(lc.period * 1e9)
                            back_end.loop_closure()
                    back_end.drain()
                    if bar is not None:
                        bar.update(1)
                back_end.drain(wait=True)
            finally:
                if bar is not None:
                    bar.close()
    finally:
        back_end.close()
    result.wall_time = time.perf_counter() - start
    result.counts['keyframes'] = len(mo.keyframes) if mapping else 0
    return result


def _one_scan(msg, stamp: int, params: Params, ip, fa, back_end: '_BackEnd', result: RunResult) -> None:
    t0 = time.perf_counter()
    try:
        points = cloud_msg_to_array(msg)
        data = prepare_input(points, params)
        segmentation = ip.process(data)
    except (CloudLayoutError, InputError) as exc:
        result.count('scans_dropped')
        print(f'warning: scan at {stamp * 1e-9:.3f} s dropped: {exc}', file=sys.stderr)
        return
    t1 = time.perf_counter()
    result.time('imageProjection', (t1 - t0) * 1e3)
    features = fa.process(ScanInput(stamp, segmentation.segmented_cloud, segmentation.cloud_info,
                                    segmentation.outlier_cloud, segmentation.segmented_time))
    result.time('featureAssociation', (time.perf_counter() - t1) * 1e3)
    problem = fa.health_problem()
    if problem is not None:   # the same self-check as the node's: start the odometry again, keep the pose
        fa.restart()
        result.count('state_resets')
        result.count('scans_dropped')
        print(f'warning: scan at {stamp * 1e-9:.3f} s: {problem}: odometry restarted', file=sys.stderr)
        return
    result.count('scans_processed')
    if features.imu_used:
        result.count('scans_with_imu')
    if not features.initialized:
        result.stamps.append(stamp)
        result.odometry.append(features.pose)
        back_end.fuse(features.pose)
    if features.corner_last is not None and features.outlier_last is not None:
        back_end.map(stamp, features.transform_sum, features.corner_last, features.surf_last,
                     features.outlier_last)


class _BackEnd:
    """mapOptimization and transformFusion of the offline run, in recording order.

    Work for mapOptimization (IMU samples, mapping inputs, loop-closure checks) goes to one worker thread in
    the order it arrives; transformFusion's events (fuse a scan's odometry, take a mapping result) are queued in
    the same order and applied by :meth:`drain` as their results become available. So every scan is fused
    with exactly the mapping results of the scans before it, whether the worker is a thread or not.
    """

    def __init__(self, mo: MapOptimization | None, fusion: TransformFusion, result: RunResult, threaded: bool):
        self.mo, self.fusion, self.result = mo, fusion, result
        self.continuity = OdometryContinuity()   # (used on the mapping worker only)
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix='mapping') if threaded else None
        self._imu: list[tuple] = []
        self._events: deque = deque()

    def _submit(self, job) -> Future:
        imu, self._imu = self._imu, []

        def with_imu():
            for sample in imu:   # the IMU samples that arrived before this job, as in the sequential run
                self.mo.imu.add(*sample)
            return job()

        if self._executor is not None:
            return self._executor.submit(with_imu)
        future = Future()
        future.set_result(with_imu())
        return future

    def add_imu(self, sample: tuple) -> None:
        if self.mo is not None:
            self._imu.append(sample)

    def fuse(self, odometry: np.ndarray) -> None:
        self._events.append(('fuse', odometry))
        self.drain()

    def map(self, stamp: int, *inputs) -> None:
        if self.mo is None:
            return

        def step():
            # CPU time of the thread: on the worker, wall time would also count the waits for the GIL while
            # the main thread runs the next scans.
            t = time.thread_time()
            transform_sum = inputs[0]
            pose = pose6_to_matrix(transform_sum)
            jump = self.continuity.check(stamp, pose)
            if jump is not None:   # the same protection as the node's: continue the map, do not drag it
                print(f'warning: mapping input at {stamp * 1e-9:.3f} s: {jump.describe()}', file=sys.stderr)
                self.mo.reanchor(jump, pose, transform_sum)
            mapped = self.mo.process(stamp, *inputs)
            problem = self.mo.health_problem() if mapped is not None else None
            if problem is not None:   # the same self-check as the node's: reset what is poisoned, keep the map
                print(f'warning: mapping step at {stamp * 1e-9:.3f} s: {problem}: {self.mo.heal()}', file=sys.stderr)
                mapped = None
            return mapped, (time.thread_time() - t) * 1e3

        self._events.append(('map', stamp, self._submit(step)))

    def loop_closure(self) -> None:
        def close():
            t = time.perf_counter()
            candidate = self.mo.detect_loop()
            loop = self.mo.close_loop(candidate) if candidate is not None else None
            return loop, (time.perf_counter() - t) * 1e3

        self._events.append(('loop', self._submit(close)))

    def drain(self, wait: bool = False) -> None:
        """Apply the queued events whose results are ready (all of them, waiting, with ``wait``)."""
        result = self.result
        while self._events:
            event = self._events[0]
            if event[0] != 'fuse' and not wait and not event[-1].done():
                return
            self._events.popleft()
            if event[0] == 'fuse':
                result.integrated.append(self.fusion.integrate(event[1]))
            elif event[0] == 'map':
                step, ms = event[2].result()
                if step is not None:
                    result.time('mapOptimization', ms)
                    result.count('mapping_steps')
                    aft, bef = pose6_to_matrix(step.transform_aft), pose6_to_matrix(step.transform_bef)
                    self.fusion.on_mapped(aft, bef)
                    result.mapped_stamps.append(event[1])
                    result.mapped.append(aft)
            else:
                loop, ms = event[1].result()
                if loop is not None:
                    result.count('loops_closed' if loop.accepted else 'loops_rejected')
                result.time('loop_closure', ms)

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)


def _timing_table(timings: dict[str, list[float]]) -> dict[str, dict[str, float]]:
    return {name: dict(median=float(np.median(v)), p95=float(np.percentile(v, 95)), mean=float(np.mean(v)),
                       count=len(v)) for name, v in timings.items() if v}


def format_summary(summary: dict) -> str:
    lines = [f"bag: {summary['bag']}"]
    c = summary.get('counts', {})
    lines.append(f"scans in {c.get('scans_in', 0)}, processed {c.get('scans_processed', 0)}, dropped "
                 f"{c.get('scans_dropped', 0)}; mapping steps {c.get('mapping_steps', 0)}, keyframes "
                 f"{c.get('keyframes', 0)}, IMU used on {c.get('scans_with_imu', 0)} scans")
    for name, t in summary.get('timings_ms', {}).items():
        lines.append(f"  {name:<20s} median {t['median']:7.1f} ms   p95 {t['p95']:7.1f} ms   (n={t['count']})")
    if 'realtime_factor' in summary:
        lines.append(f"{summary['bag_duration_s']:.1f} s of data in {summary['wall_time_s']:.1f} s: "
                     f"{summary['realtime_factor']:.2f}x real time")
    lines.extend(result_lines(summary))
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
    params = load_params(args.params_file, parse_overrides(args.param))
    out = Path(args.output or Path('output') / Path(args.bag).resolve().name)
    result = run_bag(args.bag, params, imu_topic='' if args.no_imu else None, max_scans=args.max_scans,
                     progress=not args.no_progress)
    stamps, _ = result.trajectory()
    summary = dict(bag=str(args.bag), mode='offline', counts=result.counts, timings_ms=_timing_table(result.timings_ms),
                   wall_time_s=result.wall_time, bag_duration_s=result.bag_duration,
                   realtime_factor=result.bag_duration / result.wall_time if result.wall_time > 0 else float('nan'))
    summary = write_outputs(out, args.bag, stamps, np.array(result.integrated), result.mapper, summary, params)
    print(format_summary(summary))
    written = sorted(p.name + ('/' if p.is_dir() else '') for p in out.iterdir() if not p.name.startswith('.'))
    print(f'outputs in {out}/: {", ".join(written)}')
    return 0
