"""Does the IMU turn as the lidar does? The rotation and clock offset that map the IMU's rotations onto the
lidar's, their uncertainty, and whether the motion lets one tell at all.

One estimator for both users: featureAssociation's and mapOptimization's online check
(:mod:`lego_loam_py.core.imu.monitor`) and ``lego_loam_py calibrate`` (:mod:`lego_loam_py.calibration`).

The model (the hand-eye problem for rotations): over an interval ``[a, b]`` of the lidar clock the lidar turns
by ``dR_L`` (from lidar-only odometry) and the IMU by ``dR_I``, measured over ``[a + offset, b + offset]`` of
its own stamps. An IMU fixed to the lidar with the rotation ``R`` (``R_lidar_imu``) sees the same turn in its own
axes, ``dR_L = R dR_I R^T``, so the rotation vectors obey ``phi_L = R phi_I`` exactly, whatever the size of the
turn. For each candidate offset the best ``R`` is the orthogonal Procrustes (Kabsch) solution over all
intervals; the offset minimises what is left (a grid, then a parabola through the best three).

Uncertainty: the residuals' spread per lidar axis is the noise (the lidar's yaw increments are noisier than its
roll and pitch); the covariance of the four parameters is the least-squares sandwich ``(J^T J)^-1 J^T S J
(J^T J)^-1`` (``S`` that per-axis noise), which assumes independent intervals. The rotation about an axis is
only as good as the turning about the two others: with yaw alone (a car on a flat road) the rotation about the
vertical stays unknown, which :attr:`AlignmentFit.rotation_sigma_deg` shows.

Units: rotation vectors [rad], times and offsets [s], reported angles [deg]. Axes: the lidar's (REP-103).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.frames import (
    matrix_to_rpy,
    quaternion_products,
    quaternions_to_vectors,
    rotation_vector,
    vectors_to_quaternions,
)

__all__ = [
    'AlignmentFit',
    'GyroTrack',
    'OrientationTrack',
    'best_rotation',
    'fit_alignment',
    'shifted_increments',
    'axis_name',
    'nearest_right_angle_rotation',
]

# The offsets tried first [s] (then refined between grid points).
DEFAULT_OFFSETS = np.round(np.arange(-0.1, 0.1 + 1e-9, 0.004), 6)


def best_rotation(lidar: np.ndarray, imu: np.ndarray) -> np.ndarray:
    """The rotation ``R`` minimising ``sum |lidar_k - R imu_k|^2`` over (..., n, 3) vectors (Kabsch; a proper
    rotation, never a reflection); (..., 3, 3), one for each leading index."""
    covariance = np.einsum('...ni,...nj->...ij', imu, lidar)
    u, _, vt = np.linalg.svd(covariance)
    v = np.swapaxes(vt, -1, -2)
    sign = np.where(np.linalg.det(v @ np.swapaxes(u, -1, -2)) < 0, -1.0, 1.0)
    v[..., :, 2] *= sign[..., None]
    return v @ np.swapaxes(u, -1, -2)


def shifted_increments(
    increments: np.ndarray, rate_start: np.ndarray, rate_end: np.ndarray, offsets: np.ndarray
) -> np.ndarray:
    """(m, n, 3) rotation vectors of n IMU increments (unit quaternions x, y, z, w, (n, 4)) moved each of m
    ``offsets`` [s] later at both ends, to first order in the offset: ``exp(-w_a offset) dR exp(w_b offset)`` with
    the body rates (n, 3) [rad/s] at the interval's ends (enough for the online check; the calibration shifts
    exactly). In NumPy (core.frames' stacks), so that a node's IMU check needs no scipy.spatial."""
    offsets = np.atleast_1d(np.asarray(offsets, dtype=float))
    increments = np.asarray(increments, dtype=float)
    m, n = len(offsets), len(increments)
    start = vectors_to_quaternions(-offsets[:, None, None] * rate_start[None])
    end = vectors_to_quaternions(offsets[:, None, None] * rate_end[None])
    return quaternions_to_vectors(quaternion_products(quaternion_products(start, increments[None]), end)).reshape(
        m, n, 3
    )


class OrientationTrack:
    """An attitude track (``times`` [s], increasing; (n, 4) quaternions x, y, z, w), interpolated (slerp) at any
    time inside it: the turns between two times, for :func:`fit_alignment`."""

    def __init__(self, times: np.ndarray, quaternions: np.ndarray):
        from scipy.spatial.transform import Rotation, Slerp

        times = np.asarray(times, dtype=float)
        keep = np.concatenate(([True], np.diff(times) > 0))  # (a repeated stamp says nothing new)
        self.times = times[keep]
        self._slerp = Slerp(self.times, Rotation.from_quat(np.asarray(quaternions, dtype=float)[keep]))

    def increments(self, start: np.ndarray, end: np.ndarray, offsets) -> np.ndarray:
        """(m, n, 3) rotation vectors of the turn from ``start + offset`` to ``end + offset`` [s] for each of m
        ``offsets``, in the body frame at the start."""
        offsets = np.atleast_1d(np.asarray(offsets, dtype=float))
        a = self._slerp((np.asarray(start)[None, :] + offsets[:, None]).ravel())
        b = self._slerp((np.asarray(end)[None, :] + offsets[:, None]).ravel())
        return (a.inv() * b).as_rotvec().reshape(len(offsets), len(start), 3)


class GyroTrack(OrientationTrack):
    """The attitude the gyro alone gives: its body rates [rad/s] integrated from the first sample (each step turns
    by the mean of its two rates), on the IMU's own clock. The products of the steps are formed by doubling (log2
    of the length in vectorised compositions), not one by one."""

    def __init__(self, times: np.ndarray, rates: np.ndarray):
        from scipy.spatial.transform import Rotation

        times, rates = np.asarray(times, dtype=float), np.asarray(rates, dtype=float)
        keep = np.concatenate(([True], np.diff(times) > 0))
        times, rates = times[keep], rates[keep]
        steps = Rotation.from_rotvec(0.5 * (rates[1:] + rates[:-1]) * np.diff(times)[:, None])
        attitude = Rotation.concatenate([Rotation.identity(), steps])
        span = 1
        while span < len(attitude):  # each entry becomes the product of the 2 * span steps ending there
            attitude = Rotation.concatenate([attitude[:span], attitude[:-span] * attitude[span:]])
            span *= 2
        super().__init__(times, attitude.as_quat())


def axis_name(axis: np.ndarray) -> str:
    """'x', '-z', ... for a unit vector along a lidar axis, else its components."""
    k = int(np.argmax(np.abs(axis)))
    if abs(axis[k]) > 0.95:
        return ('' if axis[k] > 0 else '-') + 'xyz'[k]
    return '(' + ', '.join(f'{v:.2f}' for v in axis) + ')'


@dataclass
class AlignmentFit:
    """The IMU's rotation and clock against the lidar's, from ``intervals`` interval pairs.

    ``rotation`` maps the IMU's rotation vectors (as the IMU buffer gives them, with the configured mounting
    applied) onto the lidar's: the mounting the parameters miss, ``R_lidar_imu(true) = rotation @
    R_lidar_imu(configured)``. ``offset`` [s] is the clock offset they miss, in the sense of ``imu.time_offset``.
    """

    rotation: np.ndarray  # (3, 3)
    offset: float  # [s]
    intervals: int
    rms_before_deg: float  # residual per interval with the configured mounting [deg]
    rms_after_deg: float  # ... with the fitted rotation and offset [deg]
    noise_deg: np.ndarray  # (3,) residual spread per lidar axis after the fit [deg]
    rotation_sigma_deg: np.ndarray  # (3,) 1-sigma of the rotation about its principal axes, weakest last [deg]
    rotation_axes: np.ndarray  # (3, 3) those principal axes (rows, lidar axes)
    rotation_covariance: np.ndarray  # (3, 3) of the rotation vector of ``rotation`` [rad^2]
    offset_sigma: float  # 1-sigma of the offset [s]
    offset_at_edge: bool  # the best offset lies at the end of the range searched

    @property
    def angle_deg(self) -> float:
        """How far the fitted rotation is from the configured mounting [deg]."""
        return float(np.degrees(np.linalg.norm(rotation_vector(self.rotation))))

    @property
    def rpy_deg(self) -> np.ndarray:
        return matrix_to_rpy(self.rotation)

    @property
    def rotation_significance(self) -> float:
        """How many standard deviations the fitted rotation lies from none (Mahalanobis distance)."""
        vector = rotation_vector(self.rotation)
        try:
            return float(math.sqrt(max(0.0, vector @ np.linalg.solve(self.rotation_covariance, vector))))
        except np.linalg.LinAlgError:
            return 0.0

    @property
    def explained_deg(self) -> float:
        """How much of the disagreement per interval the fitted rotation and offset explain [deg, RMS]."""
        return math.sqrt(max(0.0, self.rms_before_deg**2 - self.rms_after_deg**2))

    @property
    def explained(self) -> float:
        """Share of the squared disagreement the fitted rotation and offset explain (0..1)."""
        before = self.rms_before_deg**2
        return 0.0 if before == 0 else max(0.0, 1.0 - self.rms_after_deg**2 / before)


def fit_alignment(
    lidar: np.ndarray, imu_at: Callable[[np.ndarray], np.ndarray], offsets: np.ndarray = DEFAULT_OFFSETS
) -> AlignmentFit:
    """The rotation and clock offset best mapping the IMU's rotation increments onto the lidar's.

    ``lidar``: (n, 3) rotation vectors of the lidar's turn over n intervals [rad, lidar axes]; ``imu_at(offsets)``:
    (m, n, 3) rotation vectors of the IMU's turn over the same intervals moved each of m ``offsets`` [s] later on
    its clock. ``offsets``: the grid searched [s] (only 0.0: no offset fitted).
    """
    lidar = np.asarray(lidar, dtype=float)
    n = len(lidar)
    offsets = np.asarray(offsets, dtype=float)
    fitted_offset = len(offsets) > 1

    def solve(trial: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(costs (m,), rotations (m, 3, 3), IMU vectors (m, n, 3)) for m offsets."""
        imu = imu_at(trial)
        rotations = best_rotation(lidar[None], imu)
        costs = np.square(lidar[None] - np.einsum('mij,mnj->mni', rotations, imu)).sum(axis=(1, 2))
        return costs, rotations, imu

    costs = solve(offsets)[0]
    best = int(np.argmin(costs))
    offset = float(offsets[best])
    at_edge = fitted_offset and best in (0, len(offsets) - 1)
    if len(offsets) >= 3 and not at_edge:  # parabola through the best grid point and its neighbours
        c0, c1, c2 = costs[best - 1 : best + 2]
        curvature = c0 - 2 * c1 + c2
        if curvature > 0:
            step = offsets[best + 1] - offsets[best]
            offset += float(np.clip(0.5 * (c0 - c2) / curvature, -1.0, 1.0)) * step
    h = 1e-3  # for the offset's derivative
    trial = np.array([offset, 0.0] + ([offset - h, offset + h] if fitted_offset else []))
    cost, rotations, imu = solve(trial)
    rotation, residual = rotations[0], lidar - imu[0] @ rotations[0].T
    before = float(np.square(lidar - imu[1]).sum())  # the configured mounting: no rotation, no offset
    noise = np.sqrt(np.square(residual).sum(0) / max(1, n - 2))  # per lidar axis
    # Jacobian of the residuals: [R phi]x for a rotation exp(eps) R (eps about the lidar axes) and the offset's.
    columns = 4 if fitted_offset else 3
    jacobian = np.zeros((n, 3, columns))
    jacobian[:, :, :3] = _skew(imu[0] @ rotation.T)
    if fitted_offset:
        jacobian[:, :, 3] = -(imu[3] - imu[2]) @ rotation.T / (2 * h)
    j = jacobian.reshape(3 * n, columns)
    try:
        inverse = np.linalg.inv(j.T @ j)
        covariance = inverse @ (j.T * np.tile(np.square(noise), n)) @ j @ inverse
    except np.linalg.LinAlgError:
        covariance = np.full((columns, columns), np.inf)
    if np.isfinite(covariance).all():
        eigenvalues, eigenvectors = np.linalg.eigh(covariance[:3, :3])  # ascending: the weakest axis last
    else:  # (no turn at all)
        covariance = np.diag(np.full(columns, np.inf))
        eigenvalues, eigenvectors = np.full(3, np.inf), np.eye(3)
    return AlignmentFit(
        rotation=rotation,
        offset=offset,
        intervals=n,
        rms_before_deg=math.degrees(math.sqrt(before / max(1, n))),
        rms_after_deg=math.degrees(math.sqrt(float(cost[0]) / max(1, n))),
        noise_deg=np.degrees(noise),
        rotation_sigma_deg=np.degrees(np.sqrt(np.maximum(eigenvalues, 0.0))),
        rotation_axes=eigenvectors.T,
        rotation_covariance=covariance[:3, :3],
        offset_sigma=float(math.sqrt(max(covariance[3, 3], 0.0))) if fitted_offset else 0.0,
        offset_at_edge=at_edge,
    )


def _skew(v: np.ndarray) -> np.ndarray:
    """(n, 3, 3) matrices ``[v]x`` (``[v]x w = v x w``)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def nearest_right_angle_rotation(rotation: np.ndarray, tolerance_deg: float = 10.0) -> np.ndarray | None:
    """The rotation among the 24 that map axes onto axes (IMUs are mostly mounted so) within ``tolerance_deg``
    of ``rotation``, or None."""
    rounded = np.round(np.asarray(rotation))
    if (
        not (np.abs(rounded).sum(axis=0) == 1).all()
        or not (np.abs(rounded).sum(axis=1) == 1).all()
        or np.linalg.det(rounded) < 0.5
    ):
        return None
    angle = np.degrees(np.linalg.norm(rotation_vector(rounded.T @ rotation)))
    return rounded if angle <= tolerance_deg else None
