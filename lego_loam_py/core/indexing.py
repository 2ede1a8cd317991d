"""Vectorised index ranges (the windows that the original walks point by point, as flat index arrays) and row
selection.

The ranges serve the feature selection (the regions of a ring) and the correspondence search (the windows around
a nearest neighbour), so neither needs a Python loop over points. :func:`select_rows` selects rows of a cloud as
indexing does, at the speed of ``np.take`` and ``np.compress``.
"""

from __future__ import annotations

import numpy as np

__all__ = ['ranges', 'ragged', 'select_rows']


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
