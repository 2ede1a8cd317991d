"""``lego_loam_py batch``: the grid, run identities, atomic run directories, resume, failures and retries, the
report; on a Dask LocalCluster bound to 127.0.0.1."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from lego_loam_py.batch import ParameterSet, parameter_grid, run_batch, write_report
from lego_loam_py.batch.execute import PARTIAL_PREFIX, read_status
from lego_loam_py.batch.plan import expand_recordings, plan_runs, split_values
from lego_loam_py.core.params import Params, load_params, write_params_file
from lego_loam_py.errors import UsageError

SWEEP = 'feature_association.edge_threshold'
VERSION = {'package_version': 'test', 'git_commit': 'abc', 'dirty': False}


def wait_for(condition, timeout: float, what: str, interval: float = 0.05):
    """Wait until ``condition()`` holds (an event on disk or in a process), failing after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out waiting for {what}')
        time.sleep(interval)


@pytest.fixture(scope='module')
def recordings():
    """Two short simulated recordings (1.5 s each, with IMU and ground truth)."""
    from lego_loam_py.sim.simulator import cached_scenario

    return [cached_scenario('campus', duration=1.5, seed=3), cached_scenario('forest', duration=1.5, seed=3)]


@pytest.fixture(scope='module')
def client():
    """A two-worker LocalCluster on 127.0.0.1, shared by the module's batches."""
    from dask.distributed import Client

    from lego_loam_py.batch import local_cluster

    cluster = local_cluster(2)
    with Client(cluster) as dask_client:
        yield dask_client
    cluster.close()


# ------------------------------------------------------------------------------------------------ the plan


def test_sweep_values_split_on_top_level_commas_only():
    assert split_values('0.1,0.2, 0.3') == ['0.1', '0.2', '0.3']
    assert split_values("[1, 2],'a,b',{x: 1, y: 2}") == ['[1, 2]', "'a,b'", '{x: 1, y: 2}']


def test_the_grid_is_every_combination_of_sweeps_and_parameter_files(tmp_path):
    first = write_params_file(tmp_path / 'a.yaml', {'feature_association.surf_threshold': 0.2})
    second = write_params_file(tmp_path / 'b.yaml', {})
    grid = parameter_grid([f'{SWEEP}:=0.1,0.2', 'map_optimization.knn:=5,6,7'], [first, second])
    assert len(grid) == 2 * 2 * 3
    assert grid[0] == ParameterSet(first.resolve(), {SWEEP: 0.1, 'map_optimization.knn': 5})
    assert {(s.params_file.name, s.overrides[SWEEP], s.overrides['map_optimization.knn']) for s in grid} == {
        (f, e, k) for f in ('a.yaml', 'b.yaml') for e in (0.1, 0.2) for k in (5, 6, 7)
    }
    with pytest.raises(UsageError, match='name:=value1'):
        parameter_grid(['edge_threshold=0.1'])
    with pytest.raises(UsageError, match='swept twice'):
        parameter_grid([f'{SWEEP}:=0.1', f'{SWEEP}:=0.2'])


def test_recordings_come_from_paths_patterns_and_list_files(tmp_path):
    for name in ('b1.bag', 'b2.bag', 'other.txt'):
        (tmp_path / name).write_text('x')
    listing = tmp_path / 'list.txt'
    listing.write_text('# my bags\nb2.bag\n*.bag   # again: kept once\n')
    assert expand_recordings([], [listing]) == [(tmp_path / 'b2.bag').resolve(), (tmp_path / 'b1.bag').resolve()]
    assert expand_recordings([str(tmp_path / '*.bag')]) == [(tmp_path / f'b{i}.bag').resolve() for i in (1, 2)]
    with pytest.raises(UsageError, match='no recording matches'):
        expand_recordings([str(tmp_path / '*.mcap')])
    with pytest.raises(UsageError, match='no such recording'):
        expand_recordings([str(tmp_path / 'missing.bag')])


def test_a_run_is_identified_by_its_recording_parameters_imu_and_code(tmp_path):
    bag = tmp_path / 'r.bag'
    bag.write_text('x')
    grid = parameter_grid([f'{SWEEP}:=0.1,0.2'])
    ids = [s.run_id for s in plan_runs([bag], grid, 'both', VERSION)]
    assert len(set(ids)) == 4
    assert ids == [s.run_id for s in plan_runs([bag], grid, 'both', VERSION)]  # stable
    assert ids[0] not in [s.run_id for s in plan_runs([bag], grid, 'both', dict(VERSION, dirty=True))]
    os.utime(bag, ns=(1, 1))  # the recording changed
    assert ids[0] not in [s.run_id for s in plan_runs([bag], grid, 'both', VERSION)]
    # The default value given explicitly is the same computation as the default.
    explicit = parameter_grid([f'{SWEEP}:={Params().feature_association.edge_threshold}'])
    assert (
        plan_runs([bag], explicit, 'on', VERSION)[0].run_id
        == plan_runs([bag], [ParameterSet()], 'on', VERSION)[0].run_id
    )


