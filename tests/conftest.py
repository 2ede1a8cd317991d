"""Shared fixtures: isolated DDS domains, child processes that are always reaped, the shared data."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from lego_loam_py.testing.domains import DomainLease

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get('LEGO_LOAM_SHARED', REPO.parent / 'shared'))


@pytest.fixture
def ros_domain(monkeypatch):
    """A ROS_DOMAIN_ID no other test run on this machine uses; exported for child processes."""
    with DomainLease() as domain_id:
        monkeypatch.setenv('ROS_DOMAIN_ID', str(domain_id))
        monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        yield domain_id


@pytest.fixture(scope='module')
def context():
    """An rclpy context of its own on a leased domain, shared by a module's in-process tests (nodes whose handlers are
    called directly)."""
    import rclpy
    from rclpy.context import Context

    from lego_loam_py.testing.domains import DomainLease

    with DomainLease() as domain_id:
        ctx = Context()
        rclpy.init(context=ctx, domain_id=domain_id)
        yield ctx
        rclpy.try_shutdown(context=ctx)


@pytest.fixture
def rclpy_context(ros_domain):
    """An initialised rclpy context of its own on the test's domain; shut down afterwards."""
    import rclpy
    from rclpy.context import Context

    from lego_loam_py.ros.runtime import finish_within

    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    yield context
    # (Bounded: a participant stuck in the DDS library must not hang the run; see lego_loam_py.testing.nodes.release.)
    finish_within(lambda: rclpy.try_shutdown(context=context), 'shutting down the test context', 10.0)


class Processes:
    """Child processes started by a test, each in its own process group; all are ended at teardown."""

    def __init__(self):
        self.started: list[subprocess.Popen] = []

    def start(self, args, **kwargs) -> subprocess.Popen:
        kwargs.setdefault('stdout', subprocess.PIPE)
        kwargs.setdefault('stderr', subprocess.PIPE)
        kwargs.setdefault('text', True)
        proc = subprocess.Popen([str(a) for a in args], start_new_session=True, **kwargs)
        self.started.append(proc)
        return proc

    def python(self, *args, **kwargs) -> subprocess.Popen:
        return self.start([sys.executable, *args], **kwargs)

    def stop(self, proc: subprocess.Popen, sig=signal.SIGINT, timeout: float = 10.0):
        """Signal the process (group) and wait; SIGKILL if it does not exit in time. Returns (out, err)."""
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                pass
        try:
            return proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            return proc.communicate()

    def cleanup(self):
        for proc in self.started:
            if proc.poll() is None:
                self.stop(proc, signal.SIGKILL, timeout=5.0)


@pytest.fixture
def processes():
    procs = Processes()
    yield procs
    procs.cleanup()


@pytest.fixture(scope='session')
def campus_map(tmp_path_factory) -> Path:
    """The map bundle (and PCDs) that ``lego_loam_py run bags/campus_8s`` saves: 20 keyframes, 13 m of the campus."""
    from lego_loam_py.core.params import Params
    from lego_loam_py.offline import run_bag

    directory = tmp_path_factory.mktemp('campus_map')
    result = run_bag(REPO / 'bags' / 'campus_8s', Params(), progress=False)
    result.mapper.save(directory)
    return directory


@pytest.fixture(scope='session')
def shared_data() -> Path:
    """../shared/data; missing data fails when LEGO_LOAM_REQUIRE_SHARED=1 (CI), skips otherwise."""
    path = SHARED / 'data'
    if not path.is_dir():
        message = f'shared data not found at {path} (set LEGO_LOAM_SHARED)'
        if os.environ.get('LEGO_LOAM_REQUIRE_SHARED') == '1':
            pytest.fail(message)
        pytest.skip(message)
    return path


_EXIT_STATUS: list[int] = []


def pytest_sessionfinish(session, exitstatus):
    _EXIT_STATUS.append(int(exitstatus))


def pytest_unconfigure(config):
    """A DDS participant left stuck by a test (see lego_loam_py.testing.nodes.release) would hang interpreter exit:
    end the process with the session's status instead, once pytest has reported everything."""
    runtime = sys.modules.get('lego_loam_py.ros.runtime')
    if runtime is not None and runtime.stuck_teardowns() and _EXIT_STATUS:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_EXIT_STATUS[-1])
