"""The four nodes over DDS on a golden bag, as separate processes and in one process (legoLoam): mapping and fusion
equal the original."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.testing.nodes import Diagnostics, bag_clouds, links_matched, publish_in_lockstep, release, spin_until

BIN = Path(sys.executable).parent
GOLDEN_BAG = 'vlp16_static_indoor_20hz'
NODES = ('imageProjection', 'featureAssociation', 'mapOptimization', 'transformFusion')
INTERNAL_TOPICS = (
    '/segmented_cloud',
    '/segmented_cloud_info',
    '/outlier_cloud',
    '/laser_cloud_corner_last',
    '/laser_cloud_surf_last',
    '/outlier_cloud_last',
    '/laser_odom_to_init',
    '/aft_mapped_to_init',
)


def pipeline_links(clouds, features_in, mapped_in, integrated_in, composed: bool = False):
    """The links the parity test needs (see lego_loam_py.testing.nodes.links_matched): the test's clouds in, the four
    nodes between them (over DDS unless ``composed``), and the test's listeners on the outputs it waits for."""
    ip, fa, mo, tf = NODES
    if composed:
        return [
            (clouds, '/velodyne_points', [ip]),
            (mo, '/aft_mapped_to_init', [mapped_in]),
            (fa, '/laser_cloud_less_flat', [features_in]),
            (tf, '/integrated_to_init', [integrated_in]),
        ]
    return [
        (clouds, '/velodyne_points', [ip]),
        *[(ip, topic, [fa]) for topic in INTERNAL_TOPICS[:3]],
        *[(fa, topic, [mo]) for topic in INTERNAL_TOPICS[3:6]],
        (fa, '/laser_odom_to_init', [mo, tf]),
        (mo, '/aft_mapped_to_init', [tf, mapped_in]),
        (fa, '/laser_cloud_less_flat', [features_in]),
        (tf, '/integrated_to_init', [integrated_in]),
    ]


def odometry_rows(messages):
    return np.array(
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
            for m in messages
        ]
    )


def _mapping_step_for(stamp: int, mapped_stamps: list[int]) -> bool:
    """Whether the original ran a mapping step on the scan stamped ``stamp`` (its stamps are rounded to us)."""
    return any(abs(stamp - s) < 1000 for s in mapped_stamps)


def _stop_and_log(processes, procs) -> str:
    """Stop the nodes (SIGINT: they print their statistics) and return the end of what each wrote."""
    logs = []
    for name, proc in procs.items():
        out, err = processes.stop(proc)
        logs.append(f'--- {name}\n{(out or "")[-1500:]}{(err or "")[-1500:]}')
    return '\n'.join(logs)


