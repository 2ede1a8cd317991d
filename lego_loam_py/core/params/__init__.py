"""Parameters of lego_loam_py: the typed structure, read from ROS 2 parameter files and overrides.

This module is the import path for users, the nodes and the commands: it re-exports :class:`Params`, its
sections and :data:`SENSOR_PRESETS` (defined in :mod:`lego_loam_py.core.params.types`) and
:func:`params_from_mapping` (:mod:`lego_loam_py.core.params.validation`), and holds the loading.

Parameters come from a ROS 2 style YAML file (``ros__parameters`` layout, one file for all four nodes)::

    /**:
      ros__parameters:
        sensor:
          preset: HDL-32E
        image_projection:
          segment_theta: 1.0472

A sensor preset fills the geometry fields of ``sensor`` (rows, columns, resolutions, ground rows); any of
those fields given explicitly overrides the preset. Unknown keys and values of the wrong type raise
:class:`ParameterError` naming the key.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from lego_loam_py.core.params.types import (
    SENSOR_PRESETS,
    FeatureAssociationParams,
    FramesParams,
    ImageProjectionParams,
    ImuParams,
    LocalizationParams,
    LoopClosureParams,
    MapOptimizationParams,
    OccupancyGridParams,
    ParameterError,
    Params,
    ReliabilityParams,
    SensorParams,
)
from lego_loam_py.core.params.validation import flatten, params_from_mapping

__all__ = [
    'ParameterError',
    'SensorParams',
    'ImageProjectionParams',
    'FeatureAssociationParams',
    'MapOptimizationParams',
    'LoopClosureParams',
    'LocalizationParams',
    'ReliabilityParams',
    'FramesParams',
    'ImuParams',
    'OccupancyGridParams',
    'Params',
    'SENSOR_PRESETS',
    'load_params',
    'params_from_mapping',
    'flatten',
    'read_params_file',
    'write_params_file',
    'default_params_file',
    'parse_overrides',
]


def write_params_file(path: str | Path, values: Mapping[str, Any]) -> Path:
    """A ROS 2 parameter file for every node (``/**``) setting ``values``: ``'section.name'`` keys in their
    section, keys without one (``use_sim_time``) at the top; paths are written as strings. The file
    :func:`read_params_file` and ``--ros-args --params-file`` read."""
    nested: dict[str, Any] = {}
    for key, value in values.items():
        section, _, name = key.rpartition('.')
        value = str(value) if isinstance(value, Path) else value
        (nested.setdefault(section, {}) if section else nested)[name] = value
    path = Path(path)
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': nested}}, sort_keys=False))
    return path


def read_params_file(path: str | Path, node_name: str | None = None) -> dict[str, Any]:
    """Flat ``{'section.name': value}`` from a ROS 2 parameter file.

    Sections for ``/**`` apply to every node; a section named after the node (with or without a leading
    slash) applies on top. Without ``node_name`` all sections are merged in file order.
    """
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ParameterError(f'cannot read parameter file {path}: {exc.strerror}') from exc
    except yaml.YAMLError as exc:
        raise ParameterError(f'parameter file {path} is not valid YAML: {exc}') from exc
    if document is None:
        return {}
    if not isinstance(document, Mapping):
        raise ParameterError(f'parameter file {path}: expected a mapping of node names at the top level')
    merged: dict[str, Any] = {}
    for node_key, content in document.items():
        name = str(node_key).lstrip('/')
        if node_name is not None and name not in ('**', node_name.lstrip('/')):
            continue
        if not isinstance(content, Mapping) or 'ros__parameters' not in content:
            raise ParameterError(f"parameter file {path}: section '{node_key}' has no 'ros__parameters'")
        parameters = content['ros__parameters'] or {}
        if not isinstance(parameters, Mapping):
            raise ParameterError(f"parameter file {path}: '{node_key}.ros__parameters' must be a mapping")
        merged.update(flatten(parameters))
    return merged


def default_params_file() -> Path:
    """``config/params.yaml`` of the source tree (an installed copy lives in share/lego_loam_py/config)."""
    return Path(__file__).resolve().parents[3] / 'config' / 'params.yaml'


def load_params(
    path: str | Path | None = None, overrides: Mapping[str, Any] | None = None, node_name: str | None = None
) -> Params:
    """Parameters from a ROS 2 YAML file (or the defaults when ``path`` is None) plus overrides."""
    values: dict[str, Any] = {}
    if path is not None:
        values.update(read_params_file(path, node_name))
    if overrides:
        values.update(flatten(overrides))
    try:
        return params_from_mapping(values)
    except ParameterError as exc:
        if path is not None:
            raise ParameterError(f'{path}: {exc}') from None
        raise


def parse_overrides(items: Sequence[str]) -> dict:
    """``name:=value`` overrides (``-p`` on the command line) as a dict of YAML-parsed values."""
    out = {}
    for item in items:
        if ':=' not in item:
            raise ParameterError(f"parameter override '{item}' must look like name:=value")
        name, value = item.split(':=', 1)
        out[name.strip()] = yaml.safe_load(value)
    return out
