"""Exact decisions on libm's float32 ``atan2f`` [rad], mostly without computing it.

The original decides range-image columns, ground pairs and segmentation joins by comparing libm's atan2f
with fixed angles; matching it bit for bit needs the same float32 angle wherever the comparison is close.
libm's atan2f costs ~35 ns a value and NumPy's float64 arctan2 ~30 ns: the largest cost of a scan when every
pixel pair takes one. Here the angle is computed only where a comparison is close:

* :func:`decide_on_atan2f`: any monotone decision, from a float64 angle bracketed by its error;
* :func:`atan2f_exceeds`: comparisons with a few fixed angles, from the sign of a cross product;
* :class:`Atan2fSteps`: which step of a fixed staircase of angles (range-image columns), from a guessed
  step confirmed by two cross products.

The last two rest on one fact: for an exact angle A of (x, y), y cos(phi) - x sin(phi) = |(x, y)| sin(A - phi)
is positive where A exceeds phi (when |A - phi| < pi). A threshold t is tested at phi = t +- (|t| 2**-19 +
2**-22): past those, libm's value, within 2 ulp of A, lies on the same side of t as A. cos(phi) and sin(phi)
in float32 turn phi by < 2**-24 rad, inside that margin, and the float32 cross product is trusted only where
it exceeds its rounding bound, 2**-21 (|y| + |x|) + 2**-120. Elements nearer a threshold call libm.
"""

from __future__ import annotations

import math

import numpy as np

from lego_loam_py.core.parity import libm
from lego_loam_py.core.parity.libm import atan2f

__all__ = ['decide_on_atan2f', 'atan2f_exceeds', 'exceeding_tests', 'Atan2fSteps', 'first_float32_where']

_F32 = np.float32
_HALF_TURN_SLACK = 2.0**-10  # [rad] tested angles stay this far inside a half turn


def decide_on_atan2f(y: np.ndarray, x: np.ndarray, decide) -> np.ndarray:
    """``decide(atan2f(y, x))`` for float32 ``y``, ``x`` and an element-wise ``decide`` that is monotone in
    the angle, calling libm's atan2f only where the result depends on the angle's last bits.

    float64 arctan2 is within ~1e-16 of the exact angle and libm's atan2f within 2 ulp of it, so the libm
    value lies within |angle| * 2**-19 (>= 16 ulp; the constant term covers subnormal angles) of the rounded
    float64 angle. Where ``decide`` agrees at both ends of that bracket it agrees on the libm value too (NaN
    inputs give NaN at both ends and in libm alike).
    """
    with np.errstate(invalid='ignore'):
        angle = np.arctan2(y, x, dtype=np.float64).astype(_F32)
        margin = np.abs(angle)
        margin *= _F32(2.0**-19)
        margin += _F32(2.0**-140)
        result = decide(angle - margin)
        unsure = result != decide(angle + margin)
    if unsure.any():
        result[unsure] = decide(atan2f(y[unsure], x[unsure]))
    return result


def _margin(threshold):
    """[rad] beyond which the exact angle puts libm's float32 value on its side of ``threshold`` (float64)."""
    return np.abs(threshold) * 2.0**-19 + 2.0**-22


