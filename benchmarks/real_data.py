"""Real data: lego_loam_py and KISS-ICP side by side on one real recording, the same scans, the same evaluation.

    .venv/bin/python benchmarks/real_data.py [RECORDING] [--repeat N] [--out DIR] [-p NAME:=VALUE ...]
                                             [--preset HDL-64E] [--imu] [--json]

RECORDING: any recording ``lego_loam_py run`` reads that has a ground truth; by default the real KITTI city drive
``shared/data/real/kitti_raw_0001_hdl64e`` (108 HDL-64E scans as binary PCD, times.txt, ground_truth.tum).

* **lego_loam_py** runs as a user runs it, one child process:
  ``lego_loam_py run RECORDING -p sensor.preset:=HDL-64E --no-imu -o OUT --no-progress`` (``--preset``, ``--imu``
  and ``-p`` change it); its trajectory is OUT/trajectory.tum.
* **KISS-ICP** (a yardstick, never a dependency of the package) runs in a virtual environment of its own, made once
  with ``python3.11 -m venv`` and a pinned ``kiss-icp`` (``--kiss-venv``, default benchmarks/.venv-kiss-icp, reused
  while it holds that version), as one child process: ``benchmarks/kiss_icp_runner.py`` feeds the same points to
  its Python API with its default configuration. Scan folders of PCD or BIN files and KITTI sequences are read
  where they are; other recordings (bags, pcaps) are first written out as PCD scans, untimed, from what
  ``lego_loam_py.inputs`` yields, so that both systems see the same points.

Each child's whole-process CPU (user + system, every thread, start-up and imports included) comes from
``getrusage(RUSAGE_CHILDREN)`` around it, its wall time from a clock around it; per scan = CPU / scans in the
recording, x real time = recording duration / wall time. Both trajectories are evaluated by
``lego_loam_py.evaluation.evaluate`` against the recording's ground truth (``open_source(...).ground_truth()``):
ATE RMSE after an SE(3) alignment (no scale), RPE over 10 m segments in % of their length. With ``--repeat N`` the
systems run alternately N times each; the table gives the medians, every run is listed below it.

Diagnostic only (users compare with the stamps as given): each trajectory's ATE with its stamps shifted by the
best offset in [-0.12, +0.12] s (0.01 s steps), the reference interpolated at the shifted stamps (positions
linearly, rotations by slerp). It tells which instant of a sweep a pose describes, relative to its stamp.

Writes OUT/results.json, OUT/table.md (a row to paste into the README's table) and the runs under OUT/runs/;
``--json`` prints the JSON document instead of the table.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'benchmarks'))
from kiss_icp_runner import write_pcd  # noqa: E402

KISS_ICP_VERSION = '1.3.0'  # the newest release on the package index that installs here (Python 3.11)
KISS_RUNNER = ROOT / 'benchmarks' / 'kiss_icp_runner.py'
DEFAULT_KISS_VENV = ROOT / 'benchmarks' / '.venv-kiss-icp'
TIME_SHIFTS_S = np.round(np.arange(-12, 13) * 0.01, 2)
SYSTEMS = ('lego_loam_py', 'kiss_icp')


def shared_folder() -> Path:
    """shared/ beside the checkout (or beside the folder that holds it, as for a git worktree); LEGO_LOAM_SHARED
    overrides it."""
    if os.environ.get('LEGO_LOAM_SHARED'):
        return Path(os.environ['LEGO_LOAM_SHARED'])
    candidates = [ROOT.parent / 'shared', ROOT.parent.parent / 'shared']
    return next((c for c in candidates if c.is_dir()), candidates[0])


DEFAULT_RECORDING = shared_folder() / 'data' / 'real' / 'kitti_raw_0001_hdl64e'


# ---------------------------------------------------------------------------------------------- pure helpers


def interpolate_poses(stamps_ns: np.ndarray, poses: np.ndarray, at_ns: np.ndarray) -> np.ndarray:
    """(M, 4, 4) poses of a trajectory ((N,) ns stamps, increasing; (N, 4, 4) poses) at ``at_ns`` (within its
    time span): positions interpolated linearly, rotations by slerp."""
    from scipy.spatial.transform import Rotation, Slerp

    stamps_ns, at_ns = np.asarray(stamps_ns, dtype=np.int64), np.asarray(at_ns, dtype=np.int64)
    times, at = (stamps_ns - stamps_ns[0]) * 1e-9, (at_ns - stamps_ns[0]) * 1e-9
    out = np.tile(np.eye(4), (len(at), 1, 1))
    out[:, :3, 3] = np.column_stack([np.interp(at, times, np.asarray(poses)[:, i, 3]) for i in range(3)])
    out[:, :3, :3] = Slerp(times, Rotation.from_matrix(np.asarray(poses)[:, :3, :3]))(at).as_matrix()
    return out


def time_shift_scan(
    ground_truth: tuple[np.ndarray, np.ndarray],
    estimate: tuple[np.ndarray, np.ndarray],
    shifts_s: np.ndarray = TIME_SHIFTS_S,
) -> dict:
    """ATE RMSE [m] of ``estimate`` with ``shift`` [s] added to its stamps, for every shift, against the
    reference interpolated at the shifted stamps (:func:`interpolate_poses`), with the evaluation the benchmark
    uses (:func:`lego_loam_py.evaluation.evaluate`). The same poses at every shift: those whose stamps stay
    within the reference's time span at every shift. A pose stamped late by d seconds is best at shift -d."""
    from lego_loam_py.evaluation import evaluate

    truth_stamps, truth_poses = (np.asarray(a) for a in ground_truth)
    stamps, poses = np.asarray(estimate[0], dtype=np.int64), np.asarray(estimate[1])
    shifts_ns = np.round(np.asarray(shifts_s) * 1e9).astype(np.int64)
    inside = (stamps + shifts_ns.min() >= truth_stamps[0]) & (stamps + shifts_ns.max() <= truth_stamps[-1])
    ates = []
    for shift in shifts_ns:
        shifted = stamps[inside] + shift
        truth = interpolate_poses(truth_stamps, truth_poses, shifted)
        ates.append(evaluate((shifted, truth), (shifted, poses[inside])).ate_rmse_m)
    ates = np.array(ates)
    best = int(np.argmin(ates))
    zero = int(np.argmin(np.abs(shifts_ns)))
    return {
        'shifts_s': [float(s) for s in shifts_s],
        'ate_m': [float(a) for a in ates],
        'poses': int(inside.sum()),
        'best_shift_s': float(shifts_s[best]),
        'best_ate_m': float(ates[best]),
        'ate_at_zero_m': float(ates[zero]),
        'worst_ate_m': float(ates.max()),
    }


