"""Long reliability runs (issue 8): fuzzing, faults, load and a soak, with the figures for the report.

    .venv/bin/python benchmarks/reliability.py fuzz [--examples 5000]
    .venv/bin/python benchmarks/reliability.py faults [--trials 10]
    .venv/bin/python benchmarks/reliability.py load [--rate 3] [--burst 100]
    .venv/bin/python benchmarks/reliability.py soak [--minutes 30]
    .venv/bin/python benchmarks/reliability.py all

Every run starts the four nodes as processes (their logs, statistics and maps go to ``--out``, default
``/tmp/lego_loam_reliability/<mode>``) on a leased ROS_DOMAIN_ID with loopback discovery, feeds them the
simulated campus lap (``cached_scenario('campus')``, generated once, about 2 minutes) through
``lego_loam_py/testing/feeder.py`` (continuous stamps over as many laps as needed), samples the resident memory of
every node from /proc, and prints a summary (and writes ``summary.json``). The short versions of these
checks are ``tests/test_reliability.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lego_loam_py.core.params import write_params_file  # noqa: E402
from lego_loam_py.formats import pcd_is_complete, tum_is_complete  # noqa: E402
from lego_loam_py.orchestration import NODES as PIPELINE_NODES  # noqa: E402
from lego_loam_py.testing.domains import DomainLease  # noqa: E402
from lego_loam_py.testing.measure import rss_mb  # noqa: E402
from lego_loam_py.testing.nodes import spin_in_background  # noqa: E402

BIN = Path(sys.executable).parent
NODES = tuple(PIPELINE_NODES)  # the four executables, in pipeline order
OUTPUTS = {
    'imageProjection': '/segmented_cloud',
    'featureAssociation': '/laser_odom_to_init',
    'mapOptimization': '/aft_mapped_to_init',
    'transformFusion': '/integrated_to_init',
}
MAP_FILES = (
    'global_map.pcd',
    'corner_map.pcd',
    'surface_map.pcd',
    'trajectory.pcd',
    'trajectory.tum',
    'trajectory_camera_init.tum',
)


def campus_bag() -> Path:
    from lego_loam_py.sim.simulator import cached_scenario

    return cached_scenario('campus', progress=True)


class Pipeline:
    """The four nodes as processes (restartable), a listener in this process and a memory sampler."""

    def __init__(self, out: Path, domain: int, params: dict | None = None, listen=(), sample_period: float = 1.0):
        import rclpy
        from rclpy.context import Context

        self.out = out
        out.mkdir(parents=True, exist_ok=True)
        (out / 'logs').mkdir(exist_ok=True)
        self.env = dict(
            os.environ,
            ROS_DOMAIN_ID=str(domain),
            ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
            LEGO_LOAM_PY_STATS_DIR=str(out / 'stats'),
        )
        (out / 'stats').mkdir(exist_ok=True)
        params = dict(params or {})
        params.setdefault('map_optimization.file_directory', str(out / 'maps'))
        self.params_file = write_params_file(out / 'params.yaml', params)
        self.procs: dict[str, subprocess.Popen] = {}
        self.starts: dict[str, int] = {}
        self.others: list[subprocess.Popen] = []
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node('reliability_listener', context=self.context)
        self.got: dict[str, list] = {}
        self._subscribe(listen)
        from rclpy.executors import SingleThreadedExecutor

        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._spinner = spin_in_background(self.executor, self._stop)
        self.memory: list[tuple[float, dict[str, float]]] = []
        self.sample_period = sample_period
        self._sampler = threading.Thread(target=self._sample, daemon=True)
        self._sampler.start()

    # ----------------------------------------------------------------------------------------- listening
    def _subscribe(self, topics) -> None:
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import PointCloud2

        from lego_loam_py.ros import qos

        for topic in topics:
            store = self.got.setdefault(topic, [])
            if topic == '/key_pose_origin':

                def callback(msg, _store=store):
                    _store.append((time.monotonic(), _stamp(msg), int(msg.width)))

                cls, depth = PointCloud2, 2
            else:

                def callback(msg, _store=store):
                    _store.append((time.monotonic(), _stamp(msg)))

                cls, depth = (Odometry if 'init' in topic else PointCloud2), 100
            self.node.create_subscription(cls, topic, callback, qos.reliable(depth))

    def _sample(self) -> None:
        while not self._stop.wait(self.sample_period):
            self.memory.append(
                (time.monotonic(), {name: rss_mb(p.pid) for name, p in list(self.procs.items()) if p.poll() is None})
            )

    # ------------------------------------------------------------------------------------------- nodes
    def start(self, name: str) -> subprocess.Popen:
        self.starts[name] = self.starts.get(name, 0) + 1
        with open(self.out / 'logs' / f'{name}.{self.starts[name]}.log', 'w') as log:
            self.procs[name] = subprocess.Popen(
                [str(BIN / name), '--ros-args', '--params-file', str(self.params_file)],
                stdout=log,
                stderr=log,
                env=self.env,
                start_new_session=True,
            )
        return self.procs[name]

    def start_all(self, timeout: float = 60.0) -> None:
        for name in NODES:
            self.start(name)
        self.wait_for_publishers([OUTPUTS[n] for n in NODES], timeout)

    def wait_for_publishers(self, topics, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(self.node.count_publishers(t) > 0 for t in topics):
                time.sleep(0.5)
                return
            dead = [n for n, p in self.procs.items() if p.poll() is not None]
            if dead:
                raise RuntimeError(f'{dead} exited: {self.log(dead[0])[-3000:]}')
            time.sleep(0.1)
        raise RuntimeError(f'publishers of {topics} not discovered')

    def signal(self, name: str, sig=signal.SIGKILL, timeout: float = 30.0) -> int:
        proc = self.procs[name]
        if proc.poll() is None:
            os.killpg(proc.pid, sig)
        try:
            return proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            return proc.wait()

    def log(self, name: str) -> str:
        return ''.join(
            (self.out / 'logs' / f'{name}.{k}.log').read_text() for k in range(1, self.starts.get(name, 0) + 1)
        )

    def feeder(self, bag: Path, *args) -> subprocess.Popen:
        proc = subprocess.Popen(
            [sys.executable, '-m', 'lego_loam_py.testing.feeder', str(bag), *map(str, args)],
            cwd=REPO,
            env=self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            start_new_session=True,
        )
        self.others.append(proc)
        for line in proc.stdout:
            if line.startswith('ready'):
                break
        return proc

    def close(self) -> dict[str, int]:
        codes = {}
        for name in list(self.procs):
            codes[name] = self.signal(name, signal.SIGINT, timeout=60)
        for proc in self.others:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        self._stop.set()
        self._spinner.join(timeout=2)
        self._sampler.join(timeout=2)
        import rclpy

        self.executor.shutdown(timeout_sec=1)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        return codes

    def statistics(self) -> dict:
        out = {}
        for path in (self.out / 'stats').glob('*.json'):
            out[path.stem] = json.loads(path.read_text())
        return out

    def tracebacks(self) -> dict[str, int]:
        return {name: self.log(name).count('Traceback') for name in self.procs}

    def peak_memory(self) -> dict[str, float]:
        peaks: dict[str, float] = {}
        for _, values in self.memory:
            for name, value in values.items():
                if np.isfinite(value):
                    peaks[name] = max(peaks.get(name, 0.0), value)
        return peaks


def _stamp(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def fed_scan_stamps(bag: Path, seconds: float) -> list[int]:
    """Header stamps of the scans the feeder publishes in ``seconds`` of data (continuous over laps)."""
    from lego_loam_py.bag.io import BagReader
    from lego_loam_py.ros.conversions import serialized_stamp_ns

    stamps, times = [], []
    with BagReader(bag) as reader:
        lap = reader.end_time - reader.start_time + 100_000_000
        for m in reader.messages(topics=['/velodyne_points']):
            stamps.append(serialized_stamp_ns(m.data))
            times.append(m.timestamp - reader.start_time)
    out = []
    laps = int(seconds * 1e9 // lap) + 1
    for k in range(laps):
        for stamp, t in zip(stamps, times):
            if t + k * lap <= seconds * 1e9:
                out.append(stamp + k * lap)
    return out


def _mb(x: float) -> float:
    return round(float(x), 1)


def _print(summary: dict) -> None:
    print(json.dumps(summary, indent=2))


# ------------------------------------------------------------------------------------------------- soak


def soak(args) -> dict:
    """``minutes`` of simulated time through the four nodes; memory of every node sampled, keyframes counted."""
    bag = campus_bag()
    seconds = args.minutes * 60.0
    out = Path(args.out) / 'soak'
    with DomainLease() as domain:
        run = Pipeline(
            out, domain, listen=['/integrated_to_init', '/aft_mapped_to_init', '/key_pose_origin'], sample_period=5.0
        )
        try:
            run.start_all()
            feeder = run.feeder(bag, '--duration', seconds, '--rate', args.rate)
            start = time.monotonic()
            while feeder.poll() is None:
                time.sleep(10)
                kf = run.got['/key_pose_origin'][-1][2] if run.got['/key_pose_origin'] else 0
                memory = run.memory[-1][1] if run.memory else {}
                print(
                    f'[soak] {time.monotonic() - start:7.0f} s: keyframes {kf}, integrated '
                    f'{len(run.got["/integrated_to_init"])}, RSS '
                    + ', '.join(f'{n} {v:.0f} MB' for n, v in memory.items()),
                    flush=True,
                )
            fed_until = time.monotonic() - start
            time.sleep(5)
            wall = time.monotonic() - start
        finally:
            codes = run.close()  # mapOptimization saves its map on the way out (sampled as 'shutdown')
    stats = run.statistics()
    keyframes = run.got['/key_pose_origin']
    series = []  # (time, keyframes, RSS per node)
    for t, values in run.memory:
        kf = [k for (a, _, k) in keyframes if a <= t]
        series.append((t - start, kf[-1] if kf else 0, values))
    (out / 'memory.json').write_text(json.dumps(series))
    summary = dict(
        mode='soak',
        simulated_s=seconds,
        wall_s=round(wall, 1),
        rate=args.rate,
        exit_codes=codes,
        tracebacks=run.tracebacks(),
        fed_scans=len(fed_scan_stamps(bag, seconds)),
        integrated=len(run.got['/integrated_to_init']),
        mapped=len(run.got['/aft_mapped_to_init']),
        counters={n: s.get('counters', {}) for n, s in stats.items()},
        map=stats.get('mapOptimization', {}).get('map'),
    )
    warm = [s for s in series if 60.0 < s[0] <= fed_until]  # after start-up, until the data ends
    shutdown = [v.get('mapOptimization', float('nan')) for t, _, v in series if t > fed_until]
    growth = {}
    for name in NODES:
        points = [(t, kf, v[name]) for t, kf, v in warm if name in v and np.isfinite(v[name])]
        if len(points) < 3:
            continue
        t, kf, rss = (np.array(x, dtype=float) for x in zip(*points))
        growth[name] = dict(
            start_mb=_mb(rss[0]),
            end_mb=_mb(rss[-1]),
            peak_mb=_mb(rss.max()),
            mb_per_minute=round(float(np.polyfit(t / 60.0, rss, 1)[0]), 3),
        )
        if name == 'mapOptimization' and kf[-1] > kf[0]:
            growth[name]['kb_per_keyframe'] = round(float(np.polyfit(kf, rss, 1)[0]) * 1024.0, 1)
    summary['memory'] = growth
    if shutdown and np.isfinite(shutdown).any():
        summary['mapOptimization_peak_while_saving_at_shutdown_mb'] = _mb(np.nanmax(shutdown))
    if summary['map'] and summary['map']['keyframes']:
        summary['map_kb_per_keyframe'] = round(summary['map']['bytes'] / summary['map']['keyframes'] / 1024.0, 1)
    (out / 'summary.json').write_text(json.dumps(summary, indent=2))
    return summary


# ------------------------------------------------------------------------------------------------- fuzz


def fuzz(args) -> dict:
    """The fuzz tests of tests/test_reliability.py with ``examples`` random inputs per entry point."""
    out = Path(args.out) / 'fuzz'
    out.mkdir(parents=True, exist_ok=True)
    report = out / 'inputs.json'
    report.unlink(missing_ok=True)
    env = dict(os.environ, LEGO_LOAM_FUZZ_EXAMPLES=str(args.examples), LEGO_LOAM_FUZZ_REPORT=str(report))
    start = time.monotonic()
    result = subprocess.run(
        [
            sys.executable,
            '-m',
            'pytest',
            'tests/test_reliability.py',
            '-q',
            '-p',
            'no:cacheprovider',
            '-k',
            'fuzz or oversized',
            '-x',
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
    )
    tail = result.stdout.strip().splitlines()[-1:] if result.stdout.strip() else []
    inputs = json.loads(report.read_text()) if report.is_file() else {}
    return dict(
        mode='fuzz',
        examples_per_entry_point=args.examples,
        passed=result.returncode == 0,
        pytest=tail,
        wall_s=round(time.monotonic() - start, 1),
        inputs=inputs,
        failures=result.stdout[-5000:] if result.returncode else '',
    )


# ------------------------------------------------------------------------------------------------ faults


def _gap_after(arrivals: list[float], t: float) -> float | None:
    """Time from ``t`` to the first arrival after it (None: none)."""
    later = [a for a in arrivals if a > t]
    return later[0] - t if later else None


def faults(args) -> dict:
    """Each node killed with SIGKILL and restarted while the others run; mapOptimization killed while it
    saves its map (``trials`` times). Recovery time, scans lost, map files checked."""
    bag = campus_bag()
    out = Path(args.out) / 'faults'
    schedule = [
        ('imageProjection', 20.0),
        ('mapOptimization', 40.0),
        ('featureAssociation', 60.0),
        ('transformFusion', 80.0),
    ]
    seconds = 100.0 + args.trials * 12.0
    with DomainLease() as domain:
        run = Pipeline(out, domain, listen=list(OUTPUTS.values()), sample_period=1.0)
        events, saves = [], {}
        try:
            run.start_all()
            feeder = run.feeder(bag, '--duration', seconds)
            start = time.monotonic()
            for name, at in schedule:
                while time.monotonic() - start < at:
                    time.sleep(0.05)
                killed = time.monotonic()
                run.signal(name, signal.SIGKILL)
                run.start(name)
                events.append(dict(node=name, killed=killed))
            time.sleep(15)
            saves = _kill_during_saves(run, args.trials)
            while feeder.poll() is None:
                time.sleep(0.5)
            time.sleep(3)
        finally:
            codes = run.close()
    fed = fed_scan_stamps(bag, seconds)
    results = []
    for event in events:
        name, killed = event['node'], event['killed']
        own = run.got[OUTPUTS[name]]
        recovery = _gap_after([a for a, _ in own], killed)
        row = dict(node=name, recovery_s=None if recovery is None else round(recovery, 2))
        # Scans lost: the fed scans inside the largest gap between consecutive outputs around the outage (for
        # every output downstream of the killed node). Scans skipped under load count too.
        for topic in ('/laser_odom_to_init', '/integrated_to_init', '/aft_mapped_to_init'):
            window_end = killed + (recovery or 10.0) + 3.0
            stamps = sorted(s for a, s in run.got[topic] if killed - 2.0 <= a <= window_end)
            if len(stamps) < 2:
                continue
            k = int(np.argmax(np.diff(stamps)))
            lost = [s for s in fed if stamps[k] < s < stamps[k + 1]]
            label = {
                '/laser_odom_to_init': 'odometry',
                '/integrated_to_init': 'fused',
                '/aft_mapped_to_init': 'mapping',
            }[topic]
            row[f'scans_without_{label}'] = len(lost)
            row[f'{label}_gap_s'] = round((stamps[k + 1] - stamps[k]) * 1e-9, 1)
        results.append(row)
    processed = {t: len({s for _, s in v}) for t, v in run.got.items()}
    summary = dict(
        mode='faults',
        exit_codes=codes,
        tracebacks=run.tracebacks(),
        restarts=results,
        sigkill_during_save=saves,
        fed_scans=len(fed),
        outputs=processed,
        reanchored=run.log('mapOptimization').count('re-anchored'),
        note='scans_without_X: fed scans in the largest gap of output X around the outage; X_gap_s: '
        'that gap in data time. Under load the pipeline skips scans anyway: see outputs.',
    )
    (out / 'summary.json').write_text(json.dumps(summary, indent=2))
    return summary


def _kill_during_saves(run: Pipeline, trials: int) -> dict:
    """Call save_map and SIGKILL mapOptimization the moment (plus 0-5 ms) a temporary map file appears; check
    that every map file is complete (the previous version or the new one) and that the restarted node
    removes the temporaries."""
    from std_srvs.srv import Trigger

    maps = run.out / 'maps'
    rng = random.Random(8)
    outcome = dict(
        trials=0,
        caught_mid_save=0,
        files_checked=0,
        partial_files=0,
        temporaries_left=0,
        temporaries_removed_on_restart=0,
        saves_completed_before_the_kill=0,
    )
    for _ in range(trials):
        client = run.node.create_client(Trigger, 'save_map')
        deadline = time.monotonic() + 60
        latest = run.out / 'logs' / f'mapOptimization.{run.starts["mapOptimization"]}.log'
        while time.monotonic() < deadline and 'maps saved to' not in latest.read_text():
            time.sleep(0.1)
        client.wait_for_service(timeout_sec=30)
        time.sleep(6)  # the restarted node builds a map again
        caught = False
        for _attempt in range(10):
            future = client.call_async(Trigger.Request())
            limit = time.monotonic() + 20
            while time.monotonic() < limit and not future.done():
                if any('.tmp' in e.name for e in os.scandir(maps)):
                    time.sleep(rng.uniform(0.0, 0.005))
                    run.signal('mapOptimization', signal.SIGKILL)
                    caught = True
                    break
            if caught:
                break
            outcome['saves_completed_before_the_kill'] += 1
        if not caught:
            run.signal('mapOptimization', signal.SIGKILL)
        run.node.destroy_client(client)
        outcome['trials'] += 1
        temporaries = [p for p in maps.iterdir() if '.tmp' in p.name]
        outcome['caught_mid_save'] += caught
        outcome['temporaries_left'] += len(temporaries)
        for path in maps.iterdir():
            if path.name.startswith('.'):
                continue
            outcome['files_checked'] += 1
            complete = pcd_is_complete(path) if path.suffix == '.pcd' else tum_is_complete(path)
            if not complete:  # (a complete file is the previous version or the new one)
                outcome['partial_files'] += 1
        run.start('mapOptimization')
        deadline = time.monotonic() + 30
        while temporaries and time.monotonic() < deadline and any(p.exists() for p in temporaries):
            time.sleep(0.1)
        outcome['temporaries_removed_on_restart'] += sum(not p.exists() for p in temporaries)
    return outcome


# -------------------------------------------------------------------------------------------------- load


def load(args) -> dict:
    """The campus lap at ``rate`` x real time, then a burst of ``burst`` clouds at 1x: memory, drops, catch-up."""
    bag = campus_bag()
    results = {}
    for label, feeder_args, seconds in (
        (f'{args.rate:g}x', ['--rate', args.rate, '--duration', 120.0], 120.0),
        (f'burst {args.burst}', ['--burst', args.burst, '--duration', 30.0], 30.0),
    ):
        out = Path(args.out) / 'load' / label.replace(' ', '_')
        with DomainLease() as domain:
            run = Pipeline(out, domain, listen=list(OUTPUTS.values()), sample_period=0.2)
            try:
                run.start_all()
                time.sleep(2)
                baseline = {n: rss_mb(p.pid) for n, p in run.procs.items()}
                feeder = run.feeder(bag, *feeder_args)
                lines = []
                for line in feeder.stdout:
                    lines.append(line.strip())
                fed_end = time.monotonic()
                feeder.wait()
                # Catch-up: until every node published the last scan's result (or 60 s).
                fed = fed_scan_stamps(bag, seconds)
                last = fed[-1]
                deadline = fed_end + 60
                caught_up = {}
                while time.monotonic() < deadline and len(caught_up) < 2:
                    for topic in ('/segmented_cloud', '/integrated_to_init'):
                        if topic not in caught_up and run.got[topic] and run.got[topic][-1][1] == last:
                            caught_up[topic] = round(run.got[topic][-1][0] - fed_end, 2)
                    time.sleep(0.05)
                time.sleep(2)
            finally:
                codes = run.close()
        stats = run.statistics()
        peak = run.peak_memory()
        results[label] = dict(
            fed_scans=len(fed),
            exit_codes=codes,
            tracebacks=run.tracebacks(),
            processed={
                'imageProjection': stats.get('imageProjection', {}).get('counters', {}).get('clouds_out'),
                'featureAssociation': stats.get('featureAssociation', {}).get('counters', {}).get('scans'),
                'mapOptimization steps': stats.get('mapOptimization', {}).get('counters', {}).get('steps'),
                'transformFusion': stats.get('transformFusion', {}).get('counters', {}).get('integrated'),
            },
            baseline_mb={n: _mb(v) for n, v in baseline.items()},
            peak_mb={n: _mb(v) for n, v in peak.items()},
            catch_up_after_feed_s=caught_up,
            feeder=lines[-3:],
            median_ms={
                n: round(next(iter(s['timings_ms'].values())).get('median', 0), 1)
                for n, s in stats.items()
                if s.get('timings_ms')
            },
        )
    summary = dict(mode='load', runs=results)
    (Path(args.out) / 'load' / 'summary.json').write_text(json.dumps(summary, indent=2))
    return summary


# ------------------------------------------------------------------------------------------------- main


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('mode', choices=['fuzz', 'faults', 'load', 'soak', 'all'])
    parser.add_argument('--out', default='/tmp/lego_loam_reliability')
    parser.add_argument('--minutes', type=float, default=30.0, help='soak: simulated minutes')
    parser.add_argument('--rate', type=float, default=None, help='soak: 1.0 (default), load: 3.0 (default)')
    parser.add_argument('--burst', type=int, default=100)
    parser.add_argument('--trials', type=int, default=10, help='faults: SIGKILL-during-save trials')
    parser.add_argument('--examples', type=int, default=5000, help='fuzz: inputs per entry point')
    args = parser.parse_args(argv)
    modes = ['fuzz', 'faults', 'load', 'soak'] if args.mode == 'all' else [args.mode]
    results = {}
    for mode in modes:
        local = argparse.Namespace(**vars(args))
        if local.rate is None:
            local.rate = 3.0 if mode == 'load' else 1.0
        results[mode] = globals()[mode](local)
        _print(results[mode])
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / f'summary_{args.mode}.json').write_text(json.dumps(results, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
