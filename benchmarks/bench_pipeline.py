"""Speed of the whole pipeline: ms per scan per node, x real time offline, and DDS replay at 1x and 2x.

    .venv/bin/python benchmarks/bench_pipeline.py [--quick] [--rates 1 2] [--no-dds] [--no-write]

For each bag (the committed recordings bags/campus_8s and bags/aggressive_6s, and the full campus loop,
``cached_scenario('campus')``, 239 s, generated on first use; ``--quick`` skips it):

* **offline** (``lego_loam_py run``: the four cores in one process, as fast as the machine goes): ms per
  scan of imageProjection and featureAssociation and per mapping step of mapOptimization (median, p95),
  throughput as x real time, ATE against the ground truth;
* **DDS** (``lego_loam_py demo``: four processes, the player at ``--rates``, the recorder): the fraction of
  the bag's scans that reach /integrated_to_init, the nodes' own timings and the ATE.

Results are printed and written into benchmarks/results.md (the section between the bench_pipeline markers;
the rest of the file is kept), with the date, the machine and its load when the run started.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from lego_loam_py.core.params import Params  # noqa: E402
from lego_loam_py.evaluation import evaluate  # noqa: E402
from lego_loam_py.inputs.sidecars import load_ground_truth  # noqa: E402
from lego_loam_py.offline import run_bag  # noqa: E402

RESULTS = ROOT / 'benchmarks' / 'results.md'
BEGIN, END = '<!-- bench_pipeline:begin -->', '<!-- bench_pipeline:end -->'
NODES = ('imageProjection', 'featureAssociation', 'mapOptimization')


def _stats(values) -> dict | None:
    if not values:
        return None
    v = np.asarray(values, dtype=float)
    return dict(median=float(np.median(v)), p95=float(np.percentile(v, 95)), count=int(v.size))


def _ms(entry: dict | None) -> str:
    return f'{entry["median"]:.1f} / {entry["p95"]:.1f}' if entry else 'n/a'


def offline(bag: Path) -> dict:
    """One offline run with the default parameters."""
    start = time.perf_counter()
    result = run_bag(bag, Params(), progress=False)
    wall = time.perf_counter() - start
    stamps, poses = result.trajectory()
    ground_truth = load_ground_truth(bag)
    ate = evaluate(ground_truth, (stamps, poses)).ate_rmse_m if ground_truth is not None else float('nan')
    return dict(
        scans=result.counts.get('scans_in', 0),
        duration=result.bag_duration,
        wall=wall,
        realtime=result.bag_duration / wall,
        ate=ate,
        timings={name: _stats(result.timings_ms.get(name)) for name in NODES},
    )


def dds(bag: Path, rate: float) -> dict:
    """One DDS replay through the supervisor (lego_loam_py demo) on a leased ROS domain."""
    from lego_loam_py.demo import run_demo
    from lego_loam_py.testing.domains import DomainLease

    with DomainLease() as domain, tempfile.TemporaryDirectory(prefix='bench_pipeline_') as out:
        os.environ['ROS_DOMAIN_ID'] = str(domain)
        os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        result = run_demo(bag, out, rate=rate, announce=lambda _: None)
    s = result.summary
    timings = {name: t.as_dict() for name, t in s.timings_ms.items()}
    return dict(
        scans=s.scans_in,
        integrated=s.integrated,
        fraction=s.integrated_fraction,
        imu=s.scans_with_imu,
        processed=s.processed,
        ate=s.outputs.accuracy.ate_rmse_m if s.outputs.accuracy else float('nan'),
        timings={name: timings.get(name) for name in NODES + ('transformFusion',)},
        exit_code=result.exit_code,
        failures=s.failures,
    )


def _machine() -> str:
    model = platform.processor() or platform.machine()
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                model = line.split(':', 1)[1].strip()
                break
    except OSError:
        pass
    return f'{model}, {os.cpu_count()} cores, Python {platform.python_version()}'


def render(rows_offline: list, rows_dds: list, load: tuple, load_end: tuple, rates: list[float]) -> str:
    busy = ''
    if load[0] > 0.5 * (os.cpu_count() or 1):  # before the benchmark's own work: other jobs were running
        busy = (
            ' **Other work was running on the machine** (load average at the start): the timings are high '
            'and the DDS fractions low compared with an idle machine.'
        )
    lines = [
        BEGIN,
        '## Pipeline: `benchmarks/bench_pipeline.py`',
        '',
        f'{time.strftime("%Y-%m-%d")}, {_machine()}; load average (1 / 5 / 15 min) '
        f'{load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} when the run started, '
        f'{load_end[0]:.2f} / {load_end[1]:.2f} / {load_end[2]:.2f} when it ended (its own processes '
        f'included). Default parameters '
        f'(IMU on).{busy}',
        '',
        '**Offline** (`lego_loam_py run`: the four cores in one process, as fast as possible). ms per scan, '
        'median / p95; mapOptimization per mapping step (about one scan in four), CPU time of its worker thread, '
        'which overlaps the next scans of the other two.',
        '',
        '| bag | scans | data [s] | imageProjection [ms] | featureAssociation [ms] | mapOptimization [ms] '
        '| x real time | ATE RMSE [m] |',
        '|---|---|---|---|---|---|---|---|',
    ]
    for name, r in rows_offline:
        t = r['timings']
        lines.append(
            f'| {name} | {r["scans"]} | {r["duration"]:.1f} | {_ms(t["imageProjection"])} | '
            f'{_ms(t["featureAssociation"])} | {_ms(t["mapOptimization"])} | {r["realtime"]:.2f} | '
            f'{r["ate"]:.3f} |'
        )
    if rows_dds:
        played = ', '.join(f'{x:g}x' for x in rates)
        lines += [
            '',
            f'**Over DDS** (`lego_loam_py demo`: four processes, player at {played},'
            ' recorder; two cores for all of them). Reach = scans with an /integrated_to_init '
            '(the first scan only initialises the odometry, so 79/80 is everything); timings are the '
            "nodes' own, message conversion and publishing included.",
            '',
            '| bag | rate | reach /integrated_to_init | IMU used | imageProjection [ms] | '
            'featureAssociation [ms] | mapOptimization [ms] | transformFusion [ms] | ATE RMSE [m] |',
            '|---|---|---|---|---|---|---|---|---|',
        ]
        for name, rate, r in rows_dds:
            t = r['timings']
            failed = ' (FAILED: ' + '; '.join(r['failures']) + ')' if r['exit_code'] else ''
            lines.append(
                f'| {name} | {rate:g}x | {r["integrated"]}/{r["scans"]} = {r["fraction"]:.1%}{failed} | '
                f'{r["imu"]} | {_ms(t["imageProjection"])} | {_ms(t["featureAssociation"])} | '
                f'{_ms(t["mapOptimization"])} | {_ms(t.get("transformFusion"))} | {r["ate"]:.3f} |'
            )
    lines.append(END)
    return '\n'.join(lines)


def write_results(section: str) -> None:
    """Replace this benchmark's section of results.md (or add it), keeping everything else."""
    text = (
        RESULTS.read_text() if RESULTS.exists() else '# Benchmark results\n\nWritten by the scripts in this folder.\n'
    )
    if BEGIN in text and END in text:
        text = text[: text.index(BEGIN)] + section + text[text.index(END) + len(END) :]
    else:
        text = text.rstrip('\n') + '\n\n' + section + '\n'
    RESULTS.write_text(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='only the committed recordings (skip the campus loop)')
    parser.add_argument('--bags', nargs='*', type=Path, default=None, help='other bags instead of the defaults')
    parser.add_argument('--rates', nargs='*', type=float, default=[1.0, 2.0], help='DDS playback rates')
    parser.add_argument('--no-dds', action='store_true', help='offline only')
    parser.add_argument('--no-write', action='store_true', help=f'do not update {RESULTS.relative_to(ROOT)}')
    args = parser.parse_args()
    load = os.getloadavg()
    bags = args.bags or [ROOT / 'bags' / 'campus_8s', ROOT / 'bags' / 'aggressive_6s']
    names = [b.name for b in bags]
    if not args.bags and not args.quick:
        from lego_loam_py.sim.simulator import cached_scenario

        bags.append(Path(cached_scenario('campus')))
        names.append('campus loop (239 s)')
    rows_offline, rows_dds = [], []
    for name, bag in zip(names, bags):
        r = offline(bag)
        rows_offline.append((name, r))
        t = r['timings']
        print(
            f'offline {name:<22s} IP {_ms(t["imageProjection"]):>13s}  FA {_ms(t["featureAssociation"]):>13s}  '
            f'MO {_ms(t["mapOptimization"]):>13s} ms   {r["realtime"]:.2f}x real time   ATE {r["ate"]:.3f} m',
            flush=True,
        )
        if args.no_dds:
            continue
        for rate in args.rates:
            d = dds(bag, rate)
            rows_dds.append((name, rate, d))
            t = d['timings']
            print(
                f'dds {rate:g}x {name:<20s} {d["integrated"]}/{d["scans"]} = {d["fraction"]:.1%} reach '
                f'/integrated_to_init (IMU on {d["imu"]})   IP {_ms(t["imageProjection"])}  '
                f'FA {_ms(t["featureAssociation"])}  MO {_ms(t["mapOptimization"])} ms   ATE {d["ate"]:.3f} m'
                + (f'   FAILED: {d["failures"]}' if d['exit_code'] else ''),
                flush=True,
            )
    section = render(rows_offline, rows_dds, load, os.getloadavg(), args.rates)
    if not args.no_write:
        write_results(section)
        print(f'written to {RESULTS}')


if __name__ == '__main__':
    main()
