"""The process-wide allocator settings of the nodes and offline mode (lego_loam_py.allocator)."""

from __future__ import annotations

import subprocess
import sys

_SCRIPT = """
import resource, sys
import numpy as np
from lego_loam_py.allocator import keep_heap_pages, release_memory
applied = keep_heap_pages() if sys.argv[1] == 'keep' else None
faults = []
for _ in range(4):   # a scan-sized block, freed and taken again as each scan does
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = np.ones(20 << 20, np.uint8)
    del block
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
release_memory()
print(applied, *faults)
"""


def _faults(mode: str) -> tuple[str, list[int]]:
    out = subprocess.run([sys.executable, '-c', _SCRIPT, mode], capture_output=True, text=True, check=True)
    applied, *faults = out.stdout.split()
    return applied, [int(f) for f in faults]


def test_freed_scan_sized_blocks_are_taken_again_without_page_faults():
    """With keep_heap_pages a 20 MB block freed and allocated again reuses the heap's pages: only the first
    allocation faults its pages in. (glibc's adaptive thresholds unmap such a block when it is freed the first
    time and fault it in again the second time, at some 5 us per page on a virtual machine.)"""
    applied, faults = _faults('keep')
    assert applied == 'True'
    assert faults[0] > 100  # the first time, the pages come in
    assert max(faults[1:]) < 50, faults  # then they are reused