def median_summary(runs: list[dict]) -> dict:
    """The median over runs of every numeric figure of the run records."""
    keys = [k for k, v in runs[0].items() if isinstance(v, (int, float)) and not isinstance(v, bool) and k != 'run']
    return {k: float(np.median([r[k] for r in runs])) for k in keys}


MARKDOWN_HEADER = (
    '| drive | path | lego_loam_py ATE / RPE | KISS-ICP ATE / RPE '
    '| CPU per scan lego_loam_py / KISS-ICP | x real time lego_loam_py / KISS-ICP |\n'
    '|---|---|---|---|---|---|'
)


def markdown_row(name: str, path_m: float, lego: dict, kiss: dict) -> str:
    """A row of the README's real-data table from the two systems' median figures."""

    def accuracy(m):
        return f'{m["ate_m"]:.3f} m / {m["rpe_percent"]:.2f} %' if 'ate_m' in m else '-'

    return (
        f'| {name} | {path_m:.1f} m | {accuracy(lego)} | {accuracy(kiss)} | {lego["cpu_ms_per_scan"]:.0f} ms / '
        f'{kiss["cpu_ms_per_scan"]:.0f} ms | {lego["x_realtime"]:.2f}x / {kiss["x_realtime"]:.2f}x |'
    )


# ---------------------------------------------------------------------------------------------- running


def timed_child(command: list[str], log: Path, env: dict | None = None) -> tuple[float, float]:
    """Run ``command`` to its end (output to ``log``); (whole-process CPU [s], user + system of it and every child
    it waited for, all threads; wall time [s]). Exits with the log's tail when it fails."""
    log.parent.mkdir(parents=True, exist_ok=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    with open(log, 'w') as output:
        code = subprocess.run(
            command, stdout=output, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env
        ).returncode
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if code != 0:
        tail = '\n'.join(log.read_text(errors='replace').splitlines()[-15:])
        sys.exit(f'{command[0]} failed (exit {code}); {log}:\n{tail}')
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), wall


def kiss_environment() -> dict:
    """The environment for the KISS-ICP venv's Python: nothing of this venv's Python paths."""
    env = {k: v for k, v in os.environ.items() if k not in ('PYTHONPATH', 'PYTHONHOME', 'VIRTUAL_ENV')}
    env['PYTHONNOUSERSITE'] = '1'
    return env


