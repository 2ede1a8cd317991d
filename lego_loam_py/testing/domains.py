"""Machine-wide unique ROS_DOMAIN_IDs for concurrent test runs, leased with file locks."""

from __future__ import annotations

import fcntl
import os
import random
import tempfile
from pathlib import Path

LOCK_DIR = Path(tempfile.gettempdir()) / 'lego_loam_py_domains'
DOMAIN_IDS = range(1, 101)  # Fast DDS port arithmetic is safe for 0..101 on Linux


class DomainLease:
    """Context manager yielding a domain id that no other lease holds while it is open."""

    def __init__(self):
        self._file = None

    def __enter__(self) -> int:
        LOCK_DIR.mkdir(parents=True, exist_ok=True)
        candidates = list(DOMAIN_IDS)
        random.Random(os.getpid()).shuffle(candidates)
        for domain_id in candidates:
            handle = open(LOCK_DIR / f'{domain_id}.lock', 'w')
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.close()
                continue
            self._file = handle
            return domain_id
        raise RuntimeError('no free ROS_DOMAIN_ID: 100 concurrent test runs?')

    def __exit__(self, *exc) -> None:
        if self._file is not None:
            fcntl.flock(self._file, fcntl.LOCK_UN)
            self._file.close()
            self._file = None
