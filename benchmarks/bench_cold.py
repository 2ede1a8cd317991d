"""What a small per-message callback costs when its caches were evicted since the last message, beside the same
callback warm.

    .venv/bin/python benchmarks/bench_cold.py [--messages 1000] [--sweep-mb 64]

Over DDS, two cores, the four nodes share a core (``bench_dds.py --pinned``): between two messages of one node the
others run, and its code and data are no longer in the caches. A callback of little work then costs several times
what it costs called in a loop. This script runs, in one process, transformFusion's odometry callback (publishing
left out) and the conversions every node runs per pose, each message either right after the previous one
(warm) or after a sweep over ``--sweep-mb`` of memory (cold), and prints the median microseconds per call of each.
Alternating warm and cold blocks, twice each; the figures of a shared machine vary by some 10 %.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lego_loam_py.testing.domains import DomainLease  # noqa: E402


def odometry_messages(count: int):
    """``count`` nav_msgs/Odometry at 10 Hz along x, with a diagonal covariance."""
    from nav_msgs.msg import Odometry

    out = []
    for k in range(count):
        msg = Odometry()
        msg.header.frame_id, msg.child_frame_id = 'camera_init', 'laser_odom'
        msg.header.stamp.sec, msg.header.stamp.nanosec = 100 + k // 10, (k % 10) * 100_000_000
        msg.pose.pose.position.x = 0.1 * k
        msg.pose.pose.orientation.w = 1.0
        msg.pose.covariance = [1e-4 if i % 7 == 0 else 0.0 for i in range(36)]
        out.append(msg)
    return out


def timed(call, messages, sweep: np.ndarray | None) -> list[float]:
    """Seconds of each ``call(message)``, after sweeping ``sweep`` (None: warm) before each."""
    times = []
    for msg in messages:
        if sweep is not None:
            sweep += 1.0
        start = time.perf_counter()
        call(msg)
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--messages', type=int, default=1000, help='per block (four blocks)')
    parser.add_argument('--sweep-mb', type=int, default=64, help='memory swept between two cold calls [MB]')
    args = parser.parse_args()
    with DomainLease() as domain:
        os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
        import rclpy

        from lego_loam_py.core.frames import make_pose
        from lego_loam_py.ros.conversions import make_header, odometry_to_pose, serialized_odometry
        from lego_loam_py.ros.transform_fusion_node import TransformFusionNode

        rclpy.init()
        node = TransformFusionNode()
        for publisher in node.publishers:
            publisher.publish = lambda msg: None
        node.tf.send_serialized = lambda *a, **k: None
        covariance = np.diag([1e-4] * 3 + [1e-6] * 3)
        header = make_header(0, 'camera_init')
        callbacks = {
            'transformFusion odometry callback': node.on_odometry,
            'odometry_to_pose': odometry_to_pose,
            'serialized_odometry (with covariance)': lambda msg: serialized_odometry(
                make_pose(), header, 'laser_odom', pose_covariance=covariance
            ),
        }
        sweep = np.zeros((args.sweep_mb << 20) // 8)
        messages = odometry_messages(4 * args.messages)
        print(f'median us per call, {args.messages} calls a block, cold = after a {args.sweep_mb} MB sweep')
        for name, call in callbacks.items():
            figures = {'warm': [], 'cold': []}
            for block in range(4):
                mode = 'cold' if block % 2 else 'warm'
                part = messages[block * args.messages : (block + 1) * args.messages]
                figures[mode] += timed(call, part, sweep if mode == 'cold' else None)
            warm, cold = (float(np.median(figures[mode])) * 1e6 for mode in ('warm', 'cold'))
            print(f'  {name:40s} warm {warm:7.1f}   cold {cold:7.1f}   ({cold / warm:.1f}x)')
        node.destroy_node()
        rclpy.shutdown()


if __name__ == '__main__':
    main()
