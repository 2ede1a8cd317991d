"""Small helpers shared by the benchmark scripts."""

from __future__ import annotations

import compileall
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np


def compile_bytecode(*trees: Path | str | None) -> list[Path]:
    """Write the bytecode caches (``__pycache__``) of the ``lego_loam_py`` package of each checkout given, and of
    every one on ``PYTHONPATH``, as ``pip install`` and ``colcon build`` do for an installed package: start-up is
    measured as a user pays it, not with the compilation of every module. (A shell with
    ``PYTHONDONTWRITEBYTECODE=1``, as this project's development machine has, never writes them itself, and a
    node then compiles its hundred modules at every start: 0.03-0.06 s of its CPU.) Returns the packages compiled."""
    done = []
    for tree in [*trees, *os.environ.get('PYTHONPATH', '').split(os.pathsep)]:
        package = Path(tree) / 'lego_loam_py' if tree else None
        if package is not None and package.is_dir() and package not in done:
            compileall.compile_dir(str(package), quiet=1)
            done.append(package)
    return done


def time_ms(function: Callable[[], object], repeat: int = 200, warmup: int = 10) -> np.ndarray:
    """Wall time of each call [ms]."""
    for _ in range(warmup):
        function()
    out = np.empty(repeat)
    for i in range(repeat):
        start = time.perf_counter()
        function()
        out[i] = (time.perf_counter() - start) * 1e3
    return out


def summary(name: str, samples_ms: np.ndarray) -> str:
    return (
        f'{name:<44s} median {np.median(samples_ms):8.3f} ms   p95 {np.percentile(samples_ms, 95):8.3f} ms   '
        f'(n={len(samples_ms)})'
    )


def run_shifted(bag, params, imu: bool, skip: int):
    """``run_bag`` without the first ``skip`` clouds (and the IMU samples before them): the mapping steps fall on
    other scans, as a run over DDS may have them. The spread this gives is the run-to-run noise."""
    from lego_loam_py.bag.io import BagReader, cloud_msg_to_array
    from lego_loam_py.core.imu.buffer import imu_sample
    from lego_loam_py.core.pipeline import Pipeline

    pipeline = Pipeline(params, mapping_thread=False, warn=lambda text: None)
    clouds = 0
    with BagReader(bag) as reader:
        topics = [params.sensor.point_cloud_topic] + ([params.sensor.imu_topic] if imu else [])
        for message in reader.messages(topics=topics):
            msg = reader.deserialize(message)
            if message.topic != params.sensor.point_cloud_topic:
                if clouds >= skip:
                    pipeline.add_imu(imu_sample(msg))
                continue
            clouds += 1
            if clouds > skip:
                stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
                pipeline.process_scan(cloud_msg_to_array(msg), stamp)
    return pipeline.finish()
