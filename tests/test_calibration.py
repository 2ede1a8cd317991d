"""``lego_loam_py calibrate``: the IMU-to-lidar rotation and time offset from a recording, with uncertainty; its
refusals (issue 17). Synthetic motion whose answer is known (tests.test_imu_alignment's), and the command on
real and simulated recordings."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from lego_loam_py.calibration import CalibrationRefused, calibrate
from lego_loam_py.core.frames import rpy_to_matrix
from tests.test_imu_alignment import imu_and_lidar


def test_calibration_recovers_rotation_and_offset_with_honest_uncertainty():
    stamps, lidar, imu = imu_and_lidar(40.0, mount_rpy=(25.0, -40.0, 130.0), offset=0.02, lidar_noise_deg=0.05)
    result = calibrate(stamps, lidar, imu)
    assert result.refused is None
    error = math.degrees(Rotation.from_matrix(result.rotation.T @ rpy_to_matrix((25.0, -40.0, 130.0))).magnitude())
    assert error < 0.3 and abs(result.time_offset - 0.02) < 0.002
    assert (result.rotation_sigma_deg < 0.3).all() and result.time_offset_sigma < 0.002
    # The orientation field is the gyro's own frame here.
    assert math.degrees(Rotation.from_matrix(result.orientation_rotation).magnitude()) < 0.1
    imu = yaml.safe_load(result.parameter_block())['/**']['ros__parameters']['imu']
    assert imu['rotation_rpy'] == pytest.approx([25.0, -40.0, 130.0], abs=0.3)
    assert imu['time_offset'] == pytest.approx(0.02, abs=0.002) and set(imu) == {'rotation_rpy', 'time_offset'}


def test_calibration_refuses_a_drive_without_turns_and_a_short_one():
    stamps, lidar, imu = imu_and_lidar(40.0, mount_rpy=(0.0, 0.0, 90.0), tilt=0.0, lidar_noise_deg=0.05)
    straight = imu | dict(rates=imu['rates'] * [1.0, 1.0, 0.02])  # hardly any yaw either
    straight_lidar = np.array([rpy_to_matrix((0.0, 0.0, 0.0))] * len(stamps))
    result = calibrate(stamps, straight_lidar, straight)
    assert result.refused is not None and 'does not show' in result.refused
    result = calibrate(stamps, lidar, imu)  # yaw only: the rotation about z is what cannot be told
    assert result.refused is not None and "about the lidar's z axis" in result.refused
    with pytest.raises(CalibrationRefused, match='too short'):
        calibrate(stamps[:30], lidar[:30], imu)


def test_the_command_refuses_the_real_ouster_capture_as_too_short(shared_data, tmp_path):
    """The Ouster OS1-128 capture here is three scans (0.2 s) with the sensor's own IMU packets: converted, it is a
    bag calibrate can read, and it says why it cannot calibrate from it (exit code 1, no traceback)."""
    import subprocess
    import sys
    from pathlib import Path

    cli = Path(sys.executable).parent / 'lego_loam_py'
    folder = shared_data / 'real' / 'ouster_os128_pcaps_with_imu'
    bag = tmp_path / 'os1'
    done = subprocess.run(
        [
            str(cli),
            'convert',
            str(folder / 'OS-1-128_v2.3.0_1024x10_lb_n3.pcap'),
            '--metadata',
            str(folder / 'OS-1-128_v2.3.0_1024x10.json'),
            '-o',
            str(bag),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    done = subprocess.run(
        [
            str(cli),
            'calibrate',
            str(bag),
            '--no-progress',
            '-p',
            'sensor.n_scan:=128',
            '-p',
            'sensor.horizon_scan:=1024',
            '-p',
            'sensor.ground_scan_ind:=40',
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 1 and 'Traceback' not in done.stderr
    assert 'too short: 3 scans' in done.stderr and 's of IMU (30 samples)' in done.stderr


def synthetic_bag(tmp_path, stamps, lidar, imu, base: float = 1000.0):
    """``imu`` written as sensor_msgs/Imu on /imu/data and the lidar attitudes as a TUM file (the command's
    --trajectory): the command end to end without running the pipeline."""
    from lego_loam_py.bag.io import BagWriter

    bag = tmp_path / 'bag'
    with BagWriter(bag) as writer:
        T = writer.types
        unknown = np.zeros(9)
        for stamp, rate, q in zip(imu['stamps'] + base, imu['rates'], imu['orientations']):
            stamp_ns = int(round(stamp * 1e9))
            writer.write_msg(
                '/imu/data',
                stamp_ns,
                T['sensor_msgs/msg/Imu'](
                    header=writer.header(stamp_ns, 'imu_link'),
                    orientation=T['geometry_msgs/msg/Quaternion'](
                        x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
                    ),
                    orientation_covariance=unknown,
                    angular_velocity=T['geometry_msgs/msg/Vector3'](
                        x=float(rate[0]), y=float(rate[1]), z=float(rate[2])
                    ),
                    angular_velocity_covariance=unknown,
                    linear_acceleration=T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=9.81),
                    linear_acceleration_covariance=unknown,
                ),
            )
    tum = tmp_path / 'lidar.tum'
    quaternions = Rotation.from_matrix(lidar).as_quat()
    np.savetxt(tum, np.column_stack([stamps + base, np.zeros((len(stamps), 3)), quaternions]), fmt='%.9f')
    return bag, tum


def test_the_command_prints_a_parameter_block_or_refuses_a_straight_drive_with_exit_code_1(tmp_path, capsys):
    """The IMU yawed 90 deg and 20 ms late: the output is a parameter block to paste (its comments say how well
    each value is known). A straight drive (hardly any turn about any axis): exit code 1 and the reason."""
    from lego_loam_py.cli import main

    stamps, lidar, imu = imu_and_lidar(30.0, mount_rpy=(0.0, 0.0, 90.0), offset=0.02, lidar_noise_deg=0.05)
    (tmp_path / 'turns').mkdir()
    bag, tum = synthetic_bag(tmp_path / 'turns', stamps, lidar, imu)
    assert main(['calibrate', str(bag), '--trajectory', str(tum), '--no-progress']) == 0
    printed = yaml.safe_load(capsys.readouterr().out)['/**']['ros__parameters']['imu']
    assert printed['rotation_rpy'] == pytest.approx([0.0, 0.0, 90.0], abs=0.5)  # within 0.5 deg, 2 ms here
    assert printed['time_offset'] == pytest.approx(0.02, abs=0.002)

    straight = imu | dict(rates=imu['rates'] * [0.02, 0.02, 0.02])
    still = np.array([np.eye(3)] * len(stamps))
    (tmp_path / 'straight').mkdir()
    bag, tum = synthetic_bag(tmp_path / 'straight', stamps, still, straight)
    assert main(['calibrate', str(bag), '--trajectory', str(tum), '--no-progress']) == 1
    err = capsys.readouterr().err
    assert 'error: ' in err and 'does not show' in err and 'Traceback' not in err
