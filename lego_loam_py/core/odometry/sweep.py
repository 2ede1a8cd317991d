"""Motion within one sweep (docs/original.md §5.3, §6.2 steps 1, 8 and 10): relative times, deskewing and the
six-vector conventions the scan-to-scan odometry uses.

Conventions (LOAM camera axes: x left, y up, z forward). The motion over one sweep is the six-vector
``θ = (rx, ry, rz, tx, ty, tz)`` with ``R(θ) = Rz(rz) Rx(rx) Ry(ry)``: a point measured at relative time ``s``
of the sweep maps to the sweep-start frame as ``p_start = R(sθ)^T (p - s t)`` (linear interpolation of the
motion = deskewing without IMU). The accumulated pose ``transform_sum`` uses the world convention
``R = Ry(ry) Rx(rx) Rz(rz)`` (:func:`lego_loam_py.core.frames.euler_to_matrix`); each sweep composes
``W_{k+1} = W_k · T(θ)^-1``.

A point's intensity carries its ring and relative time as ``ring + 0.1 s`` (:func:`ring_of`,
:func:`relative_time_of`); :func:`relative_time_from_azimuth` and :func:`relative_time` give ``s``.
"""

from __future__ import annotations

import math

import numpy as np

from lego_loam_py.core.frames import (
    GENERATOR_X,
    GENERATOR_Y,
    GENERATOR_Z,
    euler_to_matrix,
    invert_pose,
    matrix_to_euler,
    rot_x,
    rot_y,
    rot_z,
    scaled_motion,
)
from lego_loam_py.core.indexing import copy_columns, xyz_columns
from lego_loam_py.core.parity.libm import atan2f
from lego_loam_py.core.projection.cloud_info import CloudInfo

try:  # SweepStartFrame's products and rows in C (native/feature_kernels.c); optional, NumPy gives the same
    from lego_loam_py.core import _feature_kernels
except ImportError:
    _feature_kernels = None
try:  # the azimuths' relative times in one pass (native/libm_compat.c); optional, NumPy gives the same
    from lego_loam_py.core import _libm_compat
except ImportError:
    _libm_compat = None

__all__ = [
    'sweep_rotation',
    'sweep_angles',
    'ring_of',
    'relative_time_of',
    'relative_time_from_azimuth',
    'relative_time',
    'SweepStartFrame',
    'SweepTrig',
    'transform_to_start',
    'transform_to_end',
    'start_jacobian',
    'plane_jacobian_rows',
    'accumulate',
    'motion_to_theta',
    'imu_free_motion',
    'StampInstant',
]

_F32 = np.float32
TWO_PI = 2 * math.pi


def sweep_rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    """``R(θ) = Rz(rz) Rx(rx) Ry(ry)`` of a sweep motion."""
    return rot_z(rz) @ rot_x(rx) @ rot_y(ry)


