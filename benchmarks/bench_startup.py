"""Start-up of each node as a user pays it: whole-process CPU and wall time until the node is ready.

    .venv/bin/python benchmarks/bench_startup.py [--runs 3] [--nodes imageProjection ...] [--floor] [--settle 2]
                                                 [--source DIR] [--profile] [--json FILE]

Each node (or ``legoLoam``, the four in one process, ready when the last of them answers) is started the way
``ros2 run lego_loam_py <node>`` starts it (its console script in the venv, a process
of its own, on sim time as with a bag, ``ROS_DOMAIN_ID`` leased for this benchmark, discovery on loopback).
**Ready** means the node answers: this process asks the node for a parameter (its ``get_parameters`` service) every
50 ms from the moment it starts, and the node is ready when the first answer arrives. An answer needs everything a
scan needs before its callback can run: the interpreter, the imports, ``rclpy.init``, the parameters declared,
every subscription and publisher created, the executor spinning, and DDS discovery between two processes (which a
peer such as the bag player also waits for; now and then it takes one more heartbeat, 3 s, in either version).
Per node and run:

* **wall** [s]: from the process's start (``Popen``) to the answer;
* **CPU** [s]: user + system time of the node's process (all its threads, from ``/proc/<pid>/stat``, 10 ms ticks)
  at the answer;
* **CPU settled** [s]: the same ``--settle`` seconds later, with no data flowing: the first ``/diagnostics``
  messages (one a second) and anything else a waiting node does. What a core imports for its first scan
  (``LegoLoamNode.import_deferred``: gtsam for mapOptimization, 0.1 s of CPU) comes with the node's first input,
  and so in neither figure.

The package's bytecode caches are written first, as an install has them (``benchmarks.common.compile_bytecode``:
without them a node compiles every module it imports at each start).

Runs alternate between nodes (the machine is shared: load drifts); medians are printed with every run's value.
``--floor`` adds a bare rclpy node (rclpy and two message packages, one subscription, one publisher): what no
node can go below. ``--source DIR`` puts another checkout first on ``PYTHONPATH`` (the venv's scripts then import
that tree: a before/after comparison with one venv). ``--profile`` also starts each node once under ``python -X
importtime`` with cProfile, up to the end of its construction, and prints where start-up goes: the phases, the
imports grouped by package, and the costliest calls after the imports; then, as a phase of its own, what the node
imports with its first input (its core's ``DEFERRED_IMPORTS``).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import compile_bytecode  # noqa: E402
from lego_loam_py.orchestration import COMPOSED as COMPOSED_COMMAND  # noqa: E402
from lego_loam_py.orchestration import NODES as MODULES  # noqa: E402
from lego_loam_py.testing.domains import DomainLease  # noqa: E402

BIN = Path(sys.executable).parent
NODES = tuple(MODULES)  # the four executables, in pipeline order (MODULES: each one's module)
# The four in one process (lego_loam_py.ros.composed_node): ready when the last one created answers.
COMPOSED = COMPOSED_COMMAND[0]
ANSWERED_BY = {COMPOSED: NODES[-1]}
# The floor: a bare rclpy node (rclpy and two message packages imported, one subscription, one publisher), spinning.
FLOOR = 'bareRclpyNode'
_FLOOR_SCRIPT = textwrap.dedent(
    """
    import rclpy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2
    from rclpy.executors import SingleThreadedExecutor
    rclpy.init()
    node = rclpy.create_node('bareRclpyNode')
    node.create_subscription(PointCloud2, '/velodyne_points', lambda m: None, 2)
    node.create_publisher(Odometry, '/x', 5)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except KeyboardInterrupt:
        pass
    """
)
READY_TIMEOUT_S = 60.0
RETRY_S = 0.05  # [s] between two requests while the node has not answered


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far, all threads [s] (NaN when it is gone)."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return float('nan')
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def node_env(domain: int, source: Path | None) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    if source is not None:
        env['PYTHONPATH'] = os.pathsep.join([str(source)] + [p for p in [env.get('PYTHONPATH')] if p])
    return env


class Prober:
    """A client node in this process that asks a node for a parameter as soon as its service shows up."""

    def __init__(self, domain: int):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node('bench_startup_probe', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._spinner = threading.Thread(target=self._spin, daemon=True)
        self._spinner.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def wait_ready(self, name: str, proc: subprocess.Popen, timeout: float) -> tuple[float, float]:
        """(monotonic time of the answer, the node's CPU then); raises if it never answers."""
        from rcl_interfaces.srv import GetParameters

        client = self.node.create_client(GetParameters, f'/{ANSWERED_BY.get(name, name)}/get_parameters')
        answered = threading.Event()
        at: list[float] = []

        def done(_future) -> None:
            if not at:
                at.extend((time.monotonic(), cpu_seconds(proc.pid)))
            answered.set()

        try:
            deadline = time.monotonic() + timeout
            # Asked every RETRY_S from the start, without waiting for the ROS graph to list the service: that list
            # comes on a topic of its own whose news can wait for a writer's next heartbeat (3 s), and so can a
            # request sent while the two ends are still matching each other; DDS's luck, not the node's start-up.
            while True:
                client.call_async(GetParameters.Request(names=['use_sim_time'])).add_done_callback(done)
                if answered.wait(RETRY_S):
                    break
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f'{name} did not answer (exit code {proc.poll()})')
            return at[0], at[1]
        finally:
            self.node.destroy_client(client)

    def close(self) -> None:
        import rclpy

        self._stop.set()
        self._spinner.join()
        self.executor.shutdown(1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def measure(name: str, domain: int, env: dict, params: Path, settle: float, log: Path) -> dict:
    # A new probe for each start: a participant that outlived the previous node's (same ports, same names) often
    # took one more heartbeat (3 s) to see the next one.
    prober = Prober(domain)
    try:
        return _measure(name, prober, env, params, settle, log)
    finally:
        prober.close()


def _measure(name: str, prober: Prober, env: dict, params: Path, settle: float, log: Path) -> dict:
    with open(log, 'w') as out:
        start = time.monotonic()
        command = [sys.executable, '-c', _FLOOR_SCRIPT] if name == FLOOR else [str(BIN / name)]
        proc = subprocess.Popen(
            [*command, '--ros-args', '--params-file', str(params)],
            stdout=out,
            stderr=out,
            env=env,
            cwd=tempfile.gettempdir(),
        )
        try:
            ready_at, cpu = prober.wait_ready(name, proc, READY_TIMEOUT_S)
            time.sleep(settle)
            settled = cpu_seconds(proc.pid)
        finally:
            stop(proc)
    return {'wall_s': ready_at - start, 'cpu_s': cpu, 'cpu_settled_s': settled}


def _fmt(values: list[float]) -> str:
    return f'{statistics.median(values):6.3f}  [{" ".join(f"{v:.3f}" for v in values)}]'


# ------------------------------------------------------------------------------------------------ profile
_PROFILE_CHILD = textwrap.dedent(
    """
    import cProfile, io, json, pstats, sys, time
    cpu0, wall0 = time.process_time(), time.monotonic()
    import importlib
    module = importlib.import_module(sys.argv[1])
    cpu1, wall1 = time.process_time(), time.monotonic()
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from lego_loam_py.ros.runtime import make_executor
    profile = cProfile.Profile()
    profile.enable()
    rclpy.init(args=['x', '--ros-args', '--params-file', sys.argv[3]], signal_handler_options=SignalHandlerOptions.NO)
    cpu2, wall2 = time.process_time(), time.monotonic()
    executor, spin_once = make_executor()
    node = getattr(module, sys.argv[2])()
    executor.add_node(node)
    spin_once(0.0)
    cpu3, wall3 = time.process_time(), time.monotonic()
    profile.disable()
    text = io.StringIO()
    pstats.Stats(profile, stream=text).sort_stats('cumulative').print_stats(30)
    print(FIRST_INPUT, file=sys.stderr, flush=True)  # (the import times below are not the start-up's)
    cpu3b, wall3b = time.process_time(), time.monotonic()
    thread = node.import_deferred() if hasattr(node, 'import_deferred') else None
    if thread is not None:
        thread.join()
    cpu4, wall4 = time.process_time(), time.monotonic()
    node.destroy_node()
    rclpy.try_shutdown()
    print(json.dumps({'phases': {'imports': [cpu1 - cpu0, wall1 - wall0], 'rclpy.init': [cpu2 - cpu1, wall2 - wall1],
                                 'node construction, first spin': [cpu3 - cpu2, wall3 - wall2],
                                 'imports with the first input': [cpu4 - cpu3b, wall4 - wall3b]},
                      'before_main_cpu_s': cpu0, 'profile': text.getvalue()}))
    """
)
# Printed by the profiled child between its start-up and what its first input imports (LegoLoamNode.import_deferred).
_FIRST_INPUT_MARK = '--- first input'
_PROFILE_CHILD = _PROFILE_CHILD.replace('FIRST_INPUT', repr(_FIRST_INPUT_MARK))

_CLASSES = {
    'imageProjection': 'ImageProjectionNode',
    'featureAssociation': 'FeatureAssociationNode',
    'mapOptimization': 'MapOptimizationNode',
    'transformFusion': 'TransformFusionNode',
}


def profile_node(name: str, env: dict, params: Path, top: int = 12) -> str:
    """Phases of one start-up, its imports by top-level package (self time) and its costliest calls."""
    proc = subprocess.run(
        [sys.executable, '-X', 'importtime', '-c', _PROFILE_CHILD, MODULES[name], _CLASSES[name], str(params)],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    if proc.returncode != 0:
        return f'{name}: profile failed: {proc.stderr[-2000:]}'
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    by_package: dict[str, float] = {}
    biggest: list[tuple[float, str]] = []
    start_up = proc.stderr.split(_FIRST_INPUT_MARK)[0]
    for line in start_up.splitlines():
        if not line.startswith('import time:') or 'self [us]' in line:
            continue
        _, self_us, cumulative_us, module = (part.strip() for part in line.replace('import time:', '|').split('|'))
        package = module.split('.')[0]
        if package in ('lego_loam_py', 'scipy', 'numpy', 'rclpy'):
            package = '.'.join(module.split('.')[:2])
        by_package[package] = by_package.get(package, 0.0) + int(self_us) * 1e-6
        biggest.append((int(cumulative_us) * 1e-6, module))
    lines = [f'== {name}: CPU before the first import (interpreter, site) {result["before_main_cpu_s"]:.3f} s']
    lines += [
        f'   {phase:<32s} CPU {cpu:6.3f} s   wall {wall:6.3f} s' for phase, (cpu, wall) in result['phases'].items()
    ]
    lines.append('   imports, self time by package (wall, -X importtime):')
    for package, seconds in sorted(by_package.items(), key=lambda kv: -kv[1])[:top]:
        lines.append(f'     {seconds:6.3f} s  {package}')
    lines.append('   largest imports (cumulative):')
    seen: set[str] = set()
    for seconds, module in sorted(biggest, reverse=True):
        root = module.split('.')[0]
        if root in seen and root != 'lego_loam_py':
            continue
        seen.add(root)
        lines.append(f'     {seconds:6.3f} s  {module}')
        if len(seen) >= top:
            break
    lines.append('   after the imports (cProfile, cumulative; includes imports made then):')
    profile_lines = result['profile'].splitlines()
    head = next((i for i, text in enumerate(profile_lines) if text.strip().startswith('ncalls')), 0)
    lines += ['     ' + text for text in profile_lines[head : head + 1 + top + 8] if text.strip()]
    return '\n'.join(lines)


def report(results: dict[str, list[dict]], settle: float, source: Path) -> str:
    lines = [
        f'\nstart-up until the node answers (median  [every run]), lego_loam_py from {source}:',
        f'{"node":<20s} {"wall [s]":<28s} {"CPU [s]":<28s} CPU {settle:g} s later [s]',
    ]
    for name, rows in results.items():
        lines.append(
            f'{name:<20s} {_fmt([r["wall_s"] for r in rows]):<28s} {_fmt([r["cpu_s"] for r in rows]):<28s} '
            f'{_fmt([r["cpu_settled_s"] for r in rows])}'
        )
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument(
        '--nodes',
        nargs='+',
        choices=[*NODES, COMPOSED],
        default=list(NODES),
        help=f'the executables to start (default: the four nodes; {COMPOSED}: the four in one process)',
    )
    parser.add_argument('--floor', action='store_true', help=f'also measure a bare rclpy node ({FLOOR})')
    parser.add_argument('--settle', type=float, default=2.0, help='seconds after ready for "CPU settled"')
    parser.add_argument('--source', type=Path, help='a checkout to import lego_loam_py from (PYTHONPATH)')
    parser.add_argument('--profile', action='store_true', help='also profile one start-up of each node')
    parser.add_argument('--json', type=Path, help='write every value here')
    args = parser.parse_args(argv)

    names = [*args.nodes, *([FLOOR] if args.floor else [])]
    results: dict[str, list[dict]] = {name: [] for name in names}
    compile_bytecode(args.source or REPO)
    with tempfile.TemporaryDirectory(prefix='bench_startup_') as tmp, DomainLease() as domain:
        params = Path(tmp) / 'params.yaml'
        params.write_text(
            f'/**:\n  ros__parameters:\n    use_sim_time: true\n    map_optimization.file_directory: {tmp}/maps/\n'
        )
        env = node_env(domain, args.source)
        for run in range(args.runs):
            for name in names:
                row = measure(name, domain, env, params, args.settle, Path(tmp) / f'{name}_{run}.log')
                results[name].append(row)
                print(
                    f'run {run + 1} {name:<20s} wall {row["wall_s"]:.3f} s  CPU {row["cpu_s"]:.3f} s  '
                    f'settled {row["cpu_settled_s"]:.3f} s',
                    flush=True,
                )
        if args.runs:
            print(report(results, args.settle, args.source or REPO))
        if args.profile:
            for name in args.nodes:
                if name in _CLASSES:  # (the composed process: its nodes' profiles are each node's)
                    print(profile_node(name, env, params), flush=True)
    if args.json:
        args.json.write_text(json.dumps({'source': str(args.source or REPO), 'results': results}, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
