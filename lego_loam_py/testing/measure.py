"""What a process costs, read from /proc (psutil is not a dependency): the tests and the benchmarks use it."""

from __future__ import annotations

from pathlib import Path

__all__ = ['rss_mb']


def rss_mb(pid: int) -> float:
    """Resident memory of a process [MB]; NaN when it is gone."""
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float('nan')
