"""The imageProjection node as its own process over DDS: golden bag in, the original's outputs out."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.testing.nodes import Diagnostics, bag_clouds, publish_in_lockstep, release, spin_until

BIN = Path(sys.executable).parent
GOLDEN_BAG = 'vlp16_static_indoor_20hz'


def subscribe(node, topics):
    """Subscriptions that store every message per topic."""
    from sensor_msgs.msg import PointCloud2

    from cloud_msgs.msg import CloudInfo
    from lego_loam_py.ros import qos

    got = {t: [] for t in topics}
    for topic in topics:
        msg_type = CloudInfo if topic == '/segmented_cloud_info' else PointCloud2
        node.create_subscription(msg_type, topic, got[topic].append, qos.reliable(100))
    return got


def wait_for_publishers(context, node, topics, proc, timeout=20.0):
    ok = spin_until(
        context, node, lambda: all(node.count_publishers(t) > 0 for t in topics) or proc.poll() is not None, timeout
    )
    assert proc.poll() is None, f'the node exited: {proc.communicate()[1]}'
    assert ok, f'publishers of {topics} not discovered'


def test_golden_bag_over_dds_gives_the_originals_outputs(shared_data, rclpy_context, processes):
    import rclpy
    from sensor_msgs.msg import PointCloud2

    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import cloud_msg_to_xyzi, stamp_to_ns

    golden = np.load(shared_data / 'golden' / f'{GOLDEN_BAG}.npz')
    n_scans = len(golden['stamps'])
    node = rclpy.create_node('ip_listener', context=rclpy_context)
    topics = ['/segmented_cloud', '/segmented_cloud_info', '/outlier_cloud', '/ground_cloud']
    got = subscribe(node, topics)
    clouds = node.create_publisher(PointCloud2, '/velodyne_points', qos.reliable(10))
    from lego_loam_py.core.params import default_params_file

    ip = processes.start(
        [BIN / 'imageProjection', '--ros-args', '--params-file', default_params_file().parent / 'original.yaml']
    )
    wait_for_publishers(rclpy_context, node, topics, ip)
    assert spin_until(rclpy_context, node, lambda: clouds.get_subscription_count() > 0, 20)
    # One scan at a time, the next once every output of the previous one is in: the input is a depth-1
    # queue, as the original's, and parity needs every scan however slow a loaded machine is.
    scans = bag_clouds(shared_data / 'golden' / f'{GOLDEN_BAG}_ros2')
    assert len(scans) == n_scans
    left = publish_in_lockstep(
        rclpy_context,
        node,
        clouds.publish,
        scans,
        lambda stamp: all(got[t] and stamp_to_ns(got[t][-1].header.stamp) == stamp for t in topics),
    )
    assert not left, {t: len(v) for t, v in got.items()}
    assert ip.poll() is None, 'imageProjection exited'
    stamps = golden['stamps'].tolist()
    for topic in topics:
        assert [stamp_to_ns(m.header.stamp) for m in got[topic]] == stamps, topic
    assert {m.header.frame_id for t in ('/segmented_cloud', '/outlier_cloud', '/ground_cloud') for m in got[t]} == {
        'base_link'
    }
    assert {m.header.frame_id for m in got['/segmented_cloud_info']} == {'velodyne'}
    for k in range(n_scans):
        segmented = cloud_msg_to_xyzi(got['/segmented_cloud'][k])
        info = got['/segmented_cloud_info'][k]
        assert np.array_equal(segmented, golden[f's{k}_segmented_cloud'])
        assert np.array_equal(cloud_msg_to_xyzi(got['/outlier_cloud'][k]), golden[f's{k}_outlier_cloud'])
        assert np.array_equal(cloud_msg_to_xyzi(got['/ground_cloud'][k]), golden[f's{k}_ground_cloud'])
        # CloudInfo arrays are as long as the segmented cloud (the original's 28800-long tails are stale).
        assert len(info.segmented_cloud_range) == len(info.segmented_cloud_col_ind) == len(segmented)
        assert len(info.segmented_cloud_ground_flag) == len(segmented)
        assert np.array_equal(
            np.frombuffer(info.segmented_cloud_col_ind, np.uint32),
            golden[f's{k}_segmented_cloud_col_ind'][: len(segmented)],
        )
        assert np.array_equal(np.frombuffer(info.start_ring_index, np.int32), golden[f's{k}_start_ring_index'])
        assert np.float32(info.orientation_diff) == golden[f's{k}_orientation_diff']
    # The PointCloud2 layout is PCL's PointXYZI, as the original publishes; the input's per-point time rides
    # in its padding for featureAssociation's use_point_time.
    fields = [(f.name, f.offset) for f in got['/segmented_cloud'][0].fields]
    assert fields == [('x', 0), ('y', 4), ('z', 8), ('intensity', 16), ('time', 20)]
    assert [(f.name, f.offset) for f in got['/outlier_cloud'][0].fields] == [
        ('x', 0),
        ('y', 4),
        ('z', 8),
        ('intensity', 16),
    ]
    from lego_loam_py.ros.conversions import cloud_msg_to_array

    times = cloud_msg_to_array(got['/segmented_cloud'][0])['time']
    assert 0 <= times.min() and times.max() <= 0.051  # the 20 Hz recording's sweeps last 50 ms
    release(node)


def make_bad_clouds():
    """(description, PointCloud2) pairs that must be dropped with a warning."""
    from sensor_msgs.msg import PointCloud2, PointField

    from lego_loam_py.core.pointcloud import velodyne_points
    from lego_loam_py.ros.conversions import array_to_cloud_msg, make_header

    header = make_header(1_000_000_000, 'velodyne')
    good = array_to_cloud_msg(velodyne_points(np.ones((10, 3))), header)
    truncated = array_to_cloud_msg(velodyne_points(np.ones((10, 3))), header)
    truncated.data = truncated.data[:-7]
    no_xyz = PointCloud2(
        header=header,
        height=1,
        width=2,
        point_step=4,
        row_step=8,
        data=bytes(8),
        fields=[PointField(name='intensity', offset=0, datatype=7, count=1)],
    )
    overlap = PointCloud2(
        header=header,
        height=1,
        width=1,
        point_step=8,
        row_step=8,
        data=bytes(8),
        fields=[
            PointField(name='x', offset=0, datatype=7, count=1),
            PointField(name='y', offset=2, datatype=7, count=1),
            PointField(name='z', offset=4, datatype=7, count=1),
        ],
    )
    empty = array_to_cloud_msg(velodyne_points(np.zeros((0, 3))), header)
    all_nan = array_to_cloud_msg(velodyne_points(np.full((100, 3), np.nan)), header)
    # Ouster's organized cloud without a single return: every point at the origin.
    all_at_origin = array_to_cloud_msg(velodyne_points(np.zeros((100, 3))).reshape(4, 25), header)
    # Times spanning 5 s (or 5 ms): about a 0.1 s sweep in no unit.
    bad_time = array_to_cloud_msg(velodyne_points(np.ones((10, 3)), time=np.linspace(0.0, 5.0, 10)), header)
    return [
        ('truncated data', truncated),
        ('no x/y/z', no_xyz),
        ('overlapping fields', overlap),
        ('empty cloud', empty),
        ('all NaN', all_nan),
        ('all at the origin', all_at_origin),
        ('time in an unknown unit', bad_time),
    ], good


def test_bad_clouds_are_dropped_and_the_node_keeps_serving(rclpy_context, processes):
    import rclpy
    from sensor_msgs.msg import PointCloud2

    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import array_to_cloud_msg, make_header
    from tests.support.scenes import floor_ranges, scene_points, wall_ranges

    node = rclpy.create_node('ip_bad_input', context=rclpy_context)
    got = subscribe(node, ['/segmented_cloud'])
    diagnostics = Diagnostics(node)
    publisher = node.create_publisher(PointCloud2, '/velodyne_points', qos.reliable(10))
    ip = processes.start([BIN / 'imageProjection'])
    wait_for_publishers(rclpy_context, node, ['/segmented_cloud'], ip)
    assert spin_until(rclpy_context, node, lambda: publisher.get_subscription_count() > 0, 20)
    bad, _ = make_bad_clouds()
    # Each bad cloud once the node has taken the one before (its counters, on /diagnostics): the input is a
    # depth-1 queue, and every one of them must be seen. The first is sent again until the node has matched us.
    items = [(k + 1, msg) for k, (_, msg) in enumerate(bad)]
    left = publish_in_lockstep(
        rclpy_context,
        node,
        publisher.publish,
        items,
        lambda k: diagnostics.counter('imageProjection', 'clouds_dropped') >= k,
    )
    assert not left, diagnostics.latest
    assert diagnostics.counter('imageProjection', 'clouds_out') == 0
    scan = scene_points(np.fmin(floor_ranges(1.5), wall_ranges(6.0, half_width=2.5, z_min=-1.5)))
    publisher.publish(array_to_cloud_msg(scan, make_header(2_000_000_000, 'velodyne')))
    assert spin_until(
        rclpy_context,
        node,
        lambda: len(got['/segmented_cloud']) >= 1 and diagnostics.counter('imageProjection', 'clouds_out') >= 1,
        30,
    )
    assert len(got['/segmented_cloud']) == 1 and got['/segmented_cloud'][0].header.stamp.sec == 2
    assert diagnostics.counter('imageProjection', 'clouds_dropped') >= len(bad)  # (a resent first one may count twice)
    assert ip.poll() is None
    _, err = processes.stop(ip)
    assert ip.returncode == 0
    for fragment in ('data has', 'no x/y/z field', "'x' and 'y' overlap", 'no valid point', "time field 'time'"):
        assert fragment in err, fragment
    assert 'Traceback' not in err
    release(node)


def test_invalid_parameters_stop_the_node_with_a_clear_error(tmp_path, ros_domain):
    import subprocess

    params = tmp_path / 'bad.yaml'
    params.write_text('/**:\n  ros__parameters:\n    sensor:\n      preset: VLP-17\n')
    result = subprocess.run(
        [str(BIN / 'imageProjection'), '--ros-args', '--params-file', str(params)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert "parameter 'sensor.preset' must be one of" in result.stderr
    result = subprocess.run(
        [str(BIN / 'imageProjection'), '--ros-args', '-p', 'sensor.n_scann:=3'],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "did you mean 'sensor.n_scan'" in result.stderr


@pytest.mark.parametrize('preset', ['HDL-32E'])
def test_params_file_selects_the_preset(tmp_path, rclpy_context, processes, preset):
    import rclpy
    from sensor_msgs.msg import PointCloud2

    from lego_loam_py.core.pointcloud import velodyne_points
    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import array_to_cloud_msg, cloud_msg_to_xyzi, make_header

    params = tmp_path / 'p.yaml'
    params.write_text(
        f'/**:\n  ros__parameters:\n    sensor:\n      preset: {preset}\n      point_cloud_topic: /points_raw\n'
    )
    node = rclpy.create_node('ip_params', context=rclpy_context)
    got = subscribe(node, ['/segmented_cloud'])
    publisher = node.create_publisher(PointCloud2, '/points_raw', qos.reliable(10))
    ip = processes.start([BIN / 'imageProjection', '--ros-args', '--params-file', params])
    wait_for_publishers(rclpy_context, node, ['/segmented_cloud'], ip)
    assert spin_until(rclpy_context, node, lambda: publisher.get_subscription_count() > 0, 20)
    # A wall seen by rings 20..30: rows that exist only with 32 beams.
    rows = np.repeat(np.arange(20, 31), 40)
    cols = np.tile(np.arange(880, 920), 11)
    az = np.radians(90.0 - (cols - 900) * 0.2)
    xyz = np.stack([8 * np.sin(az), 8 * np.cos(az), np.linspace(-1, 2, len(rows))], axis=1)
    cloud = array_to_cloud_msg(velodyne_points(xyz, ring=rows), make_header(3_000_000_000, 'velodyne'))
    assert not publish_in_lockstep(
        rclpy_context, node, publisher.publish, [(0, cloud)], lambda _: got['/segmented_cloud']
    )
    rows_out = np.floor(cloud_msg_to_xyzi(got['/segmented_cloud'][0])[:, 3] + 1e-4)
    assert rows_out.max() >= 20
    release(node)
