"""``lego_loam_py launch``: the four nodes as separate, supervised processes (ros2 launch without launch).

ros2 launch is not installable from PyPI, so this module does for lego_loam_py what ``ros2 launch`` does
with the original's ``run.launch``: it starts imageProjection, featureAssociation, mapOptimization and
transformFusion as separate processes with one parameter file, optionally the bag player (``-p
use_sim_time:=true`` for every node then), the recorder and rviz2, and stops all of them cleanly. With a
full ROS 2 install, ``launch/lego_loam.launch.py`` does the same through ``ros2 launch``.

Life of a run (:func:`run_pipeline`):

1. **start** the recorder first (so it is subscribed before data flows), then the nodes in pipeline order.
   Every child gets its own process group (session), so a Ctrl-C in the terminal reaches only the
   supervisor, which then stops the children in order; on Linux every child also gets SIGTERM from the
   kernel if the supervisor itself dies (``PR_SET_PDEATHSIG``), so even a ``kill -9`` of the supervisor
   leaves no orphan.
2. **ready**: wait until every node publishes its always-on output topic in the ROS graph (and the recorder
   subscribed to the recorded topics), then start the player, which also waits for its subscribers.
3. **run** until Ctrl-C / SIGTERM, until a process exits on its own (a node that exits is a crash: the
   run stops and fails), or until the bag ends.
4. **drain** after the bag: wait until no /integrated_to_init arrived for ``drain_quiet`` seconds (the last
   scans went through the pipeline) or ``drain_timeout`` passed.
5. **stop**: SIGINT to each process group in reverse start order, waiting up to ``stop_timeout`` for each
   (the nodes save maps and statistics on the way out), SIGKILL to whatever is left of any group.

The exit code is 0 when every process started, ran and stopped cleanly (a Ctrl-C included) and 1 when any
did not (a crash, a non-zero exit, a process that had to be killed, the pipeline not becoming ready), 2
for invalid arguments or parameters.
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence, TextIO

from lego_loam_py.errors import UsageError

__all__ = ['NODES', 'READY_TOPICS', 'ProcessSpec', 'ProcessResult', 'Supervisor', 'PipelineConfig',
           'PipelineOutcome', 'GraphMonitor', 'run_pipeline', 'resolve_command', 'package_file',
           'Interrupts', 'add_arguments', 'main', 'main_argv']

PACKAGE = 'lego_loam_py'
# Executable -> module with a main(), in pipeline order.
NODES = {
    'imageProjection': 'lego_loam_py.ros.image_projection_node',
    'featureAssociation': 'lego_loam_py.ros.feature_association_node',
    'mapOptimization': 'lego_loam_py.ros.map_optimization_node',
    'transformFusion': 'lego_loam_py.ros.transform_fusion_node',
}
# A topic each node publishes from start-up on: its publisher in the ROS graph means the node is up.
READY_TOPICS = {
    'imageProjection': '/segmented_cloud_info',
    'featureAssociation': '/laser_odom_to_init',
    'mapOptimization': '/aft_mapped_to_init',
    'transformFusion': '/integrated_to_init',
}
RECORDER_NODE = 'lego_loam_py_recorder'
OUTPUT_TOPIC = '/integrated_to_init'
# Exit statuses that mean "stopped by the signal we sent" (SIGINT during start-up, before a node installed
# its handler, kills it with the signal itself).
_CLEAN_STOP_CODES = (0, -signal.SIGINT, 128 + signal.SIGINT)

# Run argv[2:] with PR_SET_PDEATHSIG = SIGTERM: the kernel stops the child when the supervisor dies, even
# by SIGKILL. A bare interpreter (-I -S: no site, no .pth, only ctypes) sets it and execs the real command,
# so no Python code runs in a forked copy of the (multi-threaded) supervisor.
_PDEATHSIG_EXEC = (
    'import ctypes, os, sys\n'
    'ctypes.CDLL(None, use_errno=True).prctl(1, 15, 0, 0, 0)\n'   # PR_SET_PDEATHSIG, SIGTERM
    'if os.getppid() != int(sys.argv[1]):\n'                      # the supervisor died before prctl
    '    sys.exit(143)\n'
    'os.execvp(sys.argv[2], sys.argv[2:])\n')


def package_file(*parts: str) -> Path:
    """A file of the package's share directory (``config/params.yaml``, ``config/lego_loam.rviz``, …):
    the installed copy when the ament index knows the package, else the source tree's."""
    try:
        from ament_index_python.packages import get_package_share_directory
        installed = Path(get_package_share_directory(PACKAGE), *parts)
        if installed.exists():
            return installed
    except Exception:  # not installed with the ament layout (or ament_index_python missing)
        pass
    return Path(__file__).resolve().parents[1].joinpath(*parts)


