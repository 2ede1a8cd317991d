"""The supervisor's own ROS node: is the pipeline up, and is its output still flowing?

:func:`lego_loam_py.orchestration.run_pipeline` starts the nodes as processes (:mod:`lego_loam_py.supervisor`,
which knows no ROS) and asks this node about the ROS graph: which nodes publish their always-on topic yet,
whether the recorder subscribed to what it records, and when the last pipeline output arrived (the drain).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping, Sequence

import rclpy
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from lego_loam_py.ros import qos
from lego_loam_py.ros.runtime import finish_within

__all__ = ['GraphMonitor']


class GraphMonitor:
    """Counts the Odometry messages of ``counted_topic`` and answers readiness questions about the ROS graph.

    ``ready_topics``: node name -> a topic the node publishes from start-up on (its publisher in the graph
    means the node is up); ``recorder_node``: the name of the recorder's ROS node. rclpy runs in a
    background thread with its own context, so the caller's signal handling stays its own; call
    :meth:`close`."""

    def __init__(self, counted_topic: str, ready_topics: Mapping[str, str], recorder_node: str):
        self.ready_topics = dict(ready_topics)
        self.recorder_node = recorder_node
        self.context = Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('lego_loam_py_launch', context=self.context, start_parameter_services=False)
        self.count = 0
        self.last_arrival: float | None = None  # time.monotonic() [s] of the last counted message
        self.node.create_subscription(Odometry, counted_topic, self._on_output, qos.reliable(100), raw=True)
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name='graph-monitor', daemon=True)
        self._thread.start()

    def _on_output(self, _data) -> None:
        self.count += 1
        self.last_arrival = time.monotonic()

    def _spin(self) -> None:
        while not self._stop.is_set():
            try:
                self._executor.spin_once(timeout_sec=0.05)
            except Exception:  # context shut down under us
                break

    def not_ready(self, nodes: Sequence[str], recorded_topics: Sequence[str] = ()) -> list[str]:
        """What is still missing: nodes whose always-on topic has no publisher yet, recorded topics with a
        publisher but without the recorder's subscription."""
        missing = [name for name in nodes if not self.node.get_publishers_info_by_topic(self.ready_topics[name])]
        for topic in recorded_topics:
            if self.node.get_publishers_info_by_topic(topic) and not any(
                info.node_name == self.recorder_node for info in self.node.get_subscriptions_info_by_topic(topic)
            ):
                missing.append(f'recorder on {topic}')
        return missing

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

        def teardown() -> None:
            try:
                self._executor.shutdown(timeout_sec=0.5)
                self.node.destroy_node()
            finally:
                rclpy.try_shutdown(context=self.context)

        finish_within(teardown, "the supervisor's graph monitor shutdown")
