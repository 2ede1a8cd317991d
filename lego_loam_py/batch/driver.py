"""The batch driver: plans the runs, skips those already finished, runs the rest on Dask and writes the report.

Dask is the engine: a ``LocalCluster`` on 127.0.0.1 with one single-threaded worker process per core by
default, or any scheduler given (``tcp://HOST:PORT``, which reaches SLURM/PBS/Kubernetes through
dask-jobqueue or dask-kubernetes), or a ``dask.distributed.Client`` from Python. Each task is one run
(:func:`lego_loam_py.batch.execute.run_one`), a ``lego_loam_py run`` child of its worker. A worker lost
mid-run is Dask's to handle: the scheduler gives the task to another worker (``allowed-failures``, 3 by
default); a run that fails on its own (exit code, timeout) is retried here up to ``retries`` times. Workers
of a remote cluster must see the recordings and the output folder at the same paths (a shared file system).
"""

from __future__ import annotations

import json
import os
import shlex
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from lego_loam_py.batch.execute import read_status, record_failure, remove_partials, run_one
from lego_loam_py.batch.plan import ParameterSet, RunSpec, code_version, expand_recordings, plan_runs
from lego_loam_py.batch.report import collect_records, write_report
from lego_loam_py.errors import LegoLoamError, UsageError
from lego_loam_py.formats import write_text_atomic

__all__ = ['BatchResult', 'run_batch', 'local_cluster']

LOCK_NAME = '.batch.lock'


@dataclass
class BatchResult:
    """What a batch did: every run's record (see :func:`~lego_loam_py.batch.report.collect_records`), how
    many ran now, how many were reused from an earlier batch, and the report files."""

    records: list[dict]
    ran: int = 0
    reused: int = 0
    report: dict[str, Path] = field(default_factory=dict)

    @property
    def failed(self) -> list[dict]:
        return [r for r in self.records if r['status'] != 'ok']

    def table(self):
        """The records as a pandas DataFrame."""
        from lego_loam_py.batch.report import as_dataframe

        return as_dataframe(self.records)


class BatchBusy(LegoLoamError):
    """Another batch is running on the same output folder."""


