"""The offline run on every core (lego_loam_py.front_end_process): the recording read and projected in one child
process, featureAssociation in another, the mapping in the caller's.

* the result is the sequential run's, bit for bit, with and without an IMU: featureAssociation takes every mapped
  pose at the same scan as in one process (the one feedback between the processes);
* without IMU samples featureAssociation does not wait for the mapped poses (they would change nothing);
* a failure in a child is raised in the caller, a child that dies is reported, no child is left behind, and a
  dropped scan is warned about and counted in the caller.
"""

from __future__ import annotations

import multiprocessing
import os
from pathlib import Path

import numpy as np
import pytest

import lego_loam_py.offline as offline
from lego_loam_py.core.odometry.feature_association import FeatureAssociation
from lego_loam_py.core.params import Params
from lego_loam_py.core.projection.image_projection import ImageProjection, InputError
from lego_loam_py.front_end_process import FrontEndProcessError
from lego_loam_py.offline import run_bag

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / 'bags' / 'campus_8s'
SCANS = 40
IMU_SAMPLE = (0.0, (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 0.0, 9.81))


def _split_runs(monkeypatch) -> list:
    """Make run_source record each use of the front-end processes."""
    calls = []
    real = offline.run_split
    monkeypatch.setattr(offline, 'run_split', lambda *a: calls.append(1) or real(*a))
    return calls


def _log_mapped_poses(monkeypatch, path: Path) -> None:
    """Append (scans featureAssociation processed, stamp of the mapped pose) to ``path`` at each pose it takes, in
    whichever process it runs."""
    real = FeatureAssociation.add_mapped_pose

    def logged(self, stamp_ns, pose):
        with path.open('a') as log:
            log.write(f'{self.scans} {stamp_ns} {self.takes_mapped_poses}\n')
        return real(self, stamp_ns, pose)

    monkeypatch.setattr(FeatureAssociation, 'add_mapped_pose', logged)


def _assert_same_run(split, sequential) -> None:
    assert split.counts == sequential.counts and split.counts['mapping_steps'] >= 5
    for name in ('stamps', 'odometry', 'integrated', 'mapped', 'mapped_stamps', 'integrated_covariance'):
        assert np.array_equal(np.array(getattr(split, name)), np.array(getattr(sequential, name))), name
    assert [event.message for _, event in split.imu_alignment] == [e.message for _, e in sequential.imu_alignment]
    assert set(split.timings_ms) == set(sequential.timings_ms)
    assert len(split.timings_ms['featureAssociation']) == len(sequential.timings_ms['featureAssociation'])


