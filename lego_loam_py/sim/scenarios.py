"""The simulator's scenarios: seeded procedural worlds and the trajectories through them.

=============  ==============================================================================================
``campus``     outdoor loop of ~400 m on a gentle slope: asphalt road with curbs, buildings (some L-shaped,
               with windows), trees, lamp poles with signs, parked cars, bushes; a car-mounted VLP-16 at
               1.8 m drives it at ~1.7 m/s (4 min a lap) and returns to its start (loop closure).
``forest``     ~240 m trail loop through a dense forest on uneven terrain: trunks of varying radius, crowns,
               bushes, logs, boulders; few planes; a small robot (lidar at 0.75 m) rolls and pitches with
               the ground.
``corridor``   walk around an indoor corridor loop (60 x 30 m office floor): walls, ceiling, doors,
               pillars, side openings into rooms; a handheld lidar at 1.7 m with walking bob and sway.
``aggressive`` a campus-like area driven hard: straights at 8 m/s, hairpins and chicanes with yaw rates
               up to 90 deg/s and up to ~1 g of lateral acceleration: the scenario where deskewing matters.
``rows``       a city block between rows of identical buildings, poles and cars (every 26 m), a lap and a
               half: repeated structure where false loop closures tempt.
``open_road``  a 690 m road across open fields at 8 m/s, little beside it: the mapping drifts along it
               before the loop closes at a built-up start.
``long_road``  ``open_road`` with 500 m straights (1.25 km a lap): the drift before the loop closes is about a
               metre, more without IMU.
``straight``   a 480 m street driven straight and back: no turn in its first 50 s (IMU calibration refuses it).
=============  ==============================================================================================

The seed fixes the scenery (placement, sizes, materials) and, in the simulator, the noise; the roads and
paths of a scenario are the same for every seed. The world frame is gravity-aligned (z up).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from lego_loam_py.sim.scene import (
    GROUND_ID,
    Scene,
    SceneBuilder,
    Terrain,
    box_mesh,
    cylinder_mesh,
    ellipsoid_mesh,
    heightfield_mesh,
    material_index,
    transform_mesh,
)
from lego_loam_py.sim.trajectory import ClosedPath, InPlaceTurns, Oscillation, PathTrajectory, SpeedProfile, Trajectory

__all__ = ['World', 'SCENARIOS', 'ScenarioInfo', 'build_world', 'scenario_names', 'scenario_rng']


def scenario_rng(seed: int, purpose: str, *indices: int) -> np.random.Generator:
    """Independent, reproducible random stream for (seed, purpose, indices)."""
    import zlib

    return np.random.default_rng(np.random.SeedSequence([int(seed), zlib.crc32(purpose.encode()), *indices]))


@dataclass
class World:
    """A scenario instance: the scene, the lidar trajectory and facts about them."""

    name: str
    seed: int
    scene: Scene
    trajectory: Trajectory
    default_duration: float  # [s]: one full lap
    description: str
    facts: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------ placement helpers


class _Clearance:
    """Distance from points to a path (dense polyline samples)."""

    def __init__(self, path: ClosedPath, spacing: float = 0.5):
        self.points = path.polyline(spacing)
        self.tree = cKDTree(self.points)

    def distance(self, xy: np.ndarray) -> np.ndarray:
        return self.tree.query(np.atleast_2d(xy))[0]


class _Occupancy:
    """Raster of occupied ground (0.5 m cells) so objects do not intersect each other."""

    def __init__(self, x_range: tuple[float, float], y_range: tuple[float, float], cell: float = 0.5):
        self.origin = np.array([x_range[0], y_range[0]])
        self.cell = cell
        self.grid = np.zeros(
            (int((y_range[1] - y_range[0]) / cell) + 1, int((x_range[1] - x_range[0]) / cell) + 1), dtype=bool
        )

    def _cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ij = np.floor((np.atleast_2d(xy) - self.origin) / self.cell).astype(int)
        inside = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < self.grid.shape[1]) & (ij[:, 1] < self.grid.shape[0])
        return ij[:, 1], ij[:, 0], inside

    def free(self, xy: np.ndarray) -> bool:
        row, col, inside = self._cells(xy)
        return bool(inside.all() and not self.grid[row, col].any())

    def mark(self, xy: np.ndarray) -> None:
        row, col, inside = self._cells(xy)
        self.grid[row[inside], col[inside]] = True


def _rectangle_samples(
    center: np.ndarray, yaw: float, length: float, width: float, margin: float = 0.0, spacing: float = 0.5
) -> np.ndarray:
    """Points covering a rotated rectangle (plus margin) on a grid."""
    u = np.arange(-0.5 * length - margin, 0.5 * length + margin + 1e-9, spacing)
    v = np.arange(-0.5 * width - margin, 0.5 * width + margin + 1e-9, spacing)
    uu, vv = np.meshgrid(u, v)
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack([center[0] + c * uu.ravel() - s * vv.ravel(), center[1] + s * uu.ravel() + c * vv.ravel()])


def _disc_samples(center: np.ndarray, radius: float) -> np.ndarray:
    r = np.arange(-radius, radius + 1e-9, 0.5)
    xx, yy = np.meshgrid(r, r)
    keep = xx**2 + yy**2 <= radius**2 + 1e-9
    return np.vstack([center[:2], np.column_stack([center[0] + xx[keep], center[1] + yy[keep]])])


def _ground_z(terrain: Terrain, xy: np.ndarray) -> tuple[float, float]:
    """(lowest, highest) terrain height under a set of points."""
    z = terrain.height(xy[:, 0], xy[:, 1])
    return float(z.min()), float(z.max())


# ------------------------------------------------------------------------------------------ object kits


def _add_building(
    builder: SceneBuilder,
    terrain: Terrain,
    center: np.ndarray,
    yaw: float,
    length: float,
    width: float,
    height: float,
    wall: str,
    rng: np.random.Generator,
    wing: tuple[float, float, float] | None = None,
) -> None:
    """A box building (optionally L-shaped: ``wing`` = (length, width, offset along the main axis)) with a
    grid of glass windows standing 3 cm proud of the facades."""
    boxes = [(center, yaw, length, width)]
    if wing is not None:
        wl, ww, offset = wing
        c, s = math.cos(yaw), math.sin(yaw)
        along = np.array([c, s])
        across = np.array([-s, c])
        wing_center = center + along * offset + across * (0.5 * width + 0.5 * wl - 0.5)
        boxes.append((wing_center, yaw + 0.5 * math.pi, wl, ww))
    footprint = np.vstack([_rectangle_samples(c_, y_, l_, w_) for c_, y_, l_, w_ in boxes])
    low, high = _ground_z(terrain, footprint)
    base = low - 0.5
    top = high + height
    parts = []
    for c_, y_, l_, w_ in boxes:
        v, f = box_mesh((l_, w_, top - base))
        parts.append((transform_mesh(v, y_, (c_[0], c_[1], base)), f, wall))
        # Windows: 1.4 x 1.5 m panes every 3 m, one row per 3.2 m floor, from 1.0 m above the ground.
        floors = np.arange(high + 1.0, top - 1.6, 3.2)
        for side_length, side_offset, side_yaw in (
            (l_, 0.5 * w_, 0.0),
            (l_, -0.5 * w_, math.pi),
            (w_, 0.5 * l_, -0.5 * math.pi),
            (w_, -0.5 * l_, 0.5 * math.pi),
        ):
            columns = np.arange(-0.5 * side_length + 2.0, 0.5 * side_length - 1.9, 3.0)
            if not len(columns) or not len(floors):
                continue
            pane_v, pane_f = box_mesh((1.4, 0.06, 1.5))
            for z0 in floors:
                for u in columns:
                    # local facade frame: along the side (u), outward normal (+y of the pane after side_yaw)
                    local = (
                        np.array([u, side_offset + 0.03 * np.sign(side_offset)])
                        if side_yaw in (0.0, math.pi)
                        else np.array([side_offset + 0.03 * np.sign(side_offset), u])
                    )
                    pane_yaw = y_ + (0.0 if side_yaw in (0.0, math.pi) else 0.5 * math.pi)
                    c, s = math.cos(y_), math.sin(y_)
                    world = c_ + np.array([c * local[0] - s * local[1], s * local[0] + c * local[1]])
                    parts.append((transform_mesh(pane_v, pane_yaw, (world[0], world[1], z0)), pane_f, 'glass'))
    builder.add_object('building', parts)


def _add_tree(
    builder: SceneBuilder,
    terrain: Terrain,
    xy: np.ndarray,
    rng: np.random.Generator,
    conifer: bool,
    trunk_radius: float,
    height: float,
    crown_radius: float,
    crown_base: float | None = None,
    segments: int = 10,
) -> None:
    """Trunk (bark cylinder, slightly tilted and tapering) and crown (rough ellipsoid or cone)."""
    z = float(terrain.height(xy[0], xy[1])) - 0.3
    tilt = rng.normal(0.0, math.radians(2.0), 2)
    azimuth = rng.uniform(0.0, 2.0 * math.pi)
    trunk_v, trunk_f = cylinder_mesh(trunk_radius, height, segments, top_radius=trunk_radius * 0.5)
    parts = [(transform_mesh(trunk_v, azimuth, (xy[0], xy[1], z), roll=tilt[0], pitch=tilt[1]), trunk_f, 'bark')]
    top = (
        np.array([xy[0], xy[1], z])
        + transform_mesh(np.array([[0.0, 0.0, height]]), azimuth, roll=tilt[0], pitch=tilt[1])[0]
    )
    if conifer:
        base = crown_base if crown_base is not None else 0.35 * height
        cone_v, cone_f = cylinder_mesh(crown_radius, height - base + 1.0, 12, top_radius=0.05)
        parts.append((transform_mesh(cone_v, azimuth, (top[0], top[1], z + base)), cone_f, 'foliage'))
    else:
        vertical = crown_radius * rng.uniform(0.8, 1.2)
        crown_v, crown_f = ellipsoid_mesh(
            (crown_radius, crown_radius * rng.uniform(0.8, 1.2), vertical), 2, roughness=0.18, rng=rng
        )
        parts.append((transform_mesh(crown_v, azimuth, (top[0], top[1], top[2] + 0.45 * vertical)), crown_f, 'foliage'))
    builder.add_object('tree', parts)


def _add_pole(builder: SceneBuilder, terrain: Terrain, xy: np.ndarray, facing: float, sign: bool) -> None:
    """Lamp post (metal, 6 m) with its lamp head; optionally a retro-reflective sign at 2.2 m facing
    ``facing`` [rad] (the direction the sign's face looks towards)."""
    z = float(terrain.height(xy[0], xy[1])) - 0.2
    pole_v, pole_f = cylinder_mesh(0.07, 6.2, 8)
    parts = [(transform_mesh(pole_v, 0.0, (xy[0], xy[1], z)), pole_f, 'metal')]
    head_v, head_f = box_mesh((0.8, 0.3, 0.15))
    c, s = math.cos(facing + 0.5 * math.pi), math.sin(facing + 0.5 * math.pi)
    parts.append(
        (transform_mesh(head_v, facing + 0.5 * math.pi, (xy[0] + 0.3 * c, xy[1] + 0.3 * s, z + 6.1)), head_f, 'metal')
    )
    if sign:
        plate_v, plate_f = box_mesh((0.6, 0.03, 0.6))
        offset = 0.1
        parts.append(
            (
                transform_mesh(
                    plate_v,
                    facing - 0.5 * math.pi,
                    (xy[0] + offset * math.cos(facing), xy[1] + offset * math.sin(facing), z + 2.4),
                ),
                plate_f,
                'retroreflector',
            )
        )
    builder.add_object('pole', parts)


def _add_car(builder: SceneBuilder, terrain: Terrain, xy: np.ndarray, yaw: float, rng: np.random.Generator) -> None:
    """Parked car: body, glass cabin, four wheels."""
    length, width = rng.uniform(4.0, 4.9), rng.uniform(1.7, 1.9)
    corners = _rectangle_samples(xy, yaw, length, width, spacing=1.0)
    z = _ground_z(terrain, corners)[0]
    body_v, body_f = box_mesh((length, width, 0.75))
    cabin_v, cabin_f = box_mesh((length * 0.55, width * 0.9, 0.6))
    parts = [
        (transform_mesh(body_v, yaw, (xy[0], xy[1], z + 0.32)), body_f, 'car_paint'),
        (
            transform_mesh(
                cabin_v, yaw, (xy[0] - 0.05 * length * math.cos(yaw), xy[1] - 0.05 * length * math.sin(yaw), z + 1.07)
            ),
            cabin_f,
            'glass',
        ),
    ]
    wheel_v, wheel_f = cylinder_mesh(0.33, 0.22, 10)
    wheel_v = wheel_v[:, [0, 2, 1]] - [0.0, 0.11, 0.0]  # axle along y
    for a in (0.32, -0.32):
        for b in (0.5, -0.5):
            local = np.array([a * length, b * (width - 0.2)])
            c, s = math.cos(yaw), math.sin(yaw)
            center = xy + [c * local[0] - s * local[1], s * local[0] + c * local[1]]
            parts.append((transform_mesh(wheel_v, yaw, (center[0], center[1], z + 0.33)), wheel_f, 'asphalt'))
    builder.add_object('car', parts)


def _add_curbs(
    builder: SceneBuilder,
    terrain: Terrain,
    path: ClosedPath,
    clearance: _Clearance,
    offset: float,
    height: float = 0.15,
    width: float = 0.3,
) -> None:
    """Curbs on both sides of the road, ``offset`` [m] from the centre line, cut where another branch of
    the road passes (crossings); each continuous run is one 'curb' object."""
    n = max(16, int(path.length / 1.0))
    s = np.arange(n) * (path.length / n)
    xy = path.xy(s)
    tangent = path.tangent(s)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    for side in (1.0, -1.0):
        inner = xy + side * offset * normal
        outer = xy + side * (offset + width) * normal
        keep = (clearance.distance(inner) > offset - 0.25) & (clearance.distance(outer) > offset - 0.25)
        if not keep.any():
            continue
        # Runs of kept samples (cyclic).
        if keep.all():
            runs = [np.append(np.arange(n), 0)]
        else:
            start = int(np.flatnonzero(~keep)[0])
            order = np.roll(np.arange(n), -start)
            runs, current = [], []
            for i in order:
                if keep[i]:
                    current.append(i)
                elif current:
                    runs.append(np.array(current))
                    current = []
            if current:
                runs.append(np.array(current))
        for run in runs:
            if len(run) < 3:
                continue
            zi = terrain.height(inner[run, 0], inner[run, 1])
            zo = terrain.height(outer[run, 0], outer[run, 1])
            top = np.maximum(zi, zo) + height
            vertices = np.concatenate(
                [
                    np.column_stack([inner[run], zi - 0.05]),
                    np.column_stack([inner[run], top]),
                    np.column_stack([outer[run], top]),
                    np.column_stack([outer[run], zo - 0.05]),
                ]
            )
            m = len(run)
            i = np.arange(m - 1)
            faces = []
            for lower, upper in ((0, 1), (1, 2), (2, 3)):
                a, b = lower * m + i, upper * m + i
                faces += [np.stack([a, a + 1, b + 1], 1), np.stack([a, b + 1, b], 1)]
            builder.add_object('curb', [(vertices, np.vstack(faces), 'concrete')])


def _ground(
    builder: SceneBuilder,
    terrain: Terrain,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    spacing: float,
    material_of: Callable[[np.ndarray], np.ndarray],
) -> None:
    """The terrain mesh, labelled ground, with per-triangle materials from the triangle centroids."""
    vertices, triangles = heightfield_mesh(terrain, x_range, y_range, spacing)
    centroids = vertices[triangles].mean(axis=1)[:, :2]
    builder.add(vertices, triangles, material_of(centroids), GROUND_ID)


def _extent(points: np.ndarray, margin: float) -> tuple[tuple[float, float], tuple[float, float]]:
    lo = np.floor(points.min(axis=0) - margin)
    hi = np.ceil(points.max(axis=0) + margin)
    return (float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1]))


