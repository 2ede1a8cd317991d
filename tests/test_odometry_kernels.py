"""The sweep-start odometry's Gauss-Newton blocks in C (native/odometry_kernels.c): against the NumPy loop they
replace, on the blocks of real registrations, and by hand."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from lego_loam_py.core.gauss_newton import DegeneracyProjection
from lego_loam_py.core.odometry import laser_odometry
from lego_loam_py.core.odometry.feature_association import FeatureAssociation, ScanInput
from lego_loam_py.core.odometry.laser_odometry import SweepStartOdometry
from lego_loam_py.core.params import Params
from lego_loam_py.core.projection.image_projection import ImageProjection, prepare_input
from tests.support.sweeps import motion_pose, room_world, sweep

kernels = laser_odometry._odometry_kernels
pytestmark = pytest.mark.skipif(kernels is None, reason='the C extension is not built here')

# Both run the same per-point arithmetic; only the sums' order and the 3x3 solve differ (a few ulps of the step).
TOLERANCE = 1e-12  # [rad], [m]


def _recorded_blocks(corridor: bool, prior: float, threshold: float) -> list[tuple]:
    """Every block of the registrations of six sweeps through a room (a corridor: its walls back up the planes),
    each run from the same state by the NumPy loop and by the kernel: (NumPy theta, C theta, NumPy and C
    (iterations, smallest eigenvalue), NumPy and C DegeneracyProjection). ``prior``: the rotation prior's weight
    (an IMU's, here without one); ``threshold``: the degeneracy threshold."""
    theta = np.array([0.0, math.radians(1.5), 0.0, 0.02, 0.0, -0.5])
    scene = room_world(seed=5, corridor=corridor)
    params = Params().replace(feature_association__degeneracy_threshold=threshold)
    ip, fa = ImageProjection(params), FeatureAssociation(params)
    blocks = []
    original, register = SweepStartOdometry._block, SweepStartOdometry._register

    def with_prior(self, *args):
        self.rotation_prior = prior
        return register(self, *args)

    def both(self, stage, residual, count, first, stats):
        if (
            count > 0
            and residual.block is not None
            and residual.points >= params.feature_association.min_correspondences
        ):
            start, state = self.transform_cur.copy(), copy.deepcopy(stage.degeneracy.__dict__)
            numpy_result = self._numpy_block(stage, residual, count, first)
            numpy_theta, numpy_state = self.transform_cur.copy(), copy.deepcopy(stage.degeneracy)
            native_state = DegeneracyProjection(3)
            native_state.__dict__.update(copy.deepcopy(state))
            native_theta = start.copy()
            native_result = residual.block(native_theta, count, first, native_state)
            blocks.append((numpy_theta, native_theta, numpy_result, native_result, numpy_state, native_state))
            self.transform_cur = start
            stage.degeneracy.__dict__.update(state)
        return original(self, stage, residual, count, first, stats)

    pose = np.eye(4)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(SweepStartOdometry, '_block', both)
        patch.setattr(SweepStartOdometry, '_register', with_prior)
        for k in range(6):
            r = ip.process(prepare_input(sweep(scene, pose, theta), params))
            fa.process(ScanInput.from_segmentation(k * 100_000_000, r))
            pose = pose @ motion_pose(theta, 1.0)
    return blocks


@pytest.mark.parametrize(
    ('corridor', 'prior', 'threshold'), [(False, 0.0, 10.0), (True, 0.0, 10.0), (True, 1e4, 120.0)]
)
def test_blocks_equal_the_numpy_loop(corridor, prior, threshold):
    blocks = _recorded_blocks(corridor, prior, threshold)
    assert len(blocks) >= 10
    for numpy_theta, native_theta, numpy_result, native_result, numpy_state, native_state in blocks:
        assert native_result[0] == numpy_result[0]  # the same iterations: the same steps accepted
        np.testing.assert_allclose(native_theta, numpy_theta, rtol=0, atol=TOLERANCE)
        if not math.isnan(numpy_result[1]):  # (the stage's first iteration: its smallest eigenvalue)
            assert native_result[1] == pytest.approx(numpy_result[1], rel=1e-9)
        assert native_state.degenerate == numpy_state.degenerate
        if numpy_state.degenerate:
            np.testing.assert_allclose(native_state.projection, numpy_state.projection, atol=1e-9)
    # Some blocks moved the estimate by much more than the tolerance: the comparison says something.
    assert max(np.abs(b[0] - b[1]).max() for b in blocks) < TOLERANCE
    assert sum(1 for b in blocks if b[2][0] > 1) >= 3
    # The threshold of 120 is above the plane stages' smallest eigenvalues here (about 30-110): their steps are
    # projected, those of the line stages (about 150) are not.
    assert (sum(b[4].degenerate for b in blocks) >= 3) == (threshold > 100)


def _plane_term(points: np.ndarray, normal, offset, s: float = 1.0):
    """A plane term (kind 1, float64) of ``points`` (n, 3) on the plane ``normal . p + offset = 0``, weights 1."""
    n = len(points)
    normals = np.tile(np.asarray(normal, dtype=np.float64), (n, 1))
    return (
        1,
        np.ascontiguousarray(points.T, dtype=np.float64),
        np.full(n, s),
        np.ones(n),
        normals,
        np.full(n, float(offset)),
        normals.copy(),
    )


def _run(theta, terms, active=(0, 2, 4), threshold=0.0, prior=0.0, iterations=10, first=True):
    theta = np.array(theta, dtype=np.float64)
    projection, degenerate = np.eye(3).reshape(-1).copy(), np.zeros(1, np.uint8)
    done, smallest = kernels.sweep_block(
        theta,
        np.array(active, dtype=np.int64),
        terms,
        prior,
        iterations,
        int(first),
        threshold,
        projection,
        degenerate,
        0.01,
        0.01,
        4,
    )
    return theta, done, smallest, projection.reshape(3, 3), bool(degenerate[0])


def test_points_on_a_floor_recover_its_height_by_hand():
    # Points of the floor y = -1 seen at the sweep's end (s = 1) at y = -0.75: the start points are R^T (p - t),
    # so ty = 0.25 puts them back on the floor (values exact in float32, as the start points are). One step
    # gets there, the next is below the thresholds.
    rng = np.random.default_rng(0)
    floor = np.column_stack([rng.uniform(-10, 10, 50), np.full(50, -0.75), rng.uniform(-10, 10, 50)])
    theta, done, smallest, _, degenerate = _run(np.zeros(6), [_plane_term(floor, (0.0, 1.0, 0.0), 1.0)])
    np.testing.assert_allclose(theta, [0, 0, 0, 0, 0.25, 0], atol=1e-12)
    assert done == 2
    assert smallest > 1.0 and not degenerate


def test_a_threshold_above_every_eigenvalue_holds_the_estimate():
    # Every direction below the degeneracy threshold: the projection is zero, no step is taken.
    rng = np.random.default_rng(1)
    floor = np.column_stack([rng.uniform(-10, 10, 50), np.full(50, -0.75), rng.uniform(-10, 10, 50)])
    theta, done, smallest, projection, degenerate = _run(
        np.zeros(6), [_plane_term(floor, (0.0, 1.0, 0.0), 1.0)], threshold=1e12
    )
    assert degenerate and done == 1 and 1.0 < smallest < 1e12
    np.testing.assert_array_equal(theta, np.zeros(6))
    np.testing.assert_array_equal(projection, np.zeros((3, 3)))


def test_a_degenerate_direction_is_projected_out():
    # Walls x = 2 and x = -2 (normals along x) and the parameters ry, tx, tz: the walls hold tx and the turn
    # about y, nothing of tz (its Jacobian column is zero at ry = 0): a zero eigenvalue, below the threshold, so
    # tz stays where it was while tx comes back to the walls (they were seen 0.1 m off).
    rng = np.random.default_rng(2)
    walls = [np.column_stack([np.full(30, x), rng.uniform(-1, 2, 30), rng.uniform(-10, 10, 30)]) for x in (2.0, -2.0)]
    terms = [_plane_term(walls[0], (1.0, 0.0, 0.0), -2.0), _plane_term(walls[1], (1.0, 0.0, 0.0), 2.0)]
    start = np.array([0.0, 0.0, 0.0, 0.1, 0.0, 0.3])
    theta, done, smallest, projection, degenerate = _run(start, terms, active=(1, 3, 5), threshold=1.0)
    assert degenerate and smallest == 0.0
    np.testing.assert_allclose(projection, np.diag([1.0, 1.0, 0.0]), atol=1e-12)
    assert theta[5] == 0.3
    assert abs(theta[3]) < 1e-6 and abs(theta[1]) < 1e-6 and done >= 2


def test_the_rotation_prior_holds_the_rotations_at_zero():
    # Without points (all at s = 0, so nothing depends on theta), only the prior: each step halves nothing and
    # goes straight to zero rotation; the translation, unconstrained (a singular normal matrix), stays.
    points = np.zeros((5, 3))
    term = _plane_term(points, (0.0, 1.0, 0.0), 1.0, s=0.0)
    theta, done, _, _, _ = _run(np.array([0.02, 0.0, -0.01, 0.0, 0.5, 0.0]), [term], prior=1e4)
    np.testing.assert_allclose(theta, [0.0, 0.0, 0.0, 0.0, 0.5, 0.0], atol=1e-15)
    assert np.isfinite(theta).all() and done == 2


def test_inconsistent_inputs_are_refused():
    floor = np.column_stack([np.arange(5.0), np.full(5, -1.0), np.arange(5.0)])
    term = _plane_term(floor, (0.0, 1.0, 0.0), 1.0)
    with pytest.raises(ValueError, match='term buffer sizes'):
        _run(np.zeros(6), [term[:6] + (term[6][:3],)])
    with pytest.raises(ValueError, match='parameters are 0 to 5'):
        _run(np.zeros(6), [term], active=(0, 2, 6))
    with pytest.raises(ValueError, match='number of terms'):
        _run(np.zeros(6), [])
    with pytest.raises(ValueError, match='term buffer sizes'):
        _run(np.zeros(6), [(3,) + term[1:]])


def _term_fields(term):
    return None if term is None else (term.xyz, term.s, term.weight, term.first, term.second, term.coefficients)


@pytest.mark.skipif(
    not hasattr(laser_odometry._feature_kernels, 'line_term'), reason='the C extension is not built here'
)
@pytest.mark.parametrize('seed', range(12))
def test_line_terms_equal_numpy_bit_for_bit(seed):
    """The line terms made in C (feature_kernels.c line_term) against _term's NumPy code, bit for bit: sharp points
    near the lines of a last cloud of 16 rings (some points duplicated, so that a line has no direction; some far
    off, so that their weight falls below the minimum), weighted or not, from a small estimated motion."""
    from lego_loam_py.core.odometry.correspondences import LastCloud

    rng = np.random.default_rng(seed)
    m = 400
    rings = np.sort(rng.integers(0, 16, m))
    last = np.empty((m, 4), dtype=np.float32)
    last[:, :3] = rng.uniform(-20, 20, (m, 3))
    last[:, 3] = rings + 0.05
    duplicated = rng.random(m) < 0.1
    last[1:][duplicated[1:], :3] = last[:-1][duplicated[1:], :3]
    n = 150
    source = rng.integers(0, m, n)
    points = last[source].copy()
    points[:, :3] += rng.normal(0.0, 0.05, (n, 3)).astype(np.float32) * rng.choice([1.0, 20.0], (n, 1), p=[0.8, 0.2])
    points[:, 3] = rings[source] + 0.1 * rng.random(n).astype(np.float32)
    odometry = SweepStartOdometry(Params())
    odometry.transform_cur = rng.normal(0.0, 0.01, 6)
    cloud = LastCloud(last, 16)
    for weighted in (False, True):
        made = []
        for native in (False, True):
            odometry.native = native
            odometry._prepared_points = {}
            made.append(_term_fields(odometry._term('corner', points, cloud, weighted, len(points))))
        numpy_term, native_term = made
        assert (numpy_term is None) == (native_term is None)
        if numpy_term is not None:
            assert len(numpy_term[2]) >= 10
            for reference, value in zip(numpy_term, native_term):
                assert reference.shape == value.shape and reference.dtype == value.dtype
                np.testing.assert_array_equal(value.view(np.int64), reference.view(np.int64))
