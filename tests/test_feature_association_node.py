"""imageProjection + featureAssociation as separate processes over DDS on a played bag."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from lego_loam_py.testing.nodes import Diagnostics, bag_clouds, links_matched, release, spin_until

BIN = Path(sys.executable).parent
GOLDEN_BAG = 'vlp16_static_indoor_20hz'
LAST_TOPICS = ['/laser_cloud_corner_last', '/laser_cloud_surf_last', '/outlier_cloud_last']


def start_pipeline(processes, params_file=None):
    extra = ['--ros-args', '--params-file', str(params_file)] if params_file else []
    return [processes.start([BIN / exe, *extra]) for exe in ('imageProjection', 'featureAssociation')]


def wait_ready(context, node, topics, procs, timeout=30.0):
    ok = spin_until(
        context,
        node,
        lambda: all(node.count_publishers(t) > 0 for t in topics) or any(p.poll() is not None for p in procs),
        timeout,
    )
    for p in procs:
        assert p.poll() is None, f'a node exited: {p.communicate()[1]}'
    assert ok


def wait_linked(context, node, links, timeout=60.0):
    """Every link matched at both ends (see lego_loam_py.testing.nodes.links_matched; a message sent before is lost, as
    with any DDS publisher)."""
    diagnostics = Diagnostics(node)
    linked = spin_until(context, node, lambda: links_matched(diagnostics, links), timeout)
    assert linked, {
        name: {k: v for k, v in values.items() if k.startswith('matched')}
        for name, values in diagnostics.latest.items()
    }


def stamp_of(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_odometry_for_every_scan_over_dds_equals_the_original(shared_data, tmp_path, rclpy_context, processes):
    import rclpy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2
    from tf2_msgs.msg import TFMessage

    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import cloud_msg_to_xyzi, stamp_to_ns
    from lego_loam_py.testing.nodes import publish_in_lockstep

    golden = np.load(shared_data / 'golden' / f'{GOLDEN_BAG}.npz')
    stamps = golden['stamps'].tolist()
    from lego_loam_py.core.params import default_params_file

    params = default_params_file().parent / 'original.yaml'
    node = rclpy.create_node('fa_listener', context=rclpy_context)
    odometry, tf, last, finished = [], [], {t: [] for t in LAST_TOPICS}, set()
    listeners = {
        '/laser_odom_to_init': node.create_subscription(
            Odometry, '/laser_odom_to_init', odometry.append, qos.reliable(100)
        ),
        '/tf': node.create_subscription(TFMessage, '/tf', tf.append, qos.reliable(100)),
    }
    for topic in LAST_TOPICS:
        listeners[topic] = node.create_subscription(PointCloud2, topic, last[topic].append, qos.reliable(100))
    # featureAssociation publishes the less-flat features of every scan it processed (while subscribed),
    # after the scan's odometry: the event that says it is done with a scan.
    listeners['/laser_cloud_less_flat'] = node.create_subscription(
        PointCloud2, '/laser_cloud_less_flat', lambda m: finished.add(stamp_to_ns(m.header.stamp)), qos.reliable(100)
    )
    clouds = node.create_publisher(PointCloud2, '/velodyne_points', qos.reliable(10))
    procs = start_pipeline(processes, params)
    wait_ready(rclpy_context, node, ['/laser_odom_to_init', '/segmented_cloud'], procs)
    wait_linked(
        rclpy_context,
        node,
        [
            (clouds, '/velodyne_points', ['imageProjection']),
            *[
                ('imageProjection', t, ['featureAssociation'])
                for t in ('/segmented_cloud', '/segmented_cloud_info', '/outlier_cloud')
            ],
            *[('featureAssociation', t, [listener]) for t, listener in listeners.items()],
        ],
    )
    # One scan at a time, the next once featureAssociation is done with the previous one: parity needs every
    # scan, and the nodes' depth-1 inputs (the original's 'latest wins') would let a loaded machine skip one.
    scans = bag_clouds(shared_data / 'golden' / f'{GOLDEN_BAG}_ros2')
    assert [s for s, _ in scans] == stamps
    left = publish_in_lockstep(rclpy_context, node, clouds.publish, scans, lambda stamp: stamp in finished)
    assert not left, f'no output for scans {[stamps.index(s) for s in left]}; {len(odometry)} odometry messages'
    # The last clouds of the last scan are published right after its features.
    expected_last = {topic: sum(golden[f'published_{topic.strip("/")}']) for topic in LAST_TOPICS}
    assert spin_until(
        rclpy_context,
        node,
        lambda: all(len(last[t]) >= n for t, n in expected_last.items()) and len(tf) >= len(odometry),
        10,
    ), {t: len(v) for t, v in last.items()}
    # One pose per scan but the first (initialisation), with the scan's stamp and the original's frames.
    assert [stamp_to_ns(m.header.stamp) for m in odometry] == stamps[1:]
    assert {(m.header.frame_id, m.child_frame_id) for m in odometry} == {('camera_init', 'laser_odom')}
    ours = np.array(
        [
            [
                m.pose.pose.position.x,
                m.pose.pose.position.y,
                m.pose.pose.position.z,
                m.pose.pose.orientation.x,
                m.pose.pose.orientation.y,
                m.pose.pose.orientation.z,
                m.pose.pose.orientation.w,
            ]
            for m in odometry
        ]
    )
    theirs = golden['laser_odom_to_init']
    assert np.abs(ours[:, :3] - theirs[:, :3]).max() < 1e-5
    assert np.abs(np.abs(ours[:, 3:]) - np.abs(theirs[:, 3:])).max() < 1e-6
    transforms = [t for m in tf for t in m.transforms if t.child_frame_id == 'laser_odom']
    assert len(transforms) == len(odometry) and transforms[0].header.frame_id == 'camera_init'
    # 'last' clouds every second scan, in frame camera, as the original publishes them.
    for topic in LAST_TOPICS:
        flags = golden[f'published_{topic.strip("/")}']
        assert [stamp_to_ns(m.header.stamp) for m in last[topic]] == [s for s, f in zip(stamps, flags) if f], topic
        assert {m.header.frame_id for m in last[topic]} == {'camera'}
    k = stamps.index(stamp_to_ns(last['/laser_cloud_corner_last'][3].header.stamp))
    assert (
        np.abs(cloud_msg_to_xyzi(last['/laser_cloud_corner_last'][3]) - golden[f's{k}_laser_cloud_corner_last']).max()
        < 1e-5
    )
    for p in procs:
        assert p.poll() is None
        _, err = processes.stop(p)
        assert p.returncode == 0 and 'Traceback' not in err
    release(node)


def test_bad_cloud_info_is_dropped_and_a_time_jump_resets(rclpy_context, processes, tmp_path):
    """Inconsistent CloudInfo is dropped with a warning; a scan from the past (bag restarted) resets."""
    import rclpy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    from cloud_msgs.msg import CloudInfo
    from lego_loam_py.core.params import Params
    from lego_loam_py.core.projection.image_projection import ImageProjection, prepare_input
    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import cloud_info_to_msg, make_header, xyzi_to_cloud_msg
    from tests.support.sweeps import room_world, sweep

    node = rclpy.create_node('fa_feeder', context=rclpy_context)
    pubs = {
        '/segmented_cloud': node.create_publisher(PointCloud2, '/segmented_cloud', qos.reliable(10)),
        '/segmented_cloud_info': node.create_publisher(CloudInfo, '/segmented_cloud_info', qos.reliable(10)),
        '/outlier_cloud': node.create_publisher(PointCloud2, '/outlier_cloud', qos.reliable(10)),
    }
    odometry, finished = [], set()
    node.create_subscription(Odometry, '/laser_odom_to_init', odometry.append, qos.reliable(100))
    node.create_subscription(
        PointCloud2, '/laser_cloud_less_flat', lambda m: finished.add(stamp_of(m)), qos.reliable(100)
    )
    diagnostics = Diagnostics(node)
    log_path = tmp_path / 'featureAssociation.log'
    with open(log_path, 'w') as log:
        fa = processes.start([BIN / 'featureAssociation'], stdout=log, stderr=log)
    wait_ready(rclpy_context, node, ['/laser_odom_to_init'], [fa])
    assert spin_until(
        rclpy_context,
        node,
        lambda: (
            all(p.get_subscription_count() for p in pubs.values())
            and node.count_subscribers('/laser_cloud_less_flat') > 0
        ),
        20,
    )
    params = Params()
    ip = ImageProjection(params)
    scene = room_world(seed=1)
    results = [ip.process(prepare_input(sweep(scene, np.eye(4)), params)) for _ in range(2)]

    def logged(text: str):
        return lambda: text in log_path.read_text()

    def send(result, stamp_ns, handled, info=None):
        """Publish one scan, then wait until featureAssociation has handled it (its inputs are depth-1 queues:
        the next scan must not overwrite this one)."""
        header = make_header(stamp_ns, 'base_link')
        pubs['/segmented_cloud'].publish(xyzi_to_cloud_msg(result.segmented_cloud, header))
        pubs['/segmented_cloud_info'].publish(info or cloud_info_to_msg(result.cloud_info, make_header(stamp_ns, 'v')))
        pubs['/outlier_cloud'].publish(xyzi_to_cloud_msg(result.outlier_cloud, header))
        assert spin_until(rclpy_context, node, handled, 60), (stamp_ns, log_path.read_text())

    t0 = 50_000_000_000
    send(results[0], t0, lambda: t0 in finished)  # initialisation
    bad = cloud_info_to_msg(results[1].cloud_info, make_header(t0 + 100_000_000, 'v'))
    bad.segmented_cloud_range = bad.segmented_cloud_range[:10]  # shorter than the cloud
    send(results[1], t0 + 100_000_000, logged('segmented_cloud_range length = 10, shorter than'), bad)
    send(results[1], t0 + 200_000_000, lambda: t0 + 200_000_000 in finished)  # good: odometry
    send(results[1], t0 + 150_000_000, logged('out of order'))  # out of order: dropped
    # 10 s back: held until three scans in a row confirm the restart (one or two wrong stamps cost only themselves)
    send(results[0], t0 - 10_000_000_000, lambda: diagnostics.counter('featureAssociation', 'held') >= 1)
    send(results[1], t0 - 9_900_000_000, lambda: diagnostics.counter('featureAssociation', 'held') >= 2)
    send(results[1], t0 - 9_800_000_000, lambda: t0 - 9_800_000_000 in finished)  # ... confirmed: reset
    assert spin_until(rclpy_context, node, lambda: len(odometry) >= 3, 10)  # (published before the features)
    assert [stamp_of(m) for m in odometry] == [
        t0 + 200_000_000,
        t0 - 9_900_000_000,  # again, from the origin
        t0 - 9_800_000_000,
    ]
    assert fa.poll() is None
    processes.stop(fa)
    err = log_path.read_text()
    assert (
        'segmented_cloud_range length = 10, shorter than' in err and 'out of order' in err and 'odometry reset' in err
    )
    assert 'Traceback' not in err
    release(node)


def test_each_scan_reports_how_well_the_odometry_was_held(context, tmp_path):
    """The per-scan condition of both odometry stages (smallest eigenvalue of the normal matrix) is in the
    node's statistics and on /diagnostics, beside the counters of degenerate and skipped stages."""
    from tests.support.inprocess import pipeline_outputs

    outputs = pipeline_outputs(context, tmp_path)
    measures = outputs['fa_statistics']['measures']
    scans = outputs['fa_statistics']['counters']['scans_processed']
    for stage in ('surf', 'corner'):
        # Every scan after the first registers both stages on the campus (enough floor and edges).
        assert measures[f'{stage}_condition']['count'] == scans - 1
        assert measures[f'{stage}_condition']['median'] > 0
        assert f'{stage}_stage_skipped' not in outputs['fa_statistics']['counters']
    keys = {value.key: value.value for value in outputs['fa_diagnostics'].values}
    assert float(keys['surf_condition_last']) > 0 and float(keys['corner_condition_median']) > 0
    # The share of sharp points matched: most of them on the campus, so the odometry was never lost.
    assert measures['corner_match_ratio']['count'] == scans - 1 and measures['corner_match_ratio']['median'] > 0.5
    assert 0.5 < float(keys['corner_match_ratio_median']) <= 1.0
    assert 'odometry_lost' not in outputs['fa_statistics']['counters']
