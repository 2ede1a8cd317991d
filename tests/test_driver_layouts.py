"""Every common driver's PointCloud2 layout gives the points, rings and times of the plain one.

A short simulated campus recording (3 s) is rewritten into each driver's layout (lego_loam_py.sim.driver_layouts:
Velodyne organized with NaN, Ouster organized with zero points and ``t`` in ns, Hesai and RoboSense with absolute
float64 ``timestamp``, Livox ``offset_time``, float64 coordinates, x/y/z/intensity alone), and

* each sweep reads into the plain sweep's points, rings and times, and imageProjection's outputs are the plain
  ones bit for bit (the sweep's start orientation included);
* the offline pipeline gives the plain layout's trajectory exactly (the points are bit-identical), and, with the
  per-point times in use (``relative_time_source: point_time``), within 2 % of its ATE;
* layouts that cannot be read are refused with one line naming the field and what was expected, and the
  pipeline drops such a scan, counted, and goes on.
"""

from __future__ import annotations

import numpy as np
import pytest

from lego_loam_py.bag.io import BagReader, cloud_msg_to_array
from lego_loam_py.core.params import Params
from lego_loam_py.core.pipeline import Pipeline
from lego_loam_py.core.pointcloud import (
    POINT_XYZI_DTYPE,
    VELODYNE_POINT_DTYPE,
    CloudLayoutError,
    array_to_cloud,
    cloud_to_array,
    velodyne_points,
)
from lego_loam_py.core.projection.driver_layouts import read_cloud, rings_count_down, seconds_since_sweep_start
from lego_loam_py.core.projection.image_projection import ImageProjection, prepare_input
from lego_loam_py.evaluation import evaluate
from lego_loam_py.inputs.sidecars import load_ground_truth
from lego_loam_py.offline import run_bag
from lego_loam_py.sim.driver_layouts import LAYOUTS, OUSTER_DTYPE, cached_layout, in_layout, pixels_of

PARAMS = Params()
POINT_TIME = PARAMS.replace(feature_association__relative_time_source='point_time')
ROWS, COLUMNS, STAMP_NS = 16, 1800, 1_700_000_000_100_000_000
OTHERS = [layout for layout in LAYOUTS if layout != 'plain']
WITH_TIME = [layout for layout in OTHERS if layout != 'xyzi']


@pytest.fixture(scope='module')
def bag():
    from lego_loam_py.sim.simulator import cached_scenario

    return cached_scenario('campus', duration=3.0)


@pytest.fixture(scope='module')
def sweeps(bag):
    """The first three sweeps of the recording (plain layout)."""
    out = []
    with BagReader(bag) as reader:
        for message in reader.messages(['/velodyne_points']):
            out.append(cloud_msg_to_array(reader.deserialize(message)).copy())
            if len(out) == 3:
                return out


def through_the_message(points: np.ndarray) -> np.ndarray:
    """The array as a PointCloud2's bytes and back (organized clouds keep their rows)."""
    return cloud_to_array(array_to_cloud(points))


def by_coordinates(xyz: np.ndarray) -> np.ndarray:
    """The order that sorts points by x, then y, then z (every simulated point is unique)."""
    return np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))


# ------------------------------------------------------------------------------------ each layout, one sweep


@pytest.mark.parametrize('layout', OTHERS)
def test_each_layout_reads_into_the_plain_points_rings_and_times(sweeps, layout):
    for points in sweeps:
        plain = prepare_input(points, PARAMS)
        driver = prepare_input(through_the_message(in_layout(points, layout, STAMP_NS, ROWS, COLUMNS)), PARAMS)
        assert driver.xyz.shape == plain.xyz.shape
        # The same points with the same rings; in the plain order but for the organized Velodyne cloud, which
        # keeps its own order within a firing (ring by ring).
        mine, theirs = by_coordinates(driver.xyz), by_coordinates(plain.xyz)
        assert np.array_equal(driver.xyz[mine], plain.xyz[theirs])
        if layout != 'velodyne_organized':
            assert np.array_equal(driver.xyz, plain.xyz)
        if layout in ('xyzi', 'livox'):  # no ring field (Livox's 'line' is no beam of a spinning head)
            assert driver.ring is None
        else:
            assert np.array_equal(driver.ring[mine], plain.ring[theirs])
        if layout == 'xyzi':
            assert driver.time is None
            continue
        # Times: seconds since the sweep start; absolute ones since the sweep's earliest point.
        expected = plain.time[theirs].astype(np.float64)
        if layout in ('hesai', 'robosense'):
            expected -= plain.time.min()
        assert np.abs(driver.time[mine] - expected).max() < 1e-6
        assert driver.rings_from_top == (layout in ('ouster', 'hesai'))
        assert driver.time_ordered == (layout == 'ouster')


