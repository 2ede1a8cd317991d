"""The never-silent campaign over DDS (issue 14): malformed input on every subscribed topic, judged from outside.

    .venv/bin/python benchmarks/campaign.py [--per-topic 5000] [--burst 250] [--out DIR]   # the full campaign
    .venv/bin/python benchmarks/campaign.py --short                                      # about a minute
    .venv/bin/python benchmarks/campaign.py --cases                                      # the issue's four cases

The four nodes run as processes (``ros2 run`` executables) on a leased ROS_DOMAIN_ID with loopback discovery.
This process feeds them the committed campus recording one scan at a time (lockstep: the next scan once the
previous one's /integrated_to_init is out, or after 2 s) and, between those scans, bursts of malformed
messages on each topic a node subscribes to, from ``lego_loam_py/testing/malformed.py`` (every field of every
message type: boundary and absurd values, broken layouts, other lengths, stamps far away; a few clouds of
2,000,000 points). After each burst the valid scans resume, and for every node it measures:

* inputs sent per topic, and taken by the node (its ``received <topic>`` counter on /diagnostics);
* crashes (a process that exited), non-finite outputs (any pose or cloud published with NaN/inf);
* silent periods: a resumption after which a node published nothing for 20 valid scans (the nodes' own
  watchdog threshold, ``reliability.watchdog_inputs``: 2 s of data);
* the recovery: from the first valid scan after a burst to the node's first output for valid input, in
  seconds and in valid scans (lockstep waits up to 2 s for a scan that gives no fused pose, so a scan lost to a
  wrong stamp costs 2 s here; at the sensor's rate it costs 0.1 s);
* resident memory before the campaign, its peak, and after it (from /proc).

It prints a table and writes ``summary.json`` into ``--out``. Nothing leaves 127.0.0.1.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lego_loam_py.formats import pcd_is_complete  # noqa: E402
from lego_loam_py.orchestration import NODES as PIPELINE_NODES  # noqa: E402
from lego_loam_py.testing.domains import DomainLease  # noqa: E402
from lego_loam_py.testing.malformed import MUTATORS  # noqa: E402
from lego_loam_py.testing.measure import rss_mb  # noqa: E402
from lego_loam_py.testing.messages import restamped, stamp_of  # noqa: E402
from lego_loam_py.testing.nodes import spin_in_background  # noqa: E402

BIN = Path(sys.executable).parent
BAG = REPO / 'bags' / 'campus_8s'
NODES = tuple(PIPELINE_NODES)  # the four executables, in pipeline order
OUTPUT = {
    'imageProjection': '/segmented_cloud',
    'featureAssociation': '/laser_odom_to_init',
    'mapOptimization': '/aft_mapped_to_init',
    'transformFusion': '/integrated_to_init',
}
SUBSCRIBERS = {  # topic -> the nodes that subscribe to it
    '/velodyne_points': ('imageProjection',),
    '/segmented_cloud': ('featureAssociation',),
    '/segmented_cloud_info': ('featureAssociation',),
    '/outlier_cloud': ('featureAssociation',),
    '/imu/data': ('featureAssociation', 'mapOptimization'),
    '/laser_cloud_corner_last': ('mapOptimization',),
    '/laser_cloud_surf_last': ('mapOptimization',),
    '/outlier_cloud_last': ('mapOptimization',),
    '/laser_odom_to_init': ('mapOptimization', 'transformFusion'),
    '/aft_mapped_to_init': ('transformFusion',),
}
CLOUD_TOPICS = (
    '/velodyne_points',
    '/segmented_cloud',
    '/outlier_cloud',
    '/laser_cloud_corner_last',
    '/laser_cloud_surf_last',
    '/outlier_cloud_last',
)
RESUME_SCANS = 8  # valid scans after each burst (0.8 s of data) ...
SILENT_SCANS = 20  # ... and up to this many while a node is still without output (the nodes' watchdog)
SCAN_TIMEOUT_S = 2.0  # lockstep: the next scan after this long without the previous one's fused pose


def message_type(topic: str):
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu, PointCloud2

    from cloud_msgs.msg import CloudInfo

    if topic == '/segmented_cloud_info':
        return CloudInfo
    if topic == '/imu/data':
        return Imu
    if topic in ('/laser_odom_to_init', '/aft_mapped_to_init', '/integrated_to_init'):
        return Odometry
    return PointCloud2


def finite(msg) -> bool:
    if hasattr(msg, 'pose'):
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        return bool(np.isfinite([p.x, p.y, p.z, q.x, q.y, q.z, q.w]).all())
    from lego_loam_py.ros.conversions import cloud_msg_to_xyzi

    return bool(np.isfinite(cloud_msg_to_xyzi(msg)).all())


class Campaign:
    """The four nodes as processes, and this process's publishers, listener and memory sampler."""

    def __init__(self, out: Path, domain: int):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        from lego_loam_py.ros import qos
        from lego_loam_py.testing.nodes import Diagnostics

        self.out = out
        (out / 'logs').mkdir(parents=True, exist_ok=True)
        params = out / 'params.yaml'
        params.write_text(f'/**:\n  ros__parameters:\n    map_optimization:\n      file_directory: {out / "maps"}\n')
        env = dict(
            os.environ,
            ROS_DOMAIN_ID=str(domain),
            ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
            LEGO_LOAM_PY_STATS_DIR=str(out / 'stats'),
        )
        self.procs = {}
        for name in NODES:
            with open(out / 'logs' / f'{name}.log', 'w') as log:
                self.procs[name] = subprocess.Popen(
                    [str(BIN / name), '--ros-args', '--params-file', str(params)],
                    stdout=log,
                    stderr=log,
                    env=env,
                    start_new_session=True,
                )
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node('campaign', context=self.context)
        self.lock = threading.Lock()
        self.outputs: dict[str, list] = {n: [] for n in NODES}  # (arrival, stamp) of every output
        self.non_finite: dict[str, int] = defaultdict(int)
        self.templates: dict[str, list] = defaultdict(list)  # valid messages of every topic
        self.fused = threading.Condition(self.lock)
        self._own: dict[str, set] = {}  # topic -> DDS ids of this process's publishers (its own messages)
        for name, topic in OUTPUT.items():
            self.node.create_subscription(
                message_type(topic), topic, lambda m, info, _n=name: self._on_output(_n, m, info), qos.reliable(100)
            )
        for topic in SUBSCRIBERS:
            if topic not in OUTPUT.values() and topic not in ('/velodyne_points', '/imu/data'):
                self.node.create_subscription(
                    message_type(topic), topic, lambda m, info, _t=topic: self._keep(_t, m, info), qos.reliable(10)
                )
        self.diagnostics = Diagnostics(self.node)
        self.publishers = {
            topic: self.node.create_publisher(message_type(topic), topic, qos.reliable(100)) for topic in SUBSCRIBERS
        }
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._spinner = spin_in_background(self.executor, self._stop)
        self.peak: dict[str, float] = defaultdict(float)
        self._sampler = threading.Thread(target=self._sample, daemon=True)
        self._sampler.start()
        self._load_bag()

    # ------------------------------------------------------------------------------------------ plumbing
    def _sample(self) -> None:
        while not self._stop.wait(0.2):
            for name, proc in self.procs.items():
                value = rss_mb(proc.pid)
                if math.isfinite(value):
                    self.peak[name] = max(self.peak[name], value)

    def _from_here(self, topic: str, info) -> bool:
        """Whether a message on ``topic`` came from this process (the malformed ones it sends itself)."""
        gid = info.get('publisher_gid') if isinstance(info, dict) else None
        data = bytes(gid['data']) if isinstance(gid, dict) and gid.get('data') is not None else None
        if data is None:
            return False
        if data not in self._own.get(topic, set()):
            self._own[topic] = {
                bytes(i.endpoint_gid)
                for i in self.node.get_publishers_info_by_topic(topic)
                if i.node_name == 'campaign'
            }
        return data in self._own[topic]

    def _on_output(self, node: str, msg, info) -> None:
        if self._from_here(OUTPUT[node], info):
            return
        ok = finite(msg)
        with self.lock:
            self.outputs[node].append((time.monotonic(), stamp_of(msg)))
            if not ok:
                self.non_finite[node] += 1
            self.fused.notify_all()
        self._keep(OUTPUT[node], msg)

    def _keep(self, topic: str, msg, info=None) -> None:
        if info is not None and self._from_here(topic, info):
            return
        with self.lock:
            if len(self.templates[topic]) < 8:
                self.templates[topic].append(msg)

    def _load_bag(self) -> None:
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import Imu, PointCloud2

        from lego_loam_py.bag.io import BagReader

        self.scans: list[tuple[object, list]] = []  # (cloud, IMU samples recorded before it)
        imu = []
        with BagReader(BAG) as reader:
            self.lap_ns = reader.end_time - reader.start_time + 100_000_000
            for m in reader.messages(topics=['/velodyne_points', '/imu/data']):
                if m.topic == '/imu/data':
                    imu.append(deserialize_message(bytes(m.data), Imu))
                else:
                    self.scans.append((deserialize_message(bytes(m.data), PointCloud2), imu))
                    imu = []
        self.templates['/velodyne_points'] = [cloud for cloud, _ in self.scans[:8]]
        self.templates['/imu/data'] = self.scans[1][1][:8]
        self.next_scan = 0

    def wait_ready(self, timeout: float = 90.0) -> None:
        deadline = time.monotonic() + timeout
        internal = [t for t in SUBSCRIBERS if t not in ('/velodyne_points', '/imu/data')]
        while time.monotonic() < deadline:
            dead = self.crashed()
            if dead:
                raise RuntimeError(f'{dead} exited: {self.log(dead[0])[-2000:]}')
            if all(self.node.count_publishers(t) > 0 for t in OUTPUT.values()) and all(
                self.node.count_subscribers(t) >= (2 if t in internal else 1) for t in SUBSCRIBERS
            ):
                return
            time.sleep(0.1)
        raise RuntimeError('the nodes did not come up')

    def crashed(self) -> list[str]:
        return [name for name, proc in self.procs.items() if proc.poll() is not None]

    def log(self, name: str) -> str:
        return (self.out / 'logs' / f'{name}.log').read_text()

    def rss(self) -> dict[str, float]:
        return {name: round(rss_mb(proc.pid), 1) for name, proc in self.procs.items()}

    # -------------------------------------------------------------------------------------------- input
    def clock_ns(self) -> int:
        """The stamp of the next valid scan (continuous over laps of the recording)."""
        lap, k = divmod(self.next_scan, len(self.scans))
        return stamp_of(self.scans[k][0]) + lap * self.lap_ns

    def feed(self, count: int, rate_hz: float | None = None) -> list[tuple[float, int]]:
        """``count`` valid scans, in lockstep or (``rate_hz``) at a sensor's rate; returns (time sent, stamp)."""
        sent = []
        start = time.monotonic()
        for index in range(count):
            lap, k = divmod(self.next_scan, len(self.scans))
            self.next_scan += 1
            cloud, imu = self.scans[k]
            offset = lap * self.lap_ns
            for sample in imu:
                self.publishers['/imu/data'].publish(restamped(sample, stamp_of(sample) + offset) if offset else sample)
            stamp = stamp_of(cloud) + offset
            with self.lock:
                count_before = len(self.outputs['transformFusion'])
            self.publishers['/velodyne_points'].publish(restamped(cloud, stamp) if offset else cloud)
            sent.append((time.monotonic(), stamp))
            if rate_hz is not None:
                delay = start + (index + 1) / rate_hz - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                continue
            with self.lock:
                self.fused.wait_for(
                    lambda: any(s >= stamp for _, s in self.outputs['transformFusion'][count_before:]),
                    timeout=SCAN_TIMEOUT_S,
                )
        return sent

    def burst(self, topic: str, count: int, rng, huge: int = 0, rate: float = 200.0) -> int:
        """``count`` malformed messages on ``topic`` (``huge`` of them clouds of 2,000,000 points), at most
        ``rate`` per second, stamped around the valid time (a generator may move a stamp far away)."""
        mutate = MUTATORS[topic]
        with self.lock:
            templates = list(self.templates[topic])
        if not templates:
            raise RuntimeError(f'no valid {topic} message seen to build malformed ones from')
        publisher = self.publishers[topic]
        clock = self.clock_ns()
        start = time.monotonic()
        for k in range(count):
            template = restamped(
                templates[int(rng.integers(len(templates)))], clock + int(rng.integers(-150_000_000, 150_000_000))
            )
            if k < huge:
                msg = mutate(rng, template, huge=True)
            else:
                msg = mutate(rng, template)
            publisher.publish(msg)
            delay = start + (k + 1) / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        return count

    def close(self) -> dict[str, int]:
        codes = {}
        for name, proc in self.procs.items():
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
            try:
                codes[name] = proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                codes[name] = proc.wait()
        self._stop.set()
        self._spinner.join(timeout=2)
        import rclpy

        from lego_loam_py.ros.runtime import finish_within

        finish_within(
            lambda: (
                self.executor.shutdown(timeout_sec=1),
                self.node.destroy_node(),
                rclpy.try_shutdown(context=self.context),
            ),
            'the campaign node shutdown',
            10.0,
        )
        return codes


