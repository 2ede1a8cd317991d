"""An occupancy grid as nav2's map_server reads it: ``<name>.yaml`` and its image ``<name>.pgm``, and back.

The image is a binary PGM (P5, 8 bits) in map_server's trinary colours: occupied black (0), free white (254),
unknown grey (205), its first row the grid's top (highest y): the grid's row 0, at the origin, is the image's last
row. The YAML names the image (relative to itself), ``mode: trinary``, the resolution [m], the origin ``[x, y, yaw]``
of the lower-left pixel in the map frame, ``negate: 0`` and the thresholds map_server applies to each pixel's
occupancy ``(255 - value) / 255``: above ``occupied_thresh`` (0.65) occupied, below ``free_thresh`` (0.196) free,
unknown between (205 gives 0.196078..., just above the free threshold).

Both files are written under a temporary name and renamed (:mod:`lego_loam_py.formats`), the image first, so the
YAML a reader opens names a complete image (a crash between the two leaves the previous YAML beside the new image).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from lego_loam_py.core.mapping.occupancy_grid import FREE, OCCUPIED, UNKNOWN, TernaryGrid
from lego_loam_py.errors import LegoLoamError
from lego_loam_py.formats import atomic_path, write_text_atomic

__all__ = [
    'OccupancyFilesError',
    'write_occupancy_files',
    'read_occupancy_files',
    'saved_occupancy_grid',
    'OCCUPANCY_NAME',
    'OCCUPIED_THRESH',
    'FREE_THRESH',
    'PIXEL_OCCUPIED',
    'PIXEL_FREE',
    'PIXEL_UNKNOWN',
]

OCCUPANCY_NAME = 'occupancy'  # the files' stem in a saved map: occupancy.yaml, occupancy.pgm

PIXEL_OCCUPIED, PIXEL_FREE, PIXEL_UNKNOWN = 0, 254, 205
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196


class OccupancyFilesError(LegoLoamError, ValueError):
    """Map_server files that cannot be read (or a grid that cannot be written): what is wrong, and where."""


def _number(value: float) -> str:
    """A float as YAML text, without the binary noise of ``index x resolution`` (-79.30000000000001 -> -79.3)."""
    return repr(float(f'{float(value):.10g}'))


def write_occupancy_files(directory: str | Path, grid: TernaryGrid, name: str = OCCUPANCY_NAME) -> dict[str, Path]:
    """Write ``grid`` as ``directory/<name>.yaml`` and ``directory/<name>.pgm``; returns their paths ('yaml',
    'image')."""
    if grid.width == 0 or grid.height == 0:
        raise OccupancyFilesError(f'{name}: the occupancy grid is empty (no keyframe seen yet): nothing to write')
    directory = Path(directory)
    image_path, yaml_path = directory / f'{name}.pgm', directory / f'{name}.yaml'
    pixels = np.full(grid.cells.shape, PIXEL_UNKNOWN, np.uint8)
    pixels[grid.cells == OCCUPIED] = PIXEL_OCCUPIED
    pixels[grid.cells == FREE] = PIXEL_FREE
    header = (
        f'P5\n# lego_loam_py occupancy grid, frame {grid.frame_id}, {grid.resolution:g} m per pixel\n'
        f'{grid.width} {grid.height}\n255\n'
    ).encode()
    with atomic_path(image_path) as temporary:
        temporary.write_bytes(header + np.ascontiguousarray(pixels[::-1]).tobytes())
    origin = ', '.join(_number(v) for v in (grid.origin[0], grid.origin[1], grid.origin_yaw))
    write_text_atomic(
        yaml_path,
        f'image: {image_path.name}\nmode: trinary\nresolution: {_number(grid.resolution)}\n'
        f'origin: [{origin}]\nnegate: 0\noccupied_thresh: {OCCUPIED_THRESH}\n'
        f'free_thresh: {FREE_THRESH}\n',
    )
    return {'yaml': yaml_path, 'image': image_path}


def _read_pgm(path: Path) -> np.ndarray:
    """(height, width) pixel values of a PGM (binary P5 or text P2, 8 or 16 bits) scaled to 0..1, first row top."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise OccupancyFilesError(f'{path}: cannot read the map image: {exc.strerror or exc}') from None
    # The header: magic, width, height, maxval, separated by whitespace and comments, then one whitespace byte.
    tokens, position = [], 0
    pattern = re.compile(rb'\s*(?:#[^\n]*\n\s*)*(\S+)')
    while len(tokens) < 4:
        match = pattern.match(data, position)
        if match is None:
            raise OccupancyFilesError(f'{path}: not a PGM image (its header ends early)')
        tokens.append(match.group(1))
        position = match.end()
    if tokens[0] not in (b'P5', b'P2'):
        raise OccupancyFilesError(
            f'{path}: not a PGM image (it starts with {tokens[0][:8]!r}; map_server images '
            'written here are binary PGM, P5)'
        )
    try:
        width, height, maxval = (int(t) for t in tokens[1:])
    except ValueError:
        raise OccupancyFilesError(f'{path}: unreadable PGM header {b" ".join(tokens)!r}') from None
    if width <= 0 or height <= 0 or not 0 < maxval < 65536:
        raise OccupancyFilesError(f'{path}: bad PGM size {width} x {height} or maximum {maxval}')
    if tokens[0] == b'P2':
        values = np.array(data[position:].split(), dtype=np.int64)
    else:
        dtype = np.dtype('u1') if maxval < 256 else np.dtype('>u2')
        body = data[position + 1 : position + 1 + width * height * dtype.itemsize]
        values = np.frombuffer(body, dtype=dtype)
    if values.size != width * height:
        raise OccupancyFilesError(f'{path}: {values.size} pixels for a {width} x {height} image (truncated?)')
    return values.reshape(height, width).astype(np.float64) / maxval


