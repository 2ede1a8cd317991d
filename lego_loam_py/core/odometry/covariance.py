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

What that information cannot see, because no residual shows it, is added as three explicit terms
(:func:`unmodelled_covariance`, ``feature_association.covariance_*``), each an error of the deskewing that the
registration then absorbs into the motion: the sweep's path bent by a turn, its speed changing within the sweep,
and the stamps' jitter. docs/covariance.md gives the measurements behind each.
"""

from __future__ import annotations

import numpy as np

from lego_loam_py.core.frames import (
    compound_covariance,
    covariance_from_information,
    make_pose,
    pose_jacobian,
    rotation_log,
)
from lego_loam_py.core.odometry.sweep import sweep_rotation

__all__ = ['MAX_MOTION_VARIANCE', 'sweep_motion', 'motion_covariance', 'unmodelled_covariance', 'OdometryCovariance']

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
    the sweep was not registered, every direction at :data:`MAX_MOTION_VARIANCE`), its variances times ``scale``
    (the points' residuals are not independent), and the IMU rotation prior's (``prior_information`` [rad⁻²]),
    as it is: the prior's information is what the gyro's agreement with the mapping vouches for
    (core.imu.agreement), which owes nothing to how the points' residuals are correlated."""
    if information is None:
        return np.eye(6) * MAX_MOTION_VARIANCE
    total = information / scale + (0.0 if prior_information is None else prior_information)
    theta_covariance = covariance_from_information(total, MAX_MOTION_VARIANCE)
    jacobian = pose_jacobian(lambda x: sweep_motion(x, shift, rotation_after), theta)
    out = jacobian @ theta_covariance @ jacobian.T
    return 0.5 * (out + out.T)


def unmodelled_covariance(
    motion: np.ndarray,
    previous: np.ndarray | None,
    gyro: bool,
    period: float,
    turn: float,
    change: float,
    stamp_jitter: float,
) -> np.ndarray:
    """6x6 covariance (start-frame axes, isotropic per block) of what a sweep's registration cannot see: errors of
    the deskewing, which every point of the sweep shares, so that no residual shows them and the registration
    absorbs them into the motion. For the sweep's ``motion`` (4x4, translation ``t`` [m], rotation ``φ`` [rad]) after
    the sweep's ``previous`` motion (4x4; None: the first), each a standard deviation per axis:

    * ``turn * |t| |φ|`` [m]: the deskewing moves the sensor along a straight line in the start frame; a turn bends
      the path into an arc, off that line by ``|t| |φ| / 8`` mid-sweep and ``|t| |φ| / 2`` at the end;
    * ``change * |t - t_prev|`` [m] (and ``change * |φ - φ_prev|`` [rad] without a gyro): the deskewing assumes the
      sweep's motion constant; what it changed by since the last sweep (an acceleration times the period², a
      handheld sensor's bob) is how far that assumption was off;
    * ``stamp_jitter * |t| / period`` [m] and ``stamp_jitter * |φ| / period`` [rad]: a sweep stamped ``δt`` [s] off
      moves by the velocity times ``δt``.
    """
    translation, rotation = motion[:3, 3], rotation_log(motion[:3, :3])
    distance, angle = float(np.linalg.norm(translation)), float(np.linalg.norm(rotation))
    jitter = stamp_jitter / period
    position = (turn * distance * angle) ** 2 + (jitter * distance) ** 2
    attitude = (jitter * angle) ** 2
    if previous is not None:
        position += (change * float(np.linalg.norm(translation - previous[:3, 3]))) ** 2
        if not gyro:  # (with a gyro the deskewing turns as the gyro measured, whatever the rate did)
            attitude += (change * float(np.linalg.norm(rotation - rotation_log(previous[:3, :3])))) ** 2
    return np.diag([position] * 3 + [attitude] * 3)


class OdometryCovariance:
    """The covariance of the accumulated odometry pose (camera_init parent frame), zero where the odometry
    started (camera_init is that pose) and compounded with each sweep's motion."""

    def __init__(self):
        self.pose = np.zeros((6, 6))
        self.motion = np.eye(6) * MAX_MOTION_VARIANCE  # of the last sweep's motion
        self.last_motion: np.ndarray | None = None  # the last sweep's motion (4x4), None before the first

    def add(self, start_pose: np.ndarray, motion: np.ndarray, motion_covariance: np.ndarray) -> np.ndarray:
        """Compound the sweep's ``motion`` (4x4, with its covariance in the start frame's axes) onto the sweep's
        start pose ``start_pose`` (4x4 in camera_init); returns the end pose's covariance."""
        self.motion = motion_covariance
        self.last_motion = np.array(motion, dtype=float)
        self.pose = compound_covariance(start_pose, self.pose, motion, motion_covariance)
        return self.pose
