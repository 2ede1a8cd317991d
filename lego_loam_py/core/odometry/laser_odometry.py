"""Scan-to-scan odometry of featureAssociation: the two odometry models (docs/original.md §5.3, §6.2 steps
5-10, quirks 8.1, 8.10, 8.11).

The previous sweep's features are expressed in its end frame, which is the current sweep's start frame, so
registering the current features against them estimates the sweep motion ``θ`` (conventions in
:mod:`lego_loam_py.core.odometry.sweep`; correspondences in :mod:`lego_loam_py.core.odometry.correspondences`).

Registration is the original's two-step Gauss-Newton: planes from flat (ground) points fix
``(rx, rz, ty)``, then lines from sharp points fix ``(ry, tx, tz)``, each stage with its degeneracy
projection (:class:`~lego_loam_py.core.gauss_newton.DegeneracyProjection`). ``transform_cur`` is not reset
between sweeps, which is the constant-velocity prior. Two models, chosen once from
``feature_association.odometry_model`` by :func:`make_laser_odometry`:

* :class:`OriginalOdometry` (``original``): each step moves 5 % of the full Gauss-Newton step,
  correspondences are re-associated every 5 iterations and weighted from iteration 5 on, directions whose
  eigenvalue is below the threshold on the first iteration are frozen, and iterations stop when the update is
  below 0.1 deg and 0.1 cm. Jacobians are the analytic derivatives of ``R(θ)^T (p - t)`` with respect to the
  active parameters at the full ``θ`` (as the original, which does not scale them by ``s``).
* :class:`SweepStartOdometry` (``sweep_start``, the default) differs on purpose: the exact Jacobian of the
  residual minimised, full Gauss-Newton steps in blocks of ``reassociate_every`` iterations with fixed
  weights and backtracking, and the point-to-line residual is the perpendicular offset as a 3-vector, smooth
  where a point meets its line. It keeps the original's correspondence search with quirk 8.1: searching whole
  neighbouring rings instead (no bound) was measured worse, 46 % instead of 4.6 % drift in the simulated
  corridor with IMU, where the bound keeps matches near the scan's own stretch of wall.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from lego_loam_py.core.gauss_newton import DegeneracyProjection, residual_information
from lego_loam_py.core.geometry import (
    fit_planes_at,
    line_coefficients,
    line_offsets,
    nearest_within,
    plane_coefficients,
    plane_distance,
    plane_through,
    squared_lengths,
)
from lego_loam_py.core.imu.agreement import FULL_TRUST
from lego_loam_py.core.indexing import copy_columns, select_rows, xyz_columns
from lego_loam_py.core.odometry.correspondences import (
    CornerCorrespondences,
    LastCloud,
    SurfCorrespondences,
    find_corner_correspondences,
    find_surf_correspondences,
)
from lego_loam_py.core.odometry.sweep import (
    SweepStartFrame,
    SweepTrig,
    plane_jacobian_rows,
    relative_time_of,
    transform_to_start,
)
from lego_loam_py.core.params.types import OdometryModel, Params

try:  # a block's Gauss-Newton iterations in one call (native/odometry_kernels.c); optional, the NumPy loop otherwise
    from lego_loam_py.core import _odometry_kernels
except ImportError:
    _odometry_kernels = None
try:  # the line terms in one pass (native/feature_kernels.c); optional, NumPy gives the same
    from lego_loam_py.core import _feature_kernels
except ImportError:
    _feature_kernels = None

__all__ = ['LaserOdometry', 'OriginalOdometry', 'SweepStartOdometry', 'make_laser_odometry', 'OdometryStats']

_F32 = np.float32
HALVINGS = 4  # a step is halved at most this many times before the sweep-start model gives it up


@dataclass
class OdometryStats:
    surf_iterations: int = 0
    corner_iterations: int = 0
    surf_correspondences: int = 0
    corner_correspondences: int = 0
    surf_degenerate: bool = False
    corner_degenerate: bool = False
    # Smallest eigenvalue of each stage's normal matrix on its first iteration (NaN: the stage did not run):
    # the per-scan condition of the three parameters the stage estimates.
    surf_condition: float = float('nan')
    corner_condition: float = float('nan')
    surf_walls: bool = False  # the stage had too few correspondences of its own and used the walls
    corner_walls: bool = False
    # Share of the sharp points matched in the corner stage's last association (sweep-start model; NaN: none).
    corner_match_ratio: float = float('nan')
    lost: bool = False  # below feature_association.lost_match_ratio (extra['lost_match_ratio']) ...
    recovered: bool = False  # ... and registering again from standing still matched more
    skipped: str = ''
    extra: dict = field(default_factory=dict)
    # 6x6 Fisher information of the sweep motion θ (rx, ry, rz [rad], tx, ty, tz [m]) at convergence: both
    # stages' point residuals differentiated with respect to all six parameters, each stage's residual variance
    # estimated from its own residuals (:func:`stage_information`); None: not registered. And the IMU rotation
    # prior's (what the IMU's turn over a sweep is worth, from the prior's weight: see the end of register(); None: no
    # prior).
    information: np.ndarray | None = None
    prior_information: np.ndarray | None = None


ALL_PARAMS = [0, 1, 2, 3, 4, 5]
# Smallest residual standard deviation a stage's variance estimate may give [m]: below it the residuals of a
# few dozen matches near convergence say more about the luck of the draw than about the range noise of a lidar.
MIN_RESIDUAL_SIGMA = 0.005


def stage_information(jtj: np.ndarray, squared_residuals: float, residuals: int) -> np.ndarray:
    """The information of one registration stage (6x6 ``jtj`` of its weighted residuals with respect to all six
    parameters), the stage estimating three parameters (:func:`~lego_loam_py.core.gauss_newton.residual_information`).
    """
    return residual_information(jtj, squared_residuals, residuals, 3, MIN_RESIDUAL_SIGMA)


# Wall points, or a function preparing them on first use.
WallPoints = np.ndarray | Callable[[], np.ndarray] | None


class _Stage(NamedTuple):
    """One registration stage: its points, what they match, the parameters it moves (rows of the step that are
    rotations and translations, for the convergence test) and its degeneracy state."""

    kind: str  # 'surf' (planes, flat points) or 'corner' (lines, sharp points)
    points: np.ndarray
    last: LastCloud
    active: list[int]
    rotation_rows: list[int]
    translation_rows: list[int]
    degeneracy: DegeneracyProjection
    # Wall points (prepared on first use) that back up the stage when it has too few matches of its own
    # (sweep-start model).
    walls: Callable[[], np.ndarray] | None = None


class _Term(NamedTuple):
    """Fixed correspondences of one kind within a block: the points (3, n) float64 and their relative times,
    weights, the anchors (planes: normal, offset; lines: a point, the unit direction) and the weighted
    residual coefficients."""

    kind: str
    xyz: np.ndarray
    s: np.ndarray
    weight: np.ndarray
    first: np.ndarray
    second: np.ndarray
    coefficients: np.ndarray
    wall: bool = False
    trig: SweepTrig | None = None  # the sines and cosines of ``s``, remembered across the block's evaluations

    @property
    def points(self) -> int:
        return len(self.s)

    def values(self, frame: SweepStartFrame) -> np.ndarray:
        """Weighted residuals at the frame's ``θ``: plane distances, or line offsets (three per point)."""
        if self.kind == 'surf':
            return self.weight * plane_distance(self.first, self.second, frame.xyz()).astype(np.float64)
        return (self.weight[:, None] * line_offsets(frame.xyz().astype(np.float64), self.first, self.second)).reshape(
            -1
        )


