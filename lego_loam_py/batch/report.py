"""The report of a batch, built from its finished run directories alone (so ``batch --report DIR`` rebuilds it
at any time): ``report.csv`` (one row per run), ``report.md`` (the table, per-parameter summaries of a sweep,
the plots) and the plots ``ate_per_run.png`` and ``ate_vs_<parameter>.png``.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lego_loam_py.batch.execute import PARTIAL_PREFIX, read_status
from lego_loam_py.formats import write_text_atomic

__all__ = ['collect_records', 'write_report', 'swept_keys', 'as_dataframe', 'COLUMNS']

# The per-run figures of the table, in order: (record key, heading, format).
COLUMNS = [
    ('ate_rmse_m', 'ATE m', '.3f'),
    ('rpe_percent', 'RPE %', '.2f'),
    ('drift_percent', 'drift %', '.2f'),
    ('length_m', 'length m', '.1f'),
    ('ms_per_scan', 'ms/scan', '.1f'),
    ('x_real_time', 'x RT', '.2f'),
]


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def collect_records(out: str | Path) -> list[dict]:
    """One record per run directory of ``out/runs`` (finished or failed; never a ``.partial-`` one): its
    inputs (recording, parameter file, overrides, IMU), status and metrics, sorted by recording and inputs."""
    runs = Path(out) / 'runs'
    records = []
    for run_dir in sorted(runs.iterdir()) if runs.is_dir() else []:
        if run_dir.name.startswith('.') or not run_dir.is_dir():
            continue
        status = read_status(run_dir)
        if status is None:  # not a run directory of ours (a run directory always has one)
            continue
        inputs = _read_json(run_dir / 'inputs.json')
        record = {
            'run': run_dir.name,
            'recording': Path(inputs.get('recording', '')).name,
            'recording_path': inputs.get('recording', ''),
            'params_file': Path(inputs.get('params_file') or '').name,
            'imu': inputs.get('imu'),
            'status': status.get('status'),
            'error': status.get('error', ''),
            'attempt': status.get('attempt'),
            'elapsed_s': status.get('elapsed_s'),
            'overrides': inputs.get('overrides', {}),
            'run_id': status.get('run_id', ''),
        }
        record.update(_read_json(run_dir / 'metrics.json'))
        records.append(record)
    records.sort(
        key=lambda r: (r['recording'], r['params_file'], json.dumps(r['overrides'], sort_keys=True), not r['imu'])
    )
    return records


def swept_keys(records: Sequence[dict]) -> list[str]:
    """The inputs that vary across the runs: overridden parameters, 'params_file', 'imu'."""
    keys: list[str] = []
    for record in records:
        keys += [k for k in record['overrides'] if k not in keys]
    varying = [k for k in keys if len({json.dumps(r['overrides'].get(k)) for r in records}) > 1]
    for key in ('params_file', 'imu'):
        if len({str(r[key]) for r in records}) > 1:
            varying.append(key)
    return varying


def _value(record: dict, key: str) -> Any:
    return record[key] if key in ('params_file', 'imu') else record['overrides'].get(key)


def _fmt(value: Any, spec: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return '-'
    return format(value, spec) if isinstance(value, (int, float)) and not isinstance(value, bool) else str(value)


def _csv_text(records: Sequence[dict], keys: Sequence[str]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    figures = [key for key, _, _ in COLUMNS]
    writer.writerow(['run', 'recording', *keys, 'status', *figures, 'scans', 'attempt', 'error'])
    for r in records:
        writer.writerow(
            [
                r['run'],
                r['recording'],
                *[_value(r, k) for k in keys],
                r['status'],
                *[r.get(f) for f in figures],
                r.get('scans'),
                r['attempt'],
                r['error'],
            ]
        )
    return buffer.getvalue()


def _summaries(records: Sequence[dict], keys: Sequence[str]) -> list[str]:
    """Per swept input: the mean and best ATE of the finished runs at each of its values."""
    lines = []
    for key in keys:
        lines += [f'### {key}', '', '| value | runs ok | mean ATE m | best ATE m |', '|---|---|---|---|']
        values: dict[str, list[float]] = {}
        for r in records:
            if r['status'] == 'ok':
                values.setdefault(json.dumps(_value(r, key)), [])
                if r.get('ate_rmse_m') is not None:
                    values[json.dumps(_value(r, key))].append(r['ate_rmse_m'])
        for value, ates in values.items():
            mean = sum(ates) / len(ates) if ates else None
            runs_ok = sum(1 for r in records if r['status'] == 'ok' and json.dumps(_value(r, key)) == value)
            lines.append(
                f'| {json.loads(value)} | {runs_ok} '
                f'| {_fmt(mean, ".3f")} | {_fmt(min(ates) if ates else None, ".3f")} |'
            )
        lines.append('')
    return lines


def _plots(records: Sequence[dict], keys: Sequence[str], out: Path) -> list[str]:
    """ate_per_run.png and ate_vs_<key>.png (one line per recording); the names of those written."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    done = [r for r in records if r['status'] == 'ok' and r.get('ate_rmse_m') is not None]
    if not done:
        return []
    written = []
    fig, ax = plt.subplots(figsize=(max(6.0, 0.35 * len(done)), 4.0))
    ax.bar(range(len(done)), [r['ate_rmse_m'] for r in done], color='tab:blue')
    # A run is told apart by its recording and the values swept, not by its hash.
    labels = [' '.join([r['recording'], *(f'{k.rsplit(".", 1)[-1]}={_value(r, k)}' for k in keys)]) for r in done]
    ax.set_xticks(range(len(done)), labels, rotation=75, ha='right', fontsize=7)
    ax.set_ylabel('ATE RMSE [m]')
    ax.set_title('ATE per run')
    fig.tight_layout()
    fig.savefig(out / 'ate_per_run.png', dpi=110)
    plt.close(fig)
    written.append('ate_per_run.png')
    for key in keys:
        fig, ax = plt.subplots(figsize=(6.0, 4.0))
        numeric = all(isinstance(_value(r, key), (int, float)) for r in done)
        labels = sorted({json.dumps(_value(r, key)) for r in done})
        for recording in sorted({r['recording'] for r in done}):
            mine = [r for r in done if r['recording'] == recording]
            mine.sort(key=lambda r: _value(r, key) if numeric else labels.index(json.dumps(_value(r, key))))
            xs = [(_value(r, key) if numeric else labels.index(json.dumps(_value(r, key)))) for r in mine]
            ax.plot(xs, [r['ate_rmse_m'] for r in mine], 'o-', label=recording)
        if not numeric:
            ax.set_xticks(range(len(labels)), [json.loads(v) for v in labels])
        ax.set_xlabel(key)
        ax.set_ylabel('ATE RMSE [m]')
        ax.legend(fontsize=7)
        fig.tight_layout()
        name = f'ate_vs_{key.replace(".", "_")}.png'
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        written.append(name)
    return written


