"""The offline run on every core: the recording read and projected (imageProjection) in one forked child process,
featureAssociation in another, mapOptimization and transformFusion in the caller's.

Python runs one thread at a time, so a worker thread overlaps the others only where numpy releases the GIL, which
its many small calls seldom do for long. Processes each have a core. The stages pass each scan on in recording
order: the reader sends each scan's projection, with the IMU samples read before it, to featureAssociation, which
sends what it made of the scan (:class:`~lego_loam_py.core.pipeline.FrontStep`) to the parent, which applies it
(:meth:`Pipeline.apply`). The parent sends back the pose of each mapping step as it finishes; featureAssociation's
IMU check takes it only for scans stamped ``MAPPED_POSE_LAG_NS`` later (and, without IMU samples, not at all:
FeatureAssociation.takes_mapped_poses), so featureAssociation waits for it only where it must. Every
stage takes the same inputs in the same order as in one process: the result is the same, bit for bit.

The big messages flow one way (reader -> featureAssociation -> parent) and only small ones back, so no two
processes can wait on each other's full pipe. The children are forked, not spawned: each starts in milliseconds
with the pipeline the parent built, parameters, open recording and all, and nothing is pickled but the messages.
Before the forks the parent runs no thread of its own (the pipeline's workers start on their first job; one BLAS
thread, see lego_loam_py.blas).
"""

from __future__ import annotations

import dataclasses
import fcntl
import multiprocessing
import os
import pickle
import signal
import traceback
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from lego_loam_py.core.pipeline import Pipeline
from lego_loam_py.errors import LegoLoamError
from lego_loam_py.inputs import ImuSample, Scan

__all__ = ['FrontEndProcessError', 'run_split', 'can_split']

# (item, projected) pairs in the order the pipeline takes them (see lego_loam_py.offline.items_in_turn); an item None
# ends a recording cut short, its pair's second value the seconds of recording read.
ItemsInTurn = Iterator[tuple[object, object]]

# What featureAssociation does not read of a segmentation (core.projection.SegmentationResult): left out of the
# messages, a 64-beam scan's range image and full clouds being most of their bytes.
_NOT_SENT = (
    'ground_cloud',
    'segmented_cloud_pure',
    'full_cloud',
    'full_info_cloud',
    'range_image',
    'ground_mask',
    'label_image',
)
_EMPTY = {name: np.empty(0, np.float32) for name in _NOT_SENT} | {'pixel_point': None}  # (their stand-ins)
_JOIN_S = 5.0
READER_NICENESS = 10
# A pipe's capacity [bytes] between two stages: a VLP-16 scan's projection is about 0.3 MB, its featureAssociation
# step 0.06 MB; a 64-beam scan's a few times more.
PIPE_BYTES = 4 << 20
F_SETPIPE_SZ = getattr(fcntl, 'F_SETPIPE_SZ', 1031)  # (Python 3.10+ names it on Linux)


class FrontEndProcessError(LegoLoamError, RuntimeError):
    """A front-end process failed or ended without finishing the recording."""


def can_split() -> bool:
    """Whether this process can fork the front end: not on Windows (no fork), nor in a daemonic process (a
    worker of a process pool, which may not have children)."""
    return 'fork' in multiprocessing.get_all_start_methods() and not multiprocessing.current_process().daemon


def run_split(pipeline: Pipeline, items: ItemsInTurn, on_scan: Callable[[], None]) -> float | None:
    """Run the recording's ``items`` through ``pipeline``, the front end in forked children; ``on_scan()`` after
    each scan applied. Returns the seconds of recording read when the items were cut short, else None.
    ``pipeline`` must have no mapping thread (its mapping runs here, between the scans) and no listener (whose
    events hold whole clouds). ``items`` is read in the reader process only. What the stages import on first use
    is best imported before (run_source does): once here, not in each child."""
    context = multiprocessing.get_context('fork')
    projected_in, projected_out = context.Pipe(duplex=False)
    steps_in, steps_out = context.Pipe(duplex=False)
    for end in (projected_out, steps_out):
        _widen(end)
    poses_in, poses_out = context.Pipe(duplex=False)
    ends = (projected_in, projected_out, steps_in, steps_out, poses_in, poses_out)
    # Each process keeps only its own ends open: a pipe ends (EOFError, BrokenPipeError) only when every copy of
    # the other end is closed, and a process that died must end its pipes for the others to learn of it.
    stages = [
        ('lego_loam_py reader', _reader, (pipeline, items, projected_out)),
        ('lego_loam_py odometry', _odometry, (pipeline, projected_in, steps_out, poses_in)),
    ]
    children = [
        context.Process(target=_in_child, args=(ends, stage, *args), name=name, daemon=True)
        for name, stage, args in stages
    ]
    for child in children:
        child.start()
    for end in ends:
        if end not in (steps_in, poses_out):
            end.close()
    cut = None
    child_listens = True  # (it stops once it has read the whole recording: the last mapping results are not for it)
    try:
        while True:
            kind, imu, payload = _receive(steps_in, children)
            for sample, rejected in imu:
                pipeline.apply_imu(sample, rejected)
            if kind == 'scan':
                pipeline.apply(payload)
                for finished in pipeline.mapping_results():
                    if child_listens:
                        try:
                            poses_out.send(finished)
                        except BrokenPipeError:
                            child_listens = False
                on_scan()
            elif kind == 'cut':
                cut = payload
            elif kind == 'end':
                break
            else:
                raise payload
    finally:
        steps_in.close()
        poses_out.close()
        for child in children:  # (they wait for nothing once their pipes are closed; killing is the last resort)
            child.join(_JOIN_S)
            if child.is_alive():
                child.kill()
                child.join()
    return cut


