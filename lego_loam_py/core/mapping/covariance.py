"""The covariance of mapOptimization's pose (/aft_mapped_to_init): the scan-to-map registration's information for
the mapped pose, on top of the uncertainty of the map it registered against, which is that of the keyframes, kept
by a pose graph of their own (:class:`KeyframeCovariance`) so that a loop closure shrinks it.

Conventions: :mod:`lego_loam_py.core.frames` (pose covariance): of the error in the parent frame camera_init,
position in camera_init's axes [m²], rotation a small rotation vector about them [rad²], ROS order (x, y, z, rot x,
rot y, rot z). camera_init is the map frame here: the first keyframe is where it is, so its covariance is ~0.

Why a graph of its own: the mapping's pose graph (:class:`~lego_loam_py.core.mapping.pose_graph.PoseGraph`) holds
the original's fixed variances (1e-6 rad², 1e-8 m² per keyframe), which say nothing about how well a keyframe was
registered and which its estimates (and so the trajectories) depend on. :class:`KeyframeCovariance` has the same
keyframes and the same loop constraints, but each keyframe's between factor carries the covariance its scan-to-map
registration had; only its marginal covariances are read, never its estimates.
"""

from __future__ import annotations

import numpy as np

from lego_loam_py.core.frames import (
    CAMERA_TO_LIDAR,
    LIDAR_TO_CAMERA,
    bounded_covariance,
    camera_pose_to_lidar,
    compound_covariance,
    covariance_from_information,
    invert_pose,
    pose6_to_matrix,
    pose_jacobian,
    relative_covariance,
    rotate_covariance,
)

__all__ = [
    'MAX_REGISTRATION_VARIANCE',
    'registration_covariance',
    'mapped_covariance',
    'SweepCovariance',
    'KeyframeCovariance',
]

# A registration never leaves a direction less certain than this [m², rad²]: a direction the map does not hold
# (a corridor's axis) stays at the odometry's prediction, whose error over a mapping interval is below that.
MAX_REGISTRATION_VARIANCE = 1.0
# The first keyframe defines the map frame: its variances [m², rad²].
_ORIGIN_VARIANCE = 1e-10


def registration_covariance(pose6: np.ndarray, information: np.ndarray | None, scale: float = 1.0) -> np.ndarray:
    """6x6 covariance of the pose ``pose6`` (world convention six-vector) relative to the map it was registered
    against, from the registration's information of the six-vector (None: not registered, every direction at
    :data:`MAX_REGISTRATION_VARIANCE`), in camera_init axes; the residual variance times ``scale``
    (``map_optimization.covariance_scale``)."""
    if information is None or not np.any(information):
        return np.eye(6) * MAX_REGISTRATION_VARIANCE
    six = scale * covariance_from_information(information, MAX_REGISTRATION_VARIANCE / max(scale, 1e-12))
    jacobian = pose_jacobian(pose6_to_matrix, np.asarray(pose6, dtype=float))
    out = jacobian @ six @ jacobian.T
    return 0.5 * (out + out.T)


def mapped_covariance(
    anchor: np.ndarray, anchor_covariance: np.ndarray, pose: np.ndarray, registration: np.ndarray
) -> np.ndarray:
    """Covariance of a mapped pose (4x4) registered with covariance ``registration`` (camera_init axes) against a
    map whose uncertainty is that of the keyframe ``anchor`` (4x4, with its covariance)."""
    relative = invert_pose(anchor) @ pose
    return compound_covariance(anchor, anchor_covariance, relative, rotate_covariance(registration, anchor[:3, :3].T))


