"""Messages seen by a test or a benchmark: their header stamp, and a copy stamped at another time."""

from __future__ import annotations

import copy

from lego_loam_py.ros.conversions import ns_to_stamp, stamp_to_ns

__all__ = ['stamp_of', 'restamped']


def stamp_of(msg) -> int:
    """The header stamp of ``msg`` [ns]."""
    return stamp_to_ns(msg.header.stamp)


def restamped(msg, stamp_ns: int):
    """A copy of ``msg`` with another header stamp [ns] (messages are shared between tests: never mutate them)."""
    out = copy.copy(msg)
    out.header = copy.copy(msg.header)
    out.header.stamp = ns_to_stamp(stamp_ns)
    return out
