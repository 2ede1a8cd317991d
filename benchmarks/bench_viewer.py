"""What the Rerun viewer costs the offline pipeline: CPU per scan with and without --viewer-save.

    .venv/bin/python benchmarks/bench_viewer.py [BAG] [--rounds 3]

Runs ``run_source`` on the bag (default bags/campus_8s) alternately without and with a viewer that saves to a
temporary .rrd, ``--rounds`` times each, and prints the process CPU time per scan (every thread: the pipeline's,
the mapping worker's and Rerun's own encoder and writer threads) and wall time, medians over the rounds, and the
viewer's share. Outputs are checked to be the same with and without the viewer.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def one_run(bag: Path, viewer: bool, workdir: Path) -> tuple[float, float, int, np.ndarray, int]:
    """(CPU s, wall s, scans, fused poses, .rrd bytes) of one run."""
    from lego_loam_py.core.params import Params
    from lego_loam_py.inputs import open_source
    from lego_loam_py.offline import run_source

    rrd = workdir / f'run{time.monotonic_ns()}.rrd'
    with open_source(bag) as source:
        view = None
        if viewer:
            from lego_loam_py.viewer.pipeline_view import PipelineView
            from lego_loam_py.viewer.scene import SceneLog

            view = PipelineView(SceneLog(source.name, save=rrd), source.ground_truth())
        cpu, wall = time.process_time(), time.perf_counter()
        result = run_source(source, Params(), progress=False, listener=view)
        if view is not None:
            view.finish()
            view.scene.rec.disconnect()  # (the file is complete once the sink is closed)
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    size = rrd.stat().st_size if rrd.exists() else 0
    return cpu, wall, result.counts['scans_in'], np.array(result.integrated), size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('bag', nargs='?', type=Path, default=REPO / 'bags' / 'campus_8s')
    parser.add_argument('--rounds', type=int, default=3)
    args = parser.parse_args()
    figures = {False: [], True: []}
    reference = None
    with tempfile.TemporaryDirectory() as tmp:
        one_run(args.bag, True, Path(tmp))  # warm-up: imports, caches, Rerun's threads
        for _ in range(args.rounds):
            for viewer in (False, True):
                cpu, wall, scans, poses, size = one_run(args.bag, viewer, Path(tmp))
                reference = poses if reference is None else reference
                assert np.array_equal(poses, reference), 'the viewer changed the result'
                figures[viewer].append((cpu / scans * 1e3, wall / scans * 1e3, size))
    for viewer in (False, True):
        cpu = statistics.median(f[0] for f in figures[viewer])
        wall = statistics.median(f[1] for f in figures[viewer])
        size = statistics.median(f[2] for f in figures[viewer])
        label = 'with --viewer-save' if viewer else 'without viewer   '
        extra = f', .rrd {size / 1e6:.1f} MB' if viewer else ''
        print(f'{label}: CPU {cpu:6.1f} ms/scan, wall {wall:6.1f} ms/scan (median of {args.rounds}){extra}')
    base = statistics.median(f[0] for f in figures[False])
    with_viewer = statistics.median(f[0] for f in figures[True])
    base_wall = statistics.median(f[1] for f in figures[False])
    viewer_wall = statistics.median(f[1] for f in figures[True])
    print(
        f'viewer cost: CPU +{100 * (with_viewer - base) / base:.1f} %, '
        f'wall +{100 * (viewer_wall - base_wall) / base_wall:.1f} %'
    )


if __name__ == '__main__':
    main()
