"""Logging a SLAM run to Rerun: the entities of :mod:`lego_loam_py.viewer`, fed by arrays (no ROS, no pipeline).

Poses are 4x4 in the ``map`` frame (REP-103 axes); clouds are (n, >=3) float arrays [m] in the frame the method
names. Trajectories are logged in pieces of :data:`TRAJECTORY_PIECE` poses (each piece once), and the map as the
voxels each keyframe adds, so a long run costs the viewer what it adds, not what it has.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lego_loam_py.viewer import require_rerun

__all__ = ['SceneLog', 'SCAN_CLASSES', 'TRAJECTORY_PIECE', 'MAP_VOXEL']

TRAJECTORY_PIECE = 10  # poses per logged piece of a trajectory
MAP_VOXEL = 0.4  # [m] the map keeps one point per voxel of this size (the original's global map leaf)
# Class ids of the scan's points (annotation context of world/lidar): name, colour.
SCAN_CLASSES = {
    0: ('ground', (120, 200, 80)),
    1: ('segmented', (80, 160, 255)),
    2: ('outlier', (150, 150, 150)),
    3: ('corner', (255, 60, 40)),
    4: ('surface', (255, 200, 0)),
}
TRAJECTORY_COLOURS = {
    'odometry': (255, 140, 0),
    'mapped': (200, 0, 200),
    'fused': (0, 120, 255),
    'ground_truth': (230, 230, 230),
}


class _Trajectory:
    """A growing trajectory, logged in pieces that share their end points (so the pieces join)."""

    def __init__(self, log, name: str):
        self.log, self.name = log, name
        self.pending: list[np.ndarray] = []
        self.last: np.ndarray | None = None
        self.pieces = 0

    def add(self, position: np.ndarray) -> None:
        self.pending.append(np.asarray(position, dtype=np.float64))
        if len(self.pending) >= TRAJECTORY_PIECE:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        points = ([self.last] if self.last is not None else []) + self.pending
        rr = self.log.rr
        self.log.rec.log(
            f'world/trajectory/{self.name}/{self.pieces:05d}',
            rr.LineStrips3D([np.array(points)], colors=[TRAJECTORY_COLOURS[self.name]], radii=rr.Radius.ui_points(3.0)),
        )
        self.last, self.pending = self.pending[-1], []
        self.pieces += 1


class SceneLog:
    """One Rerun recording of a run: saved to ``save`` (.rrd), shown in a spawned native viewer (``spawn``), or
    both; ``recording`` = a ``rerun.RecordingStream`` to log into instead (tests)."""

    def __init__(self, name: str, *, save: str | Path | None = None, spawn: bool = False, recording=None):
        rr = self.rr = require_rerun()
        self.rec = recording or rr.RecordingStream('lego_loam_py', recording_id=name)
        if recording is None:
            sinks = []
            if save is not None:
                Path(save).parent.mkdir(parents=True, exist_ok=True)
                sinks.append(rr.FileSink(str(save)))
            if spawn:
                rr.spawn(connect=False)  # a native viewer on this machine, listening on its default port
                sinks.append(rr.GrpcSink())
            if sinks:
                self.rec.set_sinks(*sinks)
        self.rec.send_blueprint(self._blueprint())
        self.rec.log('world', rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.log(
            'world/lidar',
            rr.AnnotationContext([(k, name, colour) for k, (name, colour) in SCAN_CLASSES.items()]),
            static=True,
        )
        self._trajectories = {name: _Trajectory(self, name) for name in TRAJECTORY_COLOURS}
        self._map_voxels = np.zeros(0, dtype=np.int64)
        self._map_pieces = 0
        self._series: set[str] = set()

    def _blueprint(self):
        import rerun.blueprint as rrb

        plots = rrb.Vertical(
            rrb.TimeSeriesView(origin='timings', name='ms per scan'),
            rrb.TimeSeriesView(origin='health/odometry_condition', name='odometry: stage condition'),
            rrb.TimeSeriesView(origin='health/odometry', name='odometry: matched, degenerate, lost'),
            rrb.TimeSeriesView(origin='health/mapping', name='mapping: iterations, degenerate'),
        )
        # Seen from behind and above the sensor, following it (orbit with the mouse).
        eye = rrb.EyeControls3D(
            kind=rrb.Eye3DKind.Orbital,
            position=(-30.0, -18.0, 28.0),
            look_target=(0.0, 0.0, 0.0),
            eye_up=(0.0, 0.0, 1.0),
            tracking_entity='world/lidar',
        )
        scene = rrb.Spatial3DView(origin='world', name='map', background=(12, 14, 18), eye_controls=eye)
        return rrb.Blueprint(rrb.Horizontal(scene, plots, column_shares=[3, 1]), collapse_panels=True)

    # ------------------------------------------------------------------------------------------- time
    def at_scan(self, index: int, stamp_ns: int) -> None:
        """What follows belongs to scan ``index`` stamped ``stamp_ns``."""
        self.rec.set_time('scan', sequence=int(index))
        self.rec.set_time('stamp', timestamp=np.datetime64(int(stamp_ns), 'ns'))

    # ------------------------------------------------------------------------------------------- scan
    def sensor_pose(self, pose: np.ndarray) -> None:
        """The sensor's pose in ``map`` (4x4): the frame of the scan and feature clouds."""
        self.rec.log('world/lidar', self.rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))

    def scan(self, ground: np.ndarray, segmented: np.ndarray, outlier: np.ndarray) -> None:
        """The scan's points by label, sensor frame."""
        clouds = (ground, segmented, outlier)
        self._classified('world/lidar/scan', clouds, (0, 1, 2), radius=self.rr.Radius.ui_points(2.0))

    def features(self, corner: np.ndarray, surface: np.ndarray) -> None:
        """The scan's corner and surface features, sensor frame."""
        self._classified('world/lidar/features', (corner, surface), (3, 4), radius=self.rr.Radius.ui_points(4.0))

    def _classified(self, path: str, clouds, classes, radius) -> None:
        positions = np.concatenate([np.asarray(c)[:, :3] for c in clouds]).astype(np.float32)
        ids = np.repeat(np.array(classes, dtype=np.uint16), [len(c) for c in clouds])
        self.rec.log(path, self.rr.Points3D(positions, class_ids=ids, radii=radius))

    # ---------------------------------------------------------------------------------------- the map
    def map_points(self, points: np.ndarray) -> int:
        """Add points in ``map`` to the map, one per voxel of :data:`MAP_VOXEL` not yet in it; returns how many
        were new (logged as one more piece of ``world/map``)."""
        xyz = np.asarray(points, dtype=np.float64)[:, :3]
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        cells = np.floor(xyz / MAP_VOXEL).astype(np.int64) + (1 << 20)  # (within +-400 km of the origin)
        keys = (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]
        keys, first = np.unique(keys, return_index=True)
        # Membership in the sorted voxels of the map by binary search: O(new points x log map), not a sort of the
        # whole map per keyframe; the new keys go in at their places (one copy of the key array).
        at = np.searchsorted(self._map_voxels, keys)
        known = at < len(self._map_voxels)
        known[known] = self._map_voxels[at[known]] == keys[known]
        new = ~known
        if not new.any():
            return 0
        self._map_voxels = np.insert(self._map_voxels, at[new], keys[new])
        fresh = xyz[first[new]]
        self.rec.log(
            f'world/map/{self._map_pieces:05d}',
            self.rr.Points3D(
                fresh.astype(np.float32), colors=_height_colours(fresh[:, 2]), radii=self.rr.Radius.ui_points(1.5)
            ),
        )
        self._map_pieces += 1
        return int(new.sum())

    # ----------------------------------------------------------------------------------- trajectories
    def trajectory_pose(self, name: str, pose: np.ndarray) -> None:
        """One more pose of the trajectory ``name`` ('odometry', 'mapped' or 'fused'), ``map`` frame."""
        self._trajectories[name].add(pose[:3, 3])

    def ground_truth(self, poses: np.ndarray) -> None:
        """The whole true trajectory (poses in ``map``), logged once for every time."""
        self.rec.log(
            'world/trajectory/ground_truth',
            self.rr.LineStrips3D(
                [np.asarray(poses)[:, :3, 3]],
                colors=[TRAJECTORY_COLOURS['ground_truth']],
                radii=self.rr.Radius.ui_points(2.0),
            ),
            static=True,
        )

    def keyframes(self, positions: np.ndarray) -> None:
        """Every keyframe's position in ``map``."""
        self.rec.log(
            'world/keyframes',
            self.rr.Points3D(
                np.asarray(positions, dtype=np.float32), colors=[(255, 80, 200)], radii=self.rr.Radius.ui_points(5.0)
            ),
        )

    def loop(self, index: int, start: np.ndarray, end: np.ndarray) -> None:
        """An accepted loop closure between two keyframe positions in ``map``."""
        self.rec.log(
            f'world/loops/{index:04d}',
            self.rr.LineStrips3D([np.array([start, end])], colors=[(0, 230, 0)], radii=self.rr.Radius.ui_points(4.0)),
        )

    # ---------------------------------------------------------------------------------------- plots
    def scalar(self, path: str, value: float) -> None:
        """A plotted value, e.g. ``timings/imageProjection`` [ms] or ``health/corner_condition``."""
        if value is not None and np.isfinite(value):
            self.rec.log(path, self.rr.Scalars(float(value)))

    def scalars(self, path: str, values: dict[str, float]) -> None:
        """Several plotted values of one entity (one log call), each its own named series; NaN leaves a gap."""
        if path not in self._series:
            self._series.add(path)
            self.rec.log(path, self.rr.SeriesLines(names=list(values)), static=True)
        self.rec.log(path, self.rr.Scalars(np.array(list(values.values()), dtype=np.float64)))

    def finish(self) -> None:
        """Log what is still pending and flush the sinks."""
        for trajectory in self._trajectories.values():
            trajectory.flush()
        self.rec.flush()


def _height_colours(z: np.ndarray, low: float = -2.0, high: float = 6.0) -> np.ndarray:
    """(n, 3) uint8 colours from blue (``low``) to yellow (``high``) by height ``z`` [m] in ``map`` (fixed bounds:
    every piece of the map shares the scale)."""
    t = np.clip((np.asarray(z) - low) / (high - low), 0.0, 1.0)[:, None]
    return (np.array([40, 60, 200]) * (1 - t) + np.array([250, 220, 40]) * t).astype(np.uint8)