@pytest.mark.parametrize('layout', OTHERS)
def test_each_layout_gives_the_plain_image_projection_bit_for_bit(sweeps, layout):
    ip = ImageProjection(PARAMS)
    for points in sweeps:
        plain = ip.process(prepare_input(points, PARAMS))
        driver = ip.process(
            prepare_input(through_the_message(in_layout(points, layout, STAMP_NS, ROWS, COLUMNS)), PARAMS)
        )
        assert driver.cloud_info.start_orientation == plain.cloud_info.start_orientation
        assert driver.cloud_info.end_orientation == plain.cloud_info.end_orientation
        for name in ('segmented_cloud', 'outlier_cloud', 'ground_cloud', 'full_cloud', 'label_image'):
            assert np.array_equal(getattr(driver, name), getattr(plain, name), equal_nan=True), name
        missing = ROWS * COLUMNS - len(points)
        assert driver.stats['at_origin'] == (missing if layout == 'ouster' else 0)
        assert driver.stats['non_finite'] == (missing if layout == 'velodyne_organized' else 0)
        assert driver.stats['input_points'] == (
            ROWS * COLUMNS if layout in ('ouster', 'velodyne_organized') else len(points)
        )


def test_the_ouster_layout_is_the_drivers(sweeps):
    """Rows x columns, row 0 the top beam, zero points where no return, t in ns, 48-byte points, dense."""
    points = sweeps[0]
    grid = in_layout(points, 'ouster', STAMP_NS, ROWS, COLUMNS)
    cloud = array_to_cloud(grid)
    assert (cloud.height, cloud.width, cloud.point_step, cloud.is_dense) == (ROWS, COLUMNS, 48, True)
    assert grid.dtype == OUSTER_DTYPE and np.array_equal(grid['ring'][:, 0], np.arange(ROWS))
    empty = (grid['x'] == 0) & (grid['y'] == 0) & (grid['z'] == 0)
    assert np.count_nonzero(~empty) == len(points)
    top = points[points['ring'] == ROWS - 1]
    assert np.count_nonzero(~empty[0]) == len(top)  # the top beam is row 0
    assert grid['t'].dtype == np.uint32 and grid['t'].max() < 100_000_000
    velodyne = in_layout(points, 'velodyne_organized', STAMP_NS, ROWS, COLUMNS)
    assert velodyne.shape == (COLUMNS, ROWS) and not array_to_cloud(velodyne).is_dense


def test_points_at_the_origin_never_set_the_sweeps_start_orientation(sweeps):
    """A beam-major cloud whose first pixels have no return: the orientation still comes from the sweep's first
    measured point (the origin's atan2 would say 0, the top beam's first return somewhere later)."""
    points = sweeps[0]
    grid = in_layout(points, 'ouster', STAMP_NS, ROWS, COLUMNS)
    grid[:, :40]['x'] = 0  # the first 40 columns (8 deg) lose every return: the sweep starts later
    grid[:, :40]['y'] = 0
    grid[:, :40]['z'] = 0
    kept = points[pixels_of(points, COLUMNS)[1] >= 40]
    ip = ImageProjection(PARAMS)
    driver, plain = ip.process(prepare_input(grid, PARAMS)), ip.process(prepare_input(kept, PARAMS))
    assert driver.cloud_info.start_orientation == plain.cloud_info.start_orientation
    assert abs(float(plain.cloud_info.start_orientation) - np.radians(8.0)) < np.radians(0.3)
    assert np.array_equal(driver.segmented_cloud, plain.segmented_cloud)


# ------------------------------------------------------------------------------ each layout, whole pipeline


@pytest.fixture(scope='module')
def plain_runs(bag):
    return {
        params_name: run_bag(bag, params, progress=False)
        for params_name, params in (('default', PARAMS), ('point_time', POINT_TIME))
    }


@pytest.mark.parametrize('layout', OTHERS)
def test_each_layout_gives_the_plain_trajectory(bag, plain_runs, layout):
    """The points are bit-identical in every layout: the offline pipeline's trajectory is the plain one exactly."""
    plain = plain_runs['default']
    result = run_bag(cached_layout(bag, layout), PARAMS, progress=False)
    assert result.counts['scans_processed'] == plain.counts['scans_processed'] == 30
    stamps, poses = result.trajectory()
    plain_stamps, plain_poses = plain.trajectory()
    assert np.array_equal(stamps, plain_stamps) and np.array_equal(poses, plain_poses)


