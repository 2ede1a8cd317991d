"""``lego_loam_py batch`` against the same ``lego_loam_py run`` commands one after another: wall time, and the
trajectories compared bit for bit.

    .venv/bin/python benchmarks/bench_batch.py [--seconds 20] [--scenarios campus forest corridor aggressive]
                                               [--workers N] [--out DIR]

The recordings are the simulator's scenarios (``--seconds`` of each, generated into the cache on first use),
each run with the IMU and without it: 8 runs by default. Prints both wall times, their ratio and whether every
trajectory and map file of the batch equals the sequential run's.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lego_loam_py.batch import run_batch  # noqa: E402
from lego_loam_py.sim.simulator import cached_scenario  # noqa: E402

COMPARED = (
    'trajectory.tum',
    'trajectory_camera_init.tum',
    'map/global_map.pcd',
    'map/corner_map.pcd',
    'map/surface_map.pcd',
    'map/trajectory.pcd',
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--scenarios', nargs='*', default=['campus', 'forest', 'corridor', 'aggressive'])
    parser.add_argument('--workers', type=int, default=None)
    parser.add_argument('--out', type=Path, default=Path('/tmp/bench_batch'))
    args = parser.parse_args()
    bags = [cached_scenario(name, duration=args.seconds, progress=True) for name in args.scenarios]
    shutil.rmtree(args.out, ignore_errors=True)
    sequential = args.out / 'sequential'
    start = time.perf_counter()
    for bag in bags:
        for imu in (True, False):
            out = sequential / f'{bag.name}-{"imu" if imu else "no_imu"}'
            subprocess.run(
                [
                    sys.executable,
                    '-m',
                    'lego_loam_py.cli',
                    'run',
                    str(bag),
                    '-o',
                    str(out),
                    '--no-progress',
                    *([] if imu else ['--no-imu']),
                ],
                check=True,
                stdout=subprocess.DEVNULL,
            )
    sequential_s = time.perf_counter() - start
    start = time.perf_counter()
    result = run_batch(bags, None, args.out / 'batch', imu='both', workers=args.workers, progress=True)
    batch_s = time.perf_counter() - start
    same, compared = 0, 0
    for record in result.records:
        mine = args.out / 'batch' / 'runs' / record['run']
        theirs = sequential / f'{Path(record["recording_path"]).name}-{"imu" if record["imu"] else "no_imu"}'
        for name in COMPARED:
            if (theirs / name).is_file():
                compared += 1
                same += (mine / name).read_bytes() == (theirs / name).read_bytes()
    print(
        f'{len(result.records)} runs ({len(result.failed)} failed): sequential {sequential_s:.1f} s, '
        f'batch {batch_s:.1f} s = {batch_s / sequential_s:.2f}x; {same} of {compared} files identical'
    )


if __name__ == '__main__':
    main()
