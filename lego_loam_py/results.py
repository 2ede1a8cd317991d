"""The summary of a run, as printed at its end and written to ``summary.json``.

``lego_loam_py run`` fills an :class:`OfflineSummary`, the demo a :class:`DemoSummary`; what both write beside
the trajectory (its length, the accuracy against a ground truth, the map files, the PNG) is :class:`RunOutputs`,
measured by :func:`lego_loam_py.outputs.write_outputs`. ``as_dict()`` is the layout of ``summary.json``, which
users and tests read: its keys, their order and their values are part of the interface.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np

if TYPE_CHECKING:
    from lego_loam_py.evaluation import ErrorInMap, TrajectoryMetrics
    from lego_loam_py.supervisor import ProcessResult

__all__ = [
    'TimingStats',
    'MapToScene',
    'RunOutputs',
    'LoopClosures',
    'LocalizationSummary',
    'OfflineSummary',
    'DemoSummary',
]


@dataclass(frozen=True)
class TimingStats:
    """Milliseconds one stage took per call: per scan, for mapOptimization per mapping step."""

    median: float  # [ms]
    p95: float  # [ms]
    mean: float  # [ms]
    count: int  # calls measured

    @classmethod
    def of(cls, values_ms: Sequence[float]) -> TimingStats:
        """The statistics of a non-empty list of durations [ms]."""
        values = np.fromiter(values_ms, dtype=np.float64, count=len(values_ms))  # (a deque: converted once)
        return cls(
            median=float(np.median(values)),
            p95=float(np.percentile(values, 95)),
            mean=float(np.mean(values)),
            count=len(values),
        )

    @classmethod
    def from_dict(cls, entry: dict) -> TimingStats:
        """From a node's statistics file (``timings_ms`` entries have these four keys)."""
        return cls(median=entry['median'], p95=entry['p95'], mean=entry['mean'], count=entry['count'])

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class MapToScene:
    """Distances [m] from the map's points to the surfaces of the simulated scene the bag was made in."""

    median_m: float
    p90_m: float
    points: int  # map points measured


@dataclass(frozen=True)
class LoopClosures:
    """The loops mapOptimization closed and turned down. ``loops``: one dict per accepted loop, in the order they
    went into the pose graph: ``time_s`` (of the newest keyframe, since the first keyframe), ``latest`` and
    ``candidate`` (keyframe indices and stamps [ns]), ``detector`` ('radius' or 'scan_context'), ``score``
    (descriptor distance, 0 same .. 1 unrelated; None for the radius search), ``rmse_m`` and ``overlap`` of the
    registration, ``correction_m`` / ``correction_deg`` (how far the loop said the newest keyframe was from where
    the graph had it) and ``applied_m`` (how far it moved when the loops went in)."""

    accepted: int
    rejected: int  # verified and turned down, or never confirmed by a second loop
    rejected_because: dict[str, int]  # first word of the reason -> count ('overlap', 'rmse', 'correction', ...)
    loops: list[dict]

    @classmethod
    def of(cls, loops: Sequence, first_stamp_ns: int) -> LoopClosures:
        """From a mapper's ``loops`` (:class:`lego_loam_py.core.loop.closure.LoopResult`)."""
        accepted = [loop for loop in loops if loop.accepted]
        reasons: dict[str, int] = {}
        for loop in loops:
            if not loop.accepted:
                key = loop.reason.split()[0] if loop.reason else 'unknown'
                reasons[key] = reasons.get(key, 0) + 1
        return cls(
            accepted=len(accepted),
            rejected=len(loops) - len(accepted),
            rejected_because=reasons,
            loops=[
                dict(time_s=round((loop.latest_stamp_ns - first_stamp_ns) * 1e-9, 3), **loop.summary())
                for loop in accepted
            ],
        )

    def lines(self) -> list[str]:
        """The summary's lines about them."""
        because = ', '.join(f'{k} {v}' for k, v in sorted(self.rejected_because.items()))
        out = [
            f'loop closures: {self.accepted} accepted, {self.rejected} rejected' + (f' ({because})' if because else '')
        ]
        for loop in self.loops:
            score = f', score {loop["score"]:.3f}' if loop['score'] is not None else ''
            out.append(
                f'  t {loop["time_s"]:7.1f} s  keyframe {loop["latest"]} -> {loop["candidate"]} '
                f'({loop["detector"]}{score}), rmse {loop["rmse_m"]:.3f} m, overlap {loop["overlap"]:.2f}, '
                f'correction {loop["correction_m"]:.3f} m / {loop["correction_deg"]:.2f} deg'
            )
        return out