class LaserOdometry:
    """Two-stage scan-to-scan registration; call :meth:`register` once per sweep. The two models
    (:class:`OriginalOdometry`, :class:`SweepStartOdometry`) differ in how a stage iterates."""

    SURF_PARAMS = [0, 2, 4]  # rx, rz, ty
    CORNER_PARAMS = [1, 3, 5]  # ry, tx, tz

    def __init__(self, params: Params, fix_scan_bound: bool = False):
        self.params = params
        self.fix_scan_bound = fix_scan_bound
        self.transform_cur = np.zeros(6)
        self._surf_stage = DegeneracyProjection(3)
        self._corner_stage = DegeneracyProjection(3)
        self.last_corner: LastCloud | None = None
        self.last_surf: LastCloud | None = None
        # Weight of a prior holding the sweep rotation at zero [m^2/rad^2] (0: none): with an IMU the
        # registration only estimates the rotation the IMU missed, see FeatureAssociation.
        self.rotation_prior = 0.0
        self._prepared_points: dict = {}  # (sweep-start model, see _prepared)

    def set_last(self, corner: np.ndarray, surf: np.ndarray) -> None:
        """New 'last' clouds; KD-trees are rebuilt only when they are big enough, as in the original."""
        fa = self.params.feature_association
        n_rings = self.params.sensor.n_scan
        self.last_corner_count, self.last_surf_count = len(corner), len(surf)
        if self.last_corner is None or (
            len(corner) > fa.min_last_corner_points and len(surf) > fa.min_last_surf_points
        ):
            self.last_corner = LastCloud(corner, n_rings)
            self.last_surf = LastCloud(surf, n_rings)

    def register(self, sharp: np.ndarray, flat: np.ndarray, wall: WallPoints = None) -> OdometryStats:
        """Refine ``transform_cur`` from the sweep's sharp and flat points (camera axes, ring + 0.1 s). Wall
        points, or a function preparing them (called only if a stage needs them), back up a stage short of
        matches in the sweep-start model; the original model has none."""
        fa = self.params.feature_association
        stats = OdometryStats()
        if (
            self.last_corner is None
            or self.last_corner_count < fa.min_last_corner_points
            or self.last_surf_count < fa.min_last_surf_points
        ):
            stats.skipped = 'too few points in the last clouds'
            return stats
        return self._register(sharp, flat, wall, stats)

    def _register(self, sharp: np.ndarray, flat: np.ndarray, wall: WallPoints, stats: OdometryStats) -> OdometryStats:
        raise NotImplementedError

    def _stages(self, sharp: np.ndarray, flat: np.ndarray, wall: WallPoints = None) -> tuple[_Stage, _Stage]:
        """Planes first (rx, rz, ty), then lines (ry, tx, tz); the wall planes, if any, in both (walls hold
        the roll, yaw and lateral position; ceilings the pitch and height where the floor is hardly seen)."""
        if wall is not None and not callable(wall):
            points, wall = wall, lambda: points
        return (
            _Stage('surf', flat, self.last_surf, self.SURF_PARAMS, [0, 1], [2], self._surf_stage, wall),
            _Stage('corner', sharp, self.last_corner, self.CORNER_PARAMS, [0], [1, 2], self._corner_stage, wall),
        )

    def _forward_bound(self, last: LastCloud, points: np.ndarray) -> int:
        """Where the forward correspondence scan stops: the current feature count (quirk 8.1) unless fixed."""
        return len(last.points) if self.fix_scan_bound else len(points)

    def _apply(self, x: np.ndarray, active: list[int], rotation_rows: list[int], translation_rows: list[int]) -> bool:
        """Add the step; False when converged (update below the thresholds)."""
        fa = self.params.feature_association
        self.transform_cur[active] += x
        self.transform_cur[~np.isfinite(self.transform_cur)] = 0.0
        delta_r = math.sqrt(sum(math.degrees(x[i]) ** 2 for i in rotation_rows))
        delta_t = math.sqrt(sum((x[i] * 100.0) ** 2 for i in translation_rows))
        return not (delta_r < fa.convergence_rotation and delta_t < fa.convergence_translation)


