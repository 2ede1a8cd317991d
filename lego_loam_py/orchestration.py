"""The four nodes as one supervised pipeline: start, wait until ready, replay, drain, stop.

:func:`run_pipeline` is what ``lego_loam_py launch`` (:mod:`lego_loam_py.launch`, the command line) and
``lego_loam_py demo`` run: imageProjection, featureAssociation, mapOptimization and transformFusion as
separate processes with one parameter file, optionally the bag player (``-p use_sim_time:=true`` for every
node then), the recorder and rviz2. The processes are the :class:`~lego_loam_py.supervisor.Supervisor`'s;
the ROS graph is watched by :class:`~lego_loam_py.ros.graph_monitor.GraphMonitor`.

Life of a run:

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
"""

from __future__ import annotations

import shutil
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from lego_loam_py.errors import UsageError
from lego_loam_py.supervisor import PACKAGE, ProcessResult, ProcessSpec, Supervisor, package_file, resolve_command

if TYPE_CHECKING:
    from lego_loam_py.ros.graph_monitor import GraphMonitor

__all__ = ['NODES', 'READY_TOPICS', 'DEFAULT_RECORD_TOPICS', 'PipelineConfig', 'PipelineOutcome', 'run_pipeline']

# Executable -> module with a main(), in pipeline order.
NODES = {
    'imageProjection': 'lego_loam_py.ros.image_projection_node',
    'featureAssociation': 'lego_loam_py.ros.feature_association_node',
    'mapOptimization': 'lego_loam_py.ros.map_optimization_node',
    'transformFusion': 'lego_loam_py.ros.transform_fusion_node',
}
# The four nodes in one process (their messages to each other in memory: lego_loam_py.ros.composition).
COMPOSED = ('legoLoam', 'lego_loam_py.ros.composed_node')
# A topic each node publishes from start-up on: its publisher in the ROS graph means the node is up.
READY_TOPICS = {
    'imageProjection': '/segmented_cloud_info',
    'featureAssociation': '/laser_odom_to_init',
    'mapOptimization': '/aft_mapped_to_init',
    'transformFusion': '/integrated_to_init',
}
RECORDER_NODE = 'lego_loam_py_recorder'  # the ROS node name of `lego_loam_py record`
OUTPUT_TOPIC = '/integrated_to_init'

# The pipeline's odometry outputs: what a run records unless told otherwise.
DEFAULT_RECORD_TOPICS = ('/integrated_to_init', '/laser_odom_to_init', '/aft_mapped_to_init')


@dataclass
class PipelineConfig:
    """What :func:`run_pipeline` starts. ``overrides`` are ROS parameter assignments 'name:=value' for every
    node; ``ros_args`` more ROS arguments for every node (remappings, …). Times are seconds."""

    nodes: Sequence[str] = tuple(NODES)
    composed: bool = False  # the four nodes in one process (legoLoam) instead of four
    params_file: Path | None = None
    overrides: Sequence[str] = ()
    ros_args: Sequence[str] = ()
    use_sim_time: bool | None = None  # None: on when a bag is played
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
    viewer: bool = False  # `lego_loam_py viewer` beside the nodes: a Rerun window ...
    viewer_save: Path | None = None  # ... and/or a .rrd recording of it
    keep_alive: bool = False  # keep the nodes running after the bag ended
    ready_timeout: float = 60.0
    settle: float = 0.5  # after ready, for the nodes to match each other's endpoints
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
    integrated_count: int = 0  # /integrated_to_init messages the supervisor received
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
    commands = {COMPOSED[0]: COMPOSED[1]} if config.composed else {name: NODES[name] for name in config.nodes}
    return [
        ProcessSpec(
            name, resolve_command(name, module) + ros_args, role='node', env=dict(env), stop_timeout=config.stop_timeout
        )
        for name, module in commands.items()
    ]


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
        raise BagError(
            f'{bag}: no {cloud} topic (topics: {", ".join(sorted(available)) or "none"}); '
            f'set sensor.point_cloud_topic or remap'
        )
    return [cloud] + ([imu] if imu and imu in available else [])


