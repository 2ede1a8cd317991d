"""What a run writes and says about its result, shared by ``lego_loam_py run`` (offline) and the demo (DDS):
the trajectories (TUM, REP-103 ``map`` and the original's camera_init axes), the map (PCD), a PNG of both and
``summary.json``, with the accuracy against a ground truth found beside the bag.
"""

from __future__ import annotations

import os
import pickle
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from lego_loam_py.core.mapping.map_files import in_map_axes
from lego_loam_py.core.mapping.map_optimization import MapOptimization
from lego_loam_py.core.params import Params
from lego_loam_py.core.pipeline import pose_time_offset_ns
from lego_loam_py.core.trajectory import Trajectory
from lego_loam_py.formats import write_kitti_poses_atomic, write_text_atomic, write_tum_atomic
from lego_loam_py.front_end_process import can_split
from lego_loam_py.results import DemoSummary, MapToScene, OfflineSummary, RunOutputs

__all__ = ['write_outputs', 'write_summary', 'result_lines', 'pose_time_offset_ns', 'TRAJECTORY_FORMATS']

TRAJECTORY_FORMATS = ('tum', 'kitti')
_BESIDE_THE_BAG = object()  # write_outputs' default ground truth: the simulator's ground_truth.tum beside the bag


def write_summary(out_dir: str | Path, summary: OfflineSummary | DemoSummary) -> None:
    """``out_dir/summary.json``."""
    write_text_atomic(Path(out_dir) / 'summary.json', summary.to_json())


def write_outputs(
    out_dir: str | Path,
    bag: str | Path,
    trajectory: Trajectory,
    mapper: MapOptimization | None,
    summary: OfflineSummary | DemoSummary,
    params: Params,
    map_dir: str | Path | None = None,
    in_saved_map: bool = False,
    *,
    ground_truth=_BESIDE_THE_BAG,
    trajectory_format: str = 'tum',
    parallel: bool = False,
) -> RunOutputs:
    """Trajectories, maps, PNG and summary.json into ``out_dir``; measures what they show (with the accuracy
    when there is a ground truth) into ``summary.outputs``, which it returns.

    ``trajectory``: the published poses (in either frame). ``ground_truth``: the recording's (a trajectory), None for
    none (default: the one beside the bag). ``trajectory_format`` 'kitti' adds ``trajectory_kitti.txt``: the TUM file's
    poses (lidar in ``map``, REP-103) in KITTI's layout, 12 numbers a line, one line per pose.

    The maps come from ``mapper`` (saved into ``out_dir/map``) or, without one, from ``map_dir`` where they
    were saved already (by the mapOptimization node, or the saved map a localization ran in): listed in the summary
    and drawn under the PNG. ``in_saved_map``: the poses are in a saved map's frame (localization), so the drawn
    ground truth starts at the first pose instead of the origin.

    ``parallel``: draw the PNG, and measure the map's distance to a simulated scene, each in a forked child process
    (:class:`ForkedCall`) while this one saves the maps and measures the accuracy; for a process with no other
    thread at work (the offline run's, once its run is over). The files and figures are the same either way."""
    from lego_loam_py.evaluation import evaluate, path_length, plot_trajectories
    from lego_loam_py.inputs.sidecars import load_ground_truth, load_scenario

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stamps, poses_map = trajectory.to('map')
    result = summary.outputs = RunOutputs(poses=int(len(poses_map)))
    if len(poses_map):  # (no pose, no file: an empty trajectory file would look like a broken one)
        write_tum_atomic(out / 'trajectory.tum', stamps, poses_map)
        write_tum_atomic(out / 'trajectory_camera_init.tum', stamps, trajectory.to('camera_init').poses)
        if trajectory_format == 'kitti':
            write_kitti_poses_atomic(out / 'trajectory_kitti.txt', poses_map)
    result.trajectory_length_m = path_length(poses_map)
    maps = None  # the mapper's maps, to be saved
    map_points = None  # the global map (REP-103 map axes) as its saved file holds it
    if mapper is not None and mapper.builds_map and mapper.keyframes:
        maps = mapper.maps()
        map_points = in_map_axes(maps['global_map'])
    elif map_dir is not None and (Path(map_dir) / 'global_map.pcd').is_file():
        from lego_loam_py.formats import read_pcd

        saved_files = sorted(p for p in Path(map_dir).iterdir() if p.suffix in ('.pcd', '.tum'))
        result.map_files = {p.name: str(p) for p in saved_files}
        map_points = read_pcd(Path(map_dir) / 'global_map.pcd')
    if ground_truth is _BESIDE_THE_BAG:
        ground_truth = load_ground_truth(bag)
    trajectories = {'lego_loam_py': poses_map}
    if ground_truth is not None and len(stamps):
        # Show the ground truth in the estimate's frame: both start at identity at the first scan (mapping), or the
        # truth starts at the first pose (localization: the poses are in a saved map's frame).
        gt_stamps, gt_poses = ground_truth
        first = np.argmin(np.abs(gt_stamps - stamps[0]))
        start = poses_map[0] if in_saved_map else np.eye(4)
        trajectories = {'ground truth': (start @ np.linalg.inv(gt_poses[first]))[None] @ gt_poses, **trajectories}
    # The picture and the map's distance to a simulated scene may each take as long as the rest together.
    picture = None
    if any(len(poses) for poses in trajectories.values()) or (map_points is not None and len(map_points)):
        # (nothing to draw, no picture: an empty plot would look like a broken run)
        title = f'{Path(bag).name}: trajectory over the map (top view)'
        picture = ForkedCall(
            lambda: plot_trajectories(out / 'trajectory.png', trajectories, map_points, title=title), parallel
        )
    scene_distance = None
    if map_points is not None and len(map_points) and len(stamps):
        from lego_loam_py.sim.output import map_distance_to_scene

        scene_distance = ForkedCall(
            lambda: map_distance_to_scene(bag, map_points, int(stamps[0]), poses_map[0]),
            parallel and load_scenario(bag) is not None,  # (no scene beside the bag: nothing to measure)
        )
    try:
        if maps is not None:
            saved = mapper.save(out / 'map', maps=maps)
            result.map_files = {k: str(v) for k, v in saved.items()}
        if ground_truth is not None and len(stamps) < 3:
            result.accuracy_error = (
                f'not evaluated: {len(stamps)} pose(s); the evaluation needs at least 3 (the '
                'first scan only initialises the odometry)'
            )
        elif ground_truth is not None:
            try:
                result.accuracy = evaluate(ground_truth, trajectory)
            except ValueError as exc:
                result.accuracy_error = str(exc)
        distance = None if scene_distance is None else scene_distance.result()
        if distance is not None and len(distance):
            result.map_to_scene = MapToScene(
                median_m=float(np.median(distance)), p90_m=float(np.percentile(distance, 90)), points=int(len(distance))
            )
        if picture is not None:
            result.png = str(picture.result())
    finally:
        for call in (picture, scene_distance):
            if call is not None:
                call.close()
    write_summary(out, summary)
    return result


