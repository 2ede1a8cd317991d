"""Running one :class:`~lego_loam_py.batch.plan.RunSpec`, on a Dask worker or anywhere: a ``lego_loam_py run``
child process, its outputs gathered in a run directory that appears only when complete.

A run directory (``OUT/runs/<recording>-<id>``) holds what ``run`` writes (trajectories, map, PNG,
summary.json) and ``params.yaml`` (every parameter, as the run read them), ``command.txt``, ``version.json``
(git commit, dirty flag), ``run.log`` (the child's output), ``metrics.json`` and, written last,
``status.json``. It is assembled under ``OUT/runs/.partial-...`` and renamed into place: a run killed half way
(SIGKILL, a worker lost, a power cut) leaves only a ``.partial-`` folder, which the next batch removes and
never reads as a result.
"""

from __future__ import annotations

import ctypes
import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

from lego_loam_py.batch.plan import RunSpec
from lego_loam_py.core.params import write_params_file
from lego_loam_py.formats import write_text_atomic

__all__ = ['run_one', 'run_command', 'read_status', 'publish', 'remove_partials', 'PARTIAL_PREFIX', 'metrics_of']

PARTIAL_PREFIX = '.partial-'
_REPLACED_PREFIX = '.replaced-'
_PR_SET_PDEATHSIG = 1


def run_command(spec: RunSpec, output: Path, params_file: Path) -> list[str]:
    """The ``lego_loam_py run`` arguments of a run (what a user would type, with every parameter in a file)."""
    command = [
        'lego_loam_py',
        'run',
        str(spec.recording),
        '-o',
        str(output),
        '--params-file',
        str(params_file),
        '--no-progress',
        *spec.run_args,
    ]
    return command + ([] if spec.imu else ['--no-imu'])


def _child_command(command: list[str]) -> list[str]:
    """How a worker starts ``command``: this interpreter, through :func:`die_with_parent_then_run` (a run whose
    worker is lost mid-way must not live on, still writing)."""
    return [sys.executable, '-m', 'lego_loam_py.batch.execute', str(os.getpid()), *command[1:]]


def die_with_parent_then_run(parent_pid: int, argv: list[str]) -> int:
    """The child's first step: ask the kernel to kill it when its parent (the worker) dies, then run the
    ``lego_loam_py`` command ``argv``. (Done here rather than in ``preexec_fn``, which is unsafe in a
    threaded worker.)"""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # not Linux: the run outlives a killed worker, as any child would
        pass
    if os.getppid() != parent_pid:  # the worker died before the request took effect
        return 1
    from lego_loam_py.cli import main

    return main(argv)


def metrics_of(summary: dict) -> dict:
    """The figures a batch reports of one finished run, from its summary.json."""
    accuracy = summary.get('accuracy') or {}
    counts = summary.get('counts') or {}
    scans = counts.get('scans_in') or 0
    wall = summary.get('wall_time_s')
    return {
        'scans': scans,
        'length_m': summary.get('trajectory_length_m'),
        'ate_rmse_m': accuracy.get('ate_rmse_m'),
        'ate_max_m': accuracy.get('ate_max_m'),
        'rpe_percent': accuracy.get('rpe_percent'),
        'drift_percent': accuracy.get('drift_percent'),
        'ms_per_scan': 1e3 * wall / scans if wall and scans else None,
        'x_real_time': summary.get('realtime_factor'),
    }


def read_status(run_dir: Path) -> dict | None:
    """A run directory's status.json, or None when there is none (or it cannot be read)."""
    try:
        return json.loads((run_dir / 'status.json').read_text())
    except (OSError, ValueError):
        return None


def publish(partial: Path, final: Path) -> None:
    """Rename a complete run directory into place, replacing an earlier attempt's (a failed one) if any."""
    replaced = None
    if final.exists():
        replaced = final.with_name(f'{_REPLACED_PREFIX}{final.name}-{uuid.uuid4().hex[:8]}')
        os.replace(final, replaced)
    os.replace(partial, final)
    if replaced is not None:
        shutil.rmtree(replaced, ignore_errors=True)


def remove_partials(runs: Path) -> list[Path]:
    """Remove what killed runs left in ``runs`` (call it only while no batch runs there)."""
    removed = []
    if runs.is_dir():
        for path in runs.iterdir():
            if path.name.startswith((PARTIAL_PREFIX, _REPLACED_PREFIX)):
                shutil.rmtree(path, ignore_errors=True)
                removed.append(path)
    return removed


