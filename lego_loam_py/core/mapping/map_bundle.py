"""The map bundle: a map mapOptimization saved, in a form it can load again to localize in (format version 1).

A bundle is two files in one directory (beside the PCDs users view, which stay as they are):

* ``map_bundle.json``, the manifest: format name and version, the frame conventions, the parameters that
  matter for reuse (sensor preset and geometry, voxel leaves, the descriptor's geometry), counts, the pose
  graph's summary, where the map came from when known, and the name and SHA-256 of the data file;
* ``map_bundle.<token>.npz``, the data (numpy arrays, uncompressed so that it loads at disk speed):

  ==========================  ==============================================================================
  ``stamps_ns``               (K,) int64 keyframe stamps [ns]
  ``poses6``                  (K, 6) keyframe poses in the map: six-vectors (rx, ry, rz, tx, ty, tz), LOAM
                              camera axes, ``R = Ry(ry) Rx(rx) Rz(rz)``, ``p_map = R p_keyframe + t``
  ``corner``, ``surf``,       each keyframe's downsampled clouds, concatenated: (N, 4) float32 x y z intensity
  ``outlier``                 in the keyframe's sensor frame, camera axes; ``<name>_offsets`` (K + 1,) int64
                              delimit keyframe k's rows ``[offsets[k], offsets[k + 1])``
  ``corner_map``,             the whole map voxel-filtered (corner 0.2 m, surface + outliers 0.4 m by default),
  ``surface_map``             (M, 4) float32 in the map frame, camera axes (derived; saves rebuilding it)
  ``factor_keys``             (F, 2) int64 pose-graph factors: keyframe indices (a prior: both the same)
  ``factor_kinds``            (F,) int8: 0 prior, 1 odometry, 2 loop
  ``factor_measured``         (F, 4, 4) the measured pose of keys[1] in keys[0]'s frame (lidar axes, as gtsam
                              Pose3 in the graph); a prior's: the keyframe's pose
  ``factor_information``      (F, 6, 6) information (rotation, translation: gtsam's tangent order)
  ``factor_kernels``          (F,) int8 robust kernel: 0 none, 1 Huber, 2 Cauchy; ``factor_kernel_widths`` (F,)
                              its width in standard deviations
  ==========================  ==============================================================================

Writing is atomic as for every file users keep (:mod:`lego_loam_py.formats`): the data goes under a new name
first, then the manifest that names it replaces the old one, then data files no manifest names are removed. A
crash at any moment leaves the previous bundle or the new one, never a mixture; a reader opens the manifest
first and checks the data's checksum. :func:`read_bundle` names what is wrong (missing, corrupt, another format
version); :func:`check_compatible` what does not fit the parameters of the run (another sensor).
"""

from __future__ import annotations

import hashlib
import json
import math
import secrets
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lego_loam_py.core.params.types import Params
from lego_loam_py.errors import LegoLoamError
from lego_loam_py.formats import atomic_path, write_text_atomic

__all__ = [
    'FORMAT',
    'FORMAT_VERSION',
    'MANIFEST',
    'MapBundleError',
    'GraphFactor',
    'MapBundle',
    'write_bundle',
    'read_bundle',
    'read_manifest',
    'check_compatible',
    'is_bundle',
    'reuse_parameters',
    'FACTOR_KINDS',
    'KERNELS',
]

FORMAT = 'lego_loam_py map bundle'
FORMAT_VERSION = 1
MANIFEST = 'map_bundle.json'
_DATA_PREFIX = 'map_bundle.'
FACTOR_KINDS = ('prior', 'odometry', 'loop')
KERNELS = ('none', 'huber', 'cauchy')
_CLOUDS = ('corner', 'surf', 'outlier')

FRAMES = {
    'map_frame': 'camera_init: the frame of the mapping run (its first pose; levelled by the IMU when it had '
    'one); the static map -> camera_init turns its LOAM camera axes into REP-103 axes',
    'axes': 'LOAM camera axes: x left, y up, z forward = (y, z, x) of REP-103 lidar axes',
    'keyframe_poses': 'six-vectors (rx, ry, rz, tx, ty, tz) [rad, m]: R = Ry(ry) Rx(rx) Rz(rz), p_map = R p + t',
    'keyframe_clouds': 'per keyframe, in its sensor frame, camera axes: x y z [m] intensity, float32, voxel-filtered',
    'pose_graph': 'gtsam Pose3 between factors in REP-103 lidar axes; information in (rotation, translation) order',
    'stamps': 'nanoseconds, the header stamp of the scan each keyframe was made from',
}


class MapBundleError(LegoLoamError):
    """A map bundle that cannot be used: missing, corrupt, of another format version or for another sensor."""


