"""Loop closure against the simulator's ground truth: does it make the map better, never worse?

    .venv/bin/python benchmarks/loop_closure.py [--scenarios campus forest corridor aggressive ...]
        [--imu both|on|off] [--modes off on original] [--closures] [--json out.json] [--seed N] [--skip 0 1 2]

For every scenario (default: all but ``straight``; generated into the cache on first use), IMU on and off, and
each mode (``off``: loop closure off; ``on``: the defaults' loop closure; ``original``: the C++ original's loop
closure, radius search + ICP with its fitness gate, variances = fitness, the last 50 keyframes as the map), the
offline runner is run and printed:

* ATE RMSE of the published trajectory (/integrated_to_init, as the robot had it) and of the final keyframe
  trajectory (the pose graph's estimate at the end, what the saved map is built on);
* loops accepted / rejected, and the **false** ones among the accepted: relative pose off from the ground
  truth by more than 0.5 m or 2 deg;
* the drift before the first closure: how far the graph's relative pose of the first accepted pair was from
  the truth before its constraint went in;
* the detection cost: CPU of loop detection and verification over the CPU of the mapping steps.

``--closures`` prints every accepted closure: the error of its constraint against the ground truth (translation,
rotation, and the z / roll / pitch parts in the latest keyframe's frame), its fitness and its variances.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks.common import run_shifted  # noqa: E402
from lego_loam_py.core.frames import camera_pose_to_lidar, pose6_to_matrix  # noqa: E402
from lego_loam_py.core.params import Params, default_params_file, load_params  # noqa: E402
from lego_loam_py.evaluation import evaluate  # noqa: E402
from lego_loam_py.inputs.sidecars import load_ground_truth  # noqa: E402
from lego_loam_py.offline import run_bag  # noqa: E402
from lego_loam_py.results import LoopClosures  # noqa: E402

FALSE_LOOP_M, FALSE_LOOP_DEG = 0.5, 2.0


def mode_params(mode: str) -> Params:
    base = Params()
    if mode == 'off':
        return base.replace(loop_closure__loop_closure_enable_flag=False)
    if mode == 'on':
        return base.replace(loop_closure__loop_closure_enable_flag=True)
    if mode == 'original':  # the original's loop closure on top of our defaults elsewhere
        original = load_params(default_params_file().parent / 'original.yaml')
        flat = {k: v for k, v in original.to_flat().items() if k.startswith('loop_closure.')}
        flat['loop_closure.loop_closure_enable_flag'] = True
        return base.replace(**{k.replace('.', '__'): v for k, v in flat.items()})
    raise ValueError(mode)


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> dict:
    """Error of a relative pose (4x4, lidar axes) against the truth, in the estimate's frame."""
    from scipy.spatial.transform import Rotation

    error = np.linalg.inv(truth) @ estimate
    roll, pitch, yaw = Rotation.from_matrix(error[:3, :3]).as_euler('xyz', degrees=True)
    angle = math.degrees(np.linalg.norm(Rotation.from_matrix(error[:3, :3]).as_rotvec()))
    return dict(
        translation_m=float(np.linalg.norm(error[:3, 3])),
        rotation_deg=angle,
        dx_m=float(error[0, 3]),
        dy_m=float(error[1, 3]),
        dz_m=float(error[2, 3]),
        roll_deg=float(roll),
        pitch_deg=float(pitch),
        yaw_deg=float(yaw),
    )


