"""Hand-built VLP-16 scans: points placed at chosen range-image pixels, and simple geometric scenes."""

from __future__ import annotations

import numpy as np

from lego_loam_py.core.pointcloud import velodyne_points

VLP16_ELEVATIONS_DEG = -15.0 + 2.0 * np.arange(16)


def pixel_points(
    rows, cols, ranges, horizon: int = 1800, ang_res_x: float = 0.2, elevations_deg=VLP16_ELEVATIONS_DEG
) -> np.ndarray:
    """Velodyne-layout points at the centres of pixels (row = ring, col as the original computes it)."""
    rows, cols, ranges = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (rows, cols, ranges))
    azimuth = np.radians(90.0 - (cols - horizon // 2) * ang_res_x)  # = atan2(x, y)
    elevation = np.radians(np.asarray(elevations_deg)[rows.astype(int)])
    rho = ranges * np.cos(elevation)
    xyz = np.stack([rho * np.sin(azimuth), rho * np.cos(azimuth), ranges * np.sin(elevation)], axis=1)
    return velodyne_points(xyz, intensity=np.full(len(rows), 10.0), ring=rows.astype(int))


def rays(horizon: int = 1800, ang_res_x: float = 0.2):
    """Unit ray directions (16, horizon, 3) of every VLP-16 pixel, in the sensor frame."""
    cols = np.arange(horizon)
    azimuth = np.radians(90.0 - (cols - horizon // 2) * ang_res_x)
    elevation = np.radians(VLP16_ELEVATIONS_DEG)[:, None]
    return np.stack(
        np.broadcast_arrays(
            np.cos(elevation) * np.sin(azimuth), np.cos(elevation) * np.cos(azimuth), np.sin(elevation)
        ),
        axis=-1,
    )


def scene_points(hit_range: np.ndarray) -> np.ndarray:
    """Points for a (16, H) array of ranges along the pixel rays (NaN/inf: no return)."""
    rows, cols = np.nonzero(np.isfinite(hit_range))
    return pixel_points(rows, cols, hit_range[rows, cols], horizon=hit_range.shape[1])


def floor_ranges(height: float = 1.5, max_range: float = 100.0) -> np.ndarray:
    """Ranges to a flat floor ``height`` metres below the sensor."""
    d = rays()
    with np.errstate(divide='ignore'):
        t = np.where(d[..., 2] < 0, -height / d[..., 2], np.inf)
    return np.where(t <= max_range, t, np.inf)


def wall_ranges(x: float = 6.0, half_width: float = 4.0, z_min: float = -1.4, z_max: float = 2.0) -> np.ndarray:
    """Ranges to a vertical wall (plane x = const) facing the sensor."""
    d = rays()
    with np.errstate(divide='ignore', invalid='ignore'):
        t = np.where(d[..., 0] > 0, x / d[..., 0], np.inf)
        p = d * t[..., None]
    inside = (np.abs(p[..., 1]) <= half_width) & (p[..., 2] >= z_min) & (p[..., 2] <= z_max)
    return np.where(inside, t, np.inf)
