"""What a batch runs: recordings x parameter sets x IMU modes, each combination a :class:`RunSpec` with the
identity that lets a batch resume (a hash of the recording, the resolved parameters and the code version).
"""

from __future__ import annotations

import glob
import hashlib
import itertools
import json
import subprocess
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from lego_loam_py import __version__
from lego_loam_py.core.params import load_params
from lego_loam_py.errors import UsageError

__all__ = [
    'RunSpec',
    'ParameterSet',
    'expand_recordings',
    'parameter_grid',
    'code_version',
    'plan_runs',
    'split_values',
]

IMU_MODES = {'on': (True,), 'off': (False,), 'both': (True, False)}


@dataclass(frozen=True)
class ParameterSet:
    """One point of the grid: a parameter file (or None: the defaults) and ``name -> value`` overrides on top."""

    params_file: Path | None = None
    overrides: Mapping[str, Any] = field(default_factory=dict)

    def label(self) -> str:
        parts = [self.params_file.name] if self.params_file is not None else []
        parts += [f'{name}={value}' for name, value in self.overrides.items()]
        return ', '.join(parts) or 'defaults'


@dataclass(frozen=True)
class RunSpec:
    """One run of the batch: ``lego_loam_py run`` of ``recording`` with ``parameters`` (the IMU on or off).

    ``run_id`` is the hash of the recording (path, sizes and modification times of its files), every resolved
    parameter and the code version: a finished run with the same id is the same computation."""

    recording: Path
    parameters: ParameterSet
    imu: bool
    flat_params: Mapping[str, Any]
    run_id: str
    run_args: tuple[str, ...] = ()  # more arguments of ``run``: how to read the recording (--dataloader, ...)

    @property
    def name(self) -> str:
        """The run directory's name: the recording's name and the start of the id."""
        return f'{recording_name(self.recording)}-{self.run_id[:12]}'

    def describe(self) -> dict:
        """What the report shows of the run's inputs (JSON-ready)."""
        return {
            'recording': str(self.recording),
            'params_file': str(self.parameters.params_file or ''),
            'overrides': dict(self.parameters.overrides),
            'imu': self.imu,
            'run_args': list(self.run_args),
            'run_id': self.run_id,
        }


def recording_name(path: Path) -> str:
    """A recording's short name: a bag file's stem, else the folder's name."""
    return path.stem if path.is_file() else path.name


def expand_recordings(items: Sequence[str], list_files: Sequence[str | Path] = ()) -> list[Path]:
    """Recordings from paths, glob patterns (``'bags/*.mcap'``, ``'runs/**/metadata.yaml'`` is not needed:
    a ROS 2 bag is its folder) and list files (one path or pattern per line, ``#`` comments); resolved, in the
    order given, each once. A pattern that matches nothing, or a path that does not exist, is an error."""
    entries: list[tuple[str, Path]] = [(item, Path.cwd()) for item in items]
    for list_file in list_files:
        path = Path(list_file)
        try:
            lines = path.read_text().splitlines()
        except OSError as exc:
            raise UsageError(f'cannot read the list of recordings {path}: {exc.strerror}') from None
        entries += [(line.split('#', 1)[0].strip(), path.resolve().parent) for line in lines]
    out: list[Path] = []
    for item, base in entries:
        if not item:
            continue
        pattern = item if Path(item).is_absolute() else str(base / item)
        if glob.has_magic(item):
            matches = sorted(Path(p) for p in glob.glob(pattern, recursive=True))
            if not matches:
                raise UsageError(f"no recording matches '{item}'")
        else:
            matches = [Path(pattern)]
            if not matches[0].exists():
                raise UsageError(f'no such recording: {item}')
        for match in matches:
            resolved = match.resolve()
            if resolved not in out:
                out.append(resolved)
    if not out:
        raise UsageError('no recordings given')
    return out


def split_values(text: str) -> list[str]:
    """``'0.1,0.2,[1, 2]'`` -> ``['0.1', '0.2', '[1, 2]']``: the comma-separated values of one ``-p`` sweep,
    commas inside brackets or quotes kept (a list value is one value)."""
    values, depth, quote, current = [], 0, None, []
    for char in text:
        if quote:
            quote = None if char == quote else quote
        elif char in '\'"':
            quote = char
        elif char in '[{':
            depth += 1
        elif char in ']}':
            depth -= 1
        elif char == ',' and depth == 0:
            values.append(''.join(current).strip())
            current = []
            continue
        current.append(char)
    values.append(''.join(current).strip())
    return values


