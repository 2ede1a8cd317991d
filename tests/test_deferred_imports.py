"""What a node imports after it is ready (LegoLoamNode.import_deferred): its core's DEFERRED_IMPORTS once, and the
IMU_IMPORTS only when IMU samples arrive, so that a node without an IMU never pays for them."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import json, sys
    import rclpy
    from sensor_msgs.msg import Imu

    from lego_loam_py.ros.feature_association_node import FeatureAssociationNode

    rclpy.init()
    node = FeatureAssociationNode()
    asked, threads = [], []
    ask = node.import_deferred

    def recorded(attribute='DEFERRED_IMPORTS'):
        asked.append(attribute)
        thread = ask(attribute)
        threads.append(thread)
        return thread

    node.import_deferred = recorded
    node.import_deferred()  # as run_node does once the node is ready
    ready = 'scipy.spatial' in sys.modules
    sample = Imu()
    sample.header.stamp.sec = 100
    sample.orientation.w = 1.0
    sample.linear_acceleration.z = 9.81
    for n in range(3):
        sample.header.stamp.nanosec = n * 5_000_000
        node.on_imu(sample)
    for thread in threads:
        if thread is not None:
            thread.join(60)
    print(json.dumps({'asked': asked, 'threads': [t is not None for t in threads], 'ready': ready,
                      'after_imu': 'scipy.spatial' in sys.modules, 'dropped': node.counters.get('imu_dropped', 0)}))
    node.destroy_node()
    rclpy.shutdown()
    """
)


def test_feature_association_imports_the_imu_checks_library_with_the_first_imu_sample_only(ros_domain):
    done = subprocess.run([sys.executable, '-c', SCRIPT], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    assert seen['dropped'] == 0  # (the samples were taken)
    assert not seen['ready']  # nothing of scipy.spatial for the scans
    assert seen['asked'] == ['DEFERRED_IMPORTS', 'IMU_IMPORTS']  # once, with the first sample
    assert seen['threads'] == [False, True] and seen['after_imu']