class SweepCovariance:
    """The covariance of the odometry's motion since the previous mapping input, read off the odometry's pose
    covariance (that of /laser_odom_to_init): what it grew by from one input to the next
    (:func:`~lego_loam_py.core.frames.relative_covariance`), in the earlier input's axes [m², rad²]. With
    ``feature_association.skip_frame_num`` 1 that is two sweeps: the one whose scan is registered and the one
    before it.

    Why the mapping needs it: the scan mapOptimization registers was deskewed with the odometry's motion estimate
    (that sweep's, assumed constant over it; how far that was off, the change from the sweep before, is one of the
    odometry's deskewing terms, core.odometry.covariance), so an error in the motion bends the scan, and the
    registration places the bent scan where its residuals are smallest: an error of the mapped pose that no
    scan-to-map residual shows. :meth:`deskewing` adds it to the mapped pose's covariance. Per input: two 6x6
    products and an eigendecomposition (``relative_covariance``'s bound).
    """

    def __init__(self):
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # the previous input's pose (4x4) and covariance
        self.covariance: np.ndarray | None = None  # of the motion since the previous input, in that input's axes
        self.rotation = np.eye(3)  # the rotation since the previous input (this input's axes in that one's)

    def add(self, pose: np.ndarray, covariance: np.ndarray | None) -> None:
        """The odometry's pose (4x4, camera_init) and its covariance (None: unknown) for the next input."""
        last, self._last = self._last, (None if covariance is None else (pose, np.asarray(covariance, dtype=float)))
        if last is None or covariance is None:
            self.covariance = None
            return
        self.covariance = relative_covariance(last[0], last[1], pose, self._last[1])
        self.rotation = last[0][:3, :3].T @ pose[:3, :3]

    def reset(self) -> None:
        """The odometry restarted: the next input starts a new chain."""
        self._last, self.covariance = None, None

    def deskewing(self, pose: np.ndarray, weight: float) -> np.ndarray:
        """``weight`` (``map_optimization.covariance_deskew``) times the covariance of the motion since the
        previous input, in the axes of the map frame (camera_init) where this input's scan is at ``pose`` (4x4, its
        mapped pose): the deskewing's error the mapped pose carries [m², rad²] (zeros when the odometry gave no
        covariance or restarted)."""
        if self.covariance is None or weight == 0.0:
            return np.zeros((6, 6))
        return weight * rotate_covariance(self.covariance, np.asarray(pose)[:3, :3] @ self.rotation.T)


def _tangent_to_parent(rotation: np.ndarray) -> np.ndarray:
    """6x6 ``M`` taking gtsam's Pose3 tangent (rotation, translation; right perturbation ``T exp(ξ)``) to the
    parent-frame error (position, rotation) of a pose with this rotation: ``δp = R v``, ``δφ = R ω``."""
    out = np.zeros((6, 6))
    out[:3, 3:] = rotation
    out[3:, :3] = rotation
    return out


