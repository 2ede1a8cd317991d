"""A stand-in for one pipeline node that computes nothing: what rclpy alone costs for that node's messages.

    python benchmarks/floor_node.py NODE CAPTURE_BAG --ros-args -p use_sim_time:=true

It has the real node's subscriptions (same topics, types, QoS, serialized or not, the IMU polled and taken with each
input as the real nodes do, /clock through ``use_sim_time``, polled where the node polls it) and spins in the same
executor (:func:`lego_loam_py.ros.runtime.make_executor`). On each message of its trigger topic it publishes, on
the real node's publishers, the next messages that node published in ``CAPTURE_BAG`` (recorded by ``bench_dds.py
--floor`` from a run of the real pipeline): the same bytes, so the same sizes, spread evenly over the triggers.
Whole-process CPU of these four processes on the same recording is the floor under any rclpy implementation of the
pipeline; ``bench_dds.py --floor`` measures it beside the real nodes.
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

# The real nodes' wiring (see lego_loam_py/ros/*_node.py), with use_sim_time: subscriptions (topic, type, QoS,
# serialized), polled subscriptions (topic, type, QoS, taken on each trigger: the IMU; /clock is read about once a
# second, see LegoLoamNode.POLL_CLOCK), the trigger topic, and publishers (topic, type, QoS, the /tf child frame of that
# node's transforms when the topic is /tf).
IMU = '/imu/data'
CLOCK = '/clock'
POLLED_CLOCK = (CLOCK, 'Clock', 'sensor1', False)
WIRING = {
    'imageProjection': dict(
        subscribe=[('/velodyne_points', 'PointCloud2', 'sensor1', True)],
        polled=[POLLED_CLOCK],
        trigger='/velodyne_points',
        publish=[
            ('/segmented_cloud', 'PointCloud2', 'reliable1', None),
            ('/segmented_cloud_info', 'CloudInfo', 'reliable1', None),
            ('/outlier_cloud', 'PointCloud2', 'reliable1', None),
        ],
    ),
    'featureAssociation': dict(
        subscribe=[
            ('/segmented_cloud', 'PointCloud2', 'reliable1', True),
            ('/segmented_cloud_info', 'CloudInfo', 'reliable1', True),
            ('/outlier_cloud', 'PointCloud2', 'reliable1', True),
            ('/aft_mapped_to_init', 'Odometry', 'reliable5', True),
        ],
        polled=[POLLED_CLOCK, (IMU, 'Imu', 'sensor200', True)],
        trigger='/outlier_cloud',
        publish=[
            ('/laser_cloud_corner_last', 'PointCloud2', 'reliable2', None),
            ('/laser_cloud_surf_last', 'PointCloud2', 'reliable2', None),
            ('/outlier_cloud_last', 'PointCloud2', 'reliable2', None),
            ('/laser_odom_to_init', 'Odometry', 'reliable5', None),
            ('/tf', 'TFMessage', 'tf', 'laser_odom'),
        ],
    ),
    'mapOptimization': dict(
        subscribe=[
            ('/laser_cloud_corner_last', 'PointCloud2', 'reliable2', True),
            ('/laser_cloud_surf_last', 'PointCloud2', 'reliable2', True),
            ('/outlier_cloud_last', 'PointCloud2', 'reliable2', True),
            ('/laser_odom_to_init', 'Odometry', 'reliable5', True),
            (CLOCK, 'Clock', 'sensor1', False),  # (rclpy's time source: mapOptimization's timers run on ROS time)
        ],
        polled=[('/laser_odom_to_init', 'Odometry', 'reliable20', True), (IMU, 'Imu', 'sensor200', True)],
        trigger='/laser_odom_to_init',
        publish=[('/aft_mapped_to_init', 'Odometry', 'reliable5', None), ('/tf', 'TFMessage', 'tf', 'aft_mapped')],
    ),
    'transformFusion': dict(
        subscribe=[
            ('/laser_odom_to_init', 'Odometry', 'reliable5', True),
            ('/aft_mapped_to_init', 'Odometry', 'reliable5', True),
        ],
        polled=[POLLED_CLOCK],
        trigger='/laser_odom_to_init',
        publish=[('/integrated_to_init', 'Odometry', 'reliable5', None), ('/tf', 'TFMessage', 'tf', 'camera')],
    ),
}
# Every topic a capture records: the triggers and what the nodes publish.
CAPTURE_TOPICS = sorted(
    {w['trigger'] for w in WIRING.values()} | {topic for w in WIRING.values() for topic, *_ in w['publish']}
)


def _qos(name: str):
    from lego_loam_py.ros import qos
    from lego_loam_py.ros.tf import TF_QOS

    if name == 'tf':
        return TF_QOS
    kind, depth = name.rstrip('0123456789'), int(name[len(name.rstrip('0123456789')) :])
    return qos.sensor_input(depth) if kind == 'sensor' else qos.reliable(depth)


def _type(name: str):
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Imu, PointCloud2
    from tf2_msgs.msg import TFMessage

    from cloud_msgs.msg import CloudInfo

    types = (PointCloud2, CloudInfo, Odometry, Imu, TFMessage, Clock)
    return {t.__name__: t for t in types}[name]


def captured_outputs(bag: Path, node: str) -> tuple[int, dict[str, list[bytes]]]:
    """How many trigger messages ``bag`` holds and, per publisher of ``node``, the bytes it published (a /tf
    publisher: the messages carrying its child frame)."""
    from lego_loam_py.bag.io import BagReader

    wiring = WIRING[node]
    outputs: dict[str, list[bytes]] = {topic: [] for topic, *_ in wiring['publish']}
    tf_child = {topic: child for topic, _, _, child in wiring['publish'] if child}
    triggers = 0
    with BagReader(bag) as reader:
        for message in reader.messages(set(outputs) | {wiring['trigger']}):
            if message.topic == wiring['trigger']:
                triggers += 1
            if message.topic not in outputs:
                continue
            if message.topic in tf_child:
                children = {t.child_frame_id for t in reader.deserialize(message).transforms}
                if tf_child[message.topic] not in children:
                    continue
            outputs[message.topic].append(message.data)
    return triggers, outputs


def main(argv: list[str] | None = None) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node

    from lego_loam_py.ros.runtime import make_executor

    argv = list(sys.argv if argv is None else argv)
    rclpy.init(args=argv)
    name, bag = argv[1], Path(argv[2])
    wiring = WIRING[name]
    triggers, outputs = captured_outputs(bag, name)
    node = Node(name)
    publishers = [
        (node.create_publisher(_type(t), topic, _qos(q)), outputs[topic]) for topic, t, q, _ in wiring['publish']
    ]
    polled_node = rclpy.create_node(
        f'{name}_polled', use_global_arguments=False, enable_rosout=False, start_parameter_services=False
    )
    if any(topic == CLOCK for topic, *_ in wiring['polled']):  # the node polls /clock instead of rclpy's time source
        source = node._time_source
        if source._clock_sub is not None:
            node.destroy_subscription(source._clock_sub)
            source._clock_sub = None
    polled = [
        (polled_node.create_subscription(_type(t), topic, lambda _: None, _qos(q), raw=True), per_trigger)
        for topic, t, q, per_trigger in wiring['polled']
    ]
    fired = [0]

    def on_trigger(_msg) -> None:
        for subscription, per_trigger in polled:  # the queued IMU samples (and odometry) come with each input
            while per_trigger:
                with subscription.handle:
                    if subscription.handle.take_message(subscription.msg_type, subscription.raw) is None:
                        break
        k = fired[0] = fired[0] + 1
        for publisher, messages in publishers:
            # The messages published between the (k-1)-th and the k-th trigger, as spread over the capture.
            for data in messages[(k - 1) * len(messages) // max(triggers, 1) : k * len(messages) // max(triggers, 1)]:
                publisher.publish(data)

    for topic, t, q, raw in wiring['subscribe']:
        if topic == CLOCK:
            continue  # (rclpy's time source subscribes it)
        callback = on_trigger if topic == wiring['trigger'] else (lambda _: None)
        node.create_subscription(_type(t), topic, callback, _qos(q), raw=raw)
    executor, spin_once = make_executor()
    executor.add_node(node)
    try:
        while rclpy.ok():
            spin_once(0.5)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        polled_node.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