# --------------------------------------------------------------------------------------- urban worlds


def _urban_scene(
    path: ClosedPath,
    terrain: Terrain,
    rng: np.random.Generator,
    road_half_width: float = 4.5,
    ground_margin: float = 90.0,
    building_rows: int = 2,
) -> Scene:
    """Road along the path with curbs and sidewalks, then cars, poles, trees, buildings, bushes."""
    builder = SceneBuilder()
    clearance = _Clearance(path)
    polyline = path.polyline(0.5)
    x_range, y_range = _extent(polyline, ground_margin)
    occupancy = _Occupancy(x_range, y_range)
    sidewalk = road_half_width + 2.6

    asphalt, concrete, grass = (material_index(m) for m in ('asphalt', 'concrete', 'grass'))

    def ground_material(centroids: np.ndarray) -> np.ndarray:
        d = clearance.distance(centroids)
        return np.where(d < road_half_width, asphalt, np.where(d < sidewalk, concrete, grass)).astype(np.uint8)

    _ground(builder, terrain, x_range, y_range, 1.0, ground_material)
    _add_curbs(builder, terrain, path, clearance, road_half_width)
    # Keep the road and the sidewalks clear of objects.
    tangent = path.tangent(np.linspace(0.0, path.length, len(polyline), endpoint=False))
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    for offset in np.arange(-sidewalk + 0.5, sidewalk, 0.5):
        occupancy.mark(polyline + offset * normal)

    length = path.length
    # Parked cars along straight stretches, in the parking lane.
    for s in np.arange(0.0, length, 6.5):
        curvature = abs(float(path.curvature(np.array([s]))[0]))
        if curvature > 1.0 / 40.0 or rng.random() > 0.6:
            continue
        side = rng.choice([-1.0, 1.0])
        tangent = path.tangent(np.array([s]))[0]
        normal = np.array([-tangent[1], tangent[0]])
        xy = path.xy(np.array([s]))[0] + side * (road_half_width - 1.25) * normal
        footprint = _rectangle_samples(xy, math.atan2(tangent[1], tangent[0]), 5.0, 2.0)
        if clearance.distance(footprint).min() < road_half_width - 2.3:
            continue
        _add_car(
            builder, terrain, xy, math.atan2(tangent[1], tangent[0]) + (0.0 if rng.random() < 0.5 else math.pi), rng
        )
    # Lamp poles on the sidewalks, alternating sides; some carry a retro-reflective sign.
    for k, s in enumerate(np.arange(5.0, length, 27.0)):
        side = 1.0 if k % 2 == 0 else -1.0
        tangent = path.tangent(np.array([s]))[0]
        normal = np.array([-tangent[1], tangent[0]])
        xy = path.xy(np.array([s]))[0] + side * (road_half_width + 1.0) * normal
        if clearance.distance(xy)[0] < road_half_width + 0.8:
            continue
        facing = math.atan2(-tangent[1], -tangent[0])  # towards oncoming traffic
        _add_pole(builder, terrain, xy, facing, sign=rng.random() < 0.35)
    # Trees lining the road just behind the sidewalks.
    for side in (1.0, -1.0):
        s = rng.uniform(0.0, 8.0)
        while s < length:
            tangent = path.tangent(np.array([s]))[0]
            normal = np.array([-tangent[1], tangent[0]])
            xy = path.xy(np.array([s]))[0] + side * (sidewalk + 1.5 + rng.uniform(-0.4, 0.8)) * normal
            disc = _disc_samples(xy, 0.6)
            if rng.random() < 0.75 and clearance.distance(disc).min() > sidewalk and occupancy.free(disc):
                occupancy.mark(_disc_samples(xy, 2.0))
                _add_tree(
                    builder,
                    terrain,
                    xy,
                    rng,
                    conifer=rng.random() < 0.2,
                    trunk_radius=rng.uniform(0.14, 0.3),
                    height=rng.uniform(3.0, 5.5),
                    crown_radius=rng.uniform(1.8, 3.2),
                )
            s += rng.uniform(9.0, 15.0)
    # Buildings in rows behind the trees.
    for row in range(building_rows):
        for side in (1.0, -1.0):
            s = rng.uniform(0.0, 20.0)
            while s < length:
                bl, bw = rng.uniform(14.0, 36.0), rng.uniform(9.0, 18.0)
                tangent = path.tangent(np.array([s]))[0]
                normal = np.array([-tangent[1], tangent[0]])
                yaw = math.atan2(tangent[1], tangent[0])
                distance = 13.0 + row * 26.0 + 0.5 * bw + rng.uniform(0.0, 6.0)
                center = path.xy(np.array([s]))[0] + side * distance * normal
                wing = None
                if rng.random() < 0.35:
                    wing = (rng.uniform(8.0, 16.0), rng.uniform(7.0, 11.0), rng.choice([-1.0, 1.0]) * (0.5 * bl - 4.0))
                samples = _rectangle_samples(center, yaw, bl, bw, margin=2.0)
                if wing is not None:
                    c, sn = math.cos(yaw), math.sin(yaw)
                    wc = center + np.array([c, sn]) * wing[2] + np.array([-sn, c]) * (0.5 * bw + 0.5 * wing[0] - 0.5)
                    samples = np.vstack(
                        [samples, _rectangle_samples(wc, yaw + 0.5 * math.pi, wing[0], wing[1], margin=2.0)]
                    )
                if clearance.distance(samples).min() > 11.0 and occupancy.free(samples):
                    occupancy.mark(samples)
                    _add_building(
                        builder,
                        terrain,
                        center,
                        yaw,
                        bl,
                        bw,
                        rng.uniform(6.0, 18.0),
                        str(rng.choice(['plaster', 'brick', 'concrete'])),
                        rng,
                        wing,
                    )
                    s += bl + rng.uniform(4.0, 14.0)
                else:
                    s += 4.0  # no room here: try a little further on
    # Trees scattered over the lawns, and bushes (unlabeled clutter).
    for _ in range(int(length * 0.5)):
        xy = np.array([rng.uniform(*x_range), rng.uniform(*y_range)])
        disc = _disc_samples(xy, 1.5)
        d = clearance.distance(disc).min()
        if 9.0 < d < 60.0 and occupancy.free(disc):
            occupancy.mark(disc)
            _add_tree(
                builder,
                terrain,
                xy,
                rng,
                conifer=rng.random() < 0.3,
                trunk_radius=rng.uniform(0.12, 0.35),
                height=rng.uniform(3.0, 6.0),
                crown_radius=rng.uniform(1.5, 3.5),
            )
    for _ in range(int(length * 0.8)):
        xy = np.array([rng.uniform(*x_range), rng.uniform(*y_range)])
        disc = _disc_samples(xy, 0.8)
        if sidewalk + 0.5 < clearance.distance(disc).min() < 40.0 and occupancy.free(disc):
            occupancy.mark(disc)
            radius = rng.uniform(0.35, 0.9)
            v, f = ellipsoid_mesh(
                (radius * rng.uniform(0.9, 1.6), radius, radius * rng.uniform(0.6, 0.9)), 1, roughness=0.25, rng=rng
            )
            z = float(terrain.height(xy[0], xy[1]))
            builder.add_clutter(
                transform_mesh(v, rng.uniform(0, 2 * math.pi), (xy[0], xy[1], z + 0.3 * radius)), f, 'foliage'
            )
    return builder.build()