def closure_errors(mapper, ground_truth) -> list[dict]:
    """Every accepted closure of ``mapper`` against the ground truth."""
    gt_stamps, gt_poses = ground_truth
    stamps = [kf.stamp_ns for kf in mapper.keyframes]

    def truth(k: int) -> np.ndarray:
        i = int(np.argmin(np.abs(gt_stamps - stamps[k])))
        return gt_poses[i]

    out = []
    for loop in mapper.loops:
        if not loop.accepted or loop.relative is None:
            continue
        true_relative = np.linalg.inv(truth(loop.latest)) @ truth(loop.candidate)
        error = pose_error(camera_pose_to_lidar(loop.relative), true_relative)
        before = pose_error(camera_pose_to_lidar(loop.relative_before), true_relative)
        error.update(
            latest=loop.latest,
            candidate=loop.candidate,
            time_s=(stamps[loop.latest] - stamps[0]) * 1e-9,
            fitness=float(loop.fitness),
            detector=loop.detector,
            overlap=float(loop.overlap),
            variances=[
                float(v)
                for v in (loop.variances if loop.variances is not None else np.diag(np.linalg.inv(loop.information)))
            ],
            drift_before_m=before['translation_m'],
            drift_before_deg=before['rotation_deg'],
            false=bool(error['translation_m'] > FALSE_LOOP_M or error['rotation_deg'] > FALSE_LOOP_DEG),
        )
        out.append(error)
    return out


