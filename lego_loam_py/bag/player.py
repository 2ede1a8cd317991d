"""``lego_loam_py play``: replay a ROS 1 or ROS 2 bag over DDS, publishing /clock.

Messages are published as serialized CDR (no deserialization for ROS 2 bags), paced by their recording
time divided by the rate factor. /clock carries the bag time at ``clock_hz`` (40 Hz as rosbag2, or before
every message with 0), so nodes with ``use_sim_time`` follow the bag. ``--loop`` plays the bag again and again, like
``rosbag play -l``: stamps and /clock jump back to the bag's start at every repetition.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from dataclasses import dataclass, field

import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock

from lego_loam_py.bag.io import BagReader
from lego_loam_py.errors import UsageError
from lego_loam_py.ros import qos
from lego_loam_py.ros.conversions import ns_to_stamp
from lego_loam_py.ros.message_types import get_message_class
from lego_loam_py.ros.runtime import teardown_guard

__all__ = ['PlayStats', 'play', 'add_arguments', 'main']

_LATCHED_TOPICS = ('/tf_static',)


@dataclass
class PlayStats:
    published: dict[str, int] = field(default_factory=dict)
    skipped_topics: dict[str, str] = field(default_factory=dict)  # topic -> reason
    wall_time: float = 0.0
    bag_time: float = 0.0
    interrupted: bool = False
    loops: int = 0  # complete plays of the bag


def _parse_remaps(remaps: list[str]) -> dict[str, str]:
    out = {}
    for item in remaps:
        if ':=' not in item:
            raise ValueError(f"remap '{item}' must look like /from:=/to")
        source, target = item.split(':=', 1)
        out[source] = target
    return out


def play(
    node: Node,
    reader: BagReader,
    *,
    topics: list[str] | None = None,
    rate: float = 1.0,
    start_offset: float = 0.0,
    clock_hz: float = 40.0,
    publish_clock: bool = True,
    remaps: dict[str, str] | None = None,
    wait_for_subscribers: float = 0.0,
    depth: int = 100,
    progress: bool = True,
    stop: threading.Event | None = None,
    loops: int = 1,
) -> PlayStats:
    """Publish the bag's messages on ``node``; returns what was published. Blocks until done or ``stop``.

    ``loops``: how many times the bag is played (0: until ``stop``)."""
    if rate <= 0:
        raise ValueError('rate must be positive')
    if loops < 0:
        raise ValueError('loops must be 0 (forever) or positive')
    stop = stop or threading.Event()
    remaps = remaps or {}
    stats = PlayStats()
    available = reader.topics()
    selected = [t for t in (topics or sorted(available)) if t in available]
    for t in topics or []:
        if t not in available:
            stats.skipped_topics[t] = 'not in the bag'
    publishers = {}
    for topic in selected:
        try:
            cls = get_message_class(available[topic])
        except LookupError as exc:
            stats.skipped_topics[topic] = str(exc)
            continue
        profile = qos.latched(depth=1) if topic in _LATCHED_TOPICS else qos.reliable(depth)
        publishers[topic] = node.create_publisher(cls, remaps.get(topic, topic), profile)
    clock_pub = node.create_publisher(Clock, '/clock', qos.reliable(10)) if publish_clock else None

    if wait_for_subscribers > 0 and publishers:
        deadline = time.monotonic() + wait_for_subscribers
        while time.monotonic() < deadline and not stop.is_set():
            if all(p.get_subscription_count() > 0 for p in publishers.values()):
                break
            time.sleep(0.02)

    start = reader.start_time + int(start_offset * 1e9)
    total = sum(n for t, n in reader.topic_counts().items() if t in publishers)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(
            total=total * loops if loops else None,
            unit='msg',
            desc='play',
            file=sys.stderr,
            dynamic_ncols=True,
            mininterval=0.5,
        )
    clock_period = 1.0 / clock_hz if clock_hz > 0 else float('inf')

    def publish_clock_at(bag_ns: int) -> None:
        if clock_pub is not None:
            clock_pub.publish(Clock(clock=ns_to_stamp(bag_ns)))

    wall_start = time.monotonic()
    bag_start = None
    last_clock = -1.0
    last_stamp = start
    bag_span = 0.0
    try:
        while not stop.is_set() and (loops == 0 or stats.loops < loops):
            loop_wall_start = time.monotonic()
            bag_start = None
            published_in_loop = 0
            for message in reader.messages(topics=list(publishers), start=start):
                if stop.is_set():
                    stats.interrupted = True
                    break
                if bag_start is None:
                    bag_start = message.timestamp
                    publish_clock_at(bag_start)
                    last_clock = time.monotonic()
                target = loop_wall_start + (message.timestamp - bag_start) / 1e9 / rate
                while not stop.is_set():
                    now = time.monotonic()
                    if now >= target:
                        break
                    if now - last_clock >= clock_period:
                        publish_clock_at(bag_start + int((now - loop_wall_start) * rate * 1e9))
                        last_clock = now
                    time.sleep(min(target - now, clock_period))
                if stop.is_set():
                    stats.interrupted = True
                    break
                # /clock at most at clock_hz (every subscriber with use_sim_time pays a callback per tick);
                # with clock_hz 0, before every message.
                now = time.monotonic()
                if clock_period == float('inf') or now - last_clock >= clock_period:
                    publish_clock_at(message.timestamp)
                    last_clock = now
                publishers[message.topic].publish(message.data)
                stats.published[message.topic] = stats.published.get(message.topic, 0) + 1
                last_stamp = message.timestamp
                published_in_loop += 1
                if bar is not None:
                    bar.update(1)
            if bag_start is not None:
                publish_clock_at(last_stamp)  # the clock ends where the bag's messages end
                bag_span += (last_stamp - bag_start) / 1e9
            if stats.interrupted:
                break
            stats.loops += 1
            if published_in_loop == 0:
                break  # nothing to play: never spin on an empty selection
        if stop.is_set() and (loops == 0 or stats.loops < loops):
            stats.interrupted = True
    finally:
        if bar is not None:
            bar.close()
    # Reliable delivery of the last messages before the publishers go away.
    for publisher in publishers.values():
        try:
            publisher.wait_for_all_acked(Duration(seconds=2.0))
        except Exception:  # not supported by every RMW
            pass
    stats.wall_time = time.monotonic() - wall_start
    stats.bag_time = bag_span
    return stats


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('bag', help='ROS 1 .bag file or ROS 2 bag directory (.db3 or .mcap)')
    parser.add_argument('-r', '--rate', type=float, default=1.0, help='playback rate factor (default 1.0)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC', help='play only these topics (default: all)')
    parser.add_argument(
        '-s', '--start-offset', type=float, default=0.0, metavar='SEC', help='skip the first SEC seconds of the bag'
    )
    parser.add_argument(
        '--clock',
        type=float,
        default=40.0,
        metavar='HZ',
        help='publish /clock at this rate, with the messages and between them (default 40, as '
        'rosbag2; 0: before every message)',
    )
    parser.add_argument('--no-clock', action='store_true', help='do not publish /clock')
    parser.add_argument('--remap', nargs='+', default=[], metavar='FROM:=TO', help='topic remappings')
    parser.add_argument(
        '--wait-for-subscribers',
        type=float,
        default=0.0,
        metavar='SEC',
        help='before playing, wait up to SEC seconds until every topic has a subscriber',
    )
    parser.add_argument('--qos-depth', type=int, default=100, help='publisher queue depth (default 100)')
    parser.add_argument(
        '-l',
        '--loop',
        type=int,
        nargs='?',
        const=0,
        default=1,
        metavar='N',
        help='play the bag N times (without N: until interrupted), like rosbag play -l; '
        'stamps and /clock jump back to the start at every repetition',
    )
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    parser.add_argument('-q', '--quiet', action='store_true', help='no summary at the end')


def main(args: argparse.Namespace) -> int:
    try:
        remaps = _parse_remaps(args.remap)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.loop < 0:
        raise UsageError('--loop N needs N >= 1 (or no N: forever)')
    reader = BagReader(args.bag)
    reader.open()
    stop = threading.Event()
    rclpy.init(args=getattr(args, 'ros_args', None), signal_handler_options=SignalHandlerOptions.NO)
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    node = rclpy.create_node('lego_loam_py_player')
    try:
        stats = play(
            node,
            reader,
            topics=args.topics,
            rate=args.rate,
            start_offset=args.start_offset,
            clock_hz=args.clock,
            publish_clock=not args.no_clock,
            remaps=remaps,
            wait_for_subscribers=args.wait_for_subscribers,
            depth=args.qos_depth,
            progress=not args.no_progress,
            stop=stop,
            loops=args.loop,
        )
        reader.close()
        for topic, reason in stats.skipped_topics.items():
            print(f'warning: {topic} not played: {reason}', file=sys.stderr)
        if not args.quiet:
            count = sum(stats.published.values())
            rate = count / stats.wall_time if stats.wall_time > 0 else 0.0
            state = 'interrupted' if stats.interrupted else 'done'
            loops = f' ({stats.loops} plays)' if stats.loops > 1 else ''
            print(
                f'{state}: {count} messages on {len(stats.published)} topics, {stats.bag_time:.2f} s of bag{loops} '
                f'in {stats.wall_time:.2f} s ({rate:.1f} msg/s)',
                file=sys.stderr,
                flush=True,
            )
    finally:
        reader.close()
        guard = teardown_guard(0, "the player's ROS 2 shutdown")
        node.destroy_node()
        rclpy.try_shutdown()
        guard.cancel()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
