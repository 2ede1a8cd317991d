"""A folder of scans, one file each (PCD, PLY or KITTI BIN), as a source.

Scans are taken in name order (numbers in names compare as numbers: ``scan_2`` before ``scan_10``). Each is
stamped from ``times.txt`` in the folder when there is one (one time [s] a line), else at ``rate_hz`` (default
10 Hz) from 0. Ground truth, when the folder has it: ``poses.txt`` (KITTI layout, 12 numbers a line, one pose per
scan; camera poses when a KITTI ``calib.txt`` is beside it, else the lidar's) or ``ground_truth.tum``.
Fields are kept as the files have them, so a PCD with ``ring`` and ``time`` feeds the pipeline as a bag does.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from lego_loam_py.core.trajectory import Trajectory
from lego_loam_py.formats import read_tum
from lego_loam_py.inputs.kitti import lidar_ground_truth, read_times
from lego_loam_py.inputs.point_files import POINT_FILE_SUFFIXES, read_points
from lego_loam_py.inputs.sidecars import GROUND_TRUTH
from lego_loam_py.inputs.source import Scan, Source, SourceError, SourceItem

__all__ = ['ScanFolderSource', 'scan_files', 'natural_key']


def natural_key(path: Path) -> list:
    """Sort key of a file name with its digit runs as numbers."""
    return [int(part) if part.isdigit() else part for part in re.split(r'(\d+)', path.name)]


def scan_files(folder: Path) -> list[Path]:
    """The point files of a folder in name order."""
    return sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in POINT_FILE_SUFFIXES and p.is_file()), key=natural_key
    )


class ScanFolderSource(Source):
    """A folder of point files (see the module docstring)."""

    kind = 'scans'

    def __init__(self, path: str | Path, rate_hz: float = 10.0):
        self.path = Path(path)
        self.name = self.path.resolve().name
        if not self.path.is_dir():
            raise SourceError(f'{self.path}: not a folder of scans')
        self.files = scan_files(self.path)
        if not self.files:
            raise SourceError(f'{self.path}: no scan files ({", ".join(POINT_FILE_SUFFIXES)}) in it')
        kinds = sorted({p.suffix.lower() for p in self.files})
        if len(kinds) > 1:
            raise SourceError(f'{self.path} mixes scan formats ({", ".join(kinds)}): keep one kind per folder')
        times = self.path / 'times.txt'
        if times.is_file():
            self.stamps = read_times(times, len(self.files), f'{kinds[0]} files')
            self.timed_by = str(times)
        else:
            self.stamps = np.round(np.arange(len(self.files)) * 1e9 / rate_hz).astype(np.int64)
            self.timed_by = f'{rate_hz:g} Hz'
        self._ground_truth = self._find_ground_truth()

    def _find_ground_truth(self) -> Trajectory | None:
        truth = lidar_ground_truth(self.path, self.stamps)
        tum = self.path / GROUND_TRUTH
        if truth is None and tum.is_file():
            try:
                truth = Trajectory(*read_tum(tum), 'map')
            except ValueError as exc:
                raise SourceError(str(exc)) from None
        return truth

    @property
    def duration_s(self) -> float:
        return float(self.stamps[-1] - self.stamps[0]) * 1e-9

    def scan_count(self) -> int:
        return len(self.files)

    def ground_truth(self) -> Trajectory | None:
        return self._ground_truth

    def describe(self) -> str:
        truth = 'with ground truth' if self._ground_truth is not None else 'no ground truth'
        return (
            f'{len(self.files)} {self.files[0].suffix.lower()} scans in {self.path} timed by {self.timed_by}, {truth}'
        )

    def items(self) -> Iterator[SourceItem]:
        for stamp, path in zip(self.stamps, self.files):
            yield Scan(int(stamp), read_points(path), int(stamp))
