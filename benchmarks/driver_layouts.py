"""Accuracy per driver layout: the same simulated recording in every driver's PointCloud2 layout, run offline.

    .venv/bin/python benchmarks/driver_layouts.py [--scenario campus] [--duration 20] [--seed 0]
                                                  [--layouts plain ouster ...] [--times azimuth point_time]

The scenario is simulated into the cache (as ``lego_loam_py simulate campus --duration 20``), rewritten into each
layout of lego_loam_py.sim.driver_layouts (same points, same IMU, same ground truth; cached beside it) and run
through the offline pipeline (``lego_loam_py run``'s cores, IMU on). For each relative-time source (``azimuth``,
the default, and ``point_time``: the sweeps deskewed with each layout's own per-point times) it prints the fused
trajectory's ATE RMSE, its difference to the plain layout's and whether the trajectory is the plain one exactly.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from lego_loam_py.core.params import Params  # noqa: E402
from lego_loam_py.evaluation import evaluate  # noqa: E402
from lego_loam_py.inputs.sidecars import load_ground_truth  # noqa: E402
from lego_loam_py.offline import run_bag  # noqa: E402
from lego_loam_py.sim.driver_layouts import LAYOUTS, cached_layout  # noqa: E402
from lego_loam_py.sim.simulator import cached_scenario  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenario', default='campus')
    parser.add_argument('--duration', type=float, default=20.0, help='simulated seconds')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--layouts', nargs='*', default=list(LAYOUTS), choices=LAYOUTS)
    parser.add_argument(
        '--times',
        nargs='*',
        default=['azimuth', 'point_time'],
        choices=['azimuth', 'point_time'],
        help='feature_association.relative_time_source values to run',
    )
    args = parser.parse_args()
    layouts = ['plain'] + [layout for layout in args.layouts if layout != 'plain']
    bag = cached_scenario(args.scenario, duration=args.duration, seed=args.seed)
    truth = load_ground_truth(bag)
    print(f'{args.scenario}, {args.duration:g} s, seed {args.seed}: {bag}')
    print(f'{"layout":<20s} {"times":<11s} {"ATE [m]":>8s} {"vs plain":>9s} {"trajectory":>13s} {"x RT":>6s}')
    for source in args.times:
        params = Params().replace(feature_association__relative_time_source=source)
        plain_ate, plain_poses = None, None
        for layout in layouts:
            path = bag if layout == 'plain' else cached_layout(bag, layout)
            start = time.perf_counter()
            result = run_bag(path, params, progress=False)
            realtime = result.bag_duration / (time.perf_counter() - start)
            stamps, poses = result.trajectory()
            ate = evaluate(truth, (stamps, poses)).ate_rmse_m
            if plain_ate is None:
                plain_ate, plain_poses = ate, poses
            same = (
                'identical'
                if np.array_equal(poses, plain_poses)
                else f'{np.abs(poses[:, :3, 3] - plain_poses[:, :3, 3]).max() * 1e3:.2f} mm off'
                if poses.shape == plain_poses.shape
                else 'other poses'
            )
            print(
                f'{layout:<20s} {source:<11s} {ate:8.4f} {100 * (ate - plain_ate) / plain_ate:+8.1f}% {same:>13s} '
                f'{realtime:6.2f}',
                flush=True,
            )


if __name__ == '__main__':
    main()