@dataclass(frozen=True)
class LocalizationSummary:
    """Localization in a saved map (``lego_loam_py run --map``). Times are seconds of data from the first scan."""

    map_path: str
    map_keyframes: int
    time_to_first_fix_s: float | None  # to the first verified fix; None: never localized
    localized_fraction: float  # scans whose fused pose was published (in the map) / scans in
    fixes: int  # verified fixes (the first and those after losing track)
    losses: int
    attempts: int  # relocalization attempts
    places_verified: int  # candidate places that passed the verification
    places_rejected: int
    events: list[dict]  # time_s, kind ('fix', 'lost', 'rejected', 'hint'), detail
    error_in_map: list[ErrorInMap]  # when the ground truth can be put in the map's frame (simulated, same scene)

    @classmethod
    def of(
        cls, localization, scans_in: int, published: int, first_scan_ns: int, error_in_map: Sequence[ErrorInMap] = ()
    ) -> LocalizationSummary:
        """From a :class:`lego_loam_py.core.localization.localizer.Localization` after a run."""
        counters = localization.counters
        first_fix = localization.first_fix_ns
        return cls(
            map_path=str(localization.prior.bundle.path),
            map_keyframes=len(localization.prior),
            time_to_first_fix_s=None if first_fix is None else round((first_fix - first_scan_ns) * 1e-9, 3),
            localized_fraction=published / scans_in if scans_in else 0.0,
            fixes=counters.get('fixes', 0),
            losses=counters.get('losses', 0),
            attempts=counters.get('attempts', 0),
            places_verified=counters.get('places_verified', 0),
            places_rejected=counters.get('places_rejected', 0),
            events=[
                dict(time_s=round((e.stamp_ns - first_scan_ns) * 1e-9, 3), kind=e.kind, detail=e.detail)
                for e in localization.events
            ],
            error_in_map=list(error_in_map),
        )

    def lines(self) -> list[str]:
        fix = (
            'never localized'
            if self.time_to_first_fix_s is None
            else f'first fix after {self.time_to_first_fix_s:.1f} s'
        )
        out = [
            f'localization in {self.map_path} ({self.map_keyframes} keyframes): {fix}, '
            f'{self.localized_fraction:.1%} of the scans localized; {self.fixes} fix(es), {self.losses} loss(es), '
            f'{self.attempts} relocalization attempt(s), {self.places_verified} place(s) verified, '
            f'{self.places_rejected} rejected'
        ]
        out += [f'  t {e["time_s"]:7.1f} s  {e["kind"]}: {e["detail"]}' for e in self.events if e['kind'] != 'hint']
        for error in self.error_in_map:
            out.append(
                f'  error in the map frame without alignment ({error.anchor}): median {error.median_m:.3f} m, '
                f'p95 {error.p95_m:.3f} m, max {error.max_m:.3f} m over {error.poses} poses (the map itself: '
                f'median {error.map_median_m:.3f} m, p95 {error.map_p95_m:.3f} m)'
            )
        return out


@dataclass
class RunOutputs:
    """What :func:`~lego_loam_py.outputs.write_outputs` wrote and measured. ``poses`` is None when it did not run
    (a demo that recorded no pose): then only the trajectory length (0 m) goes into the summary."""

    trajectory_length_m: float = 0.0
    poses: int | None = None  # poses in the trajectory files
    map_files: dict[str, str] | None = None  # map name -> path of the file
    accuracy: TrajectoryMetrics | None = None  # against the ground truth beside the bag
    accuracy_error: str | None = None  # why there is a ground truth but no accuracy
    # Loop closure on: the trajectory moved into the pose graph's final frame (trajectory_optimized.tum) and its
    # accuracy; the published one keeps the poses before a closure in the drifted frame.
    accuracy_optimized: TrajectoryMetrics | None = None
    map_to_scene: MapToScene | None = None
    png: str | None = None  # path of trajectory.png

    def as_dict(self) -> dict:
        out = {} if self.poses is None else {'poses': self.poses}
        out['trajectory_length_m'] = self.trajectory_length_m
        if self.map_files is not None:
            out['map_files'] = self.map_files
        if self.accuracy_error is not None:
            out['accuracy_error'] = self.accuracy_error
        if self.accuracy is not None:
            out['accuracy'] = self.accuracy.as_dict()
        if self.accuracy_optimized is not None:
            out['accuracy_optimized'] = self.accuracy_optimized.as_dict()
        if self.map_to_scene is not None:
            out['map_to_scene'] = asdict(self.map_to_scene)
        if self.png is not None:
            out['png'] = self.png
        return out


