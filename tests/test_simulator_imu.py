"""The simulator's IMU: error models, profiles, rates, stamps and recording order (issue 34), measured on the
simulated samples against the ground truth; and the default recordings unchanged, byte for byte."""
from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lego_loam_py.bag.io import BagReader
from lego_loam_py.core.pointcloud import VELODYNE_POINT_DTYPE
from lego_loam_py.sim import output as sidecars
from lego_loam_py.sim.lidar import LidarModel, simulate_sweep
from lego_loam_py.sim.scenarios import build_world, scenario_rng
from lego_loam_py.sim.simulator import SimConfig, simulate

# ------------------------------------------------------------------------------- default bytes unchanged

# Recordings with the default IMU options, as the simulator wrote them before the IMU error models existed
# (commit b004333): the simulator is deterministic, so these digests of every message (topic, bag time, raw
# bytes) and every sidecar file change only when the data do.
DIGEST_CONFIGS = {
    'aggressive_default': dict(scenario='aggressive', duration=0.5),
    'forest_mounted_400hz': dict(scenario='forest', duration=0.3, imu_rate=400.0, imu_time_offset=0.02,
                                 imu_extrinsic_rpy=(0.0, 0.0, 90.0), imu_lever_arm=(0.1, 0.0, -0.1),
                                 imu_orientation_rpy=(180.0, 0.0, 0.0)),
    'corridor_ideal_100hz_ros1': dict(scenario='corridor', duration=0.3, imu_rate=100.0, ideal=True, ros1=True,
                                      layout='packed'),
}
DIGESTS = {   # name -> (cache key, digest)
    'aggressive_default': ('a6059bfaeaa6', 'ed431091e6cf458d'),
    'forest_mounted_400hz': ('ff16c75b6ce8', '44fbe6fcc55bf3f4'),
    'corridor_ideal_100hz_ros1': ('43c584011b29', 'ac8ec70547053b60'),
}
# The digests hold on a machine whose libraries round like the one they were recorded on (ray casting in
# Embree's SIMD paths, numpy's transcendental functions): this fingerprint of those libraries' results, taken
# without the simulator's driver, says whether this machine does.
PLATFORM_FINGERPRINT = '42e1f6c6bf4cbaa8'


def platform_fingerprint() -> str:
    """Digest of what the libraries compute for a recording, independently of the IMU model and the driver:
    trajectory samples, their rotations as quaternions, and the first sweep of the aggressive drive."""
    world = build_world('aggressive', 0)
    t = np.arange(101) / 200.0
    rotation, position = world.trajectory.pose(t)
    digest = hashlib.sha256()
    for array in (rotation, position, world.trajectory.angular_velocity(t), world.trajectory.acceleration(t),
                  Rotation.from_matrix(rotation).as_quat(), np.einsum('nji,nj->ni', rotation, position)):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    sweep = simulate_sweep(LidarModel.from_preset('VLP-16'), world.scene, world.trajectory, 0.0,
                           scenario_rng(0, 'lidar', 0), VELODYNE_POINT_DTYPE)
    digest.update(sweep.points.tobytes())
    return digest.hexdigest()[:16]


def recording_digest(bag: Path) -> str:
    """sha256 over every message (topic, bag time, raw bytes) in recording order and every sidecar file (the
    package version in scenario.yaml and README.md left out)."""
    digest = hashlib.sha256()
    with BagReader(bag) as reader:
        for message in reader.messages():
            digest.update(f'{message.topic} {message.timestamp} {len(bytes(message.data))}\n'.encode())
            digest.update(bytes(message.data))
    for name in (sidecars.GROUND_TRUTH, sidecars.GROUND_TRUTH_DENSE, sidecars.LABELS, sidecars.SCENARIO,
                 sidecars.NOTE):
        data = sidecars.sidecar_path(bag, name).read_bytes()
        if name in (sidecars.SCENARIO, sidecars.NOTE):
            data = re.sub(rb'lego_loam_py [0-9][^ ,)]*', b'lego_loam_py VERSION', data)
        digest.update(name.encode() + b'\n' + data)
    return digest.hexdigest()[:16]


def simulate_for_digest(name: str, folder: Path) -> tuple[str, str]:
    config = SimConfig(**DIGEST_CONFIGS[name])
    result = simulate(config, folder / name)
    return config.validate().cache_key(), recording_digest(result.bag_path)


@pytest.mark.parametrize('name', list(DIGEST_CONFIGS))
def test_default_imu_options_keep_the_recordings_byte_for_byte(name, tmp_path):
    cache_key, digest = simulate_for_digest(name, tmp_path)
    assert cache_key == DIGESTS[name][0], 'the default options changed the cache key'
    fingerprint = platform_fingerprint()
    if fingerprint != PLATFORM_FINGERPRINT:
        pytest.skip(f'libraries round differently here ({fingerprint}, digests recorded with {PLATFORM_FINGERPRINT}): '
                    'tests/test_simulator.py compares the committed recordings within their tolerances instead')
    assert digest == DIGESTS[name][1], 'the default options changed the recorded bytes'


if __name__ == '__main__':   # prints the digests to record (run at the commit whose bytes are the reference)
    import tempfile
    with tempfile.TemporaryDirectory() as folder:
        print('PLATFORM_FINGERPRINT =', repr(platform_fingerprint()))
        for config_name in DIGEST_CONFIGS:
            print(f'    {config_name!r}: {simulate_for_digest(config_name, Path(folder))!r},')