class OriginalOdometry(LaserOdometry):
    """The original's model: 5 % Gauss-Newton steps with the Jacobian at the full ``θ``."""

    def _register(self, sharp: np.ndarray, flat: np.ndarray, wall: WallPoints, stats: OdometryStats) -> OdometryStats:
        fa = self.params.feature_association
        information = np.zeros((6, 6))
        for stage in self._stages(sharp, flat):  # (no walls in the original)
            find, rows = (
                (find_surf_correspondences, self._surf_rows)
                if stage.kind == 'surf'
                else (find_corner_correspondences, self._corner_rows)
            )
            match, iteration = None, 0
            for iteration in range(fa.max_iterations):
                setattr(stats, f'{stage.kind}_iterations', iteration + 1)
                if iteration % fa.reassociate_every == 0:
                    match = find(
                        transform_to_start(stage.points, self.transform_cur),
                        stage.last,
                        self.params,
                        self._forward_bound(stage.last, stage.points),
                    )
                a, b = rows(stage.points, match, iteration)
                setattr(stats, f'{stage.kind}_correspondences', len(b))
                if len(b) < fa.min_correspondences:
                    continue
                x = stage.degeneracy.step(a, b, iteration == 0, fa.degeneracy_threshold)
                setattr(stats, f'{stage.kind}_degenerate', stage.degeneracy.degenerate)
                if not self._apply(x, stage.active, stage.rotation_rows, stage.translation_rows):
                    break
            if match is not None:
                # The last association's rows at the final θ, over all six parameters (b = -step_scale w d).
                a, b = rows(stage.points, match, iteration, ALL_PARAMS)
                if len(b) >= fa.min_correspondences:
                    residual = b / fa.step_scale
                    information += stage_information(a.T @ a, float(residual @ residual), len(b))
        stats.information = information if information.any() else None
        return stats

    def _weights(self, distance: np.ndarray, scale: np.ndarray, iteration: int) -> np.ndarray:
        fa = self.params.feature_association
        # Unweighted for the first iterations (the basin of a coarse alignment), then 1 - gain * |d|.
        if iteration < fa.reassociate_every:
            return np.ones(len(distance), dtype=_F32)
        return (1.0 - fa.weight_gain * np.abs(distance.astype(np.float64)) / scale).astype(_F32)

    def _surf_rows(self, flat: np.ndarray, match: SurfCorrespondences, iteration: int, parameters=None):
        fa = self.params.feature_association
        usable = np.flatnonzero((match.index2 >= 0) & (match.index3 >= 0))
        points = flat[usable]
        p_start = transform_to_start(points, self.transform_cur)
        last = self.last_surf.points
        normal, distance = plane_coefficients(
            p_start, last[match.index1[usable]], last[match.index2[usable]], last[match.index3[usable]]
        )
        norm = np.sqrt(np.sqrt(squared_lengths(p_start)))
        weight = self._weights(distance, norm, iteration)
        ok = (weight > fa.min_weight) & (distance != 0) & np.isfinite(distance)
        coeff = np.concatenate([normal[ok] * weight[ok, None], (weight[ok] * distance[ok])[:, None]], axis=1)
        rows = plane_jacobian_rows(points[ok], coeff, self.transform_cur, parameters or self.SURF_PARAMS)
        return rows, -fa.step_scale * coeff[:, 3].astype(np.float64)

    def _corner_rows(self, sharp: np.ndarray, match: CornerCorrespondences, iteration: int, parameters=None):
        fa = self.params.feature_association
        usable = np.flatnonzero(match.index2 >= 0)
        points = sharp[usable]
        p_start = transform_to_start(points, self.transform_cur)
        last = self.last_corner.points
        gradient, distance = line_coefficients(p_start, last[match.index1[usable]], last[match.index2[usable]])
        weight = self._weights(distance, np.ones(len(distance)), iteration)
        ok = (weight > fa.min_weight) & np.isfinite(distance) & np.isfinite(gradient).all(axis=1)
        coeff = np.concatenate([gradient[ok] * weight[ok, None], (weight[ok] * distance[ok])[:, None]], axis=1)
        rows = plane_jacobian_rows(points[ok], coeff, self.transform_cur, parameters or self.CORNER_PARAMS)
        return rows, -fa.step_scale * coeff[:, 3].astype(np.float64)