def read_occupancy_files(yaml_path: str | Path) -> TernaryGrid:
    """The grid of map_server files (the YAML's path), read as map_server reads them: ``mode`` trinary (the default),
    scale or raw, ``negate``, the thresholds, the image relative to the YAML."""
    import yaml

    yaml_path = Path(yaml_path)
    try:
        meta = yaml.safe_load(yaml_path.read_text())
    except OSError as exc:
        raise OccupancyFilesError(f'{yaml_path}: cannot read the map file: {exc.strerror or exc}') from None
    except yaml.YAMLError as exc:
        raise OccupancyFilesError(f'{yaml_path}: not YAML: {exc}') from None
    missing = [key for key in ('image', 'resolution', 'origin') if not isinstance(meta, dict) or key not in meta]
    if missing:
        raise OccupancyFilesError(f'{yaml_path}: a map_server map file needs {", ".join(missing)}')
    try:
        resolution = float(meta['resolution'])
        origin = [float(v) for v in meta['origin']]
        negate = bool(int(meta.get('negate', 0)))
        occupied = float(meta.get('occupied_thresh', OCCUPIED_THRESH))
        free = float(meta.get('free_thresh', FREE_THRESH))
    except (TypeError, ValueError) as exc:
        raise OccupancyFilesError(f'{yaml_path}: bad value: {exc}') from None
    mode = str(meta.get('mode', 'trinary'))
    if not resolution > 0 or len(origin) != 3 or not all(math.isfinite(v) for v in origin):
        raise OccupancyFilesError(
            f'{yaml_path}: resolution must be > 0 and origin [x, y, yaw], got {resolution}, {meta["origin"]}'
        )
    if mode not in ('trinary', 'scale', 'raw'):
        raise OccupancyFilesError(f'{yaml_path}: unknown mode {mode!r} (trinary, scale or raw)')
    shade = _read_pgm(yaml_path.parent / str(meta['image']))[::-1]  # the image's last row is the grid's row 0
    if mode == 'raw':  # the pixel value itself, as a signed byte (255: -1, unknown)
        cells = np.rint(shade * 255).astype(np.uint8).view(np.int8)
    else:
        occupancy = shade if negate else 1.0 - shade
        cells = np.full(occupancy.shape, UNKNOWN, np.int8)
        if mode == 'scale':
            between = (occupancy >= free) & (occupancy <= occupied)
            cells[between] = np.rint(99.0 * (occupancy[between] - free) / (occupied - free)).astype(np.int8)
        cells[occupancy > occupied] = OCCUPIED
        cells[occupancy < free] = FREE
    return TernaryGrid(resolution, (origin[0], origin[1]), np.ascontiguousarray(cells), origin[2])


def saved_occupancy_grid(directory: str | Path, params) -> TernaryGrid:
    """The occupancy grid of the map saved in ``directory``: its map_server files when it has them, else rendered
    from its map bundle's keyframes with ``params`` (:class:`~lego_loam_py.core.params.types.OccupancyGridParams`;
    a map saved before the grid existed). A :class:`OccupancyFilesError` or
    :class:`~lego_loam_py.core.mapping.map_bundle.MapBundleError` says what is missing."""
    from lego_loam_py.core.mapping.map_bundle import read_bundle
    from lego_loam_py.core.mapping.map_optimization import Keyframe
    from lego_loam_py.core.mapping.occupancy_grid import OccupancyGrid

    directory = Path(directory)
    yaml_path = directory / f'{OCCUPANCY_NAME}.yaml'
    if yaml_path.is_file():
        return read_occupancy_files(yaml_path)
    bundle = read_bundle(directory)
    grid = OccupancyGrid(params)
    grid.redraw(
        Keyframe(k, int(bundle.stamps_ns[k]), bundle.poses6[k], bundle.corner[k], bundle.surf[k], bundle.outlier[k])
        for k in range(len(bundle))
    )
    return grid.ternary()
