"""Stage 1, imageProjection: a cloud's valid points read from any driver's layout, its range image, the ground,
the segmentation, and the corrections real lidars need (rows from the laser order, the beams' elevation error).

Its public API, each name from the module that defines it (imported on first use)."""

from __future__ import annotations

from lego_loam_py.core._exports import lazy_exports

_EXPORTS = {
    'CloudInfo': 'cloud_info',
    'ABSOLUTE_AFTER': 'driver_layouts',
    'ABSOLUTE_TIME_FIELDS': 'driver_layouts',
    'CloudPoints': 'driver_layouts',
    'KNOWN_TIME_FIELDS': 'driver_layouts',
    'SWEEP_SPAN': 'driver_layouts',
    'TIME_ORDER_TOLERANCE': 'driver_layouts',
    'TimeReading': 'driver_layouts',
    'read_cloud': 'driver_layouts',
    'rings_count_down': 'driver_layouts',
    'seconds_since_sweep_start': 'driver_layouts',
    'time_field_of': 'driver_layouts',
    'ElevationBias': 'elevation_bias',
    'apply_elevation_offset': 'elevation_bias',
    'elevation_note': 'elevation_bias',
    'ground_cone_deg': 'elevation_bias',
    'GroundRemoval': 'ground',
    'ImageProjection': 'image_projection',
    'InputError': 'image_projection',
    'NO_LABEL': 'image_projection',
    'OUTLIER_LABEL': 'image_projection',
    'ProjectionInput': 'image_projection',
    'SegmentationResult': 'image_projection',
    'prepare_input': 'image_projection',
    'MIN_STEP_DEG': 'laser_order',
    'rows_from_laser_order': 'laser_order',
    'RangeImage': 'range_image',
    'RangeImageProjection': 'range_image',
    'Segmentation': 'segmentation',
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
