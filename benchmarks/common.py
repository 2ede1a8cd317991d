"""Small helpers shared by the benchmark scripts."""
from __future__ import annotations

import time
from typing import Callable

import numpy as np


def time_ms(function: Callable[[], object], repeat: int = 200, warmup: int = 10) -> np.ndarray:
    """Wall time of each call [ms]."""
    for _ in range(warmup):
        function()
    out = np.empty(repeat)
    for i in range(repeat):
        start = time.perf_counter()
        function()
        out[i] = (time.perf_counter() - start) * 1e3
    return out


def summary(name: str, samples_ms: np.ndarray) -> str:
    return (f'{name:<44s} median {np.median(samples_ms):8.3f} ms   p95 {np.percentile(samples_ms, 95):8.3f} ms   '
            f'(n={len(samples_ms)})')
