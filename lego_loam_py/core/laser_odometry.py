"""Scan-to-scan odometry of featureAssociation (docs/original.md §5.3, §6.2 steps 5-10, quirks 8.1, 8.10, 8.11).

Conventions (LOAM camera axes: x left, y up, z forward). The motion over one sweep is the six-vector
``transform_cur = (rx, ry, rz, tx, ty, tz)`` with ``R(θ) = Rz(rz) Rx(rx) Ry(ry)``: a point measured at
relative time ``s`` of the sweep maps to the sweep-start frame as ``p_start = R(sθ)^T (p - s t)``
(linear interpolation of the motion = deskewing without IMU). The previous sweep's features are expressed
in its end frame, which is the current sweep's start frame, so registering the current features against
them estimates ``θ``. The accumulated pose ``transform_sum`` uses the world convention
``R = Ry(ry) Rx(rx) Rz(rz)`` (:func:`lego_loam_py.core.frames.euler_to_matrix`); each sweep composes
``W_{k+1} = W_k · T(θ)^-1``.

Registration is the original's two-step Gauss-Newton: planes from flat (ground) points fix
``(rx, rz, ty)``, then lines from sharp points fix ``(ry, tx, tz)``. Each step moves 5 % of the full
Gauss-Newton step, correspondences are re-associated every 5 iterations and weighted from iteration 5 on,
directions whose eigenvalue is below the threshold on the first iteration are frozen, and iterations stop
when the update is below 0.1 deg and 0.1 cm. ``transform_cur`` is not reset between sweeps, which is the
constant-velocity prior. Jacobians are the analytic derivatives of ``R(θ)^T (p - t)`` with respect to the
active parameters at the full ``θ`` (as the original, which does not scale them by ``s``).

Correspondence search follows the original: nearest neighbour in the last cloud (KD-tree), then the
nearest point on the same ring and on another ring within ±2.5 rings, scanning the ring-ordered last cloud
outwards from the nearest neighbour; the forward scan is bounded by the *current* feature count (quirk 8.1,
kept for parity; ``fix_scan_bound`` removes it).

The default sweep-start model (``odometry_model: sweep_start``, an exact Jacobian) differs on purpose:
full Gauss-Newton steps in blocks of ``reassociate_every`` iterations with fixed weights and backtracking
(:meth:`LaserOdometry._register_blocks`), and the point-to-line residual is the perpendicular offset as a
3-vector, smooth where a point meets its line. It keeps the original's correspondence search with quirk
8.1: searching whole neighbouring rings instead (no bound) was measured worse, 46 % instead of 4.6 % drift
in the simulated corridor with IMU, where the bound keeps matches near the scan's own stretch of wall.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from lego_loam_py.core.frames import euler_to_matrix, matrix_to_euler, rot_x, rot_y, rot_z
from lego_loam_py.core.params import Params

__all__ = ['sweep_rotation', 'sweep_angles', 'transform_to_start', 'transform_to_end', 'plane_jacobian_rows',
           'LaserOdometry', 'OdometryStats', 'accumulate', 'CornerCorrespondences', 'SurfCorrespondences',
           'find_surf_correspondences', 'find_corner_correspondences', 'ring_of']

_F32 = np.float32
_GX = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # d/da Rx(a) = Rx(a) @ _GX
_GY = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
_GZ = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


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


class _SweepStart:
    """``R(sθ)^T (p - s t)`` of fixed points at one ``θ`` and its Jacobian rows, sharing the per-point sines,
    cosines and partial products (the Gauss-Newton loop evaluates both at every step).

    ``R(sθ)^T = Ry(-s ry) Rx(-s rx) Rz(-s rz)`` is applied right to left: ``u = Rz q``, ``v = Rx u`` with
    ``q = p - s t``, the start point is ``Ry v``.
    """

    def __init__(self, xyz: np.ndarray, s: np.ndarray, transform: np.ndarray):
        """``xyz`` (3, n) float64, ``s`` (n,) float64."""
        transform = np.asarray(transform, dtype=np.float64)
        self.s = s
        # The three angles (and the three coordinates) in one call each: small arrays, per-call cost dominates.
        angles = np.multiply.outer(transform[:3], s)
        self.cx, self.cy, self.cz = np.cos(angles)
        self.sx, self.sy, self.sz = np.sin(angles)
        self.qx, self.qy, self.qz = xyz - np.multiply.outer(transform[3:], s)
        cx, sx, cz, sz = self.cx, self.sx, self.cz, self.sz
        self.ux, self.uy = cz * self.qx + sz * self.qy, -sz * self.qx + cz * self.qy   # uz = qz
        self.vy, self.vz = cx * self.uy + sx * self.qz, -sx * self.uy + cx * self.qz   # vx = ux
        self._factors = {}

    @classmethod
    def of(cls, points: np.ndarray, transform: np.ndarray) -> '_SweepStart':
        """For (n, 4) points with intensity ring + 0.1 s."""
        xyz = points[:, :3].T.astype(np.float64, order='C')
        return cls(xyz, relative_time_of(points[:, 3]).astype(np.float64), transform)

    def xyz(self) -> np.ndarray:
        """(n, 3) float32 start points."""
        out = np.empty((len(self.s), 3), dtype=_F32)
        out[:, 0] = self.cy * self.ux - self.sy * self.vz
        out[:, 1] = self.vy
        out[:, 2] = self.sy * self.ux + self.cy * self.vz
        return out

    def _factor(self, column: int):
        """The coefficient-free parts of a rotation column (see :meth:`rows`)."""
        if column not in self._factors:
            cx, sx, cy, sy, cz, sz = self.cx, self.sx, self.cy, self.sy, self.cz, self.sz
            if column == 0:     # dRx(-rx) u = (0, -sx uy + cx uz, -cx uy - sx uz)
                value = (-sx * self.uy + cx * self.qz, -cx * self.uy - sx * self.qz)
            elif column == 1:   # dRy(-ry) v = (-sy vx - cy vz, 0, cy vx - sy vz)
                value = (-sy * self.ux - cy * self.vz, cy * self.ux - sy * self.vz)
            else:               # dRz(-rz) q = (-sz qx + cz qy, -cz qx - sz qy, 0)
                value = (-sz * self.qx + cz * self.qy, -cz * self.qx - sz * self.qy)
            self._factors[column] = value
        return self._factors[column]

    def rows(self, coeff: np.ndarray, active: list[int]) -> np.ndarray:
        """``coeff · d/dθ_active [R(sθ)^T (p - s t)]``: (n, len(active)) for ``coeff`` (n, 3) float64, or for
        m coefficient vectors per point, ``coeff`` (n, m, 3), (n * m, len(active)) point by point (all m
        in the same calls).

        The rotation derivatives are ``s Ry Rx dRz q``, ``s Ry dRx u`` and ``s dRy v``; the translation ones
        ``-s R^T e_k``, dotted with ``coeff``: ``-s (Rz^T Rx^T Ry^T coeff)_k``. No per-point 3x3 matrices.
        """
        batched = coeff.ndim == 3

        def per_point(value):
            return value[:, None] if batched else value

        cx, sx, cy, sy, cz, sz, s = (per_point(v) for v in (self.cx, self.sx, self.cy, self.sy, self.cz, self.sz,
                                                             self.s))
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
    out[:, :3] = _SweepStart.of(points, transform).xyz()
    out[:, 3] = points[:, 3]
    return out


def transform_to_end(points: np.ndarray, transform: np.ndarray,
                     imu_correction: np.ndarray | None = None, imu_shift: np.ndarray | None = None) -> np.ndarray:
    """Re-project a sweep's points to its end: to the start with :func:`transform_to_start`, then
    ``p_end = R(θ) p_start + t``; with an IMU, then ``C (p_end - shift)`` (``C`` = IMU rotation from the end
    attitude back, see :class:`FeatureAssociation`). The intensity becomes the ring (``int``)."""
    start = transform_to_start(points, transform)
    rotation = sweep_rotation(*transform[:3])
    end = start[:, :3].astype(np.float64) @ rotation.T + np.asarray(transform[3:], dtype=np.float64)
    if imu_correction is not None:
        shift = np.zeros(3) if imu_shift is None else np.asarray(imu_shift, dtype=np.float64)
        end = (end - shift) @ np.asarray(imu_correction).T
    out = np.empty((len(points), 4), dtype=_F32)
    out[:, :3] = end
    out[:, 3] = np.trunc(points[:, 3])
    return out


def start_jacobian(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """(n, 3, 6): derivative of ``R(θ)^T (p - t)`` w.r.t. (rx, ry, rz, tx, ty, tz) at the full ``θ``."""
    rx, ry, rz = (float(v) for v in transform[:3])
    t = np.asarray(transform[3:], dtype=np.float64)
    Ry_, Rx_, Rz_ = rot_y(-ry), rot_x(-rx), rot_z(-rz)
    q = points[:, :3].astype(np.float64) - t
    d_rx = Ry_ @ (-Rx_ @ _GX) @ Rz_   # d/drx of Ry(-ry) Rx(-rx) Rz(-rz)
    d_ry = (-Ry_ @ _GY) @ Rx_ @ Rz_
    d_rz = Ry_ @ Rx_ @ (-Rz_ @ _GZ)
    rotation_t = Ry_ @ Rx_ @ Rz_
    jac = np.empty((len(points), 3, 6))
    jac[:, :, 0] = q @ d_rx.T
    jac[:, :, 1] = q @ d_ry.T
    jac[:, :, 2] = q @ d_rz.T
    jac[:, :, 3:] = -rotation_t[None, :, :]
    return jac


def plane_jacobian_rows(points: np.ndarray, coeff: np.ndarray, transform: np.ndarray, active: list[int],
                        exact: bool = False) -> np.ndarray:
    """Rows of the Gauss-Newton matrix: ``coeff_xyz · d p_start / d θ_active`` for each point.

    ``exact`` differentiates the residual actually minimised, ``R(sθ)^T (p - s t)``: ``s · J(sθ)``. Without
    it, the original's rows: ``J(θ)``, the derivative at the full motion whatever the point's time.
    """
    if not exact:
        jac = start_jacobian(points, transform)[:, :, active]
        return np.einsum('ni,nij->nj', coeff[:, :3].astype(np.float64), jac)
    return _SweepStart.of(points, transform).rows(coeff[:, :3].astype(np.float64), active)


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


# ----------------------------------------------------------------------------------- correspondences

@dataclass
class SurfCorrespondences:
    index1: np.ndarray   # nearest point in the last cloud (or -1), per current flat point
    index2: np.ndarray   # nearest on the same ring (or -1)
    index3: np.ndarray   # nearest on a neighbouring ring (or -1)


@dataclass
class CornerCorrespondences:
    index1: np.ndarray
    index2: np.ndarray


# The original scans the last cloud forwards from the nearest point, then backwards, and tells the points it
# meets apart by ring. Each query's window is cut into four segments, each the candidates of one kind met in
# one direction, in increasing index order: other rings met backwards (below the nearest point's ring), its
# own ring backwards, its own ring forwards, other rings forwards (above). Plane points 2 come from the 'same'
# segments, plane points 3 and line points 2 from the 'other' ones.
_BACK_OTHER, _BACK_SAME, _FORWARD_SAME, _FORWARD_OTHER = range(4)
_SAME, _OTHER = [_BACK_SAME, _FORWARD_SAME], [_BACK_OTHER, _FORWARD_OTHER]
_BACKWARD = np.array([True, True, False, False])


def _ranges(lo: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """The integers of the ranges [lo, lo + length), back to back (lengths >= 0)."""
    return np.arange(int(lengths.sum())) + np.repeat(lo - (np.cumsum(lengths) - lengths), lengths)


def _ragged(lo: np.ndarray, hi: np.ndarray):
    """(owner, position) of every integer in the half-open windows [lo, hi)."""
    lengths = np.maximum(hi - lo, 0)
    return np.repeat(np.arange(len(lo)), lengths), _ranges(lo, lengths)


def _next_above(rings: np.ndarray, n_rings: int) -> np.ndarray:
    """(n_rings + 3, N + 1): first index >= j whose ring exceeds r, for thresholds r = -1 .. n_rings + 1."""
    n = len(rings)
    thresholds = np.arange(-1, n_rings + 2)
    above = rings[None, :] > thresholds[:, None]
    index = np.where(above, np.arange(n)[None, :], n)
    out = np.full((len(thresholds), n + 1), n, dtype=np.int64)
    out[:, :n] = np.minimum.accumulate(index[:, ::-1], axis=1)[:, ::-1]
    return out


def _prev_below(rings: np.ndarray, n_rings: int) -> np.ndarray:
    """(n_rings + 3, N + 1): last index <= j - 1 ... stored at j: last index < j whose ring is below r
    (or -1), for thresholds r = -1 .. n_rings + 1."""
    n = len(rings)
    thresholds = np.arange(-1, n_rings + 2)
    below = rings[None, :] < thresholds[:, None]
    index = np.where(below, np.arange(n)[None, :], -1)
    out = np.full((len(thresholds), n + 1), -1, dtype=np.int64)
    out[:, 1:] = np.maximum.accumulate(index, axis=1)
    return out


class _LastCloud:
    """A 'last' feature cloud with its KD-tree and ring look-ups."""

    def __init__(self, points: np.ndarray, n_rings: int):
        self.points = points
        self.n_rings = n_rings
        self.rings = ring_of(points[:, 3])
        # Features are extracted ring by ring, so the rings normally ascend: every window bound is then a
        # binary search and every segment an index range. Other clouds take the general (slower) path.
        self.ring_ordered = bool(np.all(self.rings[1:] >= self.rings[:-1]))
        # One contiguous array per coordinate: the window search gathers them once per candidate.
        self.columns = tuple(np.ascontiguousarray(points[:, k]) for k in range(3))
        self.tree = cKDTree(points[:, :3].astype(np.float64)) if len(points) else None
        self._tables = None

    def _window_tables(self):
        if self._tables is None:
            low = int(self.rings.min(initial=0))
            high = int(self.rings.max(initial=0))
            offset = -min(low, 0) + 3
            span = max(high, self.n_rings) + offset + 3
            shifted = self.rings + offset
            self._tables = (offset, _next_above(shifted, span), _prev_below(shifted, span))
        return self._tables

    def window(self, closest: np.ndarray, scan: np.ndarray, window: float, forward_bound: int):
        """Forward [closest+1, hi) and backward (lo, closest-1] index windows of the original's scans."""
        n = len(self.points)
        limit = int(math.floor(window))       # int(ring) > scan + 2.5  <=>  ring > scan + floor(2.5)
        if self.ring_ordered:
            hi = np.searchsorted(self.rings, scan + limit, side='right')     # first ring > scan + limit
            lo = np.minimum(np.searchsorted(self.rings, scan - limit, side='left'), closest) - 1
        else:
            offset, next_above, prev_below = self._window_tables()
            up = np.clip(scan + limit + offset + 1, 0, next_above.shape[0] - 1)
            down = np.clip(scan - limit + offset + 1, 0, prev_below.shape[0] - 1)
            hi = next_above[up, np.minimum(closest + 1, n)]
            lo = prev_below[down, closest]  # last index < closest whose ring < scan - 2
        hi = np.minimum(hi, forward_bound)
        return np.maximum(hi, closest + 1), lo

    def segments(self, closest: np.ndarray, scan: np.ndarray, hi: np.ndarray, lo: np.ndarray, kinds: list[int]):
        """The window segments (see ``_BACK_OTHER``) of every query: (positions back to back, (n, 4) lengths);
        segments not in ``kinds`` are left empty."""
        n_queries = len(closest)
        if self.ring_ordered:
            ring_start = np.searchsorted(self.rings, scan, side='left')
            ring_end = np.searchsorted(self.rings, scan, side='right')
            backward_cut = np.clip(ring_start, lo + 1, closest)
            forward_cut = np.clip(ring_end, closest + 1, hi)
            # Columns in the order of _BACK_OTHER, _BACK_SAME, _FORWARD_SAME, _FORWARD_OTHER.
            starts = np.stack([lo + 1, backward_cut, closest + 1, forward_cut], axis=1)
            stops = np.stack([backward_cut, closest, forward_cut, hi], axis=1)
            lengths = np.zeros((n_queries, 4), dtype=np.int64)
            lengths[:, kinds] = stops[:, kinds] - starts[:, kinds]
            return _ranges(starts.reshape(-1), lengths.reshape(-1)), lengths
        # General path: class every window point as the original's loops do, then group by query and segment.
        forward_owner, forward = _ragged(closest + 1, hi)
        backward_owner, backward = _ragged(lo + 1, closest)
        forward_kind = np.where(self.rings[forward] <= scan[forward_owner], _FORWARD_SAME, _FORWARD_OTHER)
        backward_kind = np.where(self.rings[backward] >= scan[backward_owner], _BACK_SAME, _BACK_OTHER)
        key = np.concatenate((backward_owner * 4 + backward_kind, forward_owner * 4 + forward_kind))
        position = np.concatenate((backward, forward))
        wanted = np.isin(key % 4, kinds)
        key, position = key[wanted], position[wanted]
        position = position[np.argsort(key, kind='stable')]
        return position, np.bincount(key, minlength=4 * n_queries).reshape(n_queries, 4)


