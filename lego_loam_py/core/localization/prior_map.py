"""The saved map as localization uses it: never modified, searched by position and by the look of a place.

Built once from a :class:`~lego_loam_py.core.mapping.map_bundle.MapBundle`:

* the whole map voxel-filtered (corner and surface + outlier points, the bundle's ``corner_map`` and
  ``surface_map``), in the map frame (LOAM camera axes, as every pose of the pipeline); :meth:`PriorMap.local`
  cuts the part around a position for the scan-to-map registration of tracking, with its KD-trees, and keeps it
  until the robot has moved on (the map does not change, so neither do its trees);
* the keyframes' poses, and a Scan Context descriptor of each keyframe (:mod:`lego_loam_py.core.loop.place_recognition`)
  made from its clouds levelled by its pose, as the loop closure makes them: :attr:`PriorMap.places` finds where a
  scan was seen from, whatever its heading;
* :meth:`PriorMap.region` the map around a place in REP-103 lidar axes, thinned, as the target of the verifying
  registration (:mod:`lego_loam_py.core.loop.registration`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lego_loam_py.core.frames import camera_pose_to_lidar, camera_to_lidar, pose6_to_matrix
from lego_loam_py.core.loop.place_recognition import PlaceDatabase, ScanContextConfig, scan_context
from lego_loam_py.core.mapping.map_bundle import MapBundle
from lego_loam_py.core.mapping.scan_to_map import map_trees
from lego_loam_py.core.params.types import Params
from lego_loam_py.core.voxel import voxel_downsample

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

__all__ = ['PriorMap', 'LocalMap', 'levelling', 'heading']

# The map around the robot for tracking: points within this of its position [m] (a scan reaches 100 m, but
# the registration's correspondences are rarely farther than the mapping's 50 m of keyframes), cut again once
# the robot is this far from where it was cut [m]: at least 40 m around it. A smaller map makes every
# neighbour search of the registration cheaper: 50 m instead of 70 m cost 5-14 % less CPU per tracking step on
# the simulated campus, forest and aggressive drives, the error in the map's frame unchanged to 1 mm.
LOCAL_RADIUS, RECUT_DISTANCE = 50.0, 10.0
# The verifying registration's target: the map within this of the candidate place [m], at most this many points
# (the leaf grows until it fits; a 20k-point target costs some 100 ms).
REGION_RADIUS, REGION_MAX_POINTS = 40.0, 20000
# Places whose ring key (the yaw-invariant summary) is nearest the scan's, ranked then by the full descriptor. The
# whole map is searched, not the neighbourhood of a drifted estimate as in loop closure: with the loop closure's 10,
# the right place of a 597-keyframe campus map was missing from the list for 2 s of a drive (5 attempts); 50 cost
# some 1.5 ms per attempt.
RING_KEY_CANDIDATES = 50


def heading(pose_lidar: np.ndarray) -> float:
    """Yaw [rad] of a 4x4 pose in REP-103 axes (x forward, z up)."""
    return math.atan2(pose_lidar[1, 0], pose_lidar[0, 0])


def levelling(pose_lidar: np.ndarray) -> np.ndarray:
    """The 3x3 rotation that levels a sensor's points by its roll and pitch in the map (REP-103), keeping its yaw:
    ``R = Rz(yaw) @ levelling(pose)``."""
    yaw = heading(pose_lidar)
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ pose_lidar[:3, :3]


def thinned(points: np.ndarray, leaf: float, max_points: int) -> np.ndarray:
    """(N, 3) points voxel-filtered with ``leaf`` [m], coarser (x1.25 at a time) until at most ``max_points``."""
    cloud = np.column_stack([points[:, :3], np.zeros(len(points))]).astype(np.float32)
    out = voxel_downsample(cloud, leaf)
    while len(out) > max_points:
        leaf *= 1.25
        out = voxel_downsample(cloud, leaf)
    return out[:, :3].astype(np.float64)


@dataclass(frozen=True)
class LocalMap:
    """The map around a position for tracking (map frame, camera axes) and its KD-trees."""

    centre: np.ndarray  # (3,) where it was cut
    corner: np.ndarray  # (n, 4) float32
    surf: np.ndarray
    trees: tuple  # (corner, surface) searches, as scan_to_map.map_trees


class PriorMap:
    """A loaded map bundle, ready to localize in (see the module docstring)."""

    def __init__(self, bundle: MapBundle, params: Params):
        self.bundle = bundle
        self.params = params
        self.poses = np.array([pose6_to_matrix(p) for p in bundle.poses6]).reshape(-1, 4, 4)  # camera axes
        self.poses_lidar = camera_pose_to_lidar(np.asarray(self.poses).reshape(-1, 4, 4))
        self.positions = self.poses[:, :3, 3].copy()
        self.corner_map = np.ascontiguousarray(bundle.corner_map, dtype=np.float32)
        self.surface_map = np.ascontiguousarray(bundle.surface_map, dtype=np.float32)
        # Horizontal coordinates (camera axes: x and z; y is up) of every map point, to cut by distance.
        self._corner_xz = self.corner_map[:, [0, 2]].astype(np.float64)
        self._surface_xz = self.surface_map[:, [0, 2]].astype(np.float64)
        self._local: LocalMap | None = None
        self._edges_lidar: cKDTree | None = None
        lc = params.loop_closure
        self.places = PlaceDatabase(
            ScanContextConfig(
                rings=lc.scan_context_rings, sectors=lc.scan_context_sectors, max_radius=lc.scan_context_max_radius
            ),
            ring_key_candidates=RING_KEY_CANDIDATES,
        )
        for k in range(len(bundle)):
            self.places.add(k, self.descriptor(self.keyframe_points(k), self.poses_lidar[k]))

    def __len__(self) -> int:
        return len(self.positions)

    def keyframe_points(self, k: int) -> np.ndarray:
        """(n, 3) all points of keyframe ``k`` in its sensor frame, REP-103 lidar axes."""
        b = self.bundle
        return camera_to_lidar(np.concatenate([b.corner[k], b.surf[k], b.outlier[k]])[:, :3].astype(np.float64))

    def descriptor(self, points_lidar: np.ndarray, pose_lidar: np.ndarray) -> np.ndarray:
        """Scan Context of sensor-frame points (lidar axes) seen from ``pose_lidar`` (only its roll and pitch
        count: the points are levelled by them)."""
        return scan_context(points_lidar[:, :3] @ levelling(pose_lidar).T, self.places.config)

    def nearest_keyframe(self, position: np.ndarray) -> tuple[int, float]:
        """(index, distance [m]) of the keyframe nearest ``position`` (map frame, camera axes)."""
        distance = np.linalg.norm(self.positions - position, axis=1)
        k = int(np.argmin(distance))
        return k, float(distance[k])

    def local(self, position: np.ndarray) -> LocalMap:
        """The map within LOCAL_RADIUS (horizontally) of ``position`` (camera axes), cut again only when the
        robot moved RECUT_DISTANCE from where the last one was cut."""
        local = self._local
        if local is not None and np.linalg.norm(local.centre - position) < RECUT_DISTANCE:
            return local
        centre = np.asarray(position, dtype=np.float64)[[0, 2]]
        corner = self.corner_map[
            np.einsum('ij,ij->i', self._corner_xz - centre, self._corner_xz - centre) <= LOCAL_RADIUS**2
        ]
        surf = self.surface_map[
            np.einsum('ij,ij->i', self._surface_xz - centre, self._surface_xz - centre) <= LOCAL_RADIUS**2
        ]
        trees = map_trees(corner, surf, self.params.map_optimization.knn_max_sq_dist)
        self._local = LocalMap(np.asarray(position, dtype=np.float64).copy(), corner, surf, trees)
        return self._local

    def region(self, position_lidar: np.ndarray, leaf: float) -> np.ndarray:
        """(m, 3) map points within REGION_RADIUS (horizontally) of ``position_lidar`` (map frame, REP-103), thinned:
        the target of a verifying registration."""
        lidar_xy = np.asarray(position_lidar, dtype=np.float64)[:2]
        centre = np.array([lidar_xy[1], lidar_xy[0]])  # (x, z) in camera axes = (y, x) in lidar axes
        points = np.concatenate(
            [
                self.corner_map[
                    np.einsum('ij,ij->i', self._corner_xz - centre, self._corner_xz - centre) <= REGION_RADIUS**2
                ],
                self.surface_map[
                    np.einsum('ij,ij->i', self._surface_xz - centre, self._surface_xz - centre) <= REGION_RADIUS**2
                ],
            ]
        )
        return camera_to_lidar(thinned(points, leaf, REGION_MAX_POINTS))

    def edge_tree(self) -> cKDTree:
        """KD-tree of the map's corner (edge) points in REP-103 lidar axes (built once, when first needed)."""
        from scipy.spatial import cKDTree

        if self._edges_lidar is None:
            self._edges_lidar = cKDTree(camera_to_lidar(self.corner_map[:, :3].astype(np.float64)))
        return self._edges_lidar
