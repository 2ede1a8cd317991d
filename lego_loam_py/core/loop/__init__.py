"""Loop closure: candidates (Scan Context and radius), their verification by registration, and the original's method.

Its public API, each name from the module that defines it (imported on first use)."""

from __future__ import annotations

from lego_loam_py.core._exports import lazy_exports

_EXPORTS = {
    'LoopCandidate': 'closure',
    'LoopCloser': 'closure',
    'LoopResult': 'closure',
    'align_loop': 'closure',
    'find_loop_candidate': 'closure',
    'rotation_angle_deg': 'closure',
    'PlaceDatabase': 'place_recognition',
    'PlaceMatch': 'place_recognition',
    'ScanContextConfig': 'place_recognition',
    'descriptor_distance': 'place_recognition',
    'ring_key': 'place_recognition',
    'scan_context': 'place_recognition',
    'Registration': 'registration',
    'register': 'registration',
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