def _nearest_in_segments(query: np.ndarray, last: _LastCloud, position: np.ndarray, lengths: np.ndarray,
                         limit: float):
    """Per query and segment, the candidate the original's scan keeps: the smallest squared distance below
    ``limit`` (its float32 expression), the first index met on ties (the highest in a backward segment).

    Returns (n, 4) indices (-1: none) and squared distances (inf: none).
    """
    flat_lengths = lengths.reshape(-1)
    index = np.full(len(flat_lengths), -1, dtype=np.int64)
    best = np.full(len(flat_lengths), np.inf, dtype=_F32)
    if len(position):
        per_query = lengths.sum(axis=1)
        x, y, z = last.columns
        dx = x[position] - np.repeat(query[:, 0], per_query)
        dy = y[position] - np.repeat(query[:, 1], per_query)
        dz = z[position] - np.repeat(query[:, 2], per_query)
        dist = dx * dx + dy * dy + dz * dz
        ends = np.cumsum(flat_lengths)
        filled = np.flatnonzero(flat_lengths)
        best[filled] = np.fmin.reduceat(dist, (ends - flat_lengths)[filled])   # fmin: NaN never wins
        at_minimum = np.flatnonzero(dist == np.repeat(best, flat_lengths))
        segment = np.searchsorted(ends, at_minimum, side='right')
        new_segment = segment[1:] != segment[:-1]
        keep = np.where(_BACKWARD[segment % 4], np.append(new_segment, True), np.insert(new_segment, 0, True))
        index[segment[keep]] = position[at_minimum[keep]]
    outside = ~(best < _F32(limit))
    index[outside] = -1
    best[outside] = np.inf
    return index.reshape(-1, 4), best.reshape(-1, 4)