def resolve_command(executable: str, module: str) -> list[str]:
    """The command that runs a lego_loam_py executable with this interpreter's environment: the console
    script beside this Python (the venv), else the one ``ros2 run`` would use (``<prefix>/lib/<package>/``),
    else ``python -m module``."""
    candidates = [Path(sys.executable).parent / executable]
    candidates += [Path(prefix, 'lib', PACKAGE, executable)
                   for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if prefix]
    for path in candidates:
        if path.is_file() and os.access(path, os.X_OK):
            return [str(path)]
    return [sys.executable, '-m', module]


# ------------------------------------------------------------------------------------------ supervisor
@dataclass
class ProcessSpec:
    """One child process.

    ``role``: 'node' and 'recorder' (must run until stopped), 'player' (exits 0 at the end of the bag) or
    'tool' (rviz2: may be closed, exit 0, without stopping the run). ``output``: None for the supervisor's
    default, 'screen' (lines prefixed with ``[name]``), 'log' (``<log_dir>/<name>.log`` only) or 'inherit'
    (the terminal as it is, for a progress bar).
    """

    name: str
    argv: list[str]
    role: str = 'node'
    env: dict[str, str] = field(default_factory=dict)
    output: str | None = None
    stop_timeout: float = 30.0


@dataclass
class ProcessResult:
    """How a child ended. ``how``: 'stopped' (exited after our SIGINT), 'exited' (on its own), 'killed'
    (SIGKILL after ``stop_timeout``) or 'running' (not ended yet)."""

    name: str
    role: str
    pid: int
    returncode: int | None
    how: str
    failure: str | None = None

    def describe(self) -> str:
        code = 'no exit code' if self.returncode is None else (
            f'signal {-self.returncode}' if self.returncode < 0 else f'exit code {self.returncode}')
        text = {'stopped': 'stopped', 'exited': 'exited on its own', 'killed': 'killed',
                'running': 'still running'}[self.how]
        return f'{self.name} (pid {self.pid}): {text}, {code}' + (f' - FAILED: {self.failure}' if self.failure else '')


class _Child:
    def __init__(self, spec: ProcessSpec, popen: subprocess.Popen, log_file, pumps: list[threading.Thread]):
        self.spec = spec
        self.popen = popen
        self.log_file = log_file
        self.pumps = pumps
        self.stop_requested = False
        self.killed = False
        self.reported = False   # an unexpected exit was already returned by Supervisor.poll()

    @property
    def pid(self) -> int:
        return self.popen.pid


