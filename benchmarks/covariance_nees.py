"""Are the published covariances consistent with the errors? NEES against the simulator's ground truth, per scenario.

    .venv/bin/python benchmarks/covariance_nees.py [--scenarios campus corridor aggressive] [--bags DIR ...]
                                                   [-p NAME:=VALUE ...] [--window 1.0] [--max-scans N]

For each recording the offline pipeline (the cores the nodes run) is run once with the given parameters, and the
normalised estimation error squared ``NEES = eᵀ Σ⁻¹ e`` (6 degrees of freedom: a consistent covariance averages 6;
the acceptance band is a factor 2, 3..12) is averaged over the lap for:

* **relative**: the odometry's motion over ``--window`` seconds (the scans' sweep motions and their covariances
  compounded, core.frames.compound_covariance) against the truth's motion over the same scans, the error in the
  window's first pose's axes;
* **mapped**: /aft_mapped_to_init's pose and covariance against the truth, aligned at the start as camera_init is
  (the first odometry pose), the error in camera_init's axes.

Also printed: the translational and rotational parts (3 dof each), the median, the share beyond the 95 % chi-square
bound, the scale on the residual variance that would bring the average to 6 (NEES scales as 1 / scale where no
variance is clipped), and where the odometry's 1 s translational covariance is largest the angle between its
principal axis and the direction of travel (in the corridor: along the corridor, the direction the walls do not
hold).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import numpy as np  # noqa: E402

from lego_loam_py.core.frames import compound_covariance, invert_pose, pose6_to_matrix, pose_error  # noqa: E402
from lego_loam_py.core.params import Params  # noqa: E402
from lego_loam_py.core.params.validation import params_from_mapping  # noqa: E402
from lego_loam_py.inputs import open_source  # noqa: E402
from lego_loam_py.offline import run_source  # noqa: E402

CHI2_95 = {3: 7.815, 6: 12.592}


def nees(error: np.ndarray, covariance: np.ndarray) -> float:
    return float(error @ np.linalg.solve(covariance, error))


def summary(values: list[float], dof: int) -> str:
    values = np.asarray(values)
    return (
        f'mean {values.mean():7.2f}  median {np.median(values):6.2f}  '
        f'> chi2_95 {np.mean(values > CHI2_95[dof]) * 100:5.1f} %  (n {len(values)})'
    )


def truth_at(stamps: np.ndarray, truth) -> tuple[np.ndarray, np.ndarray]:
    """(indices of ``stamps`` with a truth pose within 1 ms, those truth poses (camera axes))."""
    t_stamps, t_poses = truth.to('camera_init')
    index = np.clip(np.searchsorted(t_stamps, stamps), 1, len(t_stamps) - 1)
    nearer = np.where(np.abs(t_stamps[index - 1] - stamps) < np.abs(t_stamps[index] - stamps), index - 1, index)
    ok = np.abs(t_stamps[nearer] - stamps) < 1_000_000
    return np.flatnonzero(ok), t_poses[nearer[ok]]


def evaluate_run(result, truth, window_s: float) -> dict:
    stamps = np.asarray(result.stamps) + result.pose_time_offset_ns
    odometry = np.asarray(result.odometry)
    keep, truth_poses = truth_at(stamps, truth)
    odometry, motion_cov, stamps = odometry[keep], [result.motion_covariance[i] for i in keep], stamps[keep]
    mapped_stamps = np.asarray(result.mapped_stamps) + result.pose_time_offset_ns
    mapped_keep, mapped_truth = truth_at(mapped_stamps, truth)
    # The truth in camera_init: aligned at the first keyframe, which fixes the map frame (the sensor where the
    # odometry started, levelled by the IMU's roll and pitch when there is one; its covariance is ~0).
    first = result.mapper.keyframes[0]
    _, first_truth = truth_at(np.array([first.stamp_ns + result.pose_time_offset_ns]), truth)
    align = pose6_to_matrix(first.pose6) @ invert_pose(first_truth[0])
    truth_poses = align @ truth_poses
    out = {'relative': [], 'relative_t': [], 'relative_r': [], 'principal': [], 'errors': [], 'sigmas': []}
    period = np.median(np.diff(stamps)) * 1e-9
    steps = max(1, int(round(window_s / period)))
    # One sweep: is what each sweep's covariance says consistent on its own (errors independent from sweep to sweep
    # add up over a window as the compounded covariances do; errors that persist over sweeps grow faster)?
    single = []
    for k in range(1, len(stamps)):
        step = invert_pose(odometry[k - 1]) @ odometry[k]
        true = invert_pose(truth_poses[k - 1]) @ truth_poses[k]
        single.append(nees(pose_error(step, true), motion_cov[k]))
    out['single'] = single
    for i in range(len(stamps) - steps):
        j = i + steps
        if (stamps[j] - stamps[i]) * 1e-9 > 1.5 * window_s:  # (a gap: not one window)
            continue
        covariance, pose = np.zeros((6, 6)), np.eye(4)
        for k in range(i + 1, j + 1):
            step = invert_pose(odometry[k - 1]) @ odometry[k]
            covariance = compound_covariance(pose, covariance, step, motion_cov[k])
            pose = pose @ step
        true = invert_pose(truth_poses[i]) @ truth_poses[j]
        error = pose_error(pose, true)
        out['errors'].append(error)
        out['sigmas'].append(np.sqrt(np.diag(covariance)))
        out['relative'].append(nees(error, covariance))
        out['relative_t'].append(nees(error[:3], covariance[:3, :3]))
        out['relative_r'].append(nees(error[3:], covariance[3:, 3:]))
        values, vectors = np.linalg.eigh(covariance[:3, :3])
        travel = true[:3, 3] / max(np.linalg.norm(true[:3, 3]), 1e-9)  # in the window's first pose's axes
        angle = np.degrees(np.arccos(min(1.0, abs(float(vectors[:, 2] @ travel)))))
        out['principal'].append(((stamps[i] - stamps[0]) * 1e-9, np.sqrt(values[2]), np.sqrt(values[0]), angle))
    out.update(mapped=[], mapped_t=[], mapped_r=[], mapped_sigma=[])
    for k, true in zip(mapped_keep, align @ mapped_truth):
        covariance = result.mapped_covariance[k]
        if covariance is None:
            continue
        error = pose_error(result.mapped[k], true)
        out['mapped'].append(nees(error, covariance))
        out['mapped_t'].append(nees(error[:3], covariance[:3, :3]))
        out['mapped_r'].append(nees(error[3:], covariance[3:, 3:]))
        out['mapped_sigma'].append((np.sqrt(np.diag(covariance)[:3]), np.abs(error[:3])))
    return out


def report(name: str, out: dict, params: Params) -> None:
    fa, mo = params.feature_association.covariance_scale, params.map_optimization.covariance_scale
    print(f'\n== {name}')
    print(f'relative {args_window:.1f} s  NEES (6) {summary(out["relative"], 6)}')
    print(f'   translation (3) {summary(out["relative_t"], 3)}   rotation (3) {summary(out["relative_r"], 3)}')
    print(f'   scale for mean 6: feature_association.covariance_scale ~ {fa * np.mean(out["relative"]) / 6:.3g}')
    print(f'   one sweep NEES (6) {summary(out["single"], 6)}')
    errors, sigmas = np.array(out['errors']), np.array(out['sigmas'])
    print(
        '   RMS error / RMS sigma (x, y, z [m], rot x, y, z [rad], window axes): '
        + ', '.join(f'{e:.3g}/{s:.3g}' for e, s in zip(np.sqrt((errors**2).mean(0)), np.sqrt((sigmas**2).mean(0))))
    )
    if out['mapped']:
        print(f'mapped        NEES (6) {summary(out["mapped"], 6)}')
        print(f'   translation (3) {summary(out["mapped_t"], 3)}   rotation (3) {summary(out["mapped_r"], 3)}')
        print(f'   scale for mean 6: map_optimization.covariance_scale ~ {mo * np.mean(out["mapped"]) / 6:.3g}')
        sigma = np.array([s for s, _ in out['mapped_sigma']])
        error = np.array([e for _, e in out['mapped_sigma']])
        print(
            '   mapped sigma x/y/z at 25/50/100 % of the lap [m]: '
            + '  '.join(
                '/'.join(f'{v:.3f}' for v in sigma[min(len(sigma) - 1, int(q * len(sigma)))]) for q in (0.25, 0.5, 1.0)
            )
            + f'; |error| at the end {"/".join(f"{v:.3f}" for v in error[-1])}'
        )
        # A loop closure: the largest fall of the mapped position's sigma from one step to the next (after the first
        # steps, whose fall is the first registration's).
        norm = np.linalg.norm(sigma, axis=1)
        k = int(np.argmin(np.diff(norm[2:]))) + 2 if len(norm) > 3 else 0
        if len(norm) > 3 and norm[k + 1] < norm[k]:
            print(
                f'   largest fall of the mapped position sigma (a loop closure): {norm[k]:.3f} -> {norm[k + 1]:.3f} m '
                f'at step {k + 1} of {len(norm)} (|error| there {np.linalg.norm(error[k]):.3f} -> '
                f'{np.linalg.norm(error[k + 1]):.3f} m)'
            )
    principal = np.array(out['principal'])
    if len(principal):
        order = np.argsort(principal[:, 1])[::-1]
        top = order[: max(1, len(order) // 20)]  # the 5 % most uncertain windows
        print(
            f'   1 s translation: largest sigma median {np.median(principal[:, 1]):.4f} m, smallest '
            f'{np.median(principal[:, 2]):.4f} m; in the 5 % most uncertain windows the principal axis is '
            f'{np.median(principal[top, 3]):.0f} deg (median) from the direction of travel '
            f'(all windows: {np.median(principal[:, 3]):.0f} deg)'
        )
        for t, largest, smallest, angle in principal[top[:6]]:
            print(
                f'     t {t:6.1f} s: sigma {largest:.4f} m along an axis {angle:4.0f} deg from travel, {smallest:.4f} m'
            )


def main() -> None:
    global args_window
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenarios', nargs='*', default=['campus', 'corridor', 'aggressive'])
    parser.add_argument(
        '--bags', nargs='*', default=[], help='recordings with a ground truth (any that lego_loam_py run reads)'
    )
    parser.add_argument('-p', '--param', action='append', default=[], metavar='NAME:=VALUE')
    parser.add_argument('--window', type=float, default=1.0, help='relative motion window [s]')
    parser.add_argument('--max-scans', type=int, default=None)
    args = parser.parse_args()
    args_window = args.window
    overrides = {}
    for item in args.param:
        name, value = item.split(':=', 1)
        overrides[name] = yaml_value(value)
    params = params_from_mapping(overrides) if overrides else Params()
    bags = [Path(b) for b in args.bags]
    if not bags:
        from lego_loam_py.sim.simulator import cached_scenario

        bags = [cached_scenario(name) for name in args.scenarios]
    for bag in bags:
        weak = WeakestDirections()
        with open_source(bag, cloud_topic=params.sensor.point_cloud_topic, imu_topic=params.sensor.imu_topic) as source:
            truth = source.ground_truth()
            result = run_source(source, params, progress=False, max_scans=args.max_scans, listener=weak)
        report(bag.name, evaluate_run(result, truth, args.window), params)
        weak.report(truth)


class WeakestDirections:
    """A pipeline listener keeping, per odometry sweep and per mapping step, how well the registration held its
    worst direction (the smallest eigenvalue of its normal matrix) and the covariance it gave; :meth:`report`
    prints, for the 5 % least held, the principal axis of the translation covariance against the truth's direction
    of travel and the vertical (camera y)."""

    def __init__(self):
        self.sweeps, self.steps = [], []

    def __call__(self, event) -> None:
        from lego_loam_py.core.pipeline_events import MapStepped, ScanProcessed

        if isinstance(event, ScanProcessed) and event.features.odometry is not None:
            stats = event.features.odometry
            condition = np.nanmin([stats.surf_condition, stats.corner_condition, np.inf])
            covariance = event.features.motion_covariance
            if covariance is not None and np.isfinite(condition):
                self.sweeps.append((event.stamp_ns, condition, covariance, event.odometry))
        elif isinstance(event, MapStepped) and event.step.registration_covariance is not None:
            self.steps.append((event.stamp_ns, event.step.condition, event.step.registration_covariance, event.pose))

    def report(self, truth) -> None:
        t_stamps, t_poses = truth.to('camera_init')
        for name, items in (('odometry sweeps', self.sweeps), ('mapping steps', self.steps)):
            if len(items) < 20:
                continue
            conditions = np.array([c for _, c, _, _ in items])
            weakest = np.argsort(conditions)[: max(1, len(items) // 20)]
            rows = []
            for k in weakest:
                stamp, condition, covariance, pose = items[k]
                i = int(np.clip(np.searchsorted(t_stamps, stamp), 1, len(t_stamps) - 2))
                travel = t_poses[i + 1][:3, 3] - t_poses[i - 1][:3, 3]  # (truth: its camera_init, levelled alike)
                # The covariance's axes: the sweep start's (odometry) or camera_init (mapping); the travel in the
                # same axes.
                axes = pose[:3, :3] if name == 'odometry sweeps' else np.eye(3)
                travel = axes.T @ travel / max(np.linalg.norm(travel), 1e-9)
                values, vectors = np.linalg.eigh(covariance[:3, :3])
                axis = vectors[:, 2]
                vertical = axes.T @ np.array([0.0, 1.0, 0.0])
                rows.append(
                    (
                        (stamp - items[0][0]) * 1e-9,
                        condition,
                        np.sqrt(values[2]),
                        np.sqrt(values[0]),
                        np.degrees(np.arccos(min(1.0, abs(float(axis @ travel))))),
                        np.degrees(np.arccos(min(1.0, abs(float(axis @ vertical))))),
                    )
                )
            rows = np.array(rows)
            everything = np.array([np.sqrt(np.linalg.eigvalsh(c[:3, :3])[2]) for _, _, c, _ in items])
            print(
                f'   {name}: the 5 % least held (condition < {conditions[weakest].max():.3g}, median of all '
                f'{np.median(conditions):.3g}): largest translation sigma median {np.median(rows[:, 2]):.4f} m '
                f'(all: {np.median(everything):.4f} m), its axis {np.median(rows[:, 4]):.0f} deg from the travel, '
                f'{np.median(rows[:, 5]):.0f} deg from the vertical (medians)'
            )
            for row in rows[np.argsort(rows[:, 0])][:: max(1, len(rows) // 8)]:
                print(
                    f'     t {row[0]:6.1f} s condition {row[1]:8.3g}: sigma {row[2]:.4f} m along an axis '
                    f'{row[4]:3.0f} deg from travel, {row[5]:3.0f} deg from vertical; smallest {row[3]:.4f} m'
                )


def yaml_value(text: str):
    import yaml

    return yaml.safe_load(text)


args_window = 1.0

if __name__ == '__main__':
    main()
