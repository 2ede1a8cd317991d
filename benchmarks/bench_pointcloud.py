"""Cost of PointCloud2 <-> numpy for a 1 MB VLP-16 cloud (32768 points x 32 bytes, the driver's layout).

    .venv/bin/python benchmarks/bench_pointcloud.py
Target: under 1 ms each way.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import summary, time_ms  # noqa: E402

from lego_loam_py.core.pointcloud import velodyne_points, xyz_array  # noqa: E402
from lego_loam_py.ros.conversions import array_to_cloud_msg, cloud_msg_to_array, make_header  # noqa: E402


def main() -> None:
    n = 32768
    rng = np.random.default_rng(0)
    points = velodyne_points(
        rng.normal(size=(n, 3)) * 30, rng.uniform(0, 255, n), rng.integers(0, 16, n), np.linspace(0, 0.1, n)
    )
    header = make_header(1, 'velodyne')
    msg = array_to_cloud_msg(points, header)
    print(f'cloud: {n} points, {len(msg.data) / 2**20:.2f} MiB')
    print(summary('numpy -> PointCloud2 (array_to_cloud_msg)', time_ms(lambda: array_to_cloud_msg(points, header))))
    print(summary('PointCloud2 -> numpy (cloud_msg_to_array)', time_ms(lambda: cloud_msg_to_array(msg))))
    print(
        summary(
            'PointCloud2 -> numpy + xyz float32 copy', time_ms(lambda: xyz_array(cloud_msg_to_array(msg), np.float32))
        )
    )
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2

    raw = serialize_message(msg)
    print(summary('rclpy serialize (for reference)', time_ms(lambda: serialize_message(msg), repeat=50)))
    print(
        summary('rclpy deserialize (for reference)', time_ms(lambda: deserialize_message(raw, PointCloud2), repeat=50))
    )


if __name__ == '__main__':
    main()
