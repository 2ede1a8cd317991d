"""featureAssociation's C kernels (native/feature_kernels.c): by hand, and against the NumPy/Python code they
replace."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lego_loam_py.core.odometry import features, sweep
from lego_loam_py.core.odometry.features import greedy_selection


def _select(native, edges, edge_bounds, flats, flat_bounds, jumps, half_window, taken, regions, *limits):
    taken = bytearray(taken)
    out = greedy_selection(
        np.array(edges, dtype=np.int64),
        np.array(edge_bounds),
        np.array(flats, dtype=np.int64),
        np.array(flat_bounds),
        np.array(jumps),
        half_window,
        taken,
        regions,
        *limits,
        native=native,
    )
    return [a.tolist() for a in out], bytes(taken)


def _native_or_skip(native):
    if native and not hasattr(features._feature_kernels, 'select_features'):
        pytest.skip('the C extension is not built here')


@pytest.mark.parametrize('native', [False, True])
def test_picks_suppress_their_neighbours_by_hand(native):
    _native_or_skip(native)
    # 10 points, one region, no column jump inside: each pick marks [k - 1, k + 2) (half window 1). Edge
    # candidates by curvature: 5, 6, 2, 8; 5 is sharp and marks 4..6, so 6 is skipped; 2 is the second (less
    # sharp, limit 2), marks 1..3; 8 exceeds the limit. Flats: 3 (taken by 2's mark), then 0 and 9: surf_num 1
    # stops after 0, without marking it.
    (sharp, less_sharp, flat, region), taken = _select(
        native, [5, 6, 2, 8], [0, 4], [3, 0, 9], [0, 3], [0, 10], 1, bytes(10), 1, 1, 2, 1
    )
    assert sharp == [5] and less_sharp == [5, 2] and region == [0, 0] and flat == [0]
    assert taken == bytes([0, 1, 1, 1, 1, 1, 1, 0, 0, 0])


@pytest.mark.parametrize('native', [False, True])
def test_suppression_stops_at_a_column_jump_by_hand(native):
    _native_or_skip(native)
    # 10 points, the column jumps between points 5 and 6 (jump at 6), half window 2. Edge 5 marks 3..5, not 6
    # or 7, so 6 is the next pick and marks 6..8 (its backward walk stops at the jump). The phantom entry -1
    # reads point 9, untaken: a flat pick whose slice is the Python slice [-3:0], empty.
    (sharp, less_sharp, flat, region), taken = _select(
        native, [5, 6], [0, 2], [-1, 2], [0, 2], [0, 6, 10], 2, bytes(10), 1, 2, 2, 2
    )
    assert sharp == [5, 6] and less_sharp == [5, 6] and region == [0, 0] and flat == [-1, 2]
    assert taken == bytes([0, 0, 0, 1, 1, 1, 1, 1, 1, 0])


@pytest.mark.skipif(
    not hasattr(features._feature_kernels, 'select_features'), reason='the C extension is not built here'
)
@settings(max_examples=200, deadline=None)
@given(st.data())
def test_native_selection_equals_the_python_loop(data):
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    n = int(rng.integers(1, 200))
    regions = int(rng.integers(0, 8))
    limits = (int(rng.integers(0, 4)), int(rng.integers(0, 10)), int(rng.integers(1, 6)))
    limits = (limits[0], max(limits[0], limits[1]), limits[2])

    def candidates():
        counts = rng.integers(0, 12, regions)
        index = rng.integers(-1, n, int(counts.sum()))  # -1: the phantom entry, read as point n - 1
        return index, np.concatenate(([0], np.cumsum(counts)))

    edges, edge_bounds = candidates()
    flats, flat_bounds = candidates()
    inner = np.flatnonzero(rng.random(max(n - 1, 0)) < 0.1) + 1
    jumps = np.concatenate(([0], inner, [n]))
    taken = (rng.random(n) < 0.2).astype(np.uint8).tobytes()
    args = (edges, edge_bounds, flats, flat_bounds, jumps, int(rng.integers(0, 6)), taken, regions, *limits)
    assert _select(True, *args) == _select(False, *args)


def _cloud(rng, n, nan=False):
    """n float32 points on a 1 m grid (so that distances tie), rings ascending in the intensity; with ``nan``
    a few NaN coordinates (queries may have them; a last cloud's KD-tree refuses them)."""
    points = np.zeros((n, 4), np.float32)
    points[:, :3] = rng.integers(-3, 4, (n, 3))
    if nan:
        points[rng.random(n) < 0.1, 0] = np.nan
    points[:, 3] = np.sort(rng.integers(0, 16, n)) + 0.05
    return points


@pytest.mark.skipif(features._feature_kernels is None, reason='the C extension is not built here')
@settings(max_examples=200, deadline=None)
@given(st.data())
def test_native_window_search_equals_numpy(data):
    from lego_loam_py.core.odometry.correspondences import LastCloud, _nearest_in_segments

    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    last = LastCloud(_cloud(rng, int(rng.integers(1, 60))), 16)
    queries = _cloud(rng, int(rng.integers(0, 12)), nan=True)[:, :3]
    lengths = rng.integers(0, 6, (len(queries), 4))
    position = rng.integers(0, len(last.points), int(lengths.sum()))
    limit = float(rng.choice([0.5, 2.0, 25.0]))
    native = _nearest_in_segments(queries, last, position, lengths, limit)
    reference = _nearest_in_segments(queries, last, position, lengths, limit, native=False)
    np.testing.assert_array_equal(native[0], reference[0])
    np.testing.assert_array_equal(native[1], reference[1])


def test_the_window_search_keeps_the_first_tie_forward_and_the_last_backward():
    from lego_loam_py.core.odometry.correspondences import LastCloud, _nearest_in_segments

    # Points 0 and 2 are 1 m from the query, point 1 is 2 m: a backward segment (kind 0) over [0, 1, 2] keeps 2,
    # a forward one (kind 2) keeps 0; a segment whose nearest point is beyond the limit keeps none.
    points = np.array([[1, 0, 0, 0], [2, 0, 0, 0], [-1, 0, 0, 0]], np.float32)
    last = LastCloud(points, 16)
    query = np.zeros((1, 3), np.float32)
    for native in (True, False):
        index, best = _nearest_in_segments(
            query, last, np.array([0, 1, 2, 0, 1, 2, 1]), np.array([[3, 0, 3, 1]]), 1.5, native=native
        )
        assert index.tolist() == [[2, -1, 0, -1]]
        assert best.tolist() == [[1.0, np.inf, 1.0, np.inf]]


@pytest.mark.skipif(features._feature_kernels is None, reason='the C extension is not built here')
@settings(max_examples=150, deadline=None)
@given(st.data())
def test_native_whole_window_search_equals_numpy(data):
    """The one-pass search of a ring-ordered cloud (windows, segments and nearest points in C) against the NumPy
    windows, segments and nearest points, for both correspondence kinds, any forward bound and window."""
    from lego_loam_py.core.odometry.correspondences import LastCloud

    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    last = LastCloud(_cloud(rng, int(rng.integers(1, 300))), 16)
    queries = _cloud(rng, int(rng.integers(0, 20)))  # (the KD-tree refuses NaN queries)
    queries[:, :3] += rng.normal(0.0, 0.3, (len(queries), 3)).astype(np.float32) * (rng.random() < 0.5)
    _assert_window_search_equals_numpy(rng, last, queries, windows=[0.5, 1.0, 2.5, 4.0])


def _assert_window_search_equals_numpy(rng, last, queries, windows) -> None:
    """The C window search of ``queries`` in the LastCloud ``last`` equals NumPy's, for a limit, a ring window (one
    of ``windows``), a forward bound and the correspondence kinds drawn with ``rng``."""
    from lego_loam_py.core.odometry.correspondences import _OTHER, _SAME, _window_search
    from lego_loam_py.core.params import Params

    params = Params().replace(
        feature_association__nearest_feature_search_sq_dist=float(rng.choice([0.5, 2.0, 25.0])),
        feature_association__ring_search_window=float(rng.choice(windows)),
    )
    bound = int(rng.integers(0, len(last.points) + 3))
    kinds = [_SAME + _OTHER, _OTHER][int(rng.integers(0, 2))]
    native = _window_search(queries, last, params, bound, kinds)
    reference = _window_search(queries, last, params, bound, kinds, native=False)
    for a, b in zip(native, reference):
        np.testing.assert_array_equal(a, b)


def _ring_cloud(rng, rings: int) -> np.ndarray:
    """Points along rings of 5-40 m as a lidar's last cloud holds them (rings ascending, each in azimuth order),
    with exact copies of some points elsewhere in their ring, so that ties lie apart."""
    parts = []
    for ring in range(rings):
        count = int(rng.integers(1, 120))
        azimuth = np.sort(rng.uniform(-np.pi, np.pi, count))
        radius = rng.uniform(5.0, 40.0) + rng.normal(0.0, 0.05, count)
        part = np.zeros((count, 4), np.float32)
        part[:, 0], part[:, 1] = radius * np.cos(azimuth), radius * np.sin(azimuth)
        part[:, 2] = ring * 0.3 - 1.0
        copies = rng.random(count) < 0.1
        part[copies, :3] = part[rng.integers(0, count, int(copies.sum())), :3]
        part[:, 3] = ring + 0.05
        parts.append(part)
    return np.concatenate(parts)


@pytest.mark.skipif(features._feature_kernels is None, reason='the C extension is not built here')
@settings(max_examples=150, deadline=None)
@given(st.data())
def test_native_window_search_on_rings_equals_numpy(data):
    """Clouds spread like a lidar's (most points far from a query, beyond the search's limit), with exact ties far
    apart in their ring and queries on points, beside them and far away: the same points and distances."""
    from lego_loam_py.core.odometry.correspondences import LastCloud

    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    last = LastCloud(_ring_cloud(rng, int(rng.integers(1, 12))), 16)
    queries = last.points[rng.integers(0, len(last.points), int(rng.integers(1, 40)))].copy()
    noise = rng.choice([0.0, 0.01, 0.5, 3.0], size=(len(queries), 1))
    queries[:, :3] += (rng.normal(size=(len(queries), 3)) * noise).astype(np.float32)
    _assert_window_search_equals_numpy(rng, last, queries, windows=[1.0, 2.5])


@pytest.mark.skipif(features._feature_kernels is None, reason='the C extension is not built here')
@settings(max_examples=200, deadline=None)
@given(st.data())
def test_native_sweep_rows_equal_numpy(data):
    """SweepStartFrame.rows in C against its NumPy expressions, bit for bit: one or three coefficient vectors per
    point, any active parameters, with and without remembered sines and cosines."""
    from lego_loam_py.core.odometry.sweep import SweepStartFrame, SweepTrig

    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    n = int(rng.integers(0, 40))
    xyz = rng.normal(0.0, 10.0, (3, n))
    s = 1.0 + rng.random(n)
    theta = rng.normal(0.0, 0.1, 6) * (rng.random(6) < 0.8)
    # (a frame made in NumPy gives the C rows its products stacked; one made in C, its own block)
    frame = SweepStartFrame(xyz, s, theta, SweepTrig(s) if rng.random() < 0.5 else None, native=rng.random() < 0.5)
    coeff = rng.normal(0.0, 1.0, (n, 3, 3) if rng.random() < 0.5 else (n, 3))
    active = [int(k) for k in rng.choice(6, int(rng.integers(1, 7)), replace=False)]
    native = frame.rows(coeff, active)
    reference = frame.rows(coeff, active, native=False)
    assert native.shape == reference.shape and (native.strides == reference.strides or not n)
    np.testing.assert_array_equal(native.view(np.int64), reference.view(np.int64))


@pytest.mark.skipif(features._feature_kernels is None, reason='the C extension is not built here')
@settings(max_examples=200, deadline=None)
@given(st.data())
def test_native_sweep_frame_equals_numpy(data):
    """SweepStartFrame's products and start points in C against its NumPy expressions, bit for bit (signed zeros
    too), with and without remembered sines and cosines."""
    from lego_loam_py.core.odometry.sweep import SweepStartFrame, SweepTrig

    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    n = int(rng.integers(0, 40))
    xyz = rng.normal(0.0, 10.0, (3, n)) * (rng.random((3, n)) < 0.9)
    s = rng.random(n) * (rng.random(n) < 0.9) + (rng.random() < 0.5)
    theta = rng.normal(0.0, 0.1, 6) * (rng.random(6) < 0.8) * rng.choice([1.0, -1.0])
    trig = SweepTrig(s) if rng.random() < 0.5 else None
    native = SweepStartFrame(xyz, s, theta, trig)
    reference = SweepStartFrame(xyz, s, theta, trig, native=False)
    for name in ('cx', 'sx', 'cy', 'sy', 'cz', 'sz', 'qx', 'qy', 'qz', 'ux', 'uy', 'vy', 'vz'):
        np.testing.assert_array_equal(getattr(native, name).view(np.int64), getattr(reference, name).view(np.int64))
    np.testing.assert_array_equal(native.xyz().view(np.int32), reference.xyz().view(np.int32))


@pytest.mark.skipif(features._feature_kernels is None, reason='the C extension is not built here')
@settings(max_examples=200, deadline=None)
@given(st.data())
def test_native_imu_rotation_equals_rotate_by_euler(data):
    """imu_rotate's C products against core.frames.rotate_by_euler, bit for bit (signed zeros too): float32 points
    of three or four columns, zero angles and coordinates among them, any left rotation."""
    from scipy.spatial.transform import Rotation

    from lego_loam_py.core.imu.buffer import imu_rotate

    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    n = int(rng.integers(0, 40))
    roll, pitch, yaw = (rng.normal(0.0, 1.0, n) * (rng.random(n) < 0.8) for _ in range(3))
    points = (rng.normal(0.0, 10.0, (n, int(rng.integers(3, 5)))) * (rng.random((n, 1)) < 0.9)).astype(np.float32)
    left = np.eye(3) if rng.random() < 0.3 else Rotation.from_rotvec(rng.normal(0.0, 1.0, 3)).as_matrix()
    left = left.T if rng.random() < 0.5 else left
    native = imu_rotate(left, roll, pitch, yaw, points)
    reference = imu_rotate(left, roll, pitch, yaw, points, native=False)
    assert native.shape == reference.shape == (n, 3)
    np.testing.assert_array_equal(native.view(np.int64), reference.view(np.int64))


@pytest.mark.skipif(features._feature_kernels is None, reason='the C extension is not built here')
@settings(max_examples=300, deadline=None)
@given(st.data())
def test_native_imu_attitude_equals_numpy(data):
    """ImuBuffer.attitude's C interpolation against the NumPy bracketing and interpolation, bit for bit: repeated
    stamps, yaw across +-pi, times before, between, on and beyond the samples (carried on at the newest rates,
    again after newer samples came), in any order and ascending, NaN."""
    from lego_loam_py.core.imu.buffer import ImuBuffer

    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    buffer = ImuBuffer(200)
    m = int(rng.integers(1, 12))
    stamps = 100.0 + np.sort(np.round(rng.random(m) * 0.1, int(rng.integers(1, 4))))  # (ties when rounded)
    rows = rng.normal(0.0, 1.0, (m, 13))
    rows[:, 0] = stamps
    rows[:, 3] = rng.uniform(-np.pi, np.pi, m)
    rows[rng.random(m) < 0.2, 1] = 0.0
    buffer._rows.extend(tuple(row) for row in rows.tolist())
    for _ in range(2):  # (then with newer samples: the newest rates the carrying on uses change)
        times = 100.0 + rng.uniform(-0.02, 0.2, int(rng.integers(0, 30)))
        exact = rng.random(len(times)) < 0.2
        times[exact] = stamps[rng.integers(0, m, int(exact.sum()))]
        if rng.random() < 0.5:  # ascending, as a sweep's times mostly are (each bracket tried from the last)
            times.sort()
        times[rng.random(len(times)) < 0.05] = np.nan
        native = np.array(buffer.attitude(times))
        reference = np.array(buffer.attitude(times, native=False))
        np.testing.assert_array_equal(native.view(np.int64), reference.view(np.int64))
        newer = rng.normal(0.0, 1.0, (3, 13))
        newer[:, 0] = stamps[-1] + np.sort(rng.uniform(0.0, 0.05, 3))
        buffer._rows.extend(tuple(row) for row in newer.tolist())
        buffer._appended += 3
        stamps = np.concatenate([stamps, newer[:, 0]])


@pytest.mark.skipif(features._feature_kernels is None, reason='the C extension is not built here')
@settings(max_examples=200, deadline=None)
@given(st.data())
def test_native_rotation_at_imu_times_equals_numpy(data):
    """ImuBuffer.rotate_at in one C pass against NumPy's attitude and rotate_by_euler, bit for bit: times between,
    on and beyond the samples (carried on), ascending or not, some NaN, points of three or four columns, the left
    rotation or its transpose."""
    from lego_loam_py.core.frames import euler_to_matrix
    from lego_loam_py.core.imu.buffer import ImuBuffer

    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    buffer = ImuBuffer(200)
    m = int(rng.integers(1, 30))
    rows = rng.normal(0.0, 0.3, (m, 13))
    rows[:, 0] = 100.0 + np.sort(rng.random(m) * 0.1)
    rows[:, 3] = rng.uniform(-np.pi, np.pi, m)
    buffer._rows.extend(tuple(row) for row in rows.tolist())
    n = int(rng.integers(0, 400))
    times = 100.0 + rng.uniform(-0.01, 0.15, n)
    if rng.random() < 0.5:
        times.sort()
    times[rng.random(n) < 0.02] = np.nan
    points = (rng.normal(0.0, 20.0, (n, int(rng.integers(3, 5))))).astype(np.float32)
    left = euler_to_matrix(*rng.uniform(-3.0, 3.0, 3))
    left = left.T if rng.random() < 0.5 else left
    native = buffer.rotate_at(times, left, points)
    reference = buffer.rotate_at(times, left, points, native=False)
    assert native.shape == reference.shape == (n, 3)
    np.testing.assert_array_equal(native, reference)  # (NaN where the time is NaN and there are two samples)


@pytest.mark.skipif(features._feature_kernels is None, reason='the C extension is not built here')
@settings(max_examples=200, deadline=None)
@given(st.data())
def test_native_imu_samples_equal_python(data):
    """ImuBuffer.add's common case in C against its Python code, bit for bit, on a stream of unit quaternions
    (some not: rejected), rates and accelerations near and beyond the bounds, NaN, stamps out of order, far
    back (a restart) and after gaps, with a time offset, the gyro's attitude (its bias changed on the way) or the
    orientation field's; the same rows, reasons, counters and gyro state."""
    from lego_loam_py.core.frames import ImuMounting
    from lego_loam_py.core.imu.buffer import ImuBuffer

    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    gyro, offset = bool(rng.random() < 0.7), float(rng.choice([0.0, 0.012]))
    n = int(rng.integers(1, 60))
    steps = rng.choice([0.005, 0.2, -0.003, -2.0, 0.0], n, p=[0.8, 0.05, 0.05, 0.05, 0.05])
    stamps = 50.0 + np.cumsum(steps)
    quaternions = rng.normal(0.0, 1.0, (n, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1)[:, None]
    quaternions[rng.random(n) < 0.1] *= 1.5
    quaternions[rng.random(n) < 0.05] = 0.0
    rates = rng.normal(0.0, 1.0, (n, 3)) * rng.choice([1.0, 80.0], (n, 1), p=[0.9, 0.1])
    accelerations = rng.normal(0.0, 5.0, (n, 3)) * rng.choice([1.0, 150.0], (n, 1), p=[0.9, 0.1])
    accelerations[rng.random(n) < 0.03, 1] = np.nan
    buffers = []
    for native in (False, True):
        buffer = ImuBuffer(64, 9.81, 0.1, ImuMounting(time_offset=offset), gyro_attitude=gyro)
        buffer.native = native
        reasons = []
        for k in range(n):
            if gyro and k == n // 2:
                buffer.gyro.bias = np.array([0.002, -0.001, 0.003])
            reasons.append(buffer.add(stamps[k], tuple(quaternions[k]), tuple(rates[k]), tuple(accelerations[k])))
        buffers.append((buffer, reasons))
    (python, python_reasons), (c, c_reasons) = buffers
    assert c._native and not python._native
    assert c_reasons == python_reasons
    assert (c.accepted, c.resets, c.rejected) == (python.accepted, python.resets, python.rejected)
    np.testing.assert_array_equal(np.array(list(c._rows)).view(np.int64), np.array(list(python._rows)).view(np.int64))
    if gyro:
        np.testing.assert_array_equal(c.gyro.state.view(np.int64), python.gyro.state.view(np.int64))


@pytest.mark.skipif(features._feature_kernels is None, reason='the C extension is not built here')
@settings(max_examples=150, deadline=None)
@given(st.data())
def test_native_occlusion_marks_equal_numpy(data):
    """features.occluded_mask in C against its NumPy version: ranges with jumps, ties, zeros and NaN, columns with
    gaps, any half window (0: the first neighbour wraps), thresholds and scan length."""
    from lego_loam_py.core.params import Params

    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    n = int(rng.integers(0, 60))
    ranges = (rng.choice([1.0, 5.0, 20.0], n) + rng.normal(0.0, 0.5, n) * (rng.random(n) < 0.7)).astype(np.float32)
    ranges[rng.random(n) < 0.05] = np.nan
    ranges[rng.random(n) < 0.05] = 0.0
    columns = np.cumsum(rng.choice([1, 1, 1, 2, 15], n)) - rng.integers(0, 3)
    params = Params().replace(
        feature_association__smoothness_half_window=int(rng.integers(0, 7)),
        feature_association__occlusion_column_gap=int(rng.choice([1, 10, 100])),
        feature_association__occlusion_depth_jump=float(rng.choice([0.1, 0.3, 3.0])),
        feature_association__parallel_beam_ratio=float(rng.choice([0.0, 0.02, 0.5])),
    )
    native = features.occluded_mask(ranges, columns, params)
    reference = features.occluded_mask(ranges, columns, params, native=False)
    np.testing.assert_array_equal(native, reference)


@pytest.mark.skipif(not hasattr(sweep._libm_compat, 'azimuth_fraction'), reason='the C extension is not built here')
@settings(max_examples=100, deadline=None)
@given(st.data())
def test_native_relative_times_from_azimuth_equal_numpys(data):
    """Points in every direction, on the axes, at the origin (signed zeros), far away and not finite, against start
    orientations anywhere in a turn and beyond, the modulo's sign cases included: every float32 bit alike."""
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    n = int(rng.integers(0, 400))
    points = (rng.normal(size=(n, 4)) * rng.choice([1e-3, 1.0, 50.0, 1e30], size=(n, 1))).astype(np.float32)
    special = np.array([0.0, -0.0, np.nan, np.inf, -np.inf, 1.0, -1.0], dtype=np.float32)
    odd = rng.random((n, 2)) < 0.1
    points[:, :2][odd] = rng.choice(special, size=int(odd.sum()))
    start = float(data.draw(st.sampled_from([-math.pi, -math.pi / 2, 0.0, -0.0, math.pi, 4.0])))
    start = start if rng.random() < 0.5 else float(rng.uniform(-4, 4))
    diff = float(data.draw(st.sampled_from([2 * math.pi, math.pi, 3 * math.pi, 1e-9]))) * float(rng.uniform(0.9, 1.1))
    info = SimpleNamespace(start_orientation=np.float32(start), orientation_diff=np.float32(diff))
    with np.errstate(all='ignore'):
        native = sweep.relative_time_from_azimuth(points, info)
        expected = sweep.relative_time_from_azimuth(points, info, native=False)
    assert native.dtype == expected.dtype == np.float32
    assert native.tobytes() == expected.tobytes()


def test_relative_times_from_azimuth_by_hand():
    """A quarter turn clockwise from the start orientation (the azimuth is -atan2(y, x)) is a quarter of a sweep of
    one turn; the start itself is 0; a point just before the start wraps to almost a whole turn."""
    info = SimpleNamespace(start_orientation=np.float32(0.0), orientation_diff=np.float32(2 * math.pi))
    points = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [-1, 0, 0, 0], [1, 1e-3, 0, 0]], dtype=np.float32)
    for native in (True, False):
        got = sweep.relative_time_from_azimuth(points, info, native=native)
        assert got[:3].tolist() == pytest.approx([0.0, 0.25, 0.5], abs=1e-6)
        assert 0.999 < got[3] < 1.0