# --------------------------------------------------------------------------------------------- campaign
def campaign(args) -> dict:
    out = Path(args.out)
    rng = np.random.default_rng(args.seed)
    started = time.monotonic()
    with DomainLease() as domain:
        run = Campaign(out, domain)
        try:
            run.wait_ready()
            run.feed(12)  # warm-up: every node has state to lose, every internal topic a template
            time.sleep(0.5)
            before = run.rss()
            report = {
                node: dict(sent={}, taken={}, crashes=0, silent_periods=0, non_finite_outputs=0, recovery_s=[])
                for node in NODES
            }
            taken_before = {node: dict(run.diagnostics.latest.get(node, {})) for node in NODES}
            for topic in SUBSCRIBERS:
                sent = 0
                huge = args.huge if topic in CLOUD_TOPICS else 0
                while sent < args.per_topic:
                    n = min(args.burst, args.per_topic - sent)
                    sent += run.burst(topic, n, rng, huge=huge if sent == 0 else 0)
                    with run.lock:
                        marks = {node: len(run.outputs[node]) for node in NODES}
                    resumed = run.feed(RESUME_SCANS)
                    time.sleep(0.3)

                    def quiet() -> list[str]:
                        valid = {s for _, s in resumed}
                        with run.lock:
                            return [
                                node
                                for node in NODES
                                if not any(s in valid for _, s in run.outputs[node][marks[node] :])
                            ]

                    # A node still without output gets more valid scans, up to the watchdog's 20: only then is it
                    # silent (a wrong stamp up to 1 s ahead legitimately costs a few scans, see StampOrder).
                    while quiet() and len(resumed) < SILENT_SCANS:
                        resumed += run.feed(1)
                    time.sleep(0.3)
                    first_valid = resumed[0][0]
                    valid = {s for _, s in resumed}
                    with run.lock:
                        for node in NODES:
                            after = [(t, s) for t, s in run.outputs[node][marks[node] :] if s in valid]
                            if after:
                                recovery = max(0.0, after[0][0] - first_valid)
                                report[node]['recovery_s'].append(recovery)
                                scans = [s for _, s in resumed].index(after[0][1]) + 1
                                report[node]['recovery_scans'] = max(report[node].get('recovery_scans', 0), scans)
                                worst = report[node].setdefault('slowest_recovery_by_topic', {})
                                worst[topic] = round(max(worst.get(topic, 0.0), recovery), 3)
                            else:
                                report[node]['silent_periods'] += 1
                                report[node].setdefault('silent_after', []).append(topic)
                    if run.crashed():
                        break
                for node in SUBSCRIBERS[topic]:
                    report[node]['sent'][topic] = sent
                print(f'{topic}: {sent} malformed messages sent', flush=True)
                if run.crashed():
                    break
            time.sleep(1.5)  # the last /diagnostics
            for node in NODES:
                latest = run.diagnostics.latest.get(node, {})
                for topic in report[node]['sent']:
                    key = f'received {topic}'
                    report[node]['taken'][topic] = int(latest.get(key, 0)) - int(taken_before[node].get(key, 0))
            after = run.rss()
            peak = dict(run.peak)
            keyframes = run.diagnostics.counter('mapOptimization', 'keyframes')
            crashed = run.crashed()
            with run.lock:
                non_finite = dict(run.non_finite)
            tracebacks = {name: run.log(name).count('Traceback') for name in NODES}
        finally:
            codes = run.close()
    for node in NODES:
        r = report[node]
        r['crashes'] = int(node in crashed)
        r['non_finite_outputs'] = non_finite.get(node, 0)
        r['memory_mb'] = dict(before=before[node], peak=round(peak.get(node, float('nan')), 1), after=after[node])
        r['recovery_s'] = dict(
            median=round(float(np.median(r['recovery_s'])), 3) if r['recovery_s'] else None,
            max=round(float(np.max(r['recovery_s'])), 3) if r['recovery_s'] else None,
            resumptions=len(r['recovery_s']),
        )
        r['exit_code'] = codes.get(node)
        r['tracebacks_logged'] = tracebacks[node]
    summary = dict(
        per_topic=args.per_topic,
        burst=args.burst,
        huge_per_cloud_topic=args.huge,
        nodes=report,
        valid_scans_fed=run.next_scan,
        map_keyframes=keyframes,
        wall_time_s=round(time.monotonic() - started, 1),
    )
    (out / 'summary.json').write_text(json.dumps(summary, indent=2))
    return summary


