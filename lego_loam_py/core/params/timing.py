"""When a published pose is, from the parameters: the header stamp's instant in the sweep (``sensor.stamp_position``)
and the odometry model."""

from __future__ import annotations

__all__ = ['pose_delay']


def pose_delay(params) -> float:
    """[s] from a scan's header stamp to the instant of the pose published for it: the sweep's end with the
    original odometry model (its poses are the sweep end's), the stamp itself with the sweep-start model (its
    outputs are moved there, :class:`~lego_loam_py.core.odometry.sweep.StampInstant`)."""
    if params.feature_association.odometry_model == 'original':
        return (1.0 - params.sensor.stamp_position) * params.sensor.scan_period
    return 0.0
