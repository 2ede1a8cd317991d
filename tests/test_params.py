"""Parameters: defaults equal the original and config/params.yaml, presets, clear errors, ROS declaration."""

from __future__ import annotations

import dataclasses
import math
import textwrap

import pytest

from lego_loam_py.core.params import (
    SENSOR_PRESETS,
    ParameterError,
    Params,
    default_params_file,
    load_params,
    params_from_mapping,
    read_params_file,
)


def write(tmp_path, text: str):
    path = tmp_path / 'params.yaml'
    path.write_text(textwrap.dedent(text))
    return path


def test_defaults_are_the_originals_vlp16_values():
    p = Params()
    s = p.sensor
    assert (s.n_scan, s.horizon_scan, s.ang_res_x, s.ang_res_y, s.ground_scan_ind) == (16, 1800, 0.2, 2.0, 7)
    assert s.ang_bottom == pytest.approx(15.1)
    assert s.sensor_minimum_range == 1.0 and s.scan_period == 0.1 and s.use_cloud_ring
    assert s.point_cloud_topic == '/velodyne_points' and s.imu_topic == '/imu/data'
    assert s.segment_alpha_x == pytest.approx(0.2 / 180 * math.pi)
    assert s.segment_alpha_y == pytest.approx(2.0 / 180 * math.pi)
    ip = p.image_projection
    assert ip.segment_theta == pytest.approx(60 / 180 * math.pi)
    assert (ip.segment_valid_point_num, ip.segment_valid_line_num, ip.segment_min_cluster_size) == (5, 3, 30)
    assert ip.ground_slope_threshold == 10.0
    fa = p.feature_association
    assert (fa.edge_threshold, fa.surf_threshold, fa.nearest_feature_search_sq_dist) == (0.1, 0.1, 25.0)
    assert (fa.edge_feature_num, fa.less_edge_feature_num, fa.surf_feature_num, fa.sections_total) == (2, 20, 4, 6)
    assert (fa.max_iterations, fa.degeneracy_threshold, fa.skip_frame_num) == (25, 10.0, 1)
    mo = p.map_optimization
    assert mo.mapping_process_interval == 0.3 and mo.surrounding_keyframe_search_radius == 50.0
    assert (mo.corner_leaf_size, mo.surf_leaf_size, mo.keyframe_distance) == (0.2, 0.4, 0.3)
    assert mo.prior_noise_variances == (1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-6)
    lc = p.loop_closure
    assert lc.loop_closure_enable_flag and lc.method == 'verified'  # a deliberate deviation: the original has it off
    assert (lc.history_keyframe_search_radius, lc.history_keyframe_search_num, lc.history_keyframe_fitness_score) == (
        7.0,
        25,
        0.3,
    )


def test_deliberate_deviations_and_the_file_that_restores_the_original():
    """The defaults differ from the C++ on purpose in a few documented places; config/original.yaml puts
    every one of them back."""
    default = Params()
    assert (
        default.image_projection.ground_rule,
        default.feature_association.relative_time_source,
        default.feature_association.odometry_model,
        default.feature_association.step_scale,
    ) == ('refined', 'azimuth', 'sweep_start', 1.0)
    assert default.feature_association.imu_rotation_prior > 0
    assert default.map_optimization.degeneracy_threshold == 10.0
    original = load_params(default_params_file().parent / 'original.yaml')
    assert (
        original.image_projection.ground_rule,
        original.feature_association.relative_time_source,
        original.feature_association.odometry_model,
        original.feature_association.step_scale,
        original.feature_association.imu_rotation_prior,
    ) == ('original', 'original', 'original', 0.05, 0.0)
    assert original.map_optimization.degeneracy_threshold == 100.0
    assert (default.loop_closure.method, original.loop_closure.method) == ('verified', 'original')
    assert default.loop_closure.loop_closure_enable_flag and not original.loop_closure.loop_closure_enable_flag
    assert default.imu.alignment_check and not original.imu.alignment_check


def test_config_file_equals_the_defaults():
    assert load_params(default_params_file()) == Params()


def test_every_parameter_is_in_the_config_file():
    """config/params.yaml documents every parameter (the preset geometry as comments)."""
    text = default_params_file().read_text()
    for name in Params().to_flat():
        assert f' {name.split(".", 1)[1]}:' in text, name


@pytest.mark.parametrize('preset', sorted(SENSOR_PRESETS))
def test_presets_set_the_geometry(preset):
    p = load_params(overrides={'sensor.preset': preset})
    for key, value in SENSOR_PRESETS[preset].items():
        assert getattr(p.sensor, key) == value
    assert p.sensor.ground_scan_ind < p.sensor.n_scan


def test_preset_values_from_the_reference():
    hdl32 = load_params(overrides={'sensor': {'preset': 'HDL-32E'}}).sensor
    assert (hdl32.n_scan, hdl32.horizon_scan, hdl32.ground_scan_ind) == (32, 1800, 20)
    assert hdl32.ang_res_y == pytest.approx(41.33 / 31) and hdl32.ang_bottom == pytest.approx(30.67)
    os64 = load_params(overrides={'sensor': {'preset': 'OS1-64'}}).sensor
    assert (os64.n_scan, os64.horizon_scan, os64.ground_scan_ind) == (64, 1024, 15)
    assert os64.ang_res_x == pytest.approx(360 / 1024)