def sweep_angles(rotation: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`sweep_rotation`: (rx, ry, rz) with rx in [-pi/2, pi/2]."""
    rx = math.asin(max(-1.0, min(1.0, float(rotation[2, 1]))))
    ry = math.atan2(-rotation[2, 0], rotation[2, 2])
    rz = math.atan2(-rotation[0, 1], rotation[1, 1])
    return rx, ry, rz


def ring_of(intensity: np.ndarray) -> np.ndarray:
    """C ``int()`` of the intensity (truncation toward zero): the ring stored in the integer part."""
    return np.trunc(intensity).astype(np.int64)


def relative_time_of(intensity: np.ndarray) -> np.ndarray:
    """``s = 10 * (intensity - int(intensity))`` in float32, the fraction of the sweep a point was measured at."""
    intensity = np.asarray(intensity, dtype=_F32)
    return _F32(10) * (intensity - np.trunc(intensity).astype(_F32))


def relative_time_from_azimuth(points_lidar: np.ndarray, info: CloudInfo, native: bool = True) -> np.ndarray:
    """Relative time in [0, 1) of each point: its clockwise angle from the start orientation, modulo a turn,
    over the sweep's orientation difference. In C for float32 rows when the extension is built (one pass instead
    of some ten NumPy calls and two column copies); ``native=False`` runs the NumPy version (the tests compare the
    two)."""
    start, diff = float(info.start_orientation), float(info.orientation_diff)
    if (
        native
        and hasattr(_libm_compat, 'azimuth_fraction')
        and isinstance(points_lidar, np.ndarray)
        and points_lidar.dtype == _F32
        and points_lidar.ndim == 2
        and points_lidar.shape[1] >= 2
        and points_lidar.flags.c_contiguous
    ):
        out = np.empty(len(points_lidar), dtype=_F32)
        _libm_compat.azimuth_fraction(points_lidar, points_lidar.shape[1], start, TWO_PI, diff, out)
        return out
    ori = -atan2f(points_lidar[:, 1], points_lidar[:, 0]).astype(np.float64)
    angle = np.mod(ori - start, TWO_PI)
    return (angle / diff).astype(_F32)


def relative_time(points_lidar: np.ndarray, info: CloudInfo) -> np.ndarray:
    """Relative time in [about -0.25, 1.25] of each point from its azimuth, as the original computes it.

    The orientation ``-atan2(y, x)`` is unwrapped against the sweep's start orientation until it passes
    half a turn and against the end orientation afterwards; the switch happens once per cloud (the cloud is
    ordered by ring, so later rings use the end rule throughout and their first quarter gets 1 + s).
    """
    ori = -atan2f(points_lidar[:, 1], points_lidar[:, 0]).astype(np.float64)
    start = float(info.start_orientation)
    end = float(info.end_orientation)
    first = np.where(
        ori < start - math.pi / 2, ori + TWO_PI, np.where(ori > start + 3 * math.pi / 2, ori - TWO_PI, ori)
    )
    first = first.astype(_F32)
    passed = (first - _F32(start)).astype(np.float64) > math.pi
    switch = int(np.argmax(passed)) if passed.any() else len(ori)
    second = (ori + TWO_PI).astype(_F32).astype(np.float64)
    second = np.where(
        second < end - 3 * math.pi / 2, second + TWO_PI, np.where(second > end + math.pi / 2, second - TWO_PI, second)
    ).astype(_F32)
    final = np.where(np.arange(len(ori)) <= switch, first, second)
    return ((final - _F32(start)) / _F32(info.orientation_diff)).astype(_F32)


class SweepTrig:
    """``cos(s θ_k)`` and ``sin(s θ_k)`` of fixed relative times ``s`` (n,) float64, remembered per angle (by its
    bits): a registration stage moves three of the six parameters, so the sines and cosines of the angles it
    holds fixed are the same at every evaluation, and those it moves repeat between a step's trial and the next
    iteration. The same products and the same elementwise functions as :class:`SweepStartFrame` computes."""

    def __init__(self, s: np.ndarray):
        self.s = s
        self._known: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def of(self, transform: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """(cosines, sines) of the three angles of ``transform`` (float64), each a list of three (n,) arrays."""
        keys = list(enumerate(transform[:3].view(np.int64).tolist()))
        missing = [k for k, key in enumerate(keys) if key not in self._known]
        if missing:  # all missing angles in one call each (small arrays: per-call cost dominates)
            angles = np.multiply.outer(transform[missing], self.s)
            for k, cosine, sine in zip(missing, np.cos(angles), np.sin(angles)):
                self._known[keys[k]] = cosine, sine
        pairs = [self._known[key] for key in keys]
        return [pair[0] for pair in pairs], [pair[1] for pair in pairs]


class SweepStartFrame:
    """``R(sθ)^T (p - s t)`` of fixed points at one ``θ`` and its Jacobian rows, sharing the per-point sines,
    cosines and partial products (the Gauss-Newton loop evaluates both at every step).

    ``R(sθ)^T = Ry(-s ry) Rx(-s rx) Rz(-s rz)`` is applied right to left: ``u = Rz q``, ``v = Rx u`` with
    ``q = p - s t``, the start point is ``Ry v``.
    """

    def __init__(
        self, xyz: np.ndarray, s: np.ndarray, transform: np.ndarray, trig: SweepTrig | None = None, native: bool = True
    ):
        """``xyz`` (3, n) float64, ``s`` (n,) float64; ``trig``: the sines and cosines of these ``s`` remembered
        (:class:`SweepTrig`). The products and start points in C when the extension is built (one pass instead of
        some twenty NumPy calls); ``native=False`` runs the NumPy version (the tests compare the two)."""
        transform = np.asarray(transform, dtype=np.float64)
        self.s = s
        if trig is None:
            # The three angles (and the three coordinates) in one call each: small arrays, per-call cost dominates.
            angles = np.multiply.outer(transform[:3], s)
            cosines, sines = np.cos(angles), np.sin(angles)
        else:
            cosines, sines = trig.of(transform)
        self._factors = {}
        self._block = self._start = None
        if native and hasattr(_feature_kernels, 'sweep_frame') and xyz.dtype == np.float64 and s.dtype == np.float64:
            self._block = np.empty((14, len(s)))
            self._start = np.empty((len(s), 3), dtype=_F32)
            _feature_kernels.sweep_frame(
                np.ascontiguousarray(xyz),
                np.ascontiguousarray(s),
                np.ascontiguousarray(transform[3:6]),
                *(np.ascontiguousarray(v) for v in (*cosines, *sines)),
                self._block,
                self._start,
            )
            (self.cx, self.sx, self.cy, self.sy, self.cz, self.sz, _, self.qx, self.qy, self.qz) = self._block[:10]
            self.ux, self.uy, self.vz, self.vy = self._block[10:]
            return
        self.cx, self.cy, self.cz = cosines
        self.sx, self.sy, self.sz = sines
        self.qx, self.qy, self.qz = xyz - np.multiply.outer(transform[3:], s)
        cx, sx, cz, sz = self.cx, self.sx, self.cz, self.sz
        self.ux, self.uy = cz * self.qx + sz * self.qy, -sz * self.qx + cz * self.qy  # uz = qz
        self.vy, self.vz = cx * self.uy + sx * self.qz, -sx * self.uy + cx * self.qz  # vx = ux

    @classmethod
    def of(cls, points: np.ndarray, transform: np.ndarray) -> SweepStartFrame:
        """For (n, 4) points with intensity ring + 0.1 s."""
        xyz = points[:, :3].T.astype(np.float64, order='C')
        return cls(xyz, relative_time_of(points[:, 3]).astype(np.float64), transform)

    def xyz(self) -> np.ndarray:
        """(n, 3) float32 start points (made with the frame in C: not to be written to)."""
        if self._start is not None:
            return self._start
        out = np.empty((len(self.s), 3), dtype=_F32)
        out[:, 0] = self.cy * self.ux - self.sy * self.vz
        out[:, 1] = self.vy
        out[:, 2] = self.sy * self.ux + self.cy * self.vz
        return out

    def _factor(self, column: int):
        """The coefficient-free parts of a rotation column (see :meth:`rows`)."""
        if column not in self._factors:
            cx, sx, cy, sy, cz, sz = self.cx, self.sx, self.cy, self.sy, self.cz, self.sz
            if column == 0:  # dRx(-rx) u = (0, -sx uy + cx uz, -cx uy - sx uz)
                value = (-sx * self.uy + cx * self.qz, -cx * self.uy - sx * self.qz)
            elif column == 1:  # dRy(-ry) v = (-sy vx - cy vz, 0, cy vx - sy vz)
                value = (-sy * self.ux - cy * self.vz, cy * self.ux - sy * self.vz)
            else:  # dRz(-rz) q = (-sz qx + cz qy, -cz qx - sz qy, 0)
                value = (-sz * self.qx + cz * self.qy, -cz * self.qx - sz * self.qy)
            self._factors[column] = value
        return self._factors[column]

    def rows(self, coeff: np.ndarray, active: list[int], native: bool = True) -> np.ndarray:
        """``coeff · d/dθ_active [R(sθ)^T (p - s t)]``: (n, len(active)) for ``coeff`` (n, 3) float64, or for
        m coefficient vectors per point, ``coeff`` (n, m, 3), (n * m, len(active)) point by point (all m
        in the same calls).

        The rotation derivatives are ``s Ry Rx dRz q``, ``s Ry dRx u`` and ``s dRy v``; the translation ones
        ``-s R^T e_k``, dotted with ``coeff``: ``-s (Rz^T Rx^T Ry^T coeff)_k``. No per-point 3x3 matrices.
        In C when the extension is built (the same expressions in one pass instead of some forty NumPy calls);
        ``native=False`` runs the NumPy version (the tests compare the two).
        """
        batched = coeff.ndim == 3
        if native and hasattr(_feature_kernels, 'sweep_rows') and coeff.dtype == np.float64:
            per_point = (
                self._block[:13]
                if self._block is not None
                else np.array(
                    (self.cx, self.sx, self.cy, self.sy, self.cz, self.sz, self.s)
                    + (self.qx, self.qy, self.qz, self.ux, self.uy, self.vz),
                    dtype=np.float64,
                )
            )
            out = np.empty((len(active), coeff.size // 3))
            _feature_kernels.sweep_rows(per_point, np.ascontiguousarray(coeff), np.asarray(active, dtype=np.int64), out)
            return out.T  # (column by column, as the NumPy version returns them)

        def per_point(value):
            return value[:, None] if batched else value

        cx, sx, cy, sy, cz, sz, s = (
            per_point(v) for v in (self.cx, self.sx, self.cy, self.sy, self.cz, self.sz, self.s)
        )
        ax, ay, az = coeff[..., 0], coeff[..., 1], coeff[..., 2]
        # coeff^T Ry: the row vector that turns a vector w into coeff · (Ry w); then the same for Ry Rx w.
        bx, by, bz = ax * cy + az * sy, ay, -ax * sy + az * cy
        cx_, cy_ = bx, by * cx - bz * sx
        # Filled and returned column by column (Fortran order, as the solver has always received them).
        out = np.empty((len(active),) + coeff.shape[:-1])
        for j, column in enumerate(active):
            if column == 0:
                f1, f2 = (per_point(f) for f in self._factor(0))
                value = by * f1 + bz * f2
            elif column == 1:
                f1, f2 = (per_point(f) for f in self._factor(1))
                value = ax * f1 + az * f2
            elif column == 2:
                f1, f2 = (per_point(f) for f in self._factor(2))
                value = cx_ * f1 + cy_ * f2
            elif column == 3:
                value = -(cx_ * cz - cy_ * sz)
            elif column == 4:
                value = -(cx_ * sz + cy_ * cz)
            else:
                value = -(by * sx + bz * cx)
            out[j] = value * s
        return out.reshape(len(active), -1).T


def transform_to_start(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Map (n, 4) points (camera axes, intensity = ring + 0.1 s) to the sweep start: ``R(sθ)^T (p - s t)``."""
    out = np.empty((len(points), 4), dtype=_F32)
    copy_columns(out, SweepStartFrame.of(points, transform).xyz())
    out[:, 3] = points[:, 3]
    return out


