"""Over DDS, between processes: CloudInfo intact, latched /tf_static for late subscribers, `ros2 run`."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.testing.nodes import release, spin_until, wait_for_line
from tests.support.samples import cloud_info_arrays

REPO = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent


def test_cloud_info_between_processes(rclpy_context, processes):
    import rclpy

    from cloud_msgs.msg import CloudInfo
    from lego_loam_py.ros import qos

    publisher = processes.python('-m', 'tests.support.publisher', 'cloud_info', cwd=REPO)
    wait_for_line(publisher, 'ready')
    node = rclpy.create_node('cloud_info_listener', context=rclpy_context)
    received = []
    node.create_subscription(CloudInfo, '/segmented_cloud_info', received.append, qos.reliable(1))
    assert spin_until(rclpy_context, node, lambda: received, timeout=20), 'no CloudInfo received'
    msg = received[0]
    expected = cloud_info_arrays()
    assert msg.header.frame_id == 'velodyne'
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_600_000_000, 250_000_000)
    assert np.array_equal(np.frombuffer(msg.start_ring_index, np.int32), expected['start_ring_index'])
    assert np.array_equal(np.frombuffer(msg.end_ring_index, np.int32), expected['end_ring_index'])
    assert np.float32(msg.start_orientation) == expected['start_orientation']
    assert np.float32(msg.end_orientation) == expected['end_orientation']
    assert np.float32(msg.orientation_diff) == expected['orientation_diff']
    assert np.array_equal(np.array(msg.segmented_cloud_ground_flag, bool), expected['segmented_cloud_ground_flag'])
    assert np.array_equal(np.frombuffer(msg.segmented_cloud_col_ind, np.uint32), expected['segmented_cloud_col_ind'])
    assert np.array_equal(np.frombuffer(msg.segmented_cloud_range, np.float32), expected['segmented_cloud_range'])
    release(node)


def test_tf_static_reaches_a_late_subscriber(rclpy_context, processes):
    import rclpy
    from tf2_msgs.msg import TFMessage

    from lego_loam_py.core import frames
    from lego_loam_py.ros import qos

    publisher = processes.python('-m', 'tests.support.publisher', 'tf_static', cwd=REPO)
    wait_for_line(publisher, 'ready')
    time.sleep(1.5)  # the transforms were sent long before this subscriber exists
    node = rclpy.create_node('late_tf_listener', context=rclpy_context)
    received = []
    node.create_subscription(TFMessage, '/tf_static', received.append, qos.latched())
    assert spin_until(rclpy_context, node, lambda: received, timeout=20), 'no /tf_static received'
    transforms = {(t.header.frame_id, t.child_frame_id): t for t in received[-1].transforms}
    assert set(transforms) == {('map', 'camera_init'), ('camera', 'base_link')}
    for key, expected in [
        (('map', 'camera_init'), frames.MAP_T_CAMERA_INIT),
        (('camera', 'base_link'), frames.CAMERA_T_BASE_LINK),
    ]:
        r = transforms[key].transform.rotation
        assert np.allclose(frames.quaternion_to_matrix([r.x, r.y, r.z, r.w]), expected[:3, :3])
        assert transforms[key].header.stamp.nanosec == 42
    release(node)


def test_tf2_msgs_type_hash_is_the_official_one():
    """The TFMessage built into the venv (or a real ROS install's) has Kilted's type hash."""
    import json

    from ament_index_python.packages import get_package_share_directory
    from rosbags.typesys import Stores, get_typestore

    expected = get_typestore(Stores.ROS2_KILTED).hash_rihs01('tf2_msgs/msg/TFMessage')
    installed = Path(get_package_share_directory('tf2_msgs'), 'msg', 'TFMessage.json')
    hashes = json.loads(installed.read_text())['type_hashes']
    assert {h['type_name']: h['hash_string'] for h in hashes}['tf2_msgs/msg/TFMessage'] == expected


def ros2(*args, **kwargs):
    return subprocess.run([str(VENV_BIN / 'ros2'), *args], capture_output=True, text=True, timeout=60, **kwargs)


def test_ros2_run_prints_usage_of_the_cli():
    result = ros2('run', 'lego_loam_py', 'lego_loam_py', 'play', '--help')
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith('usage: lego_loam_py play') and '--rate' in result.stdout


def test_ros2_run_unknown_executable_and_package_fail_clearly():
    result = ros2('run', 'lego_loam_py', 'nosuch')
    assert result.returncode == 1 and 'No executable found' in result.stderr
    result = ros2('run', 'nosuch_package', 'x')
    assert result.returncode == 1 and "Package 'nosuch_package' not found" in result.stderr
    result = ros2('run', 'lego_loam_py')
    assert result.returncode == 2 and 'required' in result.stderr


def test_every_console_script_is_in_the_ros_layout():
    from importlib.metadata import distribution

    libdir = Path(sys.prefix, 'lib', 'lego_loam_py')
    scripts = {ep.name for ep in distribution('lego_loam_py').entry_points if ep.group == 'console_scripts'}
    assert scripts and scripts <= {p.name for p in libdir.iterdir()}
    assert Path(sys.prefix, 'share', 'ament_index', 'resource_index', 'packages', 'lego_loam_py').exists()
    from ament_index_python.packages import get_package_share_directory

    share = Path(get_package_share_directory('lego_loam_py'))
    assert (share / 'package.xml').is_file() and (share / 'config' / 'params.yaml').is_file()


@pytest.mark.parametrize('command', [['--help'], ['play', '--help'], ['record', '--help']])
def test_cli_help(command):
    result = subprocess.run([str(VENV_BIN / 'lego_loam_py'), *command], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.startswith('usage: lego_loam_py')


@pytest.mark.parametrize('executor', ['events', 'single'])
def test_a_node_serves_with_either_executor(rclpy_context, processes, executor):
    """The nodes spin rclpy's EventsExecutor by default; LEGO_LOAM_PY_EXECUTOR=single selects the
    SingleThreadedExecutor. Either way transformFusion fuses odometry and answers over DDS."""
    import os

    import rclpy
    from nav_msgs.msg import Odometry

    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import make_header, pose_to_odometry, stamp_to_ns
    from lego_loam_py.testing.nodes import Diagnostics, links_matched, publish_in_lockstep

    env = dict(os.environ, LEGO_LOAM_PY_EXECUTOR=executor)
    node = rclpy.create_node(f'executor_probe_{executor}', context=rclpy_context)
    fused = {}
    subscription = node.create_subscription(
        Odometry, '/integrated_to_init', lambda m: fused.setdefault(stamp_to_ns(m.header.stamp), m), qos.reliable(10)
    )
    odometry = node.create_publisher(Odometry, '/laser_odom_to_init', qos.reliable(10))
    diagnostics = Diagnostics(node)
    fusion = processes.start([VENV_BIN / 'transformFusion'], env=env)
    # Both links matched at both ends before the first message: transformFusion drops a resent stamp as not
    # newer, so a first fused pose sent before its writer knew this reader would never come again.
    links = [
        (odometry, '/laser_odom_to_init', ['transformFusion']),
        ('transformFusion', '/integrated_to_init', [subscription]),
    ]
    assert spin_until(rclpy_context, node, lambda: links_matched(diagnostics, links) or fusion.poll() is not None, 60)
    assert fusion.poll() is None, fusion.communicate()[1]
    items = []
    for k in range(3):
        pose = np.eye(4)
        pose[2, 3] = 0.5 * k
        stamp = 10**12 + k * 10**8
        items.append((stamp, pose_to_odometry(pose, make_header(stamp, 'camera_init'), 'laser_odom')))
    assert publish_in_lockstep(rclpy_context, node, odometry.publish, items, lambda stamp: stamp in fused, 30) == []
    assert [fused[stamp].pose.pose.position.z for stamp, _ in items] == [0.0, 0.5, 1.0]
    _, err = processes.stop(fusion)
    assert fusion.returncode == 0 and 'Traceback' not in err
    release(node)


@pytest.mark.parametrize('executable', ['imageProjection', 'legoLoam'])
def test_ros_arguments_rcl_cannot_parse_are_a_clear_error(executable):
    result = subprocess.run(
        [VENV_BIN / executable, '--ros-args', '-p', 'sensor.imu_topic:='], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2, result.stderr
    assert "error: failed to initialize rcl: Couldn't parse parameter override rule: '-p sensor.imu_topic:='" in (
        result.stderr
    )
    assert 'Traceback' not in result.stderr


def test_an_unknown_executor_is_a_clear_error(processes):
    import os

    proc = processes.start([VENV_BIN / 'transformFusion'], env=dict(os.environ, LEGO_LOAM_PY_EXECUTOR='threads'))
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert 'LEGO_LOAM_PY_EXECUTOR must be events or single' in err and 'Traceback' not in err


def test_with_sim_time_a_node_reads_the_newest_clock_tick_without_waking_for_each(rclpy_context):
    """/clock is polled by the nodes whose timers run on wall time: rclpy's own /clock subscription (a wake-up
    per tick) is gone, and the clock handed out (diagnostics stamps) is the newest tick's time. mapOptimization,
    whose timers run on ROS time, keeps rclpy's subscription."""
    import rclpy
    from builtin_interfaces.msg import Time
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock

    from lego_loam_py.ros.map_optimization_node import MapOptimizationNode
    from lego_loam_py.ros.transform_fusion_node import TransformFusionNode

    sim_time = [Parameter('use_sim_time', value=True)]
    fusion = TransformFusionNode(context=rclpy_context, parameter_overrides=sim_time)
    mapping = MapOptimizationNode(context=rclpy_context, parameter_overrides=sim_time)
    player = rclpy.create_node('clock_player', context=rclpy_context)
    try:
        assert fusion._time_source._clock_sub is None and fusion._polled_clock is not None
        assert all(s.topic_name != '/clock' for s in fusion.subscriptions)
        assert mapping._polled_clock is None and mapping._time_source._clock_sub is not None
        publisher = player.create_publisher(Clock, '/clock', 10)
        ticks = iter(range(10**6))

        def newest_tick_applied() -> bool:
            tick = next(ticks)
            publisher.publish(Clock(clock=Time(sec=1000 + tick, nanosec=500)))
            now = fusion.get_clock().now().nanoseconds
            return now >= 1000 * 10**9 + 500 and (now - 500) % 10**9 == 0

        assert spin_until(rclpy_context, player, newest_tick_applied, timeout=20), fusion.get_clock().now()
        latest = fusion.get_clock().now().nanoseconds
        publisher.publish(Clock(clock=Time(sec=5_000_000, nanosec=7)))
        assert spin_until(rclpy_context, player, lambda: fusion.get_clock().now().nanoseconds != latest, timeout=20)
        assert fusion.get_clock().now().nanoseconds == 5_000_000 * 10**9 + 7
    finally:
        for node in (fusion, mapping, player):
            node.destroy_node()