def write_report(out: str | Path, records: Sequence[dict] | None = None, plots: bool = True) -> dict[str, Path]:
    """report.csv, report.md and the plots in ``out`` from its run directories; returns the files written."""
    out = Path(out)
    records = collect_records(out) if records is None else list(records)
    keys = swept_keys(records)
    files = {'csv': write_text_atomic(out / 'report.csv', _csv_text(records, keys))}
    ok = sum(r['status'] == 'ok' for r in records)
    partial = sum(1 for p in (out / 'runs').glob(f'{PARTIAL_PREFIX}*')) if (out / 'runs').is_dir() else 0
    lines = [
        f'# Batch report: {out.name}',
        '',
        f'{len(records)} runs: {ok} finished, {len(records) - ok} failed'
        + (f' ({partial} unfinished, left by an interrupted batch)' if partial else '')
        + '.',
        '',
        '| run | recording | '
        + ''.join(f'{k} | ' for k in keys)
        + 'status | '
        + ' | '.join(h for _, h, _ in COLUMNS)
        + ' |',
        '|---|---|' + '---|' * len(keys) + '---|' + '---|' * len(COLUMNS),
    ]
    for r in records:
        figures = ' | '.join(_fmt(r.get(key), spec) for key, _, spec in COLUMNS)
        lines.append(
            f'| {r["run"]} | {r["recording"]} | '
            + ''.join(f'{_value(r, k)} | ' for k in keys)
            + f'{r["status"]} | {figures} |'
        )
    failed = [r for r in records if r['status'] != 'ok']
    if failed:
        lines += ['', '## Failed runs', ''] + [f'- `{r["run"]}` (attempt {r["attempt"]}): {r["error"]}' for r in failed]
    if keys:
        lines += ['', '## Per parameter', ''] + _summaries(records, keys)
    if plots:
        for name in _plots(records, keys, out):
            files[name] = out / name
            lines += ['', f'![{name}]({name})']
    files['md'] = write_text_atomic(out / 'report.md', '\n'.join(lines) + '\n')
    return files


def as_dataframe(records: Sequence[dict]):
    """The records as a pandas DataFrame (pandas comes with evo), overrides spread into columns."""
    import pandas as pd

    rows = [{**{k: v for k, v in r.items() if k != 'overrides'}, **r['overrides']} for r in records]
    return pd.DataFrame(rows)