def _rounding_bound(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Bound on the float32 rounding of y cos(phi) - x sin(phi): 2**-21 (|y| + |x|) + 2**-120."""
    bound = np.abs(y)
    bound += np.abs(x)
    bound *= _F32(2.0**-21)
    bound += _F32(2.0**-120)
    return bound


def exceeding_tests(threshold: float, angle_range: tuple[float, float]) -> tuple[float, float] | None:
    """The two angles [rad] just below and above the float32 ``threshold`` at which :func:`atan2f_exceeds` tests
    the sign of a cross product, or None where ``angle_range`` puts one of them a half turn from an end of the
    range (every element then takes libm's angle)."""
    t = float(_F32(threshold))
    test = (t - _margin(t), t + _margin(t))
    low, high = angle_range
    if any(max(abs(phi - low), abs(high - phi)) >= math.pi - _HALF_TURN_SLACK for phi in test):
        return None
    return test


def atan2f_exceeds(y: np.ndarray, x: np.ndarray, thresholds, angle_range: tuple[float, float]) -> list[np.ndarray]:
    """``[atan2f(y, x) > t for t in thresholds]`` (libm's angle; False where y or x is NaN) for float32 arrays
    ``y``, ``x`` that are finite or NaN and float32 ``thresholds`` [rad].

    ``angle_range`` bounds atan2(y, x) as the caller knows it from the signs of its inputs: (0, pi) for
    y >= 0, (-pi/2, pi/2) for x >= 0. The cross-product sign says which side of a tested angle the exact angle
    lies on only within a half turn of it: where a tested angle lies a half turn (less 2**-10 rad) or more
    from an end of ``angle_range``, every element calls libm.
    """
    y = np.asarray(y, dtype=_F32)
    x = np.asarray(x, dtype=_F32)
    thresholds = [_F32(t) for t in thresholds]
    tests = [exceeding_tests(t, angle_range) for t in thresholds]
    if any(test is None for test in tests):
        angle = atan2f(y, x)
        return [angle > t for t in thresholds]
    with np.errstate(invalid='ignore', over='ignore'):
        bound = _rounding_bound(y, x)
        negative_bound = -bound
        side = np.empty_like(y)
        other = np.empty_like(y)

        def left_of(phi: float) -> np.ndarray:
            """y cos(phi) - x sin(phi) in float32: > 0 where the angle exceeds phi (up to the rounding)."""
            np.multiply(y, _F32(math.cos(phi)), out=side)
            np.multiply(x, _F32(math.sin(phi)), out=other)
            return np.subtract(side, other, out=side)

        results, unsure = [], None
        for lower, upper in tests:
            above = left_of(upper) > bound
            # "not >= -bound" rather than "< -bound": NaN (no angle) is never above, as in libm.
            not_above = ~(left_of(lower) >= negative_bound)
            undecided = ~(above | not_above)
            unsure = undecided if unsure is None else unsure | undecided
            results.append(above)
    if unsure is not None and unsure.any():
        angle = atan2f(y[unsure], x[unsure])
        for result, t in zip(results, thresholds):
            result[unsure] = angle > t
    return results


class Atan2fSteps:
    """How many of some fixed angles libm's atan2f(y, x) reaches: a staircase of the angle, such as the
    range-image column, mostly without computing angles.

    ``thresholds``: ascending float32 angles t_1 <= ... <= t_m [rad]. Step j holds the float32 angles a with
    t_j <= a < t_(j+1), i.e. (t_j - 1 ulp, t_(j+1) - 1 ulp]. :meth:`count` guesses each element's step from a
    pseudo-angle, y / (|x| + |y|) on each side of the y axis, looked up in a table of ``bins`` bins, and
    confirms it where the exact angle lies in the step's wedge shrunk by the margins (two cross products, see
    the module docstring). The first and last steps, which touch +-pi where the wedge would wrap around,
    steps narrower than their margins and steps wider than a half turn are never confirmed.
    """

    def __init__(self, thresholds: np.ndarray, bins: int = 32768):
        t = np.asarray(thresholds, dtype=_F32)
        below_t = np.nextafter(t, _F32(-np.inf)).astype(np.float64)
        lower = np.concatenate([[-np.inf], below_t])  # step j: lower[j] < a <= upper[j]
        upper = np.concatenate([below_t, [np.inf]])
        with np.errstate(invalid='ignore'):
            phi_low = lower + _margin(lower)
            phi_high = upper - _margin(upper)
            # Two half planes meet in the wedge between their edges only if it is narrower than a half turn.
            width = phi_high - phi_low
            usable = (
                (phi_low > -math.pi + _HALF_TURN_SLACK)
                & (phi_high < math.pi - _HALF_TURN_SLACK)
                & (width > 2.0**-21)
                & (width < math.pi - _HALF_TURN_SLACK)
            )
            # Unusable steps get NaN directions: their cross products are NaN and never confirm.
            phi_low[~usable] = np.nan
            phi_high[~usable] = np.nan
            self._low_cos, self._low_sin, self._high_cos, self._high_sin = (
                f(phi).astype(_F32) for phi in (phi_low, phi_high) for f in (np.cos, np.sin)
            )
        # The guess: the step of each bin's centre. An element's position is (y / (|x| + |y|) + 1) with the sign
        # of x, in [-2, 0] for x < 0 and [0, 2] for x >= 0, and its bin index (position + 2) * bins / 4.
        self._scale = bins / 4.0
        position = (np.arange(bins) + 0.5) / self._scale - 2.0
        pseudo = np.abs(position) - 1.0  # y / (|x| + |y|) at the centres
        across = np.where(position < 0, -1.0, 1.0) * (1.0 - np.abs(pseudo))
        self._guess = np.searchsorted(t.astype(np.float64), np.arctan2(pseudo, across), side='right').astype(np.int64)

    def count(self, y: np.ndarray, x: np.ndarray, native: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(number of thresholds that libm's atan2f(y, x) reaches, where that number is confirmed) for finite
        float32 arrays; unconfirmed elements hold a guess. In one C pass when the extension is built and the arrays
        are contiguous (the same values); ``native=False``: NumPy's passes (the tests compare the two)."""
        kernels = libm._libm_compat
        if (
            native
            and hasattr(kernels, 'atan2f_steps')
            and all(isinstance(a, np.ndarray) and a.dtype == _F32 and a.flags.c_contiguous for a in (y, x))
            and y.shape == x.shape
        ):
            step, confirmed = np.empty(y.shape, dtype=np.int64), np.empty(y.shape, dtype=bool)
            kernels.atan2f_steps(
                y.reshape(-1),
                x.reshape(-1),
                self._guess,
                self._low_cos,
                self._low_sin,
                self._high_cos,
                self._high_sin,
                self._scale,
                step.reshape(-1),
                confirmed.reshape(-1),
            )
            return step, confirmed
        with np.errstate(invalid='ignore', divide='ignore', over='ignore'):
            length = np.abs(x)
            length += np.abs(y)  # |x| + |y|
            position = np.divide(y, length)  # in [-1, 1]; NaN at the origin
            position += _F32(1.0)
            np.copysign(position, x, out=position)
            position += _F32(2.0)
            position *= _F32(self._scale)
            # fmin: the top end into the last bin and NaN (the origin) into it too: only the guess suffers.
            np.fmin(position, _F32(len(self._guess) - 1), out=position)
            step = np.take(self._guess, position.astype(np.intp))
            bound = length
            bound *= _F32(2.0**-21)
            bound += _F32(2.0**-120)
            side = y * np.take(self._low_cos, step)
            side -= x * np.take(self._low_sin, step)
            confirmed = side > bound
            np.multiply(y, np.take(self._high_cos, step), out=side)
            side -= x * np.take(self._high_sin, step)
            np.negative(bound, out=bound)
            confirmed &= side < bound
        return step, confirmed


def _order_key(value: np.ndarray) -> np.ndarray:
    """int64 keys in the order of float32 values (-0 and +0 share 0)."""
    bits = np.asarray(value, dtype=_F32).view(np.int32).astype(np.int64)
    return np.where(bits >= 0, bits, -(bits & 0x7FFFFFFF))


def _from_order_key(key: np.ndarray) -> np.ndarray:
    return np.where(key >= 0, key, -key - 2**31).astype(np.int32).view(_F32)


def first_float32_where(predicate, low: float, high: float, count: int = 1) -> np.ndarray:
    """Element i: the smallest float32 v in [low, high] with ``predicate(values)[i]`` true, +inf where none.

    ``predicate`` maps ``count`` float32 candidates to ``count`` booleans, element i testing its own condition,
    which must be false then true as the value grows (a bisection over float32 values, all i at once).
    """
    lo = np.full(count, _order_key(np.array([low]))[0])
    hi = np.full(count, _order_key(np.array([high]))[0])
    never = ~np.asarray(predicate(_from_order_key(hi)), dtype=bool)
    while (searching := lo < hi).any():
        middle = (lo + hi) // 2
        true = np.asarray(predicate(_from_order_key(middle)), dtype=bool)
        hi = np.where(searching & true, middle, hi)
        lo = np.where(searching & ~true, middle + 1, lo)
    out = _from_order_key(lo).copy()
    out[never] = np.inf
    return out
