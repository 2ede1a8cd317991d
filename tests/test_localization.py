"""Localization in a saved map (issue 18): the localization core, ``run --map``, the node.

The map is the one ``lego_loam_py run bags/campus_8s`` makes (13 m of the campus loop, 20 keyframes; the
``campus_map`` fixture). The drives that localize in it are simulated through the same scene on another route:
from 12 m along the loop, the other way round, 6 s (``simulate campus --route-start 12 --reverse``; cached), with
the ground truth beside them. The truth is put in the map's frame through the map's keyframes (their rigid fit to
their true poses), so the figures measure the localization, not the 1-2 % drift of the map itself (the benchmark
reports both).
"""
from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.core.params import Params

REPO = Path(__file__).resolve().parents[1]
CAMPUS = REPO / 'bags' / 'campus_8s'
AGGRESSIVE = REPO / 'bags' / 'aggressive_6s'
BIN = Path(sys.executable).parent


@pytest.fixture(scope='module')
def reverse_drive() -> Path:
    from lego_loam_py.sim.simulator import cached_scenario

    return cached_scenario('campus', duration=6.0, route_start=12.0, reverse=True)


def localize(bag: Path, map_dir: Path, **overrides):
    from lego_loam_py.offline import run_bag

    params = Params().replace(map_optimization__mode='localization', map_optimization__map_path=str(map_dir),
                              **overrides)
    return run_bag(bag, params, progress=False)


def errors_against_truth(result, bag: Path) -> np.ndarray:
    """Position errors [m] of the published poses against the truth in the map's frame (map placed by its
    keyframes' fit: see the module docstring)."""
    from lego_loam_py.evaluation import errors_in_map

    prior = result.mapper.prior
    stamps, poses = result.trajectory()
    (fit,) = [e for e in errors_in_map(bag, prior.bundle.source, prior.bundle.stamps_ns, prior.poses_lidar, stamps,
                                       poses) if e.anchor == 'map_fit']
    return fit


# ------------------------------------------------------------------------------------------- hand-checked pieces

def test_levelling_keeps_the_heading_and_removes_roll_and_pitch():
    from scipy.spatial.transform import Rotation

    from lego_loam_py.core.prior_map import heading, levelling

    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler('ZYX', [30.0, 4.0, -3.0], degrees=True).as_matrix()
    assert math.degrees(heading(pose)) == pytest.approx(30.0)
    tilt = levelling(pose)
    assert np.allclose(Rotation.from_euler('z', 30.0, degrees=True).as_matrix() @ tilt, pose[:3, :3])
    assert Rotation.from_matrix(tilt).as_euler('ZYX', degrees=True) == pytest.approx([0.0, 4.0, -3.0])


def test_a_hint_moves_on_with_the_odometry():
    from lego_loam_py.core.relocalization import Hint

    pose, odometry = np.eye(4), np.eye(4)
    pose[:3, 3] = (10.0, 5.0, 0.0)          # in the map
    odometry[:3, 3] = (2.0, 0.0, 0.0)       # in the odometry's own frame, when the hint was given
    later = odometry.copy()
    later[0, 3] = 3.5                       # 1.5 m further forward
    assert np.allclose(Hint(pose, odometry, 5.0).now(later)[:3, 3], (11.5, 5.0, 0.0))


def test_fusion_in_localization_publishes_only_with_a_recent_map_correction():
    from lego_loam_py.core.transform_fusion import TransformFusion

    mapping = TransformFusion()
    assert mapping.publishable(5_000_000_000)   # mapping: always, as the original
    fusion = TransformFusion(max_correction_age_ns=2_000_000_000)
    assert not fusion.publishable(1_000_000_000)          # no fix yet
    fusion.on_mapped(np.eye(4), np.eye(4), 1_000_000_000)
    assert fusion.publishable(1_100_000_000) and fusion.publishable(3_000_000_000)
    assert not fusion.publishable(3_100_000_000)           # the last verified step is older than 2 s
    fusion.reset()
    assert fusion.max_correction_age_ns == 2_000_000_000 and not fusion.publishable(1_100_000_000)


# -------------------------------------------------------------------------------------------- localization

def test_without_an_initial_pose_the_place_is_found_verified_and_tracked(campus_map, reverse_drive):
    result = localize(reverse_drive, campus_map)
    loc = result.mapper
    assert loc.counters['fixes'] == 1 and 'losses' not in loc.counters
    fix = (loc.first_fix_ns - result.first_scan_ns) * 1e-9
    assert fix <= 3.0
    # Nothing published before the fix; every scan after it (the transformFusion of the scans that follow).
    stamps, _ = result.trajectory()
    assert stamps[0] > loc.first_fix_ns and len(stamps) >= result.counts['scans_in'] - 10 * fix - 3
    error = errors_against_truth(result, reverse_drive)
    assert error.median_m < 0.05 and error.max_m < 0.15, error
    # The saved map stays as it was: localization adds no keyframe.
    assert result.counts['keyframes'] == 0 and loc.save('/nonexistent') == {}


