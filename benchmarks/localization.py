"""Localization in a saved map against the simulator's ground truth (issue 18).

    .venv/bin/python benchmarks/localization.py [--scenarios campus forest aggressive] [--starts 20]
        [--drive 20] [--start-drive 4] [--out DIR] [--json out.json] [--skip-load] [--map-loops] [--stress]
        [--process-cpu N]

For every scenario: a map from one drive (the scenario's own lap, generated into the cache on first use, mapped
by ``lego_loam_py run``'s pipeline and saved as a bundle), then other drives through the same scene, driven the
other way round from another start (``simulate --route-start --reverse``), localized in it:

* **known**: with the true initial pose (as the map has the place: the nearest keyframe's map pose composed with
  the truth's offset from it), given as ``localization.initial_pose``;
* **off**: with an initial pose 3 m and 20 deg off;
* **none**: no initial pose (global relocalization);
* **kidnap**: no initial pose, 10 s cut out of the recording after 5 s;
* **other scenes**: drives through other worlds (the other scenarios, and the campus with other scenery on the
  same roads, seed 1) against every map, which must never localize;
* **starts**: ``--starts`` short drives (``--start-drive`` s) from points spread along the map's lap, every second
  one driven the other way, no initial pose: when the first fix came, and whether it was the right place.

Errors are in the saved map's frame without aligning the trajectory, with the map placed in the world two ways
(:func:`lego_loam_py.evaluation.errors_in_map`): by its first keyframe (the map's own drift counts) and by the
rigid fit of its keyframes to the truth. A fix is **wrong** when the first pose published after it is more than
1 m or 10 deg from the truth (map-fit placement); every published pose is checked too. CPU: mapOptimization's CPU
per step (the worker thread's) mapping each localization drive, run just before localizing it (same scans, same
load of the machine), against its CPU per step localizing; and the time to load a 1000-keyframe bundle (the
campus map's keyframes repeated side by side when it has fewer).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from lego_loam_py.core.frames import camera_pose_to_lidar, pose6_to_matrix  # noqa: E402
from lego_loam_py.core.mapping.map_bundle import MapBundle, read_bundle, write_bundle  # noqa: E402
from lego_loam_py.core.params import Params  # noqa: E402
from lego_loam_py.evaluation import errors_in_map, rigid_fit  # noqa: E402
from lego_loam_py.inputs.sidecars import load_scenario  # noqa: E402
from lego_loam_py.offline import run_bag  # noqa: E402
from lego_loam_py.sim.output import true_poses  # noqa: E402
from lego_loam_py.sim.simulator import cached_scenario  # noqa: E402
from lego_loam_py.testing.bags import cut_bag  # noqa: E402

WRONG_M, WRONG_DEG = 1.0, 10.0
# Where the localization drives start on each scenario's path [m of arc length] (in the mapped lap, the other
# way round), and the scenes a map must never localize in.
DRIVE_STARTS = {'campus': 120.0, 'forest': 100.0, 'aggressive': 200.0}
OTHER_SCENES = (('campus', 1), ('forest', 0), ('aggressive', 0), ('campus', 0))


def simulated(bag: Path) -> dict:
    scenario = load_scenario(bag)
    return {'config': scenario['config'], 'start_stamp_ns': int(scenario['recording']['start_stamp_ns'])}


def make_map(name: str, out: Path, loops: bool = False) -> tuple[Path, dict]:
    """The bundle of the scenario's own lap (made once into ``out``; ``loops``: with loop closure on) and the
    mapping's CPU figures."""
    directory = out / ('maps_with_loops' if loops else 'maps') / name
    stats_file = directory / 'mapping.json'
    if stats_file.is_file():
        return directory, json.loads(stats_file.read_text())
    bag = cached_scenario(name, progress=True)
    result = run_bag(bag, Params().replace(loop_closure__loop_closure_enable_flag=loops), progress=True)
    result.mapper.save(directory)
    steps = np.array(result.timings_ms['mapOptimization'])
    stats = dict(
        bag=str(bag),
        keyframes=len(result.mapper.keyframes),
        steps=len(steps),
        cpu_ms_per_step_median=float(np.median(steps)),
        cpu_ms_per_step_mean=float(steps.mean()),
        cpu_ms_per_scan=float(steps.sum() / result.counts['scans_in']),
    )
    stats_file.write_text(json.dumps(stats, indent=2))
    return directory, stats


