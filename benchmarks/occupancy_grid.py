"""The occupancy grid (lego_loam_py/core/mapping/occupancy_grid.py) against the simulator's scene, before and after
the loop closures, and its cost.

    .venv/bin/python benchmarks/occupancy_grid.py [--scenarios campus forest corridor] [--json out.json]

For each scenario the full lap (``simulate NAME --cached``) is mapped once with the default parameters (loop
closure on, as ``lego_loam_py run``), and saved as a run saves it (``output/occupancy_grid/NAME/lap``: the map files,
the map bundle and the grid as nav2 map_server files, occupancy.yaml / .pgm). While it maps, the keyframes are
copied just before the first loop closure moves them (``before_loops.npz`` beside the map). Three grids are
measured, at the default ``occupancy_grid`` parameters:

* **before loops**: the grid the node held just before the first loop closure: the keyframes mapped until then,
  at their poses then (drawn in one redraw, as :meth:`OccupancyGrid.sync` does);
* **after loops, same keyframes**: those keyframes at their final poses (the same part of the lap, corrected);
* **saved**: the grid the save wrote (every keyframe, final poses), read back from occupancy.yaml.

Each is placed in the simulated world by its first keyframe's true pose (so the map's own drift counts, as the
README's map-vs-scene distance does).

**Accuracy**: the share of occupied cells within ``2 cells + 0.1 m`` (horizontally) of a true obstacle: a surface of
the scene other than the ground, 0.3-2.0 m above the terrain, within 30 m of the path. A cell is tested by a column
of points 0.3..2.0 m above the terrain at its centre (every 0.1 m), each against the closest point of the scene's
non-ground triangles: the cell passes when one of those closest points is within the tolerance horizontally, lies in
the band (+-0.05 m, the column's step) and within 30 m of the path. Printed with the cells occupied / free /
unknown and how many of the scene's objects (by class) within 10 m of the path have an occupied cell within the
tolerance of their surface in the band.

**Cost**: wall time of each keyframe added to the grid, one at a time as the node adds them (mean, p95, max: the max
includes the arrays' growth), and of a redraw of every keyframe after a loop closure (each keyframe's classification
cached, as the node's grid has it, and from scratch).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from lego_loam_py.core.mapping import (  # noqa: E402
    Keyframe,
    MapOptimization,
    OccupancyGrid,
    TernaryGrid,
    keyframe_lidar_pose,
    read_bundle,
    read_occupancy_files,
)
from lego_loam_py.core.params import Params  # noqa: E402
from lego_loam_py.sim.output import true_poses, world_of  # noqa: E402
from lego_loam_py.sim.scene import GROUND_ID  # noqa: E402

OUT = ROOT / 'output' / 'occupancy_grid'
BAND = (0.3, 2.0)
PATH_REACH = 30.0
BEFORE = 'before_loops.npz'


def _keyframes_of(bundle, count: int | None = None, poses6: np.ndarray | None = None) -> list[Keyframe]:
    count = len(bundle) if count is None else count
    poses6 = bundle.poses6 if poses6 is None else poses6
    return [
        Keyframe(
            k, int(bundle.stamps_ns[k]), np.asarray(poses6[k]), bundle.corner[k], bundle.surf[k], bundle.outlier[k]
        )
        for k in range(count)
    ]


def map_lap(name: str, directory: Path) -> None:
    """Map the scenario's lap with the default parameters, keep the keyframes' poses just before the first loop
    closure (``directory/before_loops.npz``) and save the map as a run does."""
    from lego_loam_py.offline import run_bag
    from lego_loam_py.sim.simulator import cached_scenario

    before: dict[str, np.ndarray] = {}
    originals = {name: getattr(MapOptimization, name) for name in ('add_verified_loops', 'add_loop_factor')}

    def keeping_the_poses_before(method):
        def wrapped(self, *args, **kwargs):
            if not before:  # (the first loop closure: the poses as they were until now)
                kept = self.keyframes_now()
                before['stamps_ns'] = np.array([kf.stamp_ns for kf in kept], dtype=np.int64)
                before['poses6'] = np.array([kf.pose6 for kf in kept]).reshape(-1, 6)
            return method(self, *args, **kwargs)

        return wrapped

    for method_name, method in originals.items():  # (this benchmark only: a look at the poses, nothing changed)
        setattr(MapOptimization, method_name, keeping_the_poses_before(method))
    try:
        print(f'{name}: mapping the lap once (kept in {directory})', flush=True)
        result = run_bag(cached_scenario(name, progress=True), Params(), progress=True)
    finally:
        for method_name, method in originals.items():
            setattr(MapOptimization, method_name, method)
    start = time.perf_counter()
    result.mapper.save(directory)
    print(f'{name}: saved in {time.perf_counter() - start:.1f} s (the grid drawn from scratch included)', flush=True)
    if not before:
        print(f'{name}: no loop closure on this lap', flush=True)
        before = dict(stamps_ns=np.zeros(0, np.int64), poses6=np.zeros((0, 6)))
    np.savez(directory / BEFORE, **before)


class SceneTruth:
    """The scene's obstacles in the band near the path, to test occupied cells against."""

    def __init__(self, simulated: dict, path_xy: np.ndarray):
        import open3d as o3d
        from scipy.spatial import cKDTree

        world = world_of(simulated)
        self.scene = world.scene
        self.terrain = world.trajectory.terrain
        keep = self.scene.triangle_instance != GROUND_ID
        self.raycasting = o3d.t.geometry.RaycastingScene()
        self.raycasting.add_triangles(
            o3d.core.Tensor(self.scene.vertices), o3d.core.Tensor(np.ascontiguousarray(self.scene.triangles[keep]))
        )
        self.path = cKDTree(path_xy)

    def found(
        self, occupied_world: np.ndarray, tolerance: float, reach: float = 10.0, samples: int = 2_000_000
    ) -> dict[str, tuple[int, int]]:
        """Per class, (objects found, objects): the scene's objects with a surface 0.3-2.0 m above the terrain within
        ``reach`` of the path, found when an occupied cell lies within ``tolerance`` of that surface (sampled
        uniformly by area; clutter, label 0, left out)."""
        from scipy.spatial import cKDTree

        scene, rng = self.scene, np.random.default_rng(0)
        vertices = scene.vertices.astype(np.float64)
        a, b, c = (vertices[scene.triangles[:, k]] for k in range(3))
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1) * (scene.triangle_instance > GROUND_ID)
        pick = rng.choice(len(area), samples, p=area / area.sum())
        u, v = rng.random(samples), rng.random(samples)
        flip = u + v > 1.0
        u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
        points = a[pick] + u[:, None] * (b[pick] - a[pick]) + v[:, None] * (c[pick] - a[pick])
        above = points[:, 2] - self.terrain.height(points[:, 0], points[:, 1])
        keep = (above >= BAND[0]) & (above <= BAND[1]) & (self.path.query(points[:, :2])[0] <= reach)
        instance = scene.triangle_instance[pick][keep]
        hit = cKDTree(occupied_world).query(points[keep, :2])[0] <= tolerance
        found_ids = set(np.unique(instance[hit]).tolist())
        out: dict[str, tuple[int, int]] = {}
        for i in np.unique(instance):
            name = scene.classes[int(i)]
            total, found = out.get(name, (0, 0))
            out[name] = (total + 1, found + int(int(i) in found_ids))
        return {name: (found, total) for name, (total, found) in sorted(out.items())}

    def within(self, centres_world: np.ndarray, tolerance: float, chunk: int = 20000) -> np.ndarray:
        """Whether each world-frame cell centre (k, 2) lies within ``tolerance`` [m] of a true obstacle."""
        import open3d as o3d

        heights = np.arange(BAND[0], BAND[1] + 1e-9, 0.1)
        out = np.zeros(len(centres_world), bool)
        for start in range(0, len(centres_world), chunk):
            xy = centres_world[start : start + chunk]
            ground = self.terrain.height(xy[:, 0], xy[:, 1])
            columns = np.empty((len(xy), len(heights), 3), np.float32)
            columns[..., :2] = xy[:, None, :]
            columns[..., 2] = ground[:, None] + heights[None, :]
            closest = self.raycasting.compute_closest_points(o3d.core.Tensor(columns.reshape(-1, 3)))
            q = closest['points'].numpy().astype(np.float64).reshape(len(xy), len(heights), 3)
            horizontal = np.hypot(q[..., 0] - xy[:, None, 0], q[..., 1] - xy[:, None, 1])
            above = q[..., 2] - self.terrain.height(q[..., 0], q[..., 1])
            in_band = (above >= BAND[0] - 0.05) & (above <= BAND[1] + 0.05)
            near_path = self.path.query(q[..., :2].reshape(-1, 2))[0].reshape(horizontal.shape) <= PATH_REACH
            out[start : start + chunk] = ((horizontal <= tolerance) & in_band & near_path).any(axis=1)
        return out