@pytest.mark.parametrize('layout', WITH_TIME)
def test_each_layouts_times_give_the_plain_accuracy(bag, plain_runs, layout):
    """With the per-point times deskewing the sweeps, every layout's times (ns, absolute, since the stamp) give the
    plain run's ATE within 2 % (exactly where the times are the plain float32 seconds)."""
    truth = load_ground_truth(bag)
    plain = evaluate(truth, plain_runs['point_time'].trajectory()).ate_rmse_m
    result = run_bag(cached_layout(bag, layout), POINT_TIME, progress=False)
    ate = evaluate(truth, result.trajectory()).ate_rmse_m
    assert abs(ate - plain) <= 0.02 * plain, (ate, plain)
    if layout in ('velodyne_organized', 'float64'):
        assert np.array_equal(result.trajectory().poses, plain_runs['point_time'].trajectory().poses)


# ----------------------------------------------------------------------------------------- the conversions


def test_time_units_are_read_from_the_span_of_a_sweep():
    sweep = np.linspace(0.0, 0.0999, 1000)
    for unit, scale, dtype in (
        ('s', 1.0, np.float32),
        ('ms', 1e3, np.float32),
        ('us', 1e6, np.float64),
        ('ns', 1e9, np.uint32),
        ('ns', 1e9, np.int64),
        ('ms', 1e3, np.uint16),
    ):
        values = (
            np.rint(sweep * scale).astype(dtype)
            if dtype not in (np.float32, np.float64)
            else (sweep * scale).astype(dtype)
        )
        seconds, reading = seconds_since_sweep_start(values, 'stamp', 0.1)
        assert reading.unit == unit and not reading.absolute, (unit, dtype)
        assert np.abs(seconds - sweep).max() < 1e-6 + 0.5 / scale
    # A 20 Hz sweep (50 ms) and a quarter sweep (an azimuth window) are still about a scan period.
    assert seconds_since_sweep_start(np.linspace(0, 0.05, 9).astype(np.float32), 'time', 0.1)[1].unit == 's'
    assert seconds_since_sweep_start(np.arange(0, 25_000_000, 97_656, dtype=np.uint32), 't', 0.1)[1].unit == 'ns'
    # Too short a span to tell (a few points, all at one instant): the type's usual unit.
    assert seconds_since_sweep_start(np.zeros(5, np.float32), 'time', 0.1)[1].unit == 's'
    assert seconds_since_sweep_start(np.array([7, 9], np.uint32), 't', 0.1)[1].unit == 'ns'


def test_absolute_times_count_from_the_sweeps_earliest_valid_point():
    stamp = 1_700_000_000.25
    sweep = np.linspace(0.0, 0.0999, 1000)
    seconds, reading = seconds_since_sweep_start(stamp + 0.002 + sweep, 'timestamp', 0.1)  # Hesai, RoboSense
    assert reading.absolute and reading.unit == 's' and np.abs(seconds - sweep).max() < 1e-6
    nanoseconds = (np.int64(1_700_000_000_250_000_000) + np.rint(sweep * 1e9).astype(np.int64)).astype(np.uint64)
    seconds, reading = seconds_since_sweep_start(nanoseconds, 'stamp_ns', 0.1)  # any absolute field, by its value
    assert reading.absolute and reading.unit == 'ns' and np.abs(seconds - sweep).max() < 1e-8
    # A relative field keeps its offset from the header stamp (Livox offset_time, Velodyne time).
    seconds, reading = seconds_since_sweep_start((np.rint((sweep + 0.01) * 1e9)).astype(np.uint32), 'offset_time', 0.1)
    assert not reading.absolute and abs(float(seconds.min()) - 0.01) < 1e-8
    # The earliest *valid* point: a NaN point's time is not looked at.
    cloud = np.zeros(4, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('timestamp', '<f8')])
    cloud['x'] = [np.nan, 5.0, 5.0, 5.0]
    cloud['y'] = [0.0, 1.0, 2.0, 3.0]
    cloud['timestamp'] = stamp + np.array([0.0, 0.01, 0.02, 0.06])
    read = read_cloud(cloud, 16, None, 'time', 0.1)
    assert read.dropped_non_finite == 1 and np.allclose(read.time, [0.0, 0.01, 0.05], atol=1e-6)


def test_the_configured_time_field_comes_first_and_an_empty_one_switches_times_off():
    cloud = np.zeros(3, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('time', '<f4'), ('t', '<u4')])
    cloud['x'] = 5.0
    cloud['time'] = [0.0, 0.05, 0.09]
    cloud['t'] = [0, 20_000_000, 30_000_000]
    assert np.allclose(read_cloud(cloud, 16, None, 'time', 0.1).time, [0.0, 0.05, 0.09])
    assert np.allclose(read_cloud(cloud, 16, None, 't', 0.1).time, [0.0, 0.02, 0.03])
    assert read_cloud(cloud, 16, None, '', 0.1).time is None
    assert read_cloud(cloud[['x', 'y', 'z', 't']], 16, None, 'time', 0.1).time_reading.field == 't'


