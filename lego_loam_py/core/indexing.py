"""Vectorised index ranges (the windows that the original walks point by point, as flat index arrays) and row
selection.

The ranges serve the feature selection (the regions of a ring) and the correspondence search (the windows around
a nearest neighbour), so neither needs a Python loop over points. :func:`select_rows` selects rows of a cloud as
indexing does, at the speed of ``np.take`` and ``np.compress``; :func:`copy_columns` and :func:`xyz_columns` copy a
cloud's coordinates between arrays of different widths a column at a time.
"""

from __future__ import annotations

import numpy as np

__all__ = ['ranges', 'ragged', 'select_rows', 'copy_columns', 'xyz_columns']


def ranges(lo: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """The integers of the ranges [lo, lo + length), back to back (lengths >= 0)."""
    return np.arange(int(lengths.sum())) + np.repeat(lo - (np.cumsum(lengths) - lengths), lengths)


def ragged(lo: np.ndarray, hi: np.ndarray):
    """(owner, position) of every integer in the half-open windows [lo, hi)."""
    lengths = np.maximum(hi - lo, 0)
    return np.repeat(np.arange(len(lo)), lengths), ranges(lo, lengths)


def select_rows(array: np.ndarray, which: np.ndarray) -> np.ndarray:
    """``array[which]`` for a boolean mask or integer indices along the first axis: a new array of the same values.

    NumPy 2.4's indexing of a 2-D array by an index array or a mask runs an iterator per row, several times slower
    than ``np.take`` and ``np.compress`` on the rows of a cloud (about 10 ns against 1 ns a row of four float32)."""
    which = np.asarray(which)
    if which.dtype == np.bool_:
        if which.shape != array.shape[:1]:  # (np.compress would take a shorter mask as False beyond its end)
            raise IndexError(f'a mask of {which.shape} for {array.shape[0]} rows')
        return np.compress(which, array, axis=0)
    return np.take(array, which, axis=0)


def copy_columns(out: np.ndarray, source: np.ndarray, columns: tuple[int, ...] = (0, 1, 2)) -> np.ndarray:
    """``out[:, :k] = source[:, columns]`` (k = len(columns)), cast as that assignment casts; returns ``out``.

    NumPy 2.4 copies a block of a few columns into rows of another width (the x, y, z of (n, 4) points) a row at a
    time, some five times slower than the columns one by one (95 against 20 us for 20 000 points)."""
    for target, column in enumerate(columns):
        out[:, target] = source[:, column]
    return out


def xyz_columns(points: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    """``points[:, :3].astype(dtype)``: the (n, 3) coordinates of (n, >= 3) points as a new C-ordered array, copied a
    column at a time (see :func:`copy_columns`)."""
    return copy_columns(np.empty((len(points), 3), dtype=dtype), points)
