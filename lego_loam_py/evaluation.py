"""Trajectory accuracy against ground truth (with evo) and the plots the demo and ``lego_loam_py eval`` draw.

Metrics (all on trajectories in REP-103 axes, associated by timestamp):

* **ATE**: absolute trajectory error after an SE(3) alignment (Umeyama, no scale) of the estimate onto the
  ground truth: RMSE, mean, median, max of the translation error [m];
* **RPE**: relative pose error over segments of a given length (``delta`` metres of path), translation
  part, as a percentage of the segment length (KITTI style) and in metres;
* **end-point error** and **drift**: distance between the estimated and true last pose, with both
  trajectories expressed relative to their first pose (no alignment), and that distance over the path
  length [%]; for loops this is also the "return to start" error of the LeGO-LOAM paper (Table V).

:func:`error_over_time` gives the error of every pose as it happens (both trajectories relative to their first
pose, no alignment): the position error in the true heading's frame (along, left, up), the attitude error as a
tilt and a heading error, beside the true yaw rate, to tell where a run goes wrong (a turn, a straight part).
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lego_loam_py.core.trajectory import Trajectory
from lego_loam_py.errors import LegoLoamError, UsageError

__all__ = [
    'TrajectoryMetrics',
    'ErrorOverTime',
    'evaluate',
    'error_over_time',
    'path_length',
    'plot_trajectories',
    'relative_to_first',
    'rigid_fit',
    'in_map',
    'view_limits',
    'ErrorInMap',
    'errors_in_map',
]


@dataclass
class TrajectoryMetrics:
    matched_poses: int
    path_length_m: float
    ate_rmse_m: float
    ate_mean_m: float
    ate_median_m: float
    ate_max_m: float
    rpe_percent: float  # mean translational RPE over `rpe_delta_m` segments, % of segment length
    rpe_delta_m: float
    rpe_rmse_m: float
    end_point_error_m: float
    drift_percent: float
    rotation_end_error_deg: float

    def as_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        return (
            f'ATE RMSE {self.ate_rmse_m:.3f} m (max {self.ate_max_m:.3f} m) over {self.matched_poses} poses, '
            f'{self.path_length_m:.1f} m of path; RPE {self.rpe_percent:.2f} % over {self.rpe_delta_m:g} m; '
            f'end point {self.end_point_error_m:.3f} m = {self.drift_percent:.2f} % drift, '
            f'{self.rotation_end_error_deg:.2f} deg'
        )


def path_length(poses: np.ndarray) -> float:
    """Length [m] of the polyline through the positions of (N, 4, 4) poses."""
    positions = np.asarray(poses)[:, :3, 3]
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()) if len(positions) > 1 else 0.0


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    """Poses expressed relative to the first one (first = identity)."""
    poses = np.asarray(poses, dtype=float)
    return np.linalg.inv(poses[0])[None] @ poses if len(poses) else poses


def in_map(trajectory: Trajectory | tuple[np.ndarray, np.ndarray]) -> Trajectory:
    """``trajectory`` in the map frame (REP-103 axes); a (stamps [ns], poses) pair is taken to be in it already."""
    if isinstance(trajectory, Trajectory):
        return trajectory.to('map')
    return Trajectory(*trajectory, 'map')


def _trajectory(stamps_ns: np.ndarray, poses: np.ndarray):
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(
        poses_se3=list(np.asarray(poses, dtype=float)), timestamps=np.asarray(stamps_ns, dtype=np.int64) * 1e-9
    )


def _associate(ref_stamps, ref_poses, est_stamps, est_poses, max_diff: float):
    from evo.core import sync

    return sync.associate_trajectories(
        _trajectory(ref_stamps, ref_poses), _trajectory(est_stamps, est_poses), max_diff=max_diff
    )


def evaluate(
    ground_truth: Trajectory | tuple[np.ndarray, np.ndarray],
    estimate: Trajectory | tuple[np.ndarray, np.ndarray],
    rpe_delta_m: float = 10.0,
    max_time_diff: float = 0.01,
) -> TrajectoryMetrics:
    """Metrics of ``estimate`` against ``ground_truth``: trajectories (compared in the map frame), or (stamps [ns],
    (N, 4, 4) poses in REP-103 axes) pairs."""
    from evo.core import metrics
    from evo.core.units import Unit

    ref, est = _associate(*in_map(ground_truth), *in_map(estimate), max_diff=max_time_diff)
    if ref.num_poses < 2:
        raise ValueError(f'only {ref.num_poses} poses of the estimate match the ground truth in time')
    ref_poses = np.array(ref.poses_se3)
    est_poses = np.array(est.poses_se3)
    length = path_length(ref_poses)
    # End point, both relative to their first pose: the drift of dead reckoning.
    ref_rel, est_rel = relative_to_first(ref_poses), relative_to_first(est_poses)
    end_error = float(np.linalg.norm(ref_rel[-1, :3, 3] - est_rel[-1, :3, 3]))
    rotation_error = ref_rel[-1, :3, :3].T @ est_rel[-1, :3, :3]
    rotation_end_deg = float(np.degrees(np.arccos(np.clip((np.trace(rotation_error) - 1) / 2, -1.0, 1.0))))

    aligned = copy.deepcopy(est)
    try:
        aligned.align(ref, correct_scale=False)
    except Exception as exc:  # evo's GeometryException: positions on a line (or a point) fix no rotation
        raise ValueError(
            f'{ref.num_poses} matched poses cannot be aligned with the ground truth ({exc}): '
            'a run needs poses that span more than a straight line'
        ) from None
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, aligned))
    stats = ape.get_all_statistics()

    delta = min(rpe_delta_m, max(length / 2, 1e-6))
    try:
        rpe = metrics.RPE(
            metrics.PoseRelation.translation_part,
            delta=delta,
            delta_unit=Unit.meters,
            rel_delta_tol=0.2,
            all_pairs=True,
        )
        rpe.process_data((ref, est))
        rpe_rmse = float(rpe.get_statistic(metrics.StatisticsType.rmse))
        rpe_percent = float(np.mean(rpe.error) / delta * 100.0)
    except Exception:  # evo raises when no segment of that length exists (very short runs)
        rpe_rmse, rpe_percent = float('nan'), float('nan')
    return TrajectoryMetrics(
        matched_poses=int(ref.num_poses),
        path_length_m=length,
        ate_rmse_m=float(stats['rmse']),
        ate_mean_m=float(stats['mean']),
        ate_median_m=float(stats['median']),
        ate_max_m=float(stats['max']),
        rpe_percent=rpe_percent,
        rpe_delta_m=float(delta),
        rpe_rmse_m=rpe_rmse,
        end_point_error_m=end_error,
        drift_percent=float(end_error / length * 100.0) if length > 0 else float('nan'),
        rotation_end_error_deg=rotation_end_deg,
    )


@dataclass
class ErrorOverTime:
    """The error of each matched pose of an estimate (see :func:`error_over_time`); arrays of one length."""

    time_s: np.ndarray  # since the first matched pose [s]
    position_m: np.ndarray  # (n, 3) estimated minus true position, world axes (z up) [m]
    rotation_deg: np.ndarray  # (n, 3) rotation vector of R_est R_true^T, world axes [deg]
    heading_rad: np.ndarray  # the true heading (of the x axis, seen from above) [rad]
    yaw_rate_deg_s: np.ndarray  # the true yaw rate [deg/s]

    @property
    def along_m(self) -> np.ndarray:
        """Position error along the true heading [m]."""
        return np.cos(self.heading_rad) * self.position_m[:, 0] + np.sin(self.heading_rad) * self.position_m[:, 1]

    @property
    def left_m(self) -> np.ndarray:
        """Position error to the left of the true heading [m]."""
        return -np.sin(self.heading_rad) * self.position_m[:, 0] + np.cos(self.heading_rad) * self.position_m[:, 1]

    @property
    def up_m(self) -> np.ndarray:
        return self.position_m[:, 2]

    @property
    def tilt_deg(self) -> np.ndarray:
        """Roll/pitch part of the attitude error, whatever the heading [deg]."""
        return np.linalg.norm(self.rotation_deg[:, :2], axis=1)

    @property
    def heading_deg(self) -> np.ndarray:
        """Heading error (about the vertical, anticlockwise) [deg]."""
        return self.rotation_deg[:, 2]


def error_over_time(
    ground_truth: Trajectory | tuple[np.ndarray, np.ndarray],
    estimate: Trajectory | tuple[np.ndarray, np.ndarray],
    max_time_diff: float = 0.01,
) -> ErrorOverTime:
    """Error of every pose of ``estimate`` = (stamps [ns], (N, 4, 4) poses, REP-103 axes) that has a
    ground-truth pose within ``max_time_diff`` [s], both relative to their first matched pose (no alignment:
    the error as it builds up), in the world (z up): positions, and the attitude error ``R_est R_true^T`` as a
    rotation vector."""
    from scipy.spatial.transform import Rotation

    truth_stamps, truth_poses = in_map(ground_truth)
    stamps, poses = in_map(estimate)
    index = np.clip(np.searchsorted(truth_stamps, stamps), 1, max(len(truth_stamps) - 1, 1))
    nearest = np.where(
        np.abs(truth_stamps[index - 1] - stamps) <= np.abs(truth_stamps[index] - stamps), index - 1, index
    )
    matched = np.abs(truth_stamps[nearest] - stamps) <= max_time_diff * 1e9
    if matched.sum() < 2:
        raise ValueError(f'only {int(matched.sum())} poses of the estimate match the ground truth in time')
    truth = relative_to_first(truth_poses[nearest[matched]])
    ours = relative_to_first(poses[matched])
    time_s = (stamps[matched] - stamps[matched][0]) * 1e-9
    heading = np.arctan2(truth[:, 1, 0], truth[:, 0, 0])
    attitude = np.einsum('nij,nkj->nik', ours[:, :3, :3], truth[:, :3, :3])
    return ErrorOverTime(
        time_s=time_s,
        position_m=ours[:, :3, 3] - truth[:, :3, 3],
        rotation_deg=np.degrees(Rotation.from_matrix(attitude).as_rotvec()),
        heading_rad=heading,
        yaw_rate_deg_s=np.degrees(np.gradient(np.unwrap(heading), time_s)),
    )


def rigid_fit(points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """The 4x4 rotation and translation (no scale) that best maps (N, 3) ``points`` onto ``targets`` (least
    squares, Umeyama)."""
    mean_p, mean_t = points.mean(axis=0), targets.mean(axis=0)
    u, _, vt = np.linalg.svd((points - mean_p).T @ (targets - mean_t))
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    fit = np.eye(4)
    fit[:3, :3] = vt.T @ flip @ u.T
    fit[:3, 3] = mean_t - fit[:3, :3] @ mean_p
    return fit


@dataclass(frozen=True)
class ErrorInMap:
    """Position error [m] of the published poses against the ground truth expressed in the saved map's frame,
    without aligning the trajectory. ``anchor`` says how the map frame is placed in the simulated world:
    'first_keyframe' (where the map's first keyframe says it is: the map's own drift counts) or 'map_fit' (the
    rigid fit of all the map's keyframes to their true poses: the map's own error mostly does not)."""

    anchor: str
    median_m: float
    p95_m: float
    max_m: float
    poses: int
    map_median_m: float  # the map's keyframes against their ground truth in the same placement
    map_p95_m: float


def errors_in_map(
    bag: str | Path,
    map_source: dict,
    keyframe_stamps: np.ndarray,
    keyframe_poses: np.ndarray,
    stamps: np.ndarray,
    poses: np.ndarray,
) -> list[ErrorInMap]:
    """Position errors of ``poses`` ((N, 4, 4) REP-103, in a saved map's frame, at ``stamps`` [ns]) against the
    ground truth of a simulated ``bag`` expressed in that map's frame, without aligning the poses
    (:class:`ErrorInMap`, one per placement of the map in the world; see there). [] when
    either recording is not simulated, or they were made in different worlds. ``map_source``: the bundle's
    ``source``; ``keyframe_stamps`` / ``keyframe_poses`` (K, 4, 4) REP-103: the map's keyframes."""
    from lego_loam_py.inputs.sidecars import load_scenario
    from lego_loam_py.sim.output import same_scene, true_poses

    scenario, mapped = load_scenario(bag), map_source.get('simulated')
    if scenario is None or mapped is None or not len(poses) or not same_scene(scenario, mapped):
        return []
    here = {'config': scenario['config'], 'start_stamp_ns': int(scenario['recording']['start_stamp_ns'])}
    truth = true_poses(here, stamps)
    keyframes_true = true_poses(mapped, keyframe_stamps)
    out = []
    for anchor, world_from_map in (
        ('first_keyframe', keyframes_true[0] @ np.linalg.inv(keyframe_poses[0])),
        ('map_fit', rigid_fit(keyframe_poses[:, :3, 3], keyframes_true[:, :3, 3])),
    ):
        map_from_world = np.linalg.inv(world_from_map)
        error = np.linalg.norm((map_from_world @ truth)[:, :3, 3] - poses[:, :3, 3], axis=1)
        map_error = np.linalg.norm((map_from_world @ keyframes_true)[:, :3, 3] - keyframe_poses[:, :3, 3], axis=1)
        out.append(
            ErrorInMap(
                anchor,
                float(np.median(error)),
                float(np.percentile(error, 95)),
                float(error.max()),
                int(len(error)),
                float(np.median(map_error)),
                float(np.percentile(map_error, 95)),
            )
        )
    return out


def view_limits(
    trajectories: dict[str, np.ndarray], margin_fraction: float = 0.25, min_margin_m: float = 10.0
) -> tuple[float, float, float, float] | None:
    """(x min, x max, y min, y max) [m] of a top view that frames the trajectories ((N, 4, 4) poses, by name): their
    extent and a margin of ``margin_fraction`` of it, at least ``min_margin_m``, so that a short drive is seen
    with the map around it rather than lost in the whole map. None without a pose."""
    xy = [np.asarray(poses).reshape(-1, 4, 4)[:, :2, 3] for poses in trajectories.values()]
    xy = np.concatenate([a for a in xy if len(a)]) if any(len(a) for a in xy) else np.zeros((0, 2))
    if not len(xy):
        return None
    low, high = xy.min(axis=0), xy.max(axis=0)
    margin = max(min_margin_m, margin_fraction * float((high - low).max()))
    return float(low[0] - margin), float(high[0] + margin), float(low[1] - margin), float(high[1] + margin)


def plot_trajectories(
    path: str | Path, trajectories: dict[str, np.ndarray], map_points: np.ndarray | None = None, title: str = ''
) -> Path:
    """PNG of trajectories ((N, 4, 4) poses in REP-103 axes, by name) seen from above, over a map's points
    (N, 3+) coloured by height; the view frames the trajectories (:func:`view_limits`), or the map without one."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from lego_loam_py.formats import atomic_path

    figure, axes = plt.subplots(figsize=(9, 9), dpi=110)
    limits = view_limits(trajectories)
    if map_points is not None and len(map_points):
        pts = np.asarray(map_points)
        if limits is not None:  # (the points out of view would only cost time and thin out those in it)
            pts = pts[
                (pts[:, 0] >= limits[0])
                & (pts[:, 0] <= limits[1])
                & (pts[:, 1] >= limits[2])
                & (pts[:, 1] <= limits[3])
            ]
        if len(pts) > 400_000:
            pts = pts[np.random.default_rng(0).choice(len(pts), 400_000, replace=False)]
        if len(pts):
            z = pts[:, 2]
            lo, hi = np.percentile(z, [2, 98])
            axes.scatter(pts[:, 0], pts[:, 1], c=np.clip(z, lo, hi), s=0.2, cmap='gray_r', alpha=0.6, linewidths=0)
    colours = ['tab:green', 'tab:red', 'tab:blue', 'tab:orange', 'tab:purple']
    for (name, poses), colour in zip(trajectories.items(), colours):
        xy = np.asarray(poses).reshape(-1, 4, 4)[:, :2, 3]
        if len(xy) == 0:
            continue
        axes.plot(xy[:, 0], xy[:, 1], '-', color=colour, linewidth=1.6, label=name)
        axes.plot(xy[0, 0], xy[0, 1], 'o', color=colour, markersize=5)
    if limits is not None:
        axes.set_xlim(limits[0], limits[1])
        axes.set_ylim(limits[2], limits[3])
    axes.set_aspect('equal', adjustable='datalim')
    axes.set_xlabel('x [m] (map, REP-103)')
    axes.set_ylabel('y [m]')
    axes.grid(True, linewidth=0.3)
    if axes.get_legend_handles_labels()[0]:
        axes.legend(loc='best')
    if title:
        axes.set_title(title)
    figure.tight_layout()
    with atomic_path(path, suffix='.png') as temporary:
        figure.savefig(temporary)
    plt.close(figure)
    return Path(path)


def add_arguments(parser) -> None:
    parser.add_argument('estimate', help='estimated trajectory (TUM; REP-103 axes, e.g. trajectory.tum of a run)')
    parser.add_argument(
        'ground_truth', nargs='?', default=None, help='ground-truth TUM file, or a bag with ground_truth.tum beside it'
    )
    parser.add_argument('--bag', default=None, help='take the ground truth from beside this bag')
    parser.add_argument('--delta', type=float, default=10.0, help='RPE segment length [m] (default 10)')
    parser.add_argument('--max-time-diff', type=float, default=0.01, help='association tolerance [s]')
    parser.add_argument('--plot', default=None, help='write a PNG of both trajectories (top view)')
    parser.add_argument('--json', default=None, help='write the metrics as JSON')


def main(args) -> int:
    import json

    from lego_loam_py.formats import read_tum
    from lego_loam_py.inputs.sidecars import load_ground_truth

    source = args.bag or args.ground_truth
    if source is None:
        raise UsageError('give a ground-truth TUM file or --bag')
    try:
        estimate = Trajectory(*read_tum(args.estimate), 'map')
        path = Path(source)
        ground_truth = (
            Trajectory(*read_tum(path), 'map') if path.is_file() and path.suffix != '.bag' else load_ground_truth(path)
        )
        if ground_truth is None:
            raise LegoLoamError(f'no ground truth beside {source}')
        metrics = evaluate(ground_truth, estimate, rpe_delta_m=args.delta, max_time_diff=args.max_time_diff)
    except (OSError, ValueError) as exc:  # unreadable files, trajectories that cannot be compared (evo)
        raise LegoLoamError(str(exc)) from None
    print(metrics.summary())
    if args.json:
        from lego_loam_py.formats import write_text_atomic

        write_text_atomic(args.json, json.dumps(metrics.as_dict(), indent=2))
    if args.plot:
        first = int(np.argmin(np.abs(ground_truth.stamps_ns - estimate.stamps_ns[0])))
        aligned_truth = relative_to_first(ground_truth.poses[first:])
        drawn = {'ground truth': aligned_truth, 'estimate': relative_to_first(estimate.poses)}
        print(f'plot: {plot_trajectories(args.plot, drawn)}')
    return 0