class Supervisor:
    """Starts child processes, each in its own process group, watches them and stops them in order.

    Output of the children goes to ``stream`` with a ``[name]`` prefix ('screen'), to
    ``log_dir/<name>.log`` ('log'; with 'screen' too when a ``log_dir`` is given), or straight to the
    terminal ('inherit'). ``announce`` receives the supervisor's own messages.
    """

    def __init__(self, output: str = 'screen', log_dir: str | Path | None = None, stream: TextIO | None = None,
                 announce: Callable[[str], None] | None = None, pdeathsig: bool = True):
        if output not in ('screen', 'log', 'inherit'):
            raise ValueError(f"output must be 'screen', 'log' or 'inherit', not {output!r}")
        if output == 'log' and log_dir is None:
            raise ValueError("output 'log' needs a log_dir")
        self.output = output
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.stream = stream or sys.stdout
        self.announce = announce or (lambda text: print(f'[launch] {text}', file=sys.stderr, flush=True))
        self.pdeathsig = pdeathsig and sys.platform.startswith('linux')
        self.children: list[_Child] = []
        self.hurry = threading.Event()      # a second Ctrl-C: stop without waiting
        self._write_lock = threading.Lock()

    # ----------------------------------------------------------------------------------------- start
    def start(self, spec: ProcessSpec) -> _Child:
        if any(c.spec.name == spec.name for c in self.children):
            raise ValueError(f'a process named {spec.name!r} was started already')
        env = os.environ.copy()
        env.update(spec.env)
        env.setdefault('PYTHONUNBUFFERED', '1')   # log lines as they happen, not when a buffer fills
        mode = spec.output or self.output
        log_file, stdout = None, None
        if self.log_dir is not None and mode in ('screen', 'log'):
            self.log_dir.mkdir(parents=True, exist_ok=True)
            log_file = open(self.log_dir / f'{spec.name}.log', 'wb')
        if mode == 'screen':
            stdout = subprocess.PIPE
        elif mode == 'log':
            stdout = log_file
        argv = [str(a) for a in spec.argv]
        if self.pdeathsig:
            argv = [sys.executable, '-I', '-S', '-c', _PDEATHSIG_EXEC, str(os.getpid()), *argv]
        try:
            popen = subprocess.Popen(argv, env=env, stdin=subprocess.DEVNULL, stdout=stdout,
                                     stderr=subprocess.STDOUT if stdout is not None else None,
                                     start_new_session=True)
        except OSError:
            if log_file is not None:
                log_file.close()
            raise
        pumps = []
        if mode == 'screen':
            pump = threading.Thread(target=self._pump, args=(popen.stdout, spec.name, log_file),
                                    name=f'output-{spec.name}', daemon=True)
            pump.start()
            pumps.append(pump)
        child = _Child(spec, popen, log_file, pumps)
        self.children.append(child)
        self.announce(f'started {spec.name} (pid {popen.pid}): {" ".join(str(a) for a in spec.argv)}')
        return child

    def _pump(self, pipe, name: str, log_file) -> None:
        prefix = f'[{name}] '
        for raw in iter(pipe.readline, b''):
            if log_file is not None:
                log_file.write(raw)
                log_file.flush()
            line = raw.decode('utf-8', errors='replace').rstrip('\r\n')
            with self._write_lock:
                try:
                    self.stream.write(prefix + line + '\n')
                    self.stream.flush()
                except (OSError, ValueError):  # the terminal went away: keep draining the pipe
                    pass
        pipe.close()

    # ----------------------------------------------------------------------------------------- watch
    def child(self, name: str) -> _Child:
        for c in self.children:
            if c.spec.name == name:
                return c
        raise KeyError(name)

    def poll(self) -> list[_Child]:
        """Children that exited on their own since the last call (each reported once)."""
        out = []
        for c in self.children:
            if not c.reported and not c.stop_requested and c.popen.poll() is not None:
                c.reported = True
                out.append(c)
        return out

    def running(self) -> list[_Child]:
        return [c for c in self.children if c.popen.poll() is None]

    # ------------------------------------------------------------------------------------------ stop
    def _signal_group(self, child: _Child, sig: int) -> None:
        try:
            os.killpg(child.pid, sig)   # the group of a child started with start_new_session: pgid == pid
        except (ProcessLookupError, PermissionError):
            pass

    def _wait(self, child: _Child, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while child.popen.poll() is None:
            if self.hurry.is_set() or time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return True

    def stop(self, child: _Child, timeout: float | None = None) -> None:
        """SIGINT to the child's process group, wait, SIGKILL the group when it did not exit in time."""
        child.stop_requested = True
        if child.popen.poll() is None:
            self._signal_group(child, signal.SIGINT)
            if not self._wait(child, child.spec.stop_timeout if timeout is None else timeout):
                if child.popen.poll() is None:
                    child.killed = True
                    why = 'second interrupt' if self.hurry.is_set() else f'no exit within {child.spec.stop_timeout:g} s'
                    self.announce(f'killing {child.spec.name} (pid {child.pid}): {why}')
                    self._signal_group(child, signal.SIGKILL)
                child.popen.wait()
        self._finish(child)

    def stop_all(self) -> None:
        """Stop every child in reverse start order, then SIGKILL whatever is left of their process groups
        (grandchildren a child did not take down with it)."""
        for child in reversed(self.children):
            self.stop(child)
        for child in self.children:
            self._signal_group(child, signal.SIGKILL)

    def _finish(self, child: _Child) -> None:
        for pump in child.pumps:
            pump.join(timeout=5.0)
        if child.log_file is not None and not child.log_file.closed:
            child.log_file.close()

    def results(self) -> list[ProcessResult]:
        out = []
        for c in self.children:
            rc = c.popen.poll()
            if rc is None:
                out.append(ProcessResult(c.spec.name, c.spec.role, c.pid, None, 'running'))
                continue
            if c.killed:
                how, failure = 'killed', f'did not stop within {c.spec.stop_timeout:g} s of SIGINT'
                if self.hurry.is_set():
                    failure = 'killed after a second interrupt'
            elif c.reported or not c.stop_requested:
                how = 'exited'
                # A player at the end of its bag and a closed tool window (rviz2) are not failures.
                failure = None if (c.spec.role in ('player', 'tool') and rc == 0) else (
                    f'exited on its own with code {rc}' if rc >= 0 else f'died of signal {-rc}')
            else:
                how = 'stopped'
                failure = None if rc in _CLEAN_STOP_CODES else f'exit code {rc} when stopped'
            out.append(ProcessResult(c.spec.name, c.spec.role, c.pid, rc, how, failure))
        return out


# ------------------------------------------------------------------------------------- graph monitor
class GraphMonitor:
    """The supervisor's own ROS node: counts /integrated_to_init and answers readiness questions about
    the ROS graph. rclpy runs in a background thread with its own context; call :meth:`close`."""

    def __init__(self, topic: str = OUTPUT_TOPIC):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from nav_msgs.msg import Odometry

        from lego_loam_py.ros import qos

        self._rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('lego_loam_py_launch', context=self.context,
                                      start_parameter_services=False)
        self.count = 0
        self.last_arrival: float | None = None
        self.node.create_subscription(Odometry, topic, self._on_output, qos.reliable(100), raw=True)
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name='graph-monitor', daemon=True)
        self._thread.start()

    def _on_output(self, _data) -> None:
        self.count += 1
        self.last_arrival = time.monotonic()

    def _spin(self) -> None:
        while not self._stop.is_set():
            try:
                self._executor.spin_once(timeout_sec=0.05)
            except Exception:  # context shut down under us
                break

    def not_ready(self, nodes: Sequence[str], recorded_topics: Sequence[str] = ()) -> list[str]:
        """What is still missing: nodes whose always-on topic has no publisher yet, recorded topics with a
        publisher but without the recorder's subscription."""
        missing = [name for name in nodes if not self.node.get_publishers_info_by_topic(READY_TOPICS[name])]
        for topic in recorded_topics:
            if self.node.get_publishers_info_by_topic(topic) and not any(
                    info.node_name == RECORDER_NODE for info in self.node.get_subscriptions_info_by_topic(topic)):
                missing.append(f'recorder on {topic}')
        return missing

    def close(self) -> None:
        from lego_loam_py.ros.runtime import finish_within

        self._stop.set()
        self._thread.join(timeout=2.0)

        def teardown() -> None:
            try:
                self._executor.shutdown(timeout_sec=0.5)
                self.node.destroy_node()
            finally:
                self._rclpy.try_shutdown(context=self.context)

        finish_within(teardown, "the supervisor's graph monitor shutdown")