def ensure_kiss_venv(venv: Path, version: str, python: str) -> Path:
    """The Python of a venv holding kiss-icp ``version``, made with ``python -m venv`` and pip the first time (a
    marker file says the install finished; a venv without it is made again)."""
    marker = venv / '.kiss-icp-installed'
    if marker.is_file() and marker.read_text().strip() == version:
        return venv / 'bin' / 'python'
    if venv.exists():
        if not (venv / 'pyvenv.cfg').is_file():
            sys.exit(f'{venv} exists and is not a virtual environment: give another --kiss-venv')
        shutil.rmtree(venv)
    print(f'creating {venv} with kiss-icp=={version} (once; about a minute)', file=sys.stderr, flush=True)
    subprocess.run([python, '-m', 'venv', str(venv)], check=True)
    log = venv / 'install.log'
    with open(log, 'w') as output:
        code = subprocess.run(
            [
                str(venv / 'bin' / 'python'),
                '-m',
                'pip',
                'install',
                '--disable-pip-version-check',
                f'kiss-icp=={version}',
            ],
            stdout=output,
            stderr=subprocess.STDOUT,
            env=kiss_environment(),
        ).returncode
    if code != 0:
        sys.exit(f'pip could not install kiss-icp=={version} into {venv}; see {log}')
    marker.write_text(version + '\n')
    return venv / 'bin' / 'python'


def scan_manifest(source, folder: Path) -> tuple[Path, str]:
    """A manifest of the recording's scans for the KISS-ICP runner (``<stamp ns> <path>`` a line) and how the
    scans reach it: the files themselves when the runner reads them (PCD ascii/binary, KITTI BIN), else PCD
    files written from what ``source`` yields (x y z, and ``time`` when the points have it)."""
    files = getattr(source, 'files', None) or getattr(source, 'scan_files', None)
    stamps = getattr(source, 'stamps', None)
    folder.mkdir(parents=True, exist_ok=True)
    manifest = folder / 'scans.txt'
    if files and stamps is not None and _runner_reads(files[0]):
        manifest.write_text(''.join(f'{int(s)} {Path(f).resolve()}\n' for s, f in zip(stamps, files)))
        return manifest, 'read where they are'
    from lego_loam_py.inputs import Scan

    scans = folder / 'scans'
    shutil.rmtree(scans, ignore_errors=True)
    scans.mkdir()
    lines = []
    for item in source.items():
        if isinstance(item, Scan):
            points = item.points
            path = scans / f'{len(lines):06d}.pcd'
            xyz = np.column_stack([points['x'], points['y'], points['z']])
            write_pcd(path, xyz, points['time'] if 'time' in (points.dtype.names or ()) else None)
            lines.append(f'{item.stamp_ns} {path}\n')
    manifest.write_text(''.join(lines))
    return manifest, f'written out as PCD into {scans} (untimed)'


def _runner_reads(path: Path) -> bool:
    path = Path(path)
    if path.suffix.lower() == '.bin':
        return True
    if path.suffix.lower() != '.pcd':
        return False
    with open(path, 'rb') as handle:
        head = handle.read(4096).decode('ascii', errors='replace')
    return any(line.split()[:2] in (['DATA', 'binary'], ['DATA', 'ascii']) for line in head.splitlines())


def lego_executable() -> str:
    beside = Path(sys.executable).with_name('lego_loam_py')
    found = str(beside) if beside.is_file() else shutil.which('lego_loam_py')
    if not found:
        sys.exit('lego_loam_py is not installed: run install.sh and this script with .venv/bin/python')
    return found


