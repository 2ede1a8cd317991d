"""The whole pipeline on one scan at a time, without ROS: imageProjection -> featureAssociation ->
transformFusion, and mapOptimization on the mapping inputs, in the order a replay delivers them.

    pipeline = Pipeline(params)
    pipeline.add_imu(sample)                      # each IMU sample, as core.imu.imu_sample gives it
    output = pipeline.process_scan(points, stamp_ns)   # each cloud (structured array, see core.pointcloud)
    record = pipeline.finish()                    # every pose, count and timing

The offline mode (``lego_loam_py run``) is this call in a loop over a bag; the ROS nodes run the same cores,
one per process. The call is also in two halves, for a front end in another process
(lego_loam_py.front_end_process): :meth:`Pipeline.front_step` (imageProjection's result through
featureAssociation, into a :class:`FrontStep` of plain values) and :meth:`Pipeline.apply` (that step into the
run: counts, warnings, transformFusion and mapOptimization); ``process_scan`` is the one after the other.
With ``map_optimization.mode: localization`` mapOptimization's core is
:class:`~lego_loam_py.core.localization.localizer.Localization` in the saved map of ``map_optimization.map_path``, and
transformFusion publishes only while its map correction is recent (see :class:`TransformFusion`).
mapOptimization may run on a worker thread (``mapping_thread``): it then overlaps the next scans'
imageProjection and featureAssociation (numpy and scipy release the GIL), with the same result as without it,
since the worker takes the mapping inputs and IMU samples in arrival order and transformFusion applies each
mapping result before the scans that follow it. imageProjection may also run on a worker thread
(``projection_thread``): a caller that knows the next scan hands it to :meth:`Pipeline.project` before the scans
ahead of it reach featureAssociation (the offline runner does), and the projection overlaps them; it depends on
nothing but the scans before it, so the result is the same.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from lego_loam_py.core.frames import pose6_to_matrix, transform_cloud
from lego_loam_py.core.guard import (
    MAPPING_DEGENERATE,
    MAPPING_STEPS,
    MAPPING_STEPS_FAILED,
    SCANS_DROPPED,
    SCANS_IN,
    SCANS_PROCESSED,
    SCANS_WITH_IMU,
    STATE_RESETS,
    StepGuard,
)
from lego_loam_py.core.imu.buffer import uncovered_counter, uncovered_warning, warn_uncovered
from lego_loam_py.core.localization.localizer import Localization
from lego_loam_py.core.mapping.map_optimization import MapOptimization
from lego_loam_py.core.mapping.mapper import Mapper
from lego_loam_py.core.mapping.odometry_continuity import OdometryContinuity
from lego_loam_py.core.mapping.transform_fusion import TransformFusion
from lego_loam_py.core.odometry.feature_association import FeatureAssociation, ScanInput
from lego_loam_py.core.params.timing import pose_delay
from lego_loam_py.core.params.types import Params
from lego_loam_py.core.pipeline_events import LoopChecked, MapStepped, PipelineListener, ScanFused, ScanProcessed
from lego_loam_py.core.pointcloud import CloudLayoutError
from lego_loam_py.core.projection.elevation_bias import elevation_note
from lego_loam_py.core.projection.image_projection import ImageProjection, InputError, prepare_input
from lego_loam_py.core.trajectory import Trajectory

__all__ = ['Pipeline', 'FrontStep', 'ScanOutput', 'RunResult', 'pose_time_offset_ns']

# featureAssociation hears of mapOptimization's pose of a scan (/aft_mapped_to_init, for its IMU check) before the
# first scan stamped this much later [ns]: a fixed lag, so that a run does not depend on the mapping thread's pace.
MAPPED_POSE_LAG_NS = 300_000_000


def pose_time_offset_ns(params: Params) -> int:
    """[ns] to add to a scan's stamp to get the time of the sensor pose the pipeline publishes for it (see
    :func:`~lego_loam_py.core.params.timing.pose_delay`). Applies to /laser_odom_to_init and /integrated_to_init
    alike."""
    return int(round(pose_delay(params) * 1e9))


@dataclass
class RunResult:
    """Everything a run produced; poses are 4x4 in camera_init (LOAM camera axes)."""

    stamps: list[int] = field(default_factory=list)  # scans with an odometry pose
    integrated: list[np.ndarray] = field(default_factory=list)  # /integrated_to_init (those not published too)
    published: list[bool] = field(default_factory=list)  # of each: published (localization: in the map)
    odometry: list[np.ndarray] = field(default_factory=list)  # /laser_odom_to_init
    mapped_stamps: list[int] = field(default_factory=list)
    mapped: list[np.ndarray] = field(default_factory=list)  # /aft_mapped_to_init
    # The 6x6 covariances of those poses (camera_init: position [m²] in its axes, rotation [rad²] about them; ROS
    # order; core.frames), unbounded, and of each scan's sweep motion (in the previous sweep start's axes).
    odometry_covariance: list[np.ndarray] = field(default_factory=list)
    motion_covariance: list[np.ndarray] = field(default_factory=list)
    integrated_covariance: list[np.ndarray] = field(default_factory=list)
    mapped_covariance: list[np.ndarray] = field(default_factory=list)
    timings_ms: dict[str, list[float]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    wall_time: float = 0.0
    bag_duration: float = 0.0
    first_scan_ns: int | None = None  # stamp of the first cloud
    mapper: Mapper | None = None
    pose_time_offset_ns: int = 0  # the original odometry model's pose of scan k is the sensor's at k + one sweep
    # What the IMU checks decided, in order: (node, core.imu_monitor.AlignmentEvent).
    imu_alignment: list[tuple[str, object]] = field(default_factory=list)

    def count(self, name: str, amount: int = 1) -> None:
        self.counts[name] = self.counts.get(name, 0) + amount

    def time(self, name: str, ms: float) -> None:
        self.timings_ms.setdefault(name, []).append(ms)

    def trajectory(self, axes: str = 'map', which: str = 'integrated') -> Trajectory:
        """The sensor's trajectory (core.trajectory: unpacks as ``stamps, poses``) of the fused ('integrated') or
        odometry ('odometry') poses; ``axes`` 'map' (REP-103) or 'camera_init'. Stamps include the model's pose time
        offset. The fused trajectory holds the poses transformFusion published (in localization: those in the saved
        map)."""
        stamps = np.array(self.stamps, dtype=np.int64) + self.pose_time_offset_ns
        poses = np.array(self.integrated if which == 'integrated' else self.odometry).reshape(-1, 4, 4)
        trajectory = Trajectory(stamps, poses, 'camera_init')
        if which == 'integrated' and not all(self.published):
            trajectory = trajectory.select(np.array(self.published, dtype=bool))
        return trajectory.to(axes)

    def optimized_trajectory(self, axes: str = 'map') -> Trajectory:
        """The fused trajectory as the pose graph has it at the end: each pose moved by the correction its last
        keyframe (at or before it) received since it was mapped (the loops closed later), so that the whole path
        is in the corrected frame. Without a mapper, or without corrections, it is :meth:`trajectory`."""
        stamps, poses = self.trajectory(axes='camera_init')
        if self.mapper is not None and self.mapper.builds_map and self.mapper.keyframes and len(poses):
            mapped = dict(zip(self.mapped_stamps, self.mapped))
            keyframes = [kf for kf in self.mapper.keyframes if kf.stamp_ns in mapped]
            key_stamps = np.array([kf.stamp_ns for kf in keyframes], dtype=np.int64) + self.pose_time_offset_ns
            # (the first keyframe is the graph's anchor: it never moves, though the step that made it published
            # no mapped pose of its own yet)
            corrections = np.array(
                [
                    np.eye(4)
                    if kf is self.mapper.keyframes[0]
                    else pose6_to_matrix(kf.pose6) @ np.linalg.inv(mapped[kf.stamp_ns])
                    for kf in keyframes
                ]
            ).reshape(-1, 4, 4)
            which = np.searchsorted(key_stamps, stamps, side='right') - 1
            if len(keyframes):
                moved = np.einsum('nij,njk->nik', corrections[np.maximum(which, 0)], poses)
                poses = np.where((which >= 0)[:, None, None], moved, poses)
        return Trajectory(stamps, poses, 'camera_init').to(axes)


@dataclass(frozen=True)
class ScanOutput:
    """What one scan gave: its odometry pose (4x4, camera_init; None for the first scan, which only
    initialises, and for a dropped one) or why it was dropped."""

    stamp_ns: int
    odometry: np.ndarray | None = None
    dropped: str | None = None
    imu_used: bool = False


def _to_stderr(text: str) -> None:
    print(f'warning: {text}', file=sys.stderr)


class Pipeline:
    """The four cores on one scan at a time (see the module docstring). ``mapping=False``: odometry and
    fusion only. ``warn`` receives a line for each scan or step dropped or repaired (default: stderr).
    ``listener`` receives the run's events (core.pipeline_events) as they happen; without one none is made."""

    def __init__(
        self,
        params: Params,
        *,
        mapping: bool = True,
        mapping_thread: bool = False,
        projection_thread: bool = False,
        warn: Callable[[str], None] | None = None,
        listener: PipelineListener | None = None,
    ):
        self.params = params
        # imageProjection's worker (see the module docstring): its CPU time is its thread's own, as the mapping's.
        self._projector = (
            ThreadPoolExecutor(max_workers=1, thread_name_prefix='projection') if projection_thread else None
        )
        self._projection_clock = time.thread_time if projection_thread else time.perf_counter
        self.ip, self.fa = ImageProjection(params), FeatureAssociation(params)
        self.localizing = params.map_optimization.mode == 'localization' and mapping
        # (Localization.load raises MapBundleError, naming the problem, for a bundle it cannot use.)
        self.mo = Localization.load(params) if self.localizing else MapOptimization(params)
        self.fusion = TransformFusion(int(params.localization.max_correction_age * 1e9) if self.localizing else None)
        self.mapping = mapping
        self.record = RunResult(mapper=self.mo if mapping else None)
        self.record.pose_time_offset_ns = pose_time_offset_ns(params)
        self._warn = warn or _to_stderr
        self._listener = listener
        self._fa_guard = StepGuard(params.reliability.reset_after_failures)
        self._back_end = _BackEnd(
            self.mo if mapping else None,
            self.fusion,
            self.record,
            self._warn,
            threaded=mapping and mapping_thread,
            listener=listener,
        )
        self._next_loop_check: int | None = None
        self._uncovered: dict[str, int] = {}  # scans whose sweep the IMU could not cover, by why (for the warnings)

    def add_imu(self, sample: tuple) -> None:
        """One IMU sample (``core.imu.imu_sample``: time [s], quaternion, angular velocity, acceleration)."""
        self.apply_imu(sample, self.front_imu(sample))

    def front_imu(self, sample: tuple) -> bool:
        """featureAssociation's part of :meth:`add_imu`: whether it rejected the sample."""
        return self.fa.add_imu(*sample) is not None

    def apply_imu(self, sample: tuple, rejected: bool) -> None:
        """The rest of :meth:`add_imu`: the sample counted if rejected, and kept for mapOptimization."""
        if rejected:
            self.record.count('imu_rejected')
        self._back_end.add_imu(sample)

    def mapping_results(self) -> list[tuple[int, np.ndarray | None]]:
        """(stamp, mapped pose six-vector; None for a step that gave none) of every mapping step finished and not
        given before, in the order of their scans: what :meth:`front_step` needs of them, for a front end that runs
        elsewhere."""
        return self._back_end.finished_steps()

    def skip_scan(self, stamp_ns: int, reason: str) -> ScanOutput:
        """A scan the caller could not even decode: counted and warned about like any dropped scan."""
        return self.apply(self.skipped(stamp_ns, reason))

    def skipped(self, stamp_ns: int, reason: str) -> FrontStep:
        """The front end's part of :meth:`skip_scan`."""
        return FrontStep(
            stamp_ns, counts=[SCANS_IN, SCANS_DROPPED], notices=[_dropped_note(stamp_ns, reason)], dropped=reason
        )

    def project(self, points: np.ndarray) -> Future:
        """Start imageProjection on a cloud (on the projection worker, if there is one): a future of (its
        segmentation, ms of imageProjection), for :meth:`process_scan`. Clouds must be handed over in the order of
        their scans (the projection learns from the scans before it, e.g. a beam-elevation error)."""

        def job():
            start = self._projection_clock()
            segmentation = self.ip.process(prepare_input(points, self.params))
            return segmentation, (self._projection_clock() - start) * 1e3

        if self._projector is not None:
            return self._projector.submit(job)
        future = Future()
        try:
            future.set_result(job())
        except Exception as exc:  # (raised again where the result is taken, as on the worker)
            future.set_exception(exc)
        return future

    def process_scan(self, points: np.ndarray, stamp_ns: int, projected: Future | None = None) -> ScanOutput:
        """One cloud (structured array with x, y, z, intensity and optionally ring / time) stamped
        ``stamp_ns`` [ns]: its odometry now, its fused pose and mapping as their results come (see
        :meth:`finish`). ``projected``: what :meth:`project` returned for this cloud, if it was started ahead."""
        projected = projected if projected is not None else self.project(points)
        return self.apply(self.front_step(projected, stamp_ns, self._back_end.mapped_before))

    def apply(self, step: FrontStep) -> ScanOutput:
        """Take what the front end made of a scan (:meth:`front_step`, :meth:`skipped`) into the run: its counts,
        timings and warnings, its odometry pose to transformFusion, its mapping inputs to mapOptimization."""
        record = self.record
        for name in step.counts:
            record.count(name)
        for note in step.notices:
            if isinstance(note, str):
                self._warn(note)
            else:
                self._back_end.imu_alignment('featureAssociation', note)
        for stage, ms in step.timings_ms.items():
            record.time(stage, ms)
        if self._listener is not None and step.event is not None:  # (before the fusion, whose event follows)
            self._listener(step.event)
        if step.odometry is not None:
            pose, pose_covariance, motion_covariance = step.odometry
            record.stamps.append(step.stamp_ns)
            record.odometry.append(pose)
            record.odometry_covariance.append(pose_covariance)
            record.motion_covariance.append(motion_covariance)
            self._back_end.fuse(step.stamp_ns, pose, pose_covariance)
        if step.map_inputs is not None:
            *inputs, odometry_covariance = step.map_inputs
            self._back_end.map(step.stamp_ns, *inputs, odometry_covariance=odometry_covariance)
        self._after_scan(step.stamp_ns)
        if step.dropped is not None:
            return ScanOutput(step.stamp_ns, dropped=step.dropped)
        return ScanOutput(step.stamp_ns, None if step.odometry is None else step.odometry[0], imu_used=step.imu_used)

    def _after_scan(self, stamp_ns: int) -> None:
        if self.record.first_scan_ns is None:
            self.record.first_scan_ns = stamp_ns
        lc = self.params.loop_closure
        if self.mapping and lc.loop_closure_enable_flag and not self.localizing:  # every loop_closure.period s
            if self._next_loop_check is None:
                self._next_loop_check = stamp_ns + int(lc.period * 1e9)
            elif stamp_ns >= self._next_loop_check:
                self._next_loop_check = stamp_ns + int(lc.period * 1e9)
                self._back_end.loop_closure()
        self._back_end.drain()

    def finish(self) -> RunResult:
        """Wait for the mapping still under way, apply its results, and return the record of the run."""
        try:
            self._back_end.drain(wait=True)
        finally:
            self.close()
        self.record.counts['keyframes'] = len(self.mo.keyframes) if self.mapping and self.mo.builds_map else 0
        if self.localizing:
            self.record.counts.update({f'localization_{k}': v for k, v in self.mo.counters.items()})
        if self.mapping and self.mo.builds_map and self.params.loop_closure.loop_closure_enable_flag:
            # (a loop verified and left waiting for a second one that never came counts as rejected)
            accepted = sum(loop.accepted for loop in self.mo.loops)
            self.record.counts.update(loops_closed=accepted, loops_rejected=len(self.mo.loops) - accepted)
        return self.record

    def close(self) -> None:
        """Stop the projection and mapping workers (idempotent)."""
        if self._projector is not None:
            self._projector.shutdown(wait=True, cancel_futures=True)
        self._back_end.close()

    def front_step(
        self, projected: Future, stamp: int, mapped_before: Callable[[int], list[tuple[int, np.ndarray]]]
    ) -> FrontStep:
        """featureAssociation on a projected scan (:meth:`project`): what the run takes of it (:meth:`apply`).
        ``mapped_before(stamp)`` gives the mapping steps of scans stamped up to ``stamp`` not given before, as
        (stamp, mapped pose six-vector), for featureAssociation's IMU check."""
        step = FrontStep(stamp, counts=[SCANS_IN])
        try:
            segmentation, projection_ms = projected.result()
        except (CloudLayoutError, InputError) as exc:
            step.counts.append(SCANS_DROPPED)
            step.notices.append(_dropped_note(stamp, str(exc)))
            step.dropped = str(exc)
            return step
        t1 = time.perf_counter()
        step.timings_ms['imageProjection'] = projection_ms
        if 'elevation_offset_found' in segmentation.stats:
            step.notices.append(elevation_note(segmentation.stats['elevation_offset_found'], stamp))
        for mapped_stamp, pose6 in mapped_before(stamp - MAPPED_POSE_LAG_NS):
            event = self.fa.add_mapped_pose(mapped_stamp, pose6_to_matrix(pose6))  # (featureAssociation's IMU check)
            if event is not None:
                step.notices.append(event)
        features = self.fa.process(ScanInput.from_segmentation(stamp, segmentation))
        t2 = time.perf_counter()
        step.timings_ms['featureAssociation'] = (t2 - t1) * 1e3
        heal = self._fa_guard.after_step(self.fa.health_problem())
        if heal is not None:  # the guard of the node's (core.guard): start the odometry again, keep the pose
            self.fa.restart()
            step.counts += [STATE_RESETS, SCANS_DROPPED]
            step.notices.append(f'scan at {stamp * 1e-9:.3f} s: {heal}: odometry restarted')
            step.dropped = f'{heal}: odometry restarted'
            return step
        step.counts.append(SCANS_PROCESSED)
        step.imu_used = features.imu_used
        if features.imu_used:
            step.counts.append(SCANS_WITH_IMU)
        if features.imu_uncovered is not None:
            counter = uncovered_counter(features.imu_uncovered)
            step.counts.append(counter)
            self._uncovered[counter] = self._uncovered.get(counter, 0) + 1
            if warn_uncovered(self._uncovered[counter]):
                step.notices.append(
                    uncovered_warning(
                        features.imu_uncovered, self._uncovered[counter], stamp, self.params.imu.time_offset
                    )
                )
        if features.imu_alignment is not None:
            step.notices.append(features.imu_alignment)
        pose = None if features.initialized else features.pose
        if self._listener is not None:
            step.event = ScanProcessed(stamp, segmentation, features, pose, dict(step.timings_ms))
        if pose is not None:
            step.odometry = (pose, features.pose_covariance, features.motion_covariance)
        if features.corner_last is not None and features.outlier_last is not None:
            step.map_inputs = (
                features.transform_sum,
                features.corner_last,
                features.surf_last,
                features.outlier_last,
                None if features.initialized else features.pose_covariance,
            )
        return step


