"""float32 math with the C library's rounding, for bit-exact parity with the C++ original.

The original computes range-image columns, ground slopes and segmentation angles with libm's ``atan2f``.
Points whose azimuth lies exactly on a column boundary (the velodyne driver quantises azimuth to 0.01 deg,
so ~4 % of real VLP-16 points do) land in one column or the other depending on the last bit of that
function. :func:`atan2f` calls the system libm through a small C extension (``native/libm_compat.c``, built
with the package); without it, NumPy's float64 ``arctan2`` rounded to float32 is used, which differs from
libm on a few tenths of a percent of such boundary points (:data:`EXACT` tells which one is active).

libm's atan2f is slow: :mod:`lego_loam_py.core.parity.atan2f_decisions` decides on its values mostly without it.
:func:`float_degrees` and :func:`round_half_away` are the original's float degree conversion and C ``round``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import math

import numpy as np

__all__ = ['atan2f', 'sinf', 'cosf', 'EXACT', 'float_degrees', 'round_half_away']

try:
    from lego_loam_py.core import _libm_compat

    EXACT = True
except ImportError:  # the extension is optional: a build without a C compiler still works
    _libm_compat = None
    EXACT = False


def atan2f(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Element-wise ``atan2f(y, x)`` on float32 arrays [rad], as the C library computes it."""
    y32 = np.ascontiguousarray(y, dtype=np.float32)
    x32 = np.ascontiguousarray(x, dtype=np.float32)
    y32, x32 = np.broadcast_arrays(y32, x32)
    y32, x32 = np.ascontiguousarray(y32), np.ascontiguousarray(x32)
    if _libm_compat is None:
        return np.arctan2(y32.astype(np.float64), x32.astype(np.float64)).astype(np.float32)
    out = np.empty(y32.shape, dtype=np.float32)
    if out.size:
        _libm_compat.atan2f(y32.reshape(-1), x32.reshape(-1), out.reshape(-1))
    return out


@functools.lru_cache(maxsize=1)
def _libm():
    path = ctypes.util.find_library('m')
    if path is None:
        return None
    lib = ctypes.CDLL(path)
    for name in ('sinf', 'cosf'):
        getattr(lib, name).restype = ctypes.c_float
        getattr(lib, name).argtypes = [ctypes.c_float]
    return lib


def sinf(value: float) -> np.float32:
    """Scalar libm ``sinf`` (used for the original's per-scan constants)."""
    lib = _libm()
    return np.float32(lib.sinf(float(np.float32(value)))) if lib else np.float32(np.sin(np.float32(value)))


def cosf(value: float) -> np.float32:
    """Scalar libm ``cosf``."""
    lib = _libm()
    return np.float32(lib.cosf(float(np.float32(value)))) if lib else np.float32(np.cos(np.float32(value)))


def float_degrees(angle_rad: np.ndarray) -> np.ndarray:
    """``angle * 180 / M_PI`` as the original evaluates it on a float: float32 product, double division."""
    return ((angle_rad * np.float32(180.0)).astype(np.float64) / math.pi).astype(np.float32)


def round_half_away(value: np.ndarray) -> np.ndarray:
    """C ``round``: halves away from zero (NumPy rounds halves to even)."""
    # Rounding to nearest is symmetric, so this equals sign(v) * floor(|v| + 0.5) bit for bit, in 3 passes.
    return np.trunc(value + np.copysign(0.5, value))