def process_cpu_per_scan(bag: Path, params: Params, first: int = 100, last: int = 200) -> float:
    """Whole-process CPU (user + system, every thread) per scan [ms] of scans ``first``..``last`` of ``bag``: the
    run to ``last`` less the run to ``first``, so start-up, the map's loading and the first fix do not count."""

    def cpu(scans: int) -> float:
        start = time.process_time()
        run_bag(bag, params, progress=False, max_scans=scans)
        return time.process_time() - start

    return (cpu(last) - cpu(first)) / (last - first) * 1e3


def mapping_cpu(bag: Path) -> dict:
    """mapOptimization's CPU per step (its worker thread's) mapping ``bag`` with the default parameters."""
    result = run_bag(bag, Params(), progress=False)
    steps = np.array(result.timings_ms['mapOptimization'])
    return dict(
        steps=len(steps), cpu_ms_per_step_median=float(np.median(steps)), cpu_ms_per_step_mean=float(steps.mean())
    )


class TruthInMap:
    """The truth of a drive through a map's scene, in that map's frame (REP-103 poses)."""

    def __init__(self, bundle: MapBundle):
        self.keyframes = np.array([camera_pose_to_lidar(pose6_to_matrix(p)) for p in bundle.poses6])
        self.stamps = bundle.stamps_ns
        self.bundle_source = bundle.source
        self.source = bundle.source['simulated']
        self.keyframes_true = true_poses(self.source, bundle.stamps_ns)
        self.map_from_world = np.linalg.inv(rigid_fit(self.keyframes[:, :3, 3], self.keyframes_true[:, :3, 3]))

    def fit(self, drive: dict, stamps: np.ndarray) -> np.ndarray:
        """The truth at ``stamps`` with the map placed by the fit of its keyframes."""
        return self.map_from_world @ true_poses(drive, stamps)

    def local(self, drive: dict, stamp: int) -> np.ndarray:
        """The truth at ``stamp`` as the map has the place: the nearest keyframe's map pose and the true offset."""
        truth = true_poses(drive, np.array([stamp]))[0]
        k = int(np.argmin(np.linalg.norm(self.keyframes_true[:, :3, 3] - truth[:3, 3], axis=1)))
        return self.keyframes[k] @ np.linalg.inv(self.keyframes_true[k]) @ truth


def initial_pose(pose: np.ndarray, offset_m: float = 0.0, offset_deg: float = 0.0) -> list[float]:
    """``localization.initial_pose`` [x, y, z, roll, pitch, yaw] (m, deg) of a REP-103 pose, moved sideways by
    ``offset_m`` and turned by ``offset_deg``."""
    from scipy.spatial.transform import Rotation

    yaw, pitch, roll = Rotation.from_matrix(pose[:3, :3]).as_euler('ZYX', degrees=True)
    left = pose[:3, 1]
    x, y, z = pose[:3, 3] + offset_m * left
    return [float(x), float(y), float(z), float(roll), float(pitch), float(yaw + offset_deg)]


