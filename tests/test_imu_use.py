"""A real IMU only helps: featureAssociation turns with the gyro (integrated from the orientation, its bias found from
how well its turns agreed with the mapped poses), not with a 9-axis unit's noisy orientation field, and holds the
gyro's rotation with the prior's full weight only while it agrees with the mapping."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from lego_loam_py.core.frames import CAMERA_TO_LIDAR
from lego_loam_py.core.imu.agreement import FULL_TRUST, MIN_SPAN, ImuAgreement
from lego_loam_py.core.imu.buffer import ImuBuffer
from lego_loam_py.core.imu.gyro import GyroAttitude, matrix_of_rpy, rpy_of
from lego_loam_py.core.params import Params
from lego_loam_py.core.pipeline import Pipeline
from lego_loam_py.inputs import ImuSample, Scan, open_source
from lego_loam_py.sim.simulator import cached_scenario


def test_the_gyro_attitude_integrates_the_rate_from_the_orientation_and_takes_its_bias_off():
    gyro = GyroAttitude()
    start = (0.02, -0.01, 0.3)
    rate = np.array([0.1, 0.0, 0.5])  # [rad/s] body axes, constant
    assert gyro.update(None, tuple(rate), start) == pytest.approx(start)
    for _ in range(100):  # 1 s at 100 Hz; the orientation field's values are ignored meanwhile
        roll, pitch, yaw = gyro.update(0.01, tuple(rate), (9.0, 9.0, 9.0))
    expected = matrix_of_rpy(*start) @ Rotation.from_rotvec(rate).as_matrix()
    np.testing.assert_allclose(matrix_of_rpy(roll, pitch, yaw), expected, atol=1e-9)
    np.testing.assert_allclose(rpy_of(expected), (roll, pitch, yaw), atol=1e-12)
    # A bias set is taken off: a gyro reading rate + bias turns by the rate.
    biased = GyroAttitude()
    biased.bias = np.array([0.003, -0.002, 0.001])
    biased.update(None, tuple(rate + biased.bias), start)
    for _ in range(100):
        attitude = biased.update(0.01, tuple(rate + biased.bias), (0.0, 0.0, 0.0))
    np.testing.assert_allclose(matrix_of_rpy(*attitude), expected, atol=1e-9)
    # After a gap it starts again from the orientation field.
    assert biased.update(None, (0.0, 0.0, 0.0), (0.1, 0.2, 0.3)) == pytest.approx((0.1, 0.2, 0.3))


def test_the_buffer_keeps_the_gyro_attitude_where_the_orientation_field_is_noisy():
    """A sensor turning at 0.3 rad/s about z, the orientation field with 0.05 deg of white noise: the gyro buffer's
    yaw over a sweep is the true turn to 1e-6 rad, the orientation buffer's only to the noise."""
    rng = np.random.default_rng(4)
    orientation, gyro = ImuBuffer(), ImuBuffer(gyro_attitude=True)
    for k in range(200):
        t = k * 0.005
        noisy = Rotation.from_rotvec([0.0, 0.0, 0.3 * t]) * Rotation.from_rotvec(rng.normal(0.0, math.radians(0.05), 3))
        for buffer in (orientation, gyro):
            assert buffer.add(t, tuple(noisy.as_quat()), (0.0, 0.0, 0.3), (0.0, 0.0, 9.81)) is None
    times = np.array([0.5, 0.6])

    def turn(buffer):
        return float(np.diff(buffer.attitude(times)[2])[0])

    assert turn(gyro) == pytest.approx(0.03, abs=1e-6)
    assert abs(turn(orientation) - 0.03) > 1e-5


def _interval_rotation(rotvec) -> np.ndarray:
    return Rotation.from_rotvec(rotvec).as_matrix()


def test_the_agreement_finds_the_bias_and_keeps_the_whole_prior_for_a_sound_gyro():
    """Mapped poses every 0.3 s turning at random, the gyro's attitude off by a constant bias (camera axes), less the
    bias found so far, and a little noise: the bias comes back once MIN_SPAN s of intervals agree, and the prior keeps
    its weight."""
    rng = np.random.default_rng(5)
    bias = np.array([0.0015, -0.002, 0.0025])  # [rad/s]
    agreement = ImuAgreement(0.1)
    lidar, imu = np.eye(3), np.eye(3)
    for k in range(100):
        stamp, time = 10**9 * (k + 1), 0.3 * (k + 1)
        turn = _interval_rotation(rng.normal(0.0, 0.05, 3))
        lidar = lidar @ turn
        # (the gyro's attitude has the bias found so far taken off, as featureAssociation's buffer does)
        imu = imu @ turn @ _interval_rotation((bias - agreement.bias) * 0.3 + rng.normal(0.0, 1e-5, 3))
        agreement.keep(stamp, time, imu)
        agreement.mapped(stamp, lidar)
        if (k + 1) * 0.3 < MIN_SPAN:
            assert agreement.sigma is None and np.all(agreement.bias == 0.0)
    np.testing.assert_allclose(agreement.bias, bias, atol=1e-4)
    assert agreement.sigma < FULL_TRUST and agreement.prior_weight(1e6) == 1e6


def test_an_imu_that_disagrees_more_than_any_mapping_loses_its_prior():
    rng = np.random.default_rng(6)
    agreement = ImuAgreement(0.1)
    lidar = imu = np.eye(3)
    for k in range(100):
        turn = _interval_rotation(rng.normal(0.0, 0.05, 3))
        lidar = lidar @ turn
        imu = imu @ turn @ _interval_rotation(rng.normal(0.0, math.radians(1.0), 3))  # ~1.7 deg a sweep
        agreement.keep(k, 0.3 * k, imu)
        agreement.mapped(k, lidar)
    assert agreement.sigma > 4 * FULL_TRUST
    assert agreement.prior_weight(1e6) == pytest.approx(1e6 * (FULL_TRUST / agreement.sigma) ** 2)
    assert agreement.prior_weight(1e6) < 0.07e6


def test_a_consumer_modules_gyro_bias_is_found_on_a_drive():
    """The simulated aggressive drive with a consumer 9-axis module (gyro biases of 1-3 mrad/s): the bias
    featureAssociation finds from the mapped poses is the drawn one within 0.8 mrad/s on every axis, and the IMU is
    used on the scans past its probation. (What is left comes from the module's 1 % scale error on the drive's
    90 deg/s hairpins and its bias wander.)"""
    bag = cached_scenario('aggressive', duration=20.0, imu_profile='consumer')
    drawn = yaml.safe_load((bag / 'scenario.yaml').read_text())['imu']['biases']['gyro']  # IMU = lidar axes here
    pipeline = Pipeline(Params(), mapping=True)
    with open_source(bag) as source:
        for item in source.items():
            if isinstance(item, ImuSample):
                pipeline.add_imu(item.sample)
            elif isinstance(item, Scan):
                pipeline.process_scan(item.points, item.stamp_ns)
    result = pipeline.finish()
    found = CAMERA_TO_LIDAR @ pipeline.fa.imu_agreement.bias
    np.testing.assert_allclose(found, drawn, atol=8e-4)
    assert np.linalg.norm(found - drawn) < 0.3 * np.linalg.norm(drawn) and np.linalg.norm(drawn) > 1.5e-3
    assert result.counts['scans_with_imu'] >= 0.9 * result.counts['scans_processed']