def _dropped_note(stamp_ns: int, reason: str) -> str:
    return f'scan at {stamp_ns * 1e-9:.3f} s dropped: {reason}'


@dataclass
class FrontStep:
    """What imageProjection and featureAssociation made of one scan, for :meth:`Pipeline.apply`: plain values
    (a listener's event aside), so that it can be made in another process."""

    stamp_ns: int
    counts: list[str] = field(default_factory=list)  # counters to add one to
    # In order: warnings (str) and featureAssociation's IMU-check decisions (core.imu.monitor.AlignmentEvent).
    notices: list = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)  # stage -> [ms]
    dropped: str | None = None  # why the scan was dropped
    imu_used: bool = False
    # (4x4 /laser_odom_to_init in camera_init, its 6x6 covariance, the sweep motion's) unless the scan initialised
    odometry: tuple | None = None
    # (transform_sum, corner_last, surf_last, outlier_last, odometry covariance or None) for mapOptimization
    map_inputs: tuple | None = None
    event: ScanProcessed | None = None  # for a listener (not made without one)


@dataclass(frozen=True)
class _Fuse:
    """transformFusion integrates a scan's odometry (4x4, camera_init)."""

    stamp_ns: int
    odometry: np.ndarray
    covariance: np.ndarray | None = None  # the odometry pose's


