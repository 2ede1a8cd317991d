"""Procedural triangle-mesh worlds for the simulator: materials, terrain, primitives, the ray-casting scene.

Everything here lives in the simulator's **world frame**: metres, z up along -gravity (the world is
gravity-aligned), x/y horizontal with an arbitrary origin near the middle of the scenario.

A :class:`Scene` is one triangle soup with two per-triangle attributes:

* ``triangle_instance`` -- the label a return on that triangle gets: 0 = none (clutter such as small
  vegetation, unlabeled), 1 = ground, >= 2 = one object instance (each building, tree, pole, car, wall
  segment is its own id); ``classes[instance]`` names the class of every id.
* ``triangle_material`` -- an index into ``materials``; the material gives the intensity and how often the
  return is lost.

All triangles go into a single open3d ``RaycastingScene`` (Embree), so a whole sweep is one
``cast_rays`` call.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    'Material',
    'MATERIALS',
    'MATERIAL_NAMES',
    'material_index',
    'Terrain',
    'box_mesh',
    'cylinder_mesh',
    'ellipsoid_mesh',
    'heightfield_mesh',
    'transform_mesh',
    'SceneBuilder',
    'Scene',
    'NONE_ID',
    'GROUND_ID',
]

NONE_ID = 0  # label of unlabeled / clutter returns
GROUND_ID = 1  # label of ground returns


@dataclass(frozen=True)
class Material:
    """Surface properties that matter to a lidar.

    ``reflectivity`` is on the Velodyne calibrated-reflectivity scale the driver puts into ``intensity``:
    0..100 for diffuse surfaces (roughly the diffuse reflectance in percent), 101..255 for
    retro-reflectors. ``transmission`` is the probability that a beam hitting the surface yields no return
    at all (glass, sparse foliage).
    """

    name: str
    reflectivity: float
    retroreflective: bool = False
    transmission: float = 0.0


# Typical VLP-16 intensities: asphalt 5-15, grass 20-40, concrete / walls 40-80, painted metal 100+,
# retro-reflective signs and plates up to 255.
MATERIALS: tuple[Material, ...] = (
    Material('asphalt', 10.0),
    Material('grass', 30.0),
    Material('concrete', 55.0),
    Material('plaster', 70.0),
    Material('brick', 42.0),
    Material('glass', 12.0, transmission=0.6),
    Material('bark', 28.0),
    Material('foliage', 24.0, transmission=0.08),
    Material('car_paint', 110.0),
    Material('metal', 120.0),
    Material('retroreflector', 250.0, retroreflective=True),
    Material('soil', 20.0),
    Material('leaf_litter', 16.0),
    Material('rock', 38.0),
    Material('wood', 45.0),
    Material('floor_tiles', 50.0),
    Material('painted_wall', 75.0),
    Material('ceiling', 85.0),
)
MATERIAL_NAMES: tuple[str, ...] = tuple(m.name for m in MATERIALS)
_MATERIAL_INDEX = {name: i for i, name in enumerate(MATERIAL_NAMES)}


def material_index(name: str) -> int:
    """Index of a material in :data:`MATERIALS` (KeyError naming the known ones otherwise)."""
    try:
        return _MATERIAL_INDEX[name]
    except KeyError:
        raise KeyError(f"unknown material '{name}' (known: {', '.join(MATERIAL_NAMES)})") from None


# ------------------------------------------------------------------------------------------------ terrain


@dataclass(frozen=True)
class Terrain:
    """Smooth analytic height field ``z = h(x, y)`` [m] in the world frame.

    ``h = offset + slope . (x, y) + sum_i a_i sin(kx_i x + ky_i y + phi_i)``. Analytic, so the trajectory
    (wheel contacts) and the ground mesh use the very same surface; the mesh is its piecewise-linear
    interpolation on a grid.
    """

    waves: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # rows: a [m], kx, ky [rad/m], phi
    slope: tuple[float, float] = (0.0, 0.0)
    offset: float = 0.0

    @staticmethod
    def random(
        rng: np.random.Generator,
        components: Sequence[tuple[float, float]],
        slope: tuple[float, float] = (0.0, 0.0),
        waves_per_component: int = 2,
    ) -> Terrain:
        """Sum of sine waves: for each (amplitude [m], wavelength [m]) ``waves_per_component`` waves with
        random directions and phases, each of amplitude ``amplitude / waves_per_component``."""
        rows = []
        for amplitude, wavelength in components:
            for _ in range(waves_per_component):
                direction = rng.uniform(0.0, 2.0 * np.pi)
                k = 2.0 * np.pi / wavelength * rng.uniform(0.8, 1.25)
                rows.append(
                    (
                        amplitude / waves_per_component,
                        k * np.cos(direction),
                        k * np.sin(direction),
                        rng.uniform(0.0, 2.0 * np.pi),
                    )
                )
        return Terrain(np.array(rows, dtype=float).reshape(-1, 4), slope)

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Terrain height [m] at world (x, y) (any broadcastable shapes)."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        z = self.offset + self.slope[0] * x + self.slope[1] * y
        for amplitude, kx, ky, phase in self.waves:
            z = z + amplitude * np.sin(kx * x + ky * y + phase)
        return z

    def gradient(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dh/dx, dh/dy) at world (x, y)."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        gx = np.full(np.broadcast(x, y).shape, self.slope[0])
        gy = np.full(gx.shape, self.slope[1])
        for amplitude, kx, ky, phase in self.waves:
            c = amplitude * np.cos(kx * x + ky * y + phase)
            gx = gx + kx * c
            gy = gy + ky * c
        return gx, gy


# ------------------------------------------------------------------------------------------ primitives
# Each returns (vertices (n, 3) float64, triangles (m, 3) int64) in a local frame.


def box_mesh(size: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Box of ``size`` (sx, sy, sz) [m], centred on the origin in x/y, from z = 0 to z = sz."""
    sx, sy, sz = (float(s) for s in size)
    corners = np.array([[x, y, z] for z in (0.0, 1.0) for y in (-0.5, 0.5) for x in (-0.5, 0.5)])
    vertices = corners * [sx, sy, sz]
    triangles = np.array(
        [
            [0, 2, 1],
            [1, 2, 3],  # bottom
            [4, 5, 6],
            [5, 7, 6],  # top
            [0, 1, 4],
            [1, 5, 4],  # -y
            [2, 6, 3],
            [3, 6, 7],  # +y
            [0, 4, 2],
            [2, 4, 6],  # -x
            [1, 3, 5],
            [3, 7, 5],  # +x
        ]
    )
    return vertices, triangles


