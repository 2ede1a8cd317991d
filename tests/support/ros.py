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


__all__ = ['spin_until', 'read_until', 'wait_for_line', 'rclpy']
