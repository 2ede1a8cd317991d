"""The whole system as users run it: the four nodes as separate processes over DDS, through the supervisor.

* ``lego_loam_py launch`` with the nodes on sim time, fed bags/campus_8s: every topic of the original with its
  type and frame (the subscriber-gated ones while this test subscribes), the TF tree, /integrated_to_init for
  >= 95 % of the scans, accuracy against the ground truth beside the bag, no crash, a clean Ctrl-C, nothing
  left running afterwards.
* ``lego_loam_py demo`` (the supervisor with its player and recorder): outputs exist and parse.

The first test plays the bag itself, in lockstep: /clock, the IMU samples and a cloud, then it waits for that
scan's /integrated_to_init before the next cloud. "Every scan comes out" then checks the pipeline (topics,
synchronisation, QoS, the supervisor), not the speed of the machine, which may be shared with other jobs: how
many scans the pipeline keeps at 1x and 2x is measured by benchmarks/bench_pipeline.py, never asserted here.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.ros.conversions import serialized_stamp_ns
from lego_loam_py.testing.nodes import Diagnostics, links_matched, read_until, release
from tests.support.topics import ALWAYS, GATED, TF_DYNAMIC, TF_STATIC, message_class

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
BAG = REPO / 'bags' / 'campus_8s'
NODES = ('imageProjection', 'featureAssociation', 'mapOptimization', 'transformFusion')
SCANS = 80
# Accuracy bound: `lego_loam_py run bags/campus_8s` (offline, the same cores) reaches an ATE RMSE of 0.022 m
# (0.032 m with the odometry of commit 28acd54; 0.033 m without the IMU); over DDS we measured 0.035 m.
# About twice the worst of the offline figures:
ATE_BOUND_M = 0.065
MIN_INTEGRATED_FRACTION = 0.95
SCAN_TIMEOUT_S = 10.0  # per scan in lockstep: only a lost scan (or a hung node) waits this long


def _alive(pid: int) -> bool:
    try:
        state = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0]
        return state not in ('Z', 'X')
    except (FileNotFoundError, IndexError):
        return False


def _started_pids(output: str) -> dict[str, int]:
    return {m.group(1): int(m.group(2)) for m in re.finditer(r'started (\S+) \(pid (\d+)\)', output)}


def _logs(directory: Path) -> str:
    return '\n'.join(f'--- {p.name}\n{p.read_text()[-3000:]}' for p in sorted(directory.glob('*.log')))


def test_pipeline_over_dds_publishes_every_topic_and_tracks_the_ground_truth(tmp_path, rclpy_context, processes):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.serialization import deserialize_message
    from rosgraph_msgs.msg import Clock
    from tf2_msgs.msg import TFMessage

    from lego_loam_py.bag.io import BagReader
    from lego_loam_py.core.frames import camera_pose_to_lidar
    from lego_loam_py.evaluation import evaluate
    from lego_loam_py.inputs.sidecars import load_ground_truth
    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import ns_to_stamp, odometry_to_pose, stamp_to_ns
    from lego_loam_py.ros.tf import TF_QOS, TF_STATIC_QOS

    logs = tmp_path / 'logs'
    launcher = processes.start(
        [
            BIN / 'lego_loam_py',
            'launch',
            '--use-sim-time',
            'true',
            '--stats-dir',
            tmp_path / 'stats',
            '--log-dir',
            logs,
            '--quiet-nodes',
            '-p',
            f'map_optimization.file_directory:={tmp_path / "maps"}',
        ],
        stderr=subprocess.STDOUT,
    )

    node = rclpy.create_node('end_to_end_listener', context=rclpy_context)
    first: dict[str, bytes] = {}
    subscriptions = {}
    for topic, (_, type_name, _, _) in {**ALWAYS, **GATED}.items():
        if topic != '/integrated_to_init':
            subscriptions[topic] = node.create_subscription(
                message_class(type_name),
                topic,
                lambda data, t=topic: first.setdefault(t, data),
                qos.reliable(2),
                raw=True,
            )
    integrated = []
    integrated_subscription = node.create_subscription(
        message_class('nav_msgs/msg/Odometry'), '/integrated_to_init', integrated.append, qos.reliable(100)
    )
    tf_pairs, static_pairs = set(), set()
    node.create_subscription(
        TFMessage, '/tf', lambda m: tf_pairs.update((t.header.frame_id, t.child_frame_id) for t in m.transforms), TF_QOS
    )
    node.create_subscription(
        TFMessage,
        '/tf_static',
        lambda m: static_pairs.update((t.header.frame_id, t.child_frame_id) for t in m.transforms),
        TF_STATIC_QOS,
    )
    diagnostics = Diagnostics(node)
    clock = node.create_publisher(Clock, '/clock', qos.reliable(10))
    reader = BagReader(BAG)
    reader.open()
    topics = reader.topics()
    publishers = {
        t: node.create_publisher(message_class(topics[t]), t, qos.reliable(100))
        for t in ('/velodyne_points', '/imu/data')
    }
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)

    def spin(condition, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not condition() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
            # Unsubscribe once a topic has been seen: a subscriber-gated topic costs its node work for every
            # scan, and every message costs this process time on the cores the pipeline runs on.
            for topic in [t for t in subscriptions if t in first]:
                node.destroy_subscription(subscriptions.pop(topic))
        return condition()

    try:
        head = read_until(launcher, 'ready after', timeout=90)
        assert spin(lambda: all(p.get_subscription_count() for p in publishers.values()), 30)
        # Every link matched at both ends before the first scan, as the nodes report it on /diagnostics: a message
        # sent on a link one end has not matched yet is lost, and this process's view of the graph does not tell
        # (a fresh clone's start lost its second and third scans so: two 10 s waits in lockstep).
        ip, fa, mo, tf = NODES
        links = [
            (publishers['/velodyne_points'], '/velodyne_points', [ip]),
            *[(ip, topic, [fa]) for topic in ('/segmented_cloud', '/segmented_cloud_info', '/outlier_cloud')],
            *[
                (fa, topic, [mo])
                for topic in ('/laser_cloud_corner_last', '/laser_cloud_surf_last', '/outlier_cloud_last')
            ],
            (fa, '/laser_odom_to_init', [mo, tf]),
            (mo, '/aft_mapped_to_init', [tf]),
            (tf, '/integrated_to_init', [integrated_subscription]),
        ]
        assert spin(lambda: links_matched(diagnostics, links), 60), diagnostics.latest
        # Lockstep: /clock, the IMU samples recorded before the cloud, the cloud, its /integrated_to_init.
        pending_imu, waited_out = [], []
        for message in reader.messages(topics=list(publishers)):
            if message.topic == '/imu/data':
                pending_imu.append(message.data)
                continue
            clock.publish(Clock(clock=ns_to_stamp(message.timestamp)))
            for data in pending_imu:
                publishers['/imu/data'].publish(data)
            pending_imu.clear()
            publishers['/velodyne_points'].publish(message.data)
            stamp = serialized_stamp_ns(message.data)
            if '/segmented_cloud' not in first:
                # The first scan only initialises the odometry: nothing comes out of the pipeline for it. It is
                # sent again until imageProjection has it: its best-effort input drops what arrives before it
                # has matched this publisher, which only it knows (a duplicate is dropped as not newer).
                for _ in range(6):
                    if spin(lambda: '/segmented_cloud' in first, 5.0):
                        break
                    publishers['/velodyne_points'].publish(message.data)
                continue
            if not spin(lambda: integrated and stamp_to_ns(integrated[-1].header.stamp) >= stamp, SCAN_TIMEOUT_S):
                waited_out.append(stamp)
        clock.publish(Clock(clock=ns_to_stamp(reader.end_time + 6_000_000_000)))  # past the 5 s map period
        spin(lambda: set(GATED) <= set(first), 10.0)
        # Every node reports on /diagnostics once a second (wall time, although the nodes run on sim time).
        spin(
            lambda: (
                diagnostics.counter('imageProjection', 'clouds_in') >= SCANS
                and set(NODES) <= set(diagnostics.latest)
                and diagnostics.counter('transformFusion', 'integrated') >= len(integrated)
            ),
            10.0,
        )
    finally:
        reader.close()
    os.kill(launcher.pid, signal.SIGINT)  # Ctrl-C
    out, _ = launcher.communicate(timeout=60)
    out = head + out
    executor.shutdown(timeout_sec=0.1)
    assert launcher.returncode == 0, out + _logs(logs)

    # No crash, clean stops, nothing left behind.
    pids = _started_pids(out)
    assert set(pids) == set(NODES), out
    for name in NODES:
        assert f'{name} (pid {pids[name]}): stopped, exit code 0' in out, out
    assert not [name for name, pid in pids.items() if _alive(pid)], 'processes of the run are still alive'
    assert 'Traceback' not in _logs(logs), _logs(logs)
    stats = {name: json.loads((tmp_path / 'stats' / f'{name}.json').read_text()) for name in NODES}
    assert stats['imageProjection']['counters']['clouds_in'] >= SCANS  # every cloud (the first may come twice)
    assert not stats['imageProjection']['counters'].get('clouds_dropped')

    # Every topic, with its type (a subscription of another type would not have matched) and frames.
    missing = sorted(set(ALWAYS) - {'/integrated_to_init'} - set(first))
    assert not missing, f'never published: {missing}'
    missing = sorted(set(GATED) - set(first))
    assert not missing, f'not published while subscribed: {missing}'
    for topic, raw in first.items():
        _, type_name, frame, child = {**ALWAYS, **GATED}[topic]
        msg = deserialize_message(raw, message_class(type_name))
        assert msg.header.frame_id == frame, (topic, msg.header.frame_id)
        if child is not None:
            assert msg.child_frame_id == child, (topic, msg.child_frame_id)
    assert {(m.header.frame_id, m.child_frame_id) for m in integrated} == {('camera_init', 'camera')}
    assert set(diagnostics.latest) >= set(NODES), diagnostics.latest
    assert diagnostics.counter('imageProjection', 'clouds_in') >= SCANS
    assert diagnostics.counter('transformFusion', 'integrated') >= len(integrated)  # (counted as published)
    assert all(level == 0 for level in diagnostics.levels.values()), diagnostics.messages
    assert tf_pairs >= TF_DYNAMIC, tf_pairs
    assert static_pairs >= TF_STATIC, static_pairs

    # /integrated_to_init for (almost) every scan; the first one only initialises the odometry.
    assert len(integrated) >= MIN_INTEGRATED_FRACTION * SCANS, f'{len(integrated)} of {SCANS} scans'
    assert len(waited_out) <= 1, (
        f'no output within {SCAN_TIMEOUT_S} s for the scans stamped {waited_out}; '
        f'/integrated_to_init stamps {[stamp_to_ns(m.header.stamp) for m in integrated[:5]]}...; counters '
        f'{ {name: stats[name]["counters"] for name in NODES} }\n{_logs(logs)}'
    )
    stamps = np.array([stamp_to_ns(m.header.stamp) for m in integrated])
    assert (np.diff(stamps) > 0).all()

    # Accuracy against the ground truth beside the bag (REP-103 poses of the lidar).
    poses = np.array([camera_pose_to_lidar(odometry_to_pose(m)) for m in integrated])
    metrics = evaluate(load_ground_truth(BAG), (stamps, poses))
    assert metrics.matched_poses >= MIN_INTEGRATED_FRACTION * SCANS
    assert metrics.ate_rmse_m < ATE_BOUND_M, metrics.summary()
    assert metrics.path_length_m > 12.0  # the car drove ~13.4 m: the estimate is not standing still
    release(node)


def _trim_bag(source: Path, target: Path, seconds: float) -> None:
    """The first ``seconds`` of a bag, with the ground truth and the scenario beside it."""
    from lego_loam_py.bag.io import BagReader, BagWriter

    with BagReader(source) as reader, BagWriter(target) as writer:
        stop = reader.start_time + int(seconds * 1e9)
        for message in reader.messages(stop=stop):
            writer.write_raw(message.topic, message.msgtype, message.timestamp, message.data)
    shutil.copy(source / 'ground_truth.tum', target / 'ground_truth.tum')
    shutil.copy(source / 'scenario.yaml', target / 'scenario.yaml')


@pytest.mark.parametrize('composed', [False, True], ids=['four processes', 'one process'])
def test_demo_writes_a_summary_trajectory_map_and_png(tmp_path, ros_domain, composed):
    from lego_loam_py.bag.io import BagReader
    from lego_loam_py.formats import read_pcd, read_tum

    bag = tmp_path / 'campus_4s'
    _trim_bag(BAG, bag, 4.0)
    with BagReader(bag) as reader:
        scans = reader.topic_counts()['/velodyne_points']
    assert 38 <= scans <= 41
    out = tmp_path / 'demo'
    # (The timeout only guards against a hang: start-up and the map's evaluation take longer on a busy machine.)
    result = subprocess.run(
        [BIN / 'lego_loam_py', 'demo', bag, '-o', out, '--rate', '0.5', '--no-progress', *(['--composed'] * composed)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr + _logs(out / 'logs')

    # The printed summary.
    text = result.stdout
    assert f'scans in {scans} (' in text
    assert ('the four nodes in one process' if composed else 'four nodes as separate processes') in text
    assert re.search(r'processed: imageProjection \d+, featureAssociation \d+ .*transformFusion \d+', text), text
    assert re.search(r'/integrated_to_init for \d+ of \d+ scans', text) and 'dropped messages' in text
    for name in ('imageProjection', 'featureAssociation', 'mapOptimization', 'transformFusion'):
        assert re.search(rf'{name}\s+\d+\.\d\s+\d+\.\d\s+\d+', text), name  # ms per scan: median, p95, n
    assert 'trajectory length' in text and 'accuracy vs ground truth: ATE RMSE' in text

    # The files, parsed.
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['scans_in'] == scans and summary['mode'] == 'dds'
    stamps, poses = read_tum(out / 'trajectory.tum')
    stamps_ci, poses_ci = read_tum(out / 'trajectory_camera_init.tum')
    assert len(stamps) == summary['integrated'] == summary['processed']['transformFusion'] >= scans // 2
    assert np.array_equal(stamps, stamps_ci) and np.isfinite(poses).all()
    # REP-103 vs camera_init axes: the car drives forward along +x in map, +z in camera_init.
    assert poses[-1, 0, 3] > 3.0 and poses_ci[-1, 2, 3] > 3.0
    assert summary['accuracy']['matched_poses'] >= len(stamps) - 1
    assert summary['accuracy']['ate_rmse_m'] < 0.2
    cloud = read_pcd(out / 'map' / 'global_map.pcd')
    assert cloud.shape[1] >= 3 and len(cloud) > 1000
    # The saved map opens with open3d and lies on the simulated scene's surfaces.
    import open3d as o3d

    assert len(o3d.io.read_point_cloud(str(out / 'map' / 'global_map.pcd')).points) == len(cloud)
    assert summary['map_to_scene']['points'] == len(cloud) and summary['map_to_scene']['median_m'] < 0.15
    assert 'median point-to-mesh distance' in text
    assert read_tum(out / 'map' / 'trajectory.tum')[0].size >= 5  # keyframes
    png = (out / 'trajectory.png').read_bytes()
    assert png[:8] == b'\x89PNG\r\n\x1a\n' and len(png) > 20_000
    assert {p.stem for p in (out / 'stats').glob('*.json')} == set(NODES)
    for path in (out / 'stats').glob('*.json'):  # no callback of any node failed
        assert json.loads(path.read_text())['counters'].get('callback_errors', 0) == 0, path.stem
    assert (out / 'recording' / 'metadata.yaml').is_file()
    processes = {p.stem for p in (out / 'logs').glob('*.log')} & {*NODES, 'legoLoam'}
    assert processes == ({'legoLoam'} if composed else set(NODES))


def test_demo_summary_accounts_for_every_scan():
    """The demo's figures from the nodes' statistics: processed per node, drops, queue overwrites, timings."""
    from lego_loam_py.demo import _node_summary, format_demo_summary
    from lego_loam_py.results import DemoSummary, RunOutputs

    timing = dict(median=10.0, p95=20.0, mean=12.0, count=70)
    stats = {
        'imageProjection': {
            'counters': {'clouds_in': 79, 'clouds_out': 78, 'clouds_dropped': 1},
            'timings_ms': {'scan': timing},
        },
        'featureAssociation': {
            'counters': {
                'scans_processed': 70,
                'scans_dropped': 2,
                'unmatched_inputs': 4,
                'imu_dropped': 0,
                'scans_with_imu': 65,
            },
            'timings_ms': {'scan': timing},
        },
        'mapOptimization': {
            'counters': {
                'mapping_steps': 22,
                'keyframes': 20,
                'unmatched_inputs': 35,
                'inputs_skipped_by_interval': 14,
            },
            'timings_ms': {'step': timing},
        },
        'transformFusion': {'counters': {'integrated': 69, 'mapped': 22}, 'timings_ms': {}},
    }
    processed, drops, timings = _node_summary(stats)
    assert processed == {'imageProjection': 78, 'featureAssociation': 70, 'mapOptimization': 22, 'transformFusion': 69}
    # mapOptimization's unmatched inputs are the odometry of scans not sent to mapping: not drops.
    assert drops == {
        'imageProjection': {'clouds_dropped': 1},
        'featureAssociation': {'scans_dropped': 2, 'unmatched_inputs': 4},
    }
    assert set(timings) == {'imageProjection', 'featureAssociation', 'mapOptimization'}
    summary = DemoSummary(
        bag='bags/x',
        rate=1.0,
        bag_duration_s=8.0,
        wall_time_s=9.0,
        scans_in=80,
        processed=processed,
        integrated=69,
        not_received=1,
        drop_counters=drops,
        queue_overwritten=6,
        keyframes=20,
        scans_with_imu=65,
        timings_ms=timings,
        processes=[],
        failures=[],
        interrupted=False,
        ready_after_s=3.0,
        outputs=RunOutputs(trajectory_length_m=13.4),
    )
    assert summary.dropped == 1 + 1 + 2 + 4 and summary.integrated_fraction == 69 / 80
    text = format_demo_summary(summary)
    assert 'scans in 80 (8.0 s of data); processed: imageProjection 78, featureAssociation 70 (IMU on 65)' in text
    assert '/integrated_to_init for 69 of 80 scans (86.2%' in text
    assert (
        'dropped messages 8: 1 never reached imageProjection; imageProjection clouds_dropped 1; '
        'featureAssociation scans_dropped 2, unmatched_inputs 4'
    ) in text
    assert '+ 6 scans featureAssociation never got' in text
    assert re.search(r'mapOptimization\s+10\.0\s+20\.0\s+70\s+\(per mapping step\)', text)
    assert 'accuracy: no ground truth beside the bag' in text
