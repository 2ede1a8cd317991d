"""The keyframe pose graph of mapOptimization (docs/original.md §6.3): a gtsam iSAM2 over the
keyframe poses, with a prior on the first, a between factor from each keyframe to the next and the loop
constraints, under the original's noise.

Poses go in and come out as world-convention six-vectors in camera axes (:mod:`lego_loam_py.core.frames`);
inside the graph they are in lidar axes, as the original keeps them, so its variances mean the same.
:attr:`PoseGraph.factors` lists what went in (for the saved map bundle, :mod:`lego_loam_py.core.mapping.map_bundle`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lego_loam_py.core.frames import camera_pose_to_lidar, lidar_pose_to_camera, matrix_to_pose6, pose6_to_matrix
from lego_loam_py.core.mapping.map_bundle import GraphFactor
from lego_loam_py.core.params.types import MapOptimizationParams

__all__ = ['PoseGraph']


class PoseGraph:
    """iSAM2 over the keyframes 0, 1, ... in the order they are added."""

    # Made when first used (the first keyframe), not at construction: importing gtsam costs 0.1 s of CPU, which
    # mapOptimization would otherwise pay before it is ready (its node imports gtsam ahead once it is).
    _MADE_ON_FIRST_USE = frozenset(('_gtsam', '_isam', '_prior_noise', '_odometry_noise'))

    def __init__(self, mo: MapOptimizationParams):
        self._params = mo
        self._prior_information = np.diag(1.0 / np.asarray(mo.prior_noise_variances, dtype=float))
        self._odometry_information = np.diag(1.0 / np.asarray(mo.odometry_noise_variances, dtype=float))
        self.last_loop_noise = None  # the noise model of the last loop constraint added
        self.factors: list[GraphFactor] = []

    def __getattr__(self, name: str):
        # (Only for attributes not set yet: the gtsam state, the first time it is needed.)
        if name not in PoseGraph._MADE_ON_FIRST_USE:
            raise AttributeError(f'{type(self).__name__!r} object has no attribute {name!r}')
        self._start()
        return self.__dict__[name]

    def _start(self) -> None:
        import gtsam

        mo = self._params
        self._gtsam = gtsam
        self._prior_noise = gtsam.noiseModel.Diagonal.Variances(np.asarray(mo.prior_noise_variances, dtype=float))
        self._odometry_noise = gtsam.noiseModel.Diagonal.Variances(np.asarray(mo.odometry_noise_variances, dtype=float))
        self.rebuild([])

    def _pose3(self, pose_camera: np.ndarray):
        """A gtsam Pose3 (lidar axes) of a 4x4 camera-axes pose."""
        lidar = camera_pose_to_lidar(pose_camera)
        return self._gtsam.Pose3(self._gtsam.Rot3(lidar[:3, :3]), lidar[:3, 3].copy())

    @staticmethod
    def _pose6(pose3) -> np.ndarray:
        return matrix_to_pose6(lidar_pose_to_camera(pose3.matrix()))

    def _record(
        self,
        kind: str,
        keys: tuple[int, int],
        measured,
        information: np.ndarray,
        kernel: str = 'none',
        width: float = 0.0,
    ) -> None:
        """Note a factor as it goes in (``measured``: a gtsam Pose3)."""
        self.factors.append(
            GraphFactor(
                kind,
                keys,
                measured.matrix(),
                np.asarray(information, float),
                kernel,
                float(width) if kernel != 'none' else 0.0,
            )
        )

    def _update(self, graph, values) -> None:
        self._isam.update(graph, values)
        self._isam.update()

    def rebuild(self, poses6: Sequence[np.ndarray]) -> None:
        """A new graph over ``poses6`` as they are now: the prior on the first, between factors along (the
        loop constraints of the old graph are in those poses already)."""
        gtsam = self._gtsam
        isam_params = gtsam.ISAM2Params()
        isam_params.setRelinearizeThreshold(self._params.isam_relinearize_threshold)
        isam_params.relinearizeSkip = self._params.isam_relinearize_skip
        # QR, not gtsam's default Cholesky: with the original's tiny variances (1e-8 m^2) Cholesky declares the
        # system indeterminate once the keyframes are some 50 m from the origin; QR stays well-conditioned.
        isam_params.setFactorization('QR')
        self._isam = gtsam.ISAM2(isam_params)
        self.factors: list[GraphFactor] = []
        if not len(poses6):
            return
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        poses = [self._pose3(pose6_to_matrix(p)) for p in poses6]
        graph.add(gtsam.PriorFactorPose3(0, poses[0], self._prior_noise))
        self._record('prior', (0, 0), poses[0], self._prior_information)
        values.insert(0, poses[0])
        for k in range(1, len(poses)):
            graph.add(gtsam.BetweenFactorPose3(k - 1, k, poses[k - 1].between(poses[k]), self._odometry_noise))
            self._record('odometry', (k - 1, k), poses[k - 1].between(poses[k]), self._odometry_information)
            values.insert(k, poses[k])
        self._update(graph, values)

    def add_keyframe(self, k: int, pose6: np.ndarray, previous6: np.ndarray | None = None) -> np.ndarray:
        """Add keyframe ``k`` at ``pose6``: the first with the prior; any later one with a between factor from
        keyframe ``k - 1`` at ``previous6`` (the motion the mapping measured). Returns its optimised pose."""
        gtsam = self._gtsam
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        pose = self._pose3(pose6_to_matrix(pose6))
        if previous6 is None:
            graph.add(gtsam.PriorFactorPose3(k, pose, self._prior_noise))
            self._record('prior', (k, k), pose, self._prior_information)
        else:
            previous = self._pose3(pose6_to_matrix(previous6))
            graph.add(gtsam.BetweenFactorPose3(k - 1, k, previous.between(pose), self._odometry_noise))
            self._record('odometry', (k - 1, k), previous.between(pose), self._odometry_information)
        values.insert(k, pose)
        self._update(graph, values)
        return self._pose6(self._isam.calculateEstimatePose3(k))

    def add_loop(self, latest: int, candidate: int, relative: np.ndarray, variances: np.ndarray) -> None:
        """The constraint 'keyframe ``candidate`` seen from keyframe ``latest`` is ``relative``' (4x4, camera
        axes), with diagonal variances (rot, rot, rot, x, y, z in lidar axes, as the original)."""
        gtsam = self._gtsam
        graph = gtsam.NonlinearFactorGraph()
        self.last_loop_noise = gtsam.noiseModel.Diagonal.Variances(np.asarray(variances, float))
        graph.add(gtsam.BetweenFactorPose3(latest, candidate, self._pose3(relative), self.last_loop_noise))
        self._record('loop', (latest, candidate), self._pose3(relative), np.diag(1.0 / np.asarray(variances, float)))
        self._update(graph, gtsam.Values())

    def add_loop_constraint(
        self,
        from_key: int,
        to_key: int,
        pose_lidar: np.ndarray,
        information: np.ndarray,
        kernel: str = 'huber',
        width: float = 1.345,
    ) -> None:
        """The constraint 'keyframe ``to_key`` sits at ``pose_lidar`` (4x4, lidar axes) in keyframe ``from_key``'s
        frame' with a 6x6 ``information`` (rot, trans; gtsam's tangent order on the ``to_key`` side) under a robust
        kernel ('huber': the pull of a constraint that disagrees with the odometry grows no faster than linearly,
        so a wrong one cannot bend a stiff chain; 'cauchy': it fades; 'none') of ``width`` standard deviations."""
        gtsam = self._gtsam
        information = 0.5 * (information + information.T) + np.eye(6) * 1e-9  # symmetric, positive definite
        noise = gtsam.noiseModel.Gaussian.Information(information)
        if kernel != 'none':
            estimator = (
                gtsam.noiseModel.mEstimator.Huber if kernel == 'huber' else gtsam.noiseModel.mEstimator.Cauchy
            ).Create(width)
            noise = gtsam.noiseModel.Robust.Create(estimator, noise)
        self.last_loop_noise = noise  # (core.mapping.covariance's graph takes the same constraint)
        pose = self._gtsam.Pose3(self._gtsam.Rot3(pose_lidar[:3, :3]), pose_lidar[:3, 3].copy())
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.BetweenFactorPose3(from_key, to_key, pose, noise))
        self._record('loop', (from_key, to_key), pose, information, kernel, width)
        self._update(graph, gtsam.Values())

    def poses(self, indices: Sequence[int]) -> list[np.ndarray]:
        """The current estimates of the keyframes ``indices`` (six-vectors)."""
        estimate = self._isam.calculateEstimate()
        return [self._pose6(estimate.atPose3(i)) for i in indices]
