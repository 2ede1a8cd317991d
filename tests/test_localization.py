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


def localize(bag: Path, map_dir: Path, max_scans: int | None = None, **overrides):
    from lego_loam_py.offline import run_bag

    params = Params().replace(
        map_optimization__mode='localization', map_optimization__map_path=str(map_dir), **overrides
    )
    return run_bag(bag, params, progress=False, max_scans=max_scans)


def errors_against_truth(result, bag: Path) -> np.ndarray:
    """Position errors [m] of the published poses against the truth in the map's frame (map placed by its
    keyframes' fit: see the module docstring)."""
    from lego_loam_py.evaluation import errors_in_map

    prior = result.mapper.prior
    stamps, poses = result.trajectory()
    (fit,) = [
        e
        for e in errors_in_map(bag, prior.bundle.source, prior.bundle.stamps_ns, prior.poses_lidar, stamps, poses)
        if e.anchor == 'map_fit'
    ]
    return fit


# ------------------------------------------------------------------------------------------- hand-checked pieces


def test_levelling_keeps_the_heading_and_removes_roll_and_pitch():
    from scipy.spatial.transform import Rotation

    from lego_loam_py.core.localization.prior_map import heading, levelling

    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler('ZYX', [30.0, 4.0, -3.0], degrees=True).as_matrix()
    assert math.degrees(heading(pose)) == pytest.approx(30.0, abs=1e-9)  # [deg]
    tilt = levelling(pose)
    assert np.allclose(Rotation.from_euler('z', 30.0, degrees=True).as_matrix() @ tilt, pose[:3, :3], atol=1e-12)
    assert Rotation.from_matrix(tilt).as_euler('ZYX', degrees=True) == pytest.approx([0.0, 4.0, -3.0], abs=1e-9)


def test_a_hint_moves_on_with_the_odometry():
    from lego_loam_py.core.localization.relocalization import Hint

    pose, odometry = np.eye(4), np.eye(4)
    pose[:3, 3] = (10.0, 5.0, 0.0)  # in the map
    odometry[:3, 3] = (2.0, 0.0, 0.0)  # in the odometry's own frame, when the hint was given
    later = odometry.copy()
    later[0, 3] = 3.5  # 1.5 m further forward
    assert np.allclose(Hint(pose, odometry, 5.0).now(later)[:3, 3], (11.5, 5.0, 0.0))


def test_fusion_in_localization_publishes_only_with_a_recent_map_correction():
    from lego_loam_py.core.mapping.transform_fusion import TransformFusion

    mapping = TransformFusion()
    assert mapping.publishable(5_000_000_000)  # mapping: always, as the original
    fusion = TransformFusion(max_correction_age_ns=2_000_000_000)
    assert not fusion.publishable(1_000_000_000)  # no fix yet
    fusion.on_mapped(np.eye(4), np.eye(4), 1_000_000_000)
    assert fusion.publishable(1_100_000_000) and fusion.publishable(3_000_000_000)
    assert not fusion.publishable(3_100_000_000)  # the last verified step is older than 2 s
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
    # The saved map stays as it was: localization adds no keyframe, it is a mapper that builds no map.
    from lego_loam_py.core.mapping.mapper import Mapper

    assert result.counts['keyframes'] == 0 and not loc.builds_map and not hasattr(loc, 'save')
    assert isinstance(loc, Mapper) and result.mapper.prior.bundle is not None


