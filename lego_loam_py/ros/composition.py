"""Several lego_loam_py nodes in one process, their messages to each other handed over in memory.

The four nodes run as four processes by default, as the original's do. Started together in one process
(``ros2 run lego_loam_py legoLoam``, or ``lego_loam_py launch --composed``), the pipeline's messages from one
node to another need not go through DDS: a topic that a node of the process publishes and another one
subscribes to is *linked*. Its publisher hands each message to the process's own subscribers, and sends it
over DDS only while a subscriber elsewhere (rviz, a recorder, another node) is matched; the process's own
subscriptions of that topic are taken out of DDS. The subscribers get exactly what DDS would have given them: the
serialized message (a message object is serialized first), in publication order, each subscription's queue as
deep as its QoS, so every node computes the same results either way.

Only topics with volatile durability are linked (what a latched topic holds for late joiners stays DDS's job), and
only between the nodes of this process: a second publisher of a linked topic in another process is not heard by
them. Messages are delivered after the callback that published them returns, by the thread that ran it
(:meth:`LocalLinks.deliver`), so a chain of nodes runs scan after scan without waking the executor.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field

from rclpy.qos import DurabilityPolicy

__all__ = ['LocalLinks', 'LinkedPublisher', 'LocalQueue']


class LocalQueue:
    """The queue of a polled subscription of a linked topic: its QoS depth, the newest kept."""

    def __init__(self, topic: str, depth: int, sender: bytes):
        self.topic = topic  # (the subscription it stands for is destroyed: its name is kept here)
        self.messages: deque = deque(maxlen=max(1, depth))
        self.sender = sender

    def put(self, data: bytes) -> None:
        self.messages.append(data)

    def take(self):
        """``(data, info)`` of the oldest message, or None: what rclpy's take gives a raw subscription."""
        if not self.messages:
            return None
        return self.messages.popleft(), {'publisher_gid': {'data': self.sender}}


@dataclass
class _Subscription:
    node: object
    subscription: object
    callback: object  # the node's guarded callback (None for a polled subscription)
    depth: int
    queue: LocalQueue | None = None


@dataclass
class _Topic:
    publishers: list = field(default_factory=list)
    subscriptions: list = field(default_factory=list)
    linked: bool = False


class LinkedPublisher:
    """A node's publisher in a composed process: rclpy's publisher, plus the hand-over to the process's own
    subscribers once its topic is linked. Everything else is the rclpy publisher's."""

    def __init__(self, publisher, links: LocalLinks, topic: _Topic):
        self._publisher = publisher
        self._links = links
        self._topic = topic
        self.sender = id(self).to_bytes(8, 'little') + bytes(8)  # a publisher id, as a gid is 16 bytes

    def __getattr__(self, name):
        return getattr(self._publisher, name)

    def get_subscription_count(self) -> int:
        local = len(self._topic.subscriptions) if self._topic.linked else 0
        return self._publisher.get_subscription_count() + local

    def publish(self, msg) -> None:
        if not self._topic.linked:
            self._publisher.publish(msg)
            return
        if not isinstance(msg, (bytes, bytearray)):
            from rclpy.serialization import serialize_message

            msg = serialize_message(msg)
        self._links.hand_over(self._topic, bytes(msg), self.sender)
        if self._publisher.get_subscription_count():  # a subscriber in another process
            self._publisher.publish(msg)


class LocalLinks:
    """The linked topics of one process (see the module). Nodes register their publishers and subscriptions as
    they create them (:class:`~lego_loam_py.ros.node_base.LegoLoamNode` with ``links=``); :meth:`link` then, before
    anything spins, links every topic that has both."""

    def __init__(self):
        self._topics: dict[str, _Topic] = {}
        self._pending: deque = deque()
        self._lock = threading.Lock()
        self._delivering = threading.local()
        self.queues: dict[int, LocalQueue] = {}  # id(polled subscription) -> its local queue

    def _topic(self, name: str) -> _Topic:
        return self._topics.setdefault(name, _Topic())

    def add_publisher(self, topic: str, publisher, qos_profile) -> LinkedPublisher | object:
        if qos_profile.durability != DurabilityPolicy.VOLATILE:
            return publisher
        entry = self._topic(topic)
        wrapped = LinkedPublisher(publisher, self, entry)
        entry.publishers.append(wrapped)
        return wrapped

    def add_subscription(self, node, topic: str, subscription, callback, qos_profile) -> None:
        if qos_profile.durability != DurabilityPolicy.VOLATILE or not subscription.raw:
            return
        self._topic(topic).subscriptions.append(_Subscription(node, subscription, callback, qos_profile.depth))

    def link(self) -> list[str]:
        """Link every topic with a publisher and a subscription here; returns their names."""
        linked = []
        for name, entry in self._topics.items():
            if not entry.publishers or not entry.subscriptions:
                continue
            for sub in entry.subscriptions:
                owner = sub.subscription  # taken out of DDS: its messages come from here now
                if sub.callback is None:
                    sub.queue = LocalQueue(name, sub.depth, entry.publishers[0].sender)
                    self.queues[id(owner)] = sub.queue
                    sub.node._polled_node.destroy_subscription(owner)
                else:
                    sub.node.destroy_subscription(owner)
            entry.linked = True
            linked.append(name)
        return sorted(linked)

    def hand_over(self, topic: _Topic, data: bytes, sender: bytes) -> None:
        with self._lock:
            for sub in topic.subscriptions:
                if sub.queue is not None:
                    sub.queue.sender = sender
                    sub.queue.put(data)
                else:
                    self._pending.append((sub.callback, data))

    def deliver(self) -> None:
        """Run the callbacks of the messages handed over so far, and of those they publish, in order. Called
        after each callback of a node of this process; a no-op inside a delivery."""
        if getattr(self._delivering, 'active', False):
            return
        self._delivering.active = True
        try:
            while True:
                with self._lock:
                    if not self._pending:
                        return
                    callback, data = self._pending.popleft()
                callback(data)  # (guarded: it never raises)
        finally:
            self._delivering.active = False
