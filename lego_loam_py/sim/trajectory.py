"""Continuous sensor trajectories: the lidar pose as a smooth function of time, with its derivatives.

A :class:`Trajectory` gives the pose of the **lidar frame** (REP-103 axes: x forward, y left, z up) in the
gravity-aligned simulator world (z up) at any time ``t`` [s since the start of the simulation]:
``p_world = R(t) p_lidar + p(t)``. Poses are vectorised over arrays of times.

Velocity, acceleration (world frame) and the angular velocity (lidar frame) come from the same pose
function by high-order central differences (5-point stencils, step 2 ms). The pose functions are built
from quintic splines (C4) and analytic terrain, so the stencils are exact to far below any sensor noise:
truncation error < 1e-9 and round-off < 1e-6 m/s^2 / 1e-9 rad/s. The lidar and the IMU therefore see one
and the same motion by construction.

:class:`PathTrajectory` drives a closed smooth path (:class:`ClosedPath`) at a speed profile that slows
down in curves (:class:`SpeedProfile`), follows a terrain with a four-wheel footprint (roll and pitch from
the wheel contact heights), and adds optional periodic oscillations (walking bob, sway).
:class:`InPlaceTurns` stops any trajectory at given moments for a whole turn on the spot.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import make_interp_spline
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from lego_loam_py.sim.scene import Terrain

__all__ = ['Trajectory', 'ClosedPath', 'SpeedProfile', 'Oscillation', 'PathTrajectory', 'InPlaceTurns', 'rotation_zyx']

_STEP = 2e-3  # [s] finite-difference step


def rotation_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations ``Rz(yaw) Ry(pitch) Rx(roll)`` [rad] (body -> world, REP-103 roll/pitch/yaw)."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    out = np.empty(np.shape(yaw) + (3, 3))
    out[..., 0, 0] = cy * cp
    out[..., 0, 1] = cy * sp * sr - sy * cr
    out[..., 0, 2] = cy * sp * cr + sy * sr
    out[..., 1, 0] = sy * cp
    out[..., 1, 1] = sy * sp * sr + cy * cr
    out[..., 1, 2] = sy * sp * cr - cy * sr
    out[..., 2, 0] = -sp
    out[..., 2, 1] = cp * sr
    out[..., 2, 2] = cp * cr
    return out


class Trajectory:
    """Base class: subclasses implement :meth:`pose`; derivatives follow from it."""

    #: time [s] after which the motion repeats (a closed loop), or None
    lap_time: float | None = None

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R (N, 3, 3) lidar -> world, p (N, 3) lidar origin in the world [m]) at times ``t`` [s]."""
        raise NotImplementedError

    def matrices(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) homogeneous poses world <- lidar."""
        rotation, position = self.pose(np.atleast_1d(np.asarray(t, dtype=float)))
        out = np.zeros((len(position), 4, 4))
        out[:, :3, :3] = rotation
        out[:, :3, 3] = position
        out[:, 3, 3] = 1.0
        return out

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) velocity of the lidar origin in the world [m/s]."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        h = _STEP
        p = [self.pose(t + k * h)[1] for k in (-2, -1, 1, 2)]
        return (p[0] - 8.0 * p[1] + 8.0 * p[2] - p[3]) / (12.0 * h)

    def acceleration(self, t: np.ndarray, offset: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) acceleration in the world [m/s^2] (gravity not included) of the lidar origin, or of the point
        fixed to the lidar at ``offset`` (3,) [m, lidar axes] (an IMU on a lever arm: the rotation adds the
        centripetal and tangential terms, which the differences of its world position contain)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        h = _STEP

        def position(times: np.ndarray) -> np.ndarray:
            rotation, origin = self.pose(times)
            return origin if offset is None else origin + rotation @ np.asarray(offset, dtype=float)

        p = [position(t + k * h) for k in (-2, -1, 0, 1, 2)]
        return (-p[0] + 16.0 * p[1] - 30.0 * p[2] + 16.0 * p[3] - p[4]) / (12.0 * h * h)

    def angular_velocity(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) angular velocity of the lidar frame w.r.t. the world, in lidar axes [rad/s]
        (what an axis-aligned gyroscope measures)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        h = _STEP
        r0 = Rotation.from_matrix(self.pose(t)[0])
        inv = r0.inv()
        f = {k: (inv * Rotation.from_matrix(self.pose(t + k * h)[0])).as_rotvec() for k in (-2, -1, 1, 2)}
        return (8.0 * (f[1] - f[-1]) - (f[2] - f[-2])) / (12.0 * h)


@dataclass(frozen=True)
class Oscillation:
    """A periodic perturbation ``amplitude * sin(2 pi frequency t + phase)`` of one pose channel.

    channel: 'surge' (along the path [m]), 'sway' (left [m]), 'heave' (up [m]), 'roll', 'pitch', 'yaw' [rad].
    """

    channel: str
    amplitude: float
    frequency: float  # [Hz]
    phase: float = 0.0

    def __call__(self, t: np.ndarray) -> np.ndarray:
        return self.amplitude * np.sin(2.0 * np.pi * self.frequency * t + self.phase)


_CHANNELS = ('surge', 'sway', 'heave', 'roll', 'pitch', 'yaw')


class ClosedPath:
    """A smooth closed planar curve through waypoints, parameterised by arc length ``s`` [m].

    A periodic quintic spline interpolates the waypoints (chord-length parameter); a second periodic
    quintic spline maps arc length to that parameter, so ``xy(s)`` moves at unit speed.
    """

    def __init__(self, waypoints: np.ndarray, arc_samples: int = 8192):
        points = np.asarray(waypoints, dtype=float)
        if points.ndim != 2 or points.shape[1] != 2 or len(points) < 4:
            raise ValueError('a closed path needs at least 4 waypoints (x, y)')
        if np.allclose(points[0], points[-1]):
            points = points[:-1]
        self.waypoints = points.copy()
        closed = np.vstack([points, points[:1]])
        chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
        self._curve = make_interp_spline(chord, closed, k=5, bc_type='periodic')
        self._curve_d1 = self._curve.derivative(1)
        u_total = chord[-1]
        # Arc length s(u) by dense trapezoid integration of |dxy/du|.
        u = np.linspace(0.0, u_total, arc_samples + 1)
        speed = np.linalg.norm(self._curve_d1(u), axis=1)
        s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(u))])
        self.length = float(s[-1])
        residual = u - s * (u_total / self.length)  # periodic in s
        residual[-1] = residual[0]
        self._u_scale = u_total / self.length
        self._u_of_s = make_interp_spline(s, residual, k=5, bc_type='periodic')
        self._u_total = u_total

    def _u(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, dtype=float)
        return s * self._u_scale + self._u_of_s(np.mod(s, self.length))

    def xy(self, s: np.ndarray) -> np.ndarray:
        """(N, 2) point at arc length ``s`` (any real value; the path repeats every ``length``)."""
        return self._curve(np.mod(self._u(s), self._u_total))

    def tangent(self, s: np.ndarray) -> np.ndarray:
        """(N, 2) unit tangent (direction of travel)."""
        d = self._curve_d1(np.mod(self._u(s), self._u_total))
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def curvature(self, s: np.ndarray) -> np.ndarray:
        """Signed curvature [1/m] (positive: turning left)."""
        u = np.mod(self._u(s), self._u_total)
        d1 = self._curve_d1(u)
        d2 = self._curve.derivative(2)(u)
        return (d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]) / np.linalg.norm(d1, axis=-1) ** 3

    def reversed(self) -> ClosedPath:
        """The same curve travelled the other way, from the same first waypoint: the point at arc length
        ``s`` of the reversed path is the one at ``length - s`` of this one. (The interpolating spline through
        the reversed waypoints is this one's, run backwards: the periodic interpolant is unique and the chord
        lengths are the same.)"""
        return ClosedPath(np.vstack([self.waypoints[:1], self.waypoints[:0:-1]]))

    def polyline(self, spacing: float = 0.5) -> np.ndarray:
        """(N, 2) points along the path about ``spacing`` [m] apart (for placing scenery)."""
        n = max(8, int(np.ceil(self.length / spacing)))
        return self.xy(np.arange(n) * (self.length / n))


class SpeedProfile:
    """Arc-length position on a closed path as a smooth function of time, ``s(t)`` [m], ``s(0) = start``.

    The speed is ``cruise_speed`` [m/s], reduced in curves so that the lateral acceleration stays below
    ``max_lateral_acceleration`` [m/s^2] (``None``: constant speed), smoothed along the path over
    ``smoothing`` [m] so that braking and accelerating are gradual. ``s(t)`` is exact at the lap time
    (``s(lap_time) = start + length``) and repeats lap after lap.
    """

    def __init__(
        self,
        path: ClosedPath,
        cruise_speed: float,
        max_lateral_acceleration: float | None = None,
        smoothing: float = 10.0,
        start: float = 0.0,
        samples: int = 8192,
    ):
        self.cruise_speed = float(cruise_speed)
        self.start = float(start)
        self.max_lateral_acceleration = max_lateral_acceleration
        self.smoothing = float(smoothing)
        self.samples = int(samples)
        length = path.length
        s = self.start + np.linspace(0.0, length, samples, endpoint=False)
        speed = np.full(samples, float(cruise_speed))
        if max_lateral_acceleration is not None:
            curvature = np.abs(path.curvature(s))
            limit = np.sqrt(max_lateral_acceleration / np.maximum(curvature, 1e-9))
            speed = np.minimum(speed, limit)
            sigma = smoothing / (length / samples)
            # Smooth the inverse speed (time per metre) so that slow sections keep their duration.
            pace = gaussian_filter1d(1.0 / speed, sigma, mode='wrap')
            speed = 1.0 / pace
        pace = 1.0 / speed
        s_closed = np.append(s - self.start, length)
        pace_closed = np.append(pace, pace[0])
        t = np.concatenate([[0.0], np.cumsum(0.5 * (pace_closed[1:] + pace_closed[:-1]) * np.diff(s_closed))])
        self.lap_time = float(t[-1])
        self.length = length
        residual = s_closed - t * (length / self.lap_time)
        residual[-1] = residual[0]
        self._residual = make_interp_spline(t, residual, k=5, bc_type='periodic')
        self.min_speed = float(speed.min())
        self.max_speed = float(speed.max())

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        return self.start + t * (self.length / self.lap_time) + self._residual(np.mod(t, self.lap_time))

    def on(self, path: ClosedPath, start: float) -> SpeedProfile:
        """The same driving (cruise speed, lateral limit, smoothing) on ``path`` from arc length ``start`` [m]."""
        return SpeedProfile(path, self.cruise_speed, self.max_lateral_acceleration, self.smoothing, start, self.samples)


class PathTrajectory(Trajectory):
    """A platform following a closed path over a terrain, carrying the lidar ``sensor_height`` above the
    ground along its own z axis.

    Heading follows the path tangent; pitch and roll come from the terrain heights under the four wheels
    (``wheelbase`` x ``track`` [m]; a walker uses a small footprint); ``oscillations`` add bob, sway and
    head motion. The arc length at t = 0 is the speed profile's ``start``.
    """

    def __init__(
        self,
        path: ClosedPath,
        speed: SpeedProfile,
        terrain: Terrain,
        sensor_height: float,
        wheelbase: float = 1.0,
        track: float = 0.8,
        oscillations: Sequence[Oscillation] = (),
    ):
        for o in oscillations:
            if o.channel not in _CHANNELS:
                raise ValueError(f"unknown oscillation channel '{o.channel}' (use one of {_CHANNELS})")
        self.path = path
        self.speed = speed
        self.terrain = terrain
        self.sensor_height = float(sensor_height)
        self.wheelbase = float(wheelbase)
        self.track = float(track)
        self.oscillations = tuple(oscillations)
        # The motion repeats only when every oscillation fits a whole number of times into a lap.
        lap = speed.lap_time
        self.lap_time = (
            lap if all(abs(o.frequency * lap - round(o.frequency * lap)) < 1e-9 for o in oscillations) else None
        )

    def _channel(self, name: str, t: np.ndarray) -> np.ndarray | float:
        total: np.ndarray | float = 0.0
        for o in self.oscillations:
            if o.channel == name:
                total = total + o(t)
        return total

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        s = self.speed(t) + self._channel('surge', t)
        xy = self.path.xy(s)
        tangent = self.path.tangent(s)
        normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)  # left of the direction of travel
        half_l, half_w = 0.5 * self.wheelbase, 0.5 * self.track
        heights = {}
        for name, a, b in (
            ('fl', half_l, half_w),
            ('fr', half_l, -half_w),
            ('rl', -half_l, half_w),
            ('rr', -half_l, -half_w),
        ):
            contact = xy + a * tangent + b * normal
            heights[name] = self.terrain.height(contact[:, 0], contact[:, 1])
        front = 0.5 * (heights['fl'] + heights['fr'])
        rear = 0.5 * (heights['rl'] + heights['rr'])
        left = 0.5 * (heights['fl'] + heights['rl'])
        right = 0.5 * (heights['fr'] + heights['rr'])
        yaw = np.arctan2(tangent[:, 1], tangent[:, 0]) + self._channel('yaw', t)
        pitch = np.arctan2(rear - front, self.wheelbase) + self._channel('pitch', t)
        roll = np.arctan2(left - right, self.track) + self._channel('roll', t)
        rotation = rotation_zyx(yaw, pitch, roll)
        ground = np.column_stack([xy, 0.25 * (front + rear + left + right)])
        mount = np.zeros((len(t), 3))
        mount[:, 1] = self._channel('sway', t)
        mount[:, 2] = self.sensor_height + self._channel('heave', t)
        return rotation, ground + np.einsum('nij,nj->ni', rotation, mount)

    def on_route(self, start: float | None = None, reverse: bool = False) -> PathTrajectory:
        """The same platform, driving and scene on another route along this path: from arc length ``start``
        [m, measured along this path's direction; None: this trajectory's own start], and with ``reverse`` the
        other way round (speed limits in curves, terrain and oscillations as before)."""
        start = self.speed.start if start is None else float(start)
        path = self.path.reversed() if reverse else self.path
        arc = (-start) % self.path.length if reverse else start
        return PathTrajectory(
            path,
            self.speed.on(path, arc),
            self.terrain,
            self.sensor_height,
            self.wheelbase,
            self.track,
            self.oscillations,
        )


def _smoothstep(x: np.ndarray) -> np.ndarray:
    """The quintic step ``6x^5 - 15x^4 + 10x^3`` on [0, 1] (0 below, 1 above): zero first and second
    derivatives at both ends; its slope peaks at 15/8 in the middle."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _smoothstep_integral(x: np.ndarray) -> np.ndarray:
    """``integral_0^x smoothstep`` for x in [0, 1] (1/2 at 1)."""
    x = np.clip(x, 0.0, 1.0)
    return x**4 * (x * (x - 3.0) + 2.5)