def evaluate_run(ground_truth, trajectory: Path) -> dict:
    from lego_loam_py.evaluation import evaluate, path_length
    from lego_loam_py.formats import read_tum

    estimate = read_tum(trajectory)
    figures = {'poses': int(len(estimate[0])), 'path_length_m': path_length(estimate[1])}
    if ground_truth is not None:
        metrics = evaluate(ground_truth, estimate)
        shift = time_shift_scan(ground_truth, estimate)
        figures.update(
            ate_m=metrics.ate_rmse_m,
            rpe_percent=metrics.rpe_percent,
            matched_poses=metrics.matched_poses,
            reference_path_m=metrics.path_length_m,
            best_shift_s=shift['best_shift_s'],
            ate_best_shift_m=shift['best_ate_m'],
            ate_shift_zero_m=shift['ate_at_zero_m'],
            ate_worst_shift_m=shift['worst_ate_m'],
            shift_poses=shift['poses'],
        )
        figures['time_shift'] = shift
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        'recording',
        nargs='?',
        default=str(DEFAULT_RECORDING),
        help='a recording lego_loam_py run reads, with ground truth (default: the KITTI city drive)',
    )
    parser.add_argument('--repeat', type=int, default=1, help='runs of each system, alternately (median reported)')
    parser.add_argument('--out', default=None, help='output folder (default: output/real_data/<recording>)')
    parser.add_argument(
        '-p',
        '--param',
        action='append',
        default=[],
        metavar='NAME:=VALUE',
        help='a parameter override passed to lego_loam_py run (repeatable)',
    )
    parser.add_argument('--preset', default='HDL-64E', help="lego_loam_py's sensor.preset ('' for none)")
    parser.add_argument('--imu', action='store_true', help='let lego_loam_py use the IMU (default: lidar only)')
    parser.add_argument('--dataloader', default=None, help='the kind of recording, as for lego_loam_py run')
    parser.add_argument('--rate-hz', type=float, default=10.0, help='scan rate of folders without times.txt')
    parser.add_argument('--kiss-venv', default=str(DEFAULT_KISS_VENV), help='the KISS-ICP virtual environment')
    parser.add_argument('--kiss-version', default=KISS_ICP_VERSION, help='the kiss-icp release it holds')
    parser.add_argument('--python', default='python3.11', help='the Python that makes the KISS-ICP venv')
    parser.add_argument('--json', action='store_true', help='print the results as JSON instead of the table')
    args = parser.parse_args()
    if args.repeat < 1:
        parser.error('--repeat must be at least 1')

    from lego_loam_py.inputs import open_source

    recording = Path(args.recording)
    source = open_source(recording, args.dataloader, rate_hz=args.rate_hz)
    name = source.name
    out = Path(args.out) if args.out else ROOT / 'output' / 'real_data' / name
    out.mkdir(parents=True, exist_ok=True)
    ground_truth = source.ground_truth()
    duration_s = source.duration_s
    kiss_python = ensure_kiss_venv(Path(args.kiss_venv).resolve(), args.kiss_version, args.python)
    manifest, scans_how = scan_manifest(source, out / 'kiss_icp_input')
    scans = len([line for line in manifest.read_text().splitlines() if line.strip()])
    source.close()

    lego_options = (['-p', f'sensor.preset:={args.preset}'] if args.preset else []) + ([] if args.imu else ['--no-imu'])
    extra = (
        [a for p in args.param for a in ('-p', p)]
        + (['--dataloader', args.dataloader] if args.dataloader else [])
        + (['--rate-hz', f'{args.rate_hz:g}'] if args.rate_hz != 10.0 else [])
    )
    runs = {system: [] for system in SYSTEMS}
    commands = {}
    kiss_info = {}
    for run in range(1, args.repeat + 1):
        for system in SYSTEMS:
            folder = out / 'runs' / f'{system}-{run}'
            shutil.rmtree(folder, ignore_errors=True)
            if system == 'lego_loam_py':
                command = [
                    lego_executable(),
                    'run',
                    str(recording),
                    *lego_options,
                    '-o',
                    str(folder),
                    '--no-progress',
                    *extra,
                ]
                cpu_s, wall_s = timed_child(command, out / 'runs' / f'{system}-{run}.log')
            else:
                command = [str(kiss_python), str(KISS_RUNNER), str(manifest), str(folder)]
                cpu_s, wall_s = timed_child(command, out / 'runs' / f'{system}-{run}.log', env=kiss_environment())
                kiss_info = json.loads((folder / 'info.json').read_text())
            commands[system] = command
            record = {
                'run': run,
                'cpu_s': cpu_s,
                'wall_s': wall_s,
                'cpu_ms_per_scan': cpu_s / scans * 1e3,
                'x_realtime': duration_s / wall_s,
            }
            record.update(evaluate_run(ground_truth, folder / 'trajectory.tum'))
            runs[system].append(record)
            if not args.json:
                accuracy = f', ATE {record["ate_m"]:.3f} m' if 'ate_m' in record else ''
                print(
                    f'run {run}/{args.repeat} {system}: CPU {cpu_s:.2f} s, wall {wall_s:.2f} s{accuracy}',
                    file=sys.stderr,
                    flush=True,
                )

    medians = {system: median_summary(runs[system]) for system in SYSTEMS}
    from lego_loam_py.evaluation import path_length

    # The drive's length: the whole reference (each system's matched part is in its figures).
    reference_path_m = path_length(ground_truth.poses) if ground_truth is not None else float('nan')
    row = markdown_row(name, reference_path_m, medians['lego_loam_py'], medians['kiss_icp'])
    results = {
        'recording': str(recording),
        'name': name,
        'scans': scans,
        'duration_s': duration_s,
        'has_ground_truth': ground_truth is not None,
        'reference_path_m': reference_path_m,
        'kiss_icp': kiss_info,
        'kiss_icp_scans': scans_how,
        'commands': {k: ' '.join(v) for k, v in commands.items()},
        'repeat': args.repeat,
        'median': medians,
        'runs': runs,
        'markdown_row': row,
    }
    (out / 'results.json').write_text(json.dumps(results, indent=2) + '\n')
    (out / 'table.md').write_text(MARKDOWN_HEADER + '\n' + row + '\n')
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print(report(results))
        print(f'\nresults: {out / "results.json"}, README row: {out / "table.md"}')


