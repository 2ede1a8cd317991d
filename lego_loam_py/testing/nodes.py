"""Helpers for tests that talk DDS from the pytest process."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import rclpy
from rclpy.executors import SingleThreadedExecutor


def spin_until(context, node, condition: Callable[[], bool], timeout: float) -> bool:
    """Spin ``node`` until ``condition()`` holds or ``timeout`` seconds pass; returns the condition."""
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            if condition():
                return True
            executor.spin_once(timeout_sec=0.05)
        return condition()
    finally:
        executor.remove_node(node)
        executor.shutdown(timeout_sec=0.1)


def read_until(proc, text: str, timeout: float = 20.0) -> str:
    """Everything the child printed on stdout up to and including the first line containing ``text``; raises
    with what it printed (and its stderr, once it has exited) when no such line came within ``timeout``."""
    deadline = time.monotonic() + timeout
    lines = []
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        lines.append(line)
        if text in line:
            return ''.join(lines)
    err = proc.stderr.read() if proc.poll() is not None and proc.stderr is not None else ''
    raise AssertionError(f'{text!r} not seen within {timeout} s; stdout={"".join(lines)!r} stderr={err!r}')


def wait_for_line(proc, text: str, timeout: float = 20.0) -> str:
    """The first line of the child's stdout containing ``text`` (see :func:`read_until`)."""
    return read_until(proc, text, timeout).splitlines(keepends=True)[-1]


def publish_in_lockstep(
    context, node, publish, items, processed, timeout: float = 60.0, resend_after: float = 5.0, resend=None
) -> list:
    """Hand ``items`` [(key, message)] to ``publish`` one at a time, each once ``processed(key)`` holds for the
    one before: a pipeline fed this way never sees two inputs at once, so the nodes' depth-1 queues ('latest
    wins', as the original's) lose nothing however slow a loaded machine makes them.

    ``publish`` is a publisher's ``publish`` (a message or serialized bytes) or any callable that sends one
    item. The first item is sent again every ``resend_after`` s while it has not come out: a best-effort
    subscriber (the nodes' sensor input) drops what arrives before it has matched the publisher, and only
    the subscriber knows when that is. A duplicate that does get through is dropped by the nodes as 'not
    newer than the previous scan'. ``resend`` (called with the message) does the same for every item: for
    feeds that may lose any of them on the way, such as bursts over a best-effort input (a full shared-memory
    segment drops what does not fit). Returns the keys that were not processed within ``timeout`` s each
    (the feed stops at the first).
    """
    for index, (key, message) in enumerate(items):
        publish(message)
        deadline = time.monotonic() + timeout
        while not spin_until(context, node, lambda: processed(key), min(resend_after, deadline - time.monotonic())):
            if time.monotonic() >= deadline:
                return [k for k, _ in items[index:]]
            if resend is not None:
                resend(message)
            elif index == 0:
                publish(message)
    return []


def bag_clouds(path) -> list[tuple[int, bytes]]:
    """(header stamp [ns], serialized PointCloud2) of every /velodyne_points message of a ROS 2 bag."""
    from lego_loam_py.bag.io import BagReader

    with BagReader(path) as reader:
        clouds = []
        for message in reader.messages(topics=['/velodyne_points']):
            stamp = reader.deserialize(message).header.stamp
            clouds.append((stamp.sec * 1_000_000_000 + stamp.nanosec, bytes(message.data)))
        return clouds


class Diagnostics:
    """The latest /diagnostics values of each node (the counters every lego_loam_py node publishes once a
    second): the events a test waits on when a node's reaction to an input has no output of its own, such as
    a dropped message."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray

        from lego_loam_py.ros import qos

        self.latest: dict[str, dict[str, str]] = {}
        self.levels: dict[str, int] = {}
        self.messages: dict[str, str] = {}
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_array, qos.reliable(50))

    def _on_array(self, array) -> None:
        for status in array.status:
            self.latest[status.name] = {kv.key: kv.value for kv in status.values}
            self.levels[status.name] = status.level[0] if isinstance(status.level, bytes) else int(status.level)
            self.messages[status.name] = status.message

    def counter(self, node_name: str, key: str) -> int:
        """The node's counter ``key`` as last published (0 before the first publication or the first count)."""
        return int(self.latest.get(node_name, {}).get(key, 0))


def links_matched(diagnostics: Diagnostics, links) -> bool:
    """Whether DDS has matched both ends of every link (writer, topic, readers): the writer with at least as many
    readers as listed, each reader with a writer. An end is a node's name (its counts as published on
    /diagnostics, see LegoLoamNode.matched_endpoints) or the test's own Publisher or Subscription.

    Seeing a topic's endpoints in the test's view of the graph is not enough: each participant discovers the
    others on its own time, and a message sent on a link not yet matched at both ends is lost.
    """

    def matched(end, topic: str, side: str) -> int:
        if isinstance(end, str):
            return diagnostics.counter(end, f'matched {side} {topic}')
        return end.get_subscription_count() if side == 'subscribers' else end.get_publisher_count()

    return all(
        matched(writer, topic, 'subscribers') >= len(readers)
        and all(matched(reader, topic, 'publishers') >= 1 for reader in readers)
        for writer, topic, readers in links
    )


def release(node, timeout: float = 10.0) -> bool:
    """``node.destroy_node()`` that cannot hang the test run: Fast DDS 3.2.3 can deadlock a participant when a
    remote writer goes away during a heartbeat response (see lego_loam_py.ros.runtime.teardown_guard), and
    deleting an entity then waits forever. Everything the test checks is checked before this is called."""
    from lego_loam_py.ros.runtime import finish_within

    return finish_within(node.destroy_node, f'destroying the test node {node.get_name()}', timeout)


def spin_in_background(executor, stop: threading.Event) -> threading.Thread:
    """A daemon thread spinning ``executor`` until the event ``stop`` is set (for scripts that publish and wait
    from their main thread); an error after ``stop`` (the context going away) ends it quietly."""
    import threading

    def spin() -> None:
        while not stop.is_set():
            try:
                executor.spin_once(timeout_sec=0.05)
            except Exception:
                if stop.is_set():
                    return
                raise

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    return thread


__all__ = [
    'spin_until',
    'spin_in_background',
    'read_until',
    'wait_for_line',
    'publish_in_lockstep',
    'bag_clouds',
    'Diagnostics',
    'release',
    'rclpy',
]
