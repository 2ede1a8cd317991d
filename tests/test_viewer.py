"""The Rerun viewer: a saved recording read back with Rerun's own API, and the package working without rerun-sdk."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / 'bags' / 'campus_8s'
CLI = Path(sys.executable).parent / 'lego_loam_py'


def _entities_and_scan_steps(rrd: Path) -> tuple[set[str], dict[str, set[int]]]:
    """Entity paths of a .rrd and, per entity, the ``scan`` timeline steps it has data at (Rerun's chunk API)."""
    from rerun.chunk import RrdReader

    store = RrdReader(rrd).store()
    steps: dict[str, set[int]] = {}
    for chunk in store.stream().to_chunks():
        batch = chunk.to_record_batch()
        if 'scan' in batch.schema.names:
            steps.setdefault(chunk.entity_path, set()).update(batch.column('scan').to_pylist())
    return set(store.schema().entity_paths()), steps


def test_viewer_save_on_the_campus_bag_holds_scan_map_and_trajectories_one_step_per_scan(tmp_path):
    pytest.importorskip('rerun')
    rrd = tmp_path / 'campus.rrd'
    done = subprocess.run(
        [str(CLI), 'run', str(BAG), '-o', str(tmp_path / 'out'), '--no-progress', '--viewer-save', str(rrd)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    assert f'viewer recording: {rrd}' in done.stdout
    entities, steps = _entities_and_scan_steps(rrd)
    for entity in (
        '/world/lidar',
        '/world/lidar/scan',
        '/world/lidar/features',
        '/world/keyframes',
        '/world/trajectory/ground_truth',
        '/timings/scan',
        '/timings/mapping',
        '/health/odometry',
        '/health/odometry_condition',
        '/health/mapping',
    ):
        assert entity in entities, entity
    for kind in ('map', 'trajectory/fused', 'trajectory/odometry', 'trajectory/mapped'):
        assert any(e.startswith(f'/world/{kind}/') for e in entities), kind
    # One step per scan: the campus bag's 80 scans, each shown once, at 0..79.
    assert steps['/world/lidar/scan'] == set(range(80))
    assert steps['/timings/scan'] == set(range(80))
    assert len(steps['/timings/mapping']) == 20  # the mapping steps, at their scans
    assert steps['/timings/mapping'] <= set(range(80))
    # The outputs are those of a run without the viewer.
    plain = subprocess.run(
        [str(CLI), 'run', str(BAG), '-o', str(tmp_path / 'plain'), '--no-progress'],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert plain.returncode == 0, plain.stderr
    assert (tmp_path / 'out' / 'trajectory.tum').read_bytes() == (tmp_path / 'plain' / 'trajectory.tum').read_bytes()


def test_the_scene_keeps_one_map_point_per_voxel_and_logs_only_new_ones():
    rr = pytest.importorskip('rerun')
    from lego_loam_py.viewer.scene import MAP_VOXEL, SceneLog

    scene = SceneLog('test', recording=rr.RecordingStream('lego_loam_py_test'))  # (no sink: kept in memory)
    rng = np.random.default_rng(0)
    cloud = rng.uniform(0, 4, (5000, 3))
    cells = len(np.unique(np.floor(cloud / MAP_VOXEL), axis=0))
    assert scene.map_points(cloud) == cells
    assert scene.map_points(cloud) == 0  # the same voxels again: nothing new
    assert scene.map_points(cloud + [10.0, 0.0, 0.0]) == cells  # a new place: all new


def test_everything_works_without_rerun_and_the_viewer_says_what_to_install(tmp_path):
    """rerun-sdk is optional: with it hidden, run works and --viewer-save fails with one line naming the package."""
    hide = 'import sys; sys.modules["rerun"] = None; from lego_loam_py.cli import main; sys.exit(main(sys.argv[1:]))'
    common = [sys.executable, '-c', hide, 'run', str(BAG), '--no-progress', '--max-scans', '5']
    plain = subprocess.run(common + ['-o', str(tmp_path / 'a')], capture_output=True, text=True, timeout=300)
    assert plain.returncode == 0, plain.stderr
    viewer = subprocess.run(
        common + ['-o', str(tmp_path / 'b'), '--viewer-save', str(tmp_path / 'x.rrd')],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert viewer.returncode == 2 and 'error: the viewer needs rerun-sdk' in viewer.stderr
    assert 'Traceback' not in viewer.stderr
