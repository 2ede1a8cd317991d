"""The offline pipeline's events (:mod:`lego_loam_py.core.pipeline_events`) shown in a :class:`SceneLog`.

``Pipeline(params, listener=PipelineView(scene))``: each scan is logged once its fused pose is known (with the
mapping thread that may be a scan or two later), at its own place on the ``scan`` timeline; mapping steps and
loop closures at the scan they belong to. Poses and clouds go from the pipeline's camera_init (LOAM camera axes)
to ``map`` (REP-103) here.
"""

from __future__ import annotations

import numpy as np

from lego_loam_py.core.frames import CAMERA_TO_LIDAR, camera_pose_to_lidar
from lego_loam_py.core.pipeline_events import LoopChecked, MapStepped, PipelineEvent, ScanFused, ScanProcessed
from lego_loam_py.core.trajectory import Trajectory
from lego_loam_py.viewer.scene import SceneLog

__all__ = ['PipelineView']


def _to_map(points_camera: np.ndarray) -> np.ndarray:
    """(n, >=3) points in camera axes -> (n, 3) in lidar axes (camera_init -> map, camera -> base_link)."""
    return np.asarray(points_camera, dtype=np.float64)[:, :3] @ CAMERA_TO_LIDAR.T


class PipelineView:
    """A pipeline listener logging to ``scene``; ``ground_truth`` (the recording's true trajectory) is drawn
    aligned with the estimate at its first fused pose."""

    def __init__(self, scene: SceneLog, ground_truth: Trajectory | None = None):
        self.scene = scene
        self._ground_truth = None if ground_truth is None else ground_truth.to('map')
        self._scan_index: dict[int, int] = {}  # stamp [ns] -> scan index on the timeline
        self._waiting: dict[int, tuple] = {}  # stamp -> clouds of a scan whose fused pose is not known yet
        self._last_index = 0

    def __call__(self, event: PipelineEvent) -> None:
        if isinstance(event, ScanProcessed):
            self._processed(event)
        elif isinstance(event, ScanFused):
            self._fused(event)
        elif isinstance(event, MapStepped):
            self._mapped(event)
        elif isinstance(event, LoopChecked):
            self._loop(event)

    def _at(self, stamp_ns: int) -> None:
        self.scene.at_scan(self._scan_index.get(stamp_ns, self._last_index), stamp_ns)

    def _processed(self, event: ScanProcessed) -> None:
        index = self._scan_index[event.stamp_ns] = len(self._scan_index)
        self._last_index = index
        scene = self.scene
        scene.at_scan(index, event.stamp_ns)
        scene.scalars('timings/scan', event.timings_ms)  # imageProjection, featureAssociation [ms]
        stats = getattr(event.features, 'odometry', None)
        if stats is not None:
            scene.scalars(
                'health/odometry_condition',
                {'corner stage': stats.corner_condition, 'surface stage': stats.surf_condition},
            )
            scene.scalars(
                'health/odometry',
                {
                    'corner match ratio': stats.corner_match_ratio,
                    'degenerate': float(stats.corner_degenerate or stats.surf_degenerate),
                    'lost': float(stats.lost),
                },
            )
        segmentation, features = event.segmentation, event.features.features
        clouds = (
            segmentation.ground_cloud,
            segmentation.segmented_cloud_pure,
            segmentation.outlier_cloud,
            _to_map(features.sharp),
            _to_map(features.flat),
        )
        if event.odometry is None:  # the first scan: it defines the origin
            self._show_scan(np.eye(4), clouds)
        else:
            scene.trajectory_pose('odometry', camera_pose_to_lidar(event.odometry))
            self._waiting[event.stamp_ns] = clouds

    def _show_scan(self, pose_map: np.ndarray, clouds: tuple) -> None:
        scene = self.scene
        scene.sensor_pose(pose_map)
        scene.scan(*clouds[:3])
        scene.features(*clouds[3:])

    def _fused(self, event: ScanFused) -> None:
        pose = camera_pose_to_lidar(event.pose)
        self._at(event.stamp_ns)
        if self._ground_truth is not None:
            self._draw_ground_truth(event.stamp_ns, pose)
        self.scene.trajectory_pose('fused', pose)
        clouds = self._waiting.pop(event.stamp_ns, None)
        if clouds is not None:
            self._show_scan(pose, clouds)

    def _draw_ground_truth(self, stamp_ns: int, pose: np.ndarray) -> None:
        stamps, poses = self._ground_truth
        self._ground_truth = None
        if len(stamps):
            nearest = int(np.argmin(np.abs(np.asarray(stamps, dtype=np.int64) - stamp_ns)))
            self.scene.ground_truth((pose @ np.linalg.inv(poses[nearest]))[None] @ poses)

    def _mapped(self, event: MapStepped) -> None:
        scene = self.scene
        self._at(event.stamp_ns)
        scene.trajectory_pose('mapped', camera_pose_to_lidar(event.pose))
        if event.keyframe_cloud is not None:
            scene.map_points(_to_map(event.keyframe_cloud))
        scene.keyframes(_to_map(event.keyframe_positions))
        step = event.step
        scene.scalars('timings/mapping', {'mapOptimization': event.cpu_ms})
        scene.scalars('health/mapping', {'iterations': step.iterations, 'degenerate': float(step.degenerate)})

    def _loop(self, event: LoopChecked) -> None:
        loop = event.loop
        if loop is None or not loop.accepted:
            return
        self.scene.at_scan(self._last_index, max(self._scan_index, key=self._scan_index.get, default=0))
        positions = _to_map(event.keyframe_positions)
        self.scene.loop(loop.latest, positions[loop.latest], positions[loop.candidate])
        self.scene.keyframes(positions)

    def finish(self) -> None:
        self.scene.finish()
