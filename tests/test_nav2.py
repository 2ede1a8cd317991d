"""What a robot's navigation stack takes, over DDS, as a user starts it: ``lego_loam_py launch --bag BAG
--record-all -p frames.rep105:=true``, the recording read back.

/tf holds the REP-105 chain map -> odom -> base_link (and base_link -> the lidar on /tf_static) beside the original's
frames; /map (nav_msgs/OccupancyGrid, latched) is published in the map frame; every message on the three odometry
topics carries a finite, symmetric, positive-definite pose covariance; the REP-105 odometry and pose topics go out.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
BAG = REPO / 'bags' / 'campus_8s'
ODOMETRY_TOPICS = ('/laser_odom_to_init', '/aft_mapped_to_init', '/integrated_to_init')


def _logs(directory: Path) -> str:
    return '\n'.join(f'--- {p.name}\n{p.read_text()[-3000:]}' for p in sorted(directory.glob('*.log')))


def test_launch_with_rep105_records_the_frames_the_grid_and_honest_covariance(tmp_path, ros_domain):
    from rclpy.serialization import deserialize_message

    from lego_loam_py.bag.io import BagReader
    from lego_loam_py.testing.bags import cut_bag
    from tests.support.topics import message_class

    bag = tmp_path / 'campus_4s'
    cut_bag(BAG, bag, start_s=4.0, duration_s=1e6)  # the first 4 s
    recording, logs = tmp_path / 'recording', tmp_path / 'logs'
    result = subprocess.run(
        [
            BIN / 'lego_loam_py',
            'launch',
            '--bag',
            bag,
            '--rate',
            '0.5',
            '--record-all',
            '-o',
            recording,
            '--log-dir',
            logs,
            '--quiet-nodes',
            '-p',
            'frames.rep105:=true',
            '-p',
            f'map_optimization.file_directory:={tmp_path / "maps"}',
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr + _logs(logs)

    messages: dict[str, list] = {}
    with BagReader(recording) as reader:
        types = reader.topics()
        for message in reader.messages():
            messages.setdefault(message.topic, []).append(
                deserialize_message(message.data, message_class(types[message.topic]))
            )

    tf_edges = {(t.header.frame_id, t.child_frame_id) for m in messages['/tf'] for t in m.transforms}
    static_edges = {(t.header.frame_id, t.child_frame_id) for m in messages['/tf_static'] for t in m.transforms}
    assert {('map', 'odom'), ('odom', 'base_link'), ('camera_init', 'camera')} <= tf_edges, tf_edges
    assert ('base_link', 'velodyne') in static_edges and ('map', 'camera_init') in static_edges
    assert ('camera', 'base_link') not in static_edges  # base_link's one parent is odom

    grids = messages['/map']
    assert grids and grids[-1].header.frame_id == 'map'
    cells = np.asarray(grids[-1].data)
    assert cells.size == grids[-1].info.width * grids[-1].info.height and (cells == 100).any() and (cells == 0).any()

    for topic in ODOMETRY_TOPICS:
        assert len(messages[topic]) >= 5, topic  # (mapping: every 0.3 s of data)
        for msg in messages[topic]:
            covariance = np.asarray(msg.pose.covariance).reshape(6, 6)
            assert np.isfinite(covariance).all(), topic
            assert np.array_equal(covariance, covariance.T), topic
            assert np.linalg.eigvalsh(covariance).min() > 0.0, topic
    odometry = messages['/lego_loam/odometry']
    assert odometry[-1].header.frame_id == 'odom' and odometry[-1].child_frame_id == 'base_link'
    assert messages['/lego_loam/pose'][-1].header.frame_id == 'map'