def transform_to_end(
    points: np.ndarray,
    transform: np.ndarray,
    imu_correction: np.ndarray | None = None,
    imu_shift: np.ndarray | None = None,
) -> np.ndarray:
    """Re-project a sweep's points to its end: to the start with :func:`transform_to_start`, then
    ``p_end = R(θ) p_start + t``; with an IMU, then ``C (p_end - shift)`` (``C`` = IMU rotation from the end
    attitude back, see :class:`FeatureAssociation`). The intensity becomes the ring (``int``)."""
    start = transform_to_start(points, transform)
    rotation = sweep_rotation(*transform[:3])
    end = xyz_columns(start) @ rotation.T + np.asarray(transform[3:], dtype=np.float64)
    if imu_correction is not None:
        shift = np.zeros(3) if imu_shift is None else np.asarray(imu_shift, dtype=np.float64)
        end = (end - shift) @ np.asarray(imu_correction).T
    out = np.empty((len(points), 4), dtype=_F32)
    copy_columns(out, end)
    out[:, 3] = np.trunc(points[:, 3])
    return out


def start_jacobian(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """(n, 3, 6): derivative of ``R(θ)^T (p - t)`` w.r.t. (rx, ry, rz, tx, ty, tz) at the full ``θ``."""
    rx, ry, rz = (float(v) for v in transform[:3])
    t = np.asarray(transform[3:], dtype=np.float64)
    Ry_, Rx_, Rz_ = rot_y(-ry), rot_x(-rx), rot_z(-rz)
    q = points[:, :3].astype(np.float64) - t
    d_rx = Ry_ @ (-Rx_ @ GENERATOR_X) @ Rz_  # d/drx of Ry(-ry) Rx(-rx) Rz(-rz)
    d_ry = (-Ry_ @ GENERATOR_Y) @ Rx_ @ Rz_
    d_rz = Ry_ @ Rx_ @ (-Rz_ @ GENERATOR_Z)
    rotation_t = Ry_ @ Rx_ @ Rz_
    jac = np.empty((len(points), 3, 6))
    jac[:, :, 0] = q @ d_rx.T
    jac[:, :, 1] = q @ d_ry.T
    jac[:, :, 2] = q @ d_rz.T
    jac[:, :, 3:] = -rotation_t[None, :, :]
    return jac


def plane_jacobian_rows(points: np.ndarray, coeff: np.ndarray, transform: np.ndarray, active: list[int]) -> np.ndarray:
    """The original model's rows of the Gauss-Newton matrix: ``coeff_xyz · J(θ)_active`` for each point, the
    derivative at the full motion whatever the point's time (the sweep-start model differentiates its residual
    exactly, :meth:`SweepStartFrame.rows`)."""
    jac = start_jacobian(points, transform)[:, :, active]
    return np.einsum('ni,nij->nj', coeff[:, :3].astype(np.float64), jac)


def accumulate(transform_sum: np.ndarray, transform_cur: np.ndarray, imu_shift: np.ndarray | None = None) -> np.ndarray:
    """``W_new = W · T(θ)^-1``: the accumulated pose after a sweep, as six-vectors (world convention).

    ``imu_shift`` (camera axes, sweep-start frame) is subtracted from the sweep translation first, as the
    original does with the IMU's non-linear shift.
    """
    world = euler_to_matrix(*transform_sum[:3])
    sweep = sweep_rotation(*transform_cur[:3])
    rotation = world @ sweep.T
    t_cur = np.asarray(transform_cur[3:], dtype=np.float64)
    if imu_shift is not None:
        t_cur = t_cur - imu_shift
    translation = np.asarray(transform_sum[3:], dtype=np.float64) - rotation @ t_cur
    return np.array([*matrix_to_euler(rotation), *translation])


def motion_to_theta(motion: np.ndarray) -> np.ndarray:
    """Six-vector θ (sweep convention) of a sweep whose end is at pose ``motion``: ``T(θ) = motion^-1``."""
    forward = invert_pose(motion)
    return np.array([*sweep_angles(forward[:3, :3]), *forward[:3, 3]])


def imu_free_motion(theta: np.ndarray, delta_end: np.ndarray, shift_end: np.ndarray) -> np.ndarray:
    """The whole motion of a sweep registered after IMU deskewing, as an IMU-free six-vector (sweep convention):
    ``theta`` is what the registration found beyond the IMU's rotation ``delta_end`` and shift ``shift_end``. The
    sweep end in the start frame is ``T(θ)^-1 · [ΔR, shift]``; its inverse is the full T."""
    full_rotation = delta_end.T @ sweep_rotation(*theta[:3])
    full_translation = delta_end.T @ (np.asarray(theta[3:]) - shift_end)
    return np.array([*sweep_angles(full_rotation), *full_translation])


class StampInstant:
    """The sweep-start model's outputs at the instant the header stamp was taken (``sensor.stamp_position`` s0,
    a fraction of the sweep): the odometry registers sweep starts, and a driver that stamps a sweep with its last
    packet (s0 = 1) would otherwise get every pose one sweep late.

    With ``M`` the sensor's pose at s0 in its sweep-start frame (the sweep's motion, scaled), the published pose
    is ``C W M`` and the published clouds ``M^-1 p``, where ``W`` is the sweep-start pose and ``C`` keeps the
    first published pose where the odometry started (camera_init is the sensor at the first stamp). The motion
    registered after a gap (a scan dropped on the way) spans more than a sweep: only one sweep's share of it is
    taken. At s0 = 0 nothing changes."""

    def __init__(self, params):
        self.position = float(params.sensor.stamp_position)
        self.period_ns = params.sensor.scan_period * 1e9
        self.offset_s = self.position * params.sensor.scan_period  # from the sweep start to the stamp [s]
        self.active = self.position > 0.0
        self._origin = np.eye(4)  # sweep-start pose the odometry started from
        self._correction = None  # C, fixed by the first sweep motion (kept across restarts)
        self._last_stamp_ns = None

    def sweep_start(self, stamp_ns: int) -> float:
        """[s] the sweep stamped ``stamp_ns`` began."""
        return stamp_ns * 1e-9 - self.offset_s

    def begin(self, world_pose: np.ndarray, stamp_ns: int | None = None) -> None:
        """The odometry (re)starts at this sweep-start pose (4x4), on the scan stamped ``stamp_ns``."""
        self._last_stamp_ns = stamp_ns
        if self._correction is None:
            self._origin = np.array(world_pose, dtype=float)

    def within(self, motion: np.ndarray, share: float = 1.0) -> np.ndarray:
        """4x4 pose at s0 in the sweep-start frame, for a sweep that moved by ``motion`` (the next start's pose);
        ``share``: the part of ``motion`` one sweep makes."""
        fraction = self.position * share
        if fraction == 1.0:
            return np.array(motion, dtype=float)
        return scaled_motion(motion, fraction)

    def share(self, stamp_ns: int) -> float:
        """The part of the motion registered at the scan stamped ``stamp_ns`` that one sweep makes."""
        last, self._last_stamp_ns = self._last_stamp_ns, stamp_ns
        gap = 0.0 if last is None else float(stamp_ns - last)
        return min(1.0, self.period_ns / gap) if gap > 1.5 * self.period_ns else 1.0

    def pose(self, world_pose: np.ndarray, motion: np.ndarray, share: float = 1.0) -> np.ndarray:
        """The published pose (4x4) of a sweep starting at ``world_pose`` and moving by ``motion`` (``share``:
        :meth:`share`)."""
        at_stamp = self.within(motion, share)
        if self._correction is None:
            self._correction = self._origin @ invert_pose(at_stamp) @ invert_pose(self._origin)
        return self._correction @ world_pose @ at_stamp

    def cloud(self, points: np.ndarray, motion: np.ndarray, share: float = 1.0) -> np.ndarray:
        """(n, 4) float32 points of the sweep-start frame in the frame at s0 (intensity kept)."""
        to_stamp = invert_pose(self.within(motion, share))
        out = points.copy()
        copy_columns(out, xyz_columns(points) @ to_stamp[:3, :3].T + to_stamp[:3, 3])
        return out
