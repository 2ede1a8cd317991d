"""The IMU mounted any way (issue 17): its conventions (core.frames.ImuMounting), and the IMU buffer applying
rotation, orientation frame, lever arm and time offset as samples enter it (core.imu.ImuBuffer)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lego_loam_py.core.frames import ImuMounting, matrix_to_rpy, rpy_to_matrix
from lego_loam_py.core.imu import ImuBuffer, imu_mounting
from lego_loam_py.core.params import ParameterError, Params

G = 9.81


# ------------------------------------------------------------------------------------------- conventions

def test_rpy_is_rz_ry_rx_about_fixed_axes():
    # Yaw 90 deg to the left: the IMU's x axis lies along the lidar's y axis, its y along the lidar's -x.
    yawed = rpy_to_matrix((0.0, 0.0, 90.0))
    assert yawed @ [1, 0, 0] == pytest.approx([0, 1, 0], abs=1e-15)
    assert yawed @ [0, 1, 0] == pytest.approx([-1, 0, 0], abs=1e-15)
    # Upside down about x: y and z flip.
    assert rpy_to_matrix((180.0, 0.0, 0.0)) == pytest.approx(np.diag([1.0, -1.0, -1.0]), abs=1e-15)
    # The composition order: roll about x first, then pitch about y, then yaw about z (all fixed axes).
    rpy = (10.0, -20.0, 30.0)
    expected = (Rotation.from_euler('z', 30, degrees=True) * Rotation.from_euler('y', -20, degrees=True)
                * Rotation.from_euler('x', 10, degrees=True)).as_matrix()
    assert rpy_to_matrix(rpy) == pytest.approx(expected, abs=1e-15)
    assert matrix_to_rpy(rpy_to_matrix(rpy)) == pytest.approx(rpy, abs=1e-12)


def test_mounting_from_parameters():
    params = Params().replace(imu__rotation_rpy=[0, 0, 90], imu__translation=[0.2, 0.1, -0.2],
                              imu__orientation_rpy=[180, 0, 0], imu__time_offset=0.02)
    mounting = imu_mounting(params)
    assert mounting.rotation == pytest.approx(rpy_to_matrix((0, 0, 90)), abs=1e-15)
    assert mounting.rotation_lidar_orientation == pytest.approx(
        rpy_to_matrix((0, 0, 90)) @ rpy_to_matrix((180, 0, 0)), abs=1e-15)
    assert list(mounting.lever_arm) == [0.2, 0.1, -0.2] and mounting.time_offset == 0.02
    assert not mounting.is_identity and imu_mounting(Params()).is_identity
    assert 'rotation_rpy [0, 0, 90] deg' in mounting.describe()
    # Identity angles give exact identity matrices: the buffer then takes the original's path.
    assert np.array_equal(ImuMounting.from_rpy().rotation, np.eye(3))
    assert ImuBuffer(mounting=imu_mounting(Params())).mounting is None


@pytest.mark.parametrize('key, value, fragment', [
    ('imu.rotation_rpy', [0, 90], 'must have 3 values'),
    ('imu.translation', [0, 0, 20], 'within 10 m'),
    ('imu.time_offset', 2.0, 'within 1 s'),
    ('imu.orientation_rpy', 'up', 'list of numbers'),
])
def test_bad_mounting_parameters_name_the_key(key, value, fragment):
    with pytest.raises(ParameterError, match=fragment) as error:
        Params().replace(**{key.replace('.', '__'): value})
    assert key in str(error.value)


# ------------------------------------------------------------------------------------------- the buffer

def lidar_attitude(buffer: ImuBuffer, t: float) -> np.ndarray:
    """The buffer's attitude of the lidar at ``t`` as a REP-103 rotation (roll, pitch, yaw about x, y, z)."""
    roll, pitch, yaw = (float(a[0]) for a in buffer.attitude([t]))
    return Rotation.from_euler('xyz', [roll, pitch, yaw]).as_matrix()


