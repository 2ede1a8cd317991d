"""Params from a mapping of parameter names: type checks, the sensor preset, range and choice checks.

Names are dotted (``'image_projection.segment_theta'``) or nested mappings. A sensor preset fills the geometry
fields of ``sensor``; any of those fields given explicitly overrides the preset. Unknown keys and values of the
wrong type or out of range raise :class:`~lego_loam_py.core.params.types.ParameterError` naming the key.
"""

from __future__ import annotations

import difflib
import functools
import math
import typing
from collections.abc import Mapping, Sequence
from dataclasses import fields
from typing import Any

from lego_loam_py.core.params.types import SENSOR_PRESETS, ParameterError, Params, SensorParams

__all__ = ['params_from_mapping', 'flatten']


def _sections() -> dict[str, type]:
    return {f.name: f.default_factory for f in fields(Params)}  # type: ignore[misc]


@functools.cache  # (get_type_hints evaluates every annotation string again: 0.5 ms a call, two calls a key)
def _field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in fields(cls)}


_VALID_KEYS: list[str] = [f'{s}.{n}' for s, cls in _sections().items() for n in _field_types(cls)]


def flatten(tree: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """Nested mapping -> ``{'a.b.c': value}`` (ROS 2 turns nested YAML into dotted names the same way)."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if not isinstance(key, str):
            raise ParameterError(f'parameter name {key!r} under {prefix or "the root"!r} is not a string')
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            out.update(flatten(value, name + '.'))
        else:
            out[name] = value
    return out


def _coerce(key: str, value: Any, annotation: Any) -> Any:
    """Check ``value`` against the field type; ints are accepted for floats, nothing else is converted."""

    def wrong(expected: str) -> ParameterError:
        return ParameterError(f"parameter '{key}' must be {expected}, got {value!r} ({type(value).__name__})")

    if annotation is bool:
        if not isinstance(value, bool):
            raise wrong('a boolean')
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise wrong('an integer')
        return value
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise wrong('a number')
        value = float(value)
        if not math.isfinite(value):
            raise wrong('a finite number')
        return value
    if annotation is str:
        if not isinstance(value, str):
            raise wrong('a string')
        return value
    if typing.get_origin(annotation) is typing.Literal:  # a mode switch: one of its names
        choices = typing.get_args(annotation)
        if value not in choices:
            quoted = [repr(c) for c in choices]
            raise wrong(f'{", ".join(quoted[:-1])} or {quoted[-1]}')
        return value
    if typing.get_origin(annotation) is tuple:
        if not isinstance(value, Sequence) or isinstance(value, str):
            raise wrong('a list of numbers')
        return tuple(_coerce(f'{key}[{i}]', v, float) for i, v in enumerate(value))
    raise TypeError(f'unsupported parameter type {annotation!r} for {key}')  # programming error


def _unknown_key_error(key: str) -> ParameterError:
    close = difflib.get_close_matches(key, _VALID_KEYS, n=1, cutoff=0.6)
    hint = f" (did you mean '{close[0]}'?)" if close else ''
    return ParameterError(f"unknown parameter '{key}'{hint}")


def params_from_mapping(values: Mapping[str, Any], apply_preset: bool = True) -> Params:
    """Build :class:`Params` from flat dotted names or a nested mapping, on top of the defaults.

    With ``apply_preset`` the geometry of ``sensor.preset`` is applied first and explicit ``sensor.*``
    geometry keys override it.
    """
    flat = flatten(values)
    sections = _sections()
    grouped: dict[str, dict[str, Any]] = {name: {} for name in sections}
    for key, value in flat.items():
        section, _, name = key.partition('.')
        if section not in sections or name not in _field_types(sections[section]):
            raise _unknown_key_error(key)
        grouped[section][name] = _coerce(key, value, _field_types(sections[section])[name])

    sensor_values = grouped['sensor']
    if sensor_values.get('beam_calibration'):  # (before the preset: the file's beams override the preset's)
        sensor_values = _with_calibrated_beams(sensor_values)
    if apply_preset:
        preset = sensor_values.get('preset', SensorParams.preset)
        if preset not in SENSOR_PRESETS:
            raise ParameterError(f"parameter 'sensor.preset' must be one of {sorted(SENSOR_PRESETS)}, got {preset!r}")
        sensor_values = {**SENSOR_PRESETS[preset], **sensor_values}
    built = {name: cls(**grouped[name]) for name, cls in sections.items() if name != 'sensor'}
    params = Params(sensor=SensorParams(**sensor_values), **built)
    _validate(params)
    return params


def _with_calibrated_beams(sensor_values: dict[str, Any]) -> dict[str, Any]:
    """The sensor values with ``beam_elevations`` read from the calibration file ``beam_calibration`` (and
    ``n_scan`` from its number of lasers unless given explicitly)."""
    from lego_loam_py.core.params.beams import read_velodyne_calibration

    try:
        table = read_velodyne_calibration(sensor_values['beam_calibration'])
    except ValueError as exc:
        raise ParameterError(f"parameter 'sensor.beam_calibration': {exc}") from None
    return {**sensor_values, 'beam_elevations': table, 'n_scan': sensor_values.get('n_scan', len(table))}


def _validate(p: Params) -> None:
    def need(condition: bool, key: str, message: str) -> None:
        if not condition:
            raise ParameterError(f"parameter '{key}' {message}")

    s = p.sensor
    need(s.preset in SENSOR_PRESETS, 'sensor.preset', f'must be one of {sorted(SENSOR_PRESETS)}')
    need(s.n_scan > 0, 'sensor.n_scan', 'must be positive')
    need(s.horizon_scan > 0, 'sensor.horizon_scan', 'must be positive')
    need(s.ang_res_x > 0, 'sensor.ang_res_x', 'must be positive')
    need(s.ang_res_y > 0, 'sensor.ang_res_y', 'must be positive')
    need(0 < s.ground_scan_ind < s.n_scan, 'sensor.ground_scan_ind', 'must lie in 1..n_scan-1')
    if s.beam_elevations:
        from lego_loam_py.core.params.beams import table_problem

        problem = table_problem(s.beam_elevations, s.n_scan)
        need(
            problem is None,
            'sensor.beam_calibration' if s.beam_calibration else 'sensor.beam_elevations',
            f'{problem}' + (f' ({s.beam_calibration})' if s.beam_calibration else ''),
        )
    need(s.scan_period > 0, 'sensor.scan_period', 'must be positive')
    need(0.0 <= s.stamp_position <= 1.0, 'sensor.stamp_position', 'must be within 0..1 (a fraction of the sweep)')
    need(s.sensor_minimum_range >= 0, 'sensor.sensor_minimum_range', 'must not be negative')
    need(abs(s.elevation_offset) <= 5.0, 'sensor.elevation_offset', 'must be within 5 degrees')
    need(s.point_cloud_topic != '', 'sensor.point_cloud_topic', 'must not be empty')
    ip = p.image_projection
    need(0 < ip.segment_theta < math.pi, 'image_projection.segment_theta', 'must lie in (0, pi) radians')
    need(0 <= ip.ground_chain_slope < 90, 'image_projection.ground_chain_slope', 'must lie in [0, 90) degrees')
    for key in ('ground_plane_radius', 'ground_chain_tolerance', 'ground_plane_tolerance'):
        need(getattr(ip, key) >= 0, f'image_projection.{key}', 'must not be negative')
    need(ip.outlier_column_stride > 0, 'image_projection.outlier_column_stride', 'must be positive')
    need(ip.ground_column_stride > 0, 'image_projection.ground_column_stride', 'must be positive')
    fa = p.feature_association
    need(fa.sections_total > 0, 'feature_association.sections_total', 'must be positive')
    need(fa.skip_frame_num >= 0, 'feature_association.skip_frame_num', 'must not be negative')
    need(fa.less_flat_leaf_size > 0, 'feature_association.less_flat_leaf_size', 'must be positive')
    need(fa.imu_que_length > 0, 'feature_association.imu_que_length', 'must be positive')
    need(fa.reassociate_every > 0, 'feature_association.reassociate_every', 'must be positive')
    need(0.0 <= fa.lost_match_ratio <= 1.0, 'feature_association.lost_match_ratio', 'must be within 0..1')
    need(fa.covariance_scale > 0, 'feature_association.covariance_scale', 'must be positive')
    for name in ('covariance_turn', 'covariance_change', 'covariance_stamp_jitter'):
        need(getattr(fa, name) >= 0, f'feature_association.{name}', 'must not be negative')
    mo = p.map_optimization
    need(mo.covariance_scale > 0, 'map_optimization.covariance_scale', 'must be positive')
    need(mo.covariance_deskew >= 0, 'map_optimization.covariance_deskew', 'must not be negative')
    for name in (
        'corner_leaf_size',
        'surf_leaf_size',
        'outlier_leaf_size',
        'surrounding_keypose_leaf_size',
        'global_map_keypose_leaf_size',
        'global_map_leaf_size',
        'global_map_publish_period',
    ):
        need(getattr(mo, name) > 0, f'map_optimization.{name}', 'must be positive')
    for name in ('prior_noise_variances', 'odometry_noise_variances'):
        value = getattr(mo, name)
        need(
            len(value) == 6 and all(v > 0 for v in value),
            f'map_optimization.{name}',
            'must be 6 positive variances (roll, pitch, yaw, x, y, z)',
        )
    need(mo.knn >= 3, 'map_optimization.knn', 'must be at least 3')
    need(0 <= mo.plane_min_aspect <= 1, 'map_optimization.plane_min_aspect', 'must be within 0..1 (0: any)')
    r = p.reliability
    need(r.max_points_per_pixel >= 1, 'reliability.max_points_per_pixel', 'must be at least 1')
    need(r.reset_after_failures >= 1, 'reliability.reset_after_failures', 'must be at least 1')
    need(r.watchdog_inputs >= 0, 'reliability.watchdog_inputs', 'must not be negative (0: off)')
    imu = p.imu
    for name in ('rotation_rpy', 'translation', 'orientation_rpy'):
        need(
            len(getattr(imu, name)) == 3,
            f'imu.{name}',
            'must have 3 values' + (' (x, y, z)' if name == 'translation' else ' (roll, pitch, yaw)'),
        )
    need(all(abs(v) <= 10.0 for v in imu.translation), 'imu.translation', 'must be within 10 m of the lidar')
    need(abs(imu.time_offset) <= 1.0, 'imu.time_offset', 'must be within 1 s')
    need(imu.alignment_window >= 1.0, 'imu.alignment_window', 'must be at least 1 s')
    need(imu.alignment_max_rotation > 0, 'imu.alignment_max_rotation', 'must be positive')
    need(imu.alignment_max_offset > 0, 'imu.alignment_max_offset', 'must be positive')
    fr = p.frames
    names = {'map_frame': fr.map_frame, 'odom_frame': fr.odom_frame, 'base_frame': fr.base_frame}
    names['lidar_frame'] = fr.lidar_frame
    for key, name in names.items():
        need(bool(name) and not name.startswith('/') and ' ' not in name, f'frames.{key}', 'must be a tf2 frame id')
    need(len(set(names.values())) == len(names), 'frames', 'map, odom, base and lidar frames must differ')
    need(len(fr.lidar_translation) == 3, 'frames.lidar_translation', 'must have 3 values (x, y, z)')
    need(len(fr.lidar_rotation_rpy) == 3, 'frames.lidar_rotation_rpy', 'must have 3 values (roll, pitch, yaw)')
    for key in ('odometry_topic', 'pose_topic'):
        need(getattr(fr, key) != '', f'frames.{key}', 'must not be empty')
    lc = p.loop_closure
    need(lc.period > 0, 'loop_closure.period', 'must be positive')
    need(lc.history_keyframe_leaf_size > 0, 'loop_closure.history_keyframe_leaf_size', 'must be positive')
    for name in ('scan_context_rings', 'scan_context_sectors', 'registration_iterations', 'min_consistent_loops'):
        need(getattr(lc, name) >= 1, f'loop_closure.{name}', 'must be at least 1')
    for name in (
        'scan_context_max_radius',
        'inlier_distance',
        'max_rmse',
        'registration_points',
        'min_registration_sigma',
        'robust_kernel_width',
        'max_source_shift',
        'max_source_shift_deg',
    ):
        need(getattr(lc, name) > 0, f'loop_closure.{name}', 'must be positive')
    need(
        len(lc.registration_distances) >= 1 and all(d > 0 for d in lc.registration_distances),
        'loop_closure.registration_distances',
        'must be one or more positive distances [m]',
    )
    need(0.0 <= lc.min_overlap <= 1.0, 'loop_closure.min_overlap', 'must be within 0..1')
    need(lc.source_keyframes >= 0, 'loop_closure.source_keyframes', 'must not be negative')
    need(lc.target_keyframes >= 0, 'loop_closure.target_keyframes', 'must not be negative')
    need(lc.skip_first_keyframes >= 0, 'loop_closure.skip_first_keyframes', 'must not be negative')
    need(
        mo.mode != 'localization' or mo.map_path.strip() != '',
        'map_optimization.map_path',
        'must name the directory of a map bundle in mode localization',
    )
    lo = p.localization
    need(
        len(lo.initial_pose) in (0, 3, 6),
        'localization.initial_pose',
        'must be [] (none), [x, y, yaw] or [x, y, z, roll, pitch, yaw] (metres, degrees)',
    )
    for name in (
        'initial_pose_radius',
        'max_rmse',
        'ambiguity_distance',
        'tracking_inlier_distance',
        'max_correction',
        'max_correction_rotation',
        'max_gap',
        'max_correction_age',
    ):
        need(getattr(lo, name) > 0, f'localization.{name}', 'must be positive')
    for name in ('relocalization_threshold', 'min_overlap', 'min_edge_overlap', 'min_tracking_overlap'):
        need(0.0 <= getattr(lo, name) <= 1.0, f'localization.{name}', 'must be within 0..1')
    for name in ('relocalization_candidates', 'lost_after_steps'):
        need(getattr(lo, name) >= 1, f'localization.{name}', 'must be at least 1')
    need(lo.confirm_steps >= 0, 'localization.confirm_steps', 'must not be negative')
    og = p.occupancy_grid
    for name in (
        'resolution',
        'max_range',
        'publish_period',
        'angular_resolution_deg',
        'hit_log_odds',
        'ground_cell',
        'ground_plane_radius',
        'see_under_deg',
        'max_cells',
    ):
        need(getattr(og, name) > 0, f'occupancy_grid.{name}', 'must be positive')
    need(0 <= og.min_height < og.max_height, 'occupancy_grid.min_height', 'must lie in 0..max_height [m]')
    need(0 <= og.min_range < og.max_range, 'occupancy_grid.min_range', 'must lie in 0..max_range [m]')
    need(
        og.max_range <= 4000 * og.resolution,
        'occupancy_grid.max_range',
        f'must be at most 4000 cells ({4000 * og.resolution:g} m at resolution {og.resolution:g} m)',
    )
    need(0 <= og.ground_tolerance <= og.min_height, 'occupancy_grid.ground_tolerance', 'must lie in 0..min_height [m]')
    for name in (
        'obstacle_margin',
        'ground_max_slope',
        'ground_search_radius',
        'ground_far_radius',
        'ground_min_neighbours',
        'ground_plane_margin',
        'ground_plane_margin_slope',
        'reclassify_tilt_deg',
    ):
        need(getattr(og, name) >= 0, f'occupancy_grid.{name}', 'must not be negative')
    need(og.miss_log_odds < 0, 'occupancy_grid.miss_log_odds', 'must be negative')
    need(og.min_log_odds < 0 < og.max_log_odds, 'occupancy_grid.min_log_odds', 'must be < 0 < max_log_odds')
    need(
        0 < og.free_threshold < 0.5 < og.occupied_threshold < 1,
        'occupancy_grid.occupied_threshold',
        'and free_threshold need 0 < free_threshold < 0.5 < occupied_threshold < 1',
    )
