"""What the four nodes cost over DDS, as a user pays it: whole-process CPU per scan, idle CPU, memory, scans out.

    .venv/bin/python benchmarks/bench_dds.py [--rates 1 2] [--pinned 1 2] [--repeat 3] [--seconds 20] [--idle 10]
                                             [--clock 40] [--profile] [--floor] [--composed] [--as-original]
                                             [--out DIR]

The recording is a simulated 20 s campus drive with IMU (VLP-16, 200 scans; ``--bag`` for another one, with ``-p
key:=value`` for the nodes' parameters, e.g. a real HDL-64E drive: ``lego_loam_py convert`` a KITTI folder, then ``--bag
BAG -p sensor.preset:=HDL-64E``), generated into the cache on first use. For each configuration the four nodes are
started with ``ros2 run``-style executables on sim time (as with a bag), this process waits until they are up and
measures, per node, from /proc:

* **idle CPU**: % of a core over ``--idle`` seconds with no data flowing (the player not started yet);
* **CPU per scan**: user + system time of the node's process from the player's start to the end of the run
  (the last fused pose, plus a second), divided by the scans in the recording: start-up excluded, everything
  else (DDS, executor, IMU, /clock, conversions, the algorithm) included; and **with start-up**: the same plus
  all the process spent before the idle window (start-up, discovery, two settling seconds), with the bytecode
  caches an installed package has (written first: ``benchmarks.common.compile_bytecode``);
* **peak RSS** while playing;
* the scans that reached /integrated_to_init, and the ATE of those poses against the ground truth.

Configurations: every rate of ``--rates`` with the nodes free to use both cores, and every rate of ``--pinned``
with the four nodes pinned to core 0 (``taskset``) and the player, the recorder of outputs (this process) on
core 1. ``--repeat`` runs each configuration several times and reports the median of each figure (a shared
machine varies by 10-20 % from run to run). The JSON also splits each node's CPU by thread (the Python main
thread, Fast DDS's dds.* threads) and gives its system time; ``--profile`` samples every node with py-spy.
``--floor`` follows each run with the same run of computation-free stand-ins of the four nodes
(``benchmarks/floor_node.py``: the same subscriptions, executor and sim time, publishing the bytes the nodes published
in a recorded run), so each node's figure sits beside what rclpy and DDS alone cost for its messages.
``--composed`` follows each configuration's runs with the same runs of ``legoLoam``, the four nodes in one process
(their messages to each other in memory). Each node's own callbacks (``callback_cpu_s`` of its statistics) are
printed beside its process: in one process, each node's share.
``--as-original`` runs the nodes with the C++ original's feature set, so that its figures compare work for work:
loop closure off (the original's default) and no occupancy grid (the original has none), this package's algorithms
otherwise. Without it the nodes run with this package's defaults, which do both. (``config/original.yaml`` is
another thing: it swaps in the original's algorithms too, for the parity tests.)
Results are printed as a table and written to ``DIR/bench_dds.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import compile_bytecode  # noqa: E402
from benchmarks.floor_node import CAPTURE_TOPICS  # noqa: E402
from lego_loam_py.core.params import parse_overrides, write_params_file  # noqa: E402
from lego_loam_py.orchestration import COMPOSED as COMPOSED_COMMAND  # noqa: E402
from lego_loam_py.orchestration import NODES as PIPELINE_NODES  # noqa: E402
from lego_loam_py.testing.domains import DomainLease  # noqa: E402
from lego_loam_py.testing.measure import rss_mb  # noqa: E402
from lego_loam_py.testing.nodes import spin_in_background  # noqa: E402

BIN = Path(sys.executable).parent
FLOOR_NODE = REPO / 'benchmarks' / 'floor_node.py'
NODES = tuple(PIPELINE_NODES)  # the four executables, in pipeline order
# The C++ original on the same kind of recording (the measurement: 200-scan VLP-16 + IMU campus, 1x).
CPP_MS_PER_SCAN = {'imageProjection': 4.3, 'featureAssociation': 7.5, 'mapOptimization': 16.2, 'transformFusion': 1.2}
CPP_TOTAL_MS_PER_SCAN = sum(CPP_MS_PER_SCAN.values())
COMPOSED = COMPOSED_COMMAND[0]  # the four nodes in one process (lego_loam_py.ros.composed_node)
CPP_MS_PER_SCAN[COMPOSED] = CPP_TOTAL_MS_PER_SCAN
# The work the original does by default, and no more (--as-original): loop closure off (its loopClosureEnableFlag),
# no occupancy grid (it has none).
AS_ORIGINAL = ('loop_closure.loop_closure_enable_flag:=false', 'occupancy_grid.enabled:=false')


def cpu_seconds(pid: int, system_only: bool = False) -> float:
    """User + system CPU time of a process so far [s] (NaN when it is gone); the system part alone with
    ``system_only``."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return float('nan')
    return (int(fields[12]) + (0 if system_only else int(fields[11]))) / os.sysconf('SC_CLK_TCK')


