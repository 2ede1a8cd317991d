"""How well the IMU's turns have agreed with the lidar's: the gyro's bias, and how much to trust the rest.

featureAssociation registers each sweep with the rotation the IMU measured since the last one held by a prior
(``feature_association.imu_rotation_prior``): a good gyro is finer over 0.1 s than the lidar, a consumer module's
bias (1-3 mrad/s: 0.01-0.02 deg a sweep, 0.1-0.2 deg/s) is not. mapOptimization's poses come back on
/aft_mapped_to_init: from one to the next the lidar turned by ``L`` (its scan-to-map registration, which the prior
barely touches), the gyro by ``G`` (its attitude, :class:`~lego_loam_py.core.imu.gyro.GyroAttitude`, less the
bias taken off then). Their difference ``rotvec(L^T G)`` is the bias over the interval plus the noise of both:

* **bias**: over the last :data:`WINDOW` seconds, the differences (with the bias then applied added back) over the
  time they span, least squares, outliers (beyond :data:`OUTLIER_SIGMAS` robust deviations, a struggling mapping
  step) left out; taken once :data:`MIN_SPAN` seconds of intervals agree;
* **trust**: what is left, per sweep (``sigma`` [rad], the intervals' residuals scaled to a sweep's length as a
  random walk), is the IMU's error and the mapping's own together: a sound gyro agrees with the mapped poses to
  0.02-0.06 deg a sweep on a car and 0.14-0.16 deg on a walking sensor (the simulated drives, consumer module
  included), where the lidar's own turns are the noisier. Up to :data:`FULL_TRUST` the prior keeps its weight
  (``feature_association.imu_rotation_prior``); beyond, the IMU disagrees more than any mapping explains (a scale
  error, a mounting the check let through) and the weight falls as ``(FULL_TRUST / sigma)^2``.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from lego_loam_py.core.frames import rotation_vector

__all__ = ['ImuAgreement', 'WINDOW', 'MIN_SPAN', 'FULL_TRUST']

WINDOW = 30.0  # [s] of intervals the estimates come from
MIN_SPAN = 5.0  # [s] of intervals before they are taken
OUTLIER_SIGMAS = 4.0
FULL_TRUST = math.radians(0.2)  # [rad] a sweep's disagreement up to which the prior keeps its whole weight


class ImuAgreement:
    """See the module docstring. ``scan_period`` [s] is a sweep's length."""

    def __init__(self, scan_period: float = 0.1):
        self.scan_period = float(scan_period)
        self.bias = np.zeros(3)  # [rad/s] lidar axes: the gyro's, as found (0 until then)
        self.sigma: float | None = None  # [rad] the IMU's turn error per sweep left after the bias
        self._states: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}  # stamp -> (time, attitude, bias)
        self._previous: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._intervals: deque[tuple[float, float, np.ndarray]] = deque()  # (end time, length, bias x length + e)

    def keep(self, stamp_ns: int, time: float, attitude: np.ndarray) -> None:
        """The IMU's attitude of the lidar (3x3, lidar axes) at the pose time ``time`` [s] of the scan stamped
        ``stamp_ns``, until that scan's mapped pose comes back."""
        self._states[stamp_ns] = (time, attitude, self.bias.copy())
        while len(self._states) > 200:
            del self._states[next(iter(self._states))]

    def mapped(self, stamp_ns: int, rotation: np.ndarray) -> None:
        """mapOptimization's pose of the scan stamped ``stamp_ns`` (its rotation, 3x3, lidar axes)."""
        state = self._states.pop(stamp_ns, None)
        if state is None:
            return
        time, attitude, bias = state
        previous, self._previous = self._previous, (time, rotation, attitude, bias)
        if previous is None or not 0.0 < time - previous[0] < 2.0:
            return
        length = time - previous[0]
        lidar_turn = previous[1].T @ rotation
        imu_turn = previous[2].T @ attitude
        difference = rotation_vector(lidar_turn.T @ imu_turn)
        # What the gyro's whole bias turned over the interval: the difference, and what was taken off then.
        self._intervals.append((time, length, difference + 0.5 * (bias + previous[3]) * length))
        while self._intervals and self._intervals[0][0] < time - WINDOW:
            self._intervals.popleft()
        self._estimate()

    def _estimate(self) -> None:
        lengths = np.array([i[1] for i in self._intervals])
        if lengths.sum() < MIN_SPAN:
            return
        turns = np.array([i[2] for i in self._intervals])
        keep = np.ones(len(lengths), dtype=bool)
        for _ in range(2):  # least squares of turn = bias x length, then without the outliers
            bias = (turns[keep] * lengths[keep, None]).sum(axis=0) / (lengths[keep] ** 2).sum()
            residual = np.linalg.norm(turns - bias[None, :] * lengths[:, None], axis=1)
            scale = 1.4826 * float(np.median(residual[keep])) + 1e-9
            keep = residual <= OUTLIER_SIGMAS * scale
        self.bias = bias
        residual = turns[keep] - bias[None, :] * lengths[keep, None]
        per_second = float((residual**2).sum() / lengths[keep].sum())  # a random walk's variance per second
        self.sigma = math.sqrt(per_second * self.scan_period)

    def prior_weight(self, largest: float) -> float:
        """The weight of the IMU's rotation prior: ``largest`` (the parameter) until the agreement is known."""
        if self.sigma is None or self.sigma <= FULL_TRUST:
            return largest
        return largest * (FULL_TRUST / self.sigma) ** 2
