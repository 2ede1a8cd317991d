"""Localization in a saved map: the prior map, tracking, and global relocalization (a mapper like mapOptimization).

Its public API, each name from the module that defines it (imported on first use)."""

from __future__ import annotations

from lego_loam_py.core._exports import lazy_exports

_EXPORTS = {
    'HINT_ATTEMPTS': 'localizer',
    'Localization': 'localizer',
    'LocalizationEvent': 'localizer',
    'LocalizationStatus': 'localizer',
    'STATES': 'localizer',
    'LocalMap': 'prior_map',
    'PriorMap': 'prior_map',
    'heading': 'prior_map',
    'levelling': 'prior_map',
    'Attempt': 'relocalization',
    'Hint': 'relocalization',
    'Relocalizer': 'relocalization',
    'Verification': 'relocalization',
    'scan_points_lidar': 'relocalization',
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