class _Summary:
    def as_dict(self) -> dict:
        raise NotImplementedError

    def to_json(self) -> str:
        """The text of ``summary.json`` (numpy numbers as plain ones)."""
        return json.dumps(self.as_dict(), indent=2, default=float)


@dataclass
class OfflineSummary(_Summary):
    """``lego_loam_py run``: the pipeline in one process on ``bag``. Times are seconds."""

    mode: ClassVar[str] = 'offline'
    bag: str
    counts: dict[str, int]  # the run's counters: scans_in, scans_processed, mapping_steps, …
    timings_ms: dict[str, TimingStats]  # stage -> its time per call
    wall_time_s: float
    bag_duration_s: float  # of the data processed
    outputs: RunOutputs = field(default_factory=RunOutputs)
    loop_closures: LoopClosures | None = None  # None: loop closure off (or no mapping)
    localization: LocalizationSummary | None = None  # None: mapping (not --map)

    @property
    def realtime_factor(self) -> float:
        """Seconds of data per second of wall time (nan when no time was measured)."""
        return self.bag_duration_s / self.wall_time_s if self.wall_time_s > 0 else float('nan')

    def as_dict(self) -> dict:
        return dict(
            bag=self.bag,
            mode=self.mode,
            counts=self.counts,
            timings_ms={name: t.as_dict() for name, t in self.timings_ms.items()},
            wall_time_s=self.wall_time_s,
            bag_duration_s=self.bag_duration_s,
            realtime_factor=self.realtime_factor,
            **self.outputs.as_dict(),
            **({} if self.loop_closures is None else {'loop_closures': asdict(self.loop_closures)}),
            **({} if self.localization is None else {'localization': asdict(self.localization)}),
        )


@dataclass
class DemoSummary(_Summary):
    """The demo: the four nodes over DDS on ``bag``, replayed at ``rate`` times real time. Counts are scans
    (mapOptimization: mapping steps) or messages; times are seconds."""

    mode: ClassVar[str] = 'dds'
    bag: str
    rate: float
    bag_duration_s: float
    wall_time_s: float
    scans_in: int  # clouds in the bag
    processed: dict[str, int]  # node -> scans it processed
    integrated: int  # /integrated_to_init recorded: the trajectory's poses
    not_received: int  # scans imageProjection never received
    drop_counters: dict[str, dict[str, int]]  # node -> its non-zero counters of messages thrown away
    queue_overwritten: int  # scans lost in featureAssociation's depth-1 input queues
    keyframes: int
    scans_with_imu: int  # scans featureAssociation corrected with the IMU
    timings_ms: dict[str, TimingStats]  # node -> its time per scan
    processes: list[ProcessResult]
    failures: list[str]
    interrupted: bool
    ready_after_s: float | None  # from the start until every node was up (None: never)
    outputs: RunOutputs = field(default_factory=RunOutputs)
    loop_closures: LoopClosures | None = None  # from mapOptimization's statistics (None: off, or none written)

    @property
    def integrated_fraction(self) -> float:
        return self.integrated / self.scans_in if self.scans_in else 0.0

    @property
    def dropped(self) -> int:
        """Scans never received plus every drop counter."""
        return self.not_received + sum(sum(counters.values()) for counters in self.drop_counters.values())

    def as_dict(self) -> dict:
        return dict(
            bag=self.bag,
            mode=self.mode,
            rate=self.rate,
            bag_duration_s=self.bag_duration_s,
            wall_time_s=self.wall_time_s,
            scans_in=self.scans_in,
            processed=self.processed,
            integrated=self.integrated,
            integrated_fraction=self.integrated_fraction,
            not_received=self.not_received,
            drop_counters=self.drop_counters,
            queue_overwritten=self.queue_overwritten,
            keyframes=self.keyframes,
            scans_with_imu=self.scans_with_imu,
            timings_ms={name: t.as_dict() for name, t in self.timings_ms.items()},
            processes=[
                dict(name=p.name, pid=p.pid, returncode=p.returncode, how=p.how, failure=p.failure)
                for p in self.processes
            ],
            failures=list(self.failures),
            interrupted=self.interrupted,
            ready_after_s=self.ready_after_s,
            dropped=self.dropped,
            **self.outputs.as_dict(),
            **({} if self.loop_closures is None else {'loop_closures': asdict(self.loop_closures)}),
        )
