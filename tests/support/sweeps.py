"""Synthetic VLP-16 sweeps of simple worlds (boxes), with the sensor moving during the sweep.

The sweep starts straight ahead and turns clockwise like a Velodyne; column k of 1800 fires at relative
time s = k / 1800. The sensor pose at time s is ``start @ motion(s)``. Points are in the sensor frame at
their own firing time (motion distortion), in message order = firing order, with ring and time fields.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from lego_loam_py.core.frames import camera_pose_to_lidar, invert_pose, make_pose
from lego_loam_py.core.odometry.sweep import sweep_rotation
from lego_loam_py.core.pointcloud import velodyne_points

ELEVATIONS = np.radians(-15.0 + 2.0 * np.arange(16))


def box(center, size) -> o3d.t.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_box(*size)
    mesh.translate(np.asarray(center, dtype=float) - np.asarray(size, dtype=float) / 2)
    return o3d.t.geometry.TriangleMesh.from_legacy(mesh)


def room_world(seed: int = 0, corridor: bool = False) -> o3d.t.geometry.RaycastingScene:
    """A 40 x 30 m yard with a floor, walls and pillars/boxes (or a long closed corridor: two walls, floor and
    ceiling, so that nothing but the walls' and floor's own shape is seen: motion along it is unobservable)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(box([0, 0, -1.6], [200, 200, 0.2]))  # floor, top at z = -1.5
    if corridor:
        scene.add_triangles(box([0, 3.0, 0], [400, 0.2, 6]))
        scene.add_triangles(box([0, -3.0, 0], [400, 0.2, 6]))
        scene.add_triangles(box([0, 0, 2.6], [400, 8, 0.2]))  # ceiling, underside at z = 2.5
        return scene
    for center, size in [
        ([20, 0, 1], [0.4, 30, 5]),
        ([-20, 0, 1], [0.4, 30, 5]),
        ([0, 15, 1], [40, 0.4, 5]),
        ([0, -15, 1], [40, 0.4, 5]),
    ]:
        scene.add_triangles(box(center, size))
    rng = np.random.default_rng(seed)
    for _ in range(25):
        c = rng.uniform([-17, -12], [17, 12])
        if np.hypot(*c) < 4:
            continue
        scene.add_triangles(box([c[0], c[1], 0.0], [*rng.uniform(0.3, 2.5, 2), rng.uniform(1.0, 4.0)]))
    return scene


def motion_pose(theta_camera: np.ndarray, s: float) -> np.ndarray:
    """Pose (lidar axes) of the sensor at relative time s, for the LOAM sweep motion θ (camera axes):
    the frame at s is ``T(sθ)^-1`` in the start frame."""
    theta = np.asarray(theta_camera, dtype=float) * s
    forward = make_pose(sweep_rotation(*theta[:3]), theta[3:])
    return camera_pose_to_lidar(invert_pose(forward))


def sweep(
    scene, start_pose: np.ndarray, theta_camera=None, noise: float = 0.0, seed: int = 0, max_range: float = 100.0
) -> np.ndarray:
    """One sweep (velodyne layout) seen from ``start_pose`` (lidar axes, world) moving by θ over the sweep (default:
    standing still)."""
    theta_camera = np.zeros(6) if theta_camera is None else theta_camera
    k = np.arange(1800)
    s = k / 1800.0
    azimuth = -2 * np.pi * s  # clockwise from straight ahead
    origins = np.empty((1800, 16, 3))
    directions = np.empty((1800, 16, 3))
    local = np.stack(
        [
            np.cos(ELEVATIONS)[None, :] * np.cos(azimuth)[:, None],
            np.cos(ELEVATIONS)[None, :] * np.sin(azimuth)[:, None],
            np.broadcast_to(np.sin(ELEVATIONS)[None, :], (1800, 16)),
        ],
        axis=-1,
    )
    poses = np.array([start_pose @ motion_pose(theta_camera, si) for si in s])
    origins[:] = poses[:, None, :3, 3]
    directions[:] = np.einsum('kij,krj->kri', poses[:, :3, :3], local)
    rays = np.concatenate([origins, directions], axis=-1).reshape(-1, 6).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))['t_hit'].numpy().reshape(1800, 16)
    rng = np.random.default_rng(seed)
    ranges = hit + (rng.normal(0, noise, hit.shape) if noise else 0.0)
    valid = np.isfinite(hit) & (hit < max_range)
    xyz = local * np.where(valid, ranges, 0.0)[..., None]
    ring = np.broadcast_to(np.arange(16), (1800, 16))
    time = np.broadcast_to(s[:, None] * 0.1, (1800, 16))
    return velodyne_points(xyz[valid], np.full(valid.sum(), 50.0), ring[valid], time[valid])
