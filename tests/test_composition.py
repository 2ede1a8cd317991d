"""Nodes in one process: the topics between them handed over in memory (lego_loam_py.ros.composition).

The links are checked here with stand-ins for rclpy's publishers and subscriptions; the four real nodes in one
process are checked over DDS against the original's results in test_pipeline_golden.py.
"""

from __future__ import annotations

import pytest

pytest.importorskip('rclpy')

from rclpy.qos import DurabilityPolicy, QoSProfile  # noqa: E402

from lego_loam_py.ros.composition import LinkedPublisher, LocalLinks  # noqa: E402

VOLATILE = QoSProfile(depth=2)
LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)


class FakePublisher:
    """rclpy's publisher as a node sees it: what it sent over DDS, and how many subscribers DDS matched."""

    def __init__(self, topic: str, remote: int = 0):
        self.topic_name = topic
        self.remote = remote
        self.sent = []

    def publish(self, msg) -> None:
        self.sent.append(msg)

    def get_subscription_count(self) -> int:
        return self.remote


class FakeSubscription:
    def __init__(self, raw: bool = True):
        self.raw = raw


class FakeNode:
    """A node: the subscriptions taken out of DDS (its own, and its polled companion's)."""

    def __init__(self):
        self.destroyed = []
        self._polled_node = self

    def destroy_subscription(self, subscription) -> None:
        self.destroyed.append(subscription)


def link_one(topic='/a', remote=0, depth=2, publisher_qos=VOLATILE, raw=True):
    """A publisher and one event subscription of ``topic``; returns (links, publisher, received, node, sub)."""
    links = LocalLinks()
    dds = FakePublisher(topic, remote)
    publisher = links.add_publisher(topic, dds, publisher_qos)
    received = []
    node, subscription = FakeNode(), FakeSubscription(raw)
    links.add_subscription(node, topic, subscription, received.append, QoSProfile(depth=depth))
    return links, publisher, dds, received, node, subscription


def test_a_linked_topic_reaches_the_subscriber_in_memory_after_the_callback_and_not_over_dds():
    links, publisher, dds, received, node, subscription = link_one()
    assert links.link() == ['/a']
    assert node.destroyed == [subscription]  # out of DDS: nothing arrives twice
    publisher.publish(b'one')
    publisher.publish(b'two')
    assert received == []  # (delivered once the publishing callback is through)
    links.deliver()
    assert received == [b'one', b'two']
    assert dds.sent == []  # nobody in another process listens


def test_a_subscriber_in_another_process_gets_it_over_dds_too():
    links, publisher, dds, received, _, _ = link_one(remote=1)
    links.link()
    publisher.publish(b'x')
    links.deliver()
    assert received == [b'x'] and dds.sent == [b'x']
    # The nodes' "is anybody listening" checks count the subscribers here as well.
    assert publisher.get_subscription_count() == 2


def test_what_a_delivered_callback_publishes_is_delivered_in_the_same_pass_in_order():
    links = LocalLinks()
    first = links.add_publisher('/a', FakePublisher('/a'), VOLATILE)
    second = links.add_publisher('/b', FakePublisher('/b'), VOLATILE)
    events = []

    def on_a(data):
        events.append(('a', data))
        second.publish(data + b'>b')
        links.deliver()  # (every guarded callback ends so: a no-op inside a delivery)
        events.append(('a done', data))

    links.add_subscription(FakeNode(), '/a', FakeSubscription(), on_a, VOLATILE)
    links.add_subscription(FakeNode(), '/b', FakeSubscription(), lambda d: events.append(('b', d)), VOLATILE)
    links.link()
    first.publish(b'1')
    first.publish(b'2')
    links.deliver()
    assert events == [('a', b'1'), ('a done', b'1'), ('a', b'2'), ('a done', b'2'), ('b', b'1>b'), ('b', b'2>b')]


def test_a_message_object_arrives_serialized_as_over_dds():
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message

    links, publisher, _, received, _, _ = link_one()
    links.link()
    msg = Odometry()
    msg.header.frame_id = 'camera_init'
    msg.pose.pose.position.x = 1.5
    expected = serialize_message(msg)
    publisher.publish(msg)
    msg.pose.pose.position.x = 2.5  # a publisher reusing its message changes nothing already sent
    links.deliver()
    assert received == [expected]


@pytest.mark.parametrize(
    'case', ['latched publisher', 'latched subscription', 'not serialized', 'no publisher here', 'no subscriber here']
)
def test_what_is_not_linked_stays_on_dds(case):
    links = LocalLinks()
    dds = FakePublisher('/a')
    node, subscription, received = FakeNode(), FakeSubscription(raw=case != 'not serialized'), []
    publisher = dds
    if case != 'no publisher here':
        publisher = links.add_publisher('/a', dds, LATCHED if case == 'latched publisher' else VOLATILE)
    if case != 'no subscriber here':
        qos = LATCHED if case == 'latched subscription' else VOLATILE
        links.add_subscription(node, '/a', subscription, received.append, qos)
    assert links.link() == []
    assert node.destroyed == []
    publisher.publish(b'x')
    links.deliver()
    assert dds.sent == [b'x'] and received == []


def test_a_polled_subscription_keeps_the_newest_of_its_depth_with_the_sender():
    links = LocalLinks()
    publisher = links.add_publisher('/odom', FakePublisher('/odom'), VOLATILE)
    node, polled = FakeNode(), FakeSubscription()
    links.add_subscription(node, '/odom', polled, None, QoSProfile(depth=3))
    links.link()
    assert node.destroyed == [polled]
    queue = links.queues[id(polled)]
    for k in range(5):
        publisher.publish(bytes([k]))
    links.deliver()  # (nothing to run: polled messages wait to be taken)
    taken = []
    while (item := queue.take()) is not None:
        taken.append(item)
    assert [data for data, _ in taken] == [b'\x02', b'\x03', b'\x04']
    assert {info['publisher_gid']['data'] for _, info in taken} == {publisher.sender}
    assert len(publisher.sender) == 16


def test_the_publisher_is_rclpys_for_everything_else():
    links, publisher, dds, _, _, _ = link_one()
    assert isinstance(publisher, LinkedPublisher)
    assert publisher.topic_name == '/a'
    assert publisher.get_subscription_count() == 0  # not linked yet: DDS's count alone
