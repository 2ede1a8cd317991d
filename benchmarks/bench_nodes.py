"""Per-scan cost of each node's core and of the imageProjection callback with conversions.

    .venv/bin/python benchmarks/bench_nodes.py [--scans 100] [--quick]

Prints median and p95 ms per scan for:
* imageProjection core on real VLP-16 scans (the golden recordings) and simulated VLP-16 / HDL-64E scans,
  and the whole node callback (PointCloud2 -> numpy, the core, four messages built and published);
* featureAssociation (features + odometry) on simulated campus scans, with and without IMU;
* mapOptimization per mapping step on the campus loop (its first lap, and two laps), and its cost and
  memory as keyframes accumulate (100, 500, 1000 keyframes).
Targets (issues): imageProjection core <= 10 ms, callback <= 20 ms; featureAssociation <= 25 ms; mapping
<= 100 ms per step on the campus scenario.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import summary  # noqa: E402

from lego_loam_py.bag.io import BagReader, cloud_msg_to_array  # noqa: E402
from lego_loam_py.core.mapping.map_optimization import MapOptimization  # noqa: E402
from lego_loam_py.core.odometry.feature_association import FeatureAssociation, ScanInput  # noqa: E402
from lego_loam_py.core.params import Params  # noqa: E402
from lego_loam_py.core.projection.image_projection import ImageProjection, ProjectionInput, prepare_input  # noqa: E402
from lego_loam_py.sim.simulator import cached_scenario  # noqa: E402

CAMPUS_LAP_S = 238.7
CAMPUS_TWO_LAPS_S = 478.0
SHARED = Path(os.environ.get('LEGO_LOAM_SHARED', ROOT.parent / 'shared')) / 'data'


def bag_scans(bag, count):
    """(clouds as structured arrays, IMU samples) of the first ``count`` scans of a bag, in order."""
    items = []
    with BagReader(bag) as reader:
        n = 0
        for message in reader.messages():
            msg = reader.deserialize(message)
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            if message.msgtype.endswith('PointCloud2'):
                n += 1
                if n > count:
                    break
                items.append(('cloud', stamp, cloud_msg_to_array(msg).copy()))
            elif message.msgtype.endswith('Imu'):
                o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
                items.append(('imu', stamp, (stamp * 1e-9, (o.x, o.y, o.z, o.w), (w.x, w.y, w.z), (a.x, a.y, a.z))))
    return items


def time_each(function, inputs):
    out = []
    for x in inputs:
        start = time.perf_counter()
        function(x)
        out.append((time.perf_counter() - start) * 1e3)
    return np.array(out)


def bench_image_projection(scans: int) -> None:
    print('== imageProjection')
    params = Params()
    ip = ImageProjection(params)
    golden = SHARED / 'golden' / 'vlp16_single_rotation.npz'
    if golden.is_file():
        g = np.load(golden)
        data = ProjectionInput(xyz=g['s0_input'][:, :3].copy(), ring=g['s0_input'][:, 4].astype(np.int64))
        for _ in range(3):
            ip.process(data)
        print(summary('core, real VLP-16 scan (28385 points)', time_each(ip.process, [data] * 50)))
    for preset in ('VLP-16', 'HDL-64E'):
        p = params.replace(sensor__preset=preset)
        core = ImageProjection(p)
        bag = cached_scenario('campus', duration=max(2.0, scans / 10 + 1), preset=preset)
        clouds = [c for kind, _, c in bag_scans(bag, scans) if kind == 'cloud']
        inputs = [prepare_input(c, p) for c in clouds]
        core.process(inputs[0])
        print(
            summary(
                f'core, simulated {preset} campus ({np.mean([len(c) for c in clouds]):.0f} points)',
                time_each(core.process, inputs),
            )
        )
    # The node callback with conversions, in-process (no subscriber: publishing costs the message build).
    import rclpy
    from rclpy.context import Context

    from lego_loam_py.ros.conversions import array_to_cloud_msg, make_header
    from lego_loam_py.ros.image_projection_node import ImageProjectionNode
    from lego_loam_py.testing.domains import DomainLease

    bag = cached_scenario('campus', duration=max(2.0, scans / 10 + 1))
    clouds = [c for kind, _, c in bag_scans(bag, scans) if kind == 'cloud']
    messages = [array_to_cloud_msg(c, make_header(k * 100_000_000, 'velodyne')) for k, c in enumerate(clouds)]
    with DomainLease() as domain:
        context = Context()
        rclpy.init(context=context, domain_id=domain)
        try:
            node = ImageProjectionNode(context=context)
            node.on_cloud(messages[0])
            print(summary('node callback: conversions + core + publishing', time_each(node.on_cloud, messages)))
            node.destroy_node()
        finally:
            rclpy.try_shutdown(context=context)


def bench_feature_association(scans: int) -> None:
    print('== featureAssociation (features + odometry)')
    params = Params()
    bag = cached_scenario('campus', duration=max(2.0, scans / 10 + 1))
    items = bag_scans(bag, scans)
    ip = ImageProjection(params)
    prepared = []
    for kind, stamp, value in items:
        if kind == 'cloud':
            r = ip.process(prepare_input(value, params))
            prepared.append(('cloud', ScanInput.from_segmentation(stamp, r)))
        else:
            prepared.append(('imu', value))
    for use_imu in (False, True):
        fa = FeatureAssociation(params)
        times, features, odometry = [], [], []
        for kind, value in prepared:
            if kind == 'imu':
                if use_imu:
                    fa.add_imu(*value)
                continue
            start = time.perf_counter()
            result = fa.process(value)
            times.append((time.perf_counter() - start) * 1e3)
            features.append(result.timings_ms.get('features', np.nan))
            odometry.append(result.timings_ms.get('odometry', np.nan))
        label = 'with IMU' if use_imu else 'without IMU'
        print(summary(f'scan, {label}', np.array(times[1:])))
        print(summary(f'  features, {label}', np.array(features[1:])))
        print(summary(f'  odometry, {label}', np.array(odometry[1:])))


def bench_mapping(quick: bool) -> None:
    print('== mapOptimization')
    from lego_loam_py.offline import run_bag

    # Two laps of the campus loop (about 1200 keyframes; on the second lap the map around the car holds both
    # laps' keyframes): the cost and memory at 100, 500 and 1000 keyframes. Sequential, so that the step
    # times are the mapping's own, not shared with the other cores on the offline run's threads.
    bag = cached_scenario('campus', duration=30.0 if quick else CAMPUS_TWO_LAPS_S)
    process = _instrument_mapping()
    result = run_bag(bag, Params(), progress=False, mapping_thread=False)
    steps = process['steps']
    times = np.array([t for t, _, _ in steps])
    print(summary('mapping step, campus', times))
    stamps = np.array(process['stamps'], dtype=np.int64)
    first_lap = times[(stamps - stamps[0]) * 1e-9 < CAMPUS_LAP_S]
    if len(first_lap) < len(times):
        print(summary('mapping step, campus, first lap', first_lap))
    keyframes = np.array([k for _, k, _ in steps])
    memory = np.array([m for _, _, m in steps]) / 2**20
    for target in (100, 500, 1000):
        near = np.flatnonzero((keyframes >= target * 0.9) & (keyframes <= target * 1.1))
        if len(near):
            print(
                f'  at ~{target:4d} keyframes: step median {np.median(times[near]):6.1f} ms, '
                f'process RSS {np.median(memory[near]):7.1f} MiB ({np.median(memory[near]) - memory[0]:+6.1f} '
                f'MiB since the first step)'
            )
    print(
        f'  {result.counts.get("keyframes", 0)} keyframes, {len(steps)} steps, offline '
        f'{result.bag_duration / result.wall_time:.2f}x real time'
    )


def rss_bytes() -> int:
    """Resident set size of this process (from /proc)."""
    with open('/proc/self/status') as status:
        for line in status:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) * 1024
    return 0


def _instrument_mapping():
    """Record (ms, keyframes, RSS bytes) of every mapping step."""
    record = {'steps': [], 'stamps': []}
    original = MapOptimization.process

    def timed(self, *args, **kwargs):
        start = time.perf_counter()
        step = original(self, *args, **kwargs)
        if step is not None:
            record['steps'].append(((time.perf_counter() - start) * 1e3, len(self.keyframes), rss_bytes()))
            record['stamps'].append(step.stamp_ns)
        return step

    MapOptimization.process = timed
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scans', type=int, default=100)
    parser.add_argument('--quick', action='store_true', help='mapping on 30 s only (no 1000-keyframe figures)')
    parser.add_argument('--only', choices=['ip', 'fa', 'mo'], default=None)
    args = parser.parse_args()
    if args.only in (None, 'ip'):
        bench_image_projection(args.scans)
    if args.only in (None, 'fa'):
        bench_feature_association(args.scans)
    if args.only in (None, 'mo'):
        bench_mapping(args.quick)


if __name__ == '__main__':
    main()
