"""What every lego_loam_py node shares: typed parameters, throttled warnings, timing statistics."""
from __future__ import annotations

import json
import os
import re
import time
import traceback
from collections import deque

import numpy as np
from rclpy.node import Node

from lego_loam_py.core.params import Params
from lego_loam_py.ros.params import declare_params

__all__ = ['LegoLoamNode']


class LegoLoamNode(Node):
    """Base node: declares all parameters (``self.params``) and keeps per-step timings.

    ``warn(key, text)`` logs at most once per ``period`` seconds per key and says how many similar warnings
    were suppressed meanwhile, so a stream of bad messages cannot flood the log.
    """

    WARN_PERIOD = 10.0

    def __init__(self, name: str, **kwargs):
        super().__init__(name, automatically_declare_parameters_from_overrides=True, **kwargs)
        self.params: Params = declare_params(self)
        self._warned: dict[str, tuple[float, int]] = {}
        self.timings_ms: dict[str, deque] = {}
        self.counters: dict[str, int] = {}

    def warn(self, key: str, text: str, period: float | None = None) -> None:
        """Log ``text`` unless a warning of the same kind was logged less than ``period`` s ago.

        The kind is ``key`` plus the text with its numbers masked, so different problems are each reported
        while a repeated one (same text but for sizes and stamps) is throttled.
        """
        key = f'{key}:{re.sub(r"[0-9]+", "#", text)[:120]}'
        now = time.monotonic()
        last, suppressed = self._warned.get(key, (-float('inf'), 0))
        if now - last >= (self.WARN_PERIOD if period is None else period):
            extra = f' ({suppressed} similar warnings suppressed)' if suppressed else ''
            self.get_logger().warning(text + extra)
            self._warned[key] = (now, 0)
        else:
            self._warned[key] = (last, suppressed + 1)

    def error(self, key: str, text: str) -> None:
        """Unexpected failure while handling a message: log with the traceback (throttled) and carry on."""
        self.warn(key, f'{text}: {traceback.format_exc(limit=6)}')

    def count(self, name: str, amount: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + amount

    def record_time(self, name: str, seconds: float, keep: int = 10000) -> None:
        self.timings_ms.setdefault(name, deque(maxlen=keep)).append(seconds * 1e3)

    def timing_summary(self) -> str:
        parts = []
        for name, values in self.timings_ms.items():
            if values:
                v = np.asarray(values)
                parts.append(f'{name}: median {np.median(v):.1f} ms, p95 {np.percentile(v, 95):.1f} ms (n={len(v)})')
        counters = ', '.join(f'{k}={v}' for k, v in sorted(self.counters.items()))
        return '; '.join(parts + ([counters] if counters else [])) or 'no data'

    def statistics(self) -> dict:
        """Counters and timing percentiles (ms) of this node, for tools and reports."""
        timings = {}
        for name, values in self.timings_ms.items():
            if values:
                v = np.asarray(values)
                timings[name] = dict(median=float(np.median(v)), p95=float(np.percentile(v, 95)),
                                     mean=float(v.mean()), count=int(len(v)))
        return dict(node=self.get_name(), counters=dict(self.counters), timings_ms=timings)

    def on_shutdown(self) -> None:
        self.get_logger().info(f'{self.get_name()} statistics: {self.timing_summary()}')
        # Tools (the demo, benchmarks) collect the statistics of every node through this directory.
        directory = os.environ.get('LEGO_LOAM_PY_STATS_DIR')
        if directory:
            try:
                from lego_loam_py.core.io import atomic_path
                with atomic_path(os.path.join(directory, f'{self.get_name()}.json'), suffix='.json') as path:
                    path.write_text(json.dumps(self.statistics(), indent=2))
            except OSError as exc:
                self.get_logger().warning(f'could not write statistics to {directory}: {exc}')