# ------------------------------------------------------------------------------------------------ cases
def _after_input(run: Campaign, node: str, send, expect: str, scans: int = 32) -> dict:
    """Send one bad input and wait until the node has handled it (``expect`` in its log), then ``scans`` valid
    scans at the sensor's rate: the node's recovery and memory."""
    with run.lock:
        mark = len(run.outputs[node])
    before = run.rss()[node]
    logged = run.log(node).count(expect)
    send()
    deadline = time.monotonic() + 60
    while run.log(node).count(expect) == logged and time.monotonic() < deadline:
        time.sleep(0.05)
    handled = run.log(node).count(expect) > logged
    resumed = run.feed(scans, rate_hz=10.0)  # the sensor's rate: what a robot would send meanwhile
    time.sleep(1.0)
    valid = {s for _, s in resumed}
    with run.lock:
        outputs = [(t, s) for t, s in run.outputs[node][mark:] if s in valid]
    first = outputs[0][0] - resumed[0][0] if outputs else None
    return dict(
        handled=handled,
        rss_before_mb=before,
        rss_peak_mb=round(run.peak[node], 1),
        rss_after_mb=run.rss()[node],
        valid_scans=scans,
        outputs_for_valid_scans=len(outputs),
        first_output_after_s=round(first, 3) if first is not None else None,
        warning=next((line for line in run.log(node).splitlines()[::-1] if expect in line), '')[-200:],
    )


