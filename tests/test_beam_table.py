"""Per-beam elevation tables: the HDL-64E's nominal layout, rows from the nearest beam, Velodyne calibration files,
and a simulated HDL-64E whose points land on their true rings without a ring field."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from lego_loam_py.core.params import ParameterError, Params, load_params
from lego_loam_py.core.params.beams import HDL64E_NOMINAL_ELEVATIONS, BeamRows, read_velodyne_calibration
from lego_loam_py.core.projection.range_image import RangeImageProjection, prepare_input
from lego_loam_py.core.projection.segmentation import Segmentation


def test_the_hdl64e_table_is_two_blocks_of_32_lasers_from_plus_2_to_minus_24_33_degrees():
    table = np.array(HDL64E_NOMINAL_ELEVATIONS)
    spacing = np.diff(table)
    assert len(table) == 64 and table[0] == pytest.approx(-24.33) and table[-1] == pytest.approx(2.0)
    assert np.allclose(spacing[:31], 0.5) and np.allclose(spacing[32:], 1 / 3)  # lower block, upper block
    assert spacing[31] == pytest.approx(0.4967, abs=1e-4)  # -8.83 -> -8.333
    params = Params().replace(sensor__preset='HDL-64E')
    assert params.sensor.beam_elevations == HDL64E_NOMINAL_ELEVATIONS
    assert Params().sensor.beam_elevations == ()  # the VLP-16 default keeps the original's uniform rows


def test_each_point_goes_to_the_row_of_its_nearest_beam():
    rows = BeamRows(HDL64E_NOMINAL_ELEVATIONS)
    rng = np.random.default_rng(0)
    true_row = rng.integers(0, 64, 20000)
    table = np.array(HDL64E_NOMINAL_ELEVATIONS)
    gap_below = np.diff(table, prepend=table[0] - 0.5)[true_row]
    gap_above = np.diff(table, append=table[-1] + 1 / 3)[true_row]
    # Anywhere within 0.49 of the gap to the neighbouring beam, below or above.
    fraction = rng.uniform(0.0, 0.49, true_row.size)
    offset = np.where(rng.random(true_row.size) < 0.5, -fraction * gap_below, fraction * gap_above)
    elevation = np.radians(table[true_row] + offset)
    distance = rng.uniform(2, 80, true_row.size)
    row = rows.rows(distance * np.sin(elevation), distance * np.cos(elevation))
    assert np.array_equal(row, true_row)
    # Beyond half a spacing past the outermost beams: outside the image.
    outside = np.radians([-24.33 - 0.3, 2.0 + 0.2, 60.0, -60.0])
    assert np.array_equal(rows.rows(np.sin(outside), np.cos(outside)), [-1, -1, -1, -1])


def test_a_velodyne_calibration_file_gives_the_table_and_the_rows(tmp_path):
    # VLP-16 lasers in laser-id order (interleaved), as velodyne_pointcloud's VLP16db.yaml lists them.
    ids = [-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15]
    calibration = {
        'lasers': [
            {'laser_id': i, 'vert_correction': math.radians(v), 'rot_correction': 0.0} for i, v in enumerate(ids)
        ],
        'num_lasers': 16,
        'distance_resolution': 0.002,
    }
    path = tmp_path / 'VLP16db.yaml'
    path.write_text(yaml.safe_dump(calibration))
    assert read_velodyne_calibration(path) == pytest.approx(tuple(range(-15, 16, 2)))
    params = load_params(overrides={'sensor.beam_calibration': str(path)})
    assert params.sensor.n_scan == 16 and params.sensor.beam_elevations == pytest.approx(tuple(range(-15, 16, 2)))
    # The same rows as the uniform VLP-16 image for points on the beams.
    elevation = np.radians(np.repeat(np.arange(-15, 16, 2), 50)).astype(np.float32)
    azimuth = np.tile(np.linspace(-3, 3, 50), 16).astype(np.float32)
    xyz = np.stack(
        [10 * np.cos(elevation) * np.cos(azimuth), 10 * np.cos(elevation) * np.sin(azimuth), 10 * np.sin(elevation)],
        axis=1,
    ).astype(np.float32)
    rows_table = RangeImageProjection(params).rows_and_columns(None, *xyz.T.copy())[0]
    rows_uniform = RangeImageProjection(Params()).rows_and_columns(None, *xyz.T.copy())[0]
    assert np.array_equal(rows_table, rows_uniform) and np.array_equal(rows_table, np.repeat(np.arange(16), 50))


def test_calibration_and_table_errors_name_the_file_and_the_problem(tmp_path):
    with pytest.raises(ParameterError, match='beam_calibration.*missing.yaml'):
        load_params(overrides={'sensor.beam_calibration': str(tmp_path / 'missing.yaml')})
    bad = tmp_path / 'bad.yaml'
    bad.write_text(yaml.safe_dump({'lasers': [{'laser_id': 0}], 'num_lasers': 1}))
    with pytest.raises(ParameterError, match='bad.yaml.*vert_correction'):
        load_params(overrides={'sensor.beam_calibration': str(bad)})
    with pytest.raises(ParameterError, match='lists 3 beams but the range image has 16 rows'):
        load_params(overrides={'sensor.beam_elevations': [-1.0, 0.0, 1.0]})
    with pytest.raises(ParameterError, match='lowest to the highest'):
        load_params(overrides={'sensor.beam_elevations': list(range(15, -17, -2))})
    # An empty table is the uniform image, even for a preset that has one.
    assert (
        load_params(overrides={'sensor.preset': 'HDL-64E', 'sensor.beam_elevations': []}).sensor.beam_elevations == ()
    )


def test_the_segmentation_uses_each_pair_of_rows_own_angle():
    uneven = Segmentation(Params().replace(sensor__preset='HDL-64E'))
    spacing = np.radians(np.diff(HDL64E_NOMINAL_ELEVATIONS))
    # One angle per pair of rows, as a column broadcast along the image's columns.
    assert uneven._sin_alpha[1].shape == (63, 1)
    assert np.allclose(uneven._sin_alpha[1][:, 0], np.sin(spacing), rtol=1e-6)
    uniform = Segmentation(Params().replace(sensor__preset='HDL-64E', sensor__beam_elevations=[]))
    assert np.ndim(uniform._sin_alpha[1]) == 0


@pytest.fixture(scope='module')
def hdl64e_recording(tmp_path_factory):
    """0.3 s of the campus seen by a simulated HDL-64E with its nominal beam table (ring = true laser)."""
    from lego_loam_py.sim.simulator import SimConfig, simulate

    return simulate(SimConfig('campus', duration=0.3, preset='HDL-64E'), tmp_path_factory.mktemp('hdl') / 'bag')


def _row_match(bag, params) -> float:
    from lego_loam_py.bag.io import BagReader, cloud_msg_to_array

    matched = total = 0
    with BagReader(bag) as reader:
        for message in reader.messages(topics=['/velodyne_points']):
            points = cloud_msg_to_array(reader.deserialize(message))
            data = prepare_input(points, params)
            assert data.ring is None and data.source_index is None  # rows from the elevation, every point valid
            xyz = [np.ascontiguousarray(data.xyz[:, axis]) for axis in range(3)]
            row, _ = RangeImageProjection(params).rows_and_columns(None, *xyz)
            matched += int(np.count_nonzero(row == points['ring'].astype(np.int64)))
            total += len(row)
    return matched / total


def test_rows_from_the_hdl64e_table_match_the_simulated_true_rings(hdl64e_recording):
    """The acceptance check: at least 99 % of the points of a simulated HDL-64E without a ring field land in the
    row of their laser with the preset's table; the uniform rows of the original's HDL-64E values do not."""
    bag = hdl64e_recording.bag_path
    table = Params().replace(sensor__preset='HDL-64E', sensor__use_cloud_ring=False)
    uniform = table.replace(sensor__beam_elevations=[])
    assert _row_match(bag, table) >= 0.99
    assert _row_match(bag, uniform) < 0.5  # (7 % on this recording: the uniform rows are shifted and compressed)


def test_simulated_hdl64e_recordings_name_their_beams_and_other_recordings_keep_their_cache_keys():
    from lego_loam_py.sim.simulator import SimConfig

    vlp = SimConfig('campus', duration=8.0).to_dict()
    assert 'beams' not in vlp and 'uniform_beams' not in vlp  # (so VLP-16 recordings keep their cache entries)
    table, uniform = SimConfig('campus', preset='HDL-64E'), SimConfig('campus', preset='HDL-64E', uniform_beams=True)
    assert table.to_dict()['beams'] == 'table' and uniform.to_dict()['beams'] == 'uniform'
    assert table.cache_key() != uniform.cache_key()
    assert '--uniform-beams' in uniform.command('out') and '--uniform-beams' not in table.command('out')