class KeyframeCovariance:
    """iSAM2 over the keyframes, in lidar axes like the mapping's graph, with the registration's covariance on
    each between factor and the loop constraints as the mapping's graph has them; :meth:`covariance` gives a
    keyframe's marginal covariance in camera_init (camera axes)."""

    def __init__(self):
        self._poses: list[np.ndarray] = []  # 4x4 camera axes, as added
        self._marginals: dict[int, np.ndarray] = {}

    def __getattr__(self, name: str):
        # The gtsam state is made by the first keyframe, not at construction: importing gtsam costs mapOptimization
        # 0.1 s of CPU before it is ready (as core.mapping.pose_graph.PoseGraph).
        if name not in ('_gtsam', '_isam'):
            raise AttributeError(f'{type(self).__name__!r} object has no attribute {name!r}')
        import gtsam

        params = gtsam.ISAM2Params()
        params.setFactorization('QR')  # (a variance of 1e-10 at the origin: see PoseGraph)
        self._gtsam, self._isam = gtsam, gtsam.ISAM2(params)
        return self.__dict__[name]

    def __len__(self) -> int:
        return len(self._poses)

    def _pose3(self, pose_camera: np.ndarray):
        lidar = camera_pose_to_lidar(pose_camera)
        return self._gtsam.Pose3(self._gtsam.Rot3(lidar[:3, :3]), lidar[:3, 3].copy())

    def add_keyframe(self, pose: np.ndarray, registration: np.ndarray | None) -> np.ndarray:
        """Keyframe ``len(self)`` at ``pose`` (4x4 camera_init), registered with covariance ``registration``
        (camera_init axes; None: the first keyframe, the origin); returns its covariance."""
        gtsam = self._gtsam
        k = len(self._poses)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        pose3 = self._pose3(pose)
        if k == 0 or registration is None:
            noise = gtsam.noiseModel.Diagonal.Variances(np.full(6, _ORIGIN_VARIANCE))
            graph.add(gtsam.PriorFactorPose3(k, pose3, noise))
        else:
            previous = self._poses[-1]
            relative = self._pose3(previous).between(pose3)
            # The registration's error, in the previous keyframe's axes, then lidar axes, then gtsam's tangent.
            in_previous = rotate_covariance(registration, CAMERA_TO_LIDAR @ previous[:3, :3].T)
            to_tangent = np.linalg.inv(_tangent_to_parent(relative.rotation().matrix()))
            covariance = bounded_covariance(to_tangent @ in_previous @ to_tangent.T)
            graph.add(gtsam.BetweenFactorPose3(k - 1, k, relative, gtsam.noiseModel.Gaussian.Covariance(covariance)))
        values.insert(k, pose3)
        self._isam.update(graph, values)
        self._poses.append(np.array(pose, dtype=float))
        self._marginals.clear()
        return self.covariance(k)

    def add_loop(self, from_key: int, to_key: int, pose_lidar: np.ndarray, noise) -> None:
        """The loop constraint 'keyframe ``to_key`` at ``pose_lidar`` (4x4, lidar axes) in keyframe ``from_key``'s
        frame' under ``noise`` (a gtsam noise model, the one the mapping's graph got)."""
        gtsam = self._gtsam
        if max(from_key, to_key) >= len(self._poses):
            return
        pose = gtsam.Pose3(gtsam.Rot3(pose_lidar[:3, :3]), pose_lidar[:3, 3].copy())
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.BetweenFactorPose3(from_key, to_key, pose, noise))
        self._isam.update(graph, gtsam.Values())
        self._isam.update()
        self._marginals.clear()

    def kept(self, indices: list[int], poses: list[np.ndarray]) -> KeyframeCovariance:
        """A graph of the keyframes ``indices`` only (the others were dropped as poisoned), renumbered 0, 1, ...
        at ``poses`` (4x4 camera_init), each held at its covariance here (their correlations are lost)."""
        gtsam = self._gtsam
        out = KeyframeCovariance()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for new, (old, pose) in enumerate(zip(indices, poses)):
            covariance = self.covariance(old) if old < len(self._poses) else np.eye(6) * MAX_REGISTRATION_VARIANCE
            estimate = out._pose3(pose)
            to_tangent = np.linalg.inv(_tangent_to_parent(estimate.rotation().matrix()))
            lidar = rotate_covariance(covariance, CAMERA_TO_LIDAR)
            noise = gtsam.noiseModel.Gaussian.Covariance(bounded_covariance(to_tangent @ lidar @ to_tangent.T))
            graph.add(gtsam.PriorFactorPose3(new, estimate, noise))
            values.insert(new, estimate)
            out._poses.append(np.array(pose, dtype=float))
        if out._poses:
            out._isam.update(graph, values)
        return out

    def covariance(self, k: int = -1) -> np.ndarray:
        """Marginal covariance of keyframe ``k`` (default: the latest) in camera_init (camera axes)."""
        k = k % len(self._poses)
        if k not in self._marginals:
            estimate = self._isam.calculateEstimatePose3(k)
            tangent = self._isam.marginalCovariance(k)
            lidar = _tangent_to_parent(estimate.rotation().matrix())
            self._marginals[k] = bounded_covariance(
                rotate_covariance(lidar @ tangent @ lidar.T, LIDAR_TO_CAMERA), _ORIGIN_VARIANCE
            )
        return self._marginals[k]