def cases(args) -> dict:
    """The four cases of the issue, replayed over DDS."""
    from std_srvs.srv import Trigger

    out = Path(args.out)
    rng = np.random.default_rng(args.seed)
    results = {}
    with DomainLease() as domain:
        run = Campaign(out, domain)
        try:
            run.wait_ready()
            run.feed(12)
            time.sleep(0.5)

            def orientation_diff_1e30():
                stamp = run.clock_ns() - 50_000_000  # between the last valid scan and the next
                with run.lock:
                    cloud = run.templates['/segmented_cloud'][-1]
                    info = run.templates['/segmented_cloud_info'][-1]
                    outlier = run.templates['/outlier_cloud'][-1]
                info = restamped(info, stamp)
                info.orientation_diff = 1e-30
                for topic, msg in (
                    ('/segmented_cloud', restamped(cloud, stamp)),
                    ('/segmented_cloud_info', info),
                    ('/outlier_cloud', restamped(outlier, stamp)),
                ):
                    run.publishers[topic].publish(msg)

            def huge(topic: str):
                with run.lock:
                    template = run.templates[topic][-1]
                msg = MUTATORS[topic](rng, restamped(template, run.clock_ns() - 50_000_000), huge=True)
                return lambda: run.publishers[topic].publish(msg)

            run.peak.clear()
            results['1 featureAssociation: CloudInfo orientation_diff 1e-30'] = _after_input(
                run, 'featureAssociation', orientation_diff_1e30, 'orientation_diff = 1e-30'
            )
            run.peak.clear()
            results['2 featureAssociation: 2,000,000-point /segmented_cloud'] = _after_input(
                run, 'featureAssociation', huge('/segmented_cloud'), 'points = 2000000'
            )
            run.peak.clear()
            results['3 mapOptimization: 2,000,000-point /laser_cloud_surf_last'] = _after_input(
                run, 'mapOptimization', huge('/laser_cloud_surf_last'), 'points = 2000000'
            )

            # 4: twenty callers of save_map at once while mapping goes on.
            feeding = threading.Thread(target=run.feed, args=(40,), daemon=True)
            feeding.start()
            time.sleep(1.0)
            clients = [run.node.create_client(Trigger, 'save_map') for _ in range(20)]
            for client in clients:
                client.wait_for_service(timeout_sec=30)
            start = time.monotonic()
            futures = [client.call_async(Trigger.Request()) for client in clients]
            answered = {}

            def note(index):
                return lambda f: answered.setdefault(index, time.monotonic() - start)

            for index, future in enumerate(futures):
                future.add_done_callback(note(index))
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and not all(f.done() for f in futures):
                time.sleep(0.05)
            feeding.join(timeout=120)
            time.sleep(1.5)  # the nodes' next /diagnostics
            responses = [f.result() for f in futures if f.done()]
            maps = out / 'maps'
            files = sorted(p for p in maps.iterdir() if p.suffix in ('.pcd', '.tum')) if maps.is_dir() else []
            results['4 mapOptimization: 20 concurrent save_map calls while mapping'] = dict(
                calls=len(futures),
                answered=len(responses),
                succeeded=sum(bool(r.success) for r in responses),
                answer_time_s=dict(min=round(min(answered.values()), 2), max=round(max(answered.values()), 2))
                if answered
                else None,
                saves=run.diagnostics.counter('mapOptimization', 'saves'),
                requests_taken=run.diagnostics.counter('mapOptimization', 'save_requests'),
                files_complete=all(pcd_is_complete(p) for p in files if p.suffix == '.pcd') and bool(files),
                files=[p.name for p in files],
            )
            crashed = run.crashed()
        finally:
            codes = run.close()
    summary = dict(cases=results, crashed=crashed, exit_codes=codes)
    (out / 'cases.json').write_text(json.dumps(summary, indent=2))
    return summary


