"""The viewer: a run shown live in Rerun, or saved as a ``.rrd`` recording to open later.

Everything is logged in the ``map`` frame (REP-103 axes: x forward, y left, z up), on the ``scan`` timeline (one
step per scan, its index) and the ``stamp`` timeline (the scan's stamp):

============================  ==========================================================================
entity                        what
============================  ==========================================================================
``world/lidar``               the sensor's fused pose (/integrated_to_init) at the scan
``world/lidar/scan``          the scan by imageProjection's label: ground, segmented, outlier
``world/lidar/features``      featureAssociation's corner (sharp) and surface (flat) points
``world/map/NNNN``            the map, in pieces as keyframes add to it, one point per 0.4 m voxel
``world/trajectory/*``        odometry, mapped (/aft_mapped_to_init), fused, ground truth (when known)
``world/keyframes``           keyframe positions; ``world/loops``: accepted loop closures as lines
``timings/*``, ``health/*``   per-scan ms of each stage; odometry and mapping condition counters
============================  ==========================================================================

:class:`~lego_loam_py.viewer.scene.SceneLog` does the logging (no ROS, no pipeline); the offline run feeds it the
pipeline's events (:class:`~lego_loam_py.viewer.pipeline_view.PipelineView`), ``lego_loam_py viewer`` the
running nodes' topics (:mod:`lego_loam_py.ros.viewer_node`). ``rerun-sdk`` is optional: without it the rest of
lego_loam_py works, and asking for the viewer says what to install.
"""

from __future__ import annotations

from lego_loam_py.errors import UsageError

__all__ = ['ViewerUnavailable', 'require_rerun']


class ViewerUnavailable(UsageError):
    """The viewer was asked for but rerun-sdk is not installed."""


def require_rerun():
    """The ``rerun`` module, or ViewerUnavailable saying how to get it."""
    try:
        import rerun
    except ImportError:
        raise ViewerUnavailable(
            'the viewer needs rerun-sdk (pip install rerun-sdk==0.41.0, or bash install.sh)'
        ) from None
    return rerun