def _pick(index: np.ndarray, best: np.ndarray, backward: int, forward: int) -> np.ndarray:
    """The original's choice between its forward and backward scans: backward only when strictly closer."""
    return np.where(best[:, backward] < best[:, forward], index[:, backward], index[:, forward])


def _nearest_and_windows(points_start: np.ndarray, last: _LastCloud, params: Params, forward_bound: int):
    """The search both correspondence kinds start with: the queries whose nearest point in the last cloud lies
    within the gate (indices ``q``), that point and its ring, and the original's index windows around it."""
    fa = params.feature_association
    dist, nearest = last.tree.query(points_start[:, :3].astype(np.float64), k=1)
    q = np.flatnonzero(dist.astype(np.float64) ** 2 < fa.nearest_feature_search_sq_dist)
    closest = nearest[q]
    scan = last.rings[closest]
    hi, lo = last.window(closest, scan, fa.ring_search_window, forward_bound)
    return q, closest, scan, hi, lo


def find_surf_correspondences(points_start: np.ndarray, last: _LastCloud, params: Params,
                              forward_bound: int) -> SurfCorrespondences:
    """The original's plane correspondences for flat points already mapped to the sweep start."""
    n = len(points_start)
    index1 = np.full(n, -1, dtype=np.int64)
    index2, index3 = index1.copy(), index1.copy()
    if n == 0 or last.tree is None:
        return SurfCorrespondences(index1, index2, index3)
    q, closest, scan, hi, lo = _nearest_and_windows(points_start, last, params, forward_bound)
    position, lengths = last.segments(closest, scan, hi, lo, _SAME + _OTHER)
    index, best = _nearest_in_segments(points_start[q], last, position, lengths,
                                       params.feature_association.nearest_feature_search_sq_dist)
    index1[q] = closest
    index2[q] = _pick(index, best, _BACK_SAME, _FORWARD_SAME)
    index3[q] = _pick(index, best, _BACK_OTHER, _FORWARD_OTHER)
    return SurfCorrespondences(index1, index2, index3)