def test_the_parameter_file_of_a_run_reads_back_as_the_same_parameters(tmp_path):
    params = Params().replace(feature_association__edge_threshold=0.123456789, sensor__preset='HDL-32E')
    written = write_params_file(tmp_path / 'params.yaml', params.to_flat())
    assert load_params(written) == params


# ------------------------------------------------------------------------------------------------ the report


def fake_run(out: Path, name: str, overrides: dict, status: str, ate: float | None, imu: bool = True) -> None:
    run = out / 'runs' / name
    run.mkdir(parents=True)
    (run / 'inputs.json').write_text(
        json.dumps(
            {
                'recording': f'/data/{name.split("-")[0]}',
                'params_file': '',
                'overrides': overrides,
                'imu': imu,
                'run_id': name,
            }
        )
    )
    (run / 'status.json').write_text(
        json.dumps({'status': status, 'attempt': 1, 'run_id': name, 'error': '' if status == 'ok' else 'exit code 1'})
    )
    if ate is not None:
        (run / 'metrics.json').write_text(json.dumps({'ate_rmse_m': ate, 'scans': 10}))


def test_the_report_is_rebuilt_from_the_run_directories_alone(tmp_path):
    fake_run(tmp_path, 'a-1', {SWEEP: 0.1}, 'ok', 0.5)
    fake_run(tmp_path, 'a-2', {SWEEP: 0.2}, 'ok', 0.3)
    fake_run(tmp_path, 'b-1', {SWEEP: 0.1}, 'failed', None)
    (tmp_path / 'runs' / f'{PARTIAL_PREFIX}b-2-1234').mkdir()  # an interrupted run: never a result
    files = write_report(tmp_path)
    rows = (tmp_path / 'report.csv').read_text().splitlines()
    assert rows[0].split(',')[:4] == ['run', 'recording', SWEEP, 'status'] and len(rows) == 4
    markdown = files['md'].read_text()
    assert '3 runs: 2 finished, 1 failed (1 unfinished' in markdown
    assert '| 0.1 | 1 | 0.500 | 0.500 |' in markdown and '| 0.2 | 1 | 0.300 | 0.300 |' in markdown
    assert '`b-1` (attempt 1): exit code 1' in markdown
    assert (tmp_path / 'ate_per_run.png').stat().st_size > 1000
    assert (tmp_path / 'ate_vs_feature_association_edge_threshold.png').is_file()


# --------------------------------------------------------------------------------------------- on Dask


def test_a_2x2_grid_runs_on_dask_resumes_and_matches_the_sequential_run(tmp_path, recordings, client):
    out = tmp_path / 'batch'
    grid = parameter_grid([f'{SWEEP}:=0.1,0.2'])
    result = run_batch(recordings, grid, out, client=client, progress=False)
    assert result.ran == 4 and result.reused == 0 and not result.failed
    assert sorted((r['recording'], r['overrides'][SWEEP]) for r in result.records) == sorted(
        (bag.name, value) for bag in recordings for value in (0.1, 0.2)
    )
    assert all(r['ate_rmse_m'] is not None and r['scans'] > 10 for r in result.records)
    table = result.table()
    assert len(table) == 4 and SWEEP in table.columns
    run_dir = out / 'runs' / result.records[0]['run']
    for name in ('params.yaml', 'command.txt', 'version.json', 'run.log', 'trajectory.tum', 'summary.json'):
        assert (run_dir / name).is_file(), name
    assert json.loads((run_dir / 'version.json').read_text())['git_commit']
    # The same command typed by hand gives the same trajectory, bit for bit.
    record = result.records[0]
    by_hand = tmp_path / 'by_hand'
    subprocess.run(
        [
            sys.executable,
            '-m',
            'lego_loam_py.cli',
            'run',
            record['recording_path'],
            '-o',
            str(by_hand),
            '-p',
            f'{SWEEP}:={record["overrides"][SWEEP]}',
            '--no-progress',
        ],
        check=True,
        capture_output=True,
    )
    assert (by_hand / 'trajectory.tum').read_bytes() == (run_dir / 'trajectory.tum').read_bytes()
    # Resumed: nothing runs again.
    again = run_batch(recordings, grid, out, client=client, progress=False)
    assert again.ran == 0 and again.reused == 4
    assert read_status(run_dir)['started'] == json.loads((run_dir / 'status.json').read_text())['started']


def test_a_corrupt_recording_fails_alone_with_its_error_after_its_retry(tmp_path, recordings, client):
    broken = tmp_path / 'broken.bag'
    broken.write_bytes(b'#ROSBAG V2.0\n' + os.urandom(200))
    result = run_batch([recordings[0], broken], None, tmp_path / 'batch', client=client, retries=1, progress=False)
    by_recording = {r['recording']: r for r in result.records}
    assert by_recording[recordings[0].name]['status'] == 'ok'
    failed = by_recording['broken.bag']
    assert failed['status'] == 'failed' and failed['attempt'] == 2 and 'exit code 1' in failed['error']
    assert 'broken.bag' in (tmp_path / 'batch' / 'report.md').read_text()