@pytest.mark.parametrize('imu', [True, False])
def test_the_front_end_processes_give_the_sequential_result(monkeypatch, tmp_path, imu):
    calls = _split_runs(monkeypatch)
    imu_topic = None if imu else ''
    _log_mapped_poses(monkeypatch, tmp_path / 'split.log')
    split = run_bag(BAG, Params(), imu_topic=imu_topic, progress=False, max_scans=SCANS)
    assert calls == [1] and not multiprocessing.active_children()
    taken_split = (tmp_path / 'split.log').read_text().splitlines() if imu else None
    assert imu or not (tmp_path / 'split.log').exists()
    monkeypatch.undo()
    calls = _split_runs(monkeypatch)
    _log_mapped_poses(monkeypatch, tmp_path / 'sequential.log')
    sequential = run_bag(BAG, Params(), imu_topic=imu_topic, progress=False, max_scans=SCANS, mapping_thread=False)
    assert calls == []
    _assert_same_run(split, sequential)
    assert (split.counts.get('scans_with_imu', 0) > SCANS // 2) == imu
    assert 0 < split.bag_duration < 0.1 * SCANS + 0.2  # (cut short: the part of the recording processed)
    taken = (tmp_path / 'sequential.log').read_text().splitlines()
    if imu:  # the same poses, each taken before the same scan
        assert len(taken) >= 5 and taken_split == taken
    else:  # in one process they are given and change nothing; the child passes them over
        assert len(taken) >= 5 and all(line.endswith('False') for line in taken)


def test_featureassociation_takes_mapped_poses_once_it_had_an_imu_sample():
    fa = FeatureAssociation(Params())
    assert not fa.takes_mapped_poses
    fa.add_imu(*IMU_SAMPLE)
    assert fa.takes_mapped_poses
    fa.restart()  # (a sane IMU buffer is kept, and with it what the check knows)
    assert fa.takes_mapped_poses
    fa.reset()
    assert not fa.takes_mapped_poses
    fa.add_imu(float('nan'), *IMU_SAMPLE[1:])  # (rejected, but given)
    assert fa.takes_mapped_poses


def _fail_on_call(monkeypatch, cls, name: str, call: int, failure) -> None:
    real = getattr(cls, name)
    seen = []

    def failing(self, *args, **kwargs):
        seen.append(1)
        if len(seen) == call:
            failure()
        return real(self, *args, **kwargs)

    monkeypatch.setattr(cls, name, failing)


def _raise(error):
    def do():
        raise error

    return do


@pytest.mark.parametrize('stage, call', [(ImageProjection, 'self.ip.process'), (FeatureAssociation, 'self.fa.process')])
def test_a_failure_in_a_front_end_process_is_raised_in_the_caller(monkeypatch, stage, call):
    calls = _split_runs(monkeypatch)
    _fail_on_call(monkeypatch, stage, 'process', 5, _raise(ZeroDivisionError('bad scan 5')))
    with pytest.raises(ZeroDivisionError, match='bad scan 5') as raised:
        run_bag(BAG, Params(), progress=False, max_scans=10)
    assert calls == [1] and 'in the front-end process' in '\n'.join(raised.value.__notes__)
    assert call in '\n'.join(raised.value.__notes__)  # (the child's traceback)
    assert not multiprocessing.active_children()


def test_a_front_end_process_that_dies_is_reported(monkeypatch):
    _fail_on_call(monkeypatch, FeatureAssociation, 'process', 3, lambda: os._exit(3))
    with pytest.raises(FrontEndProcessError, match='ended before the recording did') as raised:
        run_bag(BAG, Params(), progress=False, max_scans=10)
    assert 'lego_loam_py odometry: 3' in str(raised.value)
    assert not multiprocessing.active_children()


def test_a_scan_dropped_in_a_front_end_process_is_warned_about_and_counted(monkeypatch, capsys):
    calls = _split_runs(monkeypatch)
    _fail_on_call(monkeypatch, ImageProjection, 'process', 4, _raise(InputError('no usable point')))
    result = run_bag(BAG, Params(), progress=False, max_scans=10)
    assert calls == [1] and result.counts['scans_dropped'] == 1 and result.counts['scans_processed'] == 9
    assert 'dropped: no usable point' in capsys.readouterr().err


def test_a_recording_that_fails_while_the_reader_reads_it_is_one_error_line(monkeypatch, tmp_path, capsys):
    """The reader process reads the recording: a SourceError there (a bag cut off mid-way) reaches the command line
    as the same one-line error and exit code as without the child processes."""
    from lego_loam_py.cli import main
    from lego_loam_py.inputs.rosbag import BagSource
    from lego_loam_py.inputs.source import SourceError

    calls = _split_runs(monkeypatch)
    real = BagSource.items

    def breaking(self):
        for number, item in enumerate(real(self)):
            if number == 60:
                raise SourceError(f'{self.path}: the bag ends inside a message')
            yield item

    monkeypatch.setattr(BagSource, 'items', breaking)
    code = main(['run', str(BAG), '--no-progress', '-o', str(tmp_path / 'out')])
    assert calls == [1] and code == 1 and not multiprocessing.active_children()
    assert capsys.readouterr().err.strip().splitlines()[-1] == f'error: {BAG}: the bag ends inside a message'