def localize(bag: Path, map_dir: Path, truth: TruthInMap | None, **overrides) -> dict:
    """One localization run and its figures."""
    params = Params().replace(
        map_optimization__mode='localization', map_optimization__map_path=str(map_dir), **overrides
    )
    result = run_bag(bag, params, progress=False)
    loc = result.mapper
    stamps, poses = result.trajectory()
    first = result.first_scan_ns
    out = dict(
        bag=str(bag),
        scans=result.counts['scans_in'],
        published=int(len(stamps)),
        localized_fraction=len(stamps) / max(result.counts['scans_in'], 1),
        time_to_first_fix_s=None if loc.first_fix_ns is None else (loc.first_fix_ns - first) * 1e-9,
        fixes=loc.counters.get('fixes', 0),
        losses=loc.counters.get('losses', 0),
        events=[dict(t=round((e.stamp_ns - first) * 1e-9, 2), kind=e.kind, detail=e.detail) for e in loc.events],
        counters=dict(loc.counters),
    )
    out['verifications'] = verifications_of(loc, bag, truth)
    attempts: dict[int, float] = {}
    for v in out['verifications']:  # (an attempt's registrations share its stamp)
        attempts[v['stamp_ns']] = attempts.get(v['stamp_ns'], 0.0) + v['cpu_ms']
    out['attempt_cpu_ms'] = list(attempts.values())
    steps = result.timings_ms.get('mapOptimization', [])
    out['cpu_ms_per_localized_step_median'] = float(np.median(steps)) if steps else None
    out['cpu_ms_per_localized_step_mean'] = float(np.mean(steps)) if steps else None
    if truth is None or not len(stamps):
        out['wrong_fixes'] = out['fixes']  # (another scene: every fix is wrong)
        return out
    drive = simulated(bag)
    errors = errors_in_map(bag, truth.bundle_source, truth.stamps, truth.keyframes, stamps, poses)
    out['error_in_map'] = [e.__dict__ for e in errors]
    true = truth.fit(drive, stamps)
    distance = np.linalg.norm(true[:, :3, 3] - poses[:, :3, 3], axis=1)
    turn = np.degrees(np.arccos(np.clip((np.einsum('nij,nij->n', true[:, :3, :3], poses[:, :3, :3]) - 1) / 2, -1, 1)))
    out['wrong_poses'] = int(((distance > WRONG_M) | (turn > WRONG_DEG)).sum())
    wrong = 0
    for event in loc.events:
        if event.kind == 'fix':
            after = np.searchsorted(stamps, event.stamp_ns)
            if after < len(stamps) and (distance[after] > WRONG_M or turn[after] > WRONG_DEG):
                wrong += 1
    out['wrong_fixes'] = wrong
    out['max_error_m'] = float(distance.max())
    return out


def verifications_of(loc, bag: Path, truth: TruthInMap | None) -> list[dict]:
    """Every candidate place the run registered: its gates' figures, whether it passed, and whether it was the right
    place (within WRONG_M of the truth; never in another scene)."""
    drive = simulated(bag) if truth is not None else None
    out = []
    for stamp, v in loc.verifications:
        right = False
        if drive is not None:
            true = truth.fit(drive, np.array([stamp]))[0]
            right = bool(np.linalg.norm(true[:3, 3] - v.pose[:3, 3]) < WRONG_M)
        out.append(
            dict(
                stamp_ns=int(stamp),
                overlap=v.overlap,
                rmse=v.rmse,
                edge_overlap=v.edge_overlap,
                constraint=v.constraint,
                accepted=v.accepted,
                right=right,
                cpu_ms=v.cpu_ms,
            )
        )
    return out


def gate_figures(verifications: list[dict]) -> dict:
    """min / median / max of each gate's figure over the right and the wrong places registered."""
    out = {}
    for kind, rows in (
        ('right', [v for v in verifications if v['right']]),
        ('wrong', [v for v in verifications if not v['right']]),
    ):
        figures = {
            key: [v[key] for v in rows if math.isfinite(v[key])]
            for key in ('overlap', 'rmse', 'edge_overlap', 'constraint')
        }
        out[kind] = dict(
            count=len(rows),
            accepted=sum(v['accepted'] for v in rows),
            **{
                key: [round(min(x), 3), round(float(np.median(x)), 3), round(max(x), 3)] if x else None
                for key, x in figures.items()
            },
        )
    return out


