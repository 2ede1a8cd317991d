"""Accuracy on the simulator's ground truth: odometry alone and the whole pipeline, per scenario.

    .venv/bin/python benchmarks/accuracy.py [--scenarios campus forest corridor aggressive] [--configs ...]
                                            [--bags bags/campus_8s ...] [--odometry-only] [--loop-closure on|off]
                                            [--turn-rate DEG_S] [--duration S] [--imu-profile consumer]

Scenarios are generated into the cache on first use (lego_loam_py.sim.simulator.cached_scenario). For each
bag and configuration the offline runner (the same cores as the nodes) is run with and without the IMU and
evo's metrics are printed: ATE RMSE (SE(3)-aligned), RPE over 10 m, end-point error and drift.
``--turn-rate`` adds the simulator's whole in-place turns (at 10 s, then every 30 s) peaking at that yaw rate,
e.g. ``--scenarios corridor --imu off --turn-rate 150 --duration 60``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import numpy as np  # noqa: E402

from benchmarks.common import run_shifted  # noqa: E402
from lego_loam_py.core.params import Params  # noqa: E402
from lego_loam_py.evaluation import error_over_time, evaluate  # noqa: E402
from lego_loam_py.inputs.sidecars import load_ground_truth  # noqa: E402
from lego_loam_py.offline import run_bag  # noqa: E402

CONFIGS = {
    'default': {},
    'original': dict(
        feature_association__relative_time_source='original',
        feature_association__odometry_model='original',
        feature_association__step_scale=0.05,
    ),
    'sweep_start_step0.05': dict(feature_association__step_scale=0.05),
    'sweep_start_step1': dict(feature_association__step_scale=1.0),
    'imu_prior_0': dict(feature_association__imu_rotation_prior=0.0),
    'imu_prior_1e5': dict(feature_association__imu_rotation_prior=1e5),
    'imu_prior_1e6': dict(feature_association__imu_rotation_prior=1e6),
    # Each use of the IMU left out on its own (issue 34): the rotation between sweeps held by the prior, the
    # mapping's roll and pitch blend, the IMU check.
    'imu_no_prior': dict(feature_association__imu_rotation_prior=0.0),
    'imu_no_blend': dict(map_optimization__imu_blend_weight=0.0),
    'imu_no_check': dict(imu__alignment_check=False),
    'imu_no_prior_no_blend': dict(feature_association__imu_rotation_prior=0.0, map_optimization__imu_blend_weight=0.0),
    'imu_orientation': dict(feature_association__imu_attitude='orientation'),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenarios', nargs='*', default=['campus', 'forest', 'corridor', 'aggressive'])
    parser.add_argument(
        '--bags', nargs='*', default=[], help='bags with ground truth beside them (instead of scenarios)'
    )
    parser.add_argument('--configs', nargs='*', default=['default'], choices=sorted(CONFIGS))
    parser.add_argument('--imu', choices=['both', 'on', 'off'], default='both')
    parser.add_argument('--odometry-only', action='store_true', help='skip mapOptimization')
    parser.add_argument(
        '--loop-closure',
        choices=['on', 'off'],
        default=None,
        help="switch loop closure on or off (default: the configuration's, on in the defaults)",
    )
    parser.add_argument(
        '--turn-rate',
        type=float,
        default=0.0,
        help='whole in-place turns peaking at this yaw rate [deg/s] in the scenarios (0: none)',
    )
    parser.add_argument('--duration', type=float, help='simulated seconds of each scenario (default: a whole lap)')
    parser.add_argument(
        '--skip',
        type=int,
        nargs='*',
        default=[0],
        help='runs without the first N clouds each (e.g. 0 1 2): their spread is the run-to-run noise',
    )
    parser.add_argument(
        '--imu-profile',
        default=None,
        help='the simulated IMU unit (lego_loam_py simulate --imu-profile: default, consumer, industrial)',
    )
    args = parser.parse_args()
    bags = [Path(b) for b in args.bags]
    if not bags:
        from lego_loam_py.sim.simulator import cached_scenario

        profile = {} if args.imu_profile is None else {'imu_profile': args.imu_profile}
        bags = [
            cached_scenario(name, duration=args.duration, turn_rate=args.turn_rate, **profile)
            for name in args.scenarios
        ]
    imu_modes = {'both': [False, True], 'on': [True], 'off': [False]}[args.imu]
    print(
        f'{"bag":<28s} {"config":<22s} {"imu":<4s} {"what":<9s} {"ATE m":>7s} {"RPE %":>7s} {"end m":>7s} '
        f'{"drift %":>8s} {"rot deg":>8s} {"up m":>6s} {"path m":>7s} {"x RT":>6s} {"IMU scans":>9s}'
    )
    for bag in bags:
        ground_truth = load_ground_truth(bag)
        name = bag.name if bag.name != bag.parent.name else bag.parent.name
        for config in args.configs:
            overrides = dict(CONFIGS[config])
            if args.loop_closure is not None:
                overrides['loop_closure__loop_closure_enable_flag'] = args.loop_closure == 'on'
            params = Params().replace(**overrides)
            for imu, skip in [(i, k) for i in imu_modes for k in args.skip]:
                start = time.perf_counter()
                if skip:
                    result = run_shifted(bag, params, imu, skip)
                else:
                    result = run_bag(
                        bag, params, imu_topic=None if imu else '', progress=False, mapping=not args.odometry_only
                    )
                realtime = result.bag_duration / (time.perf_counter() - start)
                rows = [('odometry', result.trajectory(which='odometry'))]
                if not args.odometry_only:
                    rows.append(('mapped', result.trajectory(which='integrated')))
                for what, estimate in rows:
                    m = evaluate(ground_truth, estimate)
                    # The vertical error as it builds up (both from their first pose), RMS over the drive.
                    up = float(np.sqrt(np.mean(error_over_time(ground_truth, estimate).up_m ** 2)))
                    label = config if not skip else f'{config} -{skip}'
                    print(
                        f'{name[:28]:<28s} {label:<22s} {"on" if imu else "off":<4s} {what:<9s} {m.ate_rmse_m:7.3f} '
                        f'{m.rpe_percent:7.2f} {m.end_point_error_m:7.3f} {m.drift_percent:8.2f} '
                        f'{m.rotation_end_error_deg:8.2f} {up:6.3f} {m.path_length_m:7.1f} {realtime:6.2f} '
                        f'{result.counts.get("scans_with_imu", 0):9d}',
                        flush=True,
                    )


if __name__ == '__main__':
    main()
