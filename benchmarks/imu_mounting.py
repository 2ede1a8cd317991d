"""The IMU mounted any way (issue 17): accuracy with the imu.* parameters, the misalignment check without them,
and what ``lego_loam_py calibrate`` recovers, on simulated recordings whose mounting is known.

    .venv/bin/python benchmarks/imu_mounting.py [--scenarios aggressive corridor] [--mounts yaw90 roll180 arbitrary]
                                                [--lever-arm 0.2 0.1 -0.2] [--time-offset 0.02] [--spread]
                                                [--json out.json]

For each scenario the recordings (aligned IMU, and each mounting with the lever arm and the clock offset) are
generated into the simulator's cache on first use. The lidar data of a scenario is the same whatever the IMU's
mounting, so one lidar-only run serves as the no-IMU figure and as the lidar odometry every calibration uses.
Rows: ATE RMSE, RPE over 10 m and drift (evo, see lego_loam_py eval) for the aligned IMU, no IMU, each mounting
with its parameters and without them (then also the data time from the first scan to the first warning and
the scans that used the IMU), and the calibration's rotation and offset errors with their 1-sigma.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from lego_loam_py.calibration import CalibrationRefused, calibrate, read_imu, refine_calibration  # noqa: E402
from lego_loam_py.core.frames import rpy_to_matrix  # noqa: E402
from lego_loam_py.core.params import Params  # noqa: E402
from lego_loam_py.evaluation import evaluate  # noqa: E402
from lego_loam_py.inputs.sidecars import load_ground_truth  # noqa: E402
from lego_loam_py.offline import run_bag  # noqa: E402
from lego_loam_py.sim.simulator import cached_scenario  # noqa: E402

MOUNTS = {'yaw90': (0.0, 0.0, 90.0), 'roll180': (180.0, 0.0, 0.0), 'arbitrary': (10.0, -20.0, 130.0)}


def accuracy(bag: Path, result) -> dict:
    m = evaluate(load_ground_truth(bag), result.trajectory())
    return dict(ate_m=m.ate_rmse_m, rpe_percent=m.rpe_percent, drift_percent=m.drift_percent)


def run(bag: Path, params: Params, imu: bool = True) -> tuple[dict, object]:
    start = time.perf_counter()
    result = run_bag(bag, params, imu_topic=None if imu else '', progress=False)
    row = accuracy(bag, result)
    row.update(
        seconds=time.perf_counter() - start,
        scans_with_imu=result.counts.get('scans_with_imu', 0),
        scans=result.counts.get('scans_processed', 0),
    )
    first_scan = result.stamps[0] * 1e-9 - 0.1 if result.stamps else 0.0  # (the first scan only initialises)
    warnings = [(node, event) for node, event in result.imu_alignment if not event.trusted]
    if warnings:
        row['first_warning_s'] = warnings[0][1].stamp - first_scan
        row['first_warning'] = f'{warnings[0][0]}: {warnings[0][1].message}'
        row['last_warning'] = f'{warnings[-1][0]}: {warnings[-1][1].message}'
    return row, result


def line(label: str, row: dict) -> str:
    text = (
        f'  {label:<34s} ATE {row["ate_m"]:6.3f} m  RPE {row["rpe_percent"]:5.2f} %  '
        f'drift {row["drift_percent"]:5.2f} %'
    )
    if 'first_warning_s' in row:
        text += f'  warning after {row["first_warning_s"]:4.1f} s, IMU on {row["scans_with_imu"]}/{row["scans"]} scans'
    elif 'scans_with_imu' in row:
        text += f'  no warning, IMU on {row["scans_with_imu"]}/{row["scans"]} scans'
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenarios', nargs='+', default=['aggressive', 'corridor'])
    parser.add_argument('--mounts', nargs='+', default=list(MOUNTS), choices=list(MOUNTS))
    parser.add_argument('--lever-arm', type=float, nargs=3, default=(0.2, 0.1, -0.2), help='[m] (0.3 m long)')
    parser.add_argument('--time-offset', type=float, default=0.02, help='[s]')
    parser.add_argument('--duration', type=float, default=None, help='simulated seconds (default: a whole lap)')
    parser.add_argument('--calibration-only', action='store_true', help='only the calibrations (and the no-IMU run)')
    parser.add_argument(
        '--spread',
        action='store_true',
        help='also the run-to-run spread: the aligned IMU with imu.time_offset +-1 us and no IMU with '
        'map_optimization.plane_min_aspect +-1e-4 (changes that should change nothing)',
    )
    parser.add_argument('--json', type=Path, default=None)
    args = parser.parse_args()
    report = {}
    for scenario in args.scenarios:
        print(
            f'{scenario}: IMU mounted with a {np.linalg.norm(args.lever_arm):.2f} m lever arm and '
            f'{1e3 * args.time_offset:g} ms late',
            flush=True,
        )
        aligned_bag = cached_scenario(scenario, duration=args.duration)
        rows = {}
        if not args.calibration_only:
            rows['aligned IMU'], _ = run(aligned_bag, Params())
            print(line('aligned IMU', rows['aligned IMU']), flush=True)
        rows['no IMU'], lidar_only = run(aligned_bag, Params(), imu=False)
        print(line('no IMU', rows['no IMU']), flush=True)
        if args.spread and not args.calibration_only:
            for sign in (1, -1):
                label = f'aligned IMU, time_offset {sign:+d} us'
                rows[label], _ = run(aligned_bag, Params().replace(imu__time_offset=sign * 1e-6))
                print(line(label, rows[label]), flush=True)
                label = f'no IMU, plane_min_aspect {0.2 + sign * 1e-4:g}'
                nudged = Params().replace(map_optimization__plane_min_aspect=0.2 + sign * 1e-4)
                rows[label], _ = run(aligned_bag, nudged, imu=False)
                print(line(label, rows[label]), flush=True)
        stamps_ns, poses = lidar_only.trajectory()
        for mount in args.mounts:
            rpy = MOUNTS[mount]
            bag = cached_scenario(
                scenario,
                duration=args.duration,
                imu_extrinsic_rpy=rpy,
                imu_lever_arm=tuple(args.lever_arm),
                imu_time_offset=args.time_offset,
            )
            params = Params().replace(
                imu__rotation_rpy=list(rpy), imu__translation=list(args.lever_arm), imu__time_offset=args.time_offset
            )
            if not args.calibration_only:
                rows[f'{mount}, parameters set'], _ = run(bag, params)
                print(line(f'{mount} {list(rpy)}, parameters set', rows[f'{mount}, parameters set']), flush=True)
                rows[f'{mount}, as it is'], _ = run(bag, Params())
                print(line(f'{mount}, without parameters', rows[f'{mount}, as it is']), flush=True)
                print(f'    {rows[f"{mount}, as it is"].get("last_warning", "")[:400]}', flush=True)
            try:
                imu = read_imu(bag, '/imu/data')
                first = calibrate(stamps_ns * 1e-9, poses[:, :3, :3], imu)  # (what calibrate_bag does)
                result = refine_calibration(bag, Params(), first, imu)
            except CalibrationRefused as exc:
                rows[f'{mount}, calibration'] = dict(refused=str(exc))
                print(f'  calibration refused: {exc}', flush=True)
                continue
            first_error = np.degrees(Rotation.from_matrix(first.rotation.T @ rpy_to_matrix(rpy)).magnitude())
            print(
                f'  calibration, first pass: error {first_error:.2f} deg, '
                f'{1e3 * (first.time_offset - args.time_offset):+.1f} ms',
                flush=True,
            )
            error = np.degrees(Rotation.from_matrix(result.rotation.T @ rpy_to_matrix(rpy)).magnitude())
            rows[f'{mount}, calibration'] = dict(
                result.to_dict(),
                rotation_error_deg=float(error),
                time_offset_error_ms=1e3 * (result.time_offset - args.time_offset),
            )
            print(
                f'  calibration: rotation_rpy {np.round(result.rotation_rpy, 2).tolist()} (error {error:.2f} deg; 1 '
                f'sigma {np.round(result.rotation_sigma_deg, 2).tolist()} deg), time_offset '
                f'{1e3 * result.time_offset:.1f} ms (error {1e3 * (result.time_offset - args.time_offset):+.1f} ms, '
                f'1 sigma {1e3 * result.time_offset_sigma:.1f} ms)'
                + (f'; REFUSED: {result.refused}' if result.refused else ''),
                flush=True,
            )
        report[scenario] = rows
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2, default=float) + '\n')


if __name__ == '__main__':
    main()