def _tail(path: Path, lines: int = 20) -> str:
    try:
        return '\n'.join(path.read_text(errors='replace').splitlines()[-lines:])
    except OSError:
        return ''


def _error_line(log: str) -> str:
    """The line of a run's output that says why it failed (``error: ...``, else a traceback's last line)."""
    lines = [line for line in log.splitlines() if line.strip()]
    for line in reversed(lines):
        if line.startswith('error:'):
            return line[len('error:') :].strip()
    return lines[-1].strip() if lines else 'no output'


def run_one(spec: RunSpec, out: str | Path, attempt: int, version: dict, timeout_s: float | None = None) -> dict:
    """Run ``spec`` into ``out/runs/<spec.name>`` and return its status (also written as status.json).

    The run is a child process (``lego_loam_py run``): a crash or a run that never ends (``timeout_s``) fails
    this run only, and is recorded with its error; nothing is raised for them."""
    runs = Path(out) / 'runs'
    runs.mkdir(parents=True, exist_ok=True)
    partial = runs / f'{PARTIAL_PREFIX}{spec.name}-{uuid.uuid4().hex[:8]}'
    partial.mkdir()
    params_file = write_params_file(partial / 'params.yaml', spec.flat_params)
    command = run_command(spec, partial, params_file)
    # The command as it would run in the run directory's final place.
    shown = [part.replace(str(partial), str(runs / spec.name)) for part in command]
    write_text_atomic(partial / 'command.txt', shlex.join(shown) + '\n')
    write_text_atomic(partial / 'version.json', json.dumps(version, indent=1) + '\n')
    write_text_atomic(partial / 'inputs.json', json.dumps(spec.describe(), indent=1, default=str) + '\n')
    status: dict[str, Any] = {
        'run_id': spec.run_id,
        'name': spec.name,
        'attempt': attempt,
        'host': socket.gethostname(),
        'pid': os.getpid(),
        'started': time.time(),
    }
    start = time.monotonic()
    with open(partial / 'run.log', 'wb') as log:
        child = subprocess.Popen(
            _child_command(command), stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
        )
        try:
            code = child.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
            code = None
    status['elapsed_s'] = time.monotonic() - start
    status['exit_code'] = code
    if code == 0:
        try:
            summary = json.loads((partial / 'summary.json').read_text())
        except (OSError, ValueError) as exc:
            status.update(status='failed', error=f'the run finished but its summary.json is unreadable: {exc}')
        else:
            write_text_atomic(partial / 'metrics.json', json.dumps(metrics_of(summary), indent=1) + '\n')
            status['status'] = 'ok'
    elif code is None:
        status.update(status='failed', error=f'timed out after {timeout_s:g} s (killed)')
    else:
        log = _tail(partial / 'run.log')
        reason = f'killed by signal {-code}' if code < 0 else f'exit code {code}'
        status.update(status='failed', error=f'{_error_line(log)} ({reason})')
    write_text_atomic(partial / 'status.json', json.dumps(status, indent=1) + '\n')
    publish(partial, runs / spec.name)
    return status


def record_failure(spec: RunSpec, out: str | Path, attempt: int, version: dict, error: str) -> dict:
    """A run that could not be run at all (its worker was lost again and again): a run directory that says
    so, written as atomically as a finished one."""
    runs = Path(out) / 'runs'
    partial = runs / f'{PARTIAL_PREFIX}{spec.name}-{uuid.uuid4().hex[:8]}'
    partial.mkdir(parents=True)
    write_text_atomic(partial / 'version.json', json.dumps(version, indent=1) + '\n')
    write_text_atomic(partial / 'inputs.json', json.dumps(spec.describe(), indent=1, default=str) + '\n')
    status = {
        'run_id': spec.run_id,
        'name': spec.name,
        'attempt': attempt,
        'status': 'failed',
        'error': error,
        'exit_code': None,
        'started': time.time(),
        'elapsed_s': 0.0,
    }
    write_text_atomic(partial / 'status.json', json.dumps(status, indent=1) + '\n')
    publish(partial, runs / spec.name)
    return status


if __name__ == '__main__':
    sys.exit(die_with_parent_then_run(int(sys.argv[1]), sys.argv[2:]))
