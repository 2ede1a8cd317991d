"""Simulator throughput per scenario: VLP-16 sweeps per second, including the IMU and writing the bag.

    .venv/bin/python benchmarks/bench_simulator.py [--scans 100] [--scenarios campus forest ...]
        [--layout packed --compress] [--preset HDL-32E]

Target: >= 20 VLP-16 scans/s (2x real time) for every scenario. Building the world (meshes, ray-casting
structure, trajectory) is timed separately: it happens once per run.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from lego_loam_py.sim.scenarios import SCENARIOS, build_world
from lego_loam_py.sim.simulator import SimConfig, simulate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--scans', type=int, default=100, help='sweeps per scenario (default 100 = 10 s)')
    parser.add_argument('--scenarios', nargs='+', default=list(SCENARIOS), choices=list(SCENARIOS))
    parser.add_argument('--layout', choices=('driver', 'packed'), default='driver')
    parser.add_argument('--compress', action='store_true')
    parser.add_argument('--preset', default='VLP-16')
    args = parser.parse_args()
    print(
        f'{args.preset}, {args.scans} sweeps per scenario, IMU 200 Hz, layout {args.layout}, '
        f'{"zstd-compressed " if args.compress else ""}mcap'
    )
    print(
        f'{"scenario":<11s} {"world build":>11s} {"scans/s":>8s} {"ms/scan":>8s} {"x real time":>11s} '
        f'{"points/scan":>11s} {"MB/scan":>8s}'
    )
    for name in args.scenarios:
        start = time.perf_counter()
        world = build_world(name, 0)
        build = time.perf_counter() - start
        config = SimConfig(
            name, duration=args.scans * 0.1, preset=args.preset, layout=args.layout, compress=args.compress
        )
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            result = simulate(config, Path(tmp) / name)
            elapsed = time.perf_counter() - start
            size = sum(p.stat().st_size for p in (Path(tmp) / name).glob('*.mcap'))
        rate = result.scans / elapsed
        print(
            f'{name:<11s} {build:10.2f}s {rate:8.1f} {1e3 / rate:8.1f} {rate * 0.1:11.1f} '
            f'{result.points / result.scans:11.0f} {size / result.scans / 1e6:8.2f}'
        )
        del world


if __name__ == '__main__':
    main()