class InPlaceTurns(Trajectory):
    """``base`` with whole turns on the spot inserted: at each of the base times ``at`` [s] the platform
    brakes to a standstill (over ``brake`` s), turns ``angle`` [deg] (positive: left, about the world's
    vertical through the lidar) with a smooth yaw profile whose rate peaks at ``peak_rate`` [deg/s], then
    walks on as ``base`` did. The pose before and after a whole turn is the same, so the rest of the
    trajectory is the base one, :attr:`pause` later per turn.

    While braking and standing, the base trajectory slows down with it (its bob and sway too): base time
    runs at ``1 - h(t)`` of real time, with ``h`` a quintic step from 0 to 1 and back, so the motion stays
    smooth (C2) and the IMU sees it as the lidar does. Each turn alternates direction.
    """

    def __init__(
        self, base: Trajectory, at: Sequence[float], peak_rate: float, angle: float = 360.0, brake: float = 1.0
    ):
        if not peak_rate > 0 or not angle > 0 or not brake > 0:
            raise ValueError('an in-place turn needs a positive peak rate, angle and braking time')
        self.base = base
        self.angle = math.radians(angle)
        self.brake = float(brake)
        # The quintic step's slope peaks at 15/8 per unit time: the turn lasts angle * 15/8 / peak rate.
        self.turn_time = self.angle * 1.875 / math.radians(peak_rate)
        # Real time added per turn [s]: braking and walking on each lose brake/2 of base time.
        self.pause = self.brake + self.turn_time
        base_times = np.sort(np.asarray(at, dtype=float))
        # Real time each stop begins: the base time reaches `at` at the standstill, braking having lost
        # brake/2 of it, later by the pauses of the turns before.
        self.starts = base_times - 0.5 * self.brake + self.pause * np.arange(len(base_times))
        self.directions = np.where(np.arange(len(base_times)) % 2 == 0, 1.0, -1.0)
        self.lap_time = None

    def _lost(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(base time lost to the stops by real time t [s], the yaw the turns added [rad])."""
        lost = np.zeros_like(t)
        yaw = np.zeros_like(t)
        b, turn = self.brake, self.turn_time
        for start, direction in zip(self.starts, self.directions):
            tau = t - start
            braking = b * _smoothstep_integral(tau / b)
            standing = np.clip(tau - b, 0.0, turn)
            x = (tau - b - turn) / b
            walking_on = b * (np.clip(x, 0.0, 1.0) - _smoothstep_integral(x))
            lost += braking + standing + walking_on
            yaw += direction * self.angle * _smoothstep((tau - b) / turn)
        return lost, yaw

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        lost, yaw = self._lost(t)
        rotation, position = self.base.pose(t - lost)
        return rotation_zyx(yaw, np.zeros_like(yaw), np.zeros_like(yaw)) @ rotation, position
