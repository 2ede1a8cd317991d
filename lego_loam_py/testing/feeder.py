"""Feeds a bag's lidar and IMU messages over DDS for as long as wanted: the reliability tests and benchmarks.

    python -m lego_loam_py.testing.feeder BAG [--rate R] [--duration S | --laps N] [--jump-back] [--burst N]

Unlike ``lego_loam_py play``, it can play a bag for any length of time with *continuous* stamps: every lap is
restamped (the header stamps in the serialized messages are shifted by whole laps), so the nodes see one long
drive; a bag whose trajectory returns to its start (the campus lap) then becomes an arbitrarily long run.
``--jump-back`` keeps the original stamps instead (time jumps back at every lap, like ``play --loop``).
``--burst N`` publishes N clouds back to back (with consecutive stamps) after the first second, as a driver
that stalled and flushed its queue would; with ``--burst-handshake`` it first prints ``burst ready`` and waits
for a line on stdin (the test stops a subscriber meanwhile, so that the burst arrives faster than it can
work, on any machine). Prints ``ready`` once every topic has a subscriber, ``lap K`` at
the start of each lap and ``done N`` at the end (N = clouds published).
"""

from __future__ import annotations

import argparse
import signal
import struct
import sys
import threading
import time

LIDAR, IMU = '/velodyne_points', '/imu/data'


def restamp(data, offset_ns: int) -> bytes:
    """Serialized (CDR) message whose first field is a std_msgs/Header, with its stamp moved by ``offset_ns``.

    CDR: 4 bytes of encapsulation (0x00 0x01: little endian), then the stamp: int32 sec, uint32 nanosec.
    """
    data = bytearray(data)
    little = data[1] in (0x01, 0x03)
    sec, nanosec = struct.unpack_from('<iI' if little else '>iI', data, 4)
    sec, nanosec = divmod(sec * 1_000_000_000 + nanosec + offset_ns, 1_000_000_000)
    struct.pack_into('<iI' if little else '>iI', data, 4, sec, nanosec)
    return bytes(data)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('bag')
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed (x real time)')
    parser.add_argument('--duration', type=float, default=None, help='seconds of data to publish (default: one lap)')
    parser.add_argument('--laps', type=int, default=None, help='laps to publish')
    parser.add_argument('--jump-back', action='store_true', help='keep the original stamps at every lap')
    parser.add_argument('--burst', type=int, default=0, help='clouds to publish at once after one second')
    parser.add_argument(
        '--burst-handshake',
        action='store_true',
        help="print 'burst ready' and wait for a line on stdin before the burst",
    )
    parser.add_argument('--no-imu', action='store_true')
    parser.add_argument('--imu-start', type=float, default=0.0, help='publish IMU only after this many seconds')
    parser.add_argument(
        '--imu-gap', type=float, nargs=2, default=None, metavar=('FROM', 'TO'), help='no IMU between these data seconds'
    )
    parser.add_argument('--wait-for-subscribers', type=float, default=30.0)
    parser.add_argument('--depth', type=int, default=10, help='publisher queue depth')
    args = parser.parse_args(argv)

    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Imu, PointCloud2

    from lego_loam_py.bag.io import BagReader
    from lego_loam_py.ros import qos

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('reliability_feeder')
    publishers = {LIDAR: node.create_publisher(PointCloud2, LIDAR, qos.reliable(args.depth))}
    if not args.no_imu:
        publishers[IMU] = node.create_publisher(Imu, IMU, qos.reliable(max(args.depth, 50)))
    deadline = time.monotonic() + args.wait_for_subscribers
    while time.monotonic() < deadline and not stop.is_set():
        if all(p.get_subscription_count() > 0 for p in publishers.values()):
            break
        time.sleep(0.05)
    time.sleep(0.5)  # let the subscribers finish matching
    print('ready', flush=True)

    reader = BagReader(args.bag)
    reader.open()
    lap_ns = reader.end_time - reader.start_time + 100_000_000  # one sweep after the last message
    total_ns = None if args.duration is None else int(args.duration * 1e9)
    laps = args.laps if args.laps is not None else (1 if total_ns is None else 1 + total_ns // lap_ns)
    clouds = 0
    wall_start = time.monotonic()
    burst_done = args.burst == 0
    try:
        for lap in range(laps):
            print(f'lap {lap}', flush=True)
            offset = 0 if args.jump_back else lap * lap_ns
            for message in reader.messages(topics=list(publishers)):
                if stop.is_set():
                    break
                elapsed_ns = message.timestamp - reader.start_time + lap * lap_ns
                if total_ns is not None and elapsed_ns > total_ns:
                    break
                data_s = elapsed_ns * 1e-9
                if message.topic == IMU:
                    gap = args.imu_gap
                    if data_s < args.imu_start or (gap is not None and gap[0] <= data_s < gap[1]):
                        continue
                target = wall_start + data_s / args.rate
                delay = target - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                if stop.is_set():
                    break
                data = restamp(message.data, offset) if offset else bytes(message.data)
                publishers[message.topic].publish(data)
                if message.topic == LIDAR:
                    clouds += 1
                    if not burst_done and data_s >= 1.0:
                        burst_done = True
                        if args.burst_handshake:
                            print('burst ready', flush=True)
                            sys.stdin.readline()
                        for k in range(1, args.burst + 1):  # stamps 0.9 ms apart, before the next sweep
                            publishers[LIDAR].publish(restamp(data, k * 900_000))
                        clouds += args.burst
                        print(f'burst {args.burst}', flush=True)
            if stop.is_set() or (total_ns is not None and (lap + 1) * lap_ns > total_ns):
                break
    finally:
        reader.close()
        for publisher in publishers.values():
            try:
                from rclpy.duration import Duration

                publisher.wait_for_all_acked(Duration(seconds=2.0))
            except Exception:
                pass
        print(f'done {clouds}', flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