@pytest.mark.parametrize('offset_m, offset_deg', [(0.0, 0.0), (3.0, 20.0)])
def test_an_initial_pose_is_used_and_verified_even_when_3_m_and_20_deg_off(
    campus_map, reverse_drive, offset_m, offset_deg
):
    from scipy.spatial.transform import Rotation

    from lego_loam_py.core.frames import camera_pose_to_lidar, pose6_to_matrix
    from lego_loam_py.core.mapping.map_bundle import read_bundle
    from lego_loam_py.evaluation import rigid_fit
    from lego_loam_py.inputs.sidecars import load_scenario
    from lego_loam_py.sim.output import true_poses

    bundle = read_bundle(campus_map)
    keyframes = np.array([camera_pose_to_lidar(pose6_to_matrix(p)) for p in bundle.poses6])
    map_from_world = np.linalg.inv(
        rigid_fit(keyframes[:, :3, 3], true_poses(bundle.source['simulated'], bundle.stamps_ns)[:, :3, 3])
    )
    scenario = load_scenario(reverse_drive)
    drive = {'config': scenario['config'], 'start_stamp_ns': scenario['recording']['start_stamp_ns']}
    truth = map_from_world @ true_poses(drive, np.array([drive['start_stamp_ns'] + 100_000_000]))[0]
    yaw = math.degrees(math.atan2(truth[1, 0], truth[0, 0]))
    x, y = truth[:2, 3] + offset_m * truth[:2, 1]  # to the left
    result = localize(reverse_drive, campus_map, localization__initial_pose=[float(x), float(y), yaw + offset_deg])
    loc = result.mapper
    (hint,) = [e for e in loc.events if e.kind == 'hint']
    assert 'initial_pose parameter' in hint.detail
    (fix,) = [e for e in loc.events if e.kind == 'fix']
    assert 'near the initial_pose parameter' in fix.detail and (loc.first_fix_ns - result.first_scan_ns) < 3e9
    error = errors_against_truth(result, reverse_drive)
    assert error.median_m < 0.05 and error.max_m < 0.15, error
    assert Rotation.from_matrix(truth[:3, :3]).as_euler('ZYX', degrees=True)[0] == pytest.approx(yaw, abs=1e-9)


def test_a_gap_in_the_data_loses_track_and_the_place_is_found_again(campus_map, reverse_drive, tmp_path):
    from lego_loam_py.testing.bags import cut_bag

    cut = cut_bag(reverse_drive, tmp_path / 'cut', 2.0, 2.5)  # (the benchmark cuts 10 s of a longer drive)
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


def test_a_robot_carried_elsewhere_without_a_gap_loses_track_and_is_found_again(campus_map, reverse_drive):
    """A kidnap with no gap in the data: 3 s of the reverse drive (from 12 m back to 7 m along the loop), then, with
    the stamps running on, the scans of bags/campus_8s from 1.5 m on, driven the other way: the scans no longer fit
    where the odometry says the robot is, tracking fails 3 steps in a row, and the new place is found."""
    from lego_loam_py.bag.io import BagReader, cloud_msg_to_array
    from lego_loam_py.core.pipeline import Pipeline

    def clouds(bag, first, count):
        with BagReader(bag) as reader:
            messages = [m for m in reader.messages(topics=['/velodyne_points'])][first : first + count]
            return [cloud_msg_to_array(reader.deserialize(m)) for m in messages]

    params = Params().replace(
        map_optimization__mode='localization', map_optimization__map_path=str(campus_map), sensor__imu_topic=''
    )
    pipeline = Pipeline(params)
    scans = clouds(reverse_drive, 0, 30) + clouds(CAMPUS, 10, 50)
    for k, points in enumerate(scans):
        pipeline.process_scan(points, 1_700_000_000_000_000_000 + k * 100_000_000)
    result = pipeline.finish()
    loc = result.mapper
    assert [e.kind for e in loc.events] == ['fix', 'lost', 'fix'], [(e.kind, e.detail) for e in loc.events]
    lost = [e for e in loc.events if e.kind == 'lost'][0]
    assert lost.detail.startswith('3 tracking steps in a row failed')
    assert lost.stamp_ns - 1_700_000_000_000_000_000 <= 4.5e9  # (the jump at 3 s, a step every 0.4 s)
    again = [e for e in loc.events if e.kind == 'fix'][1]
    assert again.stamp_ns - lost.stamp_ns <= 3e9
    # The new place: bags/campus_8s's own poses are the map's keyframes there.
    stamps, poses = result.trajectory(axes='camera_init')
    after = poses[stamps > again.stamp_ns]
    bundle = loc.prior.bundle
    for stamp, pose in zip(stamps[stamps > again.stamp_ns], after):
        k = int(round((stamp - 1_700_000_000_000_000_000) * 1e-8)) - 30 + 10  # the scan of campus_8s it was
        truth = [
            np.interp(1_700_000_000_000_000_000 + k * 100_000_000, bundle.stamps_ns, bundle.poses6[:, 3 + i])
            for i in range(3)
        ]
        assert np.linalg.norm(pose[:3, 3] - truth) < 0.1


