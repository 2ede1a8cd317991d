"""How a lego_loam_py process asks glibc's allocator for memory (a no-op where the C library is not glibc).

A scan allocates and frees arrays of a few hundred kilobytes to a few megabytes. By default glibc serves blocks
above its mmap threshold (128 kB, raised on the fly up to the largest block freed) with fresh ``mmap`` pages and
gives freed memory at the top of the heap back once it exceeds twice that threshold, so the same pages were
unmapped and faulted in again scan after scan: about 690 page faults per scan in featureAssociation (campus,
with IMU) and half as many in mapOptimization, some 2 ms of featureAssociation's system time per scan on this
virtual machine. :func:`keep_heap_pages` fixes both thresholds instead, so that freed blocks stay in the heap for
the next scan (no faults at all once warm); the extra user-space work this costs is 0.3 % of the instructions
(callgrind: memory taken from the heap instead of fresh zeroed pages). :func:`release_memory` still hands the
memory back after a huge rejected message.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc

__all__ = ['keep_heap_pages', 'release_memory', 'MMAP_THRESHOLD', 'TRIM_THRESHOLD']

MMAP_THRESHOLD = 32 << 20  # blocks below this come from the heap (glibc's own upper bound for its adaptive one)
TRIM_THRESHOLD = 64 << 20  # free memory at the top of the heap kept for reuse before it is returned
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameters (malloc.h)


def _libc():
    try:
        return ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6')
    except OSError:
        return None


def keep_heap_pages() -> bool:
    """Fix glibc's mmap and trim thresholds (see the module docstring) for this process; True when applied."""
    libc = _libc()
    try:
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
            libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
        )
    except AttributeError:  # no C library found, or one without mallopt
        return False


def release_memory() -> None:
    """Give the memory freed by a huge rejected message back to the operating system (glibc's malloc_trim;
    a no-op where it does not exist)."""
    gc.collect()
    libc = _libc()
    try:
        libc.malloc_trim(0)
    except AttributeError:
        pass