def thread_cpu_seconds(pid: int) -> dict[str, float]:
    """User + system CPU time so far of each thread of a process [s], summed by thread name (the Python main
    thread has the executable's name; Fast DDS names its threads dds.*)."""
    out: dict[str, float] = {}
    for task in Path(f'/proc/{pid}/task').glob('*'):
        try:
            name = (task / 'comm').read_text().strip()
            fields = (task / 'stat').read_text().rsplit(')', 1)[1].split()
        except OSError:
            continue
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    return out


def default_bag(seconds: float) -> Path:
    from lego_loam_py.sim.simulator import cached_scenario

    return cached_scenario('campus', duration=seconds, progress=True)


def run_configuration(
    bag: Path,
    out: Path,
    rate: float,
    pinned: bool,
    idle: float,
    profile: bool = False,
    clock_hz: float = 40.0,
    run: int = 0,
    overrides: dict | None = None,
    capture: Path | None = None,
    floor: Path | None = None,
    composed: bool = False,
) -> dict:
    """Start the nodes, measure idle, play the bag at ``rate``, measure; returns the row.

    ``capture``: also record what the nodes publish into that bag (for ``floor`` runs); ``floor``: start the
    computation-free stand-ins of ``benchmarks/floor_node.py`` instead of the nodes, publishing what that capture
    holds. ``composed``: the one process of ``legoLoam`` instead of the four nodes' (its row's only node)."""
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from lego_loam_py.bag.io import BagReader
    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import odometry_to_pose, stamp_to_ns

    with BagReader(bag) as reader:
        scans = reader.topic_counts()['/velodyne_points']
    executables = (COMPOSED,) if composed else NODES
    kind = 'floor: ' if floor else 'composed, ' if composed else ''
    label = f'{kind}{"pinned to 1 core, " if pinned else ""}{rate:g}x'
    folder = out / (label.replace(' ', '_').replace(',', '') + (f'_run{run}' if run else ''))
    (folder / 'logs').mkdir(parents=True, exist_ok=True)
    params = folder / 'params.yaml'
    write_params_file(
        params, {'use_sim_time': True, 'map_optimization.file_directory': folder / 'maps', **(overrides or {})}
    )
    taskset = ['taskset', '-c', '0'] if pinned else []
    if pinned:
        os.sched_setaffinity(0, {1})  # this process (the listener) and the player on the other core
    with DomainLease() as domain:
        env = dict(
            os.environ,
            ROS_DOMAIN_ID=str(domain),
            ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
            LEGO_LOAM_PY_STATS_DIR=str(folder / 'stats'),
        )
        procs = {}
        for name in executables:
            command = [str(BIN / name)] if floor is None else [sys.executable, str(FLOOR_NODE), name, str(floor)]
            with open(folder / 'logs' / f'{name}.log', 'w') as log:
                procs[name] = subprocess.Popen(
                    [*taskset, *command, '--ros-args', '--params-file', str(params)],
                    stdout=log,
                    stderr=log,
                    env=env,
                    start_new_session=True,
                )
        context = Context()
        rclpy.init(context=context, domain_id=domain)
        node = rclpy.create_node('bench_dds', context=context)
        fused, lock = [], threading.Lock()

        def on_fused(msg):
            with lock:
                fused.append((time.monotonic(), stamp_to_ns(msg.header.stamp), odometry_to_pose(msg)))

        node.create_subscription(Odometry, '/integrated_to_init', on_fused, qos.reliable(100))
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        stop = threading.Event()
        spinner = spin_in_background(executor, stop)
        peak = {name: 0.0 for name in executables}
        sampling = threading.Event()

        def sample():
            while not stop.wait(0.2):
                if sampling.is_set():
                    for name, proc in procs.items():
                        peak[name] = max(peak[name], rss_mb(proc.pid))

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        try:
            deadline = time.monotonic() + 120
            while not all(
                node.count_publishers(t)
                for t in ('/segmented_cloud', '/laser_odom_to_init', '/aft_mapped_to_init', '/integrated_to_init')
            ):
                if time.monotonic() > deadline or any(p.poll() is not None for p in procs.values()):
                    raise RuntimeError('the nodes did not come up')
                time.sleep(0.1)
            time.sleep(2.0)  # discovery settles, start-up work (imports, first allocations) is over
            before_idle = {name: cpu_seconds(p.pid) for name, p in procs.items()}
            time.sleep(idle)
            after_idle = {name: cpu_seconds(p.pid) for name, p in procs.items()}
            sampling.set()
            profilers = _start_profilers(procs, folder) if profile else []
            start = {name: cpu_seconds(p.pid) for name, p in procs.items()}
            start_threads = {name: thread_cpu_seconds(p.pid) for name, p in procs.items()}
            start_system = {name: cpu_seconds(p.pid, system_only=True) for name, p in procs.items()}
            recorder = None
            if capture is not None:
                recorder = subprocess.Popen(
                    [str(BIN / 'lego_loam_py'), 'record', '-q', '-o', str(capture), *CAPTURE_TOPICS],
                    env=env,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                    start_new_session=True,
                )
                _wait_for_subscribers(node, CAPTURE_TOPICS)
                time.sleep(1.0)  # (the publishers match the recorder's subscriptions)
            played = time.monotonic()
            player = subprocess.run(
                [
                    str(BIN / 'lego_loam_py'),
                    'play',
                    str(bag),
                    '--rate',
                    f'{rate:g}',
                    '--wait-for-subscribers',
                    '30',
                    '--no-progress',
                    '--clock',
                    f'{clock_hz:g}',
                ],
                env=env,
                capture_output=True,
                text=True,
                timeout=600,
            )
            # The last scans through the pipeline: until no fused pose came for a second.
            while True:
                with lock:
                    last = fused[-1][0] if fused else played
                if time.monotonic() - max(last, played) > 1.0:
                    break
                time.sleep(0.1)
            end = {name: cpu_seconds(p.pid) for name, p in procs.items()}
            end_threads = {name: thread_cpu_seconds(p.pid) for name, p in procs.items()}
            end_system = {name: cpu_seconds(p.pid, system_only=True) for name, p in procs.items()}
            sampling.clear()
            if recorder is not None:
                os.killpg(recorder.pid, signal.SIGINT)
                recorder.wait(timeout=60)
            for profiler in profilers:
                profiler.send_signal(signal.SIGINT)
                profiler.wait(timeout=60)
            wall = time.monotonic() - played
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    os.killpg(proc.pid, signal.SIGINT)
            codes = {}
            for name, proc in procs.items():
                try:
                    codes[name] = proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    codes[name] = proc.wait()
            stop.set()
            spinner.join(timeout=2)
            from lego_loam_py.ros.runtime import finish_within

            finish_within(
                lambda: (executor.shutdown(timeout_sec=1), node.destroy_node(), rclpy.try_shutdown(context=context)),
                'the benchmark node shutdown',
                10.0,
            )
            if pinned:
                os.sched_setaffinity(0, set(range(os.cpu_count() or 1)))
    ate = _ate(bag, fused)
    nodes = {}
    for name in executables:
        ms = 1000.0 * (end[name] - start[name]) / scans
        # As a user pays it, start-up included: the process's CPU before the idle window (start-up, discovery, the
        # settling seconds) and while playing; the idle window is this benchmark's own.
        with_startup = 1000.0 * (before_idle[name] + end[name] - start[name]) / scans
        nodes[name] = dict(
            cpu_ms_per_scan=round(ms, 1),
            cpu_ms_per_scan_with_startup=round(with_startup, 1),
            startup_cpu_s=round(before_idle[name], 2),
            vs_cpp=round(ms / CPP_MS_PER_SCAN[name], 2),
            idle_cpu_percent=round(100.0 * (after_idle[name] - before_idle[name]) / idle, 2),
            peak_rss_mb=round(peak[name], 1),
            exit_code=codes[name],
            system_ms_per_scan=round(1000.0 * (end_system[name] - start_system[name]) / scans, 1),
            threads_ms_per_scan={
                thread: round(1000.0 * (seconds - start_threads[name].get(thread, 0.0)) / scans, 2)
                for thread, seconds in sorted(end_threads[name].items())
                if seconds - start_threads[name].get(thread, 0.0) > 0
            },
        )
    # Each node's own callbacks (its statistics, written at shutdown): in one process, each node's share.
    callbacks = {}
    for name in NODES:
        try:
            stats = json.loads((folder / 'stats' / f'{name}.json').read_text())
            callbacks[name] = round(1000.0 * stats['callback_cpu_s'] / scans, 2)
        except (OSError, KeyError, ValueError):
            pass
    return dict(
        configuration=label,
        callbacks_ms_per_scan=callbacks,
        rate=rate,
        pinned=pinned,
        scans=scans,
        fused=len(fused),
        fused_percent=round(100.0 * len(fused) / scans, 1),
        ate_rmse_m=ate,
        wall_s=round(wall, 1),
        player=player.stderr.strip().splitlines()[-1:] if player.stderr else [],
        total_cpu_ms_per_scan=round(sum(n['cpu_ms_per_scan'] for n in nodes.values()), 1),
        total_cpu_ms_per_scan_with_startup=round(sum(n['cpu_ms_per_scan_with_startup'] for n in nodes.values()), 1),
        nodes=nodes,
    )