def test_a_run_that_never_ends_is_stopped_at_its_timeout(tmp_path, recordings, client):
    result = run_batch(
        [recordings[0]], None, tmp_path / 'batch', client=client, timeout_s=0.5, retries=0, progress=False
    )
    assert result.records[0]['status'] == 'failed' and 'timed out after 0.5 s' in result.records[0]['error']


def test_resume_after_the_driver_is_killed_recomputes_nothing_finished(tmp_path, recordings, client):
    """SIGKILL the batch (driver, scheduler, workers: its whole process group) once some runs are done: the next
    batch reruns only the others, never takes a half-written run for a result, and reports all of them."""
    out = tmp_path / 'batch'
    command = [
        sys.executable,
        '-m',
        'lego_loam_py.cli',
        'batch',
        *map(str, recordings),
        '-p',
        f'{SWEEP}:=0.1,0.2',
        '-o',
        str(out),
        '--workers',
        '1',
        '--no-progress',
    ]
    driver = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:

        def finished():
            return (
                [p for p in (out / 'runs').glob('*') if not p.name.startswith('.')] if (out / 'runs').is_dir() else []
            )

        wait_for(lambda: len(finished()) >= 1 or driver.poll() is not None, 180, 'a first finished run')
    finally:
        os.killpg(driver.pid, signal.SIGKILL)
        driver.wait()
    done_before = {p.name: read_status(p) for p in (out / 'runs').iterdir() if not p.name.startswith('.')}
    assert 1 <= len(done_before) < 4, driver.stderr.read()
    assert all(status is not None and status['status'] == 'ok' for status in done_before.values())
    result = run_batch(recordings, parameter_grid([f'{SWEEP}:=0.1,0.2']), out, client=client, progress=False)
    assert result.reused == len(done_before) and result.ran == 4 - len(done_before)
    for name, status in done_before.items():
        assert read_status(out / 'runs' / name) == status  # not run again
    assert len(result.records) == 4 and not result.failed
    assert not list((out / 'runs').glob(f'{PARTIAL_PREFIX}*'))
    assert len((out / 'report.csv').read_text().splitlines()) == 5


def test_a_run_whose_worker_is_killed_mid_run_is_run_again(tmp_path, recordings, client):
    """SIGKILL the worker running a run: its child dies with it, the scheduler gives the task to a worker again,
    and the run finishes; the dead attempt's half-written folder is never taken for the result."""
    out = tmp_path / 'batch'
    outcome = {}
    thread = threading.Thread(
        target=lambda: outcome.update(result=run_batch([recordings[1]], None, out, client=client, progress=False))
    )
    thread.start()
    try:
        wait_for(
            lambda: (out / 'runs').is_dir() and any((out / 'runs').glob(f'{PARTIAL_PREFIX}*')), 120, 'the run to start'
        )
        pids = client.run(os.getpid)
        busy = [address for address, keys in client.processing().items() if keys]
        assert len(busy) == 1
        worker = pids[busy[0]]

        def children() -> list[int]:
            return [
                int(pid)
                for task in Path(f'/proc/{worker}/task').iterdir()
                for pid in (task / 'children').read_text().split()
            ]

        wait_for(lambda: bool(children()), 60, "the run's process")
        children = children()
        os.kill(worker, signal.SIGKILL)
        thread.join(timeout=300)
    finally:
        thread.join(timeout=300)
    result = outcome['result']
    assert not result.failed and result.records[0]['status'] == 'ok'
    status = read_status(out / 'runs' / result.records[0]['run'])
    assert status['pid'] != worker
    for child in children:  # the killed worker's run did not live on
        assert not Path(f'/proc/{child}').exists() or 'zombie' in Path(f'/proc/{child}/status').read_text()


def test_a_batch_reads_what_run_reads_with_its_loader_options(tmp_path, recordings, client):
    """A KITTI sequence folder (the campus recording exported) and its bag in one batch: run's loader options
    reach every run, enter its identity, and the folder's runs are evaluated against its poses.txt."""
    from lego_loam_py.sim.export import export_recording

    folder = tmp_path / 'seq00'
    export_recording(recordings[0], folder, 'kitti')
    result = run_batch(
        [folder], None, tmp_path / 'batch', client=client, progress=False, run_args=['--format', 'kitti']
    )
    assert not result.failed and result.records[0]['ate_rmse_m'] is not None
    run_dir = tmp_path / 'batch' / 'runs' / result.records[0]['run']
    assert (run_dir / 'trajectory_kitti.txt').is_file()
    assert '--format kitti' in (run_dir / 'command.txt').read_text()
    plain = plan_runs([folder], [ParameterSet()], 'on', VERSION)[0]
    assert plan_runs([folder], [ParameterSet()], 'on', VERSION, ['--format', 'kitti'])[0].run_id != plain.run_id