def test_explicit_geometry_overrides_the_preset(tmp_path):
    path = write(
        tmp_path,
        """
        /**:
          ros__parameters:
            sensor:
              preset: HDL-32E
              ground_scan_ind: 12
    """,
    )
    p = load_params(path)
    assert p.sensor.n_scan == 32 and p.sensor.ground_scan_ind == 12


def test_node_specific_section_applies_on_top(tmp_path):
    path = write(
        tmp_path,
        """
        /**:
          ros__parameters:
            sensor: {sensor_minimum_range: 2.0}
        imageProjection:
          ros__parameters:
            sensor: {sensor_minimum_range: 3.0}
        mapOptimization:
          ros__parameters:
            sensor: {sensor_minimum_range: 4.0}
    """,
    )
    assert load_params(path, node_name='imageProjection').sensor.sensor_minimum_range == 3.0
    assert load_params(path, node_name='/featureAssociation').sensor.sensor_minimum_range == 2.0


def test_every_mode_switch_is_typed_with_its_choices():
    """A parameter that picks a behaviour by name is a Literal of its names, not a bare string: the loader
    checks it, and the defaults are among the names."""
    import typing

    from lego_loam_py.core.params import types as param_types

    modes = {}
    for section in dataclasses.fields(Params):
        hints = typing.get_type_hints(section.default_factory)
        for name, hint in hints.items():
            if typing.get_origin(hint) is typing.Literal:
                modes[f'{section.name}.{name}'] = typing.get_args(hint)
                assert getattr(getattr(Params(), section.name), name) in typing.get_args(hint)
    assert modes == {
        'image_projection.ground_rule': typing.get_args(param_types.GroundRule),
        'feature_association.relative_time_source': ('azimuth', 'point_time', 'original'),
        'feature_association.odometry_model': ('sweep_start', 'original'),
        'feature_association.imu_attitude': ('gyro', 'orientation'),
        'map_optimization.keypose_pick': ('averaged_index', 'latest'),
        'map_optimization.mode': ('mapping', 'localization'),
        'loop_closure.method': ('verified', 'original'),
        'loop_closure.robust_kernel': ('huber', 'cauchy', 'none'),
        'frames.lidar_mount': ('parameters', 'tf_static'),
    }


def test_int_accepted_for_float():
    assert load_params(overrides={'sensor.sensor_minimum_range': 2}).sensor.sensor_minimum_range == 2.0


@pytest.mark.parametrize(
    'key,value,fragment',
    [
        ('sensor.n_scann', 16, "unknown parameter 'sensor.n_scann' (did you mean 'sensor.n_scan'?)"),
        ('sensors.n_scan', 16, "unknown parameter 'sensors.n_scan'"),
        ('sensor.n_scan', 16.0, "'sensor.n_scan' must be an integer"),
        ('sensor.n_scan', True, "'sensor.n_scan' must be an integer"),
        ('sensor.use_cloud_ring', 1, "'sensor.use_cloud_ring' must be a boolean"),
        ('sensor.ang_res_x', 'fast', "'sensor.ang_res_x' must be a number"),
        ('sensor.ang_res_x', float('nan'), "'sensor.ang_res_x' must be a finite number"),
        ('sensor.point_cloud_topic', 5, "'sensor.point_cloud_topic' must be a string"),
        ('sensor.preset', 'VLP-17', "'sensor.preset' must be one of"),
        ('sensor.ground_scan_ind', 40, "'sensor.ground_scan_ind' must lie in 1..n_scan-1"),
        ('map_optimization.prior_noise_variances', [1, 2], "'map_optimization.prior_noise_variances' must be 6"),
        ('map_optimization.prior_noise_variances', 3.0, "'map_optimization.prior_noise_variances' must be a list"),
        ('image_projection.segment_theta', 60.0, "'image_projection.segment_theta' must lie in (0, pi) radians"),
        (
            'feature_association.odometry_model',
            'sweepstart',
            "'feature_association.odometry_model' must be 'sweep_start' or 'original', got 'sweepstart'",
        ),
        (
            'feature_association.relative_time_source',
            'time',
            "'feature_association.relative_time_source' must be 'azimuth', 'point_time' or 'original'",
        ),
        ('image_projection.ground_rule', 1, "'image_projection.ground_rule' must be 'refined' or 'original', got 1"),
        (
            'map_optimization.keypose_pick',
            'first',
            "'map_optimization.keypose_pick' must be 'averaged_index' or 'latest'",
        ),
        ('map_optimization.mode', 'localisation', "'map_optimization.mode' must be 'mapping' or 'localization'"),
        ('localization.initial_pose', [1.0, 2.0], "'localization.initial_pose' must be [] (none), [x, y, yaw] or"),
        ('localization.min_overlap', 1.5, "'localization.min_overlap' must be within 0..1"),
    ],
)
def test_errors_name_the_key(key, value, fragment):
    with pytest.raises(ParameterError) as info:
        load_params(overrides={key: value})
    assert fragment in str(info.value)


