"""The launch supervisor (lego_loam_py launch), the ROS 2 launch file and the RViz configuration.

Supervisor mechanics are tested with small stand-in children (no DDS): stop order, SIGKILL escalation down
to grandchildren, crash reporting, children dying with a killed supervisor. The real nodes are tested for
Ctrl-C and for a crashed node. launch/launch_ros are not installable here: the launch file is executed
against stand-ins of their classes that accept only the real keyword arguments.
"""

from __future__ import annotations

import importlib.util
import os
import re
import runpy
import signal
import subprocess
import sys
import textwrap
import time
import types
from pathlib import Path

import pytest
import yaml

from lego_loam_py.testing.nodes import read_until, wait_for_line
from tests.support.topics import ALL, GATED

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
NODES = ('imageProjection', 'featureAssociation', 'mapOptimization', 'transformFusion')

# A stand-in child: logs "<name> <monotonic>" when it gets SIGINT and exits 0; 'ignore' ignores SIGINT,
# 'crash' exits 3 after a moment, 'grandchild' also starts a SIGINT-ignoring grandchild in its group.
FAKE_CHILD = textwrap.dedent("""
    import os, signal, subprocess, sys, time
    name, mode, log = sys.argv[1], sys.argv[2], sys.argv[3]
    def on_sigint(*_):
        with open(log, 'a') as f:
            f.write(f'{name} {time.monotonic()}\\n')
        sys.exit(0)
    signal.signal(signal.SIGINT, signal.SIG_IGN if mode in ('ignore', 'grandchild') else on_sigint)
    if mode == 'grandchild':
        g = subprocess.Popen([sys.executable, '-S', '-c',
                              'import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); time.sleep(600)'])
        print('grandchild', g.pid, flush=True)
    if mode == 'crash':
        time.sleep(0.3)
        sys.exit(3)
    print('up', os.getpid(), flush=True)
    while True:
        time.sleep(0.05)
""")


def fake(name: str, mode: str, log: Path, **kwargs):
    from lego_loam_py.supervisor import ProcessSpec

    return ProcessSpec(name, [sys.executable, '-S', '-c', FAKE_CHILD, name, mode, str(log)], **kwargs)


def alive(pid: int) -> bool:
    """True while the process exists and is not a zombie."""
    try:
        state = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0]
        return state not in ('Z', 'X')
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False


