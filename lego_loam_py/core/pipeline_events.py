"""What :class:`lego_loam_py.core.pipeline.Pipeline` tells a listener as a run goes on (a viewer, a recorder).

A listener is any callable taking one event; the pipeline calls it on the thread that calls ``process_scan``, in
the order of the run, and only when one was given (``Pipeline(params, listener=...)``): without a listener
nothing is collected. Events hold references to the stages' results, which the pipeline never changes again.

Frames: poses are 4x4 in camera_init (LOAM camera axes, as the pipeline's own); clouds say their frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

__all__ = ['ScanProcessed', 'ScanFused', 'MapStepped', 'LoopChecked', 'PipelineEvent', 'PipelineListener']


@dataclass(frozen=True)
class ScanProcessed:
    """A scan went through imageProjection and featureAssociation."""

    stamp_ns: int
    segmentation: object  # core.image_projection.SegmentationResult: clouds in the sensor frame (lidar axes)
    features: object  # core.feature_association.FeatureAssociationResult (camera axes, sweep start)
    odometry: np.ndarray | None  # 4x4 /laser_odom_to_init (None: the scan initialised the odometry)
    timings_ms: dict[str, float] = field(default_factory=dict)  # stage -> [ms]


@dataclass(frozen=True)
class ScanFused:
    """transformFusion's pose of a scan (/integrated_to_init, 4x4), with the mapping results before it applied."""

    stamp_ns: int
    pose: np.ndarray


@dataclass(frozen=True)
class MapStepped:
    """A mapping step of the scan stamped ``stamp_ns`` (/aft_mapped_to_init)."""

    stamp_ns: int
    step: object  # core.map_optimization.MappingStep
    pose: np.ndarray  # 4x4 transform_aft
    keyframe_cloud: np.ndarray | None  # (n, 4) the new keyframe's clouds in camera_init (None: no keyframe)
    keyframe_positions: np.ndarray  # (K, 3) every keyframe's position in camera_init after the step
    cpu_ms: float


@dataclass(frozen=True)
class LoopChecked:
    """A loop-closure check: ``loop`` is the core.loop_closure.LoopResult of a candidate (None: none found)."""

    loop: object | None
    keyframe_positions: np.ndarray  # (K, 3) after the correction, camera_init
    cpu_ms: float  # detection and verification, the mapping worker's CPU time


PipelineEvent = ScanProcessed | ScanFused | MapStepped | LoopChecked
PipelineListener = Callable[[PipelineEvent], None]