def _widen(connection) -> None:
    """Let a pipe hold several scans' messages (Linux: up to /proc/sys/fs/pipe-max-size, 1 MiB by default; 64 KiB
    otherwise): with less, a stage that finishes a scan while the next stage is busy waits for it to finish too,
    and the stages take turns instead of running side by side."""
    try:
        limit = int(Path('/proc/sys/fs/pipe-max-size').read_text())
        fcntl.fcntl(connection.fileno(), F_SETPIPE_SZ, min(limit, PIPE_BYTES))
    except (OSError, ValueError):  # (not Linux, or not allowed: the stages still run, in turns)
        pass


def _receive(connection, children) -> tuple:
    try:
        return connection.recv()
    except EOFError:
        for child in children:
            child.join(_JOIN_S)
        codes = ', '.join(f'{child.name}: {child.exitcode}' for child in children)
        raise FrontEndProcessError(f'a front-end process ended before the recording did (exit codes {codes})') from None


def _in_child(ends: tuple, stage: Callable, *args) -> None:
    """A child's start: ``stage(*args)`` with every pipe end not among ``args`` closed."""
    # Ctrl-C is the parent's to handle: it closes its pipes, and the children end when they find them closed.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for end in ends:
        if not any(end is arg for arg in args):
            end.close()
    stage(*args)


def _reader(pipeline: Pipeline, items: ItemsInTurn, out) -> None:
    """The first child: reads the recording and projects each scan (imageProjection), in recording order."""
    try:
        os.nice(READER_NICENESS)
        imu = []
        for item, projected in items:
            if item is None:
                out.send(('cut', imu, projected))
                imu = []
            elif isinstance(item, ImuSample):
                imu.append(item.sample)
            else:
                if isinstance(item, Scan):
                    try:
                        segmentation, projection_ms = projected.result()
                        payload = (dataclasses.replace(segmentation, **_EMPTY), projection_ms)
                    except Exception as exc:  # noqa: BLE001 (featureAssociation's step decides what it means)
                        payload = _sendable(exc)
                else:  # UnreadableScan
                    payload = item.reason
                out.send(('scan', imu, (type(item) is Scan, item.stamp_ns, payload)))
                imu = []
        out.send(('end', imu, None))
    except BaseException as exc:  # noqa: BLE001 (everything goes on to the parent, which raises it there)
        _send_error(out, exc)
    finally:
        pipeline.close()
        out.close()


def _odometry(pipeline: Pipeline, projected_in, out, poses_in) -> None:
    """The second child: featureAssociation on each projected scan, as the reader sends them."""
    try:
        awaited: deque[int] = deque()  # stamps of the mapping inputs sent whose poses have not come back
        unread = 0  # poses passed over (featureAssociation did not take them yet), still to be read and dropped

        def mapped_before(stamp_ns: int) -> list[tuple[int, np.ndarray]]:
            nonlocal unread
            out = []
            while awaited and awaited[0] <= stamp_ns:
                expected = awaited.popleft()
                if not pipeline.fa.takes_mapped_poses:  # (as if given: it would change nothing)
                    unread += 1
                    continue
                while unread:
                    poses_in.recv()
                    unread -= 1
                stamp, pose6 = poses_in.recv()
                if stamp != expected:
                    raise FrontEndProcessError(f'mapping result of {stamp} ns where {expected} ns was due')
                if pose6 is not None:
                    out.append((stamp, pose6))
            while unread and poses_in.poll():  # (so that the parent never finds the pipe full)
                poses_in.recv()
                unread -= 1
            return out

        while True:
            kind, samples, payload = projected_in.recv()
            imu = [(sample, pipeline.front_imu(sample)) for sample in samples]
            if kind == 'scan':
                readable, stamp_ns, result = payload
                if not readable:
                    step = pipeline.skipped(stamp_ns, result)
                else:
                    projected = Future()
                    if isinstance(result, BaseException):
                        projected.set_exception(result)
                    else:
                        projected.set_result(result)
                    step = pipeline.front_step(projected, stamp_ns, mapped_before)
                if step.map_inputs is not None and pipeline.mapping:
                    awaited.append(step.stamp_ns)
                out.send(('scan', imu, step))
            else:  # cut, end, error: passed on
                out.send((kind, imu, payload))
                if kind != 'cut':
                    return
    except BaseException as exc:  # noqa: BLE001 (everything goes to the parent, which raises it there)
        _send_error(out, exc)
    finally:
        pipeline.close()
        for end in (projected_in, out, poses_in):
            end.close()


def _send_error(out, exc: BaseException) -> None:
    try:
        out.send(('error', [], _sendable(exc)))
    except (OSError, ValueError):  # (the receiver is gone or stopped listening)
        pass


def _sendable(exc: BaseException) -> BaseException:
    """``exc`` for another process to raise: with this one's traceback as a note unless it is one of the package's
    errors (whose message says it all), or a FrontEndProcessError with that traceback if it does not pickle."""
    text = ''.join(traceback.format_exception(exc)).rstrip()
    try:
        if not isinstance(exc, LegoLoamError):
            exc.add_note(f'(in the front-end process)\n{text}')
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 (any failure to pickle means: send the text instead)
        return FrontEndProcessError(f'a front-end process failed:\n{text}')
