"""``lego_loam_py batch``: every recording x parameter set (x IMU on/off) through the offline pipeline on Dask,
resumable, with one report for the whole batch; ``--report DIR`` rebuilds the report of a batch folder."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lego_loam_py.errors import UsageError
from lego_loam_py.inputs import SOURCE_KINDS
from lego_loam_py.outputs import TRAJECTORY_FORMATS

__all__ = ['add_arguments', 'main']


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        'recordings', nargs='*', help="recordings (bags): paths or glob patterns (quote them: 'bags/*.mcap')"
    )
    parser.add_argument(
        '--list',
        action='append',
        default=[],
        metavar='FILE',
        help='a file listing recordings, one path or pattern per line (# comments)',
    )
    parser.add_argument(
        '-o',
        '--output',
        default='batch',
        help='batch folder: run directories and report (default: ./batch); running again into it resumes',
    )
    parser.add_argument(
        '-p',
        '--param',
        action='append',
        default=[],
        metavar='NAME:=V1,V2,...',
        help='a parameter and its values; several -p make a grid, e.g. -p feature_association.edge_threshold:=0.1,0.2',
    )
    parser.add_argument(
        '--params-file',
        action='append',
        default=[],
        type=Path,
        metavar='FILE',
        help='a parameter file; repeat it to add each as one more parameter set of the grid',
    )
    parser.add_argument(
        '--imu', choices=['on', 'off', 'both'], default='on', help='run with the IMU, without it, or both (default: on)'
    )
    parser.add_argument(
        '--scheduler',
        default=None,
        metavar='tcp://HOST:PORT',
        help='an existing Dask scheduler (default: a local cluster on 127.0.0.1)',
    )
    parser.add_argument(
        '--workers', type=int, default=None, help='worker processes of the local cluster (default: one per core)'
    )
    parser.add_argument(
        '--timeout',
        type=float,
        default=3600.0,
        metavar='S',
        help='a run still going after this many seconds is stopped and failed (default 3600)',
    )
    parser.add_argument(
        '--retries',
        type=int,
        default=1,
        help='times a failed run is tried again, in this batch or when resuming (default 1)',
    )
    inputs = parser.add_argument_group('recordings other than bags (as for run)')
    inputs.add_argument('--dataloader', choices=SOURCE_KINDS, default=None, help='force the kind of every recording')
    inputs.add_argument('--rate-hz', type=float, default=None, help='scans per second of folders without times.txt')
    inputs.add_argument('--model', choices=['auto', 'VLP-16'], default=None, help="a Velodyne pcap's model")
    parser.add_argument(
        '--format',
        choices=TRAJECTORY_FORMATS,
        default=None,
        dest='trajectory_format',
        help='trajectory files besides TUM (as for run)',
    )
    parser.add_argument(
        '--report',
        type=Path,
        default=None,
        metavar='DIR',
        help='only rebuild the report of the batch folder DIR from its finished runs',
    )
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')


def main(args: argparse.Namespace) -> int:
    from lego_loam_py.batch.report import collect_records, write_report

    if args.report is not None:
        if not (args.report / 'runs').is_dir():
            raise UsageError(f'{args.report} is not a batch folder (no runs/ in it)')
        records = collect_records(args.report)
        files = write_report(args.report, records)
        print(f'{len(records)} runs; report: {files["md"]}, {files["csv"]}')
        return 0
    from lego_loam_py.batch.driver import run_batch
    from lego_loam_py.batch.plan import expand_recordings, parameter_grid

    recordings = expand_recordings(args.recordings, args.list)
    if args.workers is not None and args.workers < 1:
        raise UsageError(f'--workers must be at least 1, got {args.workers}')
    run_args = [
        *(['--dataloader', args.dataloader] if args.dataloader else []),
        *(['--rate-hz', f'{args.rate_hz:g}'] if args.rate_hz is not None else []),
        *(['--model', args.model] if args.model else []),
        *(['--format', args.trajectory_format] if args.trajectory_format else []),
    ]
    result = run_batch(
        recordings,
        parameter_grid(args.param, args.params_file),
        args.output,
        imu=args.imu,
        run_args=run_args,
        scheduler=args.scheduler,
        workers=args.workers,
        timeout_s=args.timeout,
        retries=args.retries,
        progress=not args.no_progress,
        command_line=['lego_loam_py', *sys.argv[1:]] if sys.argv[1:2] == ['batch'] else None,
    )
    print(
        f'{len(result.records)} runs: {result.ran} run now, {result.reused} reused from an earlier batch, '
        f'{len(result.failed)} failed'
    )
    for record in result.failed:
        print(f'  failed: {record["run"]}: {record["error"]}')
    print(f'report: {result.report["md"]}, {result.report["csv"]}')
    return 1 if result.failed else 0