def _turtle_path(start_heading: float, commands: list[tuple], step: float = 3.0) -> np.ndarray:
    """Waypoints of straight ('S', length) and arc ('A', radius, degrees; + left) pieces, closed by
    spreading the end-point mismatch linearly along the way."""
    points = [np.zeros(2)]
    heading = start_heading
    position = np.zeros(2)
    for command in commands:
        if command[0] == 'S':
            n = max(1, int(round(command[1] / step)))
            for _ in range(n):
                position = position + command[1] / n * np.array([math.cos(heading), math.sin(heading)])
                points.append(position)
        else:
            radius, angle = command[1], math.radians(command[2])
            n = max(2, int(round(abs(angle) * radius / step)))
            for _ in range(n):
                dtheta = angle / n
                chord = 2.0 * radius * math.sin(abs(dtheta) / 2.0)
                heading_mid = heading + dtheta / 2.0
                position = position + chord * np.array([math.cos(heading_mid), math.sin(heading_mid)])
                heading += dtheta
                points.append(position)
    points = np.array(points)
    mismatch = points[-1] - points[0]
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    points = points - mismatch * (travelled / travelled[-1])[:, None]
    return points[:-1]


# The campus loop: a ~430 m circuit around a central quad (waypoints in metres, anticlockwise).
_CAMPUS_WAYPOINTS = np.array(
    [
        (-20.0, -37.0),
        (20.0, -34.0),
        (55.0, -36.0),
        (70.0, -27.0),
        (74.0, -5.0),
        (72.0, 14.0),
        (64.0, 31.0),
        (40.0, 37.0),
        (18.0, 34.0),
        (0.0, 26.0),
        (-18.0, 34.0),
        (-45.0, 38.0),
        (-66.0, 32.0),
        (-74.0, 12.0),
        (-73.0, -14.0),
        (-62.0, -33.0),
        (-42.0, -38.0),
    ]
)