class SweepStartOdometry(LaserOdometry):
    """The sweep-start model: full Gauss-Newton steps with the exact Jacobian, in blocks with backtracking."""

    native = True  # a block's iterations in C when the extension is built (False: the NumPy loop; tests compare)

    def _register(self, sharp: np.ndarray, flat: np.ndarray, wall: WallPoints, stats: OdometryStats) -> OdometryStats:
        """Register from the constant-velocity guess (:meth:`_iterate`). Few sharp points matched at the end:
        lost (a turn too fast for the lidar alone left the guess, and then each next one, in a wrong minimum,
        scan after scan into kilometres); register again from standing still and keep the better match."""
        guess, kept = self.transform_cur.copy(), self._iterate(sharp, flat, wall, stats)
        if not kept.corner_match_ratio < self.params.feature_association.lost_match_ratio or not guess.any():
            return kept
        estimate, self.transform_cur = self.transform_cur, np.zeros(6)
        retry = self._iterate(sharp, flat, wall, OdometryStats())
        retry.lost = kept.lost = True
        retry.extra['lost_match_ratio'] = kept.extra['lost_match_ratio'] = kept.corner_match_ratio
        retry.recovered = retry.corner_match_ratio > kept.corner_match_ratio
        self.transform_cur = self.transform_cur if retry.recovered else estimate
        return retry if retry.recovered else kept

    def _iterate(self, sharp: np.ndarray, flat: np.ndarray, wall: WallPoints, stats: OdometryStats) -> OdometryStats:
        """Both stages with full Gauss-Newton steps, in blocks of ``reassociate_every`` iterations.

        Each block associates the points anew and fixes their weights (1 in the first block, as the original;
        ``1 - gain |d|`` afterwards), so within a block the cost ``sum w d^2`` is fixed and each step is
        shortened until it does not increase that cost. Without this, full steps overshoot on the wrong
        correspondences of the first iterations and the edge stage bounces around; the original avoids that
        with 5 % steps, which then stop with up to 2 cm / 2 deg left.
        """
        fa = self.params.feature_association
        information, prior = np.zeros((6, 6)), np.zeros((6, 6))
        self._prepared_points = {}  # id -> (points, what _prepared makes of them), for this registration
        for stage in self._stages(sharp, flat, wall):
            kind = stage.kind
            iterations, first, last_residual = 0, True, None
            blocks = -(-fa.max_iterations // fa.reassociate_every)
            for block in range(blocks):
                residual = self._residual_function(stage, weighted=block > 0)
                if kind == 'corner':
                    stats.corner_match_ratio = self._own_matches / max(1, len(stage.points))
                if residual is None:
                    break
                last_residual = residual
                before = self.transform_cur.copy()
                count = min(fa.reassociate_every, fa.max_iterations - iterations)
                done, first = self._block(stage, residual, count, first, stats)
                iterations += done
                moved = self.transform_cur - before
                if (
                    np.degrees(np.abs(moved[:3])).max() < fa.convergence_rotation
                    and np.abs(moved[3:]).max() * 100 < fa.convergence_translation
                ):
                    break  # a whole block changed nothing: converged
            setattr(stats, f'{kind}_iterations', iterations)
            if last_residual is not None and iterations:
                jtj, squares, count, stage_prior = last_residual.information(self.transform_cur)
                information += stage_information(jtj, squares, count)
                prior += stage_prior
        stats.information = information if information.any() else None
        # The prior keeps its whole weight (the parameter) while the IMU agrees with the mapping to FULL_TRUST a sweep,
        # and falls as (FULL_TRUST / sigma)^2 beyond (core.imu.agreement): its information is 1 / max(FULL_TRUST,
        # sigma)^2 [rad^-2], what the agreement vouches for, no more.
        largest = self.params.feature_association.imu_rotation_prior
        stats.prior_information = prior / (largest * FULL_TRUST**2) if prior.any() and largest > 0 else None
        return stats

    def _block(self, stage: _Stage, residual, count: int, first: bool, stats: OdometryStats) -> tuple[int, bool]:
        """Up to ``count`` Gauss-Newton iterations of one block (``residual``'s correspondences and weights) from
        ``transform_cur``, which they update, in C when the extension is built (:meth:`_native_block`), else
        :meth:`_numpy_block`: (iterations run, whether the stage's first iteration is still to come)."""
        if count <= 0:
            return 0, first
        kind = stage.kind
        setattr(stats, f'{kind}_correspondences', residual.points)
        if residual.points < self.params.feature_association.min_correspondences:
            return 1, first
        if residual.block is not None:
            done, smallest = residual.block(self.transform_cur, count, first, stage.degeneracy)
        else:
            done, smallest = self._numpy_block(stage, residual, count, first)
        if first:
            setattr(stats, f'{kind}_condition', smallest)
            setattr(stats, f'{kind}_walls', residual.walls)
        setattr(stats, f'{kind}_degenerate', stage.degeneracy.degenerate)
        return done, False

    def _numpy_block(self, stage: _Stage, residual, count: int, first: bool) -> tuple[int, float]:
        """:meth:`_block`'s iterations in NumPy: (iterations run, the normal matrix's smallest eigenvalue on the
        stage's first iteration, NaN when it is not among them)."""
        fa = self.params.feature_association
        done, finds_degeneracy = 0, first
        for _ in range(count):
            done += 1
            rows, values = residual(self.transform_cur, jacobian=True)
            x = stage.degeneracy.step(rows, -values, first, fa.degeneracy_threshold)
            first = False
            x = self._shorten(x, stage.active, residual, float(np.square(values).sum()))
            if not self._apply(x, stage.active, stage.rotation_rows, stage.translation_rows):
                break  # converged
        return done, stage.degeneracy.smallest_eigenvalue if finds_degeneracy else math.nan

    def _residual_function(self, stage: _Stage, weighted: bool):
        """Associate the stage's points at the current estimate and return ``f(theta, jacobian)`` giving the weighted
        residuals (and their Jacobian rows) of the usable correspondences, weights fixed now; None with too
        few. The stage's own points (planes or lines) come first, then its wall planes (when it has any).
        """
        fa = self.params.feature_association
        own = self._term(stage.kind, stage.points, stage.last, weighted, self._forward_bound(stage.last, stage.points))
        self._own_matches = 0 if own is None else own.points
        terms = [] if own is None else [own]
        if stage.walls is not None and (0 if own is None else own.points) < fa.wall_fallback_below:
            # Too few of the stage's own correspondences (the floor of a corridor is hardly seen): without
            # the walls and ceiling the stage would be skipped and its stale motion integrated scan after scan.
            walls = self._term('wall', stage.walls(), self.last_surf, weighted, 0)
            terms += [] if walls is None else [walls]
        if sum(term.points for term in terms) < fa.min_correspondences:
            return None
        active = stage.active
        # The rotation prior: sqrt(w) * angle for each active rotation parameter, appended to the residuals.
        prior_columns = [k for k, parameter in enumerate(active) if parameter < 3] if self.rotation_prior > 0 else []
        prior_rows = np.zeros((len(prior_columns), len(active)))
        prior_rows[np.arange(len(prior_columns)), prior_columns] = math.sqrt(self.rotation_prior)
        prior_parameters = [active[k] for k in prior_columns]

        # The last evaluation, keyed by the bytes of its theta: the trial point _shorten accepts is the next
        # iteration's estimate (the same additions), whose residuals and Jacobian then reuse its frames.
        last_evaluation = [None, None, None]  # theta bytes, SweepStartFrames, values

        def residual(theta: np.ndarray, jacobian: bool = False):
            key = np.asarray(theta, dtype=np.float64).tobytes()
            if last_evaluation[0] == key:
                frames, values = last_evaluation[1], last_evaluation[2]
            else:
                frames = [SweepStartFrame(term.xyz, term.s, theta, term.trig) for term in terms]
                parts = [term.values(frame) for term, frame in zip(terms, frames)]
                if prior_parameters:
                    parts.append(math.sqrt(self.rotation_prior) * np.asarray(theta)[prior_parameters])
                values = np.concatenate(parts) if len(parts) > 1 else parts[0]
                last_evaluation[:] = key, frames, values
            if not jacobian:
                return values
            # Lines: the three components of each point, as the values.
            rows = [frame.rows(term.coefficients, active) for term, frame in zip(terms, frames)]
            if prior_parameters:
                rows.append(prior_rows)
            return (np.concatenate(rows) if len(rows) > 1 else rows[0]), values

        def information(theta: np.ndarray):
            """(JᵀJ of the correspondences' weighted residuals over all six parameters, their sum of squares, how
            many independent residuals they are (a line offset is two), the rotation prior's JᵀJ) at ``theta``."""
            residual(theta)  # (the frames at theta, usually those of the last step already)
            jtj, squares = np.zeros((6, 6)), 0.0
            for term, frame in zip(terms, last_evaluation[1]):
                rows = frame.rows(term.coefficients, ALL_PARAMS)
                jtj += rows.T @ rows
                squares += float(np.square(term.values(frame)).sum())
            prior = np.zeros((6, 6))
            prior[prior_parameters, prior_parameters] = self.rotation_prior
            count = sum(term.points * (2 if term.kind == 'corner' else 1) for term in terms)
            return jtj, squares, count, prior

        residual.points = sum(term.points for term in terms)
        residual.walls = any(term.wall for term in terms)
        residual.information = information
        residual.block = self._native_block(terms, active) if self.native else None
        return residual

    def _native_block(self, terms: list[_Term], active: list[int]):
        """``block(theta, count, first, degeneracy) -> (iterations run, smallest eigenvalue)``: up to ``count``
        iterations of a block (:meth:`_iterate`'s inner loop) in C, ``theta`` updated in place and ``degeneracy``
        (its first iteration when ``first``) as the loop leaves them; None without the extension or for terms it
        does not take (see native/odometry_kernels.c)."""
        if _odometry_kernels is None or not 1 <= len(terms) <= 4:
            return None
        packed = []
        for term in terms:
            if term.kind == 'corner':
                kind, first, second = 2, term.first, term.second
                if first.dtype != np.float64 or second.dtype != np.float64:
                    return None
            elif term.first.dtype == term.second.dtype and term.first.dtype in (np.float32, np.float64):
                kind, first, second = (0 if term.first.dtype == np.float32 else 1), term.first, term.second
            else:
                return None
            arrays = (term.xyz, term.s, term.weight, first, second, term.coefficients)
            if any(not a.flags.c_contiguous for a in arrays) or any(
                a.dtype != np.float64 for a in (term.xyz, term.s, term.weight, term.coefficients)
            ):
                return None
            packed.append((kind, *arrays))
        fa = self.params.feature_association
        active_parameters = np.asarray(active, dtype=np.int64)

        def block(theta: np.ndarray, count: int, first: bool, degeneracy: DegeneracyProjection):
            estimate = np.array(theta, dtype=np.float64)  # (a contiguous copy, written back below)
            projection = np.array(degeneracy.projection, dtype=np.float64)
            degenerate = np.array([degeneracy.degenerate], dtype=np.uint8)
            done, smallest = _odometry_kernels.sweep_block(
                estimate,
                active_parameters,
                packed,
                float(self.rotation_prior),
                int(count),
                int(bool(first)),
                float(fa.degeneracy_threshold),
                projection,
                degenerate,
                float(fa.convergence_rotation),
                float(fa.convergence_translation),
                HALVINGS,
            )
            theta[:] = estimate
            if first:
                degeneracy.projection = projection.reshape(3, 3)
                degeneracy.smallest_eigenvalue = smallest
            degeneracy.degenerate = bool(degenerate[0])
            return done, smallest

        return block

    def _term(self, kind: str, points: np.ndarray, last: LastCloud, weighted: bool, bound: int) -> _Term | None:
        """The usable correspondences of ``points`` at the current estimate, their fixed weights and residual
        coefficients; None when there are none. 'surf': planes through three points of the last cloud found
        as the original does; 'wall': least-squares planes through the nearest points of the last cloud (as
        the mapping's), for wall points, whose original-style search would cost whole rings per point;
        'corner': lines.

        Planes give one residual per point, the signed distance. Lines give three: the point's perpendicular
        offset from the line as a vector, ``(I - u u^T)(p - a)``. Its length is the original's point-to-line
        distance, but unlike that distance it is smooth where the point meets the line, so Gauss-Newton
        converges there instead of stepping back and forth across it.
        """
        fa = self.params.feature_association
        xyz, s, trig = self._prepared(points)
        start = np.empty((len(points), 4), dtype=_F32)  # transform_to_start, with what the stage keeps
        copy_columns(start, SweepStartFrame(xyz, s, self.transform_cur, trig).xyz())
        start[:, 3] = points[:, 3]
        # The planes and lines depend only on the last cloud: fixed for the whole block.
        if kind == 'wall':
            usable, normal, offset = self._wall_planes(start, last)
            p_start = select_rows(start, usable)
            distance = plane_distance(normal, offset, p_start[:, :3].astype(np.float64))
            scale = np.sqrt(np.sqrt(squared_lengths(p_start)))
            finite = np.isfinite(distance) & (distance != 0)
            anchors = (normal, offset)
        elif kind == 'surf':
            match = find_surf_correspondences(start, last, self.params, bound)
            usable = np.flatnonzero((match.index2 >= 0) & (match.index3 >= 0))
            normal, offset = plane_through(
                *(select_rows(last.points, index[usable]) for index in (match.index1, match.index2, match.index3))
            )
            p_start = select_rows(start, usable)
            distance = plane_distance(normal, offset, p_start).astype(np.float64)
            scale = np.sqrt(np.sqrt(squared_lengths(p_start)))
            finite = np.isfinite(distance) & np.isfinite(normal).all(axis=1) & (distance != 0)
            anchors = (normal, offset)
        else:
            match = find_corner_correspondences(start, last, self.params, bound)
            if self.native and hasattr(_feature_kernels, 'line_term'):
                made = self._line_terms(start, last, match, weighted)
                return None if made is None else self._made_term(kind, xyz, s, *made)
            usable = np.flatnonzero(match.index2 >= 0)
            a = xyz_columns(select_rows(last.points, match.index1[usable]))
            b = xyz_columns(select_rows(last.points, match.index2[usable]))
            with np.errstate(invalid='ignore', divide='ignore'):
                along = (a - b) / np.linalg.norm(a - b, axis=1)[:, None]
            p_start = xyz_columns(select_rows(start, usable))
            distance = np.linalg.norm(line_offsets(p_start, a, along), axis=1)
            scale = np.ones(len(distance))
            finite = np.isfinite(distance) & np.isfinite(along).all(axis=1)
            anchors = (a, along)
        weight = 1.0 - fa.weight_gain * np.abs(distance) / scale if weighted else np.ones(len(distance))
        keep = (weight > fa.min_weight) & finite
        if not keep.any():
            return None
        chosen = usable[keep]
        first, second = (select_rows(x, keep) for x in anchors)
        weight = weight[keep]
        if kind != 'corner':
            coefficients = first.astype(np.float64) * weight[:, None]  # the weighted normal
        else:
            # Rows of the projector I - u u^T, weighted: the coefficients of the three residual components.
            coefficients = (np.eye(3)[None, :, :] - second[:, :, None] * second[:, None, :]) * weight[:, None, None]
        return self._made_term(kind, xyz, s, chosen, first, second, weight, coefficients)

    @staticmethod
    def _made_term(kind, xyz, s, chosen, first, second, weight, coefficients) -> _Term:
        """The term of the points ``chosen`` among the stage's (their coordinates ``xyz`` (3, n) and times ``s``)."""
        s = s[chosen]
        return _Term(
            'surf' if kind == 'wall' else kind,
            xyz.take(chosen, axis=1),  # (the stage's float64 coordinates and times: the same values)
            s,
            weight,
            first,
            second,
            coefficients,
            kind == 'wall',
            SweepTrig(s),
        )

    def _line_terms(self, start: np.ndarray, last: LastCloud, match, weighted: bool):
        """:meth:`_term`'s lines from the correspondences ``match`` in one pass (native/feature_kernels.c
        ``line_term``, NumPy's operations in its order): (chosen, anchors, directions, weights, coefficients), or
        None when no line is usable."""
        fa = self.params.feature_association
        n = len(start)
        chosen, weight = np.empty(n, dtype=np.int64), np.empty(n)
        anchor, along, coefficients = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3))
        points = np.ascontiguousarray(last.points)
        kept = _feature_kernels.line_term(
            start,
            start.shape[1],
            points,
            points.shape[1],
            np.ascontiguousarray(match.index1, dtype=np.int64),
            np.ascontiguousarray(match.index2, dtype=np.int64),
            weighted,
            float(fa.weight_gain),
            float(fa.min_weight),
            chosen,
            anchor,
            along,
            weight,
            coefficients,
        )
        if not kept:
            return None
        return chosen[:kept], anchor[:kept], along[:kept], weight[:kept], coefficients[:kept]

    def _prepared(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, SweepTrig]:
        """(xyz (3, n) float64, relative times s (n,) float64, their :class:`SweepTrig`) of a stage's points, as
        :meth:`SweepStartFrame.of` makes them: made once per registration, not once per block (the points are
        the same, and the angles the stage holds fixed keep their sines and cosines)."""
        known = self._prepared_points.get(id(points))
        if known is None or known[0] is not points:
            s = relative_time_of(points[:, 3]).astype(np.float64)
            known = points, points[:, :3].T.astype(np.float64, order='C'), s, SweepTrig(s)
            self._prepared_points[id(points)] = known
        return known[1:]

    def _wall_planes(self, start: np.ndarray, last: LastCloud):
        """(indices of the wall points whose nearest points in the last cloud form a plane, its unit normals,
        offsets) with the mapping's neighbourhood and planarity settings."""
        mo = self.params.map_optimization
        if last.search is None or not len(start):
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
        near, index = nearest_within(last.tree, start[:, :3].astype(np.float64), mo.knn, mo.knn_max_sq_dist)
        # Neighbours all on one ring lie on a curve, about which the fitted plane may turn freely (ceilings
        # seen at grazing angles, where the rings are metres apart): only those spanning two rings or more.
        rings = last.rings[index]
        spanning = (rings != rings[:, :1]).any(axis=1)
        near, index = near[spanning], index[spanning]
        planar, normal, offset = fit_planes_at(last.points, index, mo.plane_max_residual)
        return near[planar], normal, offset

    def _shorten(
        self, x: np.ndarray, active: list[int], residual, reference: float, halvings: int = HALVINGS
    ) -> np.ndarray:
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


def make_laser_odometry(params: Params, fix_scan_bound: bool = False) -> LaserOdometry:
    """The odometry model ``feature_association.odometry_model`` names."""
    models: dict[OdometryModel, type[LaserOdometry]] = {'original': OriginalOdometry, 'sweep_start': SweepStartOdometry}
    return models[params.feature_association.odometry_model](params, fix_scan_bound)