# ------------------------------------------------------------------------------------------- pipeline
@dataclass
class PipelineConfig:
    """What :func:`run_pipeline` starts. ``overrides`` are ROS parameter assignments 'name:=value' for every
    node; ``ros_args`` more ROS arguments for every node (remappings, …). Times are seconds."""

    nodes: Sequence[str] = tuple(NODES)
    params_file: Path | None = None
    overrides: Sequence[str] = ()
    ros_args: Sequence[str] = ()
    use_sim_time: bool | None = None          # None: on when a bag is played
    bag: Path | None = None
    rate: float = 1.0
    start_offset: float = 0.0
    play_topics: Sequence[str] | None = None  # None: the lidar and IMU topics of the parameters
    player_progress: bool = False
    record_topics: Sequence[str] = ()
    record_all: bool = False
    record_output: Path | None = None
    stats_dir: Path | None = None
    rviz: bool = False
    rviz_config: Path | None = None
    keep_alive: bool = False                  # keep the nodes running after the bag ended
    ready_timeout: float = 60.0
    settle: float = 0.5                       # after ready, for the nodes to match each other's endpoints
    wait_for_subscribers: float = 20.0
    drain_quiet: float = 2.0
    drain_timeout: float = 30.0
    stop_timeout: float = 30.0
    output: str = 'screen'
    log_dir: Path | None = None