def test_localization_needs_a_map_path():
    with pytest.raises(ParameterError, match="'map_optimization.map_path' must name the directory of a map bundle"):
        load_params(overrides={'map_optimization.mode': 'localization'})
    p = load_params(
        overrides={
            'map_optimization.mode': 'localization',
            'map_optimization.map_path': '/maps/site',
            'localization.initial_pose': [1, 2, 90],
        }
    )
    assert p.localization.initial_pose == (1.0, 2.0, 90.0) and Params().localization.initial_pose == ()


def test_file_errors_name_the_file_and_key(tmp_path):
    path = write(
        tmp_path,
        """
        /**:
          ros__parameters:
            feature_association:
              edge_treshold: 0.2
    """,
    )
    with pytest.raises(ParameterError) as info:
        load_params(path)
    message = str(info.value)
    assert str(path) in message and "'feature_association.edge_treshold'" in message
    assert "did you mean 'feature_association.edge_threshold'" in message


def test_malformed_files(tmp_path):
    with pytest.raises(ParameterError, match='not valid YAML'):
        load_params(write(tmp_path, '/**: [unclosed'))
    with pytest.raises(ParameterError, match="has no 'ros__parameters'"):
        load_params(write(tmp_path, '/**:\n  sensor: {}\n'))
    with pytest.raises(ParameterError, match='cannot read parameter file'):
        load_params(tmp_path / 'missing.yaml')
    assert read_params_file(write(tmp_path, '')) == {}


def test_flat_round_trip_and_replace():
    p = Params()
    assert params_from_mapping(p.to_flat()) == p
    q = p.replace(sensor__sensor_minimum_range=0.5, map_optimization__keyframe_distance=1.0)
    assert q.sensor.sensor_minimum_range == 0.5 and q.map_optimization.keyframe_distance == 1.0
    assert q.sensor.n_scan == 16
    r = p.replace(sensor__preset='OS1-16')
    assert r.sensor.horizon_scan == 1024  # a new preset brings its geometry
    with pytest.raises(ParameterError):
        p.replace(sensor__n_scan=-1)


def test_ros_node_declares_every_parameter_from_a_params_file(tmp_path, ros_domain):
    """rclpy parses --params-file; declare_params validates and declares the full typed set."""
    import rclpy
    from rclpy.context import Context

    from lego_loam_py.ros.params import declare_params

    path = write(
        tmp_path,
        """
        /**:
          ros__parameters:
            sensor: {preset: OS1-64, sensor_minimum_range: 0.5}
            map_optimization: {prior_noise_variances: [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]}
    """,
    )
    context = Context()
    rclpy.init(
        args=['x', '--ros-args', '--params-file', str(path), '-p', 'loop_closure.time_gap:=12.5'],
        context=context,
        domain_id=ros_domain,
    )
    try:
        node = rclpy.create_node(
            'imageProjection', context=context, automatically_declare_parameters_from_overrides=True
        )
        params = declare_params(node)
        assert params.sensor.n_scan == 64 and params.sensor.sensor_minimum_range == 0.5
        assert params.loop_closure.time_gap == 12.5
        assert params.map_optimization.prior_noise_variances == (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
        assert node.get_parameter('sensor.n_scan').value == 64
        assert node.get_parameter('feature_association.edge_threshold').value == 0.1
        for name in Params().to_flat():
            assert node.has_parameter(name), name
        node.destroy_node()

        bad = rclpy.create_node(
            'bad',
            context=context,
            automatically_declare_parameters_from_overrides=True,
            parameter_overrides=[rclpy.parameter.Parameter('sensor.n_scans', value=3)],
        )
        with pytest.raises(ParameterError, match="unknown parameter 'sensor.n_scans'"):
            declare_params(bad)
        bad.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_a_written_params_file_is_read_back_and_loaded(tmp_path):
    """write_params_file (the benchmarks' and the node tests' parameter files) writes what read_params_file and
    the nodes read: sections, a top-level ROS parameter, a path as a string."""
    from pathlib import Path

    from lego_loam_py.core.params import write_params_file

    path = write_params_file(
        tmp_path / 'p.yaml',
        {
            'sensor.n_scan': 32,
            'map_optimization.file_directory': Path('/m'),
            'use_sim_time': True,
            'image_projection.ground_rule': 'original',
        },
    )
    assert read_params_file(path) == {
        'sensor.n_scan': 32,
        'map_optimization.file_directory': '/m',
        'use_sim_time': True,
        'image_projection.ground_rule': 'original',
    }
    values = read_params_file(path)
    del values['use_sim_time']
    loaded = load_params(overrides=values)
    assert (loaded.sensor.n_scan, loaded.image_projection.ground_rule) == (32, 'original')
