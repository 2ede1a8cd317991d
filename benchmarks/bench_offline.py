"""``lego_loam_py run`` as a user runs it: × real time, whole-process CPU and wall, on a VLP-16 and a 64-beam drive.

    .venv/bin/python benchmarks/bench_offline.py [--repeat 3] [--compare CHECKOUT] [--out DIR]

Recordings: the simulated 20 s campus drive with IMU (VLP-16, the one bench_dds.py plays) and the real KITTI
HDL-64E city drive of the shared data, lidar only (``-p sensor.preset:=HDL-64E --no-imu``). Each run is one
``python -m lego_loam_py.cli run REC --no-progress -o DIR`` child process. Per run:

* **× real time**: what the command prints, the recording's duration over the pipeline's wall time (reading the
  recording included; start-up and writing the outputs not);
* **CPU** and **wall** of the whole child process (start-up, imports, every process and thread, and writing the
  trajectories, maps, PNG and summary), from ``getrusage(RUSAGE_CHILDREN)`` and a clock around it.

``--compare CHECKOUT`` runs another checkout of the package the same way (its code on PYTHONPATH, this venv),
alternating with this one, for before/after figures on the same machine at the same hour. Medians, with every
run's value.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks.bench_dds import default_bag  # noqa: E402

SHARED = Path(os.environ.get('LEGO_LOAM_SHARED', ROOT.parent / 'shared'))
KITTI = SHARED / 'data' / 'real' / 'kitti_raw_0001_hdl64e'
REAL_TIME = re.compile(r'([0-9.]+)x real time')


def run_once(checkout: Path, recording: list[str], out: Path) -> dict:
    """One ``lego_loam_py run`` of ``checkout``'s code: {'x': × real time, 'cpu': s, 'wall': s}."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, '-m', 'lego_loam_py.cli', 'run', *recording, '--no-progress', '-o', str(out)],
        cwd=checkout,
        env={**os.environ, 'PYTHONPATH': str(checkout)},
        capture_output=True,
        text=True,
        timeout=1800,
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    found = REAL_TIME.search(done.stdout)
    if done.returncode != 0 or found is None:
        raise SystemExit(f'{checkout}: run failed ({done.returncode}):\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}')
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {'x': float(found.group(1)), 'cpu': cpu, 'wall': wall}


def describe(runs: list[dict], key: str, unit: str) -> str:
    values = [run[key] for run in runs]
    return f'{np.median(values):.2f}{unit} ({", ".join(f"{v:.2f}" for v in values)})'


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeat', type=int, default=3, help='runs of each checkout on each recording')
    parser.add_argument('--compare', type=Path, default=None, help='another checkout, run alternately')
    parser.add_argument('--seconds', type=float, default=20.0, help='length of the simulated campus drive [s]')
    parser.add_argument('--out', type=Path, default=None, help='folder for the runs (default: a temporary one)')
    args = parser.parse_args()
    recordings = {'campus (VLP-16, IMU)': [str(default_bag(args.seconds))]}
    if KITTI.is_dir():
        recordings['KITTI (HDL-64E, lidar only)'] = [str(KITTI), '-p', 'sensor.preset:=HDL-64E', '--no-imu']
    checkouts = {'this': ROOT} | ({'compared': args.compare.resolve()} if args.compare else {})
    with tempfile.TemporaryDirectory() as scratch:
        out = args.out or Path(scratch)
        for name, recording in recordings.items():
            runs = {label: [] for label in checkouts}
            for i in range(args.repeat):
                for label, checkout in checkouts.items():
                    runs[label].append(run_once(checkout, recording, out / f'{label}-{i}'))
            print(f'{name}:')
            for label, checkout in checkouts.items():
                print(
                    f'  {label} ({checkout}): {describe(runs[label], "x", "x")} real time; whole process: CPU '
                    f'{describe(runs[label], "cpu", " s")}, wall {describe(runs[label], "wall", " s")}'
                )


if __name__ == '__main__':
    main()