@dataclass
class PipelineOutcome:
    """How a run went; ``exit_code`` 0 means every process ran and stopped cleanly."""

    exit_code: int
    failures: list[str]
    processes: list[ProcessResult]
    interrupted: bool = False
    bag_finished: bool = False
    ready_after_s: float | None = None
    integrated_count: int = 0       # /integrated_to_init messages the supervisor received
    wall_time_s: float = 0.0


def _load_run_params(config: PipelineConfig):
    from lego_loam_py.core.params import load_params, parse_overrides
    return load_params(config.params_file, parse_overrides(list(config.overrides)), node_name='imageProjection')


def _node_specs(config: PipelineConfig, use_sim_time: bool) -> list[ProcessSpec]:
    ros_args = ['--ros-args']
    if config.params_file is not None:
        ros_args += ['--params-file', str(config.params_file)]
    for item in config.overrides:
        ros_args += ['-p', item]
    if use_sim_time:
        ros_args += ['-p', 'use_sim_time:=true']
    ros_args += list(config.ros_args)
    env = {'LEGO_LOAM_PY_STATS_DIR': str(config.stats_dir)} if config.stats_dir is not None else {}
    return [ProcessSpec(name, resolve_command(name, NODES[name]) + ros_args, role='node', env=dict(env),
                        stop_timeout=config.stop_timeout) for name in config.nodes]


def _play_topics(bag: Path, requested: Sequence[str] | None, params) -> list[str]:
    """The topics to replay: ``requested``, or the parameters' lidar topic (which must be in the bag) and
    IMU topic (when it is)."""
    from lego_loam_py.bag.io import BagError, BagReader
    with BagReader(bag) as reader:
        available = reader.topics()
    if requested is not None:
        return list(requested)
    cloud, imu = params.sensor.point_cloud_topic, params.sensor.imu_topic
    if cloud not in available:
        raise BagError(f'{bag}: no {cloud} topic (topics: {", ".join(sorted(available)) or "none"}); '
                       f'set sensor.point_cloud_topic or remap')
    return [cloud] + ([imu] if imu and imu in available else [])


