"""Bags: the player replays ROS 2 and ROS 1 bags over DDS with /clock; the recorder writes readable bags."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.bag.io import BagReader, BagWriter, cloud_msg_to_array, make_cloud_msg
from lego_loam_py.core.pointcloud import velodyne_points
from lego_loam_py.testing.nodes import release, spin_until, wait_for_line
from tests.support.samples import cloud_info_arrays

REPO = Path(__file__).resolve().parents[1]
CLI = str(Path(sys.executable).parent / 'lego_loam_py')
T0 = 1_650_000_000_000_000_000  # bag start [ns]
N_CLOUDS, N_IMU = 20, 100


def cloud_points(k: int) -> np.ndarray:
    rng = np.random.default_rng(k)
    n = 5000 + 10 * k
    return velodyne_points(
        rng.normal(size=(n, 3)), rng.uniform(0, 100, n), rng.integers(0, 16, n), np.linspace(0, 0.1, n)
    )


def write_test_bag(path: Path, ros1: bool, storage: str = 'mcap') -> None:
    """20 clouds at 10 Hz and 100 IMU messages at 50 Hz; header stamps differ from recording times."""
    with BagWriter(path, storage=storage, ros1=ros1) as bag:
        T = bag.types
        events = [(T0 + k * 100_000_000, 'cloud', k) for k in range(N_CLOUDS)]
        events += [(T0 + k * 20_000_000 + 1_000, 'imu', k) for k in range(N_IMU)]
        for t, kind, k in sorted(events):
            if kind == 'cloud':
                header = bag.header(T0 - 5_000_000 + k * 100_000_000, 'velodyne', seq=k)
                bag.write_msg('/velodyne_points', t + 3_000_000, make_cloud_msg(T, header, cloud_points(k)))
            else:
                header = bag.header(t - 1_000, 'imu_link', seq=k)
                imu = T['sensor_msgs/msg/Imu'](
                    header=header,
                    orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.zeros(9),
                    angular_velocity=T['geometry_msgs/msg/Vector3'](x=0.01 * k, y=0.0, z=0.0),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=9.81),
                    linear_acceleration_covariance=np.zeros(9),
                )
                bag.write_msg('/imu/data', t, imu)


@pytest.mark.parametrize('ros1', [False, True], ids=['ros2_mcap', 'ros1_bag'])
def test_bag_io_round_trip(tmp_path, ros1):
    path = tmp_path / ('in.bag' if ros1 else 'in')
    write_test_bag(path, ros1)
    with BagReader(path) as reader:
        assert reader.is_ros1 == ros1
        assert reader.topics() == {
            '/velodyne_points': 'sensor_msgs/msg/PointCloud2',
            '/imu/data': 'sensor_msgs/msg/Imu',
        }
        clouds = [m for m in reader.messages(topics=['/velodyne_points'])]
        assert len(clouds) == N_CLOUDS
        for k, message in enumerate(clouds):
            msg = reader.deserialize(message)
            assert msg.header.frame_id == 'velodyne'
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == T0 - 5_000_000 + k * 100_000_000
            assert np.array_equal(cloud_msg_to_array(msg), cloud_points(k))


def test_sqlite3_storage(tmp_path):
    write_test_bag(tmp_path / 'db', ros1=False, storage='sqlite3')
    assert list((tmp_path / 'db').glob('*.db3'))
    with BagReader(tmp_path / 'db') as reader:
        assert reader.message_count == N_CLOUDS + N_IMU


@pytest.mark.parametrize('ros1', [False, True], ids=['ros2_mcap', 'ros1_bag'])
def test_player_replays_every_message_in_order_with_clock(tmp_path, ros1, rclpy_context, processes):
    import rclpy
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Imu, PointCloud2

    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import cloud_msg_to_array as ros_cloud_to_array
    from lego_loam_py.ros.conversions import stamp_to_ns

    path = tmp_path / ('in.bag' if ros1 else 'in')
    write_test_bag(path, ros1)
    node = rclpy.create_node('player_listener', context=rclpy_context)
    clouds, imus, clock = [], [], []
    node.create_subscription(PointCloud2, '/velodyne_points', clouds.append, qos.reliable(100))
    node.create_subscription(Imu, '/imu/data', imus.append, qos.reliable(500))
    node.create_subscription(Clock, '/clock', lambda m: clock.append(stamp_to_ns(m.clock)), qos.reliable(500))

    player = processes.start([CLI, 'play', str(path), '--rate', '2', '--wait-for-subscribers', '20', '--no-progress'])
    done = spin_until(
        rclpy_context,
        node,
        lambda: len(clouds) == N_CLOUDS and len(imus) == N_IMU and player.poll() is not None,
        timeout=60,
    )
    out, err = player.communicate(timeout=10)
    assert done, f'clouds {len(clouds)}/{N_CLOUDS}, imu {len(imus)}/{N_IMU}; player: {err}'
    assert player.returncode == 0, err
    assert f'done: {N_CLOUDS + N_IMU} messages on 2 topics' in err
    # Every message, in order, with the header stamps of the bag (not the recording times).
    assert [stamp_to_ns(m.header.stamp) for m in clouds] == [T0 - 5_000_000 + k * 100_000_000 for k in range(N_CLOUDS)]
    assert [stamp_to_ns(m.header.stamp) for m in imus] == [T0 + k * 20_000_000 for k in range(N_IMU)]
    assert np.array_equal(ros_cloud_to_array(clouds[7]), cloud_points(7))
    assert clouds[0].header.frame_id == 'velodyne' and imus[3].angular_velocity.x == pytest.approx(0.03)
    # /clock follows the bag time: never backwards, from the first to the last recording time.
    # At 40 Hz (the default, as rosbag2) for about 1 s of wall time: far fewer ticks than messages.
    assert 20 <= len(clock) < (N_CLOUDS + N_IMU) / 2
    assert all(b >= a for a, b in zip(clock, clock[1:]))
    last_recording = max(T0 + (N_CLOUDS - 1) * 100_000_000 + 3_000_000, T0 + (N_IMU - 1) * 20_000_000 + 1_000)
    assert clock[0] == T0 + 1_000 and clock[-1] == last_recording
    release(node)


def test_player_topic_selection_and_start_offset(tmp_path, rclpy_context, processes):
    import rclpy
    from sensor_msgs.msg import Imu, PointCloud2

    from lego_loam_py.ros import qos

    write_test_bag(tmp_path / 'in', ros1=False)
    node = rclpy.create_node('selection_listener', context=rclpy_context)
    clouds, imus = [], []
    node.create_subscription(PointCloud2, '/velodyne_points', clouds.append, qos.reliable(100))
    node.create_subscription(Imu, '/imu/data', imus.append, qos.reliable(500))
    player = processes.start(
        [
            CLI,
            'play',
            str(tmp_path / 'in'),
            '--topics',
            '/velodyne_points',
            '--rate',
            '4',
            '--start-offset',
            '1.0',
            '--wait-for-subscribers',
            '20',
            '--no-progress',
        ]
    )
    # The player waits for every message to be acknowledged before it exits: then they are all here or queued.
    assert spin_until(rclpy_context, node, lambda: player.poll() is not None and len(clouds) >= N_CLOUDS - 10, 60)
    assert player.returncode == 0
    assert len(clouds) == N_CLOUDS - 10 and not imus  # recording times 1.003 s ... are kept
    release(node)


def test_player_reports_a_missing_bag(tmp_path):
    import subprocess

    result = subprocess.run([CLI, 'play', str(tmp_path / 'nope')], capture_output=True, text=True, timeout=60)
    assert result.returncode == 1 and 'bag not found' in result.stderr


def test_recorder_writes_a_readable_bag_and_finishes_on_sigint(tmp_path, rclpy_context, processes):
    """CloudInfo (custom type) and latched /tf_static from other processes, recorded into mcap."""
    out = tmp_path / 'recorded'
    recorder = processes.start([CLI, 'record', '/segmented_cloud_info', '/tf_static', '-o', str(out)])
    cloud_info = processes.python('-m', 'tests.support.publisher', 'cloud_info', cwd=REPO)
    tf_static = processes.python('-m', 'tests.support.publisher', 'tf_static', cwd=REPO)
    wait_for_line(cloud_info, 'ready')
    wait_for_line(tf_static, 'ready')
    # Record until this process has seen 12 CloudInfo messages after the recorder subscribed to both topics (it
    # finds them by polling the graph): events, so that a loaded machine only makes this slower.
    import rclpy

    from cloud_msgs.msg import CloudInfo
    from lego_loam_py.ros import qos

    node = rclpy.create_node('recording_watcher', context=rclpy_context)
    assert spin_until(
        rclpy_context,
        node,
        lambda: node.count_subscribers('/segmented_cloud_info') >= 1 and node.count_subscribers('/tf_static') >= 1,
        30,
    ), 'the recorder never subscribed'
    seen = []
    node.create_subscription(CloudInfo, '/segmented_cloud_info', seen.append, qos.reliable(1))
    assert spin_until(rclpy_context, node, lambda: len(seen) >= 12, 60), f'{len(seen)} CloudInfo messages seen'
    release(node)
    _, err = processes.stop(recorder, signal.SIGINT, timeout=20)
    assert recorder.returncode == 0, err
    assert 'recorded' in err
    assert (out / 'metadata.yaml').is_file()

    # Read back with plain rosbags and a fresh type store: the custom type comes from the bag itself.
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([out], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics == {'/segmented_cloud_info': 'cloud_msgs/msg/CloudInfo', '/tf_static': 'tf2_msgs/msg/TFMessage'}
        infos = [
            reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages() if c.topic == '/segmented_cloud_info'
        ]
        statics = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages() if c.topic == '/tf_static']
    # The publisher keeps one message (reliable, depth 1, as the original's internal topics): a recorder slowed
    # down by a busy machine may miss some of the 12, never most of them.
    assert len(infos) >= 4, f'only {len(infos)} CloudInfo messages recorded while 12 were published'
    expected = cloud_info_arrays()
    msg = infos[-1]
    assert np.array_equal(msg.segmented_cloud_range, expected['segmented_cloud_range'])
    assert np.array_equal(msg.segmented_cloud_col_ind, expected['segmented_cloud_col_ind'])
    assert np.array_equal(msg.segmented_cloud_ground_flag, expected['segmented_cloud_ground_flag'])
    assert np.array_equal(msg.start_ring_index, expected['start_ring_index'])
    assert len(statics) == 1 and {t.child_frame_id for t in statics[0].transforms} == {'camera_init', 'base_link'}
