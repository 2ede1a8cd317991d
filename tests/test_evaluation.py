"""Error against time (lego_loam_py.evaluation.error_over_time) on trajectories checked by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lego_loam_py.core.frames import make_pose, rot_x, rot_z
from lego_loam_py.evaluation import error_over_time


def turning_walk(count: int = 50, yaw_rate_deg_s: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [ns] at 10 Hz, poses): 1 m/s along the heading, which turns left at a constant rate."""
    stamps = np.arange(count, dtype=np.int64) * 100_000_000
    headings = np.radians(yaw_rate_deg_s) * stamps * 1e-9
    positions = np.cumsum(np.column_stack([np.cos(headings), np.sin(headings), np.zeros(count)]) * 0.1, axis=0)
    positions -= positions[0]
    return stamps, np.array([make_pose(rot_z(h), p) for h, p in zip(headings, positions)])


def test_errors_are_split_along_the_true_heading_into_tilt_and_heading():
    """After its first pose the estimate is 0.1 m off in world x, 0.2 m too high and tilted by 2 deg about world
    x: along and left are that 0.1 m seen from the true heading, up is 0.2 m, the tilt 2 deg whatever the
    heading, no heading error, and the true yaw rate is the walk's 10 deg/s."""
    stamps, truth = turning_walk()
    estimate = truth.copy()
    estimate[1:, :3, 3] += [0.1, 0.0, 0.2]
    estimate[1:, :3, :3] = rot_x(math.radians(2.0)) @ truth[1:, :3, :3]
    # Stamps 2 ms late are matched; one 50 ms off any ground truth is not.
    late = stamps + 2_000_000
    late[7] += 48_000_000
    errors = error_over_time((stamps, truth), (late, estimate))
    kept = np.delete(np.arange(len(stamps)), 7)
    assert np.allclose(errors.time_s, (late[kept] - late[0]) * 1e-9)
    heading = np.radians(10.0) * stamps[kept][1:] * 1e-9
    assert np.allclose(errors.along_m[1:], 0.1 * np.cos(heading), atol=1e-9)
    assert np.allclose(errors.left_m[1:], -0.1 * np.sin(heading), atol=1e-9)
    assert np.allclose(errors.up_m[1:], 0.2, atol=1e-9)
    assert np.allclose(errors.tilt_deg[1:], 2.0, atol=1e-6)
    assert np.allclose(errors.heading_deg, 0.0, atol=1e-6)
    assert errors.along_m[0] == errors.tilt_deg[0] == 0.0
    assert np.allclose(errors.yaw_rate_deg_s, 10.0, rtol=0.02)


def test_a_heading_error_is_told_from_a_tilt():
    stamps, truth = turning_walk(yaw_rate_deg_s=0.0)
    estimate = truth.copy()
    estimate[1:, :3, :3] = rot_z(math.radians(-3.0)) @ truth[1:, :3, :3]
    errors = error_over_time((stamps, truth), (stamps, estimate))
    assert errors.heading_deg[1:] == pytest.approx(np.full(len(stamps) - 1, -3.0))
    assert np.abs(errors.tilt_deg).max() < 1e-6


def test_an_estimate_that_misses_the_ground_truth_in_time_is_an_error():
    stamps, truth = turning_walk()
    with pytest.raises(ValueError, match='match the ground truth'):
        error_over_time((stamps, truth), (stamps + 50_000_000, truth))


def test_the_plot_frames_a_short_drive_not_the_whole_map(tmp_path):
    """An 8 m drive over a 200 m map: the view is the drive and 10 m around it (a quarter of a long drive's
    extent), and the PNG is drawn with the map points in that view only."""
    from lego_loam_py.evaluation import plot_trajectories, view_limits

    drive = np.tile(np.eye(4), (9, 1, 1))
    drive[:, 0, 3] = np.arange(9.0) + 50.0  # x 50..58 m, y 0
    assert view_limits({'estimate': drive}) == (40.0, 68.0, -10.0, 10.0)
    long = np.tile(np.eye(4), (2, 1, 1))
    long[1, :3, 3] = (100.0, 40.0, 0.0)
    assert view_limits({'a': long, 'b': drive}) == (-25.0, 125.0, -25.0, 65.0)
    assert view_limits({'estimate': np.zeros((0, 4, 4))}) is None
    grid = np.stack(np.meshgrid(np.arange(-100.0, 100.0, 2.0), np.arange(-100.0, 100.0, 2.0)), -1).reshape(-1, 2)
    map_points = np.column_stack([grid, np.zeros(len(grid))])
    png = plot_trajectories(tmp_path / 'drive.png', {'estimate': drive}, map_points)
    assert png.stat().st_size > 1000
    far = map_points + 500.0  # no map point in view: still a picture
    assert plot_trajectories(tmp_path / 'far.png', {'estimate': drive}, far).stat().st_size > 1000
