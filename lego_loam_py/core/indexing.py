"""Vectorised index ranges: the windows that the original walks point by point, as flat index arrays.

Used by the feature selection (the regions of a ring) and the correspondence search (the windows around a
nearest neighbour), so neither needs a Python loop over points.
"""

from __future__ import annotations

import numpy as np

__all__ = ['ranges', 'ragged']


def ranges(lo: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """The integers of the ranges [lo, lo + length), back to back (lengths >= 0)."""
    return np.arange(int(lengths.sum())) + np.repeat(lo - (np.cumsum(lengths) - lengths), lengths)


def ragged(lo: np.ndarray, hi: np.ndarray):
    """(owner, position) of every integer in the half-open windows [lo, hi)."""
    lengths = np.maximum(hi - lo, 0)
    return np.repeat(np.arange(len(lo)), lengths), ranges(lo, lengths)