def wait_gone(pids, timeout: float) -> list[int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and any(alive(p) for p in pids):
        time.sleep(0.05)
    return [p for p in pids if alive(p)]


def started_pids(output: str) -> dict[str, int]:
    """name -> pid from the supervisor's 'started NAME (pid N)' lines."""
    return {m.group(1): int(m.group(2)) for m in re.finditer(r'started (\S+) \(pid (\d+)\)', output)}


def wait_for_file_lines(path: Path, count: int, timeout: float = 10.0) -> list[str]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        lines = path.read_text().splitlines() if path.exists() else []
        if len(lines) >= count:
            return lines
        time.sleep(0.05)
    raise AssertionError(f'{path}: fewer than {count} lines')


# ------------------------------------------------------------------------------ supervisor mechanics
def test_children_stop_in_reverse_start_order_and_exit_cleanly(tmp_path):
    from lego_loam_py.supervisor import Supervisor

    log = tmp_path / 'sigint.log'
    messages = []
    supervisor = Supervisor(output='log', log_dir=tmp_path / 'logs', announce=messages.append)
    children = [supervisor.start(fake(name, 'normal', log)) for name in ('first', 'second', 'third')]
    for name in ('first', 'second', 'third'):  # each child is up (its SIGINT handler installed)
        deadline = time.monotonic() + 10
        while 'up' not in (tmp_path / 'logs' / f'{name}.log').read_text() and time.monotonic() < deadline:
            time.sleep(0.05)
    assert all(os.getpgid(c.pid) == c.pid for c in children), 'every child leads its own process group'
    assert supervisor.poll() == []
    supervisor.stop_all()
    order = [line.split()[0] for line in log.read_text().splitlines()]
    assert order == ['third', 'second', 'first']
    results = supervisor.results()
    assert [(r.name, r.how, r.returncode, r.failure) for r in results] == [
        (n, 'stopped', 0, None) for n in ('first', 'second', 'third')
    ]
    assert not wait_gone([c.pid for c in children], 1.0)
    assert any('started first (pid' in m for m in messages)


def test_a_child_ignoring_sigint_is_killed_with_its_whole_process_group(tmp_path):
    from lego_loam_py.supervisor import Supervisor

    supervisor = Supervisor(output='log', log_dir=tmp_path / 'logs', announce=lambda _: None)
    child = supervisor.start(fake('stubborn', 'grandchild', tmp_path / 'x.log', stop_timeout=1.0))
    log = tmp_path / 'logs' / 'stubborn.log'
    lines = wait_for_file_lines(log, 2)
    grandchild = int(next(line.split()[1] for line in lines if line.startswith('grandchild')))
    assert alive(grandchild) and os.getpgid(grandchild) == child.pid
    start = time.monotonic()
    supervisor.stop_all()
    assert time.monotonic() - start < 5.0
    assert not wait_gone([child.pid, grandchild], 2.0), 'the child and its grandchild are gone'
    (result,) = supervisor.results()
    assert result.how == 'killed' and result.returncode == -signal.SIGKILL
    assert 'did not stop within 1 s' in result.failure


def test_a_child_that_exits_on_its_own_is_reported_once_as_a_failure(tmp_path):
    from lego_loam_py.supervisor import ProcessSpec, Supervisor

    supervisor = Supervisor(output='log', log_dir=tmp_path / 'logs', announce=lambda _: None)
    crasher = supervisor.start(fake('crasher', 'crash', tmp_path / 'x.log'))
    supervisor.start(fake('steady', 'normal', tmp_path / 'x.log'))
    player = supervisor.start(ProcessSpec('player', [sys.executable, '-S', '-c', 'pass'], role='player'))
    supervisor.start(ProcessSpec('viewer', [sys.executable, '-S', '-c', 'pass'], role='tool'))
    deadline = time.monotonic() + 10
    exited = []
    while len(exited) < 3 and time.monotonic() < deadline:
        exited += supervisor.poll()
        time.sleep(0.05)
    assert sorted(c.spec.name for c in exited) == ['crasher', 'player', 'viewer']
    assert supervisor.poll() == []  # reported once
    supervisor.stop_all()
    results = {r.name: r for r in supervisor.results()}
    assert results['crasher'].how == 'exited' and results['crasher'].failure == 'exited on its own with code 3'
    assert results['player'].how == 'exited' and results['player'].failure is None  # a bag that ended
    assert results['viewer'].how == 'exited' and results['viewer'].failure is None  # rviz2 closed
    assert results['steady'].how == 'stopped' and results['steady'].failure is None
    assert crasher.popen.returncode == 3 and player.popen.returncode == 0


def test_children_die_with_a_killed_supervisor(tmp_path, processes):
    """kill -9 of the supervisor: the kernel sends SIGTERM to its children (PR_SET_PDEATHSIG): no orphans."""
    driver = textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(REPO)!r})
        from lego_loam_py.supervisor import ProcessSpec, Supervisor
        code = {FAKE_CHILD!r}
        supervisor = Supervisor(output='log', log_dir={str(tmp_path / 'logs')!r}, announce=lambda _: None)
        pids = [supervisor.start(ProcessSpec(n, [sys.executable, '-S', '-c', code, n, 'normal', 'x'])).pid
                for n in ('a', 'b')]
        print('pids', *pids, flush=True)
        time.sleep(600)
    """)
    proc = processes.python('-c', driver)
    line = wait_for_line(proc, 'pids', timeout=30)
    pids = [int(p) for p in line.split()[1:]]
    assert len(pids) == 2 and all(alive(p) for p in pids)
    processes.stop(proc, signal.SIGKILL)
    survivors = wait_gone(pids, 10.0)
    for pid in survivors:  # do not leave them behind when the test fails
        os.kill(pid, signal.SIGKILL)
    assert not survivors, 'children of a killed supervisor must not survive it'


# ------------------------------------------------------------------------------------ the real nodes
def _start_launch(processes, tmp_path, *extra):
    args = [
        BIN / 'lego_loam_py',
        'launch',
        '--stats-dir',
        tmp_path / 'stats',
        '--log-dir',
        tmp_path / 'logs',
        '--quiet-nodes',
        '-p',
        f'map_optimization.file_directory:={tmp_path / "maps"}',
        *extra,
    ]
    return processes.start(args, stderr=subprocess.STDOUT)


def _logs(tmp_path: Path) -> str:
    return '\n'.join(f'--- {p.name}\n{p.read_text()[-2000:]}' for p in sorted((tmp_path / 'logs').glob('*.log')))


def test_ctrl_c_stops_every_node_cleanly(tmp_path, ros_domain, processes):
    launcher = _start_launch(processes, tmp_path)
    head = read_until(launcher, 'ready after', timeout=90)
    assert 'ready after' in head and 'imageProjection, featureAssociation, mapOptimization, transformFusion' in head
    os.kill(launcher.pid, signal.SIGINT)  # what Ctrl-C in a terminal does: only the supervisor gets it
    out, _ = launcher.communicate(timeout=60)
    out = head + out
    assert launcher.returncode == 0, out + _logs(tmp_path)
    pids = started_pids(out)
    assert set(pids) == set(NODES)
    for name in NODES:
        assert f'{name} (pid {pids[name]}): stopped, exit code 0' in out, out
        # Each node ran its shutdown hook (statistics written): it was stopped by SIGINT, not killed.
        assert (tmp_path / 'stats' / f'{name}.json').is_file(), name
    assert 'done: every process stopped cleanly' in out
    assert not wait_gone(pids.values(), 2.0), 'no process of the run is left'
    assert 'Traceback' not in _logs(tmp_path)


def test_composed_the_four_nodes_run_in_one_process_and_stop_cleanly(tmp_path, ros_domain, processes):
    launcher = _start_launch(processes, tmp_path, '--composed')
    head = read_until(launcher, 'ready after', timeout=90)
    assert 'ready after' in head and 'imageProjection, featureAssociation, mapOptimization, transformFusion' in head
    os.kill(launcher.pid, signal.SIGINT)
    out, _ = launcher.communicate(timeout=60)
    out = head + out
    assert launcher.returncode == 0, out + _logs(tmp_path)
    pids = started_pids(out)
    assert set(pids) == {'legoLoam'}
    assert f'legoLoam (pid {pids["legoLoam"]}): stopped, exit code 0' in out, out
    for name in NODES:  # every node's shutdown hook ran, in the one process
        assert (tmp_path / 'stats' / f'{name}.json').is_file(), name
    assert 'handed over in memory: /aft_mapped_to_init, /laser_cloud_corner_last' in _logs(tmp_path)
    assert not wait_gone(pids.values(), 2.0)
    assert 'Traceback' not in _logs(tmp_path)


def test_composed_runs_all_four_nodes_or_none(tmp_path):
    result = subprocess.run(
        [BIN / 'lego_loam_py', 'launch', '--composed', '--nodes', 'imageProjection'],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert 'the composed process runs all four nodes' in result.stderr
    assert 'started' not in result.stderr and 'Traceback' not in result.stderr


def test_a_crashed_node_stops_the_run_with_a_failure(tmp_path, ros_domain, processes):
    launcher = _start_launch(processes, tmp_path, '--nodes', 'imageProjection', 'featureAssociation')
    head = read_until(launcher, 'ready after', timeout=90)
    pids = started_pids(head)
    assert set(pids) == {'imageProjection', 'featureAssociation'}
    os.kill(pids['featureAssociation'], signal.SIGKILL)  # a crash
    out, _ = launcher.communicate(timeout=60)
    out = head + out
    assert launcher.returncode == 1, out
    assert 'featureAssociation (pid' in out and 'ended unexpectedly (signal 9): stopping everything' in out
    assert f'imageProjection (pid {pids["imageProjection"]}): stopped, exit code 0' in out
    assert 'FAILED: featureAssociation died of signal 9' in out
    assert not wait_gone(pids.values(), 2.0)


def test_invalid_parameters_stop_before_anything_starts(tmp_path, ros_domain):
    result = subprocess.run(
        [BIN / 'lego_loam_py', 'launch', '-p', 'sensor.n_scann:=16'], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2
    assert "unknown parameter 'sensor.n_scann' (did you mean 'sensor.n_scan'?)" in result.stderr
    assert 'started' not in result.stderr
    result = subprocess.run(
        [BIN / 'lego_loam_py', 'launch', '--bag', tmp_path / 'missing'], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 1 and 'bag not found' in result.stderr  # (data, as for every command)
    assert 'Traceback' not in result.stderr and 'started' not in result.stderr


def test_cli_and_launch_script_offer_the_supervisor():
    from lego_loam_py.cli import COMMANDS

    names = [c[0] for c in COMMANDS]
    assert 'launch' in names and 'demo' in names
    result = subprocess.run(
        [sys.executable, REPO / 'launch_scripts' / 'lego_loam.py', '--help'], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0 and '--bag' in result.stdout and '--record' in result.stdout
    # ./demo.sh: install.sh (a no-op here), then `lego_loam_py demo` with the arguments passed on.
    assert os.access(REPO / 'demo.sh', os.X_OK)
    result = subprocess.run([REPO / 'demo.sh', '--help'], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith('usage: lego_loam_py demo') and 'output/demo-<bag name>' in result.stdout


# ---------------------------------------------------------------------------- launch file and RViz
class _Stand:
    """Base of the stand-ins for launch / launch_ros classes: keeps what it was given."""

    ALLOWED: tuple[str, ...] = ()
    POSITIONAL = 0

    def __init__(self, *args, **kwargs):
        assert len(args) <= self.POSITIONAL, f'{type(self).__name__}: too many positional arguments {args}'
        unknown = set(kwargs) - set(self.ALLOWED)
        assert not unknown, f'{type(self).__name__}() got unexpected keyword arguments {sorted(unknown)}'
        self.args, self.kwargs = args, kwargs

    def __eq__(self, other):
        return type(self) is type(other) and self.args == other.args and self.kwargs == other.kwargs

    __hash__ = None

    def __repr__(self):
        return f'{type(self).__name__}{self.args}{self.kwargs}'


def _stand(name: str, positional: int = 0, allowed: tuple[str, ...] = ()):
    return type(name, (_Stand,), {'POSITIONAL': positional, 'ALLOWED': allowed})


# The keyword arguments of the real classes (launch / launch_ros, Humble .. Kilted) the launch file may use.
_ACTION = ('condition',)
_EXECUTE_PROCESS = _ACTION + (
    'output',
    'emulate_tty',
    'respawn',
    'respawn_delay',
    'sigterm_timeout',
    'sigkill_timeout',
    'additional_env',
    'cwd',
    'shell',
    'prefix',
    'on_exit',
)
STANDS = {
    'launch': {'LaunchDescription': _stand('LaunchDescription', 1)},
    'launch.actions': {
        'DeclareLaunchArgument': _stand('DeclareLaunchArgument', 1, ('default_value', 'description', 'choices')),
        'EmitEvent': _stand('EmitEvent', 0, ('event',)),
        'GroupAction': _stand('GroupAction', 1, _ACTION + ('actions', 'scoped', 'forwarding', 'launch_configurations')),
        'LogInfo': _stand('LogInfo', 0, ('msg',)),
        'RegisterEventHandler': _stand('RegisterEventHandler', 1, ('event_handler',)),
        'TimerAction': _stand('TimerAction', 0, _ACTION + ('period', 'actions', 'cancel_on_shutdown')),
    },
    'launch.conditions': {'IfCondition': _stand('IfCondition', 1), 'UnlessCondition': _stand('UnlessCondition', 1)},
    'launch.event_handlers': {'OnProcessExit': _stand('OnProcessExit', 0, ('target_action', 'on_exit'))},
    'launch.events': {'Shutdown': _stand('Shutdown', 0, ('reason',))},
    'launch.substitutions': {
        'LaunchConfiguration': _stand('LaunchConfiguration', 1, ('default',)),
        'PathJoinSubstitution': _stand('PathJoinSubstitution', 1),
        'PythonExpression': _stand('PythonExpression', 1),
    },
    'launch_ros.actions': {
        'Node': _stand(
            'Node',
            0,
            _EXECUTE_PROCESS
            + (
                'executable',
                'package',
                'name',
                'namespace',
                'exec_name',
                'parameters',
                'remappings',
                'ros_arguments',
                'arguments',
            ),
        )
    },
    'launch_ros.parameter_descriptions': {'ParameterValue': _stand('ParameterValue', 1, ('value_type',))},
    'launch_ros.substitutions': {'FindPackageShare': _stand('FindPackageShare', 1)},
}


@pytest.fixture
def stand_in_launch(monkeypatch):
    for package in ('launch', 'launch_ros'):
        monkeypatch.setitem(sys.modules, package, types.ModuleType(package))
    for module_name, classes in STANDS.items():
        module = sys.modules[module_name] if module_name in ('launch',) else types.ModuleType(module_name)
        for name, cls in classes.items():
            setattr(module, name, cls)
        monkeypatch.setitem(sys.modules, module_name, module)
    return {name: cls for classes in STANDS.values() for name, cls in classes.items()}


def _load_launch_file(path: Path):
    spec = importlib.util.spec_from_file_location('lego_loam_launch_under_test', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def test_launch_file_builds_the_four_nodes_rviz_and_the_player(stand_in_launch):
    s = stand_in_launch
    description = _load_launch_file(REPO / 'launch' / 'lego_loam.launch.py')
    assert isinstance(description, s['LaunchDescription'])
    entities = description.args[0]
    arguments = {e.args[0]: e.kwargs for e in entities if isinstance(e, s['DeclareLaunchArgument'])}
    assert set(arguments) >= {'params_file', 'use_sim_time', 'rviz', 'rviz_config', 'bag', 'rate'}
    assert arguments['use_sim_time']['default_value'] == 'true'  # like the original's run.launch
    share = s['FindPackageShare']('lego_loam_py')
    assert arguments['params_file']['default_value'] == s['PathJoinSubstitution']([share, 'config', 'params.yaml'])
    assert arguments['rviz_config']['default_value'] == s['PathJoinSubstitution']([share, 'config', 'lego_loam.rviz'])

    nodes = [e for e in entities if isinstance(e, s['Node'])]
    pipeline = [n for n in nodes if n.kwargs['package'] == 'lego_loam_py' and n.kwargs['executable'] in NODES]
    assert [n.kwargs['executable'] for n in pipeline] == list(NODES)
    sim_time = {'use_sim_time': s['ParameterValue'](s['LaunchConfiguration']('use_sim_time'), value_type=bool)}
    for node in pipeline:
        assert node.kwargs['name'] == node.kwargs['executable']
        assert node.kwargs['parameters'] == [s['LaunchConfiguration']('params_file'), sim_time]
        assert node.kwargs['condition'] == s['UnlessCondition'](s['LaunchConfiguration']('composed'))
    # composed:=true: the four in one process instead, under their own names (a name would rename all four).
    (composed,) = [n for n in nodes if n.kwargs['executable'] == 'legoLoam']
    assert 'name' not in composed.kwargs
    assert composed.kwargs['parameters'] == [s['LaunchConfiguration']('params_file'), sim_time]
    assert composed.kwargs['condition'] == s['IfCondition'](s['LaunchConfiguration']('composed'))
    assert arguments['composed']['default_value'] == 'false'
    (rviz,) = [n for n in nodes if n.kwargs['package'] == 'rviz2']
    assert rviz.kwargs['arguments'] == ['-d', s['LaunchConfiguration']('rviz_config')]
    assert rviz.kwargs['condition'] == s['IfCondition'](s['LaunchConfiguration']('rviz'))
    (player,) = [n for n in nodes if n.kwargs['executable'] == 'lego_loam_py']
    assert player.kwargs['arguments'][:2] == ['play', s['LaunchConfiguration']('bag')]
    (group,) = [e for e in entities if isinstance(e, s['GroupAction'])]
    (handler,) = group.kwargs['actions']
    assert handler.args[0].kwargs['target_action'] is player
    # Every executable the file starts is one this package installs.
    scripts = runpy.run_path(str(REPO / 'setup.py'), run_name='setup_under_test')['CONSOLE_SCRIPTS']
    installed = {entry.split('=')[0].strip() for entry in scripts}
    assert {n.kwargs['executable'] for n in nodes if n.kwargs['package'] == 'lego_loam_py'} <= installed


def test_stand_ins_reject_what_the_real_classes_reject(stand_in_launch):
    """The launch-file test can fail: a misspelt keyword is caught."""
    with pytest.raises(AssertionError, match='unexpected keyword'):
        stand_in_launch['Node'](package='lego_loam_py', executable='imageProjection', paramters=[])


def test_setup_installs_the_launch_file_and_the_rviz_config():
    from ament_index_python.packages import get_package_share_directory

    data_files = dict(runpy.run_path(str(REPO / 'setup.py'), run_name='setup_under_test')['DATA_FILES'])
    assert 'launch/lego_loam.launch.py' in data_files['share/lego_loam_py/launch']
    assert 'config/lego_loam.rviz' in data_files['share/lego_loam_py/config']
    share = Path(get_package_share_directory('lego_loam_py'))
    assert (share / 'launch' / 'lego_loam.launch.py').is_file()
    assert (share / 'config' / 'lego_loam.rviz').is_file()


def test_rviz_config_shows_the_pipeline_in_the_map_frame():
    config = yaml.safe_load((REPO / 'config' / 'lego_loam.rviz').read_text())
    manager = config['Visualization Manager']
    assert manager['Global Options']['Fixed Frame'] == 'map'
    displays = manager['Displays']
    assert all(d['Class'].startswith('rviz_default_plugins/') for d in displays)
    by_topic = {d['Topic']['Value']: d for d in displays if 'Topic' in d}
    for topic in ('/laser_cloud_surround', '/registered_cloud', '/key_pose_origin', '/segmented_cloud_pure'):
        assert by_topic[topic]['Class'] == 'rviz_default_plugins/PointCloud2' and by_topic[topic]['Enabled'], topic
    assert by_topic['/integrated_to_init']['Class'] == 'rviz_default_plugins/Odometry'
    # The loop markers are latched: the display must ask for transient local to get them after they were sent.
    assert by_topic['/loop_closures']['Topic']['Durability Policy'] == 'Transient Local'
    # So is the occupancy grid (off by default: while shown, mapOptimization converts and publishes it).
    assert by_topic['/map']['Topic']['Durability Policy'] == 'Transient Local' and not by_topic['/map']['Enabled']
    assert any(d['Class'] == 'rviz_default_plugins/TF' and d['Enabled'] for d in displays)
    for topic, display in by_topic.items():  # only topics the pipeline publishes, with a matching display
        assert topic in ALL, topic
        expected = {
            'sensor_msgs/msg/PointCloud2': 'PointCloud2',
            'nav_msgs/msg/Odometry': 'Odometry',
            'visualization_msgs/msg/MarkerArray': 'MarkerArray',
            'nav_msgs/msg/OccupancyGrid': 'Map',
        }[ALL[topic][1]]
        assert display['Class'] == f'rviz_default_plugins/{expected}', topic
        assert display['Topic']['Reliability Policy'] == 'Reliable'  # the nodes publish reliable
    # Subscriber-gated clouds that are off by default cost nothing until switched on.
    assert {t for t, d in by_topic.items() if d['Enabled'] and t in GATED} == {
        '/laser_cloud_surround',
        '/registered_cloud',
        '/key_pose_origin',
        '/segmented_cloud_pure',
    }