def load_time(map_dir: Path, out: Path, keyframes: int = 1000, repeat: int = 3) -> dict:
    """Seconds to load (read, check, index) a ``keyframes``-keyframe bundle built from the map in ``map_dir``."""
    from lego_loam_py.core.localization.localizer import Localization

    bundle = read_bundle(map_dir)
    copies = math.ceil(keyframes / len(bundle))
    big = out / f'bundle_{keyframes}'
    if not (big / 'map_bundle.json').is_file():
        poses, corner, surf, outlier = [], [], [], []
        for c in range(copies):
            shifted = bundle.poses6.copy()
            shifted[:, 3] += 300.0 * c  # (side by side, camera x = lidar y)
            poses.append(shifted)
            corner += bundle.corner
            surf += bundle.surf
            outlier += bundle.outlier
        n = keyframes
        maps = [
            np.concatenate([np.asarray(m) + np.array([300.0 * c, 0, 0, 0], np.float32) for c in range(copies)])
            for m in (bundle.corner_map, bundle.surface_map)
        ]
        write_bundle(
            big,
            MapBundle(
                np.arange(n, dtype=np.int64),
                np.concatenate(poses)[:n],
                corner[:n],
                surf[:n],
                outlier[:n],
                [],
                maps[0],
                maps[1],
                bundle.parameters,
                bundle.source,
            ),
        )
    params = Params().replace(map_optimization__mode='localization', map_optimization__map_path=str(big))
    seconds = []
    for _ in range(repeat):
        start = time.perf_counter()
        Localization.load(params)
        seconds.append(time.perf_counter() - start)
    size = sum(p.stat().st_size for p in big.iterdir())
    return dict(keyframes=keyframes, bytes=size, seconds=seconds)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--scenarios', nargs='+', default=['campus', 'forest', 'aggressive'])
    parser.add_argument('--starts', type=int, default=20, help='start points of the relocalization test')
    parser.add_argument('--start-scenarios', nargs='+', default=['campus', 'forest'])
    parser.add_argument('--drive', type=float, default=20.0, help='length of the localization drives [s]')
    parser.add_argument('--start-drive', type=float, default=4.0, help='length of the start-point drives [s]')
    parser.add_argument('--out', type=Path, default=Path('output/bench_localization'))
    parser.add_argument('--json', type=Path, default=None)
    parser.add_argument('--skip-load', action='store_true')
    parser.add_argument(
        '--process-cpu',
        type=int,
        default=0,
        metavar='N',
        help='also whole-process CPU per scan, mapping vs localizing the drive, N times each',
    )
    parser.add_argument(
        '--map-loops',
        action='store_true',
        help='make the maps with loop closure on (less drift in '
        'the map, so its frame is nearer the world the truth is in)',
    )
    parser.add_argument(
        '--stress',
        action='store_true',
        help='also run the other scenes with every keyframe a '
        'candidate place (relocalization_threshold 1): the registration alone must turn them down',
    )
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    report: dict = {'maps': {}, 'drives': {}, 'other_scenes': [], 'starts': {}}
    maps = {}
    fresh = {}  # scenario: its map was made in this run (its mapping CPU then measured just before the drives)
    for name in args.scenarios:
        maps_dir = args.out / ('maps_with_loops' if args.map_loops else 'maps')
        fresh[name] = not (maps_dir / name / 'mapping.json').is_file()
        map_dir, stats = make_map(name, args.out, args.map_loops)
        maps[name] = map_dir
        report['maps'][name] = stats
        print(
            f'{name}: map of {stats["keyframes"]} keyframes, mapping {stats["cpu_ms_per_step_median"]:.1f} ms CPU '
            f'per step (median; mean {stats["cpu_ms_per_step_mean"]:.1f})',
            flush=True,
        )
        truth = TruthInMap(read_bundle(map_dir))
        bag = cached_scenario(name, duration=args.drive, route_start=DRIVE_STARTS[name], reverse=True)
        drive = simulated(bag)
        with open(Path(bag) / 'ground_truth.tum') as f:  # the second scan: when the first mapping step runs
            second = int(round(float([line for line in f if not line.startswith('#')][1].split()[0]) * 1e9))
        hint = truth.local(drive, second)
        kidnap = args.out / f'{name}_kidnap'
        if not kidnap.exists():
            cut_bag(bag, kidnap, 5.0, 10.0)
        cases = {
            'known': (bag, dict(localization__initial_pose=initial_pose(hint))),
            'off': (bag, dict(localization__initial_pose=initial_pose(hint, 3.0, 20.0))),
            'none': (bag, {}),
            'kidnap': (kidnap, {}),
        }
        report['drives'][name] = {}
        # The mapping's CPU on this very drive, run just before localizing it: the same scans in the same
        # conditions of the machine (a shared machine's load changes over minutes).
        report['drives'][name]['mapping'] = mapping = mapping_cpu(bag)
        print(
            f'  mapping this drive: mapOptimization {mapping["cpu_ms_per_step_mean"]:.1f} ms CPU per step (mean; '
            f'median {mapping["cpu_ms_per_step_median"]:.1f})',
            flush=True,
        )
        if args.process_cpu:  # the whole process, as the user pays it: mapping vs localizing, alternately
            localizing = Params().replace(
                map_optimization__mode='localization', map_optimization__map_path=str(map_dir), **cases['known'][1]
            )
            pairs = [
                (process_cpu_per_scan(bag, Params()), process_cpu_per_scan(bag, localizing))
                for _ in range(args.process_cpu)
            ]
            report['drives'][name]['process_cpu_ms_per_scan'] = pairs
            print(
                '  whole process CPU per scan (scans 100-200), mapping / localizing: '
                + ', '.join(f'{m:.1f} / {loc:.1f} ms' for m, loc in pairs)
                + f' (ratio of the means {np.mean([p[1] for p in pairs]) / np.mean([p[0] for p in pairs]):.2f})',
                flush=True,
            )
        for case, (case_bag, overrides) in cases.items():
            figures = localize(case_bag, map_dir, truth, **overrides)
            report['drives'][name][case] = figures
            errors = {e['anchor']: e for e in figures.get('error_in_map', [])}
            fit, first = errors.get('map_fit'), errors.get('first_keyframe')
            lost = [e for e in figures['events'] if e['kind'] == 'lost']
            back = [e for e in figures['events'] if e['kind'] == 'fix' and lost and e['t'] > lost[0]['t']]
            print(
                f'  {case:7s} first fix {figures["time_to_first_fix_s"] or float("nan"):5.2f} s, localized '
                f'{figures["localized_fraction"]:6.1%}, fixes {figures["fixes"]} (wrong {figures["wrong_fixes"]}), '
                f'wrong poses {figures.get("wrong_poses")}; error in map (fit) median '
                f'{fit["median_m"] if fit else float("nan"):.3f} p95 {fit["p95_m"] if fit else float("nan"):.3f} m, '
                f'(first keyframe) median {first["median_m"] if first else float("nan"):.3f} p95 '
                f'{first["p95_m"] if first else float("nan"):.3f} m; CPU per localized step '
                f'{figures["cpu_ms_per_localized_step_median"] or float("nan"):.1f} ms'
                + (f'; lost at {lost[0]["t"]:.1f} s, back after {back[0]["t"] - lost[0]["t"]:.1f} s' if back else ''),
                flush=True,
            )
    for name, map_dir in maps.items():
        for scene, seed in OTHER_SCENES:
            if (scene, seed) == (name, 0) or scene not in DRIVE_STARTS:
                continue
            bag = cached_scenario(scene, duration=args.drive, seed=seed, route_start=DRIVE_STARTS[scene], reverse=True)
            for stress in (False, True) if args.stress else (False,):
                figures = localize(
                    bag, map_dir, None, **(dict(localization__relocalization_threshold=1.0) if stress else {})
                )
                figures.update(map=name, scene=scene, seed=seed, every_place_a_candidate=stress)
                report['other_scenes'].append(figures)
                print(
                    f'  {scene} (seed {seed}) in the {name} map{" (every place a candidate)" if stress else ""}: '
                    f'fixes {figures["fixes"]}, published {figures["published"]} of {figures["scans"]}, places '
                    f'verified {figures["counters"].get("places_verified", 0)}, rejected '
                    f'{figures["counters"].get("places_rejected", 0)}',
                    flush=True,
                )
    for name in args.start_scenarios:
        if name not in maps:
            continue
        truth = TruthInMap(read_bundle(maps[name]))
        length = load_scenario(cached_scenario(name))['scenario']['path_length_m']
        rows = []
        for k in range(args.starts):
            start = (k + 0.5) * length / args.starts
            bag = cached_scenario(name, duration=args.start_drive, route_start=round(start, 1), reverse=k % 2 == 1)
            figures = localize(bag, maps[name], truth)
            figures.update(start_m=round(start, 1), reverse=k % 2 == 1)
            rows.append(figures)
            print(
                f'  {name} start {start:6.1f} m {"reverse" if k % 2 else "forward"}: first fix '
                f'{figures["time_to_first_fix_s"] or float("nan"):.2f} s, wrong fixes {figures["wrong_fixes"]}, '
                f'wrong poses {figures.get("wrong_poses")}',
                flush=True,
            )
        within = sum(
            1
            for r in rows
            if r['time_to_first_fix_s'] is not None and r['time_to_first_fix_s'] <= 3.0 and not r['wrong_fixes']
        )
        report['starts'][name] = dict(
            rows=rows, within_3s=within, of=len(rows), wrong_fixes=sum(r['wrong_fixes'] for r in rows)
        )
        print(
            f'{name}: relocalized within 3 s from {within} of {len(rows)} start points, wrong fixes '
            f'{report["starts"][name]["wrong_fixes"]}',
            flush=True,
        )
    if not args.skip_load and 'campus' in maps:
        report['load'] = load_time(maps['campus'], args.out)
        print(
            f'loading a {report["load"]["keyframes"]}-keyframe bundle ({report["load"]["bytes"] / 1e6:.0f} MB): '
            + ', '.join(f'{s:.2f}' for s in report['load']['seconds'])
            + ' s',
            flush=True,
        )
    cases = [f for d in report['drives'].values() for case, f in d.items() if case != 'mapping']
    wrong = (
        sum(f['wrong_fixes'] for f in cases)
        + sum(f['fixes'] for f in report['other_scenes'])
        + sum(s['wrong_fixes'] for s in report['starts'].values())
    )
    print(f'wrong fixes over everything: {wrong}')
    verifications = (
        [v for f in cases for v in f['verifications']]
        + [v for f in report['other_scenes'] for v in f['verifications']]
        + [v for s in report['starts'].values() for row in s['rows'] for v in row['verifications']]
    )
    report['gates'] = gate_figures(verifications)
    for kind, figures in report['gates'].items():
        print(
            f'{kind} places registered: {figures["count"]}, passed the verification {figures["accepted"]}; '
            + ', '.join(
                f'{key} {figures[key]}'
                for key in ('overlap', 'rmse', 'edge_overlap', 'constraint')
                if figures[key] is not None
            )
            + ' (min, median, max)'
        )
    cpu = {
        name: (
            report['maps'][name]['cpu_ms_per_step_mean'],
            d['mapping']['cpu_ms_per_step_mean'],
            d['known']['cpu_ms_per_localized_step_mean'],
            float(
                np.mean(
                    [
                        f['cpu_ms_per_localized_step_mean']
                        for case, f in d.items()
                        if case != 'mapping' and f['cpu_ms_per_localized_step_mean'] is not None
                    ]
                )
            ),
        )
        for name, d in report['drives'].items()
    }
    report['cpu'] = cpu
    for name, (lap, mapping, known, localizing) in cpu.items():
        made = ' (made in this run, just before)' if fresh[name] else ''
        print(
            f'{name}: mapOptimization CPU mean per step: mapping the lap {lap:.1f} ms{made}, '
            f'mapping the localization drive {mapping:.1f} ms, localizing it from the known pose right after '
            f'{known:.1f} ms ({known / lap:.2f}x the lap, {known / mapping:.2f}x the drive); all four cases '
            f'{localizing:.1f} ms',
            flush=True,
        )
    attempts = (
        [ms for f in cases for ms in f['attempt_cpu_ms']]
        + [ms for f in report['other_scenes'] for ms in f['attempt_cpu_ms']]
        + [ms for s in report['starts'].values() for row in s['rows'] for ms in row['attempt_cpu_ms']]
    )
    if attempts:
        report['attempt_cpu_ms'] = [float(np.median(attempts)), float(max(attempts))]
        print(
            f'relocalization: {report["attempt_cpu_ms"][0]:.0f} ms CPU per attempt (median; max '
            f'{report["attempt_cpu_ms"][1]:.0f}) in the registrations of its candidate places'
        )
    if args.json:
        args.json.write_text(json.dumps(report, indent=2, default=float))
    return 0


if __name__ == '__main__':
    sys.exit(main())
