"""What reproduces the C++ original's float arithmetic bit for bit: libm's atan2f and the decisions it makes.

Its public API, each name from the module that defines it (imported on first use)."""

from __future__ import annotations

from lego_loam_py.core._exports import lazy_exports

_EXPORTS = {
    'Atan2fSteps': 'atan2f_decisions',
    'atan2f_exceeds': 'atan2f_decisions',
    'decide_on_atan2f': 'atan2f_decisions',
    'first_float32_where': 'atan2f_decisions',
    'EXACT': 'libm',
    'atan2f': 'libm',
    'cosf': 'libm',
    'float_degrees': 'libm',
    'round_half_away': 'libm',
    'sinf': 'libm',
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