def evaluate(grid: TernaryGrid, world_from_map: np.ndarray, truth: SceneTruth) -> dict:
    """The grid's accuracy against the scene (module docstring), the map placed in the world by ``world_from_map``."""
    world = grid.cell_centres() @ world_from_map[:2, :2].T + world_from_map[:2, 3]
    tolerance = 2 * grid.resolution + 0.1
    near = truth.within(world, tolerance)
    return dict(
        tolerance_m=tolerance,
        share_within=float(near.mean()) if len(near) else float('nan'),
        found=truth.found(world, tolerance),
        width=grid.width,
        height=grid.height,
        **grid.counts(),
    )


def costs(keyframes: list[Keyframe], params) -> dict:
    """Wall time [ms] of each keyframe added one at a time, and of a redraw of all of them (cached, from scratch)."""
    grid = OccupancyGrid(params)
    times = np.empty(len(keyframes))
    for k, keyframe in enumerate(keyframes):
        start = time.perf_counter()
        grid.add_keyframe(keyframe)
        times[k] = (time.perf_counter() - start) * 1e3
    start = time.perf_counter()
    grid.redraw(keyframes)
    cached = time.perf_counter() - start
    start = time.perf_counter()
    OccupancyGrid(params).redraw(keyframes)
    fresh = time.perf_counter() - start
    return dict(
        ms_per_keyframe_mean=float(times.mean()),
        ms_per_keyframe_p95=float(np.percentile(times, 95)),
        ms_per_keyframe_max=float(times.max()),
        redraw_cached_s=cached,
        redraw_fresh_s=fresh,
    )


