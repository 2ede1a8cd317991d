"""BLAS threads of a lego_loam_py process: one, unless the user chose otherwise.

NumPy's OpenBLAS starts a thread per core when it is imported (60 ms of CPU per process here, a third of NumPy's
import), to split matrix products that are never large enough here to gain from it: the pipeline's products are
3x3 to 6x6 systems and (n, 3) point sets, and a node's other core is busy with the other nodes. One thread gives
the same results bit for bit (trajectories and maps checked) with less CPU.
"""

from __future__ import annotations

import os

__all__ = ['one_blas_thread']


def one_blas_thread() -> None:
    """Ask for one OpenBLAS thread, before NumPy is imported (afterwards it changes nothing); a value the user set
    in the environment is kept."""
    os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
