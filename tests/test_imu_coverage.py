"""An IMU that cannot cover a sweep is never dropped in silence: late samples are carried on at their last rate for
up to MAX_REACH; beyond that, and for a gap, samples that begin after the sweep, or none at all, the scan goes without
the IMU, counted by reason, with a throttled warning that names the cause and the parameter to change. The same
offline (core.pipeline) and over DDS (the featureAssociation node)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.core.imu.buffer import MAX_GAP, MAX_REACH, ImuBuffer, uncovered_counter, warn_uncovered
from lego_loam_py.core.params import Params
from lego_loam_py.core.pipeline import Pipeline
from lego_loam_py.inputs import ImuSample, Scan, open_source

REPO = Path(__file__).resolve().parents[1]
CAMPUS = REPO / 'bags' / 'campus_8s'


def _yawing_buffer(times: np.ndarray, yaw_rate: float = 0.5) -> ImuBuffer:
    imu = ImuBuffer()
    for t in times:
        half = 0.5 * yaw_rate * t
        assert imu.add(t, (0.0, 0.0, math.sin(half), math.cos(half)), (0.0, 0.0, yaw_rate), (0.0, 0.0, 9.81)) is None
    return imu


def test_the_coverage_of_a_sweep_says_why_it_fails():
    imu = ImuBuffer()
    assert imu.coverage(0.0, 0.1) == 'no_samples'
    imu = _yawing_buffer(np.arange(0.0, 1.0, 0.005))
    assert imu.coverage(0.2, 0.3) is None
    assert imu.coverage(-0.1, 0.0) == 'starts_after_sweep'
    assert imu.coverage(0.9, 1.0) is None  # ends 5 ms early: within reach
    assert imu.coverage(0.9 + MAX_REACH, 1.0 + MAX_REACH) == 'ends_before_sweep'
    gappy = _yawing_buffer(np.concatenate([np.arange(0.0, 0.5, 0.005), np.arange(0.5 + MAX_GAP + 0.01, 1.0, 0.005)]))
    assert gappy.coverage(0.45, 0.55) == 'gap'
    assert gappy.coverage(0.6, 0.7) is None


def test_the_table_built_from_the_appended_rows_only_is_the_whole_buffer_built_anew():
    """The arrays are extended by the rows appended since they were built (the oldest dropped past the capacity,
    a clear or a restart in between): the same as building them from every row."""
    rng = np.random.default_rng(3)
    imu, t = ImuBuffer(capacity=25), 0.0
    for burst in [0, 1, 3, 10, 24, 25, 30, 2, 0, 7]:
        for _ in range(burst):
            t += 0.005
            half = 0.25 * t
            imu.add(t, (0.0, 0.0, math.sin(half), math.cos(half)), tuple(rng.normal(0, 0.1, 3)), (0.0, 0.0, 9.81))
        if burst == 2:
            imu.clear()
        table = imu._table()
        assert table.shape == (len(imu), 13)
        np.testing.assert_array_equal(table, np.array(imu._rows, dtype=float).reshape(-1, 13))


def test_the_attitude_beyond_the_newest_sample_goes_on_at_its_last_rate():
    imu = _yawing_buffer(np.arange(0.0, 1.0, 0.005), yaw_rate=0.5)
    newest = 0.995
    roll, pitch, yaw = imu.attitude(np.array([newest, newest + 0.02, newest + 10.0]))
    np.testing.assert_allclose(yaw[:2], [0.5 * newest, 0.5 * (newest + 0.02)], atol=1e-9)
    assert yaw[2] == pytest.approx(0.5 * (newest + MAX_REACH))  # carried on for MAX_REACH at most
    np.testing.assert_allclose(np.r_[roll, pitch], 0.0, atol=1e-12)


def test_the_warning_comes_from_the_third_scan_and_then_every_hundredth():
    assert [n for n in range(1, 400) if warn_uncovered(n)] == [3, 100, 200, 300]


def _run(params: Params, imu_filter=None) -> tuple[dict, list[str]]:
    """The committed campus drive through the pipeline, its IMU samples passed through ``imu_filter`` (time [s]
    since the first scan -> keep?); returns the counters and the warnings."""
    warnings: list[str] = []
    pipeline = Pipeline(params, mapping=False, warn=warnings.append)
    first = None
    with open_source(CAMPUS) as source:
        for item in source.items():
            if isinstance(item, ImuSample):
                first = item.sample[0] if first is None else first
                if imu_filter is None or imu_filter(item.sample[0] - first):
                    pipeline.add_imu(item.sample)
            elif isinstance(item, Scan):
                pipeline.process_scan(item.points, item.stamp_ns)
    result = pipeline.finish()
    pipeline.close()
    return result.counts, warnings


def test_an_imu_whose_samples_end_too_long_before_the_sweep_is_counted_and_warned_about():
    """imu.time_offset 80 ms too large moves every sample back past the reach: no scan uses the IMU, each is counted,
    and the warning names imu.time_offset. 40 ms too large is carried over (the IMU used on every scan)."""
    counts, warnings = _run(Params().replace(imu__time_offset=0.08, imu__alignment_check=False))
    assert counts.get('scans_with_imu', 0) == 0
    assert counts[uncovered_counter('ends_before_sweep')] == counts['scans_processed']
    late = [w for w in warnings if 'newest IMU sample is older than the sweep' in w]
    assert late and 'imu.time_offset (now 0.08 s)' in late[0] and 'lego_loam_py calibrate' in late[0]
    counts, warnings = _run(Params().replace(imu__time_offset=0.04, imu__alignment_check=False))
    assert counts['scans_with_imu'] == counts['scans_processed']
    assert not any(key.startswith('imu_unused_') for key in counts) and not warnings


def test_a_gap_in_the_imu_and_an_imu_that_starts_late_are_counted_and_warned_about():
    # 80 ms of samples lost every half second: the sweeps across each hole go without the IMU, the others use it.
    counts, warnings = _run(Params().replace(imu__alignment_check=False), lambda t: t % 0.5 >= 0.08)
    gaps = counts[uncovered_counter('gap')]
    assert gaps >= 10 and any('gap of more than' in w for w in warnings)
    # Every scan used the IMU or is counted with its reason (a gap in its sweep or at the last sweep's start, the
    # first ones before the IMU began).
    unused = sum(value for key, value in counts.items() if key.startswith('imu_unused_'))
    assert counts['scans_with_imu'] + unused == counts['scans_processed']
    assert counts['scans_with_imu'] >= 0.5 * counts['scans_processed']
    # An IMU that starts 1.5 s after the lidar: until its first sample the run is lidar-only (that cannot be told
    # from a lidar without IMU); the sweep it begins in is counted; every later one uses it.
    counts, warnings = _run(Params().replace(imu__alignment_check=False), lambda t: t >= 1.5)
    assert counts[uncovered_counter('starts_after_sweep')] == 1
    assert counts['scans_with_imu'] >= counts['scans_processed'] - 17
    # imu.time_offset 0.15 s too small: the samples seem to begin 0.15 s after the first sweep; the first three
    # scans go without the IMU, and the third is warned about, naming the parameter.
    counts, warnings = _run(Params().replace(imu__time_offset=-0.15, imu__alignment_check=False))
    assert counts[uncovered_counter('starts_after_sweep')] == 3
    assert any(
        'begin after the sweep began' in w and 'imu.time_offset (now -0.15 s) may be too small' in w for w in warnings
    )


def test_a_lidar_without_imu_is_not_warned_about_but_an_imu_that_stops_is():
    counts, warnings = _run(Params(), lambda t: False)
    assert not any(key.startswith('imu_unused_') for key in counts) and not warnings
    counts, warnings = _run(Params().replace(imu__alignment_check=False), lambda t: t < 4.0)
    assert counts[uncovered_counter('ends_before_sweep')] >= 30
    assert any('IMU not used on the scan at' in w for w in warnings)


def test_the_node_counts_and_warns_the_same(context):
    """featureAssociation as a node, fed imageProjection's messages of the committed drive, with imu.time_offset
    80 ms too large: every scan counted without the IMU for its reason, and the throttled warning, as offline."""
    from lego_loam_py.ros.feature_association_node import FeatureAssociationNode
    from lego_loam_py.ros.image_projection_node import ImageProjectionNode
    from tests.support.inprocess import campus_messages, make_node

    ip, ip_rec = make_node(context, ImageProjectionNode)
    fa, fa_rec = make_node(context, FeatureAssociationNode, **{'imu.time_offset': 0.08, 'imu.alignment_check': False})
    for topic, msg in campus_messages(2.0):
        if topic == '/imu/data':
            fa.on_imu(msg)
            continue
        before = len(ip_rec.out('/segmented_cloud'))
        ip.on_cloud(msg)
        if len(ip_rec.out('/segmented_cloud')) > before:
            for part, out in (
                ('cloud', '/segmented_cloud'),
                ('info', '/segmented_cloud_info'),
                ('outlier', '/outlier_cloud'),
            ):
                fa.on_part(part, ip_rec.out(out)[-1])
    scans = len(ip_rec.out('/segmented_cloud'))
    assert scans >= 15 and fa.counters.get('scans_with_imu', 0) == 0
    assert fa.counters[uncovered_counter('ends_before_sweep')] == scans
    assert any(
        key == uncovered_counter('ends_before_sweep') and 'imu.time_offset (now 0.08 s)' in text
        for key, text in fa_rec.warnings
    )
    assert not fa_rec.errors
    ip.destroy_node()
    fa.destroy_node()
