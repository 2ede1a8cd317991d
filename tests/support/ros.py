"""Helpers for tests that talk DDS from the pytest process."""
from __future__ import annotations

import time
from typing import Callable

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


def wait_for_line(proc, text: str, timeout: float = 20.0) -> str:
    """Read the child's stdout until a line containing ``text``; raise with its stderr otherwise."""
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
            return line
    err = proc.stderr.read() if proc.poll() is not None else ''
    raise AssertionError(f'{text!r} not seen; stdout={"".join(lines)!r} stderr={err!r}')


__all__ = ['spin_until', 'wait_for_line', 'rclpy']