@dataclass(frozen=True)
class _Mapped:
    """A mapping step of the scan stamped ``stamp_ns``; the future gives (MappingStep or None, CPU ms, what a
    listener gets besides: (new keyframe's cloud or None, keyframe positions), or None without a listener)."""

    stamp_ns: int
    future: Future


@dataclass(frozen=True)
class _LoopChecked:
    """A loop-closure check; the future gives (LoopResult or None, CPU ms of detection, of verification,
    keyframe positions for a listener or None without one)."""

    future: Future


class _BackEnd:
    """mapOptimization and transformFusion of a run, in arrival order.

    Work for mapOptimization (IMU samples, mapping inputs, loop-closure checks) goes to one worker thread in
    the order it arrives; transformFusion's events (fuse a scan's odometry, take a mapping result) are queued in
    the same order and applied by :meth:`drain` as their results become available. So every scan is fused
    with exactly the mapping results of the scans before it, whether the worker is a thread or not.
    """

    def __init__(
        self,
        mo: Mapper | None,
        fusion: TransformFusion,
        result: RunResult,
        warn: Callable[[str], None],
        threaded: bool,
        listener: PipelineListener | None = None,
    ):
        self.mo, self.fusion, self.result, self.warn = mo, fusion, result, warn
        self.listener = listener
        self.continuity = OdometryContinuity()  # (used on the mapping worker only)
        self.guard = StepGuard(1 if mo is None else mo.params.reliability.reset_after_failures)  # (likewise)
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix='mapping') if threaded else None
        # CPU time of mapping and loop closure: the worker thread's own (wall time would count its waits for the
        # GIL while the main thread runs the next scans), or the whole process's when nothing else runs beside
        # them (then the threads of open3d and scipy count too).
        self._cpu_time = time.thread_time if threaded else time.process_time
        self._imu: list[tuple] = []
        self._events: deque[_Fuse | _Mapped | _LoopChecked] = deque()
        self._unheard: deque[_Mapped] = deque()  # mapping steps featureAssociation has not heard of yet

    def _submit(self, job) -> Future:
        imu, self._imu = self._imu, []

        def with_imu():
            for sample in imu:  # the IMU samples that arrived before this job, as in the sequential run
                self.mo.imu.add(*sample)
            return job()

        if self._executor is not None:
            return self._executor.submit(with_imu)
        future = Future()
        future.set_result(with_imu())
        return future

    def add_imu(self, sample: tuple) -> None:
        if self.mo is not None:
            self._imu.append(sample)

    def fuse(self, stamp_ns: int, odometry: np.ndarray, covariance: np.ndarray | None = None) -> None:
        self._events.append(_Fuse(stamp_ns, odometry, covariance))
        self.drain()

    def map(self, stamp: int, *inputs, odometry_covariance: np.ndarray | None = None) -> None:
        if self.mo is None:
            return

        def step():
            t = self._cpu_time()
            transform_sum = inputs[0]
            pose = pose6_to_matrix(transform_sum)
            jump = self.continuity.check(stamp, pose)
            if jump is not None:  # the same protection as the node's: continue the map, do not drag it
                self.warn(f'mapping input at {stamp * 1e-9:.3f} s: {jump.describe()}')
                self.mo.reanchor(jump, pose, transform_sum)
            mapped = self.mo.process(stamp, *inputs, odometry_covariance=odometry_covariance)
            heal = self.guard.after_step(self.mo.health_problem()) if mapped is not None else None
            if heal is not None:  # the guard of the node's (core.guard): reset what is poisoned, keep the map
                self.warn(f'mapping step at {stamp * 1e-9:.3f} s: {heal}: {self.mo.heal()}')
                mapped = None
            cpu_ms = (self._cpu_time() - t) * 1e3
            # (Read here, on the worker, where the keyframes cannot change meanwhile.)
            seen = self._keyframes_seen(mapped is not None and mapped.keyframe_added) if self.listener else None
            return mapped, cpu_ms, seen, heal is not None

        mapped = _Mapped(stamp, self._submit(step))
        self._events.append(mapped)
        self._unheard.append(mapped)

    def mapped_before(self, stamp_ns: int) -> list[tuple[int, np.ndarray]]:
        """(stamp, mapped pose six-vector) of every mapping step of a scan stamped up to ``stamp_ns`` not asked for
        before, waiting for them (the same steps whether the mapping has its own thread or not)."""
        out = []
        while self._unheard and self._unheard[0].stamp_ns <= stamp_ns:
            step = self._unheard.popleft().future.result()[0]
            if step is not None:
                out.append((step.stamp_ns, step.transform_aft))
        return out

    def finished_steps(self) -> list[tuple[int, np.ndarray | None]]:
        """(stamp, mapped pose six-vector or None) of the finished mapping steps not asked for before, in order."""
        out = []
        while self._unheard and self._unheard[0].future.done():
            mapped = self._unheard.popleft()
            step = mapped.future.result()[0]
            out.append((mapped.stamp_ns, None if step is None else step.transform_aft))
        return out

    def loop_closure(self) -> None:
        def close():
            t = self._cpu_time()
            candidate = self.mo.detect_loop()
            detected = self._cpu_time()
            loop = self.mo.close_loop(candidate) if candidate is not None else None
            verified = self._cpu_time()
            positions = self._keyframes_seen(False)[1] if self.listener else None
            return loop, (detected - t) * 1e3, (verified - detected) * 1e3, positions

        self._events.append(_LoopChecked(self._submit(close)))

    def drain(self, wait: bool = False) -> None:
        """Apply the queued events whose results are ready (all of them, waiting, with ``wait``)."""
        result = self.result
        while self._events:
            event = self._events[0]
            if not isinstance(event, _Fuse) and not wait and not event.future.done():
                return
            self._events.popleft()
            if isinstance(event, _Fuse):
                result.integrated.append(self.fusion.integrate(event.odometry, event.covariance, event.stamp_ns))
                result.integrated_covariance.append(self.fusion.covariance.copy())
                result.published.append(self.fusion.publishable(event.stamp_ns))
                if self.listener is not None:
                    self.listener(ScanFused(event.stamp_ns, result.integrated[-1]))
            elif isinstance(event, _Mapped):
                step, ms, seen, healed = event.future.result()
                if healed:
                    result.count(STATE_RESETS)
                    result.count(MAPPING_STEPS_FAILED)
                if step is not None and step.imu_alignment is not None:
                    self.imu_alignment('mapOptimization', step.imu_alignment)
                if step is not None:
                    result.time('mapOptimization', ms)
                    result.count(MAPPING_STEPS)
                    if step.degenerate:  # (a direction held at the prediction, see core.scan_to_map)
                        result.count(MAPPING_DEGENERATE)
                    aft, bef = pose6_to_matrix(step.transform_aft), pose6_to_matrix(step.transform_bef)
                    self.fusion.on_mapped(aft, bef, event.stamp_ns, step.pose_covariance)
                    result.mapped_stamps.append(event.stamp_ns)
                    result.mapped.append(aft)
                    result.mapped_covariance.append(step.pose_covariance)
                    if self.listener is not None:
                        self.listener(MapStepped(event.stamp_ns, step, aft, *seen, cpu_ms=ms))
            else:
                loop, detection_ms, verification_ms, positions = event.future.result()
                result.time('loop_closure', detection_ms + verification_ms)
                result.time('loop_detection', detection_ms)
                if loop is not None:
                    result.time('loop_verification', verification_ms)
                if self.listener is not None:
                    self.listener(LoopChecked(loop, positions, detection_ms + verification_ms))

    def _keyframes_seen(self, new_keyframe: bool) -> tuple[np.ndarray | None, np.ndarray]:
        """(the newest keyframe's corner, surface and outlier clouds in camera_init when ``new_keyframe``, else
        None; (K, 3) positions of every keyframe in camera_init), for a listener."""
        poses = self.mo.keyframe_poses()
        cloud = None
        if new_keyframe and self.mo.builds_map and self.mo.keyframes:
            keyframe = self.mo.keyframes[-1]
            cloud = transform_cloud(np.concatenate([keyframe.corner, keyframe.surf, keyframe.outlier]), keyframe.pose6)
        return cloud, poses[:, 3:6].copy()

    def imu_alignment(self, node: str, event) -> None:
        """An IMU check's decision: recorded, counted and warned about (the check itself repeats its advice only
        every so many seconds of data)."""
        self.result.imu_alignment.append((node, event))
        self.result.count('imu_alignment_warnings' if not event.trusted else 'imu_alignment_recoveries')
        self.warn(event.message)

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
