"""imageProjection: range image, ground removal and segmentation (docs/original.md §3, §6.1, §8).

:class:`ImageProjection` chains the three steps on one scan and assembles what the node publishes: the projection
(:mod:`lego_loam_py.core.projection.range_image`), the ground (:mod:`lego_loam_py.core.projection.ground`) and the
labels (:mod:`lego_loam_py.core.projection.segmentation`). Everything is vectorised over points and pixels. The
arithmetic follows the C++ original step by step, in float32 where it uses floats and with libm's ``atan2f`` (see
:mod:`lego_loam_py.core.parity.libm`), so on the same input the clouds and CloudInfo arrays equal the original's point
for point.

Frames: every input and output point is in the sensor frame (REP-103 lidar axes, ``base_link``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lego_loam_py.core.params.types import Params
from lego_loam_py.core.projection.cloud_info import CloudInfo
from lego_loam_py.core.projection.elevation_bias import ElevationBias
from lego_loam_py.core.projection.ground import GroundRemoval
from lego_loam_py.core.projection.range_image import (
    InputError,
    ProjectionInput,
    RangeImage,
    RangeImageProjection,
    prepare_input,
)
from lego_loam_py.core.projection.segmentation import NO_LABEL, OUTLIER_LABEL, SEGMENTATION_IMPORTS, Segmentation

# The projection's input and the label values are part of this module's API (the node and the tests use them).
__all__ = [
    'CloudInfo',
    'SegmentationResult',
    'ImageProjection',
    'ProjectionInput',
    'OUTLIER_LABEL',
    'NO_LABEL',
    'prepare_input',
    'InputError',
]


@dataclass
class SegmentationResult:
    """What imageProjection publishes for one scan; clouds are float32 (k, 4) = x, y, z, intensity."""

    segmented_cloud: np.ndarray  # intensity = row + col / 10000
    cloud_info: CloudInfo
    outlier_cloud: np.ndarray  # intensity = row + col / 10000
    ground_cloud: np.ndarray  # intensity = row + col / 10000
    segmented_cloud_pure: np.ndarray  # intensity = segment label (1, 2, ...)
    full_cloud: np.ndarray  # (N_SCAN*H, 4) row-major range image; empty cells NaN, intensity -1
    full_info_cloud: np.ndarray  # same cells, intensity = range [m]
    range_image: np.ndarray  # float32 (N_SCAN, H) [m], FLT_MAX where empty
    ground_mask: np.ndarray  # bool (N_SCAN, H)
    label_image: np.ndarray  # int32 (N_SCAN, H): -1 ground/empty, 999999 outlier, >= 1 segment
    stats: dict = field(default_factory=dict)  # point counts: input_points, non_finite, at_origin, dropped_*, ...
    segmented_time: np.ndarray | None = None  # float32 (M,) per-point time of the segmented cloud [s]
    pixel_point: np.ndarray | None = None  # int64 (N_SCAN*H,): index of the input point in each pixel, -1 empty


class ImageProjection:
    """The imageProjection algorithm for one sensor configuration; :meth:`process` handles one scan."""

    # Imported by the first scan, not with this module (a node imports them ahead with its first input).
    DEFERRED_IMPORTS = SEGMENTATION_IMPORTS

    def __init__(self, params: Params):
        self.params = params
        self.n_scan = n = params.sensor.n_scan
        self.horizon_scan = h = params.sensor.horizon_scan
        self.projection = RangeImageProjection(params)
        # A common error of the beams' elevation: the parameter's, or found from the ground (core.elevation_bias).
        self.elevation = ElevationBias(
            params.sensor.elevation_offset, params.image_projection.estimate_elevation_offset
        )
        self.ground_removal = GroundRemoval(params)
        self.segmentation = Segmentation(params)
        # Per-pixel constants of the published clouds (row-major pixel indices).
        ip, g = params.image_projection, params.sensor.ground_scan_ind
        rows = np.repeat(np.arange(n), h)
        self._cols = cols = np.tile(np.arange(h), n)
        self._ground_kept_column = (
            (cols % ip.ground_column_stride == 0)
            | (cols <= ip.ground_edge_columns)
            | (cols >= h - ip.ground_edge_columns)
        )
        self._outlier_kept_pixel = (rows > g) & (cols % ip.outlier_column_stride == 0)
        self._ground_row_pixel = rows <= g

    def process(self, data: ProjectionInput) -> SegmentationResult:
        """Project, remove ground, segment and assemble the published clouds for one scan."""
        if data.xyz.shape[0] == 0:
            raise InputError('the cloud has no valid point')
        self.elevation.correct(data.xyz)
        image = self.projection.project(data)
        ground = self.ground_removal.ground(image.full_cloud, image.filled)
        found = self.elevation.observe(image.full_cloud[ground, :3]) if self.elevation.looking else None
        labels = self.segmentation.labels(image.range, image.filled, ground)
        result = self._assemble(image, ground, labels, data)
        result.stats['elevation_offset_deg'] = self.elevation.offset_deg
        if found is not None:  # (from the next scan on)
            result.stats['elevation_offset_found'] = found
        return result

    # --------------------------------------------------------------------------------- assembling
    def _assemble(
        self, image: RangeImage, ground: np.ndarray, labels: np.ndarray, data: ProjectionInput
    ) -> SegmentationResult:
        n, h = self.n_scan, self.horizon_scan
        full, range_image, filled = image.full_cloud, image.range, image.filled
        # Pixels in row-major order, as the original walks them.
        outlier = labels == OUTLIER_LABEL
        in_segment = (labels > 0) & ~outlier
        segmented = in_segment | (ground & self._ground_kept_column)
        segmented_index = np.flatnonzero(segmented)
        outlier_index = np.flatnonzero(outlier & self._outlier_kept_pixel)

        count_before_row = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.count_nonzero(segmented.reshape(n, h), axis=1), out=count_before_row[1:])
        margin = self.params.image_projection.ring_index_margin
        start_ring = (count_before_row[:-1] - 1 + margin).astype(np.int32)
        end_ring = (count_before_row[1:] - 1 - margin).astype(np.int32)

        info = CloudInfo(
            start_ring_index=start_ring,
            end_ring_index=end_ring,
            start_orientation=image.start_orientation,
            end_orientation=image.end_orientation,
            orientation_diff=image.orientation_diff,
            segmented_cloud_ground_flag=ground[segmented_index],
            segmented_cloud_col_ind=self._cols[segmented_index].astype(np.uint32),
            segmented_cloud_range=range_image[segmented_index],
        )
        ground_index = np.flatnonzero(ground & self._ground_row_pixel)
        pure_index = np.flatnonzero(in_segment)
        pure = np.take(full, pure_index, axis=0)
        pure_labels = labels[pure_index]
        pure[:, 3] = pure_labels
        stats = dict(image.stats)
        stats.update(
            input_points=int(data.xyz.shape[0] + data.dropped_non_finite + data.dropped_origin),
            non_finite=data.dropped_non_finite,
            at_origin=data.dropped_origin,
            time_ordered=int(data.time_ordered),
            rings_from_top=int(data.rings_from_top),
            projected=int(np.count_nonzero(filled)),
            ground=int(np.count_nonzero(ground)),
            segments=int(pure_labels.max(initial=0)),
            segmented=len(segmented_index),
            outliers=len(outlier_index),
        )
        segmented_time = image.time[segmented_index] if image.time is not None else None
        return SegmentationResult(
            segmented_time=segmented_time,
            pixel_point=image.point_of_pixel,
            segmented_cloud=np.take(full, segmented_index, axis=0),
            cloud_info=info,
            outlier_cloud=np.take(full, outlier_index, axis=0),
            ground_cloud=np.take(full, ground_index, axis=0),
            segmented_cloud_pure=pure,
            full_cloud=full,
            full_info_cloud=image.full_info_cloud,
            range_image=range_image.reshape(n, h),
            ground_mask=ground.reshape(n, h),
            label_image=labels.reshape(n, h),
            stats=stats,
        )