# The aggressive circuit: long straights, hairpins and a chicane (total turning +360 deg).
_AGGRESSIVE_COMMANDS = [
    ('S', 70.0),
    ('A', 4.0, 180.0),
    ('S', 22.0),
    ('A', 4.5, -90.0),
    ('A', 4.5, 90.0),
    ('S', 16.0),
    ('A', 9.0, 90.0),
    ('S', 16.0),
    ('A', 4.0, -180.0),
    ('S', 18.0),
    ('A', 4.0, 180.0),
    ('S', 20.0),
    ('A', 10.0, 90.0),
    ('S', 6.0),
]


def _build_campus(seed: int) -> World:
    path = ClosedPath(_CAMPUS_WAYPOINTS)
    terrain_rng = scenario_rng(0, 'campus-terrain')  # the same ground for every seed
    terrain = Terrain.random(terrain_rng, [(1.6, 140.0), (0.5, 50.0)], slope=(0.012, -0.006))
    scene = _urban_scene(path, terrain, scenario_rng(seed, 'campus-scene'))
    speed = SpeedProfile(path, cruise_speed=1.7, max_lateral_acceleration=0.35, smoothing=8.0)
    trajectory = PathTrajectory(path, speed, terrain, sensor_height=1.8, wheelbase=2.7, track=1.6)
    return World(
        'campus',
        seed,
        scene,
        trajectory,
        _whole_scans(speed.lap_time),
        SCENARIOS['campus'].description,
        _facts(path, speed, trajectory),
    )


def _build_aggressive(seed: int) -> World:
    path = ClosedPath(_turtle_path(0.0, _AGGRESSIVE_COMMANDS))
    terrain = Terrain.random(scenario_rng(0, 'aggressive-terrain'), [(1.0, 120.0), (0.3, 40.0)])
    scene = _urban_scene(
        path, terrain, scenario_rng(seed, 'aggressive-scene'), road_half_width=5.0, ground_margin=90.0, building_rows=2
    )
    # Start on the straight before the right-hand hairpin: the 90 deg/s peak comes about 2 s in, so even a short
    # recording holds the hardest turn.
    speed = _speed_for_peak_yaw_rate(
        path, cruise_speed=8.0, peak_yaw_rate=math.radians(90.0), smoothing=6.0, start=152.0
    )
    trajectory = PathTrajectory(path, speed, terrain, sensor_height=1.6, wheelbase=2.6, track=1.6)
    return World(
        'aggressive',
        seed,
        scene,
        trajectory,
        _whole_scans(speed.lap_time),
        SCENARIOS['aggressive'].description,
        _facts(path, speed, trajectory),
    )


# The straight: a 480 m street and back, joined by two hairpins; a recording of up to 50 s from the start drives
# straight on (roll and pitch from the road's undulations, under 1 deg/s).
_STRAIGHT_COMMANDS = [('S', 480.0), ('A', 10.0, 180.0), ('S', 480.0), ('A', 10.0, 180.0)]


def _build_straight(seed: int) -> World:
    path = ClosedPath(_turtle_path(0.0, _STRAIGHT_COMMANDS))
    terrain = Terrain.random(scenario_rng(0, 'straight-terrain'), [(0.8, 120.0), (0.2, 40.0)])
    scene = _urban_scene(
        path, terrain, scenario_rng(seed, 'straight-scene'), road_half_width=5.0, ground_margin=60.0, building_rows=1
    )
    speed = SpeedProfile(path, cruise_speed=8.0, max_lateral_acceleration=3.0, smoothing=10.0, start=10.0)
    trajectory = PathTrajectory(path, speed, terrain, sensor_height=1.8, wheelbase=2.7, track=1.6)
    return World(
        'straight',
        seed,
        scene,
        trajectory,
        _whole_scans(speed.lap_time),
        SCENARIOS['straight'].description,
        _facts(path, speed, trajectory),
    )


def _speed_for_peak_yaw_rate(
    path: ClosedPath, cruise_speed: float, peak_yaw_rate: float, smoothing: float, start: float
) -> SpeedProfile:
    """Speed profile whose lateral-acceleration limit makes the largest yaw rate ``peak_yaw_rate``
    [rad/s] (bisection on the limit)."""
    s = np.linspace(0.0, path.length, 6000, endpoint=False)
    curvature = np.abs(path.curvature(s))

    def peak(limit: float) -> tuple[float, SpeedProfile]:
        profile = SpeedProfile(path, cruise_speed, limit, smoothing, start)
        t = np.linspace(0.0, profile.lap_time, 20000, endpoint=False)
        ds = np.gradient(profile(t), t)
        k = np.interp(np.mod(profile(t), path.length), s, curvature, period=path.length)
        return float(np.max(ds * k)), profile

    lo, hi = 0.5, 30.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if peak(mid)[0] > peak_yaw_rate:
            hi = mid
        else:
            lo = mid
    return peak(lo)[1]