def run_pipeline(config: PipelineConfig, stop: threading.Event | None = None, hurry: threading.Event | None = None,
                 announce: Callable[[str], None] | None = None) -> PipelineOutcome:
    """Start, watch, drain and stop the pipeline described by ``config`` (see the module docstring).

    ``stop`` ends the run from outside (the CLI sets it on SIGINT/SIGTERM); ``hurry`` (a second Ctrl-C)
    makes the shutdown kill instead of wait. Raises ``ParameterError`` or ``UsageError`` for an invalid
    configuration and ``BagError`` for a bag that cannot be read, before anything is started.
    """
    from lego_loam_py.bag.io import resolve_bag_path

    announce = announce or (lambda text: print(f'[launch] {text}', file=sys.stderr, flush=True))
    stop = stop or threading.Event()
    started_at = time.monotonic()
    unknown = [n for n in config.nodes if n not in NODES]
    if unknown:
        raise UsageError(f'unknown node(s) {", ".join(unknown)} (choose from {", ".join(NODES)})')
    if config.rate <= 0:
        raise UsageError('the rate must be positive')
    if config.output == 'log' and config.log_dir is None:
        raise UsageError("output 'log' needs a log directory")
    params = _load_run_params(config)          # invalid parameters stop here, before any process starts
    bag, play_topics = None, []
    if config.bag is not None:
        bag = resolve_bag_path(config.bag)
        play_topics = _play_topics(bag, config.play_topics, params)
    use_sim_time = bag is not None if config.use_sim_time is None else config.use_sim_time
    record = bool(config.record_topics) or config.record_all
    rviz_command = None
    if config.rviz:
        rviz_command = shutil.which('rviz2')
        if rviz_command is None:
            raise UsageError('rviz2 not found: it comes with a full ROS 2 install (source its setup.bash first)')
    if config.stats_dir is not None:
        Path(config.stats_dir).mkdir(parents=True, exist_ok=True)

    supervisor = Supervisor(output=config.output, log_dir=config.log_dir, announce=announce)
    if hurry is not None:
        supervisor.hurry = hurry
    failures: list[str] = []
    outcome = PipelineOutcome(exit_code=0, failures=failures, processes=[])
    cli = resolve_command(PACKAGE, 'lego_loam_py.cli')
    monitor = GraphMonitor()
    try:
        if record:
            argv = cli + ['record', *config.record_topics]
            argv += ['--all'] if config.record_all else []
            argv += ['-o', str(config.record_output)] if config.record_output is not None else []
            argv += ['--use-sim-time'] if use_sim_time else []
            supervisor.start(ProcessSpec('recorder', argv, role='recorder', stop_timeout=config.stop_timeout))
        for spec in _node_specs(config, use_sim_time):
            supervisor.start(spec)
        if rviz_command is not None:
            rviz_config = config.rviz_config or package_file('config', 'lego_loam.rviz')
            argv = [rviz_command, '-d', str(rviz_config)] + (
                ['--ros-args', '-p', 'use_sim_time:=true'] if use_sim_time else [])
            supervisor.start(ProcessSpec('rviz2', argv, role='tool', stop_timeout=config.stop_timeout))

        # ready: every node up (and the recorder subscribed), nothing crashed
        deadline = time.monotonic() + config.ready_timeout
        missing = monitor.not_ready(config.nodes, config.record_topics if record else ())
        while missing and not stop.is_set():
            crashed = supervisor.poll()
            if crashed:
                failures += [f'{c.spec.name} exited during start-up with code {c.popen.returncode}' for c in crashed]
                break
            if time.monotonic() >= deadline:
                failures.append(f'not ready within {config.ready_timeout:g} s: waiting for {", ".join(missing)}')
                break
            time.sleep(0.1)
            missing = monitor.not_ready(config.nodes, config.record_topics if record else ())
        if not failures and not stop.is_set():
            time.sleep(config.settle)
            outcome.ready_after_s = time.monotonic() - started_at
            announce(f'ready after {outcome.ready_after_s:.1f} s: {", ".join(config.nodes)}'
                     + (' (recording)' if record else ''))
            if bag is not None:
                argv = cli + ['play', str(bag), '--rate', f'{config.rate:g}', '--wait-for-subscribers',
                              f'{config.wait_for_subscribers:g}', '--topics', *play_topics]
                argv += ['--start-offset', f'{config.start_offset:g}'] if config.start_offset else []
                argv += [] if config.player_progress else ['--no-progress']
                supervisor.start(ProcessSpec('player', argv, role='player',
                                             output='inherit' if config.player_progress else None,
                                             stop_timeout=config.stop_timeout))
            _watch(config, supervisor, monitor, stop, failures, outcome, announce)
        outcome.interrupted = stop.is_set()
        if outcome.interrupted:
            announce('interrupted: stopping')
    finally:
        supervisor.stop_all()
        outcome.integrated_count = monitor.count
        monitor.close()
    outcome.processes = supervisor.results()
    for result in outcome.processes:
        if result.failure and not any(f.startswith(result.name + ' ') for f in failures):
            failures.append(f'{result.name} {result.failure}')
    outcome.exit_code = 1 if failures else 0
    outcome.wall_time_s = time.monotonic() - started_at
    for result in outcome.processes:
        announce(result.describe())
    return outcome