class ForkedCall:
    """``function()`` computed in a forked child process while this one goes on, when ``parallel`` and this process
    may fork (lego_loam_py.front_end_process.can_split), else here when :meth:`result` asks for it. The value comes
    back pickled through a pipe; when the child fails, :meth:`result` calls ``function()`` here, where the error
    shows. The child is forked with whatever this process holds: no other thread of it may be at work."""

    def __init__(self, function: Callable[[], Any], parallel: bool):
        self._function, self._pid, self._reader = function, None, None
        if parallel and can_split():
            sys.stdout.flush()  # (what is buffered now would be written twice, once by each process)
            sys.stderr.flush()
            reader, writer = os.pipe()
            pid = os.fork()
            if pid == 0:
                os.close(reader)
                _run_child(function, writer)
            os.close(writer)
            self._pid, self._reader = pid, reader

    def result(self) -> Any:
        """``function()``'s value, from the child when it succeeded."""
        if self._pid is not None:
            data = self._collect()
            if data is not None:
                return pickle.loads(data)
        return self._function()

    def close(self) -> None:
        """Wait for a child still at work (this process is leaving early, on an error): none is left behind."""
        if self._pid is not None:
            self._collect()

    def _collect(self) -> bytes | None:
        """The child's pickled value once it has ended (read first: a value larger than the pipe holds would keep it
        waiting), None when it failed."""
        with os.fdopen(self._reader, 'rb') as pipe:
            data = pipe.read()
        _, status = os.waitpid(self._pid, 0)
        self._pid = self._reader = None
        return data if os.waitstatus_to_exitcode(status) == 0 else None


def _run_child(function: Callable[[], Any], writer: int) -> None:
    """A ForkedCall's child: ``function()``'s value pickled into ``writer``, then leave at once (nothing of what the
    parent owns cleaned up here)."""
    code = 1
    try:
        data = pickle.dumps(function())
        with os.fdopen(writer, 'wb') as pipe:
            pipe.write(data)
        code = 0
    except BaseException:  # noqa: BLE001 (the parent calls the function again and raises its error there)
        traceback.print_exc()
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def result_lines(outputs: RunOutputs) -> list[str]:
    """The summary lines on the result, shared by ``run`` and the demo: trajectory length, accuracy against
    the ground truth, and the map's distance to a simulated scene when one was measured."""
    lines = [f'trajectory length {outputs.trajectory_length_m:.1f} m']
    if outputs.accuracy is not None:
        lines.append('accuracy vs ground truth: ' + outputs.accuracy.summary())
    elif outputs.accuracy_error is not None:
        lines.append(f'accuracy: {outputs.accuracy_error}')
    else:
        lines.append('accuracy: no ground truth beside the bag')
    if outputs.accuracy_optimized is not None:
        lines.append('  after the loop closures (trajectory_optimized.tum): ' + outputs.accuracy_optimized.summary())
    m = outputs.map_to_scene
    if m is not None:
        lines.append(
            f'map vs the simulated scene: median point-to-mesh distance {m.median_m:.3f} m, 90th '
            f'percentile {m.p90_m:.3f} m over {m.points} map points'
        )
    return lines