# ------------------------------------------------------------------------------------------------ forest


def _build_forest(seed: int) -> World:
    theta = np.linspace(0.0, 2.0 * math.pi, 28, endpoint=False)
    radius = 36.0 + 7.0 * np.sin(3.0 * theta + 0.7) + 3.5 * np.sin(7.0 * theta + 1.9)
    path = ClosedPath(np.column_stack([radius * np.cos(theta), 0.8 * radius * np.sin(theta)]))
    terrain = Terrain.random(scenario_rng(0, 'forest-terrain'), [(3.0, 90.0), (0.9, 24.0), (0.3, 7.0), (0.05, 3.5)])
    rng = scenario_rng(seed, 'forest-scene')
    builder = SceneBuilder()
    clearance = _Clearance(path)
    polyline = path.polyline(0.5)
    x_range, y_range = _extent(polyline, 75.0)
    soil, litter = material_index('soil'), material_index('leaf_litter')

    def ground_material(centroids: np.ndarray) -> np.ndarray:
        return np.where(clearance.distance(centroids) < 1.2, soil, litter).astype(np.uint8)

    _ground(builder, terrain, x_range, y_range, 0.75, ground_material)
    # Trunks: Poisson-disc-like thinning of uniform candidates, none on the trail.
    area = (x_range[1] - x_range[0]) * (y_range[1] - y_range[0])
    candidates = np.column_stack([rng.uniform(*x_range, int(area * 0.09)), rng.uniform(*y_range, int(area * 0.09))])
    d = clearance.distance(candidates)
    candidates = candidates[(d > 2.2) & (d < 70.0)]
    keep = np.ones(len(candidates), dtype=bool)
    for i, j in sorted(cKDTree(candidates).query_pairs(2.2)):
        if keep[i] and keep[j]:
            keep[j] = False
    occupancy = _Occupancy(x_range, y_range)
    for xy in candidates[keep]:
        trunk = float(np.clip(rng.lognormal(math.log(0.2), 0.4), 0.08, 0.55))
        conifer = rng.random() < 0.55
        height = rng.uniform(10.0, 22.0)
        _add_tree(
            builder,
            terrain,
            xy,
            rng,
            conifer,
            trunk,
            height,
            crown_radius=rng.uniform(1.5, 3.0) if conifer else rng.uniform(2.5, 4.5),
            crown_base=rng.uniform(4.0, 7.0) if conifer else None,
            segments=10,
        )
        occupancy.mark(_disc_samples(xy, trunk + 0.5))
    # Fallen logs and boulders (labelled objects), bushes (clutter).
    for _ in range(int(path.length * 0.25)):
        xy = np.array([rng.uniform(*x_range), rng.uniform(*y_range)])
        length = rng.uniform(3.0, 8.0)
        yaw = rng.uniform(0.0, math.pi)
        samples = _rectangle_samples(xy, yaw, length, 1.0)
        if clearance.distance(samples).min() > 1.8 and occupancy.free(samples):
            occupancy.mark(samples)
            r = rng.uniform(0.15, 0.35)
            v, f = cylinder_mesh(r, length, 10)
            v = v[:, [2, 1, 0]] - [0.5 * length, 0.0, 0.0]  # axis along x
            z = float(terrain.height(xy[0], xy[1])) + 0.6 * r
            builder.add_object(
                'log', [(transform_mesh(v, yaw, (xy[0], xy[1], z), roll=0.0, pitch=rng.normal(0, 0.05)), f, 'bark')]
            )
    for _ in range(int(path.length * 0.3)):
        xy = np.array([rng.uniform(*x_range), rng.uniform(*y_range)])
        radius = rng.uniform(0.3, 1.1)
        disc = _disc_samples(xy, radius + 0.3)
        if clearance.distance(disc).min() > 1.5 and occupancy.free(disc):
            occupancy.mark(disc)
            v, f = ellipsoid_mesh(
                (radius * rng.uniform(1.0, 1.6), radius, radius * rng.uniform(0.5, 0.8)), 1, roughness=0.2, rng=rng
            )
            z = float(terrain.height(xy[0], xy[1]))
            builder.add_object('rock', [(transform_mesh(v, rng.uniform(0, 2 * math.pi), (xy[0], xy[1], z)), f, 'rock')])
    for _ in range(int(path.length * 3.0)):
        xy = np.array([rng.uniform(*x_range), rng.uniform(*y_range)])
        radius = rng.uniform(0.25, 0.8)
        disc = _disc_samples(xy, radius)
        if clearance.distance(disc).min() > 1.3 and occupancy.free(disc):
            v, f = ellipsoid_mesh(
                (radius * rng.uniform(0.9, 1.5), radius, radius * rng.uniform(0.6, 1.0)), 1, roughness=0.3, rng=rng
            )
            z = float(terrain.height(xy[0], xy[1]))
            builder.add_clutter(
                transform_mesh(v, rng.uniform(0, 2 * math.pi), (xy[0], xy[1], z + 0.2 * radius)), f, 'foliage'
            )
    scene = builder.build()
    speed = SpeedProfile(path, cruise_speed=1.3, max_lateral_acceleration=0.3, smoothing=5.0)
    trajectory = PathTrajectory(
        path,
        speed,
        terrain,
        sensor_height=0.75,
        wheelbase=0.55,
        track=0.55,
        oscillations=[Oscillation('roll', math.radians(0.3), 2.3), Oscillation('pitch', math.radians(0.3), 3.1, 1.0)],
    )
    return World(
        'forest',
        seed,
        scene,
        trajectory,
        _whole_scans(speed.lap_time),
        SCENARIOS['forest'].description,
        _facts(path, speed, trajectory),
    )


# ---------------------------------------------------------------------------------------------- corridor

_CORRIDOR_HALF = (28.0, 13.0)  # centre line of the corridor loop: rectangle half-extents [m]
_CORRIDOR_HALF_WIDTH = 1.3  # [m]
_CEILING = 2.8  # [m]


def _rounded_rectangle(half_x: float, half_y: float, radius: float, step: float = 1.0) -> np.ndarray:
    """Points on a rounded rectangle, anticlockwise from the middle of the bottom side."""
    pts = []
    corners = [
        (half_x - radius, -half_y + radius, -0.5 * math.pi),
        (half_x - radius, half_y - radius, 0.0),
        (-half_x + radius, half_y - radius, 0.5 * math.pi),
        (-half_x + radius, -half_y + radius, math.pi),
    ]
    start = np.array([0.0, -half_y])
    for cx, cy, a0 in corners:
        corner_start = np.array([cx + radius * math.cos(a0), cy + radius * math.sin(a0)])
        n = max(1, int(np.linalg.norm(corner_start - start) / step))
        pts += [start + (corner_start - start) * k / n for k in range(n)]
        m = max(3, int(0.5 * math.pi * radius / (0.5 * step)))
        pts += [
            np.array(
                [cx + radius * math.cos(a0 + 0.5 * math.pi * k / m), cy + radius * math.sin(a0 + 0.5 * math.pi * k / m)]
            )
            for k in range(m)
        ]
        start = np.array([cx + radius * math.cos(a0 + 0.5 * math.pi), cy + radius * math.sin(a0 + 0.5 * math.pi)])
    end = np.array([0.0, -half_y])
    n = max(1, int(np.linalg.norm(end - start) / step))
    pts += [start + (end - start) * k / n for k in range(n)]
    return np.array(pts)