@dataclass(frozen=True)
class GraphFactor:
    """One factor of the keyframe pose graph (see the module docstring for the axes)."""

    kind: str  # 'prior', 'odometry' or 'loop'
    keys: tuple[int, int]  # keyframe indices (a prior: (k, k))
    measured: np.ndarray  # 4x4, lidar axes
    information: np.ndarray  # 6x6 (rotation, translation)
    kernel: str = 'none'  # robust kernel: 'none', 'huber' or 'cauchy' ...
    kernel_width: float = 0.0  # ... of this width [standard deviations]


@dataclass
class MapBundle:
    """A saved map: keyframes, their clouds, the pose graph and what is needed to reuse them."""

    stamps_ns: np.ndarray  # (K,) int64
    poses6: np.ndarray  # (K, 6) map frame, camera axes
    corner: list[np.ndarray]  # K x (n, 4) float32, keyframe sensor frame, camera axes
    surf: list[np.ndarray]
    outlier: list[np.ndarray]
    factors: list[GraphFactor]
    corner_map: np.ndarray  # (M, 4) float32, map frame, camera axes
    surface_map: np.ndarray
    parameters: dict[str, Any]  # the reuse-relevant parameters (see reuse_parameters)
    source: dict[str, Any] = field(default_factory=dict)  # where the map came from, when known (a bag, ...)
    path: Path | None = None  # the directory it was read from

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @classmethod
    def of(
        cls,
        keyframes: Sequence,
        factors: Sequence[GraphFactor],
        params: Params,
        corner_map: np.ndarray,
        surface_map: np.ndarray,
        source: dict | None = None,
    ) -> MapBundle:
        """From a mapper's keyframes (with ``stamp_ns``, ``pose6``, ``corner``, ``surf``, ``outlier``), its
        pose-graph factors and its maps."""
        return cls(
            np.array([kf.stamp_ns for kf in keyframes], dtype=np.int64),
            np.array([kf.pose6 for kf in keyframes], dtype=np.float64).reshape(-1, 6),
            [kf.corner for kf in keyframes],
            [kf.surf for kf in keyframes],
            [kf.outlier for kf in keyframes],
            list(factors),
            corner_map,
            surface_map,
            reuse_parameters(params),
            dict(source or {}),
        )


def reuse_parameters(params: Params) -> dict[str, Any]:
    """The parameters a map depends on: the sensor (its range image and rate), the voxel leaves of the clouds."""
    s, mo, lc = params.sensor, params.map_optimization, params.loop_closure
    return {
        'sensor': dict(
            preset=s.preset,
            n_scan=s.n_scan,
            horizon_scan=s.horizon_scan,
            ang_res_x=s.ang_res_x,
            ang_res_y=s.ang_res_y,
            scan_period=s.scan_period,
        ),
        'map_optimization': dict(
            corner_leaf_size=mo.corner_leaf_size,
            surf_leaf_size=mo.surf_leaf_size,
            outlier_leaf_size=mo.outlier_leaf_size,
            keyframe_distance=mo.keyframe_distance,
        ),
        'feature_association': dict(odometry_model=params.feature_association.odometry_model),
        'scan_context': dict(
            rings=lc.scan_context_rings, sectors=lc.scan_context_sectors, max_radius=lc.scan_context_max_radius
        ),
    }


# --------------------------------------------------------------------------------------------- writing


