"""What every lego_loam_py node shares: typed parameters, throttled warnings, timing statistics, diagnostics."""

from __future__ import annotations

import inspect
import json
import os
import re
import threading
import time
import traceback
from collections import OrderedDict, deque

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from lego_loam_py.allocator import release_memory
from lego_loam_py.core.guard import STATE_RESETS, StepGuard
from lego_loam_py.core.imu.buffer import imu_sample
from lego_loam_py.core.params import Params
from lego_loam_py.core.pointcloud import CloudLayoutError
from lego_loam_py.results import TimingStats
from lego_loam_py.ros import qos
from lego_loam_py.ros.composition import LocalLinks
from lego_loam_py.ros.conversions import (
    cloud_from_serialized,
    imu_sample_from_serialized,
    ns_to_stamp,
    odometry_from_serialized,
    serialized_stamp_ns,
    stamp_to_ns,
)
from lego_loam_py.ros.logging import NodeLogger
from lego_loam_py.ros.params import declare_params

__all__ = ['LegoLoamNode', 'release_memory', 'LARGE_MESSAGE_BYTES']

# A rejected message larger than this is followed by release_memory(): the allocator would otherwise keep its
# pages (glibc keeps freed blocks of up to 32 MB in the heap once it has seen one that size).
LARGE_MESSAGE_BYTES = 8 << 20

# rclpy's own endpoints of every node, left out of the matched counts on /diagnostics.
_HOUSEKEEPING_TOPICS = frozenset(('/parameter_events', '/rosout', '/diagnostics'))


_NUMBERS = re.compile(r'[0-9]+')
_QUOTED = re.compile(r"'[^']*'|\"[^\"]*\"")