def _wall_segments(a: float, b: float, gaps: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The parts of the interval [a, b] outside the gaps."""
    out, cursor = [], a
    for g0, g1 in sorted(gaps):
        if g0 > cursor:
            out.append((cursor, g0))
        cursor = max(cursor, g1)
    if cursor < b:
        out.append((cursor, b))
    return [(u, v) for u, v in out if v - u > 0.05]


def _build_corridor(seed: int) -> World:
    rng = scenario_rng(seed, 'corridor-scene')
    hx, hy = _CORRIDOR_HALF
    w = _CORRIDOR_HALF_WIDTH
    builder = SceneBuilder()
    flat = Terrain()
    room_depth = 5.0
    extent_x, extent_y = (
        (-hx - w - room_depth - 2.0, hx + w + room_depth + 2.0),
        (-hy - w - room_depth - 2.0, hy + w + room_depth + 2.0),
    )
    builder.add(*heightfield_mesh(flat, extent_x, extent_y, 1.0), 'floor_tiles', GROUND_ID)
    ceiling_v, ceiling_f = box_mesh((extent_x[1] - extent_x[0], extent_y[1] - extent_y[0], 0.2))
    builder.add_object('ceiling', [(transform_mesh(ceiling_v, 0.0, (0.0, 0.0, _CEILING)), ceiling_f, 'ceiling')])

    thickness = 0.2

    def wall(x0: float, y0: float, x1: float, y1: float, material: str = 'painted_wall') -> None:
        """A wall slab along the segment (x0, y0)-(x1, y1), its own object."""
        length = math.hypot(x1 - x0, y1 - y0)
        v, f = box_mesh((length, thickness, _CEILING + 0.1))
        builder.add_object(
            'wall',
            [(transform_mesh(v, math.atan2(y1 - y0, x1 - x0), (0.5 * (x0 + x1), 0.5 * (y0 + y1), -0.05)), f, material)],
        )

    # Sides of the loop: (start corner, direction, length, outward normal) for the inner and outer walls.
    for inner in (True, False):
        ex, ey = (
            (hx - w - 0.5 * thickness, hy - w - 0.5 * thickness)
            if inner
            else (hx + w + 0.5 * thickness, hy + w + 0.5 * thickness)
        )
        sides = [
            ((-ex, -ey), (1.0, 0.0), 2 * ex, (0.0, -1.0)),
            ((ex, -ey), (0.0, 1.0), 2 * ey, (1.0, 0.0)),
            ((ex, ey), (-1.0, 0.0), 2 * ex, (0.0, 1.0)),
            ((-ex, ey), (0.0, -1.0), 2 * ey, (-1.0, 0.0)),
        ]
        for (sx, sy), (dx, dy), length, (nx, ny) in sides:
            sign = -1.0 if inner else 1.0  # direction away from the corridor
            # Inner walls get doors; outer walls doors and openings into rooms.
            odds = (0.45, 0.0, 0.55) if inner else (0.45, 0.2, 0.35)
            gaps = []
            u = rng.uniform(3.0, 6.0)
            while u < length - 4.0:
                kind = rng.choice(['door', 'opening', 'none'], p=odds)
                if kind == 'door':
                    gaps.append((u, u + 1.0))
                    # Door panel recessed ~0.1 m behind the corridor-side face of the wall, its own object.
                    v, f = box_mesh((1.0, 0.05, 2.1))
                    cx = sx + dx * (u + 0.5) + sign * nx * 0.02
                    cy = sy + dy * (u + 0.5) + sign * ny * 0.02
                    builder.add_object('door', [(transform_mesh(v, math.atan2(dy, dx), (cx, cy, 0.0)), f, 'wood')])
                    # Lintel above the door.
                    lv, lf = box_mesh((1.0, thickness, _CEILING - 2.1 + 0.1))
                    builder.add_object(
                        'wall',
                        [
                            (
                                transform_mesh(lv, math.atan2(dy, dx), (sx + dx * (u + 0.5), sy + dy * (u + 0.5), 2.1)),
                                lf,
                                'painted_wall',
                            )
                        ],
                    )
                    u += rng.uniform(4.0, 9.0)
                elif kind == 'opening':
                    width = rng.uniform(1.6, 2.4)
                    gaps.append((u, u + width))
                    # A room behind the opening (outer side only): three walls and a table.
                    room_w = width + rng.uniform(2.0, 4.0)
                    c0 = u + 0.5 * width - 0.5 * room_w
                    c1 = c0 + room_w
                    p0 = np.array([sx + dx * c0, sy + dy * c0])
                    p1 = np.array([sx + dx * c1, sy + dy * c1])
                    out = np.array([nx, ny]) * room_depth
                    wall(*p0, *(p0 + out))
                    wall(*p1, *(p1 + out))
                    wall(*(p0 + out), *(p1 + out))
                    table_v, table_f = box_mesh((1.6, 0.8, 0.75))
                    centre = 0.5 * (p0 + p1) + 0.55 * out
                    builder.add_object(
                        'furniture',
                        [
                            (
                                transform_mesh(
                                    table_v, math.atan2(dy, dx) + rng.normal(0, 0.2), (centre[0], centre[1], 0.0)
                                ),
                                table_f,
                                'wood',
                            )
                        ],
                    )
                    u += width + rng.uniform(5.0, 10.0)
                else:
                    u += rng.uniform(3.0, 6.0)
            for a, b in _wall_segments(0.0, length, gaps):
                wall(sx + dx * a, sy + dy * a, sx + dx * b, sy + dy * b)
            if not inner:
                # Pillars along the outer wall, protruding into the corridor, every ~8 m.
                for u in np.arange(4.0, length - 2.0, 8.0):
                    if any(g0 - 0.5 < u < g1 + 0.5 for g0, g1 in gaps):
                        continue
                    v, f = box_mesh((0.5, 0.5, _CEILING + 0.1))
                    cx = sx + dx * u - nx * 0.25
                    cy = sy + dy * u - ny * 0.25
                    builder.add_object('pillar', [(transform_mesh(v, 0.0, (cx, cy, -0.05)), f, 'concrete')])
    # Clutter along the corridor walls: bins and plant pots (unlabeled).
    path_points = _rounded_rectangle(hx, hy, 2.5)
    for _ in range(40):
        k = rng.integers(len(path_points))
        p = path_points[k]
        q = path_points[(k + 1) % len(path_points)]
        t = (q - p) / max(np.linalg.norm(q - p), 1e-9)
        side = rng.choice([-1.0, 1.0])
        xy = p + side * (w - 0.3) * np.array([-t[1], t[0]])
        v, f = cylinder_mesh(rng.uniform(0.15, 0.25), rng.uniform(0.4, 0.9), 10)
        builder.add_clutter(transform_mesh(v, 0.0, (xy[0], xy[1], 0.0)), f, 'metal')
    scene = builder.build()
    path = ClosedPath(path_points)
    speed = SpeedProfile(path, cruise_speed=1.35, max_lateral_acceleration=0.5, smoothing=1.0)
    step = 1.8  # [Hz] step frequency of the walker
    trajectory = PathTrajectory(
        path,
        speed,
        flat,
        sensor_height=1.7,
        wheelbase=0.3,
        track=0.3,
        oscillations=[
            Oscillation('heave', 0.025, step),
            Oscillation('surge', 0.015, step, 0.5),
            Oscillation('sway', 0.02, 0.5 * step),
            Oscillation('roll', math.radians(1.2), 0.5 * step, 0.3),
            Oscillation('pitch', math.radians(0.8), step, 1.1),
            Oscillation('yaw', math.radians(2.0), 0.5 * step, 0.7),
            Oscillation('yaw', math.radians(4.0), 0.07, 0.0),
        ],
    )
    return World(
        'corridor',
        seed,
        scene,
        trajectory,
        _whole_scans(speed.lap_time),
        SCENARIOS['corridor'].description,
        _facts(path, speed, trajectory),
    )


# -------------------------------------------------------------------------------------------- city rows

_ROWS_HALF = (80.0, 25.0)  # centre line of the block loop: rectangle half-extents [m]
_ROWS_PERIOD = 26.0  # identical buildings (and poles, cars) repeat every this along the long streets [m]


def _build_rows(seed: int) -> World:
    """A city block driven around: along both long streets, rows of identical buildings, lamp posts and parked
    cars repeat every :data:`_ROWS_PERIOD` on both sides, so places one period apart (and on the other street,
    seen the other way round) look alike; only the two short streets, lined with trees, tell them apart. The
    drive is a lap and a half: the second half-lap runs over the first, where false loops tempt."""
    hx, hy = _ROWS_HALF
    path = ClosedPath(_rounded_rectangle(hx, hy, 12.0, step=2.0))
    terrain = Terrain()
    rng = scenario_rng(seed, 'rows-scene')
    builder = SceneBuilder()
    clearance = _Clearance(path)
    polyline = path.polyline(0.5)
    x_range, y_range = _extent(polyline, 70.0)
    road, sidewalk = 4.5, 7.1
    asphalt, concrete, grass = (material_index(m) for m in ('asphalt', 'concrete', 'grass'))

    def ground_material(centroids: np.ndarray) -> np.ndarray:
        d = clearance.distance(centroids)
        return np.where(d < road, asphalt, np.where(d < sidewalk, concrete, grass)).astype(np.uint8)

    _ground(builder, terrain, x_range, y_range, 1.0, ground_material)
    _add_curbs(builder, terrain, path, clearance, road)
    slots = np.arange(-hx + 14.0, hx - 13.0, _ROWS_PERIOD)
    for street_y in (-hy, hy):
        for side in (-1.0, 1.0):
            for x in slots:  # the same building, pole and car (same random draws) in every slot
                _add_building(
                    builder,
                    terrain,
                    np.array([x, street_y + side * 18.0]),
                    0.0,
                    20.0,
                    10.0,
                    12.0,
                    'concrete',
                    scenario_rng(0, 'rows-building'),
                )
                _add_pole(
                    builder,
                    terrain,
                    np.array([x + 0.5 * _ROWS_PERIOD, street_y + side * (road + 1.0)]),
                    0.5 * math.pi * (1.0 - side),
                    sign=False,
                )
                if side > 0:
                    _add_car(
                        builder,
                        terrain,
                        np.array([x, street_y + side * (road - 1.25)]),
                        0.0,
                        scenario_rng(0, 'rows-car'),
                    )
    # The short streets: trees of random sizes and places, the only thing that tells the two ends apart.
    for end_x in (-hx, hx):
        for _ in range(14):
            xy = np.array([end_x + np.sign(end_x) * rng.uniform(sidewalk + 1.0, 30.0), rng.uniform(-hy - 20, hy + 20)])
            if clearance.distance(_disc_samples(xy, 1.5)).min() > sidewalk:
                _add_tree(
                    builder,
                    terrain,
                    xy,
                    rng,
                    conifer=rng.random() < 0.3,
                    trunk_radius=rng.uniform(0.15, 0.3),
                    height=rng.uniform(3.0, 6.0),
                    crown_radius=rng.uniform(1.5, 3.0),
                )
    scene = builder.build()
    speed = SpeedProfile(path, cruise_speed=3.0, max_lateral_acceleration=0.6, smoothing=6.0)
    trajectory = PathTrajectory(path, speed, terrain, sensor_height=1.8, wheelbase=2.7, track=1.6)
    return World(
        'rows',
        seed,
        scene,
        trajectory,
        _whole_scans(1.5 * speed.lap_time),
        SCENARIOS['rows'].description,
        _facts(path, speed, trajectory),
    )


# ------------------------------------------------------------------------------------------------ open road


def _build_open_road(
    seed: int, name: str = 'open_road', straight: float = 250.0, radius: float = 30.0, field_trees: int = 100
) -> World:
    """A 690 m stadium-shaped road across open fields driven at 8 m/s: two 250 m straights with nothing beside
    them but a lamp post every 45 m and trees scattered over the fields, so the mapping has little to hold the
    motion along the road and drifts; a cluster of buildings, cars and trees around the start, where the loop closes.
    The keyword arguments give other sizes of it, with the same lamp posts and speed (``long_road``)."""
    waypoints = [(x, -radius) for x in np.arange(0.0, straight, 10.0)]
    waypoints += [(straight + radius * math.sin(a), -radius * math.cos(a)) for a in np.linspace(0.0, math.pi, 13)[1:-1]]
    waypoints += [(x, radius) for x in np.arange(straight, 0.0, -10.0)]
    waypoints += [(-radius * math.sin(a), radius * math.cos(a)) for a in np.linspace(0.0, math.pi, 13)[1:-1]]
    path = ClosedPath(np.array(waypoints) - [0.5 * straight, 0.0])
    terrain = Terrain.random(scenario_rng(0, 'open-road-terrain'), [(1.0, 150.0), (0.3, 60.0)])
    rng = scenario_rng(seed, 'open-road-scene')
    builder = SceneBuilder()
    clearance = _Clearance(path)
    x_range, y_range = _extent(path.polyline(0.5), 70.0)
    asphalt, grass = material_index('asphalt'), material_index('grass')
    _ground(
        builder,
        terrain,
        x_range,
        y_range,
        1.5,
        lambda c: np.where(clearance.distance(c) < 4.0, asphalt, grass).astype(np.uint8),
    )
    start = path.xy(np.array([0.0]))[0]
    for k, s in enumerate(np.arange(10.0, path.length, 45.0)):
        tangent = path.tangent(np.array([s]))[0]
        normal = np.array([-tangent[1], tangent[0]])
        side = 1.0 if k % 2 == 0 else -1.0
        _add_pole(builder, terrain, path.xy(np.array([s]))[0] + side * 5.5 * normal, 0.0, sign=False)
    for _ in range(field_trees):  # scattered trees in the fields
        xy = np.array([rng.uniform(*x_range), rng.uniform(*y_range)])
        if clearance.distance(_disc_samples(xy, 2.0)).min() > 8.0:
            _add_tree(
                builder,
                terrain,
                xy,
                rng,
                conifer=rng.random() < 0.3,
                trunk_radius=rng.uniform(0.15, 0.35),
                height=rng.uniform(4.0, 8.0),
                crown_radius=rng.uniform(2.0, 3.5),
            )
    # The start: buildings, parked cars and trees within 40 m (what the loop closure recognises).
    for dx, dy, yaw, length, width, height in (
        (-15.0, -50.0, 0.0, 24.0, 12.0, 9.0),
        (18.0, -48.0, 0.3, 16.0, 10.0, 6.0),
        (2.0, -12.0, 0.0, 30.0, 10.0, 12.0),
        (-25.0, -14.0, 0.1, 12.0, 8.0, 5.0),
    ):
        _add_building(builder, terrain, start + [dx, dy], yaw, length, width, height, 'brick', rng)
    for dx in (-20.0, -13.0, 4.0, 15.0):
        _add_car(builder, terrain, start + [dx, -3.0 + 0.5 * rng.uniform(-1, 1)], 0.0, rng)
    for _ in range(12):
        xy = start + rng.uniform([-40.0, -40.0], [40.0, 40.0])
        if clearance.distance(_disc_samples(xy, 2.0)).min() > 6.0:
            _add_tree(
                builder,
                terrain,
                xy,
                rng,
                conifer=rng.random() < 0.3,
                trunk_radius=rng.uniform(0.15, 0.3),
                height=rng.uniform(3.0, 6.0),
                crown_radius=rng.uniform(1.5, 3.0),
            )
    scene = builder.build()
    speed = SpeedProfile(path, cruise_speed=8.0, max_lateral_acceleration=2.0, smoothing=10.0)
    trajectory = PathTrajectory(path, speed, terrain, sensor_height=1.8, wheelbase=2.7, track=1.6)
    return World(
        name,
        seed,
        scene,
        trajectory,
        _whole_scans(speed.lap_time + 10.0),
        SCENARIOS[name].description,
        _facts(path, speed, trajectory),
    )


def _build_long_road(seed: int) -> World:
    """``open_road`` with 500 m straights (a 1.25 km lap, the same density of lamp posts and field trees), so that
    the drift before the loop closes at the start exceeds a metre (seed 0: the graph's relative pose of the first
    loop 1.4 m off the truth without the IMU, 0.8 m with it; benchmarks/loop_closure.py)."""
    return _build_open_road(seed, 'long_road', straight=500.0, radius=40.0, field_trees=200)


# ------------------------------------------------------------------------------------------------- registry


def _whole_scans(seconds: float, scan_period: float = 0.1) -> float:
    """``seconds`` rounded up to whole sweeps, plus one sweep so that the last sweep start reaches it."""
    return round((math.ceil(seconds / scan_period - 1e-9) + 1) * scan_period, 6)


def _facts(path: ClosedPath, speed: SpeedProfile, trajectory: PathTrajectory) -> dict:
    t = np.linspace(0.0, speed.lap_time, 4000, endpoint=False)
    yaw_rate = trajectory.angular_velocity(t)
    velocity = np.linalg.norm(trajectory.velocity(t), axis=1)
    return dict(
        path_length_m=round(path.length, 3),
        lap_time_s=round(speed.lap_time, 3),
        mean_speed_mps=round(float(velocity.mean()), 3),
        max_speed_mps=round(float(velocity.max()), 3),
        max_yaw_rate_deg_s=round(float(np.degrees(np.abs(yaw_rate[:, 2]).max())), 2),
        loop=trajectory.lap_time is not None,
    )


@dataclass(frozen=True)
class ScenarioInfo:
    name: str
    description: str
    build: Callable[[int], World]


SCENARIOS: dict[str, ScenarioInfo] = {
    'campus': ScenarioInfo(
        'campus',
        'outdoor campus loop (~400 m, returns to its start): buildings, trees, poles, '
        'parked cars, curbs, gentle slopes; car-mounted lidar at 1.8 m, ~1.7 m/s',
        _build_campus,
    ),
    'forest': ScenarioInfo(
        'forest',
        'forest trail loop (~240 m) on uneven terrain: dense trunks, crowns, bushes, '
        'logs, boulders, few planes; small robot (lidar at 0.75 m) rolling and pitching, '
        '~1.3 m/s',
        _build_forest,
    ),
    'corridor': ScenarioInfo(
        'corridor',
        'indoor corridor loop (~160 m around a 60 x 30 m floor): walls, ceiling, doors, pillars, '
        'side rooms; handheld lidar at 1.7 m, walking with bob and sway, ~1.3 m/s',
        _build_corridor,
    ),
    'aggressive': ScenarioInfo(
        'aggressive',
        'campus-like circuit driven hard: 8 m/s straights, hairpins and a '
        'chicane, yaw rates up to 90 deg/s: deskewing matters',
        _build_aggressive,
    ),
    'rows': ScenarioInfo(
        'rows',
        'city block loop (~400 m, a lap and a half) between rows of identical buildings, '
        'lamp posts and parked cars repeating every 26 m: places that look alike tempt false '
        'loops; car-mounted lidar at 1.8 m, ~3 m/s',
        _build_rows,
    ),
    'open_road': ScenarioInfo(
        'open_road',
        'stadium-shaped road (~690 m, a lap and 10 s) across open fields at 8 m/s: '
        'little beside the straights but sparse lamp posts and trees, so the mapping drifts '
        'along them; buildings and cars around the start, where the loop closes',
        _build_open_road,
    ),
    'long_road': ScenarioInfo(
        'long_road',
        'open_road with 500 m straights (~1.25 km, a lap and 10 s, at 8 m/s): '
        'the mapping drifts about a metre (more without IMU) before the loop closes at the built-up start',
        _build_long_road,
    ),
    'straight': ScenarioInfo(
        'straight',
        'a 480 m street driven straight at 8 m/s and back (hairpins at the ends); '
        'its first 50 s have no turn at all: a drive that cannot show how an IMU is mounted',
        _build_straight,
    ),
}


def scenario_names() -> list[str]:
    return list(SCENARIOS)


#: Base times [s] of the in-place turns ``turn_rate`` inserts: on the first straight of every scenario,
#: then every 30 s.
TURN_FIRST, TURN_EVERY = 10.0, 30.0


@functools.lru_cache(maxsize=4)
def build_world(
    name: str, seed: int = 0, turn_rate: float = 0.0, route_start: float | None = None, reverse: bool = False
) -> World:
    """The scenario ``name`` built with ``seed`` (cached: worlds are immutable). ``turn_rate`` > 0 [deg/s]
    stops the platform for a whole in-place turn, alternately left and right, with that peak yaw rate
    at :data:`TURN_FIRST` s and every :data:`TURN_EVERY` s of the lap after it.

    ``route_start`` [m of arc length along the scenario's path, in its own direction] and ``reverse`` drive
    another route through the same scene (the scenery is built from the path, never from the route): from
    another start, and with ``reverse`` the other way round. The default route is the scenario's own."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario '{name}' (known: {', '.join(SCENARIOS)})")
    world = SCENARIOS[name].build(int(seed))
    if route_start is not None or reverse:
        base = world.trajectory
        trajectory = base.on_route(route_start, reverse)
        start = base.speed.start if route_start is None else float(route_start) % base.path.length
        route = f'from {start:.1f} m along the path' + (', driven the other way' if reverse else '')
        world = World(
            name,
            world.seed,
            world.scene,
            trajectory,
            _whole_scans(trajectory.speed.lap_time + world.default_duration - base.speed.lap_time),
            f'{world.description}; route {route}',
            dict(
                _facts(trajectory.path, trajectory.speed, trajectory),
                route_start_m=round(start, 3),
                reverse=bool(reverse),
            ),
        )
    if not turn_rate:
        return world
    at = np.arange(TURN_FIRST, world.default_duration - 1.0, TURN_EVERY)
    trajectory = InPlaceTurns(world.trajectory, at, float(turn_rate))
    t = np.arange(0.0, world.default_duration + trajectory.pause * len(at), 0.01)
    facts = dict(
        world.facts,
        turns=len(at),
        turn_peak_rate_deg_s=float(turn_rate),
        max_yaw_rate_deg_s=round(float(np.degrees(np.abs(trajectory.angular_velocity(t)[:, 2]).max())), 2),
        loop=False,
    )
    return World(
        name,
        world.seed,
        world.scene,
        trajectory,
        _whole_scans(world.default_duration + trajectory.pause * len(at)),
        f'{world.description}; {len(at)} whole in-place turns at up to {turn_rate:g} deg/s',
        facts,
    )