def _watch(config: PipelineConfig, supervisor: Supervisor, monitor: GraphMonitor, stop: threading.Event,
           failures: list[str], outcome: PipelineOutcome, announce: Callable[[str], None]) -> None:
    """Run until stopped, a crash, or the end of the bag plus the drain."""
    drain_started = None
    while not stop.is_set():
        for child in supervisor.poll():
            rc = child.popen.returncode
            if child.spec.role == 'player' and rc == 0:
                outcome.bag_finished = True
                if config.keep_alive:
                    announce('the bag ended; the nodes keep running (Ctrl-C stops them)')
                else:
                    drain_started = time.monotonic()
                    announce(f'the bag ended; draining (until no {OUTPUT_TOPIC} for {config.drain_quiet:g} s, '
                             f'at most {config.drain_timeout:g} s)')
            elif child.spec.role == 'tool' and rc == 0:
                announce(f'{child.spec.name} was closed; the nodes keep running')
            else:
                failures.append(f'{child.spec.name} exited on its own with code {rc}' if rc >= 0 else
                                f'{child.spec.name} died of signal {-rc}')
                announce(f'{child.spec.name} (pid {child.pid}) ended unexpectedly '
                         f'({"code " + str(rc) if rc >= 0 else "signal " + str(-rc)}): stopping everything')
                return
        if drain_started is not None:
            now = time.monotonic()
            last = max(drain_started, monitor.last_arrival or drain_started)
            if now - last >= config.drain_quiet:
                announce(f'drained: {monitor.count} {OUTPUT_TOPIC} messages; stopping')
                return
            if now - drain_started >= config.drain_timeout:
                announce(f'drain timeout ({config.drain_timeout:g} s): {OUTPUT_TOPIC} still arriving; stopping')
                return
        time.sleep(0.05)


# ------------------------------------------------------------------------------------------------ CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lego_loam_py.cli import add_parameter_arguments

    parser.add_argument('--bag', type=Path, default=None,
                        help='replay this bag (ROS 1 .bag or ROS 2 directory) with /clock; the nodes get '
                             'use_sim_time:=true and everything stops once the bag is played and drained')
    parser.add_argument('-r', '--rate', type=float, default=1.0, help='playback rate factor (default 1)')
    parser.add_argument('--start-offset', type=float, default=0.0, metavar='SEC', help='skip the bag\'s first SEC s')
    parser.add_argument('--progress', action='store_true', help="show the player's progress bar")
    parser.add_argument('--keep-alive', action='store_true',
                        help='keep the nodes running after the bag ended (stop with Ctrl-C), e.g. to look at RViz')
    add_parameter_arguments(parser, 'ROS 2 parameter file for all four nodes (default: config/params.yaml of the '
                            'package)', 'map_optimization.file_directory:=/tmp/maps')
    parser.add_argument('--use-sim-time', choices=['auto', 'true', 'false'], default='auto',
                        help='use_sim_time of the nodes (auto: true when replaying a bag)')
    parser.add_argument('--nodes', nargs='+', choices=list(NODES), default=list(NODES), metavar='NODE',
                        help=f'start only these nodes (default: all: {" ".join(NODES)})')
    parser.add_argument('--record', nargs='*', default=None, metavar='TOPIC',
                        help='record these topics (no topic: /integrated_to_init /laser_odom_to_init '
                             '/aft_mapped_to_init) into a ROS 2 bag (see -o)')
    parser.add_argument('--record-all', action='store_true', help='record every topic')
    parser.add_argument('-o', '--record-output', type=Path, default=None,
                        help='bag directory the recorder creates (default: rosbag2_<date>-<time>)')
    parser.add_argument('--stats-dir', type=Path, default=None,
                        help="each node writes <dir>/<node>.json (counters, timings) when it stops")
    parser.add_argument('--log-dir', type=Path, default=None,
                        help='also write every process\'s output to <dir>/<name>.log')
    parser.add_argument('--quiet-nodes', action='store_true',
                        help="nodes' output only into --log-dir files, not on the terminal")
    parser.add_argument('--rviz', action='store_true', help='start rviz2 with config/lego_loam.rviz (full ROS 2 '
                                                             'installs)')
    parser.add_argument('--rviz-config', type=Path, default=None, help='another .rviz file')
    parser.add_argument('--ready-timeout', type=float, default=60.0, metavar='SEC',
                        help='give up when the nodes are not up within SEC s (default 60)')
    parser.add_argument('--drain-quiet', type=float, default=2.0, metavar='SEC',
                        help='after the bag: stop once no /integrated_to_init came for SEC s (default 2)')
    parser.add_argument('--drain-timeout', type=float, default=30.0, metavar='SEC',
                        help='after the bag: stop after SEC s at most (default 30)')
    parser.add_argument('--stop-timeout', type=float, default=30.0, metavar='SEC',
                        help='SIGKILL a process that has not exited SEC s after SIGINT (default 30)')