def test_rings_counted_from_the_top_are_turned_round_and_others_are_not(sweeps):
    points = sweeps[0]
    xyz = np.stack([points[n] for n in 'xyz'], axis=1)
    ring = points['ring'].astype(np.int64)
    assert not rings_count_down(ring, xyz, 16) and rings_count_down(15 - ring, xyz, 16)
    # Within n_scan rows: a 16-beam cloud read into a 32-row image keeps its rows when counted upwards.
    assert not rings_count_down(ring, xyz, 32) and rings_count_down(31 - ring, xyz, 32)
    # Rings beyond the image are left out of the vote: the eight lowest beams in an 8-row image still tell.
    assert not rings_count_down(ring, xyz, 8) and rings_count_down(7 - ring, xyz, 8)
    # One ring only, or none in the image: nothing to tell.
    assert not rings_count_down(np.full(len(ring), 3), xyz, 16) and not rings_count_down(ring + 40, xyz, 16)
    flipped = points.copy()
    flipped['ring'] = 15 - points['ring']
    read = prepare_input(flipped, PARAMS)
    assert read.rings_from_top and np.array_equal(read.ring, points['ring'])
    # Rings beyond the image (a wrong preset) stay beyond it, to be dropped and warned about.
    flipped['ring'] = 23 - points['ring']  # 8..23 from the top
    read = prepare_input(flipped, PARAMS)
    assert read.rings_from_top and np.array_equal(np.sort(np.unique(read.ring)), np.r_[0:8, 16:24])


def test_float64_coordinates_and_an_xyz_only_cloud(sweeps):
    points = sweeps[1]
    doubled = in_layout(points, 'float64', STAMP_NS, ROWS, COLUMNS)
    assert doubled.dtype['x'] == np.float64
    assert np.array_equal(prepare_input(doubled, PARAMS).xyz, prepare_input(points, PARAMS).xyz)
    bare = in_layout(points, 'xyzi', STAMP_NS, ROWS, COLUMNS)
    assert bare.dtype == POINT_XYZI_DTYPE
    read = prepare_input(bare[['x', 'y', 'z']], PARAMS)
    assert read.ring is None and read.time is None and len(read.xyz) == len(points)


# ---------------------------------------------------------------------------------------------- refusals


def refusal(points: np.ndarray, params: Params = PARAMS) -> str:
    with pytest.raises(CloudLayoutError) as caught:
        prepare_input(points, params)
    message = str(caught.value)
    assert '\n' not in message
    return message


def test_layouts_that_cannot_be_read_are_refused_with_one_line_naming_the_field():
    xy = np.zeros(3, dtype=[('x', '<f4'), ('y', '<f4'), ('intensity', '<f4')])
    assert refusal(xy) == 'the cloud has no z field (fields: x, y, intensity): expected x, y and z coordinates'
    # A time field spanning 3 "s" (or 3 ms): neither is about a 0.1 s sweep.
    timed = velodyne_points(np.full((4, 3), 5.0), time=np.array([0.0, 1.0, 2.0, 3.0]))
    message = refusal(timed)
    assert message.startswith(
        "time field 'time' (float32) spans 3 within one cloud: expected about one scan "
        'period (sensor.scan_period 0.1 s) in s, ms, us or ns'
    ), message
    ouster = np.zeros(4, dtype=OUSTER_DTYPE)
    ouster['x'] = 5.0
    ouster['t'] = [0, 1_000_000_000, 2_000_000_000, 3_000_000_000]  # 3 s in ns
    assert "time field 't' (uint32) spans 3e+09" in refusal(ouster)
    # The same cloud is fine for a sensor configured to sweep in 1 s.
    assert read_cloud(ouster, 16, 'ring', 'time', 1.0).time_reading.unit == 'ns'
    two_times = np.zeros(2, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('time', '<f4', (2,))])
    assert refusal(two_times) == 'field(s) time hold several values per point (count > 1): expected one'


def test_the_pipeline_drops_a_refused_scan_counted_and_goes_on(sweeps):
    pipeline = Pipeline(PARAMS, mapping=False)
    try:
        pipeline.process_scan(sweeps[0], STAMP_NS)
        bad = sweeps[1].copy()
        bad['time'] *= 40.0  # 4 s: no unit makes it a 0.1 s sweep
        dropped = pipeline.process_scan(bad, STAMP_NS + 100_000_000)
        assert dropped.dropped is not None and "time field 'time'" in dropped.dropped
        at_origin = np.zeros(10, dtype=VELODYNE_POINT_DTYPE)
        assert 'no valid point' in pipeline.process_scan(at_origin, STAMP_NS + 200_000_000).dropped
        good = pipeline.process_scan(sweeps[2], STAMP_NS + 300_000_000)
        assert good.dropped is None and good.odometry is not None
        assert pipeline.record.counts['scans_dropped'] == 2 and pipeline.record.counts['scans_processed'] == 2
    finally:
        pipeline.close()
