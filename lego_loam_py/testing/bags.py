"""Recordings made from recordings: a bag with a stretch of time cut out (a kidnapped robot, a sensor that stopped)."""

from __future__ import annotations

import shutil
from pathlib import Path


def cut_bag(source: str | Path, destination: str | Path, start_s: float, duration_s: float) -> Path:
    """A ROS 2 bag (mcap) with every message of ``source`` except those recorded from ``start_s`` [s after the
    bag's first message] for ``duration_s`` [s]; the simulator's sidecar files (ground truth, scenario) are
    copied beside it, so the stamps that remain keep their ground truth."""
    from lego_loam_py.bag.io import BagReader, BagWriter
    from lego_loam_py.inputs.sidecars import GROUND_TRUTH, GROUND_TRUTH_DENSE, SCENARIO, sidecar_path

    destination = Path(destination)
    with BagReader(source) as reader:
        begin = reader.start_time + int(start_s * 1e9)
        end = begin + int(duration_s * 1e9)
        with BagWriter(destination) as writer:
            for message in reader.messages():
                if not begin <= message.timestamp < end:
                    writer.write_raw(message.topic, message.msgtype, message.timestamp, message.data)
    for name in (GROUND_TRUTH, GROUND_TRUTH_DENSE, SCENARIO):
        if sidecar_path(source, name).is_file():
            shutil.copy(sidecar_path(source, name), sidecar_path(destination, name))
    return destination