def cylinder_mesh(
    radius: float, height: float, segments: int = 12, top_radius: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Closed cylinder (or frustum / cone with ``top_radius``) on the z axis from z = 0 to ``height``."""
    top = radius if top_radius is None else top_radius
    angles = np.arange(segments) * (2.0 * np.pi / segments)
    ring = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    bottom_ring = np.column_stack([ring * radius, np.zeros(segments)])
    top_ring = np.column_stack([ring * top, np.full(segments, height)])
    vertices = np.vstack([bottom_ring, top_ring, [[0.0, 0.0, 0.0], [0.0, 0.0, height]]])
    i = np.arange(segments)
    j = (i + 1) % segments
    n = segments
    side = np.vstack([np.stack([i, j, n + j], 1), np.stack([i, n + j, n + i], 1)])
    caps = np.vstack([np.stack([np.full(n, 2 * n), j, i], 1), np.stack([np.full(n, 2 * n + 1), n + i, n + j], 1)])
    return vertices, np.vstack([side, caps])


@functools.lru_cache(maxsize=4)
def _unit_icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_icosahedron(1.0)
    if subdivisions:
        mesh = mesh.subdivide_midpoint(subdivisions)
    vertices = np.asarray(mesh.vertices, dtype=float)
    vertices /= np.linalg.norm(vertices, axis=1, keepdims=True)
    return vertices, np.asarray(mesh.triangles, dtype=np.int64)


def ellipsoid_mesh(
    radii: Sequence[float], subdivisions: int = 2, roughness: float = 0.0, rng: np.random.Generator | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Ellipsoid centred on the origin; ``roughness`` > 0 perturbs each vertex radially by up to that
    fraction (tree crowns, bushes, rocks)."""
    unit, triangles = _unit_icosphere(subdivisions)
    scale = np.ones(len(unit))
    if roughness > 0.0:
        if rng is None:
            raise ValueError('a rough ellipsoid needs a random generator')
        scale = 1.0 + rng.uniform(-roughness, roughness, len(unit))
    return unit * scale[:, None] * np.asarray(radii, dtype=float), triangles.copy()


def heightfield_mesh(
    terrain: Terrain, x_range: tuple[float, float], y_range: tuple[float, float], spacing: float
) -> tuple[np.ndarray, np.ndarray]:
    """Grid of the terrain over the world rectangle, ``spacing`` [m] apart, two triangles per cell."""
    xs = np.arange(x_range[0], x_range[1] + 0.5 * spacing, spacing)
    ys = np.arange(y_range[0], y_range[1] + 0.5 * spacing, spacing)
    gx, gy = np.meshgrid(xs, ys)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), terrain.height(gx, gy).ravel()])
    nx, ny = len(xs), len(ys)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    a = (j * nx + i).ravel()
    b, c = a + 1, a + nx
    d = c + 1
    return vertices, np.vstack([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def transform_mesh(
    vertices: np.ndarray,
    yaw: float = 0.0,
    translation: Sequence[float] = (0.0, 0.0, 0.0),
    roll: float = 0.0,
    pitch: float = 0.0,
) -> np.ndarray:
    """Vertices rotated by ``Rz(yaw) Ry(pitch) Rx(roll)`` [rad] then translated [m]."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    rotation = np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )
    return vertices @ rotation.T + np.asarray(translation, dtype=float)


# -------------------------------------------------------------------------------------------- the scene


class SceneBuilder:
    """Collects meshes with their instance labels and materials, then builds a :class:`Scene`."""

    def __init__(self) -> None:
        self.classes: list[str] = ['none', 'ground']  # index = instance id
        self._vertices: list[np.ndarray] = []
        self._triangles: list[np.ndarray] = []
        self._instances: list[np.ndarray] = []
        self._materials: list[np.ndarray] = []
        self._vertex_count = 0

    def new_instance(self, class_name: str) -> int:
        """A fresh object id (>= 2) of class ``class_name``."""
        self.classes.append(class_name)
        return len(self.classes) - 1

    def add(self, vertices: np.ndarray, triangles: np.ndarray, material: str | np.ndarray, instance: int) -> None:
        """Add a mesh (world coordinates). ``material`` is a name or per-triangle material indices;
        ``instance`` is NONE_ID, GROUND_ID or an id from :meth:`new_instance`."""
        if not 0 <= instance < len(self.classes):
            raise ValueError(f'unknown instance id {instance}')
        triangles = np.asarray(triangles, dtype=np.int64)
        if isinstance(material, str):
            materials = np.full(len(triangles), material_index(material), dtype=np.uint8)
        else:
            materials = np.asarray(material, dtype=np.uint8)
            if materials.shape != (len(triangles),):
                raise ValueError('per-triangle materials must have one entry per triangle')
        self._vertices.append(np.asarray(vertices, dtype=float))
        self._triangles.append(triangles + self._vertex_count)
        self._instances.append(np.full(len(triangles), instance, dtype=np.uint32))
        self._materials.append(materials)
        self._vertex_count += len(vertices)

    def add_object(self, class_name: str, parts: Iterable[tuple[np.ndarray, np.ndarray, str]]) -> int:
        """Add an object made of several (vertices, triangles, material) parts under one new id."""
        instance = self.new_instance(class_name)
        for vertices, triangles, material in parts:
            self.add(vertices, triangles, material, instance)
        return instance

    def add_clutter(self, vertices: np.ndarray, triangles: np.ndarray, material: str) -> None:
        """Add geometry whose returns stay unlabeled (label 0): small vegetation, litter."""
        self.add(vertices, triangles, material, NONE_ID)

    def build(self) -> Scene:
        return Scene(
            np.vstack(self._vertices),
            np.vstack(self._triangles),
            np.concatenate(self._instances),
            np.concatenate(self._materials),
            tuple(self.classes),
        )


class Scene:
    """A triangle soup with per-triangle instance labels and materials, and its ray-casting structure."""

    def __init__(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        triangle_instance: np.ndarray,
        triangle_material: np.ndarray,
        classes: tuple[str, ...],
        materials: tuple[Material, ...] = MATERIALS,
    ):
        import open3d as o3d

        self.vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.uint32)
        self.triangle_instance = np.asarray(triangle_instance, dtype=np.uint32)
        self.triangle_material = np.asarray(triangle_material, dtype=np.uint8)
        self.classes = classes
        self.materials = materials
        self.reflectivity = np.array([m.reflectivity for m in materials])
        self.retroreflective = np.array([m.retroreflective for m in materials])
        self.transmission = np.array([m.transmission for m in materials])
        self._o3d = o3d
        self._raycasting = o3d.t.geometry.RaycastingScene()
        self._raycasting.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))

    @property
    def triangle_count(self) -> int:
        return len(self.triangles)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast rays (world frame; unit ``directions``) in one call.

        Returns ``(distance [m] (N,), triangle index (N,) int64 with -1 for a miss, triangle unit normal
        (N, 3))``; a miss has distance ``inf``.
        """
        rays = np.empty((len(origins), 6), dtype=np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = directions
        hits = self._raycasting.cast_rays(self._o3d.core.Tensor(rays))
        distance = hits['t_hit'].numpy().astype(np.float64)
        triangle = hits['primitive_ids'].numpy().astype(np.int64)
        missed = ~np.isfinite(distance)
        triangle[missed] = -1
        return distance, triangle, hits['primitive_normals'].numpy().astype(np.float64)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance [m] of world points (N, 3) to the nearest triangle."""
        query = self._o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
        return self._raycasting.compute_distance(query).numpy().astype(np.float64)

    def closest_instance(self, points: np.ndarray) -> np.ndarray:
        """Instance id of the triangle nearest to each world point (N, 3)."""
        query = self._o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
        triangle = self._raycasting.compute_closest_points(query)['primitive_ids'].numpy().astype(np.int64)
        return self.triangle_instance[triangle]