def find_corner_correspondences(points_start: np.ndarray, last: _LastCloud, params: Params,
                                forward_bound: int) -> CornerCorrespondences:
    """The original's line correspondences for sharp points already mapped to the sweep start."""
    n = len(points_start)
    index1 = np.full(n, -1, dtype=np.int64)
    index2 = index1.copy()
    if n == 0 or last.tree is None:
        return CornerCorrespondences(index1, index2)
    q, closest, scan, hi, lo = _nearest_and_windows(points_start, last, params, forward_bound)
    position, lengths = last.segments(closest, scan, hi, lo, _OTHER)
    index, best = _nearest_in_segments(points_start[q], last, position, lengths,
                                       params.feature_association.nearest_feature_search_sq_dist)
    index1[q] = closest
    index2[q] = _pick(index, best, _BACK_OTHER, _FORWARD_OTHER)
    return CornerCorrespondences(index1, index2)


def plane_through(a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Unit normal (n, 3) and offset (n,) of the planes through a, b, c (float32): ``n · p + offset = 0``."""
    ab, ac = (b - a).astype(_F32), (c - a).astype(_F32)
    pa = ab[:, 1] * ac[:, 2] - ac[:, 1] * ab[:, 2]
    pb = ab[:, 2] * ac[:, 0] - ac[:, 2] * ab[:, 0]
    pc = ab[:, 0] * ac[:, 1] - ac[:, 0] * ab[:, 1]
    pd = -(pa * a[:, 0] + pb * a[:, 1] + pc * a[:, 2])
    with np.errstate(invalid='ignore', divide='ignore'):
        ps = np.sqrt(pa * pa + pb * pb + pc * pc)
        normal = np.stack([pa / ps, pb / ps, pc / ps], axis=1)
        pd = pd / ps
    return normal, pd


def plane_distance(normal: np.ndarray, offset: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Signed distances of points p (n, >= 3) to the planes of :func:`plane_through`."""
    return normal[:, 0] * p[:, 0] + normal[:, 1] * p[:, 1] + normal[:, 2] * p[:, 2] + offset


def plane_coefficients(p_start: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Unit normal (n, 3) and signed distance (n,) of points to the planes through a, b, c (float32)."""
    normal, offset = plane_through(a, b, c)
    return normal, plane_distance(normal, offset, p_start)


def _line_offsets(p: np.ndarray, anchor: np.ndarray, along: np.ndarray) -> np.ndarray:
    """(n, 3) perpendicular offsets of points from the lines through ``anchor`` with unit direction ``along``."""
    d = p - anchor
    return d - np.einsum('ni,ni->n', d, along)[:, None] * along


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays, the same operations as ``np.cross`` without its overhead."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def line_coefficients(p: np.ndarray, a: np.ndarray, b: np.ndarray):
    """Unit direction (n, 3) from the line through a, b towards p, and the distance (n,) (float32)."""
    p, a, b = (v[:, :3].astype(_F32) for v in (p, a, b))
    pa, pb, ab = p - a, p - b, a - b
    # Cross product (p - a) x (p - b): its norm is twice the triangle area.
    cross = _cross(pa, pb)
    area = np.linalg.norm(cross, axis=1)
    length = np.linalg.norm(ab, axis=1)
    with np.errstate(invalid='ignore', divide='ignore'):
        # The gradient of the distance w.r.t. p: (a - b) x (pa x pb) / (|pa x pb| |a - b|).
        gradient = _cross(ab, cross) / (area * length)[:, None]
        distance = area / length
    return gradient.astype(_F32), distance.astype(_F32)


# ----------------------------------------------------------------------------------------- the solver

@dataclass
class OdometryStats:
    surf_iterations: int = 0
    corner_iterations: int = 0
    surf_correspondences: int = 0
    corner_correspondences: int = 0
    surf_degenerate: bool = False
    corner_degenerate: bool = False
    skipped: str = ''
    extra: dict = field(default_factory=dict)


class _Stage:
    """Degeneracy state of one Gauss-Newton stage (kept across scans, as the original's members)."""

    def __init__(self):
        self.projection = np.eye(3)
        self.degenerate = False

    def step(self, a: np.ndarray, b: np.ndarray, iteration: int, threshold: float) -> np.ndarray:
        ata = a.T @ a
        atb = a.T @ b
        try:
            x = np.linalg.solve(ata, atb)
        except np.linalg.LinAlgError:
            x = np.linalg.lstsq(ata, atb, rcond=None)[0]
        if iteration == 0:
            values, vectors = np.linalg.eigh(ata)           # ascending
            keep = np.ones(3, dtype=bool)
            self.degenerate = False
            for i in range(3):                              # from the smallest up to the first >= threshold
                if values[i] < threshold:
                    keep[i] = False
                    self.degenerate = True
                else:
                    break
            self.projection = vectors @ np.diag(keep.astype(float)) @ vectors.T
        if self.degenerate:
            x = self.projection @ x
        return x


class LaserOdometry:
    """Two-stage scan-to-scan registration; call :meth:`register` once per sweep."""

    SURF_PARAMS = [0, 2, 4]     # rx, rz, ty
    CORNER_PARAMS = [1, 3, 5]   # ry, tx, tz

    def __init__(self, params: Params, fix_scan_bound: bool = False, exact_jacobian: bool = False):
        self.params = params
        self.fix_scan_bound = fix_scan_bound
        self.exact_jacobian = exact_jacobian
        self.transform_cur = np.zeros(6)
        self._surf_stage = _Stage()
        self._corner_stage = _Stage()
        self.last_corner: _LastCloud | None = None
        self.last_surf: _LastCloud | None = None
        # Weight of a prior holding the sweep rotation at zero [m^2/rad^2] (0: none): with an IMU the
        # registration only estimates the rotation the IMU missed, see FeatureAssociation.
        self.rotation_prior = 0.0

    def set_last(self, corner: np.ndarray, surf: np.ndarray) -> None:
        """New 'last' clouds; KD-trees are rebuilt only when they are big enough, as in the original."""
        fa = self.params.feature_association
        n_rings = self.params.sensor.n_scan
        self.last_corner_count, self.last_surf_count = len(corner), len(surf)
        if self.last_corner is None or (len(corner) > fa.min_last_corner_points and
                                        len(surf) > fa.min_last_surf_points):
            self.last_corner = _LastCloud(corner, n_rings)
            self.last_surf = _LastCloud(surf, n_rings)

    def register(self, sharp: np.ndarray, flat: np.ndarray) -> OdometryStats:
        """Refine ``transform_cur`` from the sweep's sharp and flat points (camera axes, ring + 0.1 s)."""
        fa = self.params.feature_association
        stats = OdometryStats()
        if self.last_corner is None or self.last_corner_count < fa.min_last_corner_points or \
                self.last_surf_count < fa.min_last_surf_points:
            stats.skipped = 'too few points in the last clouds'
            return stats
        if self.exact_jacobian:
            return self._register_blocks(sharp, flat, stats)
        for iteration in range(fa.max_iterations):
            stats.surf_iterations = iteration + 1
            if iteration % fa.reassociate_every == 0:
                bound = len(self.last_surf.points) if self.fix_scan_bound else len(flat)
                surf_match = find_surf_correspondences(transform_to_start(flat, self.transform_cur), self.last_surf,
                                                       self.params, bound)
            a, b = self._surf_rows(flat, surf_match, iteration)
            stats.surf_correspondences = len(b)
            if len(b) < fa.min_correspondences:
                continue
            x = self._surf_stage.step(a, b, iteration, fa.degeneracy_threshold)
            stats.surf_degenerate = self._surf_stage.degenerate
            if not self._apply(x, self.SURF_PARAMS, rotation_rows=[0, 1], translation_rows=[2]):
                break
        for iteration in range(fa.max_iterations):
            stats.corner_iterations = iteration + 1
            if iteration % fa.reassociate_every == 0:
                bound = len(self.last_corner.points) if self.fix_scan_bound else len(sharp)
                corner_match = find_corner_correspondences(transform_to_start(sharp, self.transform_cur),
                                                           self.last_corner, self.params, bound)
            a, b = self._corner_rows(sharp, corner_match, iteration)
            stats.corner_correspondences = len(b)
            if len(b) < fa.min_correspondences:
                continue
            x = self._corner_stage.step(a, b, iteration, fa.degeneracy_threshold)
            stats.corner_degenerate = self._corner_stage.degenerate
            if not self._apply(x, self.CORNER_PARAMS, rotation_rows=[0], translation_rows=[1, 2]):
                break
        return stats

    # ----------------------------------------------------------- Gauss-Newton in blocks (sweep-start model)
    def _register_blocks(self, sharp: np.ndarray, flat: np.ndarray, stats: OdometryStats) -> OdometryStats:
        """Both stages with full Gauss-Newton steps, in blocks of ``reassociate_every`` iterations.

        Each block associates the points anew and fixes their weights (1 in the first block, as the original;
        ``1 - gain |d|`` afterwards), so within a block the cost ``sum w d^2`` is fixed and each step is
        shortened until it does not increase that cost. Without this, full steps overshoot on the wrong
        correspondences of the first iterations and the edge stage bounces around; the original avoids that
        with 5 % steps, which then stop with up to 2 cm / 2 deg left.
        """
        fa = self.params.feature_association
        for kind, points, active in (('surf', flat, self.SURF_PARAMS), ('corner', sharp, self.CORNER_PARAMS)):
            stage = self._surf_stage if kind == 'surf' else self._corner_stage
            iterations, first = 0, True
            blocks = -(-fa.max_iterations // fa.reassociate_every)
            for block in range(blocks):
                residual = self._residual_function(kind, points, weighted=block > 0)
                if residual is None:
                    break
                before = self.transform_cur.copy()
                for _ in range(min(fa.reassociate_every, fa.max_iterations - iterations)):
                    iterations += 1
                    rows, values = residual(self.transform_cur, jacobian=True)
                    setattr(stats, f'{kind}_correspondences', residual.points)
                    if residual.points < fa.min_correspondences:
                        break
                    x = stage.step(rows, -values, 0 if first else 1, fa.degeneracy_threshold)
                    first = False
                    setattr(stats, f'{kind}_degenerate', stage.degenerate)
                    x = self._shorten(x, active, residual, float(np.square(values).sum()))
                    converged = not self._apply(x, active, *(([0, 1], [2]) if kind == 'surf' else ([0], [1, 2])))
                    if converged:
                        break
                moved = self.transform_cur - before
                if np.degrees(np.abs(moved[:3])).max() < fa.convergence_rotation and \
                        np.abs(moved[3:]).max() * 100 < fa.convergence_translation:
                    break   # a whole block changed nothing: converged
            setattr(stats, f'{kind}_iterations', iterations)
        return stats

    def _residual_function(self, kind: str, points: np.ndarray, weighted: bool):
        """Associate ``points`` at the current estimate and return ``f(theta, jacobian)`` giving the weighted
        residuals (and their Jacobian rows) of the usable correspondences, weights fixed now.

        Planes give one residual per point, the signed distance. Lines give three: the point's perpendicular
        offset from the line as a vector, ``(I - u u^T)(p - a)``. Its length is the original's point-to-line
        distance, but unlike that distance it is smooth where the point meets the line, so Gauss-Newton
        converges there instead of stepping back and forth across it.
        """
        fa = self.params.feature_association
        start = transform_to_start(points, self.transform_cur)
        last = self.last_surf if kind == 'surf' else self.last_corner
        bound = len(last.points) if self.fix_scan_bound else len(points)
        # The planes and lines depend only on the last cloud: fixed for the whole block.
        if kind == 'surf':
            match = find_surf_correspondences(start, last, self.params, bound)
            usable = np.flatnonzero((match.index2 >= 0) & (match.index3 >= 0))
            normal, offset = plane_through(last.points[match.index1[usable]], last.points[match.index2[usable]],
                                           last.points[match.index3[usable]])
            p_start = start[usable]
            distance = plane_distance(normal, offset, p_start).astype(np.float64)
            scale = np.sqrt(np.sqrt((p_start[:, :3].astype(np.float64) ** 2).sum(axis=1)))
            finite = np.isfinite(distance) & np.isfinite(normal).all(axis=1) & (distance != 0)
            anchors = (normal, offset)
        else:
            match = find_corner_correspondences(start, last, self.params, bound)
            usable = np.flatnonzero(match.index2 >= 0)
            a = last.points[match.index1[usable], :3].astype(np.float64)
            b = last.points[match.index2[usable], :3].astype(np.float64)
            with np.errstate(invalid='ignore', divide='ignore'):
                along = (a - b) / np.linalg.norm(a - b, axis=1)[:, None]
            distance = np.linalg.norm(_line_offsets(start[usable, :3].astype(np.float64), a, along), axis=1)
            scale = np.ones(len(distance))
            finite = np.isfinite(distance) & np.isfinite(along).all(axis=1)
            anchors = (a, along)
        weight = 1.0 - fa.weight_gain * np.abs(distance) / scale if weighted else np.ones(len(distance))
        keep = (weight > fa.min_weight) & finite
        if keep.sum() < fa.min_correspondences:
            return None
        selected = points[usable[keep]]
        first, second = (x[keep] for x in anchors)
        weight = weight[keep]
        xyz = selected[:, :3].T.astype(np.float64, order='C')
        s = relative_time_of(selected[:, 3]).astype(np.float64)
        active = self.SURF_PARAMS if kind == 'surf' else self.CORNER_PARAMS

        # The rotation prior: sqrt(w) * angle for each active rotation parameter, appended to the residuals.
        prior_columns = [k for k, parameter in enumerate(active) if parameter < 3] if self.rotation_prior > 0 else []
        prior_rows = np.zeros((len(prior_columns), len(active)))
        prior_rows[np.arange(len(prior_columns)), prior_columns] = math.sqrt(self.rotation_prior)
        prior_parameters = [active[k] for k in prior_columns]
        if kind == 'surf':
            coefficients = first.astype(np.float64) * weight[:, None]   # the weighted normal
        else:
            # Rows of the projector I - u u^T, weighted: the coefficients of the three residual components.
            coefficients = (np.eye(3)[None, :, :] - second[:, :, None] * second[:, None, :]) * weight[:, None, None]

        def residual(theta: np.ndarray, jacobian: bool = False):
            frame = _SweepStart(xyz, s, theta)
            if kind == 'surf':
                values = weight * plane_distance(first, second, frame.xyz()).astype(np.float64)
            else:
                values = (weight[:, None] * _line_offsets(frame.xyz().astype(np.float64), first, second)).reshape(-1)
            if prior_parameters:
                values = np.concatenate([values, math.sqrt(self.rotation_prior) * np.asarray(theta)[prior_parameters]])
            if not jacobian:
                return values
            rows = frame.rows(coefficients, active)   # lines: the three components of each point, as the values
            return (np.concatenate([rows, prior_rows]) if prior_parameters else rows), values

        residual.points = len(selected)
        return residual

    def _shorten(self, x: np.ndarray, active: list[int], residual, reference: float, halvings: int = 4) -> np.ndarray:
        """The largest of x, x/2, x/4, ... that does not increase the block's cost (``reference``, the cost at
        the current estimate) (0 if none)."""
        start = self.transform_cur.copy()
        step = np.asarray(x, dtype=float)
        for _ in range(halvings + 1):
            trial = start.copy()
            trial[active] += step
            if np.isfinite(trial).all():
                cost = float(np.square(residual(trial)).sum())
                if np.isfinite(cost) and cost <= reference:
                    return step
            step = step / 2
        return np.zeros_like(step)

    def _apply(self, x: np.ndarray, active: list[int], rotation_rows: list[int], translation_rows: list[int]) -> bool:
        """Add the step; False when converged (update below the thresholds)."""
        fa = self.params.feature_association
        self.transform_cur[active] += x
        self.transform_cur[~np.isfinite(self.transform_cur)] = 0.0
        delta_r = math.sqrt(sum(math.degrees(x[i]) ** 2 for i in rotation_rows))
        delta_t = math.sqrt(sum((x[i] * 100.0) ** 2 for i in translation_rows))
        return not (delta_r < fa.convergence_rotation and delta_t < fa.convergence_translation)

    def _weights(self, distance: np.ndarray, scale: np.ndarray, iteration: int) -> np.ndarray:
        fa = self.params.feature_association
        # Unweighted for the first iterations (the basin of a coarse alignment), then 1 - gain * |d|.
        if iteration < fa.reassociate_every:
            return np.ones(len(distance), dtype=_F32)
        return (1.0 - fa.weight_gain * np.abs(distance.astype(np.float64)) / scale).astype(_F32)

    def _surf_rows(self, flat: np.ndarray, match: SurfCorrespondences, iteration: int):
        fa = self.params.feature_association
        usable = np.flatnonzero((match.index2 >= 0) & (match.index3 >= 0))
        points = flat[usable]
        p_start = transform_to_start(points, self.transform_cur)
        last = self.last_surf.points
        normal, distance = plane_coefficients(p_start, last[match.index1[usable]], last[match.index2[usable]],
                                              last[match.index3[usable]])
        norm = np.sqrt(np.sqrt((p_start[:, :3].astype(np.float64) ** 2).sum(axis=1)))
        weight = self._weights(distance, norm, iteration)
        ok = (weight > fa.min_weight) & (distance != 0) & np.isfinite(distance)
        coeff = np.concatenate([normal[ok] * weight[ok, None], (weight[ok] * distance[ok])[:, None]], axis=1)
        rows = plane_jacobian_rows(points[ok], coeff, self.transform_cur, self.SURF_PARAMS, self.exact_jacobian)
        return rows, -fa.step_scale * coeff[:, 3].astype(np.float64)

    def _corner_rows(self, sharp: np.ndarray, match: CornerCorrespondences, iteration: int):
        fa = self.params.feature_association
        usable = np.flatnonzero(match.index2 >= 0)
        points = sharp[usable]
        p_start = transform_to_start(points, self.transform_cur)
        last = self.last_corner.points
        gradient, distance = line_coefficients(p_start, last[match.index1[usable]], last[match.index2[usable]])
        weight = self._weights(distance, np.ones(len(distance)), iteration)
        ok = (weight > fa.min_weight) & np.isfinite(distance) & np.isfinite(gradient).all(axis=1)
        coeff = np.concatenate([gradient[ok] * weight[ok, None], (weight[ok] * distance[ok])[:, None]], axis=1)
        rows = plane_jacobian_rows(points[ok], coeff, self.transform_cur, self.CORNER_PARAMS, self.exact_jacobian)
        return rows, -fa.step_scale * coeff[:, 3].astype(np.float64)