def _start_profilers(procs: dict, folder: Path) -> list:
    """py-spy (a sampling profiler, not a dependency of the package: ``pip install py-spy``) on every node while
    the recording plays; raw stacks go to ``folder/profile/<node>.txt`` and a summary is printed."""
    import shutil

    spy = shutil.which('py-spy') or str(BIN / 'py-spy')
    if not Path(spy).exists():
        raise SystemExit('--profile needs py-spy (pip install py-spy)')
    (folder / 'profile').mkdir(exist_ok=True)
    return [
        subprocess.Popen(
            [
                spy,
                'record',
                '--pid',
                str(p.pid),
                '--rate',
                '250',
                '--format',
                'raw',
                '--nonblocking',
                '-o',
                str(folder / 'profile' / f'{name}.txt'),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for name, p in procs.items()
    ]


def profile_summary(path: Path, top: int = 15) -> str:
    """The functions holding most samples in a py-spy raw file: self time and time including callees."""
    own, total, samples = {}, {}, 0
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(' ')
        if not count.isdigit():
            continue
        frames = stack.split(';')
        samples += int(count)
        own[frames[-1]] = own.get(frames[-1], 0) + int(count)
        for frame in set(frames):
            total[frame] = total.get(frame, 0) + int(count)
    lines = [f'{path.stem}: {samples} samples']
    lines += [
        f'  self {100 * n / samples:5.1f} %  {name[:150]}'
        for name, n in sorted(own.items(), key=lambda kv: -kv[1])[:top]
    ]
    lines += [
        f'  total {100 * n / samples:5.1f} %  {name[:150]}'
        for name, n in sorted(total.items(), key=lambda kv: -kv[1])[:top]
    ]
    return '\n'.join(lines)


def _wait_for_subscribers(node, topics, timeout: float = 30.0) -> None:
    """Until every topic has a subscriber (the recorder's), or ``timeout`` [s]."""
    deadline = time.monotonic() + timeout
    while not all(node.count_subscribers(t) for t in topics) and time.monotonic() < deadline:
        time.sleep(0.1)


def median_row(runs: list[dict]) -> dict:
    """One row of several runs of a configuration: the median of every figure, and the runs' totals."""
    if len(runs) == 1:
        return runs[0]
    row = dict(
        runs[0],
        runs=len(runs),
        run_totals=[r['total_cpu_ms_per_scan'] for r in runs],
        run_totals_with_startup=[r['total_cpu_ms_per_scan_with_startup'] for r in runs],
    )
    for key in (
        'fused',
        'fused_percent',
        'ate_rmse_m',
        'wall_s',
        'total_cpu_ms_per_scan',
        'total_cpu_ms_per_scan_with_startup',
    ):
        values = [r[key] for r in runs if r[key] is not None]
        row[key] = round(float(np.median(values)), 3) if values else None
    row['fused'] = int(row['fused'])
    row['callbacks_ms_per_scan'] = {
        name: round(float(np.median([r['callbacks_ms_per_scan'].get(name, np.nan) for r in runs])), 2)
        for name in runs[0]['callbacks_ms_per_scan']
    }
    row['nodes'] = {}
    for name in runs[0]['nodes']:
        node = dict(runs[0]['nodes'][name])
        for key in (
            'cpu_ms_per_scan',
            'cpu_ms_per_scan_with_startup',
            'startup_cpu_s',
            'vs_cpp',
            'idle_cpu_percent',
            'peak_rss_mb',
            'system_ms_per_scan',
        ):
            node[key] = round(float(np.median([r['nodes'][name][key] for r in runs])), 2)
        node.pop('threads_ms_per_scan', None)
        row['nodes'][name] = node
    return row


def _ate(bag: Path, fused: list) -> float | None:
    from lego_loam_py.core.frames import camera_pose_to_lidar
    from lego_loam_py.evaluation import evaluate
    from lego_loam_py.inputs.sidecars import load_ground_truth

    truth = load_ground_truth(bag)
    if truth is None or len(fused) < 3:
        return None
    stamps = np.array([s for _, s, _ in fused])
    order = np.argsort(stamps)
    poses = np.array([camera_pose_to_lidar(p) for _, _, p in fused])[order]
    try:
        return round(evaluate(truth, (stamps[order], poses)).ate_rmse_m, 3)
    except ValueError:
        return None


def print_table(rows: list[dict]) -> None:
    print(
        '\n| configuration | node | CPU ms per scan while playing (x C++) | with start-up (start-up CPU) | idle CPU '
        '| peak RSS | scans fused | ATE |'
    )
    print('|---|---|---|---|---|---|---|---|')
    for row in rows:
        fused = f'{row["fused"]} / {row["scans"]} ({row["fused_percent"]} %)'
        for k, (name, n) in enumerate(row['nodes'].items()):
            first = k == 0
            print(
                f'| {row["configuration"] if first else ""} | {name} | {n["cpu_ms_per_scan"]} ({n["vs_cpp"]}x) | '
                f'{n["cpu_ms_per_scan_with_startup"]} ({n["startup_cpu_s"]} s) | '
                f'{n["idle_cpu_percent"]} % | {n["peak_rss_mb"]} MB | '
                f'{fused if first else ""} | '
                f'{(str(row["ate_rmse_m"]) + " m") if first else ""} |'
            )
        cpp = CPP_TOTAL_MS_PER_SCAN
        playing, with_startup = row['total_cpu_ms_per_scan'], row['total_cpu_ms_per_scan_with_startup']
        runs = startup_runs = ''
        if 'runs' in row:
            runs = f' (median of {row["runs"]} runs: {", ".join(str(t) for t in row["run_totals"])})'
            startup_runs = f' (runs: {", ".join(str(t) for t in row["run_totals_with_startup"])})'
        if row.get('callbacks_ms_per_scan'):
            shares = ', '.join(f'{name} {ms}' for name, ms in row['callbacks_ms_per_scan'].items())
            print(f'| | in callbacks | {shares} | | | | | |')
        print(
            f"| | **total** | **{playing}** ({playing / cpp:.2f}x the C++'s {cpp:.1f}){runs} | "
            f'**{with_startup}**{startup_runs} | | | | |'
        )


def print_floor(rows: list[dict]) -> None:
    """Each node's CPU per scan while playing beside its floor (the stand-in's: rclpy and DDS for the same messages)
    and the difference, the node's own work."""
    print('\n| configuration | node | node | floor | own work | C++ | 1.5x C++ minus floor |')
    print('|---|---|---|---|---|---|---|')
    floors = {r['configuration'].removeprefix('floor: '): r for r in rows if r['configuration'].startswith('floor')}
    for row in rows:
        floor = floors.get(row['configuration'])
        if floor is None:
            continue
        for k, name in enumerate(row['nodes']):
            real, base = row['nodes'][name]['cpu_ms_per_scan'], floor['nodes'][name]['cpu_ms_per_scan']
            cpp = CPP_MS_PER_SCAN[name]
            print(
                f'| {row["configuration"] if k == 0 else ""} | {name} | {real} | {base} | {real - base:.1f} | {cpp} | '
                f'{1.5 * cpp - base:.1f} |'
            )
        real, base = row['total_cpu_ms_per_scan'], floor['total_cpu_ms_per_scan']
        print(f'| | **total** | {real} | {base} | {real - base:.1f} | {CPP_TOTAL_MS_PER_SCAN:.1f} | |')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--bag', default=None, help='recording (default: simulated campus drive with IMU)')
    parser.add_argument('--seconds', type=float, default=20.0, help='length of the default recording [s]')
    parser.add_argument('--rates', type=float, nargs='*', default=[1.0], help='rates with the nodes on both cores')
    parser.add_argument(
        '--pinned', type=float, nargs='*', default=[1.0, 2.0], help='rates with the four nodes pinned to one core'
    )
    parser.add_argument('--idle', type=float, default=10.0, help='seconds of idle measurement')
    parser.add_argument('--out', default='/tmp/lego_loam_bench_dds')
    parser.add_argument(
        '--repeat', type=int, default=1, help='runs of each configuration; the table shows the median of each figure'
    )
    parser.add_argument(
        '--clock',
        type=float,
        default=40.0,
        help='/clock rate of the player [Hz] (default 40, as ros2 bag play --clock)',
    )
    parser.add_argument(
        '-p',
        '--param',
        action='append',
        default=[],
        metavar='KEY:=VALUE',
        help='a parameter of the nodes, e.g. -p sensor.preset:=HDL-64E (repeatable)',
    )
    parser.add_argument(
        '--profile',
        action='store_true',
        help='sample every node with py-spy while playing (adds CPU on the other core)',
    )
    parser.add_argument(
        '--floor',
        action='store_true',
        help='after each run, the same run with computation-free stand-ins of the nodes (benchmarks/floor_node.py) '
        'publishing what the nodes published: what rclpy alone costs for the same messages',
    )
    parser.add_argument(
        '--composed',
        action='store_true',
        help=f'also run every configuration with the four nodes in one process ({COMPOSED}, their messages to each '
        'other in memory), after the four processes',
    )
    parser.add_argument(
        '--as-original',
        action='store_true',
        help="the C++ original's feature set with this package's algorithms, to compare work for work: "
        + ', '.join(AS_ORIGINAL),
    )
    args = parser.parse_args(argv)
    compile_bytecode(REPO)  # (and any checkout on PYTHONPATH, which the nodes then import: see its docstring)
    bag = Path(args.bag) if args.bag else default_bag(args.seconds)
    out = Path(args.out)
    rows = []
    load = os.getloadavg()
    parameters = [*AS_ORIGINAL, *args.param] if args.as_original else list(args.param)
    overrides = parse_overrides(parameters)
    capture = None
    if args.floor:  # one run of the real nodes, recorded, for the stand-ins to publish
        capture = out / 'capture'
        shutil.rmtree(capture, ignore_errors=True)
        rate = (args.rates or args.pinned)[0]
        run_configuration(bag, out / 'capture_run', rate, False, 1.0, False, args.clock, 0, overrides, capture=capture)
    for pinned, rates in ((False, args.rates), (True, args.pinned)):
        for rate in rates:
            runs, floors = [], []
            for run in range(args.repeat):
                number = run + 1 if args.repeat > 1 else 0
                runs.append(
                    run_configuration(bag, out, rate, pinned, args.idle, args.profile, args.clock, number, overrides)
                )
                print(json.dumps(runs[-1]), flush=True)
                if capture is not None:
                    floors.append(
                        run_configuration(
                            bag, out, rate, pinned, args.idle, False, args.clock, number, overrides, floor=capture
                        )
                    )
                    print(json.dumps(floors[-1]), flush=True)
            rows.append(median_row(runs))
            if floors:
                rows.append(median_row(floors))
            if args.composed:
                together = []
                for run in range(args.repeat):
                    number = run + 1 if args.repeat > 1 else 0
                    together.append(
                        run_configuration(
                            bag, out, rate, pinned, args.idle, False, args.clock, number, overrides, composed=True
                        )
                    )
                    print(json.dumps(together[-1]), flush=True)
                rows.append(median_row(together))
    summary = dict(
        bag=str(bag),
        machine=f'{platform.processor() or platform.machine()}, {os.cpu_count()} cores',
        load_average_at_start=[round(x, 2) for x in load],
        parameters=parameters,
        rows=rows,
    )
    out.mkdir(parents=True, exist_ok=True)
    (out / 'bench_dds.json').write_text(json.dumps(summary, indent=2))
    if parameters:
        print(f'\nparameters: {" ".join(parameters)}')
    print_table(rows)
    if args.floor:
        print_floor(rows)
    if args.profile:
        for path in sorted(out.glob('*/profile/*.txt')):
            print(profile_summary(path))
    return 0


if __name__ == '__main__':
    sys.exit(main())
