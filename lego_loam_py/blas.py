"""BLAS threads of a lego_loam_py process: one, unless the user chose otherwise.

NumPy's OpenBLAS starts a thread per core when it is imported (60 ms of CPU per process here, a third of NumPy's
import), to split matrix products that are never large enough here to gain from it: the pipeline's products are
3x3 to 6x6 systems and (n, 3) point sets, and a node's other core is busy with the other nodes. One thread gives
the same results bit for bit (trajectories and maps checked) with less CPU.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ['one_blas_thread', 'blas_threads_for_run']


def one_blas_thread() -> None:
    """Ask for one OpenBLAS thread, before NumPy is imported (afterwards it changes nothing); a value the user set
    in the environment is kept."""
    os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')


@contextmanager
def blas_threads_for_run() -> Iterator[None]:
    """One BLAS thread for the length of a run in a process whose NumPy was imported before :func:`one_blas_thread`
    could act: a script or a notebook that imported NumPy first and then calls ``run_bag``. OpenBLAS keeps its
    thread per core there, and in each of the offline run's three processes those threads spin between the small
    products on the cores the other processes need (KITTI ran at 1.9x real time instead of 3.0x). The limit covers
    the BLAS libraries loaded when it is entered: import what the run uses first (scipy loads a BLAS of its own).
    The limits are lifted afterwards, for the caller's own work. Nothing is changed when OPENBLAS_NUM_THREADS is
    set: the user's choice, or this package's made before NumPy's import (the CLI, the nodes)."""
    if 'OPENBLAS_NUM_THREADS' in os.environ:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api='blas'):
        yield