def _acquire_lock(out: Path) -> Path:
    """``out/.batch.lock`` with this process's id; refuses while the process named in an existing lock lives."""
    lock = out / LOCK_NAME
    try:
        pid = int(lock.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        pid = None
    if pid is not None and pid != os.getpid():
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            pass
        except PermissionError:
            raise BatchBusy(f'{out} is in use by another batch (process {pid})') from None
        else:
            raise BatchBusy(f'{out} is in use by another batch (process {pid}); wait for it or stop it')
    write_text_atomic(lock, f'{os.getpid()}\n')
    return lock


def local_cluster(workers: int | None = None):
    """A Dask ``LocalCluster`` on 127.0.0.1 only: ``workers`` single-threaded worker processes (default: one
    per core), no dashboard."""
    import logging

    from dask.distributed import LocalCluster

    return LocalCluster(
        n_workers=workers or os.cpu_count() or 1,
        threads_per_worker=1,
        processes=True,
        host='127.0.0.1',
        dashboard_address=None,
        silence_logs=logging.ERROR,
    )


def _pending(specs: Sequence[RunSpec], out: Path, retries: int) -> tuple[list[tuple[RunSpec, int]], int]:
    """(the runs to do, each with its attempt number; how many finished runs are reused). A failed run is
    tried again while it has had at most ``retries`` retries."""
    todo, reused = [], 0
    for spec in specs:
        status = read_status(out / 'runs' / spec.name)
        if status is not None and status.get('status') == 'ok':
            reused += 1
        elif status is None:
            todo.append((spec, 1))
        elif int(status.get('attempt') or 1) <= retries:
            todo.append((spec, int(status.get('attempt') or 1) + 1))
    return todo, reused


def run_batch(
    recordings: Sequence[str | Path],
    parameter_sets: Sequence[ParameterSet] | None = None,
    out: str | Path = 'batch',
    *,
    imu: str = 'on',
    client=None,
    scheduler: str | None = None,
    workers: int | None = None,
    timeout_s: float | None = 3600.0,
    retries: int = 1,
    progress: bool = True,
    command_line: Sequence[str] | None = None,
    run_args: Sequence[str] = (),
) -> BatchResult:
    """Run every recording x parameter set x IMU mode (``'on'``, ``'off'``, ``'both'``) and write the report.

    ``recordings``: paths or glob patterns. ``parameter_sets``: from :func:`~lego_loam_py.batch.plan.
    parameter_grid` (default: the defaults). Runs go to ``client`` (a ``dask.distributed.Client``), else to
    the scheduler at ``scheduler``, else to a new :func:`local_cluster` of ``workers`` workers, closed at the
    end. Runs finished by an earlier batch into ``out`` are reused; failed ones are tried again. ``run_args``:
    more arguments of every ``lego_loam_py run`` (how to read the recordings, e.g. ``['--dataloader', 'kitti']``).
    """
    if retries < 0:
        raise UsageError(f'retries must be 0 or more, got {retries}')
    out = Path(out).resolve()
    paths = expand_recordings([str(r) for r in recordings])
    version = code_version()
    specs = plan_runs(paths, list(parameter_sets or [ParameterSet()]), imu, version, run_args)
    out.mkdir(parents=True, exist_ok=True)
    lock = _acquire_lock(out)
    try:
        remove_partials(out / 'runs')  # what a killed batch left; no batch runs here now (the lock)
        write_text_atomic(
            out / 'batch.json',
            json.dumps(
                {
                    'command': shlex.join(command_line) if command_line else None,
                    'version': version,
                    'runs': [dict(spec.describe(), name=spec.name) for spec in specs],
                },
                indent=1,
                default=str,
            )
            + '\n',
        )
        todo, reused = _pending(specs, out, retries)
        if todo:
            _run_on_dask(todo, out, version, client, scheduler, workers, timeout_s, retries, progress)
        remove_partials(out / 'runs')
        records = [r for r in collect_records(out) if r['run_id'] in {s.run_id for s in specs}]
        report = write_report(out, records)
    finally:
        lock.unlink(missing_ok=True)
    return BatchResult(records, ran=len(todo), reused=reused, report=report)


def _run_on_dask(
    todo: list[tuple[RunSpec, int]],
    out: Path,
    version: dict,
    client,
    scheduler: str | None,
    workers: int | None,
    timeout_s: float | None,
    retries: int,
    progress: bool,
) -> None:
    from dask.distributed import Client, as_completed

    own_cluster = None
    if client is None:
        if scheduler:
            client = Client(scheduler)
        else:
            own_cluster = local_cluster(workers)
            client = Client(own_cluster)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), unit='run', desc='batch', file=sys.stderr, dynamic_ncols=True)
    try:
        futures = {}

        def submit(spec: RunSpec, attempt: int) -> None:
            future = client.submit(
                run_one,
                spec,
                str(out),
                attempt,
                version,
                timeout_s,
                pure=False,
                key=f'lego-loam-run-{spec.run_id[:16]}-{attempt}-{time.monotonic_ns()}',
            )
            futures[future] = (spec, attempt)
            queue.add(future)

        queue = as_completed()
        for spec, attempt in todo:
            submit(spec, attempt)
        for future in queue:
            spec, attempt = futures.pop(future)
            try:
                status = future.result()
            except Exception as exc:  # the task itself failed: its workers were lost again and again
                status = record_failure(spec, out, attempt, version, f'{type(exc).__name__}: {exc}')
            if status.get('status') != 'ok' and attempt <= retries:
                submit(spec, attempt + 1)
                continue
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(f'{spec.name}: {status.get("status")}')
    finally:
        if bar is not None:
            bar.close()
        if client is not None and (own_cluster is not None or scheduler):
            client.close()
        if own_cluster is not None:
            own_cluster.close()
