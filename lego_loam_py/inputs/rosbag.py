"""ROS 1 and ROS 2 bags as a source (:mod:`lego_loam_py.bag.io` reads them): PointCloud2 scans and Imu samples.

The cloud topic is the one asked for; when none was (None), ``/velodyne_points`` if the bag has it, otherwise the
bag's only PointCloud2 topic. The IMU topic likewise (None: ``/imu/data`` or else the only Imu topic; '' reads
none; a topic asked for and missing: none, as the nodes run without an IMU). Clouds are stamped with
their header stamp; the ground truth is the simulator's ``ground_truth.tum`` beside the bag, when there is one.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from lego_loam_py.bag.io import BagError, BagReader, cloud_msg_to_array, resolve_bag_path
from lego_loam_py.core.imu.buffer import imu_sample
from lego_loam_py.core.pointcloud import CloudLayoutError
from lego_loam_py.core.trajectory import Trajectory
from lego_loam_py.inputs.source import ImuSample, Scan, Source, SourceItem, UnreadableScan

__all__ = ['BagSource', 'CLOUD_TYPE', 'IMU_TYPE']

CLOUD_TYPE = 'sensor_msgs/msg/PointCloud2'
IMU_TYPE = 'sensor_msgs/msg/Imu'
DEFAULT_CLOUD_TOPIC, DEFAULT_IMU_TOPIC = '/velodyne_points', '/imu/data'  # (sensor.* parameters' defaults)


class BagSource(Source):
    """A bag; ``cloud_topic`` / ``imu_topic`` as configured (None: chosen as the module says)."""

    kind = 'rosbag'

    def __init__(self, path: str | Path, cloud_topic: str | None = None, imu_topic: str | None = None):
        self.path = resolve_bag_path(path)
        self.name = Path(path).resolve().name
        self._reader = BagReader(self.path)
        self._reader.open()
        try:
            self.cloud_topic, self.imu_topic, self.notes = self._choose_topics(cloud_topic, imu_topic)
        except BaseException:
            self._reader.close()
            raise

    def _choose_topics(self, cloud_topic: str | None, imu_topic: str | None) -> tuple[str, str | None, list[str]]:
        topics = self._reader.topics()
        listed = ', '.join(sorted(topics)) or 'none'
        notes = []
        if cloud_topic is None and DEFAULT_CLOUD_TOPIC not in topics:
            clouds = sorted(t for t, kind in topics.items() if kind == CLOUD_TYPE)
            if len(clouds) != 1:
                raise BagError(
                    f'{self.path}: no {DEFAULT_CLOUD_TOPIC} topic and {len(clouds)} PointCloud2 topics '
                    f'to choose from (topics: {listed}); name one with -p sensor.point_cloud_topic:=TOPIC'
                )
            notes.append(f'clouds from {clouds[0]}, the only PointCloud2 topic')
            cloud_topic = clouds[0]
        cloud_topic = cloud_topic or DEFAULT_CLOUD_TOPIC
        if cloud_topic not in topics:
            raise BagError(f'{self.path}: no {cloud_topic} topic (topics: {listed})')
        if imu_topic is None and DEFAULT_IMU_TOPIC not in topics:
            imus = sorted(t for t, kind in topics.items() if kind == IMU_TYPE)
            if len(imus) == 1:
                notes.append(f'IMU from {imus[0]}, the only Imu topic')
                imu_topic = imus[0]
        imu_topic = DEFAULT_IMU_TOPIC if imu_topic is None else imu_topic
        return cloud_topic, imu_topic if imu_topic in topics else None, notes

    @property
    def duration_s(self) -> float:
        return self._reader.duration

    def scan_count(self) -> int | None:
        return self._reader.topic_counts().get(self.cloud_topic, 0)

    def ground_truth(self) -> Trajectory | None:
        from lego_loam_py.inputs.sidecars import load_ground_truth

        return load_ground_truth(self.path)

    def describe(self) -> str:
        imu = f', IMU {self.imu_topic}' if self.imu_topic else ''
        kind = 'ROS 1 bag' if self._reader.is_ros1 else 'ROS 2 bag'
        return f'{kind} {self.path}: clouds {self.cloud_topic}{imu}'

    def items(self) -> Iterator[SourceItem]:
        wanted = [self.cloud_topic] + ([self.imu_topic] if self.imu_topic else [])
        reader = self._reader
        for message in reader.messages(topics=wanted):
            msg = reader.deserialize(message)
            if message.topic != self.cloud_topic:
                yield ImuSample(imu_sample(msg), message.timestamp)
                continue
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            try:
                points = cloud_msg_to_array(msg)
            except CloudLayoutError as exc:
                yield UnreadableScan(stamp, str(exc), message.timestamp)
            else:
                yield Scan(stamp, points, message.timestamp)

    def close(self) -> None:
        self._reader.close()
