"""Start-up and shutdown shared by every executable: rclpy init, clear parameter errors, clean exit."""
from __future__ import annotations

import sys
from typing import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node

from lego_loam_py.core.params import ParameterError

__all__ = ['run_node']


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None, threads: int = 1) -> int:
    """Create the node, spin until Ctrl-C / SIGTERM / shutdown, then run its ``on_shutdown`` hook.

    Returns the process exit code: 0 after a normal shutdown, 2 for invalid parameters.
    """
    rclpy.init(args=list(sys.argv if args is None else args))
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
            executor.spin()
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        finally:
            executor.shutdown(timeout_sec=1.0)
        return 0
    finally:
        if node is not None:
            hook = getattr(node, 'on_shutdown', None)
            if hook is not None:
                hook()
            node.destroy_node()
        rclpy.try_shutdown()
