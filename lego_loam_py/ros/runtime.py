"""Start-up and shutdown shared by every executable: rclpy init, clear parameter errors, clean exit.

SIGINT and SIGTERM stop the executor while the ROS context is still valid, so a node's ``on_shutdown``
hook can still log, publish and save (mapOptimization writes its map there) before rclpy shuts down.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from lego_loam_py.allocator import keep_heap_pages
from lego_loam_py.errors import LegoLoamError, UsageError

__all__ = ['run_node', 'run_nodes', 'teardown_guard', 'finish_within', 'stuck_teardowns']

TEARDOWN_TIMEOUT_S = 5.0


def _force_exit(code: int, what: str) -> None:
    print(
        f'warning: {what} did not finish within {TEARDOWN_TIMEOUT_S:g} s (the DDS library is stuck); exiting '
        f'anyway: everything was saved before it',
        file=sys.stderr,
        flush=True,
    )
    os._exit(code)


def teardown_guard(code: int, what: str = 'the ROS 2 shutdown') -> threading.Timer:
    """A timer that ends the process with ``code`` unless cancelled within ``TEARDOWN_TIMEOUT_S`` seconds.

    Start it once the process's work is done (maps and statistics written), just before destroying its ROS
    entities, and cancel it afterwards. Fast DDS 3.2.3, the version of the Kilted wheels, can deadlock its
    event and receive threads when a remote writer goes away while a heartbeat response is being handled
    (eProsima/Fast-DDS#6502 and relatives); deleting an entity then waits forever. Without the guard the
    process would hang at Ctrl-C and be killed by whoever stops it, as a failure.
    """
    timer = threading.Timer(TEARDOWN_TIMEOUT_S, _force_exit, args=(code, what))
    timer.daemon = True
    timer.start()
    return timer


def _log_executor_error(node: Node) -> None:
    error = getattr(node, 'error', None)
    if error is not None:
        node.count('executor_errors')
        error('executor', 'unexpected error in the executor; continuing')
    else:
        node.get_logger().error(f'unexpected error in the executor; continuing: {traceback.format_exc(limit=6)}')


_STUCK: list[str] = []


def finish_within(teardown: Callable[[], None], what: str, timeout: float = TEARDOWN_TIMEOUT_S) -> bool:
    """Run ``teardown`` (destroying ROS entities) on a daemon thread and wait at most ``timeout`` seconds.

    For a process that still has work to do after its ROS part ends (the launch supervisor prints its
    summary): a teardown stuck in the DDS library (see :func:`teardown_guard`) is left behind with a
    warning and remembered, so that the process can end with ``os._exit`` (:func:`stuck_teardowns`)
    instead of hanging at interpreter exit. Returns whether the teardown finished.
    """
    done = threading.Event()
    failure: list[BaseException] = []

    def run() -> None:
        try:
            teardown()
        except BaseException as exc:  # reported below, in the caller's thread
            failure.append(exc)
        finally:
            done.set()

    threading.Thread(target=run, name=f'teardown: {what}', daemon=True).start()
    if not done.wait(timeout):
        _STUCK.append(what)
        print(
            f'warning: {what} did not finish within {timeout:g} s (the DDS library is stuck); carrying on',
            file=sys.stderr,
            flush=True,
        )
        return False
    if failure:
        raise failure[0]
    return True


def stuck_teardowns() -> list[str]:
    """The teardowns :func:`finish_within` gave up on in this process."""
    return list(_STUCK)


EXECUTOR_VARIABLE = 'LEGO_LOAM_PY_EXECUTOR'  # events (default where rclpy has it) | single


def make_executor():
    """The executor a node spins in, and a ``spin_once(timeout_s)`` for it.

    rclpy's EventsExecutor (C++, rclpy.experimental) by default: rclpy's Python executors rebuild their wait set
    and walk every entity in Python for each message, which cost a node more CPU than its algorithm (a third of
    imageProjection's time, four fifths of transformFusion's). ``LEGO_LOAM_PY_EXECUTOR=single`` selects the
    SingleThreadedExecutor (for comparison, or where rclpy has no EventsExecutor: ROS 2 before Kilted).
    Callbacks of an EventsExecutor take the message only (no message info).
    """
    choice = os.environ.get(EXECUTOR_VARIABLE, 'events')
    if choice == 'events':
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:
            choice = 'single'
        else:
            executor = EventsExecutor()
            return executor, lambda timeout_s: executor.spin_once(timeout_s)
    if choice != 'single':
        raise UsageError(f'{EXECUTOR_VARIABLE} must be events or single, got {choice!r}')
    executor = SingleThreadedExecutor()
    return executor, lambda timeout_s: executor.spin_once(timeout_sec=timeout_s)


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Create the node, spin until Ctrl-C / SIGTERM, run its ``on_shutdown`` hook, shut down.

    Returns the process exit code: 0 after a normal shutdown, 2 for invalid parameters.
    """
    return run_nodes([factory], args, links=False)


def run_nodes(factories: Sequence[Callable[..., Node]], args: Sequence[str] | None = None, links: bool = True) -> int:
    """:func:`run_node` for several nodes in one process and one executor, created in the order given and shut down
    in the reverse order. With ``links``, each factory is called with ``links=`` a
    :class:`~lego_loam_py.ros.composition.LocalLinks`, and the topics from one of these nodes to another are
    handed over in memory (see :mod:`lego_loam_py.ros.composition`)."""
    keep_heap_pages()  # freed scan-sized blocks stay in the heap instead of being faulted in again each scan
    try:
        rclpy.init(args=list(sys.argv if args is None else args), signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # rcl's RCLError: arguments it cannot parse (e.g. '-p name:=' without a value)
        reason = str(exc).split(', at ')[0].replace('Error: error not set', '').strip().rstrip('.')
        print(f'error: {reason} (an empty string is written name:="\'\'")', file=sys.stderr)
        return UsageError.exit_code
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    nodes: list[Node] = []
    code = 0
    try:
        try:
            executor, spin_once = make_executor()
            if links:
                from lego_loam_py.ros.composition import LocalLinks

                local = LocalLinks()
                nodes.extend(factory(links=local) for factory in factories)
                linked = local.link()
                nodes[0].get_logger().info(
                    f'{len(nodes)} nodes in this process; handed over in memory: {", ".join(linked) or "nothing"}'
                )
            else:
                nodes.extend(factory() for factory in factories)
        except LegoLoamError as exc:  # an unknown LEGO_LOAM_PY_EXECUTOR, invalid parameters
            print(f'error: {exc}', file=sys.stderr)
            code = exc.exit_code
            return code
        for node in nodes:
            executor.add_node(node)
        try:
            while not stop.is_set() and rclpy.ok():
                try:
                    spin_once(0.1)
                except (KeyboardInterrupt, ExternalShutdownException):
                    raise
                except Exception:
                    # Callbacks of LegoLoamNode are guarded; this is the last line of defence (an error in the
                    # executor or in taking a message): log it, keep serving, never spin hot on it.
                    _log_executor_error(nodes[0])
                    time.sleep(0.01)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        finally:
            executor.shutdown(1.0)
        return code
    finally:
        try:
            for node in reversed(nodes):  # (each node saves what it has, whatever another one's hook did)
                hook = getattr(node, 'on_shutdown', None)
                try:
                    if hook is not None:
                        hook()
                except Exception:
                    if len(nodes) == 1:
                        raise
                    traceback.print_exc()
        finally:
            names = ', '.join(node.get_name() for node in nodes) or 'node'
            guard = teardown_guard(code, f'{names} shutdown')
            for node in reversed(nodes):
                node.destroy_node()
            rclpy.try_shutdown()
            guard.cancel()
            for sig, handler in previous.items():
                signal.signal(sig, handler)
