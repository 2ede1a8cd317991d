"""Child processes in their own process groups, started, watched and stopped in order (ROS-free).

What ``lego_loam_py launch`` and the demo use to run the four nodes, the player, the recorder and rviz2
as separate processes: :class:`Supervisor` starts each child in its own session (a Ctrl-C in the terminal
reaches only the supervisor), reports the children that exit on their own, and stops them in reverse start
order with SIGINT, then SIGKILL to each process group after its ``stop_timeout``. On Linux every child also
gets SIGTERM from the kernel when the supervisor dies (``PR_SET_PDEATHSIG``), so even a ``kill -9`` of the
supervisor leaves no orphan. :class:`Interrupts` turns SIGINT/SIGTERM into events the caller polls.

This module knows processes, not ROS: it imports no rclpy (the ROS graph is watched by
:mod:`lego_loam_py.ros.graph_monitor`, the pipeline put together by :mod:`lego_loam_py.orchestration`).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

__all__ = ['PACKAGE', 'ProcessSpec', 'ProcessResult', 'Supervisor', 'Interrupts', 'package_file', 'resolve_command']

PACKAGE = 'lego_loam_py'
# Exit statuses that mean "stopped by the signal we sent" (SIGINT during start-up, before a node installed
# its handler, kills it with the signal itself).
_CLEAN_STOP_CODES = (0, -signal.SIGINT, 128 + signal.SIGINT)

# Run argv[2:] with PR_SET_PDEATHSIG = SIGTERM: the kernel stops the child when the supervisor dies, even
# by SIGKILL. A bare interpreter (-I -S: no site, no .pth, only ctypes) sets it and execs the real command,
# so no Python code runs in a forked copy of the (multi-threaded) supervisor.
_PDEATHSIG_EXEC = (
    'import ctypes, os, sys\n'
    'ctypes.CDLL(None, use_errno=True).prctl(1, 15, 0, 0, 0)\n'  # PR_SET_PDEATHSIG, SIGTERM
    'if os.getppid() != int(sys.argv[1]):\n'  # the supervisor died before prctl
    '    sys.exit(143)\n'
    'os.execvp(sys.argv[2], sys.argv[2:])\n'
)


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
    candidates += [
        Path(prefix, 'lib', PACKAGE, executable)
        for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)
        if prefix
    ]
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
        code = (
            'no exit code'
            if self.returncode is None
            else (f'signal {-self.returncode}' if self.returncode < 0 else f'exit code {self.returncode}')
        )
        text = {'stopped': 'stopped', 'exited': 'exited on its own', 'killed': 'killed', 'running': 'still running'}[
            self.how
        ]
        return f'{self.name} (pid {self.pid}): {text}, {code}' + (f' - FAILED: {self.failure}' if self.failure else '')


class _Child:
    def __init__(self, spec: ProcessSpec, popen: subprocess.Popen, log_file, pumps: list[threading.Thread]):
        self.spec = spec
        self.popen = popen
        self.log_file = log_file
        self.pumps = pumps
        self.stop_requested = False
        self.killed = False
        self.reported = False  # an unexpected exit was already returned by Supervisor.poll()

    @property
    def pid(self) -> int:
        return self.popen.pid


class Supervisor:
    """Starts child processes, each in its own process group, watches them and stops them in order.

    Output of the children goes to ``stream`` with a ``[name]`` prefix ('screen'), to
    ``log_dir/<name>.log`` ('log'; with 'screen' too when a ``log_dir`` is given), or straight to the
    terminal ('inherit'). ``announce`` receives the supervisor's own messages.
    """

    def __init__(
        self,
        output: str = 'screen',
        log_dir: str | Path | None = None,
        stream: TextIO | None = None,
        announce: Callable[[str], None] | None = None,
        pdeathsig: bool = True,
    ):
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
        self.hurry = threading.Event()  # a second Ctrl-C: stop without waiting
        self._write_lock = threading.Lock()

    # ----------------------------------------------------------------------------------------- start
    def start(self, spec: ProcessSpec) -> _Child:
        if any(c.spec.name == spec.name for c in self.children):
            raise ValueError(f'a process named {spec.name!r} was started already')
        env = os.environ.copy()
        env.update(spec.env)
        env.setdefault('PYTHONUNBUFFERED', '1')  # log lines as they happen, not when a buffer fills
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
            popen = subprocess.Popen(
                argv,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=stdout,
                stderr=subprocess.STDOUT if stdout is not None else None,
                start_new_session=True,
            )
        except OSError:
            if log_file is not None:
                log_file.close()
            raise
        pumps = []
        if mode == 'screen':
            pump = threading.Thread(
                target=self._pump, args=(popen.stdout, spec.name, log_file), name=f'output-{spec.name}', daemon=True
            )
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
            os.killpg(child.pid, sig)  # the group of a child started with start_new_session: pgid == pid
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
                failure = (
                    None
                    if (c.spec.role in ('player', 'tool') and rc == 0)
                    else (f'exited on its own with code {rc}' if rc >= 0 else f'died of signal {-rc}')
                )
            else:
                how = 'stopped'
                failure = None if rc in _CLEAN_STOP_CODES else f'exit code {rc} when stopped'
            out.append(ProcessResult(c.spec.name, c.spec.role, c.pid, rc, how, failure))
        return out


# ---------------------------------------------------------------------------------------- interrupts
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

    def __enter__(self) -> Interrupts:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
