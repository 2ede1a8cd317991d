"""The covariance of featureAssociation's odometry: of each sweep's motion, from the registration's information at
convergence, and of the accumulated pose (/laser_odom_to_init), compounded along the chain.

Conventions: :mod:`lego_loam_py.core.frames` (pose covariance): a pose's covariance is of its error in the parent
frame, position in the parent's axes [m²] and rotation as a small rotation vector about the parent's axes [rad²],
in ROS's order (x, y, z, rot x, rot y, rot z). The accumulated pose's parent is camera_init (LOAM camera axes);
a sweep motion's parent is the previous sweep start.

The registration (:mod:`lego_loam_py.core.odometry.laser_odometry`) gives the Fisher information of the six-vector
``θ`` (:attr:`OdometryStats.information`: both stages' residuals, the surface stage's (ty, rx, rz) and the corner
stage's (tx, tz, ry), each differentiated with respect to all six parameters, each with the residual variance its
own weighted residuals give). Its inverse, times ``feature_association.covariance_scale`` (why a scale:
:class:`~lego_loam_py.core.params.types.FeatureAssociationParams`), is the covariance of ``θ``; the motion's is
that mapped through the derivative of ``θ -> motion``.
"""

from __future__ import annotations

import numpy as np

from lego_loam_py.core.frames import compound_covariance, covariance_from_information, make_pose, pose_jacobian
from lego_loam_py.core.odometry.sweep import sweep_rotation

__all__ = ['MAX_MOTION_VARIANCE', 'sweep_motion', 'motion_covariance', 'OdometryCovariance']

# A sweep's motion is never less certain than this [m², rad²] per direction: a direction no correspondence holds
# (a degenerate one) keeps the constant-velocity prediction, whose error over one sweep is well below a metre or
# a radian.
MAX_MOTION_VARIANCE = 1.0


def sweep_motion(theta: np.ndarray, shift: np.ndarray | None = None, rotation_after: np.ndarray | None = None):
    """4x4 pose of a sweep's end in its start frame for the six-vector ``θ`` (:mod:`~lego_loam_py.core.odometry.sweep`
    conventions): ``T(θ)^-1`` = ``[R(θ)ᵀ, -R(θ)ᵀ (t - shift)]``, its rotation followed by ``rotation_after`` (the
    IMU's share of the turn, which the registration did not estimate)."""
    rotation = sweep_rotation(*theta[:3]).T
    translation = np.asarray(theta[3:], dtype=float) - (0.0 if shift is None else np.asarray(shift, dtype=float))
    after = np.eye(3) if rotation_after is None else rotation_after
    return make_pose(rotation @ after, -rotation @ translation)


def motion_covariance(
    theta: np.ndarray,
    information: np.ndarray | None,
    shift: np.ndarray | None = None,
    rotation_after: np.ndarray | None = None,
    scale: float = 1.0,
    prior_information: np.ndarray | None = None,
) -> np.ndarray:
    """6x6 covariance of :func:`sweep_motion` (start-frame axes) from the information of ``θ``: the points' (None:
    the sweep was not registered, every direction at :data:`MAX_MOTION_VARIANCE`) and the IMU rotation prior's
    (``prior_information``), the variances times ``scale``: the registration weighs the prior against the points'
    residuals in one cost, and what that cost's curvature overstates it overstates for both."""
    if information is None:
        return np.eye(6) * MAX_MOTION_VARIANCE
    total = (information + (0.0 if prior_information is None else prior_information)) / scale
    theta_covariance = covariance_from_information(total, MAX_MOTION_VARIANCE)
    jacobian = pose_jacobian(lambda x: sweep_motion(x, shift, rotation_after), theta)
    out = jacobian @ theta_covariance @ jacobian.T
    return 0.5 * (out + out.T)


class OdometryCovariance:
    """The covariance of the accumulated odometry pose (camera_init parent frame), zero where the odometry
    started (camera_init is that pose) and compounded with each sweep's motion."""

    def __init__(self):
        self.pose = np.zeros((6, 6))
        self.motion = np.eye(6) * MAX_MOTION_VARIANCE  # of the last sweep's motion

    def add(self, start_pose: np.ndarray, motion: np.ndarray, motion_covariance: np.ndarray) -> np.ndarray:
        """Compound the sweep's ``motion`` (4x4, with its covariance in the start frame's axes) onto the sweep's
        start pose ``start_pose`` (4x4 in camera_init); returns the end pose's covariance."""
        self.motion = motion_covariance
        self.pose = compound_covariance(start_pose, self.pose, motion, motion_covariance)
        return self.pose