class LegoLoamNode(Node):
    """Base node: declares all parameters (``self.params``) and keeps per-step timings.

    ``warn(key, text)`` logs at most once per ``period`` seconds per kind of warning and says how many
    similar warnings were suppressed meanwhile, so a stream of bad messages cannot flood the log.

    Every subscription and timer callback runs guarded: an exception it lets through is logged (throttled,
    with its traceback) and counted in ``counters['callback_errors']``, and the node keeps serving. A bug
    triggered by one message therefore costs that message, never the process or the map.

    Every ``DIAGNOSTICS_PERIOD`` seconds of wall time (whatever ``use_sim_time`` says) the node publishes its
    counters and timings on /diagnostics (diagnostic_msgs/DiagnosticArray, the ROS standard that
    rqt_robot_monitor and the diagnostic aggregator read): one status named after the node.
    """

    WARN_PERIOD = 10.0
    MAX_WARNING_KINDS = 256  # throttling state kept (oldest kinds forgotten first)
    MAX_VARIANTS_PER_KEY = 16  # distinct texts per key before the key alone decides the kind
    DIAGNOSTICS_PERIOD = 1.0  # [s] of wall time between two /diagnostics messages
    # With use_sim_time, take /clock only when the time is read (see _poll_clock_topic). A node whose timers run
    # on ROS time needs every tick as it comes, and sets this False.
    POLL_CLOCK = True

    def __init__(self, name: str, links: LocalLinks | None = None, **kwargs):
        # The process's linked topics when it runs several nodes (ros.composition), else None.
        self._links = links
        super().__init__(name, automatically_declare_parameters_from_overrides=True, **kwargs)
        self.params: Params = declare_params(self)
        self._warned: OrderedDict[str, tuple[float, int]] = OrderedDict()
        self._variants: dict[str, int] = {}
        self._warn_lock = threading.Lock()
        self.timings_ms: dict[str, deque] = {}
        self.measures: dict[str, deque] = {}
        self.counters: dict[str, int] = {}
        # CPU time of this node's callbacks [s]: in a process of several nodes, each one's share.
        self.callback_cpu_s = 0.0
        self._polled_node = None  # the companion node of create_polled_subscription
        self._release_pending = False  # a huge message was rejected: give its memory back
        self._last_problem = ''  # the latest warning or error: the watchdog's reason
        self._inputs_without_output = 0
        self.guard = StepGuard(self.params.reliability.reset_after_failures)  # (core.guard: the policy)
        # The thread of import_deferred (None: not started yet; False: nothing to import)
        self.deferred_imports: threading.Thread | bool | None = None
        self._imu_disagreement: str | None = None  # why the IMU is not used (its check found it misaligned)
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, '/diagnostics', qos.reliable(10))
        # Wall time: with use_sim_time and no /clock the ROS clock stands still, and so would the diagnostics.
        self.create_timer(
            self.DIAGNOSTICS_PERIOD, self.publish_diagnostics, clock=Clock(clock_type=ClockType.STEADY_TIME)
        )
        self._polled_clock = self._poll_clock_topic() if self.POLL_CLOCK else None

    def get_logger(self) -> NodeLogger:
        """The node's logger: rclpy's, without its source lookup on every call (see ros.logging)."""
        logger = self.__dict__.get('_node_logger')
        if logger is None:
            logger = self.__dict__['_node_logger'] = NodeLogger(super().get_logger())
        return logger

    # ------------------------------------------------------------------------------------------ the clock
    def _poll_clock_topic(self):
        """With use_sim_time, rclpy's time source wakes the node for every /clock tick (40 a second from a
        player, about 0.6 ms of CPU per scan) to keep a time these nodes read only now and then: every header
        they publish carries its input's stamp, and their timers run on wall time. The ticks wait in a polled
        subscription instead (depth 1: only the newest), and :meth:`get_clock` applies the newest before
        handing out the clock. Returns that subscription, or None (wall time, or a time source this rclpy
        does not lay out as expected: then it stays as rclpy made it)."""
        source = getattr(self, '_time_source', None)
        subscription = getattr(source, '_clock_sub', None)
        if subscription is None or not callable(getattr(source, 'clock_callback', None)):
            return None
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock as ClockMessage

        polled = self.create_polled_subscription(
            ClockMessage,
            subscription.topic_name,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT),
            raw=True,
        )
        self.destroy_subscription(subscription)
        source._clock_sub = None  # (use_sim_time set again later subscribes rclpy's way)
        return polled

    def get_clock(self):
        """The node's clock, with the newest /clock tick applied first when ticks are polled."""
        polled = getattr(self, '_polled_clock', None)  # (rclpy may ask before __init__ is through)
        if polled is not None and self._time_source.ros_time_is_active:
            newest = []
            self.drain(polled, newest.append, count=False)
            # A Clock message is a Time, laid out as a Header's stamp: the same reader applies.
            stamp_ns = serialized_stamp_ns(newest[-1]) if newest else None
            if stamp_ns is not None:
                from rosgraph_msgs.msg import Clock as ClockMessage

                self._time_source.clock_callback(ClockMessage(clock=ns_to_stamp(stamp_ns)))
        return super().get_clock()

    # ------------------------------------------------------------------------------------------ warm-up
    def import_deferred(self) -> threading.Thread | None:
        """Import on a thread of its own what the core imports only where it first uses it (its
        ``DEFERRED_IMPORTS``, e.g. gtsam for the pose graph: 0.1 s of CPU), once: called with the node's first
        input (a message on any of its subscriptions), so that a node waiting for data has not paid for it and the
        import overlaps what comes before the first use (a callback reaching it meanwhile waits for it, as it would
        have waited for its own import). The thread, or None when there is nothing to import."""
        if self.deferred_imports is not None:
            return None
        modules = tuple(getattr(getattr(self, 'core', None), 'DEFERRED_IMPORTS', ()))
        self.deferred_imports = False
        if not modules:
            return None

        def run() -> None:
            import importlib

            for module in modules:
                try:
                    importlib.import_module(module)
                except Exception:  # (the first use imports it again, and reports what fails there)
                    pass

        thread = self.deferred_imports = threading.Thread(target=run, name='deferred imports', daemon=True)
        thread.start()
        return thread

    # ---------------------------------------------------------------------------------- guarded callbacks
    def create_subscription(self, msg_type, topic, callback, qos_profile, **kwargs):
        """A subscription whose callback is guarded (see the class) and counts what it takes (``received
        <topic>``, on /diagnostics)."""
        key = f'received {topic}'

        def counted(*args):
            self.counters[key] = self.counters.get(key, 0) + 1
            if self.deferred_imports is None:  # (the first input)
                self.import_deferred()
            return callback(*args)

        counted.__signature__ = inspect.signature(callback)
        guarded = self._guarded(counted, f'message on {topic}')
        subscription = super().create_subscription(msg_type, topic, guarded, qos_profile, **kwargs)
        if self._links is not None:
            self._links.add_subscription(self, subscription.topic_name, subscription, guarded, subscription.qos_profile)
        return subscription

    def create_publisher(self, msg_type, topic, qos_profile, **kwargs):
        """rclpy's publisher; in a process of several nodes, one that hands its messages to the nodes here
        (ros.composition)."""
        publisher = super().create_publisher(msg_type, topic, qos_profile, **kwargs)
        if self._links is None:
            return publisher
        return self._links.add_publisher(publisher.topic_name, publisher, publisher.qos_profile)

    def create_timer(self, timer_period_sec, callback, *args, **kwargs):
        return super().create_timer(timer_period_sec, self._guarded(callback, 'timer'), *args, **kwargs)

    def _guarded(self, callback, what: str):
        """``callback`` wrapped so that an exception is logged and counted instead of ending the process.

        The wrapper takes as many arguments as the callback (rclpy passes the MessageInfo to callbacks that
        take two).
        """
        if callback is None:
            return None

        def call(*args):
            if self._release_pending:  # (the message that asked for it is gone by now: the executor held it)
                self._release_pending = False
                release_memory()
            started = time.thread_time()
            try:
                return callback(*args)
            except Exception:
                self.count('callback_errors')
                self.error(f'callback:{what}', f'unexpected error while handling a {what}; it was skipped')
            finally:
                self.callback_cpu_s += time.thread_time() - started
                if self._links is not None:  # what the callback published, for the nodes of this process
                    self._links.deliver()
            return None

        try:
            inspect.signature(callback).bind()
            return lambda: call()
        except TypeError:
            pass
        try:
            inspect.signature(callback).bind(object())
            return lambda msg: call(msg)
        except TypeError:
            return lambda msg, info: call(msg, info)

    def create_polled_subscription(self, msg_type, topic: str, qos_profile, raw: bool = False):
        """A subscription the executor never wakes up for: its messages wait in their DDS queue (``qos_profile``'s
        depth) until :meth:`drain` takes them.

        For inputs that are only needed when something else arrives: the IMU at 200 Hz, taken when a scan comes
        (a wake-up per sample cost more than the sample's processing). It lives on a companion node
        ``<name>_polled`` that no executor spins (same process, same DDS participant); the topic is resolved
        with this node's remappings.
        """
        if self._polled_node is None:
            import rclpy

            self._polled_node = rclpy.create_node(
                f'{self.get_name()}_polled',
                namespace=self.get_namespace(),
                context=self.context,
                use_global_arguments=False,
                enable_rosout=False,
                start_parameter_services=False,
            )
        subscription = self._polled_node.create_subscription(
            msg_type, self.resolve_topic_name(topic), lambda _: None, qos_profile, raw=raw
        )
        if self._links is not None:
            self._links.add_subscription(self, subscription.topic_name, subscription, None, subscription.qos_profile)
        return subscription

    def destroy_node(self):
        if self._polled_node is not None:
            self._polled_node.destroy_node()
            self._polled_node = None
        return super().destroy_node()

    def take_cloud(self, msg, dropped_counter: str, what: str, key: str):
        """``(True, cloud)`` for a PointCloud2, or for its bytes as the nodes' raw subscriptions take them (read
        by :func:`cloud_from_serialized`); ``(False, None)`` after counting ``dropped_counter`` and a throttled
        warning for bytes that are no cloud (see :meth:`take`)."""
        if not isinstance(msg, bytes):
            return True, msg
        return self.take(lambda: cloud_from_serialized(msg), dropped_counter, what, key, msg)

    def take_odometry(self, msg, dropped_counter: str, what: str, key: str):
        """``(True, odometry)`` for a nav_msgs/Odometry, or for its bytes as the nodes' raw subscriptions take them
        (read by :func:`odometry_from_serialized`); ``(False, None)`` after counting ``dropped_counter`` and a
        throttled warning for bytes that are no Odometry (see :meth:`take`)."""
        if not isinstance(msg, (bytes, bytearray)):
            return True, msg
        return self.take(lambda: odometry_from_serialized(msg), dropped_counter, what, key)

    def take_imu(self, msg, add) -> None:
        """One IMU sample handed to ``add`` (an ImuBuffer's ``add``): ``msg`` is a sensor_msgs/Imu, or its bytes as
        the nodes' polled raw subscriptions take them (:func:`imu_sample_from_serialized`); a sample the
        buffer rejects, or bytes that are no Imu, are dropped with a throttled warning (``imu_dropped``)."""
        try:
            sample = imu_sample_from_serialized(msg) if isinstance(msg, (bytes, bytearray)) else imu_sample(msg)
            reason = add(*sample)
        except (ValueError, TypeError, AttributeError) as exc:
            reason = f'unreadable message ({exc})'
        if reason is not None:
            self.count('imu_dropped')
            self.warn('imu', f'IMU message dropped: {reason}')

    def drain(self, subscription, callback, limit: int = 1000, with_info: bool = False, count: bool = True) -> int:
        """Hand every message waiting in ``subscription``'s queue to ``callback`` now (with its message info,
        ``with_info``); returns how many.

        For a polled subscription (see :meth:`create_polled_subscription`) this is the only way its messages are
        taken: before each scan, the IMU samples that came with it. At most ``limit`` messages, so a flood cannot
        stall the node.
        """
        if subscription is None:
            return 0
        local = self._links.queues.get(id(subscription)) if self._links is not None else None
        taken = 0
        while taken < limit:
            if local is not None:
                message = local.take()
            else:
                try:
                    with subscription.handle:
                        message = subscription.handle.take_message(subscription.msg_type, subscription.raw)
                except Exception:  # the subscription is being destroyed (shutdown)
                    break
            if message is None:
                break
            taken += 1
            if count:
                self.count(f'received {subscription.topic_name if local is None else local.topic}')
            try:
                callback(*(message if with_info else message[:1]))
            except Exception:
                self.count('callback_errors')
                self.error('drain', 'unexpected error while handling a queued message; it was skipped')
        return taken

    # ------------------------------------------------------------------------------------------- warnings
    def warn(self, key: str, text: str, period: float | None = None, level: str = 'warning') -> None:
        """Log ``text`` unless a warning of the same kind was logged less than ``period`` s ago.

        The kind is ``key`` plus the text with its numbers and quoted names masked, so different problems
        are each reported while a repeated one (same text but for sizes, stamps, frame ids and field names)
        is throttled. The state is bounded: a key with many different texts falls back to the key alone.
        """
        with self._warn_lock:  # mapOptimization warns from two executor threads
            if key != 'watchdog':
                self._last_problem = text
            self._warn(key, text, period, level)

    def _warn(self, key: str, text: str, period: float | None, level: str) -> None:
        masked = _QUOTED.sub('~', _NUMBERS.sub('#', text))[:120]
        kind = f'{key}:{masked}'
        if kind not in self._warned:
            variants = self._variants.get(key, 0)
            if variants >= self.MAX_VARIANTS_PER_KEY:
                kind = f'{key}:*'
            else:
                self._variants[key] = variants + 1
        now = time.monotonic()
        last, suppressed = self._warned.get(kind, (-float('inf'), 0))
        if now - last >= (self.WARN_PERIOD if period is None else period):
            extra = f' ({suppressed} similar warnings suppressed)' if suppressed else ''
            # (Two call sites: rclpy refuses one call site logging at two severities.)
            if level == 'error':
                self.get_logger().error(text + extra)
            else:
                self.get_logger().warning(text + extra)
            self._warned[kind] = (now, 0)
        else:
            self._warned[kind] = (last, suppressed + 1)
        self._warned.move_to_end(kind)
        while len(self._warned) > self.MAX_WARNING_KINDS:
            self._warned.popitem(last=False)

    def report_imu_alignment(self, event) -> None:
        """What the core's IMU check decided (a :class:`lego_loam_py.core.imu.monitor.AlignmentEvent`, or None):
        counted, warned about (throttled; the check itself repeats its advice only every 30 s of data), and while
        the IMU is not used the node's /diagnostics status is WARN with the reason."""
        if event is None:
            return
        self.count('imu_misaligned' if not event.trusted else 'imu_aligned_again')
        self._imu_disagreement = None if event.trusted else event.message
        if event.trusted:
            self.get_logger().info(event.message)
        else:
            self.warn('imu_alignment', event.message)

    def error(self, key: str, text: str) -> None:
        """Unexpected failure while handling a message: log with the traceback (throttled) and carry on."""
        self.warn(key, f'{text}: {traceback.format_exc(limit=6)}', level='error')

    # ------------------------------------------------------------------------------- self-healing state
    def state_reset(self, problem: str, what: str) -> None:
        """Log (one error per kind and second) and count a reset of poisoned state: ``problem`` is what the
        check found (core.guard.StepGuard), ``what`` says what was reset and what was kept."""
        self.count(STATE_RESETS)
        self.warn('state_reset', f'{problem}: {what}', period=1.0, level='error')

    def take(self, check, dropped_counter: str, what: str, key: str = 'bad_input', msg=None):
        """Run ``check()``, which returns the checked input or raises for a bad one (InputRejected,
        CloudLayoutError or another ValueError). Returns ``(True, value)``, or ``(False, None)`` after counting
        ``dropped_counter`` and one throttled warning '<what>: <reason>'; a rejected ``msg`` that was large gives
        its memory back."""
        try:
            return True, check()
        except (CloudLayoutError, ValueError) as exc:  # InputRejected is a ValueError
            self.count(dropped_counter)
            self.warn(key, f'{what}: {exc}')
            if msg is not None:
                self.reject_large(msg)
            return False, None

    def reject_large(self, msg) -> None:
        """A rejected message: when it was large, its memory goes back to the system at the next callback
        (the executor holds the message until this one returns)."""
        data = msg if isinstance(msg, bytes) else getattr(msg, 'data', None)
        if data is not None and len(data) > LARGE_MESSAGE_BYTES:
            self._release_pending = True

    # ------------------------------------------------------------------------------------------- watchdog
    def input_valid(self) -> None:
        """A valid input arrived; warns (throttled, with the latest problem) once ``reliability.watchdog_inputs``
        valid inputs in a row produced no output."""
        self._inputs_without_output += 1
        limit = self.params.reliability.watchdog_inputs
        if limit and self._inputs_without_output >= limit:
            if self._inputs_without_output == limit:
                self.count('silent_periods')
            self.warn('watchdog', self.watchdog_message())

    def output_published(self) -> None:
        self._inputs_without_output = 0

    def watchdog_message(self) -> str:
        reason = self._last_problem.splitlines()[0] if self._last_problem else 'no warning was logged'
        return f'{self._inputs_without_output} valid inputs in a row and no output; latest problem: {reason}'

    @property
    def silent(self) -> bool:
        """True while the watchdog counts more valid inputs without output than it allows."""
        limit = self.params.reliability.watchdog_inputs
        return bool(limit) and self._inputs_without_output >= limit

    def add_part(
        self, sync, name: str, msg, warn_tolerance: float | None = None, item=None, stamp_ns: int | None = None
    ) -> dict | None:
        """Give one message of a synchronised input set to ``sync`` (a StampSynchronizer), filed by its header
        stamp (``stamp_ns`` when given: a serialized message) as ``item`` (default: the message); returns the set
        once complete. Parts that lost their partners are counted as ``unmatched_inputs`` (and, with
        ``warn_tolerance`` [s], warned about)."""
        try:
            stamp = stamp_to_ns(msg.header.stamp) if stamp_ns is None else stamp_ns
            complete = sync.add(name, stamp, msg if item is None else item)
        except Exception:
            self.error('sync_exception', 'unexpected error while synchronising inputs')
            return None
        if sync.dropped:
            self.count('unmatched_inputs', sync.dropped)
            if warn_tolerance is not None:
                self.warn(
                    'unmatched',
                    f'{sync.dropped} input message(s) without matching partners within {warn_tolerance} s dropped',
                )
            sync.dropped = 0
        return complete

    def check_order(self, order, stamp_ns: int, item, stamp_of, noun: str, dropped_counter: str):
        """Apply ``order`` (a StampOrder) to an input with the warnings and counters the nodes share; returns
        the decision when something is to be processed ('process', 'jump' or 'reset': the caller resets),
        None when the input is dropped or held. ``stamp_of(item)`` [ns] names a discarded held input."""
        last = order.last_ns
        decision = order.check(stamp_ns, item)
        article = 'an' if noun[:1] in 'aeiou' else 'a'
        if decision.discarded:
            self.count(dropped_counter, len(decision.discarded))
            held = stamp_of(decision.discarded[0])
            self.warn(
                'glitch',
                f'{len(decision.discarded)} {noun}(s) stamped {(held - (last or held)) * 1e-9:+.1f} s '
                f'from the previous one dropped: the next {noun} continued the old timeline (wrong '
                'stamps)',
            )
        if decision.action == 'drop':
            self.count(dropped_counter)
            self.warn('order', f'{noun} dropped: {decision.reason} (stamp not newer than the previous {noun})')
            return None
        if decision.action == 'hold':  # a jump in time: the next inputs tell whether it is real
            self.count('held')
            self.warn(
                'hold',
                f'{article} {noun} stamped {(stamp_ns - (last or stamp_ns)) * 1e-9:+.1f} s from the '
                f'previous one is held: the next {noun}s tell whether time jumped',
            )
            return None
        if decision.action == 'jump':
            self.warn('jump', f'time jumped forward by {decision.jump_ns * 1e-9:.1f} s: carrying on', period=0.0)
            self.count('forward_jumps')
        if decision.action == 'resync':
            self.warn(
                'resync',
                f'{noun}s continue {-decision.jump_ns * 1e-9:.3f} s before the previous one: the '
                f'{noun}s ahead of them had wrong stamps; carrying on from these',
            )
            self.count('resyncs')
        return decision

    def count(self, name: str, amount: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + amount

    def record_time(self, name: str, seconds: float, keep: int = 10000) -> None:
        self.timings_ms.setdefault(name, deque(maxlen=keep)).append(seconds * 1e3)

    def record_value(self, name: str, value: float, keep: int = 10000) -> None:
        """A per-scan measure other than a duration (e.g. the odometry's condition), summarised like the
        timings in the statistics and on /diagnostics."""
        self.measures.setdefault(name, deque(maxlen=keep)).append(float(value))

    def timing_summary(self) -> str:
        parts = [
            f'{name}: median {t.median:.1f} ms, p95 {t.p95:.1f} ms (n={t.count})'
            for name, t in self.timing_stats().items()
        ]
        counters = ', '.join(f'{k}={v}' for k, v in sorted(self.counters.items()))
        return '; '.join(parts + ([counters] if counters else [])) or 'no data'

    def timing_stats(self) -> dict[str, TimingStats]:
        """Each timed stage's statistics over the recent calls [ms]."""
        return {name: TimingStats.of(values) for name, values in self.timings_ms.items() if values}

    def statistics(self) -> dict:
        """Counters and timing percentiles (ms) of this node, for tools and reports."""
        timings = {name: t.as_dict() for name, t in self.timing_stats().items()}
        measures = {name: TimingStats.of(values).as_dict() for name, values in self.measures.items() if values}
        return dict(
            node=self.get_name(),
            counters=dict(self.counters),
            timings_ms=timings,
            measures=measures,
            callback_cpu_s=round(self.callback_cpu_s, 4),
        )

    def diagnostic_status(self) -> DiagnosticStatus:
        """This node's status for /diagnostics: level, a one-line message, counters and timings as key-values."""
        values = [KeyValue(key=name, value=str(value)) for name, value in sorted(self.counters.items())]
        for name, t in self.timing_stats().items():
            values.append(KeyValue(key=f'{name}_median_ms', value=f'{t.median:.2f}'))
            values.append(KeyValue(key=f'{name}_p95_ms', value=f'{t.p95:.2f}'))
        for name, recent in self.measures.items():
            if recent:
                values.append(KeyValue(key=f'{name}_last', value=f'{recent[-1]:.4g}'))
                values.append(KeyValue(key=f'{name}_median', value=f'{TimingStats.of(recent).median:.4g}'))
        values.append(KeyValue(key='inputs_without_output', value=str(self._inputs_without_output)))
        values += [KeyValue(key=key, value=str(count)) for key, count in self.matched_endpoints().items()]
        if self.silent:
            level, message = DiagnosticStatus.WARN, self.watchdog_message()
        elif self._imu_disagreement is not None:
            level, message = DiagnosticStatus.WARN, self._imu_disagreement
        else:
            level, message = DiagnosticStatus.OK, 'running'
        return DiagnosticStatus(
            level=level, name=self.get_name(), message=message, hardware_id='lego_loam_py', values=values
        )

    def matched_endpoints(self) -> dict[str, int]:
        """How many remote endpoints DDS has matched with each of this node's topics: ``matched subscribers
        <topic>`` per publisher, ``matched publishers <topic>`` per subscription (polled ones included).

        A writer sends only to readers it has matched and a reliable reader takes only from writers it has
        matched, each side on its own time; a topic listed in the ROS graph is not yet a link. These counts say
        when it is one (an output nobody takes, an input nobody feeds), on /diagnostics.
        """
        matched = {}
        for publisher in self.publishers:
            if publisher.topic_name not in _HOUSEKEEPING_TOPICS:
                matched[f'matched subscribers {publisher.topic_name}'] = publisher.get_subscription_count()
        subscriptions = list(self.subscriptions)
        if self._polled_node is not None:
            subscriptions += list(self._polled_node.subscriptions)
        for subscription in subscriptions:
            if subscription.topic_name not in _HOUSEKEEPING_TOPICS:
                matched[f'matched publishers {subscription.topic_name}'] = subscription.get_publisher_count()
        return matched

    def publish_diagnostics(self) -> None:
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [self.diagnostic_status()]
        self._pub_diagnostics.publish(array)

    def on_shutdown(self) -> None:
        self.get_logger().info(f'{self.get_name()} statistics: {self.timing_summary()}')
        # Tools (the demo, benchmarks) collect the statistics of every node through this directory.
        directory = os.environ.get('LEGO_LOAM_PY_STATS_DIR')
        if directory:
            try:
                from lego_loam_py.formats import atomic_path

                with atomic_path(os.path.join(directory, f'{self.get_name()}.json'), suffix='.json') as path:
                    path.write_text(json.dumps(self.statistics(), indent=2))
            except OSError as exc:
                self.get_logger().warning(f'could not write statistics to {directory}: {exc}')
