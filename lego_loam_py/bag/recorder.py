"""``lego_loam_py record``: record topics into a ROS 2 bag (mcap by default), custom types included.

Subscriptions take serialized messages (no deserialization) and are created as topics appear, with a QoS
that matches their publishers (best effort when any publisher is best effort, transient local for latched
topics). SIGINT / SIGTERM finish the bag cleanly: metadata written, file complete.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from lego_loam_py.bag.io import BagError, BagWriter
from lego_loam_py.errors import UsageError
from lego_loam_py.ros.message_types import get_message_class
from lego_loam_py.ros.runtime import teardown_guard

__all__ = ['Recorder', 'add_arguments', 'main']

_IGNORED_TOPICS = ('/rosout', '/parameter_events')


class Recorder:
    """Records ``topics`` (or every topic when ``record_all``) of ``node``'s graph into ``writer``."""

    def __init__(
        self,
        node: Node,
        writer: BagWriter,
        topics: list[str] | None,
        record_all: bool = False,
        discovery_period: float = 0.2,
        depth: int = 100,
    ):
        self.node = node
        self.writer = writer
        self.wanted = set(topics or [])
        self.record_all = record_all
        self.depth = depth
        self.counts: dict[str, int] = {}
        self.warnings: list[str] = []
        self._subscriptions: dict[str, object] = {}
        self._lock = threading.Lock()
        self._closed = False
        # Steady clock: with use_sim_time the ROS clock stands still until /clock arrives, and a timer on it
        # would never discover the topics that appear after start-up.
        self._timer = node.create_timer(discovery_period, self.discover, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.discover()

    def _qos_for(self, topic: str) -> QoSProfile:
        infos = self.node.get_publishers_info_by_topic(topic)
        best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos)
        latched = bool(infos) and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
        return QoSProfile(
            depth=self.depth,
            reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
        )

    def discover(self) -> None:
        for topic, types in self.node.get_topic_names_and_types():
            if topic in self._subscriptions or topic in _IGNORED_TOPICS:
                continue
            if not (self.record_all or topic in self.wanted):
                continue
            if not self.node.get_publishers_info_by_topic(topic):
                continue  # only a subscriber so far: wait for a publisher to learn its QoS
            msgtype = types[0]
            try:
                cls = get_message_class(msgtype)
                profile = self._qos_for(topic)
                self.writer.add_topic(topic, msgtype, latching=profile.durability == DurabilityPolicy.TRANSIENT_LOCAL)
            except (LookupError, BagError) as exc:
                self.warnings.append(f'{topic}: {exc}')
                self._subscriptions[topic] = None
                continue
            self._subscriptions[topic] = self.node.create_subscription(
                cls, topic, lambda data, t=topic, m=msgtype: self._write(t, m, data), profile, raw=True
            )
            self.counts.setdefault(topic, 0)

    def _write(self, topic: str, msgtype: str, data: bytes) -> None:
        with self._lock:
            if self._closed:
                return
            self.writer.write_raw(topic, msgtype, self.node.get_clock().now().nanoseconds, data)
            self.counts[topic] += 1

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self.writer.close()


def default_output_name() -> str:
    return time.strftime('rosbag2_%Y_%m_%d-%H_%M_%S')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('topics', nargs='*', metavar='TOPIC', help='topics to record')
    parser.add_argument('-a', '--all', action='store_true', help='record every topic')
    parser.add_argument('-o', '--output', help='bag directory to create (default: rosbag2_<date>-<time>)')
    parser.add_argument(
        '-s', '--storage', choices=['mcap', 'sqlite3'], default='mcap', help='storage format (default mcap)'
    )
    parser.add_argument(
        '-d',
        '--duration',
        type=float,
        default=0.0,
        metavar='SEC',
        help='stop after SEC seconds (default: until Ctrl-C)',
    )
    parser.add_argument('--use-sim-time', action='store_true', help='stamp messages with /clock time')
    parser.add_argument('-q', '--quiet', action='store_true', help='no summary at the end')


def main(args: argparse.Namespace) -> int:
    if not args.topics and not args.all:
        raise UsageError('name topics to record or use --all')
    output = Path(args.output or default_output_name())
    writer = BagWriter(output, storage=args.storage)
    stop = threading.Event()
    rclpy.init(args=getattr(args, 'ros_args', None), signal_handler_options=SignalHandlerOptions.NO)
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    node = rclpy.create_node(
        'lego_loam_py_recorder',
        parameter_overrides=[Parameter('use_sim_time', value=True)] if args.use_sim_time else [],
    )
    recorder = Recorder(node, writer, args.topics, record_all=args.all)
    deadline = time.monotonic() + args.duration if args.duration > 0 else float('inf')
    try:
        while not stop.is_set() and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        recorder.close()
        for warning in recorder.warnings:
            print(f'warning: not recorded: {warning}', file=sys.stderr)
        if not args.quiet:
            total = sum(recorder.counts.values())
            detail = ', '.join(f'{t}: {n}' for t, n in sorted(recorder.counts.items()))
            print(f'recorded {total} messages into {output} ({detail})', file=sys.stderr, flush=True)
    finally:
        recorder.close()
        guard = teardown_guard(0, "the recorder's ROS 2 shutdown")
        node.destroy_node()
        rclpy.try_shutdown()
        guard.cancel()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