def report(results: dict) -> str:
    """The side-by-side table of :func:`main`'s results."""
    lego, kiss = results['median']['lego_loam_py'], results['median']['kiss_icp']
    info = results['kiss_icp']
    version = info.get('kiss_icp_version', '?')
    lines = [
        f'{results["name"]}: {results["scans"]} scans, {results["duration_s"]:.1f} s'
        + (
            f', reference path {results["reference_path_m"]:.1f} m'
            if results['has_ground_truth']
            else ', no ground truth'
        ),
        f'{"(median of " + str(results["repeat"]) + " runs each)" if results["repeat"] > 1 else "":<36s}'
        f'{"lego_loam_py":>14s}{"KISS-ICP " + version:>16s}',
    ]

    def line(label, key, fmt):
        if key in lego and key in kiss:
            lines.append(f'{label:<36s}{format(lego[key], fmt):>14s}{format(kiss[key], fmt):>16s}')

    line('ATE RMSE m (SE(3) aligned)', 'ate_m', '.3f')
    line('RPE % over 10 m', 'rpe_percent', '.2f')
    line('matched poses', 'matched_poses', '.0f')
    line('reference path m over those poses', 'reference_path_m', '.1f')
    line('path length m (estimated)', 'path_length_m', '.1f')
    line('whole-process CPU s', 'cpu_s', '.2f')
    line('wall s', 'wall_s', '.2f')
    line('CPU ms per scan', 'cpu_ms_per_scan', '.1f')
    line('x real time (wall)', 'x_realtime', '.2f')
    if 'ate_m' in lego:
        lines.append('diagnostic, not the comparison (stamps as given are): ATE with the stamps shifted')
        line('  poses within the reference at +-0.12 s', 'shift_poses', '.0f')
        line('  ATE m at 0 s, those poses', 'ate_shift_zero_m', '.3f')
        line('  best shift s in [-0.12, +0.12]', 'best_shift_s', '+.2f')
        line('  ATE m at the best shift', 'ate_best_shift_m', '.3f')
        line('  ATE m at the worst shift', 'ate_worst_shift_m', '.3f')
    if results['repeat'] > 1:
        lines.append('every run:')
        for system in SYSTEMS:
            for r in results['runs'][system]:
                accuracy = (
                    f'ATE {r["ate_m"]:.3f} m RPE {r["rpe_percent"]:.2f} % best shift {r["best_shift_s"]:+.2f} s '
                    if 'ate_m' in r
                    else ''
                )
                lines.append(
                    f'  {system:<13s} {r["run"]}: {accuracy}CPU {r["cpu_s"]:.2f} s '
                    f'({r["cpu_ms_per_scan"]:.1f} ms/scan) wall {r["wall_s"]:.2f} s ({r["x_realtime"]:.2f}x)'
                )
    config = info.get('config', {})
    if info:
        timed = info.get('scans_with_point_times', 0)
        deskew = (
            f'deskew on in its config; {timed} of {info["scans"]} scans had per-point times, so '
            + (
                'those were deskewed'
                if timed
                else 'no scan was deskewed (its preprocessor moved a probe scan '
                f'by {info.get("deskew_probe_shift_m", float("nan")):.3g} m under a 1 m, 10 deg motion)'
            )
            if info.get('deskew_enabled')
            else 'deskew off in its config'
        )
        threads = config['registration']['max_num_threads'] or 'all cores'
        lines += [
            f'KISS-ICP {version}, default configuration (max range {config["data"]["max_range"]:g} m, voxel '
            f'{config["mapping"]["voxel_size"]:g} m, threads: {threads}): {deskew}; '
            f'{info["register_frame_ms_median"]:.1f} ms median inside register_frame',
            f'KISS-ICP scans: {results["kiss_icp_scans"]}',
        ]
    lines += [
        f'lego_loam_py: {results["commands"].get("lego_loam_py", "")}',
        'CPU and wall: each whole child process (start-up and imports included, every thread)',
    ]
    lines += ['', MARKDOWN_HEADER, results['markdown_row']]
    return '\n'.join(lines)


if __name__ == '__main__':
    main()