def run_one(bag: Path, mode: str, imu: bool, skip: int = 0) -> dict:
    params = mode_params(mode)
    ground_truth = load_ground_truth(bag)
    start = time.perf_counter()
    # Sequential, so that the CPU times of mapping and loop closure are the whole process's (open3d's threads too).
    if skip:
        result = run_shifted(bag, params, imu, skip)
    else:
        result = run_bag(bag, params, imu_topic=None if imu else '', progress=False, mapping_thread=False)
    wall = time.perf_counter() - start
    published = evaluate(ground_truth, result.trajectory(which='integrated'))
    optimized = evaluate(ground_truth, result.optimized_trajectory())
    mapper = result.mapper
    key_stamps = np.array([kf.stamp_ns for kf in mapper.keyframes], dtype=np.int64)
    key_poses = np.array([camera_pose_to_lidar(pose6_to_matrix(kf.pose6)) for kf in mapper.keyframes])
    keyframes = evaluate(ground_truth, (key_stamps, key_poses))
    closures = closure_errors(mapper, ground_truth) if params.loop_closure.loop_closure_enable_flag else []
    mapping_ms = float(np.sum(result.timings_ms.get('mapOptimization', [0.0])))
    loop_ms = float(np.sum(result.timings_ms.get('loop_closure', [0.0])))
    detection_ms = float(np.sum(result.timings_ms.get('loop_detection', [0.0])))
    verification = (
        [loop.cpu_ms for loop in mapper.loops]
        if params.loop_closure.method == 'verified'
        else result.timings_ms.get('loop_verification', [])
    )
    back_end_ms = float(np.sum(result.timings_ms.get('loop_verification', [0.0]))) - float(np.sum(verification))
    return dict(
        bag=bag.name,
        mode=mode,
        imu=imu,
        ate_published_m=published.ate_rmse_m,
        ate_published_max_m=published.ate_max_m,
        ate_keyframes_m=keyframes.ate_rmse_m,
        ate_optimized_m=optimized.ate_rmse_m,
        end_point_m=published.end_point_error_m,
        path_m=published.path_length_m,
        accepted=result.counts.get('loops_closed', 0),
        rejected=result.counts.get('loops_rejected', 0),
        false=sum(c['false'] for c in closures),
        drift_before_m=closures[0]['drift_before_m'] if closures else float('nan'),
        loop_cpu_share=loop_ms / mapping_ms if mapping_ms else float('nan'),
        wall_s=wall,
        detection_share=detection_ms / mapping_ms if mapping_ms else float('nan'),
        back_end_share=back_end_ms / mapping_ms if mapping_ms else float('nan'),
        verifications=len(verification),
        rejected_because=LoopClosures.of(mapper.loops, 0).rejected_because
        if params.loop_closure.loop_closure_enable_flag
        else {},
        verification_ms_median=float(np.median(verification)) if verification else float('nan'),
        mapping_steps=result.counts.get('mapping_steps', 0),
        closures=closures,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        '--scenarios',
        nargs='*',
        default=['campus', 'forest', 'corridor', 'aggressive', 'rows', 'open_road', 'long_road'],
    )
    parser.add_argument('--bags', nargs='*', default=[], help='bags with ground truth beside them')
    parser.add_argument('--imu', choices=['both', 'on', 'off'], default='both')
    parser.add_argument('--modes', nargs='*', default=['off', 'on'], choices=['off', 'on', 'original'])
    parser.add_argument('--duration', type=float, help="simulated seconds (default: the scenario's lap)")
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--closures', action='store_true', help='print every accepted closure')
    parser.add_argument('--json', help='write every figure here')
    parser.add_argument(
        '--skip',
        type=int,
        nargs='*',
        default=[0],
        help='also run without the first N clouds (the mapping steps on other scans): the spread '
        'of the results is the run-to-run noise',
    )
    args = parser.parse_args()
    bags = [Path(b) for b in args.bags]
    if not bags:
        from lego_loam_py.sim.simulator import cached_scenario

        bags = [cached_scenario(name, duration=args.duration, seed=args.seed) for name in args.scenarios]
    imu_modes = {'both': [True, False], 'on': [True], 'off': [False]}[args.imu]
    rows = []
    print(
        f'{"bag":<26s} {"imu":<4s} {"mode":<9s} {"ATE pub m":>9s} {"ATE kf m":>9s} {"max m":>7s} {"acc":>4s} '
        f'{"rej":>4s} {"false":>5s} {"drift m":>8s} {"cost %":>7s} {"wall s":>7s}',
        flush=True,
    )
    for bag in bags:
        name = bag.name if bag.name != bag.parent.name else bag.parent.name
        for imu in imu_modes:
            for mode, skip in [(m, k) for m in args.modes for k in args.skip]:
                row = run_one(bag, mode, imu, skip)
                row['bag'] = name if not skip else f'{name}+{skip}'
                rows.append(row)
                print(
                    f'{name[:26]:<26s} {"on" if imu else "off":<4s} {mode:<9s} {row["ate_published_m"]:9.3f} '
                    f'{row["ate_keyframes_m"]:9.3f} {row["ate_published_max_m"]:7.3f} {row["accepted"]:4d} '
                    f'{row["rejected"]:4d} {row["false"]:5d} {row["drift_before_m"]:8.3f} '
                    f'{100 * row["loop_cpu_share"]:7.2f} {row["wall_s"]:7.1f}',
                    flush=True,
                )
                print(f'    optimised trajectory (scan rate) ATE {row["ate_optimized_m"]:.3f} m', flush=True)
                print(
                    f'    mapping {row["mapping_steps"]} steps; detection {100 * row["detection_share"]:.2f} % of '
                    f'mapping CPU, graph updates {100 * row["back_end_share"]:.2f} %; {row["verifications"]} '
                    f'verifications, median {row["verification_ms_median"]:.0f} '
                    f'ms CPU each; rejected: {row["rejected_because"]}',
                    flush=True,
                )
                if args.closures:
                    for c in row['closures']:
                        print(
                            f'    t {c["time_s"]:6.1f} s  kf {c["latest"]:4d} -> {c["candidate"]:4d}  error '
                            f'{c["translation_m"]:.3f} m {c["rotation_deg"]:.2f} deg (dz {c["dz_m"]:+.3f} m, roll '
                            f'{c["roll_deg"]:+.2f}, pitch {c["pitch_deg"]:+.2f}, yaw {c["yaw_deg"]:+.2f} deg)  '
                            f'before {c["drift_before_m"]:.3f} m  {c["detector"]} fit {c["fitness"]:.3f}  '
                            f'sigma {np.sqrt(c["variances"][0]):.3g} rad / {np.sqrt(c["variances"][3]):.3g} m'
                            f'{"  FALSE" if c["false"] else ""}',
                            flush=True,
                        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))


if __name__ == '__main__':
    main()