def _offsets(clouds: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([[0], np.cumsum([len(c) for c in clouds])]).astype(np.int64)


def _stacked(clouds: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(clouds).astype(np.float32) if clouds else np.zeros((0, 4), np.float32)


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, 'rb') as f:
        for block in iter(lambda: f.read(1 << 22), b''):
            digest.update(block)
    return digest.hexdigest()


def write_bundle(directory: str | Path, bundle: MapBundle, generator: str = '') -> dict[str, Path]:
    """Write ``bundle`` into ``directory`` atomically (see the module docstring); returns {'map_bundle': manifest,
    'map_bundle_data': data file}."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    factors = bundle.factors
    arrays = dict(
        stamps_ns=np.asarray(bundle.stamps_ns, dtype=np.int64),
        poses6=np.asarray(bundle.poses6, dtype=np.float64),
        corner_map=np.asarray(bundle.corner_map, np.float32),
        surface_map=np.asarray(bundle.surface_map, np.float32),
        factor_keys=np.array([f.keys for f in factors], dtype=np.int64).reshape(-1, 2),
        factor_kinds=np.array([FACTOR_KINDS.index(f.kind) for f in factors], dtype=np.int8),
        factor_measured=np.array([f.measured for f in factors], dtype=np.float64).reshape(-1, 4, 4),
        factor_information=np.array([f.information for f in factors], dtype=np.float64).reshape(-1, 6, 6),
        factor_kernels=np.array([KERNELS.index(f.kernel) for f in factors], dtype=np.int8),
        factor_kernel_widths=np.array([f.kernel_width for f in factors], dtype=np.float64),
    )
    for name in _CLOUDS:
        clouds = getattr(bundle, name)
        arrays[name], arrays[f'{name}_offsets'] = _stacked(clouds), _offsets(clouds)
    data = directory / f'{_DATA_PREFIX}{secrets.token_hex(6)}.npz'
    with atomic_path(data) as temporary:
        with open(temporary, 'wb') as f:
            np.savez(f, **arrays)
    kinds = arrays['factor_kinds']
    manifest = {
        'format': FORMAT,
        'format_version': FORMAT_VERSION,
        'generator': generator,
        'data_file': data.name,
        'data_sha256': _sha256(data),
        'keyframes': int(len(bundle)),
        'points': int(sum(len(arrays[name]) for name in _CLOUDS)),
        'pose_graph': {kind: int((kinds == i).sum()) for i, kind in enumerate(FACTOR_KINDS)},
        'frames': FRAMES,
        'parameters': bundle.parameters,
        'source': bundle.source,
    }
    written = {
        'map_bundle': write_text_atomic(directory / MANIFEST, json.dumps(manifest, indent=2) + '\n'),
        'map_bundle_data': data,
    }
    # The manifest names the new data now: older data files are no one's (a crash before this line leaves them
    # behind, and the next save removes them).
    for path in directory.glob(f'{_DATA_PREFIX}*.npz'):
        if path.name != data.name:
            path.unlink(missing_ok=True)
    return written


# --------------------------------------------------------------------------------------------- reading


def is_bundle(directory: str | Path) -> bool:
    return (Path(directory) / MANIFEST).is_file()


def read_manifest(directory: str | Path) -> dict[str, Any]:
    """The manifest of the bundle in ``directory``, checked for its format and version."""
    directory = Path(directory)
    where = f'map bundle {directory}'
    if not directory.is_dir():
        raise MapBundleError(f'{where}: no such directory')
    path = directory / MANIFEST
    if not path.is_file():
        raise MapBundleError(
            f"{where}: no {MANIFEST} in it (a map bundle is written by mapOptimization's save: "
            'the save_map service, its shutdown, or lego_loam_py run into OUT/map)'
        )
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapBundleError(f'{where}: {MANIFEST} cannot be read ({exc})') from None
    if not isinstance(manifest, dict) or manifest.get('format') != FORMAT:
        raise MapBundleError(f'{where}: {MANIFEST} is not a {FORMAT} manifest')
    version = manifest.get('format_version')
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise MapBundleError(f'{where}: unknown format version {version!r}')
    if version > FORMAT_VERSION:
        raise MapBundleError(
            f'{where}: format version {version} was written by a newer lego_loam_py; this one '
            f'reads version {FORMAT_VERSION}'
        )
    for key, kind in (('data_file', str), ('data_sha256', str), ('parameters', dict)):
        if not isinstance(manifest.get(key), kind):
            raise MapBundleError(f'{where}: {MANIFEST} lacks {key!r}')
    return manifest


def read_bundle(directory: str | Path, verify: bool = True) -> MapBundle:
    """The bundle in ``directory``; :class:`MapBundleError` naming the problem when it cannot be used.
    ``verify``: check the data file's SHA-256 against the manifest (0.2 s per 100 MB)."""
    directory = Path(directory)
    manifest = read_manifest(directory)
    where = f'map bundle {directory}'
    data = directory / Path(manifest['data_file']).name
    if not data.is_file():
        raise MapBundleError(f'{where}: its data file {data.name} (named by {MANIFEST}) is missing')
    if verify and _sha256(data) != manifest['data_sha256']:
        raise MapBundleError(f"{where}: {data.name} is corrupt (its checksum differs from the manifest's)")
    try:
        with np.load(data, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except (OSError, ValueError, EOFError) as exc:
        raise MapBundleError(f'{where}: {data.name} cannot be read ({exc})') from None
    return _bundle_from_arrays(arrays, manifest, directory)


def _bundle_from_arrays(arrays: dict[str, np.ndarray], manifest: dict, directory: Path) -> MapBundle:
    where = f'map bundle {directory}'

    def need(condition: bool, what: str) -> None:
        if not condition:
            raise MapBundleError(f'{where} is corrupt: {what}')

    required = (
        'stamps_ns',
        'poses6',
        'corner_map',
        'surface_map',
        'factor_keys',
        'factor_kinds',
        'factor_measured',
        'factor_information',
        'factor_kernels',
        'factor_kernel_widths',
    ) + tuple(n for name in _CLOUDS for n in (name, f'{name}_offsets'))
    missing = [name for name in required if name not in arrays]
    need(not missing, f'arrays missing: {", ".join(missing)}')
    stamps, poses = arrays['stamps_ns'], arrays['poses6']
    count = len(stamps)
    need(
        count >= 1 and stamps.ndim == 1 and poses.shape == (count, 6),
        f'{count} keyframes but poses of shape {poses.shape}',
    )
    need(
        manifest.get('keyframes', count) == count,
        f'the manifest says {manifest.get("keyframes")} keyframes, the data holds {count}',
    )
    need(bool(np.isfinite(poses).all()) and bool((np.abs(poses[:, 3:]) < 1e6).all()), 'keyframe poses not finite')
    clouds = {}
    for name in _CLOUDS:
        points, offsets = arrays[name], arrays[f'{name}_offsets']
        need(points.ndim == 2 and points.shape[1] == 4, f'{name} clouds of shape {points.shape}')
        need(
            offsets.shape == (count + 1,)
            and offsets[0] == 0
            and offsets[-1] == len(points)
            and bool((np.diff(offsets) >= 0).all()),
            f'{name} offsets do not delimit {count} clouds',
        )
        clouds[name] = np.split(points.astype(np.float32, copy=False), offsets[1:-1])
    for name in ('corner_map', 'surface_map'):
        need(arrays[name].ndim == 2 and arrays[name].shape[1] == 4, f'{name} of shape {arrays[name].shape}')
    keys, kinds = arrays['factor_keys'], arrays['factor_kinds']
    factors = len(kinds)
    need(
        keys.shape == (factors, 2)
        and arrays['factor_measured'].shape == (factors, 4, 4)
        and arrays['factor_information'].shape == (factors, 6, 6)
        and arrays['factor_kernels'].shape == (factors,)
        and arrays['factor_kernel_widths'].shape == (factors,),
        'pose-graph arrays of different lengths',
    )
    kernels = arrays['factor_kernels']
    need(
        bool(((keys >= 0) & (keys < count)).all())
        and bool(((kinds >= 0) & (kinds < len(FACTOR_KINDS))).all())
        and bool(((kernels >= 0) & (kernels < len(KERNELS))).all()),
        'pose-graph factors name keyframes, kinds or kernels that do not exist',
    )
    graph = [
        GraphFactor(
            FACTOR_KINDS[int(kind)], (int(a), int(b)), measured, information, KERNELS[int(kernel)], float(width)
        )
        for kind, (a, b), measured, information, kernel, width in zip(
            kinds,
            keys,
            arrays['factor_measured'],
            arrays['factor_information'],
            kernels,
            arrays['factor_kernel_widths'],
        )
    ]
    return MapBundle(
        stamps.astype(np.int64),
        poses.astype(np.float64),
        clouds['corner'],
        clouds['surf'],
        clouds['outlier'],
        graph,
        arrays['corner_map'].astype(np.float32, copy=False),
        arrays['surface_map'].astype(np.float32, copy=False),
        manifest['parameters'],
        manifest.get('source') or {},
        directory,
    )


def check_compatible(bundle: MapBundle, params: Params) -> list[str]:
    """Raise :class:`MapBundleError` when the bundle was made with another sensor than ``params`` describe (its
    clouds would not match the scans); return warnings for what differs but still works (voxel leaves)."""
    saved, now = bundle.parameters, reuse_parameters(params)
    where = f'map bundle {bundle.path}' if bundle.path else 'map bundle'
    sensor, current = saved.get('sensor', {}), now['sensor']
    if sensor.get('preset') != current['preset']:
        raise MapBundleError(
            f'{where} was made with sensor preset {sensor.get("preset")!r}, this run uses '
            f'{current["preset"]!r}: localization needs the sensor the map was made with'
        )
    for key in ('n_scan', 'horizon_scan', 'ang_res_x', 'ang_res_y', 'scan_period'):
        value = sensor.get(key)
        if not isinstance(value, (int, float)) or not math.isclose(float(value), float(current[key]), rel_tol=1e-6):
            raise MapBundleError(
                f'{where} was made with sensor.{key} = {value!r}, this run uses {current[key]!r}: '
                'localization needs the sensor geometry the map was made with'
            )
    warnings = []
    for section in ('map_optimization', 'scan_context'):
        for key, value in now[section].items():
            old = saved.get(section, {}).get(key)
            if old != value:
                warnings.append(f'{where}: {section}.{key} was {old!r} when it was made, {value!r} now')
    return warnings