def parameter_grid(sweeps: Sequence[str], params_files: Sequence[str | Path] = ()) -> list[ParameterSet]:
    """Every combination of the ``name:=v1,v2,...`` sweeps (YAML values, as ``-p`` of ``run``), times every
    parameter file (or the defaults when none is given), in a stable order."""
    axes: dict[str, list[Any]] = {}
    for item in sweeps:
        if ':=' not in item:
            raise UsageError(f"parameter sweep '{item}' must look like name:=value1,value2,...")
        name, text = (part.strip() for part in item.split(':=', 1))
        if name in axes:
            raise UsageError(f"parameter '{name}' is swept twice: give its values in one -p")
        try:
            axes[name] = [yaml.safe_load(value) for value in split_values(text)]
        except yaml.YAMLError as exc:
            raise UsageError(f"parameter sweep '{item}': a value is not valid YAML ({exc})") from None
    files: list[Path | None] = [Path(f).resolve() for f in params_files] or [None]
    for path in files:
        if path is not None and not path.is_file():
            raise UsageError(f'no such parameter file: {path}')
    names = list(axes)
    return [
        ParameterSet(path, dict(zip(names, values)))
        for path in files
        for values in itertools.product(*(axes[n] for n in names))
    ]


def code_version(repo: Path | None = None) -> dict:
    """The code a run used: the git commit and whether the checkout had changes (with a hash of them, so that
    two different uncommitted states are two versions), or the package version outside a git checkout."""
    repo = repo or Path(__file__).resolve().parents[2]

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(['git', '-C', str(repo), *args], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return done.stdout if done.returncode == 0 else None

    commit = git('rev-parse', 'HEAD') if (repo / '.git').exists() else None
    if commit is None:
        return {'package_version': __version__, 'git_commit': None, 'dirty': None}
    status = git('status', '--porcelain', '--untracked-files=no') or ''
    version = {'package_version': __version__, 'git_commit': commit.strip(), 'dirty': bool(status.strip())}
    if version['dirty']:
        version['diff_sha256'] = hashlib.sha256((git('diff', 'HEAD') or '').encode()).hexdigest()
    return version


def _fingerprint(recording: Path) -> list:
    """Path, size and modification time of every file of a recording (a file, or a bag folder's files)."""
    files = [recording] if recording.is_file() else sorted(p for p in recording.rglob('*') if p.is_file())
    return [[str(p), p.stat().st_size, p.stat().st_mtime_ns] for p in files]


def plan_runs(
    recordings: Iterable[Path],
    parameter_sets: Sequence[ParameterSet],
    imu: str = 'on',
    version: Mapping[str, Any] | None = None,
    run_args: Sequence[str] = (),
) -> list[RunSpec]:
    """Every recording x parameter set x IMU mode (``on``, ``off`` or ``both``), with its run id; ``run_args``
    go to every ``run`` (how to read the recordings: ``--dataloader``, ``--rate-hz``, ...) and into the id.
    Parameters are resolved (and checked) here, once, so that a typo fails before anything starts."""
    if imu not in IMU_MODES:
        raise UsageError(f"--imu must be one of {', '.join(IMU_MODES)}, got '{imu}'")
    version = dict(version or code_version())
    resolved = [load_params(s.params_file, s.overrides).to_flat() for s in parameter_sets]
    specs = []
    for recording in recordings:
        fingerprint = _fingerprint(recording)
        for parameters, flat in zip(parameter_sets, resolved):
            for use_imu in IMU_MODES[imu]:
                identity = {'recording': fingerprint, 'params': flat, 'imu': use_imu, 'version': version}
                if run_args:  # (absent when empty: the ids of plain bag runs stay as they were)
                    identity['run_args'] = list(run_args)
                digest = hashlib.sha256(json.dumps(identity, sort_keys=True, default=str).encode()).hexdigest()
                specs.append(RunSpec(recording, parameters, use_imu, flat, digest, tuple(run_args)))
    return specs