@pytest.mark.parametrize('offset_m, offset_deg', [(0.0, 0.0), (3.0, 20.0)])
def test_an_initial_pose_is_used_and_verified_even_when_3_m_and_20_deg_off(campus_map, reverse_drive, offset_m,
                                                                           offset_deg):
    from lego_loam_py.core.map_bundle import read_bundle
    from lego_loam_py.evaluation import rigid_fit
    from lego_loam_py.sim.output import load_scenario, true_poses
    from scipy.spatial.transform import Rotation

    from lego_loam_py.core.frames import camera_pose_to_lidar, pose6_to_matrix

    bundle = read_bundle(campus_map)
    keyframes = np.array([camera_pose_to_lidar(pose6_to_matrix(p)) for p in bundle.poses6])
    map_from_world = np.linalg.inv(rigid_fit(keyframes[:, :3, 3],
                                             true_poses(bundle.source['simulated'], bundle.stamps_ns)[:, :3, 3]))
    scenario = load_scenario(reverse_drive)
    drive = {'config': scenario['config'], 'start_stamp_ns': scenario['recording']['start_stamp_ns']}
    truth = map_from_world @ true_poses(drive, np.array([drive['start_stamp_ns'] + 100_000_000]))[0]
    yaw = math.degrees(math.atan2(truth[1, 0], truth[0, 0]))
    x, y = truth[:2, 3] + offset_m * truth[:2, 1]           # to the left
    result = localize(reverse_drive, campus_map, localization__initial_pose=[float(x), float(y), yaw + offset_deg])
    loc = result.mapper
    (hint,) = [e for e in loc.events if e.kind == 'hint']
    assert 'initial_pose parameter' in hint.detail
    (fix,) = [e for e in loc.events if e.kind == 'fix']
    assert 'near the initial_pose parameter' in fix.detail and (loc.first_fix_ns - result.first_scan_ns) < 3e9
    error = errors_against_truth(result, reverse_drive)
    assert error.median_m < 0.05 and error.max_m < 0.15, error
    assert Rotation.from_matrix(truth[:3, :3]).as_euler('ZYX', degrees=True)[0] == pytest.approx(yaw)


def test_a_gap_in_the_data_loses_track_and_the_place_is_found_again(campus_map, reverse_drive, tmp_path):
    from tests.support.bags import cut_bag

    cut = cut_bag(reverse_drive, tmp_path / 'cut', 2.0, 2.5)   # (the benchmark cuts 10 s of a longer drive)
    result = localize(cut, campus_map)
    loc = result.mapper
    kinds = [e.kind for e in loc.events]
    assert kinds == ['fix', 'lost', 'fix'], [(e.kind, e.detail) for e in loc.events]
    lost, again = [e for e in loc.events if e.kind != 'fix'][0], [e for e in loc.events if e.kind == 'fix'][1]
    # (2.5 s cut, and the steps 0.4 s apart on either side of it)
    assert re.fullmatch(r'a gap of 2\.[5-9] s in the data', lost.detail), lost.detail
    assert again.stamp_ns - lost.stamp_ns <= 5e9
    # Nothing published while lost (after max_correction_age without a verified step), all of it right.
    stamps, _ = result.trajectory()
    assert not ((stamps > lost.stamp_ns + 2e9) & (stamps <= again.stamp_ns)).any()
    assert errors_against_truth(result, cut).max_m < 0.15


def test_another_scene_never_localizes_its_look_alike_places_fail_the_verification(campus_map):
    # Every keyframe a candidate (relocalization_threshold 1): each must be turned down by the registration's gates.
    result = localize(AGGRESSIVE, campus_map, localization__relocalization_threshold=1.0)
    loc = result.mapper
    assert loc.counters.get('fixes', 0) == 0 and result.trajectory()[0].size == 0
    assert loc.counters['places_rejected'] >= 10 and loc.counters.get('places_verified', 0) == 0
    status = loc.status()
    assert status.state == 'relocalizing' and not status.localized
    assert status.message.startswith('no pose yet: relocalizing in the whole map (') and 'last: ' in status.message


# ------------------------------------------------------------------------------------------------- run --map

def test_run_with_a_map_localizes_and_reports_the_first_fix(campus_map, reverse_drive, tmp_path):
    out = tmp_path / 'out'
    done = subprocess.run([BIN / 'lego_loam_py', 'run', reverse_drive, '--map', campus_map, '-o', out,
                           '--no-progress'], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert 'localization in' in done.stdout and 'first fix after' in done.stdout
    summary = json.loads((out / 'summary.json').read_text())
    localization = summary['localization']
    assert localization['time_to_first_fix_s'] <= 3.0 and localization['localized_fraction'] > 0.7
    assert localization['fixes'] == 1 and localization['map_keyframes'] == 20
    assert {e['anchor'] for e in localization['error_in_map']} == {'first_keyframe', 'map_fit'}
    assert summary['counts']['keyframes'] == 0 and not (out / 'map').exists()
    assert (out / 'trajectory.tum').is_file() and summary['poses'] == round(
        localization['localized_fraction'] * summary['counts']['scans_in'])
    # A bundle that cannot be used: one line naming the problem, exit code 1, nothing else.
    done = subprocess.run([BIN / 'lego_loam_py', 'run', reverse_drive, '--map', tmp_path / 'nowhere', '-o',
                           tmp_path / 'x', '--no-progress'], capture_output=True, text=True, timeout=300)
    assert done.returncode == 1 and done.stderr.strip().splitlines()[-1] == \
        f'error: map bundle {tmp_path / "nowhere"}: no such directory'
    assert 'Traceback' not in done.stderr
