"""The presets of the lidars users have (core.sensor_presets): consistent geometry, the makers' beam tables, the
OS1-128's against a real unit's metadata, and each one simulated and run through the offline pipeline."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lego_loam_py.core.params import SENSOR_PRESETS, Params
from lego_loam_py.core.params.beams import OS1_128_UNIT_ELEVATIONS, table_problem
from lego_loam_py.core.params.presets import MORE_SENSOR_PRESETS
from lego_loam_py.core.projection.range_image import RangeImageProjection, prepare_input
from lego_loam_py.sim.lidar import LidarModel

NEW = sorted(MORE_SENSOR_PRESETS)
OUSTER = 'real/ouster_os128_pcaps_with_imu'


@pytest.mark.parametrize('preset', NEW)
def test_each_preset_is_a_consistent_geometry(preset):
    s = Params().replace(sensor__preset=preset).sensor
    assert s.preset == preset and s.horizon_scan * s.ang_res_x == pytest.approx(360.0)
    beams = np.asarray(LidarModel.from_preset(preset).ring_elevations)  # the table, or the even rows
    assert len(beams) == s.n_scan and np.all(np.diff(beams) > 0)
    if s.beam_elevations:
        assert table_problem(s.beam_elevations, s.n_scan) is None
        assert np.array_equal(beams, s.beam_elevations)
    else:
        assert np.allclose(np.diff(beams), s.ang_res_y)
    # ang_bottom 0.1 deg below the lowest beam (the original's margin), ang_res_y the span evenly divided.
    assert s.ang_bottom == pytest.approx(0.1 - beams[0])
    assert s.ang_res_y == pytest.approx((beams[-1] - beams[0]) / (s.n_scan - 1))
    # Ground rows up to the highest beam at or below -1 deg, as the VLP-16's 7.
    assert beams[s.ground_scan_ind] <= -1.0 < beams[s.ground_scan_ind + 1]


def test_the_original_presets_are_unchanged_and_the_new_ones_added():
    assert list(SENSOR_PRESETS)[:6] == ['VLP-16', 'HDL-32E', 'VLS-128', 'HDL-64E', 'OS1-16', 'OS1-64']
    assert SENSOR_PRESETS['VLP-16'] == dict(
        n_scan=16, horizon_scan=1800, ang_res_x=0.2, ang_res_y=2.0, ang_bottom=15.0 + 0.1, ground_scan_ind=7
    )
    assert set(NEW) <= set(SENSOR_PRESETS) and len(NEW) == 17
    assert {
        'VLP-32C',
        'OS0-128',
        'OS1-32',
        'OS2-64',
        'Pandar64',
        'Pandar40P',
        'PandarXT-32',
        'RS-LiDAR-16',
        'RS-LiDAR-32',
        'RS-Helios-1615',
        'RS-Ruby-128',
    } <= set(NEW)


def _metadata_angles(path) -> np.ndarray:
    document = json.loads(path.read_text())
    angles = document.get('beam_altitude_angles') or document['beam_intrinsics']['beam_altitude_angles']
    return np.asarray(angles, dtype=np.float64)


def test_the_os1_128_preset_against_a_real_units_metadata_and_scans(shared_data):
    """The OS1-128 preset's table is the unit's beam_altitude_angles (lowest first). Its scans, decoded with their
    ring field, take their rows from it; without it, from the elevation: every point in its beam's row seen from
    the optical centre, which lies 36.18 mm above os_sensor's origin (lidar_to_sensor_transform): from that origin
    under 60 % (near points tilt by more than half the 0.34 deg between rows). Ouster's rows must come from the ring."""
    from lego_loam_py.inputs.pcap import PcapSource
    from lego_loam_py.inputs.source import Scan

    folder = shared_data / OUSTER
    metadata = folder / 'OS-1-128_v2.3.0_1024x10.json'
    assert np.array_equal(_metadata_angles(metadata)[::-1], OS1_128_UNIT_ELEVATIONS)
    source = PcapSource(folder / 'OS-1-128_v2.3.0_1024x10_lb_n3.pcap', metadata=metadata)
    try:
        points = next(item.points for item in source.items() if isinstance(item, Scan))
    finally:
        source.close()
    params = Params().replace(sensor__preset='OS1-128')
    with_ring = prepare_input(points, params)
    assert not with_ring.rings_from_top and np.array_equal(
        with_ring.ring, points['ring'][with_ring.source_index] if with_ring.source_index is not None else points['ring']
    )
    no_ring = params.replace(sensor__use_cloud_ring=False)
    data = prepare_input(points, no_ring)
    ring = points['ring'] if data.source_index is None else points['ring'][data.source_index]
    x, y, z = (np.ascontiguousarray(data.xyz[:, axis]) for axis in range(3))
    projection = RangeImageProjection(no_ring)
    from_centre, _ = projection.rows_and_columns(None, x, y, (z - np.float32(0.03618)).astype(np.float32))
    from_origin, _ = projection.rows_and_columns(None, x, y, z)
    assert np.mean(from_centre == ring) > 0.999
    assert np.mean(from_origin == ring) < 0.6
    # The even geometry of the same span (the preset without its table) misses most rows even from the centre.
    even = RangeImageProjection(no_ring.replace(sensor__beam_elevations=[]))
    assert np.mean(even.rows_and_columns(None, x, y, (z - np.float32(0.03618)).astype(np.float32))[0] == ring) < 0.5


@pytest.mark.parametrize('preset', NEW)
def test_each_preset_simulates_and_runs_offline(preset):
    """1 s of the simulated campus with the sensor: every scan processed, the trajectory within a few cm."""
    from lego_loam_py.evaluation import evaluate
    from lego_loam_py.inputs.sidecars import load_ground_truth
    from lego_loam_py.offline import run_bag
    from lego_loam_py.sim.simulator import cached_scenario

    bag = cached_scenario('campus', duration=1.0, preset=preset)
    result = run_bag(bag, Params().replace(sensor__preset=preset), progress=False)
    assert result.counts['scans_in'] == result.counts['scans_processed'] == 10
    metrics = evaluate(load_ground_truth(bag), result.trajectory())
    assert metrics.ate_rmse_m < 0.05, metrics