DEFAULT_RECORD_TOPICS = ('/integrated_to_init', '/laser_odom_to_init', '/aft_mapped_to_init')


class Interrupts:
    """SIGINT/SIGTERM set ``stop``; a second one sets ``hurry`` too. Restores the old handlers on exit."""

    def __init__(self):
        self.stop = threading.Event()
        self.hurry = threading.Event()
        self._previous = {}

    def _handle(self, signum, _frame) -> None:
        if self.stop.is_set():
            self.hurry.set()
            print('[launch] second interrupt: killing the remaining processes', file=sys.stderr, flush=True)
        self.stop.set()

    def __enter__(self) -> 'Interrupts':
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def main(args: argparse.Namespace) -> int:
    if args.quiet_nodes and args.log_dir is None:
        raise UsageError('--quiet-nodes needs --log-dir')
    record_topics = list(DEFAULT_RECORD_TOPICS) if args.record == [] else list(args.record or [])
    ros_args = list(getattr(args, 'ros_args', None) or [])[1:]   # [program name, '--ros-args', ...]
    config = PipelineConfig(
        nodes=args.nodes, params_file=args.params_file or package_file('config', 'params.yaml'),
        overrides=args.param, ros_args=ros_args,
        use_sim_time=None if args.use_sim_time == 'auto' else args.use_sim_time == 'true',
        bag=args.bag, rate=args.rate, start_offset=args.start_offset, player_progress=args.progress,
        record_topics=record_topics, record_all=args.record_all, record_output=args.record_output,
        stats_dir=args.stats_dir, rviz=args.rviz, rviz_config=args.rviz_config, keep_alive=args.keep_alive,
        ready_timeout=args.ready_timeout, drain_quiet=args.drain_quiet, drain_timeout=args.drain_timeout,
        stop_timeout=args.stop_timeout, output='log' if args.quiet_nodes else 'screen', log_dir=args.log_dir)
    with Interrupts() as interrupts:
        outcome = run_pipeline(config, stop=interrupts.stop, hurry=interrupts.hurry)
    if outcome.failures:
        print('[launch] FAILED: ' + '; '.join(outcome.failures), file=sys.stderr, flush=True)
    else:
        print(f'[launch] done: every process stopped cleanly ({outcome.wall_time_s:.1f} s)', file=sys.stderr,
              flush=True)
    return outcome.exit_code


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='lego_loam.py', description=__doc__.split('\n\n')[1].replace('\n', ' '),
        epilog='ROS arguments for every node go after --ros-args (e.g. --ros-args -r /velodyne_points:=/points).')
    add_arguments(parser)
    return parser


def main_argv(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``launch_scripts/lego_loam.py``: the ``launch`` command with its own parser."""
    from lego_loam_py.cli import _split_ros_args, run_command

    ours, ros_args = _split_ros_args(list(sys.argv[1:] if argv is None else argv))
    args = build_parser().parse_args(ours)
    args.ros_args = ['lego_loam.py', *ros_args]
    return run_command(main, args)
