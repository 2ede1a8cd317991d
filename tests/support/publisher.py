"""Test helper process: publishes sample data until killed.

python -m tests.support.publisher cloud_info   # CloudInfo with tests.support.samples content, 10 Hz
python -m tests.support.publisher tf_static    # the original's static transforms, latched, once
"""

import sys
import time

import rclpy

from lego_loam_py.ros import qos
from lego_loam_py.ros.conversions import make_header, numpy_to_array
from tests.support.samples import cloud_info_arrays


def main(mode: str) -> None:
    rclpy.init()
    node = rclpy.create_node(f'test_publisher_{mode}')
    if mode == 'cloud_info':
        from cloud_msgs.msg import CloudInfo

        arrays = cloud_info_arrays()
        publisher = node.create_publisher(CloudInfo, '/segmented_cloud_info', qos.reliable(1))
        msg = CloudInfo(check_fields=False)
        msg.header = make_header(1_600_000_000_250_000_000, 'velodyne')
        msg.start_ring_index = numpy_to_array(arrays['start_ring_index'], 'i')
        msg.end_ring_index = numpy_to_array(arrays['end_ring_index'], 'i')
        msg.start_orientation = float(arrays['start_orientation'])
        msg.end_orientation = float(arrays['end_orientation'])
        msg.orientation_diff = float(arrays['orientation_diff'])
        msg.segmented_cloud_ground_flag = arrays['segmented_cloud_ground_flag'].tolist()
        msg.segmented_cloud_col_ind = numpy_to_array(arrays['segmented_cloud_col_ind'], 'I')
        msg.segmented_cloud_range = numpy_to_array(arrays['segmented_cloud_range'], 'f')
        print('ready', flush=True)
        while rclpy.ok():
            publisher.publish(msg)
            time.sleep(0.1)
    elif mode == 'tf_static':
        from lego_loam_py.ros.tf import StaticTransformBroadcaster, original_static_transforms

        broadcaster = StaticTransformBroadcaster(node)
        broadcaster.send(original_static_transforms(stamp=42))
        print('ready', flush=True)
        rclpy.spin(node)
    else:
        raise SystemExit(f'unknown mode {mode}')


if __name__ == '__main__':
    try:
        main(sys.argv[1])
    except KeyboardInterrupt:
        pass
