"""Where a run goes wrong: the error against time of the odometry and the mapped (fused) trajectory on a
simulated scenario, from its ground truth (lego_loam_py.evaluation.error_over_time).

    .venv/bin/python benchmarks/error_vs_time.py [--scenario corridor] [--imu off] [--turn-rate DEG_S]
                                                 [--duration S] [--every 5] [-p section.name:=value ...]

Both trajectories are taken relative to their first pose (no alignment), so the error is what has built up
by then: position along the true heading, to its left and up [m], the tilt of the attitude error (roll/pitch
in the world) and the heading error [deg]. One row every ``--every`` seconds (the mapped pose, then the
odometry's), marked ``turn`` when the true yaw rate passed 20 deg/s within the last interval; then the error
gained over each turn and each straight part, and in all.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from lego_loam_py.core.params import Params, parse_overrides  # noqa: E402
from lego_loam_py.evaluation import error_over_time  # noqa: E402
from lego_loam_py.inputs.sidecars import load_ground_truth  # noqa: E402
from lego_loam_py.offline import run_bag  # noqa: E402

TURN_DEG_S = 20.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenario', default='corridor')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--imu', choices=['on', 'off'], default='off')
    parser.add_argument('--turn-rate', type=float, default=0.0, help='whole in-place turns at this peak yaw rate')
    parser.add_argument('--duration', type=float, default=None)
    parser.add_argument('--every', type=float, default=5.0, help='seconds between two rows')
    parser.add_argument('-p', '--param', action='append', default=[], help='a parameter, section.name:=value')
    args = parser.parse_args()
    from lego_loam_py.sim.simulator import cached_scenario

    bag = cached_scenario(args.scenario, duration=args.duration, seed=args.seed, turn_rate=args.turn_rate)
    overrides = parse_overrides(args.param)
    params = Params().replace(**{k.replace('.', '__'): v for k, v in overrides.items()})
    result = run_bag(bag, params, imu_topic=None if args.imu == 'on' else '', progress=False)
    ground_truth = load_ground_truth(bag)
    mapped = error_over_time(ground_truth, result.trajectory(which='integrated'))
    odometry = error_over_time(ground_truth, result.trajectory(which='odometry'))
    print(
        f'{bag.name}: {args.scenario} seed {args.seed}, IMU {args.imu}, turn rate {args.turn_rate:g} deg/s, '
        f'{" ".join(args.param) or "default parameters"}; mapping steps '
        f'{result.counts.get("mapping_steps", 0)} ({result.counts.get("mapping_degenerate", 0)} degenerate)'
    )
    print(
        f'{"t s":>6s} {"":5s} | mapped: {"along":>6s} {"left":>6s} {"up":>6s} {"tilt":>5s} {"head":>6s} '
        f'| odometry: {"along":>6s} {"left":>6s} {"up":>6s} {"tilt":>5s} {"head":>6s}'
    )
    previous = 0.0
    for t in np.arange(args.every, mapped.time_s[-1] + 1e-9, args.every):
        i = min(int(np.searchsorted(mapped.time_s, t)), len(mapped.time_s) - 1)
        j = min(int(np.searchsorted(odometry.time_s, t)), len(odometry.time_s) - 1)
        window = (mapped.time_s > previous) & (mapped.time_s <= t)
        turning = np.abs(mapped.yaw_rate_deg_s[window]).max(initial=0.0) > TURN_DEG_S
        previous = t
        print(
            f'{mapped.time_s[i]:6.1f} {"turn" if turning else "":5s} | {"":7s} {_row(mapped, i)} '
            f'| {"":9s} {_row(odometry, j)}'
        )
    for name, errors in (('mapped', mapped), ('odometry', odometry)):
        print(f'{name}: ' + _gained(errors))


def _row(errors, i: int) -> str:
    return (
        f'{errors.along_m[i]:6.2f} {errors.left_m[i]:6.2f} {errors.up_m[i]:6.2f} {errors.tilt_deg[i]:5.2f} '
        f'{errors.heading_deg[i]:6.2f}'
    )


def _segments(errors) -> list[tuple[str, int, int]]:
    """(kind, first index, last index) of the turns (true yaw rate above TURN_DEG_S, merged across gaps under
    2 s) and of the straight parts between them."""
    turning = np.abs(errors.yaw_rate_deg_s) > TURN_DEG_S
    t = errors.time_s
    for gap_start in np.flatnonzero(turning[:-1] & ~turning[1:]):  # fill short gaps between turns
        later = np.flatnonzero(turning[gap_start + 1 :])
        if len(later) and t[gap_start + 1 + later[0]] - t[gap_start] < 2.0:
            turning[gap_start : gap_start + 1 + later[0]] = True
    edges = np.flatnonzero(np.diff(turning.astype(int))) + 1
    bounds = np.concatenate([[0], edges, [len(t)]])
    return [('turn' if turning[a] else 'straight', int(a), int(b) - 1) for a, b in zip(bounds[:-1], bounds[1:])]


def _gained(errors) -> str:
    """The error gained over each turn and each straight part (change of the world-frame position error [m]
    and of the tilt vector [deg] between the part's ends, each a 1 s mean to leave the scan-to-scan jitter out),
    then summed by kind."""

    def mean_at(i: int, values: np.ndarray) -> np.ndarray:
        return values[np.abs(errors.time_s - errors.time_s[i]) <= 0.5].mean(axis=0)

    totals: dict[str, list[float]] = {}
    lines = []
    for kind, a, b in _segments(errors):
        position = np.linalg.norm(mean_at(b, errors.position_m) - mean_at(a, errors.position_m))
        up = mean_at(b, errors.position_m)[2] - mean_at(a, errors.position_m)[2]
        tilt = np.linalg.norm(mean_at(b, errors.rotation_deg[:, :2]) - mean_at(a, errors.rotation_deg[:, :2]))
        seconds = errors.time_s[b] - errors.time_s[a]
        total = totals.setdefault(kind, [0.0, 0.0, 0.0])
        total[0] += seconds
        total[1] += position
        total[2] += tilt
        lines.append(
            f'  {kind:<8s} {errors.time_s[a]:6.1f}-{errors.time_s[b]:6.1f} s: position error '
            f'{position:5.2f} m (up {up:+5.2f}), tilt {tilt:4.1f} deg'
        )
    lines.append(
        '  in all: '
        + '; '.join(f'{kind}s {s:.0f} s: {p:.2f} m, {d:.1f} deg' for kind, (s, p, d) in sorted(totals.items()))
    )
    return '\n' + '\n'.join(lines)


if __name__ == '__main__':
    main()
