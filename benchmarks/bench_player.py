"""Sustained rate of `lego_loam_py play` for 1 MB PointCloud2 messages with a subscriber attached.

    .venv/bin/python benchmarks/bench_player.py [--clouds 200] [--rates 10 1000]
A bag of 1 MB VLP-16 clouds at 10 Hz is played at each rate factor; a subscriber in another process
counts what arrives. Target: >= 50 Hz sustained with the subscriber attached.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from lego_loam_py.bag.io import BagWriter, make_cloud_msg  # noqa: E402
from lego_loam_py.core.pointcloud import velodyne_points  # noqa: E402
from lego_loam_py.testing.domains import DomainLease  # noqa: E402

SUBSCRIBER = textwrap.dedent("""
    import sys, time, rclpy
    from sensor_msgs.msg import PointCloud2
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    rclpy.init()
    node = rclpy.create_node('bench_counter')
    times = []
    node.create_subscription(PointCloud2, '/velodyne_points', lambda m: times.append(time.monotonic()),
                             QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    print('ready', flush=True)
    idle_since = time.monotonic()
    while time.monotonic() - idle_since < 3.0:
        n = len(times)
        rclpy.spin_once(node, timeout_sec=0.1)
        if len(times) != n:
            idle_since = time.monotonic()
    rate = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 0.0
    print(f'received {len(times)} rate {rate:.1f}', flush=True)
""")


def make_bag(path: Path, clouds: int) -> None:
    n = 32768  # x 32 bytes = 1 MiB
    rng = np.random.default_rng(0)
    points = velodyne_points(
        rng.normal(size=(n, 3)) * 30, rng.uniform(0, 255, n), rng.integers(0, 16, n), np.linspace(0, 0.1, n)
    )
    with BagWriter(path) as bag:
        for k in range(clouds):
            t = 1_700_000_000_000_000_000 + k * 100_000_000
            bag.write_msg('/velodyne_points', t, make_cloud_msg(bag.types, bag.header(t, 'velodyne'), points))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--clouds', type=int, default=200)
    parser.add_argument('--rates', type=float, nargs='+', default=[10.0, 1000.0])
    args = parser.parse_args()
    cli = Path(sys.executable).parent / 'lego_loam_py'
    with tempfile.TemporaryDirectory() as tmp, DomainLease() as domain:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
        bag = Path(tmp) / 'clouds'
        start = time.perf_counter()
        make_bag(bag, args.clouds)
        print(f'bag: {args.clouds} clouds of 1 MiB at 10 Hz, written in {time.perf_counter() - start:.1f} s')
        for rate in args.rates:
            sub = subprocess.Popen([sys.executable, '-c', SUBSCRIBER], env=env, stdout=subprocess.PIPE, text=True)
            assert sub.stdout.readline().strip() == 'ready'
            play = subprocess.run(
                [str(cli), 'play', str(bag), '--rate', str(rate), '--wait-for-subscribers', '10', '--no-progress'],
                env=env,
                capture_output=True,
                text=True,
            )
            out, _ = sub.communicate(timeout=60)
            published = re.search(r'\(([\d.]+) msg/s\)', play.stderr)
            received = re.search(r'received (\d+) rate ([\d.]+)', out)
            print(
                f'rate factor {rate:7.1f}: player {float(published.group(1)):7.1f} msg/s; subscriber received '
                f'{received.group(1)}/{args.clouds} at {float(received.group(2)):7.1f} Hz'
            )


if __name__ == '__main__':
    main()