def test_another_scene_never_localizes_its_look_alike_places_fail_the_verification(campus_map):
    # Every keyframe a candidate (relocalization_threshold 1): each must be turned down by the registration's gates
    # (3 s of the hairpin: 7 attempts of 3 places).
    result = localize(AGGRESSIVE, campus_map, max_scans=30, localization__relocalization_threshold=1.0)
    loc = result.mapper
    assert loc.counters.get('fixes', 0) == 0 and len(result.trajectory()) == 0
    assert loc.counters.get('places_rejected', 0) >= 10 and loc.counters.get('places_verified', 0) == 0, loc.counters
    status = loc.status()
    assert status.state == 'relocalizing' and not status.localized
    assert status.message.startswith('no pose yet: relocalizing in the whole map (') and 'last: ' in status.message


# ------------------------------------------------------------------------------------------------- run --map


def test_run_with_a_map_localizes_and_reports_the_first_fix(campus_map, reverse_drive, tmp_path):
    out = tmp_path / 'out'
    done = subprocess.run(
        [BIN / 'lego_loam_py', 'run', reverse_drive, '--map', campus_map, '-o', out, '--no-progress'],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert 'localization in' in done.stdout and 'first fix after' in done.stdout
    summary = json.loads((out / 'summary.json').read_text())
    localization = summary['localization']
    assert localization['time_to_first_fix_s'] <= 3.0 and localization['localized_fraction'] > 0.7
    assert localization['fixes'] == 1 and localization['map_keyframes'] == 20
    assert {e['anchor'] for e in localization['error_in_map']} == {'first_keyframe', 'map_fit'}
    assert summary['counts']['keyframes'] == 0 and not (out / 'map').exists()
    assert (out / 'trajectory.tum').is_file() and summary['poses'] == round(
        localization['localized_fraction'] * summary['counts']['scans_in']
    )
    # A bundle that cannot be used: one line naming the problem, exit code 1, nothing else.
    done = subprocess.run(
        [
            BIN / 'lego_loam_py',
            'run',
            reverse_drive,
            '--map',
            tmp_path / 'nowhere',
            '-o',
            tmp_path / 'x',
            '--no-progress',
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert (
        done.returncode == 1
        and done.stderr.strip().splitlines()[-1] == f'error: map bundle {tmp_path / "nowhere"}: no such directory'
    )
    assert 'Traceback' not in done.stderr


# ----------------------------------------------------------------------------------------------------- the node


def _initial_pose(frame: str, x: float, y: float, yaw_deg: float, variance: float = 0.25):
    from geometry_msgs.msg import PoseWithCovarianceStamped

    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = frame
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
    msg.pose.pose.orientation.z = math.sin(math.radians(yaw_deg) / 2)
    msg.pose.pose.orientation.w = math.cos(math.radians(yaw_deg) / 2)
    msg.pose.covariance[0] = msg.pose.covariance[7] = variance
    return msg


def test_initial_pose_messages_as_rviz_sends_them():
    from lego_loam_py.ros.localization import initial_pose_of

    hint = initial_pose_of(_initial_pose('map', 3.0, -2.0, 30.0), 5.0)
    assert hint == pytest.approx((3.0, -2.0, 30.0, 5.0), abs=1e-9)  # (x, y [m], yaw [deg], radius [m])
    # A wide covariance widens the search: 3 sigma of x and y, at most 100 m.
    assert initial_pose_of(_initial_pose('map', 0.0, 0.0, 0.0, variance=16.0), 5.0)[3] == pytest.approx(12.0, abs=1e-9)
    assert initial_pose_of(_initial_pose('map', 0.0, 0.0, 0.0, variance=1e6), 5.0)[3] == 100.0
    # camera_init is the same frame in LOAM camera axes: x left, y up, z forward.
    msg = _initial_pose('camera_init', 0.0, 0.0, 0.0)
    msg.pose.pose.position.x, msg.pose.pose.position.z = 2.0, 7.0
    msg.pose.pose.orientation.y, msg.pose.pose.orientation.z = msg.pose.pose.orientation.z, 0.0
    assert initial_pose_of(msg, 5.0)[:3] == pytest.approx((7.0, 2.0, 0.0), abs=1e-9)
    bad = _initial_pose('map', float('nan'), 0.0, 0.0)
    for msg, reason in (
        (_initial_pose('odom', 0.0, 0.0, 0.0), "frame 'odom' is neither 'map' nor 'camera_init'"),
        (bad, 'the pose is not finite'),
    ):
        with pytest.raises(ValueError, match=re.escape(reason)):
            initial_pose_of(msg, 5.0)
    msg = _initial_pose('map', 0.0, 0.0, 0.0)
    msg.pose.pose.orientation.w = 3.0
    with pytest.raises(ValueError, match='no unit quaternion'):
        initial_pose_of(msg, 5.0)


def test_the_node_publishes_nothing_until_localized_and_says_why(context, campus_map, tmp_path):
    from diagnostic_msgs.msg import DiagnosticStatus

    from lego_loam_py.ros.conversions import odometry_to_pose, stamp_to_ns
    from lego_loam_py.ros.map_optimization_node import MapOptimizationNode
    from tests.support.inprocess import make_node, mapping_inputs, pipeline_outputs

    inputs = mapping_inputs(pipeline_outputs(context, tmp_path))

    def feed(node, parts):
        for name, msg in zip(('corner', 'surf', 'outlier', 'odometry'), parts):
            node.on_part(name, msg)

    # A map that is not there: an error, said once in the log and on /localization_status, and the node carries on.
    missing = tmp_path / 'no_map'
    node, rec = make_node(
        context,
        MapOptimizationNode,
        tmp_path,
        **{'map_optimization.mode': 'localization', 'map_optimization.map_path': str(missing)},
    )
    node.localization.publish_status()  # (the recorder was installed after the node's first status)
    status = rec.out('/localization_status')[-1]
    assert status.level == DiagnosticStatus.ERROR and f'map bundle {missing}: no such directory' in status.message
    for parts in inputs[:4]:
        feed(node, parts)
    node.localization.on_initial_pose(_initial_pose('map', 1.0, 0.0, 0.0))
    assert not rec.errors and not rec.out('/aft_mapped_to_init') and node.counters['inputs_without_map'] >= 1
    assert node.counters['initial_pose_dropped'] == 1
    assert node._save_now()[0] is True and 'never modified' in node._save_now()[1]
    node.destroy_node()

    node, rec = make_node(
        context,
        MapOptimizationNode,
        tmp_path,
        **{'map_optimization.mode': 'localization', 'map_optimization.map_path': str(campus_map)},
    )
    # Bad /initialpose messages are dropped with a warning.
    node.localization.on_initial_pose(_initial_pose('odom', 1.0, 0.0, 0.0))
    node.localization.on_initial_pose(_initial_pose('map', float('inf'), 0.0, 0.0))
    assert node.counters['initial_pose_dropped'] == 2
    assert sum("/initialpose dropped: frame 'odom'" in text for _, text in rec.warnings) == 1
    node.localization.publish_status()
    assert rec.out('/localization_status')[-1].level == DiagnosticStatus.WARN
    published = []
    for parts in inputs:
        feed(node, parts)
        published.append(len(rec.out('/aft_mapped_to_init')))
        if not published[-1]:  # until the fix: nothing out, and it says so
            assert rec.out('/localization_status')[-1].level == DiagnosticStatus.WARN
    assert not rec.errors and published[-1] >= 2, published
    assert any(key == 'not_localized' and text.startswith('no pose yet: ') for key, text in rec.warnings)
    last = rec.out('/localization_status')[-1]
    assert last.level == DiagnosticStatus.OK and last.message.startswith('localized in the map')
    assert node.counters['steps_not_localized'] >= 2
    # The same drive the map was made from: the poses are on the map's keyframe trajectory (camera_init = the map's
    # frame), between the keyframes before and after them in time.
    bundle = node.core.prior.bundle
    for msg in rec.out('/aft_mapped_to_init'):
        position = odometry_to_pose(msg)[:3, 3]
        on_the_way = [
            np.interp(stamp_to_ns(msg.header.stamp), bundle.stamps_ns, bundle.poses6[:, 3 + i]) for i in range(3)
        ]
        assert np.linalg.norm(position - on_the_way) < 0.05, (position, on_the_way)
    assert node.statistics()['localization']['fixes'] == 1
    assert {v.key: v.value for v in node.diagnostic_status().values}['localization_state'] == 'localized'
    node.destroy_node()


def test_no_initial_pose_message_breaks_the_node(context, campus_map, tmp_path):
    """Random /initialpose messages (non-finite, huge, zero quaternions, other frames, odd covariances): each is
    taken as a hint or dropped with a warning, and the node keeps localizing."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from lego_loam_py.ros.map_optimization_node import MapOptimizationNode
    from tests.support.inprocess import make_node, mapping_inputs, pipeline_outputs

    node, rec = make_node(
        context,
        MapOptimizationNode,
        tmp_path,
        **{'map_optimization.mode': 'localization', 'map_optimization.map_path': str(campus_map)},
    )
    values = st.floats(allow_nan=True, allow_infinity=True, width=64) | st.sampled_from([0.0, 1.0, -1.0, 1e300])
    tried = []

    @settings(
        max_examples=300,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    )
    @given(
        st.sampled_from(['map', '/map', 'camera_init', '', 'odom', 'base_link', 'map\x00']),
        st.lists(values, min_size=7, max_size=7),
        st.lists(values, min_size=36, max_size=36),
    )
    def check(frame, pose, covariance):
        msg = _initial_pose(frame, 0.0, 0.0, 0.0)
        p = msg.pose.pose
        p.position.x, p.position.y, p.position.z = pose[:3]
        p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = pose[3:]
        msg.pose.covariance = covariance
        node.localization.on_initial_pose(msg)
        tried.append(1)
        assert not rec.errors

    check()
    counted = node.counters.get('initial_poses', 0) + node.counters.get('initial_pose_dropped', 0)
    assert counted == len(tried) and node.counters['initial_pose_dropped'] > 0
    for parts in mapping_inputs(pipeline_outputs(context, tmp_path))[:4]:  # (it still runs its steps)
        for name, msg in zip(('corner', 'surf', 'outlier', 'odometry'), parts):
            node.on_part(name, msg)
    assert not rec.errors and node.core.counters['steps'] >= 1
    node.destroy_node()


# ------------------------------------------------------------------------------------------------------ over DDS


def test_launch_in_localization_mode_publishes_integrated_to_init_in_the_saved_maps_frame(
    campus_map, reverse_drive, tmp_path, ros_domain, processes
):
    """The four nodes as users start them, replaying the reverse drive: /integrated_to_init comes out in the saved
    map's frame (camera_init of the map), only once a place was verified, and the map is left as it was."""
    from lego_loam_py.bag.io import BagReader
    from lego_loam_py.core.frames import camera_pose_to_lidar, pose6_to_matrix, quaternion_to_matrix
    from lego_loam_py.core.mapping.map_bundle import read_bundle
    from lego_loam_py.evaluation import errors_in_map

    before = {p.name: p.read_bytes() for p in campus_map.iterdir()}
    record = tmp_path / 'recording'
    launcher = processes.start(
        [
            BIN / 'lego_loam_py',
            'launch',
            '--bag',
            reverse_drive,
            '--record',
            '/integrated_to_init',
            '/localization_status',
            '-o',
            record,
            '--stats-dir',
            tmp_path / 'stats',
            '--log-dir',
            tmp_path / 'logs',
            '--quiet-nodes',
            '-p',
            f'map_optimization.file_directory:={tmp_path / "maps"}',
            '-p',
            'map_optimization.mode:=localization',
            '-p',
            f'map_optimization.map_path:={campus_map}',
        ],
        stderr=subprocess.STDOUT,
    )
    out, _ = launcher.communicate(timeout=300)
    logs = '\n'.join(p.read_text()[-3000:] for p in sorted((tmp_path / 'logs').glob('*.log')))
    assert launcher.returncode == 0, out + logs
    integrated, status = [], []
    with BagReader(record) as reader:
        for message in reader.messages():
            msg = reader.deserialize(message)
            (integrated if message.topic == '/integrated_to_init' else status).append(msg)
    assert integrated and status, out + logs
    assert {(m.header.frame_id, m.child_frame_id) for m in integrated} == {('camera_init', 'camera')}
    stamps = np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in integrated])
    poses = np.tile(np.eye(4), (len(integrated), 1, 1))
    for pose, m in zip(poses, integrated):
        p, q = m.pose.pose.position, m.pose.pose.orientation
        pose[:3, :3], pose[:3, 3] = quaternion_to_matrix([q.x, q.y, q.z, q.w]), (p.x, p.y, p.z)
    bundle = read_bundle(campus_map)
    keyframes = np.array([camera_pose_to_lidar(pose6_to_matrix(p)) for p in bundle.poses6])
    lidar_poses = np.array([camera_pose_to_lidar(p) for p in poses])
    (fit,) = [
        e
        for e in errors_in_map(reverse_drive, bundle.source, bundle.stamps_ns, keyframes, stamps, lidar_poses)
        if e.anchor == 'map_fit'
    ]
    # In the map's frame: 12 m along it and the other way round, not at the odometry's origin (its first pose).
    assert fit.max_m < 0.2 and np.linalg.norm(poses[0][:3, 3]) > 5.0, fit
    statistics = json.loads((tmp_path / 'stats' / 'mapOptimization.json').read_text())['localization']
    assert statistics['fixes'] >= 1 and statistics['state'] == 'localized', statistics
    first_fix = min(e['stamp_ns'] for e in statistics['events'] if e['kind'] == 'fix')
    assert stamps.min() > first_fix  # nothing before the fix
    assert status[-1].level == 0 and status[-1].message.startswith('localized in the map')
    assert {p.name: p.read_bytes() for p in campus_map.iterdir()} == before  # the saved map, untouched
    assert 'Traceback' not in logs


def test_launch_refuses_a_saved_map_that_is_not_there(tmp_path, ros_domain):
    done = subprocess.run(
        [
            BIN / 'lego_loam_py',
            'launch',
            '-p',
            'map_optimization.mode:=localization',
            '-p',
            f'map_optimization.map_path:={tmp_path / "none"}',
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 1 and f'error: map bundle {tmp_path / "none"}: no such directory' in done.stderr
    assert 'started' not in done.stderr and 'Traceback' not in done.stderr