def describe(label: str, row: dict) -> str:
    found = ', '.join(f'{k} {f}/{t}' for k, (f, t) in row['found'].items())
    return (
        f'  {label:28s} {row["keyframes"]:4d} keyframes: {100 * row["share_within"]:6.2f} % of {row["occupied"]} '
        f'occupied cells within {row["tolerance_m"]:.2f} m of a true obstacle; free {row["free"]}, unknown '
        f'{row["unknown"]} ({row["width"]} x {row["height"]}); objects within 10 m of the path found: {found}'
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--scenarios', nargs='+', default=['campus'])
    parser.add_argument('--json', type=Path, help='write the figures here')
    args = parser.parse_args(argv)
    params = Params().occupancy_grid
    results = []
    for name in args.scenarios:
        directory = OUT / name / 'lap'
        if not (directory / BEFORE).is_file():
            map_lap(name, directory)
        bundle = read_bundle(directory)
        kept = np.load(directory / BEFORE)
        simulated = bundle.source['simulated']
        final = _keyframes_of(bundle)
        truth = true_poses(simulated, bundle.stamps_ns)
        scene = SceneTruth(simulated, truth[:, :2, 3])
        world_from_map = truth[0] @ np.linalg.inv(keyframe_lidar_pose(bundle.poses6[0]))  # by the first keyframe
        count = len(kept['stamps_ns'])
        assert np.array_equal(kept['stamps_ns'], bundle.stamps_ns[:count]), 'the keyframes before the loops differ'
        grids = {}
        if count:
            before = OccupancyGrid(params)
            before.sync(_keyframes_of(bundle, count, kept['poses6']))
            same = OccupancyGrid(params)
            same.sync(final[:count])
            grids['before loops'] = (count, before.ternary())
            grids['after loops, same keyframes'] = (count, same.ternary())
        grids['saved (all, after loops)'] = (len(final), read_occupancy_files(directory / 'occupancy.yaml'))
        # How far the loop closures moved the keyframes mapped before the first one (map frame, metres).
        moved = np.array(
            [
                np.linalg.norm(keyframe_lidar_pose(a)[:3, 3] - keyframe_lidar_pose(b)[:3, 3])
                for a, b in zip(kept['poses6'], bundle.poses6[:count])
            ]
        )
        moved_max = float(moved.max()) if count else 0.0
        moved_mean = float(moved.mean()) if count else 0.0
        print(
            f'{name}: {len(final)} keyframes, the first loop closure at keyframe {count}; the loops moved the keyframes'
            f' before it by {moved_mean:.3f} m on average, {moved_max:.3f} m at most',
            flush=True,
        )
        row = dict(
            scenario=name,
            keyframes=len(final),
            first_loop_at=count,
            loop_shift_mean_m=moved_mean,
            loop_shift_max_m=moved_max,
            resolution=params.resolution,
        )
        for label, (keyframes, grid) in grids.items():
            figures = dict(keyframes=keyframes, **evaluate(grid, world_from_map, scene))
            row[label] = figures
            print(describe(label, figures), flush=True)
        row['cost'] = costs(final, params)
        c = row['cost']
        print(
            f'  cost: ms per keyframe added: mean {c["ms_per_keyframe_mean"]:.1f}, p95 {c["ms_per_keyframe_p95"]:.1f}, '
            f'max {c["ms_per_keyframe_max"]:.1f}; redraw of {len(final)} keyframes {c["redraw_cached_s"]:.2f} s '
            f'(classification cached), {c["redraw_fresh_s"]:.2f} s (from scratch)',
            flush=True,
        )
        results.append(row)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
