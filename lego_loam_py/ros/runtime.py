"""Start-up and shutdown shared by every executable: rclpy init, clear parameter errors, clean exit.

SIGINT and SIGTERM stop the executor while the ROS context is still valid, so a node's ``on_shutdown``
hook can still log, publish and save (mapOptimization writes its map there) before rclpy shuts down.
"""
from __future__ import annotations

import signal
import sys
import threading
import time
import traceback
from typing import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from lego_loam_py.core.params import ParameterError

__all__ = ['run_node']


def _log_executor_error(node: Node) -> None:
    error = getattr(node, 'error', None)
    if error is not None:
        node.count('executor_errors')
        error('executor', 'unexpected error in the executor; continuing')
    else:
        node.get_logger().error(f'unexpected error in the executor; continuing: {traceback.format_exc(limit=6)}')


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None, threads: int = 1) -> int:
    """Create the node, spin until Ctrl-C / SIGTERM, run its ``on_shutdown`` hook, shut down.

    Returns the process exit code: 0 after a normal shutdown, 2 for invalid parameters.
    """
    rclpy.init(args=list(sys.argv if args is None else args), signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    node = None
    try:
        try:
            node = factory()
        except ParameterError as exc:
            print(f'error: invalid parameters: {exc}', file=sys.stderr)
            return 2
        executor = MultiThreadedExecutor(num_threads=threads) if threads > 1 else SingleThreadedExecutor()
        executor.add_node(node)
        try:
            while not stop.is_set() and rclpy.ok():
                try:
                    executor.spin_once(timeout_sec=0.1)
                except (KeyboardInterrupt, ExternalShutdownException):
                    raise
                except Exception:
                    # Callbacks of LegoLoamNode are guarded; this is the last line of defence (an error in the
                    # executor or in taking a message): log it, keep serving, never spin hot on it.
                    _log_executor_error(node)
                    time.sleep(0.01)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        finally:
            executor.shutdown(timeout_sec=1.0)
        return 0
    finally:
        if node is not None:
            hook = getattr(node, 'on_shutdown', None)
            try:
                if hook is not None:
                    hook()
            finally:
                node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