def print_table(summary: dict) -> None:
    print(
        f'\nmalformed inputs per topic: {summary["per_topic"]} (bursts of {summary["burst"]}, '
        f'{summary["huge_per_cloud_topic"]} of 2,000,000 points per cloud topic); {summary["valid_scans_fed"]} valid '
        f'scans between the bursts, mapped into {summary["map_keyframes"]} keyframes; {summary["wall_time_s"]} s'
    )
    print(
        '| node | topic: sent / received (valid included) | crashes | silent periods | non-finite outputs | '
        'recovery median / max [s] | recovery max [valid scans] | RSS before / peak / after |'
    )
    print('|---|---|---|---|---|---|---|---|')
    for node, r in summary['nodes'].items():
        topics = '<br>'.join(f'{t}: {r["sent"][t]} / {r["taken"].get(t, 0)}' for t in r['sent'])
        rec = r['recovery_s']
        m = r['memory_mb']
        recovery = f'{rec["median"]} / {rec["max"]}' if rec['median'] is not None else 'n/a'
        print(
            f'| {node} | {topics} | {r["crashes"]} | {r["silent_periods"]} | {r["non_finite_outputs"]} | '
            f'{recovery} | {r.get("recovery_scans", "n/a")} | {m["before"]} / {m["peak"]} / {m["after"]} MB |'
        )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--per-topic', type=int, default=5000, help='malformed messages per subscribed topic')
    parser.add_argument('--burst', type=int, default=250, help='malformed messages between two valid resumptions')
    parser.add_argument('--huge', type=int, default=2, help='2,000,000-point clouds per cloud topic')
    parser.add_argument('--seed', type=int, default=14)
    parser.add_argument('--short', action='store_true', help="the test suite's version: 60 per topic, about a minute")
    parser.add_argument('--cases', action='store_true', help="replay the issue's four cases instead")
    parser.add_argument('--out', default='/tmp/lego_loam_campaign')
    args = parser.parse_args(argv)
    if args.cases:
        summary = cases(args)
        print(json.dumps(summary, indent=2))
        return 1 if summary['crashed'] else 0
    if args.short:
        args.per_topic, args.burst, args.huge = 60, 30, 1
    summary = campaign(args)
    print_table(summary)
    bad = {
        node: r
        for node, r in summary['nodes'].items()
        if r['crashes'] or r['silent_periods'] or r['non_finite_outputs'] or r['tracebacks_logged']
    }
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