@pytest.mark.parametrize('composed', [False, True], ids=['four processes', 'one process'])
def test_mapping_and_fusion_over_dds_equal_the_original(shared_data, tmp_path, rclpy_context, processes, composed):
    import rclpy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger
    from tf2_msgs.msg import TFMessage

    from lego_loam_py.formats import read_pcd, read_tum
    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import make_header, stamp_to_ns, xyzi_to_cloud_msg

    golden = np.load(shared_data / 'golden' / f'{GOLDEN_BAG}.npz')
    stamps = golden['stamps'].tolist()
    maps = tmp_path / 'maps'
    params = tmp_path / 'params.yaml'
    params.write_text(f'/**:\n  ros__parameters:\n    map_optimization:\n      file_directory: {maps}\n')
    from lego_loam_py.core.params import default_params_file

    original = default_params_file().parent / 'original.yaml'
    node = rclpy.create_node('pipeline_listener', context=rclpy_context)
    mapped, integrated, static, features = [], [], [], set()
    mapped_in = node.create_subscription(Odometry, '/aft_mapped_to_init', mapped.append, qos.reliable(100))
    integrated_in = node.create_subscription(Odometry, '/integrated_to_init', integrated.append, qos.reliable(100))
    node.create_subscription(TFMessage, '/tf_static', static.append, qos.latched())
    # featureAssociation's less-flat features (published while subscribed): it is done with a scan.
    features_in = node.create_subscription(
        PointCloud2, '/laser_cloud_less_flat', lambda m: features.add(stamp_to_ns(m.header.stamp)), qos.reliable(100)
    )
    clouds = node.create_publisher(PointCloud2, '/velodyne_points', qos.reliable(10))
    diagnostics = Diagnostics(node)
    executables = ('legoLoam',) if composed else NODES
    procs = {
        name: processes.start([BIN / name, '--ros-args', '--params-file', original, '--params-file', params])
        for name in executables
    }
    ready = spin_until(
        rclpy_context,
        node,
        lambda: (
            node.count_publishers('/aft_mapped_to_init') > 0
            and node.count_publishers('/integrated_to_init') > 0
            and node.count_publishers('/segmented_cloud') > 0
            and node.count_publishers('/laser_odom_to_init') > 0
            or any(p.poll() is not None for p in procs.values())
        ),
        30,
    )
    for name, p in procs.items():
        assert p.poll() is None, f'{name} exited: {p.communicate()[1]}'
    assert ready
    # Every link matched at both ends: a message sent before is lost, as with any DDS publisher (a busy machine
    # once had mapOptimization miss the first mapping inputs, and the lockstep wait for their result for ever).
    links = pipeline_links(clouds, features_in, mapped_in, integrated_in, composed)
    linked = spin_until(rclpy_context, node, lambda: links_matched(diagnostics, links), 60)
    assert linked, {
        name: {k: v for k, v in values.items() if k.startswith('matched')}
        for name, values in diagnostics.latest.items()
    }
    if composed:  # the topics between the nodes are handed over in memory: no subscription of theirs on DDS
        expected = {topic: int(topic == '/aft_mapped_to_init') for topic in INTERNAL_TOPICS}  # (this test's own)

        def subscribers():
            return {topic: node.count_subscribers(topic) for topic in INTERNAL_TOPICS}

        # (Subscriptions made and taken out of DDS at start-up can linger a moment in this node's view of the graph.)
        assert spin_until(rclpy_context, node, lambda: subscribers() == expected, 10), subscribers()
    # A broken cloud first (its data shorter than its layout says): dropped with a warning, and the scans after it
    # go through as if it had never come, in one process as in four.
    broken = xyzi_to_cloud_msg(np.zeros((1000, 4), np.float32), make_header(0, 'velodyne'))
    broken.data = broken.data[:64]
    clouds.publish(broken)
    assert spin_until(rclpy_context, node, lambda: diagnostics.counter('imageProjection', 'clouds_dropped') >= 1, 15)
    # One scan at a time, the next once the whole pipeline is done with the previous one: its fused pose is out
    # and, on the scans where the original ran a mapping step, that step's result too. Parity needs every scan
    # in the original's order of events; the depth-1 inputs ('latest wins') would let a loaded machine skip one.
    expected_mapped = golden['aft_mapped_to_init_stamps'].tolist()
    integrated_stamps = set(golden['integrated_to_init_stamps'].tolist())

    def through(stamp: int) -> bool:
        done = stamp in features and (
            stamp not in integrated_stamps or stamp in {stamp_to_ns(m.header.stamp) for m in integrated}
        )
        # A mapping step is through once transformFusion has taken its result (its 'mapped' counter): the next
        # scan's fused pose must use it, as the original's did.
        return done and (
            not _mapping_step_for(stamp, expected_mapped)
            or (
                any(abs(stamp_to_ns(m.header.stamp) - stamp) < 1000 for m in mapped)
                and diagnostics.counter('transformFusion', 'mapped') >= len(mapped)
            )
        )

    scans = bag_clouds(shared_data / 'golden' / f'{GOLDEN_BAG}_ros2')
    assert [s for s, _ in scans] == stamps
    left = publish_in_lockstep(rclpy_context, node, clouds.publish, scans, through)
    missing = sorted(integrated_stamps - {stamp_to_ns(m.header.stamp) for m in integrated})
    assert not left, (
        f'{len(integrated)} integrated, {len(mapped)} mapped; no /integrated_to_init for scans '
        f'{[stamps.index(s) for s in missing if s in stamps]}: {_stop_and_log(processes, procs)}'
    )

    # /aft_mapped_to_init: the original's steps (every 0.3 s of input), poses and the twist-carried pose.
    assert [stamp_to_ns(m.header.stamp) for m in mapped] == [
        int(round(s / 1000)) * 1000 for s in expected_mapped
    ] or np.abs(np.array([stamp_to_ns(m.header.stamp) for m in mapped]) - np.array(expected_mapped)).max() < 1000
    assert {(m.header.frame_id, m.child_frame_id) for m in mapped} == {('camera_init', 'aft_mapped')}
    ours = odometry_rows(mapped)
    assert np.abs(ours[:, :3] - golden['aft_mapped_to_init'][:, :3]).max() < 1e-5
    assert np.abs(np.abs(ours[:, 3:]) - np.abs(golden['aft_mapped_to_init'][:, 3:])).max() < 1e-6
    # /integrated_to_init: one per odometry message, the original's fused poses.
    assert [stamp_to_ns(m.header.stamp) for m in integrated] == golden['integrated_to_init_stamps'].tolist()
    assert {(m.header.frame_id, m.child_frame_id) for m in integrated} == {('camera_init', 'camera')}
    ours = odometry_rows(integrated)
    assert np.abs(ours[:, :3] - golden['integrated_to_init'][:, :3]).max() < 1e-5
    assert np.abs(np.abs(ours[:, 3:]) - np.abs(golden['integrated_to_init'][:, 3:])).max() < 1e-6
    # The original's static transforms, latched.
    assert {(t.header.frame_id, t.child_frame_id) for m in static for t in m.transforms} >= {
        ('map', 'camera_init'),
        ('camera', 'base_link'),
    }

    # Saving: the service writes the maps and the trajectory atomically.
    client = node.create_client(Trigger, 'save_map')
    assert client.wait_for_service(timeout_sec=10)
    future = client.call_async(Trigger.Request())
    assert spin_until(rclpy_context, node, future.done, 30)
    assert future.result().success, future.result().message
    for name in (
        'global_map.pcd',
        'corner_map.pcd',
        'surface_map.pcd',
        'trajectory.pcd',
        'trajectory.tum',
        'trajectory_camera_init.tum',
    ):
        assert (maps / name).is_file(), name
    cloud = read_pcd(maps / 'global_map.pcd')
    assert cloud.shape[1] == 4 and len(cloud) > 300  # one keyframe: the sensor stands still
    tum_stamps, tum_poses = read_tum(maps / 'trajectory.tum')
    assert len(tum_stamps) >= 1 and np.isfinite(tum_poses).all()
    assert not [p for p in maps.iterdir() if '.tmp' in p.name]
    # Ctrl-C: every node exits cleanly; mapOptimization saves on the way out.
    (maps / 'global_map.pcd').unlink()
    for name, p in procs.items():
        _, err = processes.stop(p)
        assert p.returncode == 0, f'{name}: {err}'
        assert 'Traceback' not in err, f'{name}: {err}'
    assert (maps / 'global_map.pcd').is_file()
    release(node)