@pytest.mark.parametrize('rpy', [(0.0, 0.0, 90.0), (180.0, 0.0, 0.0), (25.0, -40.0, 130.0)])
def test_a_rotated_imu_reads_as_an_aligned_one(rpy):
    """A lidar turning at 0.5 rad/s about its z axis, tilted 10 deg in pitch, accelerating 1 m/s^2 forward,
    measured by an IMU mounted with ``rpy``: the buffer's lidar attitude, integrated rates and velocity are those
    of an aligned IMU."""
    r_li = rpy_to_matrix(rpy)
    mounted = ImuBuffer(mounting=ImuMounting.from_rpy(rpy))
    aligned = ImuBuffer()
    rate_lidar = np.array([0.0, 0.0, 0.5])
    for k in range(21):
        t = 0.005 * k
        world_lidar = Rotation.from_euler('xyz', [0.0, math.radians(10.0), 0.5 * t])
        specific_force = np.array([1.0, 0.0, 0.0]) + world_lidar.inv().apply([0.0, 0.0, G])
        assert aligned.add(t, world_lidar.as_quat(), rate_lidar, specific_force) is None
        world_imu = world_lidar * Rotation.from_matrix(r_li)
        assert mounted.add(t, world_imu.as_quat(), r_li.T @ rate_lidar, r_li.T @ specific_force) is None
    for t in (0.0, 0.0525, 0.1):
        assert lidar_attitude(mounted, t) == pytest.approx(lidar_attitude(aligned, t), abs=1e-12)
    a, b = aligned.interpolate([0.1]), mounted.interpolate([0.1])
    assert b.angle == pytest.approx(a.angle, abs=1e-12)            # the gyro, integrated in lidar axes
    assert b.velocity == pytest.approx(a.velocity, abs=1e-12)
    assert np.linalg.norm(a.velocity[0]) == pytest.approx(0.1, abs=1e-3)   # 1 m/s^2 forward for 0.1 s


def test_an_orientation_of_another_frame_is_turned_into_the_lidars():
    """A unit reporting rates in lidar axes but the attitude of a frame yawed 90 deg and upside down (as NED-style
    outputs are): with ``orientation_rpy`` set, the lidar's attitude comes out."""
    orientation_rpy = (180.0, 0.0, 90.0)
    buffer = ImuBuffer(mounting=ImuMounting.from_rpy(orientation_rpy=orientation_rpy))
    world_lidar = Rotation.from_euler('xyz', [5.0, -3.0, 40.0], degrees=True)
    reported = world_lidar * Rotation.from_matrix(rpy_to_matrix(orientation_rpy))
    buffer.add(1.0, reported.as_quat(), (0.0, 0.0, 0.0), world_lidar.inv().apply([0.0, 0.0, G]))
    assert lidar_attitude(buffer, 1.0) == pytest.approx(world_lidar.as_matrix(), abs=1e-12)
    assert buffer.interpolate([1.0]).velocity[0] == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)


def test_the_time_offset_moves_samples_to_the_lidars_clock():
    """An IMU clock 20 ms ahead: a sample stamped 10.02 s was measured at lidar time 10.00 s."""
    buffer = ImuBuffer(mounting=ImuMounting.from_rpy(time_offset=0.02))
    for k in range(5):
        buffer.add(10.02 + 0.005 * k, Rotation.from_euler('z', 0.1 * k).as_quat(), (0, 0, 0), (0, 0, G))
    assert buffer.times[0] == pytest.approx(10.0, abs=1e-12) and buffer.times[-1] == pytest.approx(10.02, abs=1e-12)
    assert float(buffer.attitude([10.01])[2][0]) == pytest.approx(0.2, abs=1e-12)   # the yaw of the sample at 10.03


@pytest.mark.parametrize('angular_acceleration', [0.0, 4.0])
def test_the_lever_arm_is_taken_off_the_accelerometer(angular_acceleration):
    """A lidar spinning on the spot about its z axis (2 rad/s, plus a spin-up of ``angular_acceleration``
    [rad/s^2]) with the IMU 0.5 m ahead of it: the IMU feels ``omega x (omega x r)`` (-omega^2 r, towards the
    axis) and ``alpha x r`` (sideways), the lidar origin nothing. The buffer integrates no velocity for it; the
    same samples read as if at the lidar origin integrate metres per second."""
    lever_arm = np.array([0.5, 0.0, 0.0])
    compensated = ImuBuffer(mounting=ImuMounting.from_rpy(lever_arm=lever_arm))
    uncompensated = ImuBuffer()
    for k in range(21):
        t = 0.005 * k
        rate = 2.0 + angular_acceleration * t
        yaw = 2.0 * t + 0.5 * angular_acceleration * t * t
        omega = np.array([0.0, 0.0, rate])
        alpha = np.array([0.0, 0.0, angular_acceleration])
        force = np.cross(alpha, lever_arm) + np.cross(omega, np.cross(omega, lever_arm)) + [0.0, 0.0, G]
        sample = (t, Rotation.from_euler('z', yaw).as_quat(), omega, force)
        compensated.add(*sample)
        uncompensated.add(*sample)
    assert np.abs(compensated.interpolate([0.1]).velocity).max() < 1e-9
    assert np.abs(uncompensated.interpolate([0.1]).velocity).max() > 0.1   # 2 m/s^2 towards the axis
