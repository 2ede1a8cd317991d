"""The one interface every recording is read through: a source of scans and IMU samples, in recording order.

    with open_source(path) as source:              # lego_loam_py.inputs.open_source guesses the kind
        for item in source.items():
            if isinstance(item, Scan): pipeline.process_scan(item.points, item.stamp_ns)
            elif isinstance(item, ImuSample): pipeline.add_imu(item.sample)
            else: pipeline.skip_scan(item.stamp_ns, item.reason)   # UnreadableScan

Besides the items a source knows its name (the default output folder), how long the recording is, how many
scans it holds when that is known without reading them, and its ground truth when it has one. ``run`` (and any
other command that feeds the pipeline) uses only this interface.

Points are structured arrays (:mod:`lego_loam_py.core.pointcloud`: x, y, z [m] in the sensor frame, REP-103 axes;
intensity, ring and time when the recording has them); stamps are integer nanoseconds of the sweep start.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lego_loam_py.core.trajectory import Trajectory
from lego_loam_py.errors import LegoLoamError

__all__ = ['Scan', 'ImuSample', 'UnreadableScan', 'SourceItem', 'Source', 'SourceError']


class SourceError(LegoLoamError, RuntimeError):
    """A recording cannot be read: a missing or inconsistent file, named in the message."""


@dataclass(frozen=True)
class Scan:
    """One sweep: ``points`` (structured array) stamped ``stamp_ns`` (sweep start); ``received_ns`` is when the
    recording got it (a bag's recording time), which orders it among the IMU samples."""

    stamp_ns: int
    points: np.ndarray
    received_ns: int


@dataclass(frozen=True)
class ImuSample:
    """One IMU sample as ``core.imu.imu_sample`` gives it: (stamp [s], orientation (x, y, z, w), angular velocity
    [rad/s], linear acceleration [m/s^2]), IMU frame."""

    sample: tuple
    received_ns: int


@dataclass(frozen=True)
class UnreadableScan:
    """A sweep in the recording whose points could not be decoded, and why (the pipeline counts it dropped)."""

    stamp_ns: int
    reason: str
    received_ns: int


SourceItem = Scan | ImuSample | UnreadableScan


class Source:
    """A recording to run the pipeline on. Subclasses set :attr:`kind`, :attr:`path`, :attr:`name` and implement
    :meth:`items`; the rest has defaults. Use as a context manager (:meth:`close` releases files)."""

    kind: str = ''  # 'rosbag', 'kitti', 'scans', 'pcap'
    path: Path
    name: str  # default name of the output folder

    @property
    def duration_s(self) -> float:
        """[s] the recording covers (a bag: first to last message; scans: first to last stamp)."""
        raise NotImplementedError

    def scan_count(self) -> int | None:
        """Scans in the recording, when known without reading them (for a progress bar)."""
        return None

    def ground_truth(self) -> Trajectory | None:
        """The sensor's true trajectory when the recording has one: lidar poses in REP-103 axes relative to the
        first (frame 'map')."""
        return None

    def describe(self) -> str:
        """One line for the user: what is read and how."""
        return f'{self.kind} {self.path}'

    def items(self) -> Iterator[SourceItem]:
        """Scans, IMU samples and unreadable scans in recording order."""
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