def run_pipeline(
    config: PipelineConfig,
    stop: threading.Event | None = None,
    hurry: threading.Event | None = None,
    announce: Callable[[str], None] | None = None,
) -> PipelineOutcome:
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
    if config.composed and list(config.nodes) != list(NODES):
        raise UsageError(
            f'the composed process runs all four nodes: {", ".join(config.nodes)} cannot be chosen with it'
        )
    if config.rate <= 0:
        raise UsageError('the rate must be positive')
    if config.output == 'log' and config.log_dir is None:
        raise UsageError("output 'log' needs a log directory")
    params = _load_run_params(config)  # invalid parameters stop here, before any process starts
    if params.map_optimization.mode == 'localization' and 'mapOptimization' in config.nodes:
        from lego_loam_py.core.mapping.map_bundle import read_manifest

        read_manifest(params.map_optimization.map_path)  # (and so does a saved map that is not there)
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
    if config.viewer or config.viewer_save is not None:
        from lego_loam_py.viewer import require_rerun

        require_rerun()  # (says what to install before anything starts)
    if config.stats_dir is not None:
        Path(config.stats_dir).mkdir(parents=True, exist_ok=True)

    supervisor = Supervisor(output=config.output, log_dir=config.log_dir, announce=announce)
    if hurry is not None:
        supervisor.hurry = hurry
    failures: list[str] = []
    outcome = PipelineOutcome(exit_code=0, failures=failures, processes=[])
    cli = resolve_command(PACKAGE, 'lego_loam_py.cli')
    from lego_loam_py.ros.graph_monitor import GraphMonitor  # (rclpy loads only for a run, not for --help)

    monitor = GraphMonitor(OUTPUT_TOPIC, READY_TOPICS, RECORDER_NODE)
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
                ['--ros-args', '-p', 'use_sim_time:=true'] if use_sim_time else []
            )
            supervisor.start(ProcessSpec('rviz2', argv, role='tool', stop_timeout=config.stop_timeout))
        if config.viewer or config.viewer_save is not None:
            argv = (
                cli
                + ['viewer']
                + (['--save', str(config.viewer_save)] if config.viewer_save else [])
                + ([] if config.viewer else ['--no-window'])
            )
            supervisor.start(ProcessSpec('viewer', argv, role='tool', stop_timeout=config.stop_timeout))

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
            announce(
                f'ready after {outcome.ready_after_s:.1f} s: {", ".join(config.nodes)}'
                + (' (recording)' if record else '')
            )
            if bag is not None:
                argv = cli + [
                    'play',
                    str(bag),
                    '--rate',
                    f'{config.rate:g}',
                    '--wait-for-subscribers',
                    f'{config.wait_for_subscribers:g}',
                    '--topics',
                    *play_topics,
                ]
                argv += ['--start-offset', f'{config.start_offset:g}'] if config.start_offset else []
                argv += [] if config.player_progress else ['--no-progress']
                supervisor.start(
                    ProcessSpec(
                        'player',
                        argv,
                        role='player',
                        output='inherit' if config.player_progress else None,
                        stop_timeout=config.stop_timeout,
                    )
                )
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


def _watch(
    config: PipelineConfig,
    supervisor: Supervisor,
    monitor: GraphMonitor,
    stop: threading.Event,
    failures: list[str],
    outcome: PipelineOutcome,
    announce: Callable[[str], None],
) -> None:
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
                    announce(
                        f'the bag ended; draining (until no {OUTPUT_TOPIC} for {config.drain_quiet:g} s, '
                        f'at most {config.drain_timeout:g} s)'
                    )
            elif child.spec.role == 'tool' and rc == 0:
                announce(f'{child.spec.name} was closed; the nodes keep running')
            else:
                failures.append(
                    f'{child.spec.name} exited on its own with code {rc}'
                    if rc >= 0
                    else f'{child.spec.name} died of signal {-rc}'
                )
                announce(
                    f'{child.spec.name} (pid {child.pid}) ended unexpectedly '
                    f'({"code " + str(rc) if rc >= 0 else "signal " + str(-rc)}): stopping everything'
                )
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
