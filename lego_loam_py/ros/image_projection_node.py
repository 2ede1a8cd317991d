"""The ``imageProjection`` node: /velodyne_points -> segmented cloud, CloudInfo and outliers.

Subscribes the lidar topic with best-effort QoS (accepts reliable and best-effort drivers) and depth 1, like
the original's queue of 1: when processing falls behind, the latest scan wins. Publishes, stamped with the
input stamp, in frame ``base_link`` (the lidar frame; CloudInfo keeps the input header):

* always: /segmented_cloud, /segmented_cloud_info, /outlier_cloud
* while subscribed: /full_cloud_projected, /full_cloud_info, /ground_cloud, /segmented_cloud_pure

Bad clouds (invalid layout, no x/y/z, nothing valid, wrong sensor, more than
``reliability.max_points_per_pixel`` times as many points as the range image has pixels) are dropped with a
throttled warning; an oversized one before it is decoded, and the memory its message took is given back. The
node keeps no state between scans, so a bad cloud costs that cloud only.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from sensor_msgs.msg import PointCloud2

from cloud_msgs.msg import CloudInfo
from lego_loam_py.core import validation
from lego_loam_py.core.frames import BASE_LINK_FRAME
from lego_loam_py.core.pointcloud import CloudLayoutError
from lego_loam_py.core.projection.elevation_bias import elevation_note
from lego_loam_py.core.projection.image_projection import ImageProjection, InputError, prepare_input
from lego_loam_py.core.validation import MAX_COORDINATE
from lego_loam_py.ros import qos
from lego_loam_py.ros.conversions import (
    cloud_msg_to_array,
    make_header,
    serialized_cloud_info,
    serialized_xyzi_cloud,
    stamp_to_ns,
)
from lego_loam_py.ros.node_base import LegoLoamNode
from lego_loam_py.ros.runtime import run_node

__all__ = ['ImageProjectionNode', 'main']


class ImageProjectionNode(LegoLoamNode):
    def __init__(self, **kwargs):
        super().__init__('imageProjection', **kwargs)
        self.core = ImageProjection(self.params)
        # The clouds are in the lidar's frame: the original's base_link, or in the REP-105 tree the lidar's own.
        frames = self.params.frames
        self.cloud_frame = frames.lidar_frame if frames.rep105 else BASE_LINK_FRAME
        topic = self.params.sensor.point_cloud_topic
        # Serialized: the cloud is read from the bytes (cloud_from_serialized), not copied into a message first.
        self.create_subscription(PointCloud2, topic, self.on_cloud, qos.sensor_input(1), raw=True)
        out = qos.reliable(1)
        self.pub_segmented = self.create_publisher(PointCloud2, '/segmented_cloud', out)
        self.pub_info = self.create_publisher(CloudInfo, '/segmented_cloud_info', out)
        self.pub_outlier = self.create_publisher(PointCloud2, '/outlier_cloud', out)
        self.pub_full = self.create_publisher(PointCloud2, '/full_cloud_projected', out)
        self.pub_full_info = self.create_publisher(PointCloud2, '/full_cloud_info', out)
        self.pub_ground = self.create_publisher(PointCloud2, '/ground_cloud', out)
        self.pub_pure = self.create_publisher(PointCloud2, '/segmented_cloud_pure', out)
        s = self.params.sensor
        rows_from = f"the '{s.ring_field}' field" if s.use_cloud_ring else 'the elevation angle'
        self.get_logger().info(
            f'imageProjection: {topic} -> /segmented_cloud; {s.preset} range image '
            f'{s.n_scan}x{s.horizon_scan}, rows from {rows_from}'
        )

    def on_cloud(self, msg: PointCloud2 | bytes) -> None:
        """A scan: a PointCloud2, or its serialized bytes."""
        start = time.perf_counter()
        self.count('clouds_in')
        ok, msg = self.take_cloud(msg, 'clouds_dropped', 'dropping unreadable cloud', 'bad_cloud')
        if not ok:
            return
        try:
            s = self.params.sensor
            try:
                validation.check_count(
                    f'{s.point_cloud_topic} points',
                    int(msg.width) * int(msg.height),
                    validation.raw_points_limit(self.params),
                    f'points {self.params.reliability.max_points_per_pixel:g} per pixel of the '
                    f'{s.n_scan}x{s.horizon_scan} range image of sensor.preset {s.preset} allow '
                    '(reliability.max_points_per_pixel): not a scan of this sensor',
                )
            except validation.InputRejected as exc:
                raise InputError(str(exc)) from None
            points = cloud_msg_to_array(msg)
            data = prepare_input(points, self.params)
            if data.xyz.shape[0] == 0:
                raise InputError('the cloud has no valid point')
        except (CloudLayoutError, InputError) as exc:
            self.count('clouds_dropped')
            self.warn(
                'bad_cloud',
                f'dropping cloud stamped {msg.header.stamp.sec}.{msg.header.stamp.nanosec:09d} '
                f'from {msg.header.frame_id!r}: {exc}',
            )
            self.reject_large(msg)
            return
        except Exception:  # never let one message take the node down
            self.count('clouds_dropped')
            self.error('cloud_exception', 'unexpected error while reading a cloud; dropped')
            return
        self.input_valid()
        try:
            self._check_sensor(points, data)
        except Exception:
            self.error('check_exception', 'unexpected error while checking a cloud')
        try:
            result = self.core.process(data)
        except InputError as exc:
            self.count('clouds_dropped')
            self.warn('bad_cloud', f'dropping cloud: {exc}')
            return
        except Exception:
            self.count('clouds_dropped')
            self.error('process_exception', 'unexpected error in imageProjection; scan dropped')
            return
        header = make_header(msg.header.stamp, self.cloud_frame)
        self.pub_segmented.publish(serialized_xyzi_cloud(result.segmented_cloud, header, time=result.segmented_time))
        self.pub_info.publish(serialized_cloud_info(result.cloud_info, msg.header))
        self.pub_outlier.publish(serialized_xyzi_cloud(result.outlier_cloud, header))
        if self.pub_full.get_subscription_count():
            self.pub_full.publish(serialized_xyzi_cloud(result.full_cloud, header, is_dense=False))
        if self.pub_full_info.get_subscription_count():
            self.pub_full_info.publish(serialized_xyzi_cloud(result.full_info_cloud, header, is_dense=False))
        if self.pub_ground.get_subscription_count():
            self.pub_ground.publish(serialized_xyzi_cloud(result.ground_cloud, header))
        if self.pub_pure.get_subscription_count():
            self.pub_pure.publish(serialized_xyzi_cloud(result.segmented_cloud_pure, header))
        if 'elevation_offset_found' in result.stats:
            self.get_logger().info(
                elevation_note(result.stats['elevation_offset_found'], stamp_to_ns(msg.header.stamp))
            )
        self.count('clouds_out')
        self.output_published()
        self.record_time('scan', time.perf_counter() - start)

    def _check_sensor(self, points: np.ndarray, data) -> None:
        """Throttled hints when the cloud does not look like the configured sensor."""
        s = self.params.sensor
        names = points.dtype.names or ()
        if s.use_cloud_ring and s.ring_field not in names:
            self.warn(
                'no_ring',
                f"the cloud has no '{s.ring_field}' field: rows come from the point order of a "
                'cloud stored laser by laser, else from the elevation angle (set '
                'sensor.use_cloud_ring: false for the elevation angle always and no warning)',
            )
        if data.ring is not None and data.ring.size:
            highest = int(data.ring.max())
            if highest >= s.n_scan:
                share = np.count_nonzero(data.ring >= s.n_scan) / data.ring.size
                self.warn(
                    'ring_range',
                    f'{share:.0%} of the points have {s.ring_field} >= {s.n_scan} (up to '
                    f'{highest}) and are dropped: is sensor.preset ({s.preset}) right?',
                )
        if data.dropped_non_finite:
            self.warn(
                'non_finite',
                f'{data.dropped_non_finite} points with NaN/inf coordinates (or beyond {MAX_COORDINATE:g} m) dropped',
                period=60.0,
            )


def main(args=None) -> int:
    return run_node(ImageProjectionNode, args)


if __name__ == '__main__':
    sys.exit(main())
