"""The IMU against the lidar (issue 17): the hand-eye estimator (core.imu_alignment) and the online check that
stops using a misaligned IMU (core.imu_monitor), on synthetic motion whose answer is known."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lego_loam_py.core.frames import ImuMounting, rpy_to_matrix
from lego_loam_py.core.imu.alignment import (
    GyroTrack,
    best_rotation,
    fit_alignment,
    nearest_right_angle_rotation,
    shifted_increments,
)
from lego_loam_py.core.imu.buffer import ImuBuffer
from lego_loam_py.core.imu.monitor import (
    MAPPING_PROBATION_MAX,
    MIN_EXPLAINED_DEG,
    PROBATION_SWEEPS,
    PROBATION_TURN_DEG,
    SIGNIFICANCE,
    ImuAlignmentMonitor,
    MappingImuCheck,
    SweepImuCheck,
)
from lego_loam_py.core.params import Params

RATE = 200.0  # IMU samples per second


def wobbly_rates(t: np.ndarray, tilt: float = 1.0) -> np.ndarray:
    """(n, 3) body rates [rad/s] of a sensor that turns left and right (up to 60 deg/s about z, the rate changing
    every couple of seconds) and rocks about x and y (``tilt`` scales that)."""
    return np.column_stack(
        [tilt * 0.15 * np.sin(2.1 * t), tilt * 0.12 * np.cos(1.3 * t + 0.4), 1.0 * np.sin(0.7 * t) * np.cos(0.23 * t)]
    )


def imu_and_lidar(
    duration: float,
    mount_rpy=(0.0, 0.0, 0.0),
    offset: float = 0.0,
    tilt: float = 1.0,
    lidar_noise_deg: float = 0.0,
    seed: int = 0,
):
    """A synthetic recording: IMU samples (gyro in its own axes, stamped ``offset`` s late, an orientation of its
    own frame) and the lidar's attitude at 10 Hz sweep starts (with white noise of ``lidar_noise_deg`` per axis)."""
    times = np.arange(0.0, duration + 1e-9, 1.0 / RATE)
    lidar_track = GyroTrack(times, wobbly_rates(times, tilt))  # the lidar's own attitude, integrated finely
    mount = rpy_to_matrix(mount_rpy)
    gyro = wobbly_rates(times, tilt) @ mount  # R^T omega for each row
    attitude = lidar_track._slerp(times) * Rotation.from_matrix(mount)
    imu = dict(stamps=times + offset, rates=gyro, orientations=attitude.as_quat())
    stamps = np.arange(0.3, duration - 0.3, 0.1)
    rng = np.random.default_rng(seed)
    lidar = lidar_track._slerp(stamps) * Rotation.from_rotvec(
        np.radians(lidar_noise_deg) * rng.standard_normal((len(stamps), 3))
    )
    return stamps, lidar.as_matrix(), imu


# ------------------------------------------------------------------------------------------- the estimator


def test_best_rotation_recovers_a_rotation_and_never_reflects():
    rng = np.random.default_rng(1)
    vectors = rng.standard_normal((20, 3))
    rotation = Rotation.from_euler('xyz', [30, -50, 120], degrees=True).as_matrix()
    assert best_rotation(vectors @ rotation.T, vectors) == pytest.approx(rotation, abs=1e-12)
    mirrored = vectors * [1.0, 1.0, -1.0]  # the best orthogonal map is a reflection: a rotation comes back
    assert np.linalg.det(best_rotation(mirrored, vectors)) == pytest.approx(1.0, abs=1e-12)


def test_gyro_track_integrates_a_constant_turn_exactly():
    times = np.arange(0.0, 2.0, 0.005)
    track = GyroTrack(times, np.tile([0.0, 0.0, 0.5], (len(times), 1)))
    turns = track.increments(np.array([0.1, 1.0]), np.array([0.6, 1.9]), [0.0])[0]
    assert np.allclose(turns, [[0, 0, 0.25], [0, 0, 0.45]], rtol=0, atol=1e-12)


def test_first_order_shift_matches_the_exact_one_for_small_offsets():
    times = np.arange(0.0, 10.0, 1.0 / RATE)
    track = GyroTrack(times, wobbly_rates(times))
    start, end = np.arange(1.0, 8.0, 0.1), np.arange(1.1, 8.1, 0.1)
    exact = track.increments(start, end, [0.02])[0]
    first_order = shifted_increments(
        Rotation.from_rotvec(track.increments(start, end, [0.0])[0]).as_quat(),
        wobbly_rates(start),
        wobbly_rates(end),
        [0.02],
    )[0]
    # The neglected term is the angular acceleration times offset^2 / 2: below 1e-4 rad here.
    unshifted = track.increments(start, end, [0.0])[0]
    assert np.abs(first_order - exact).max() < 1e-4 and np.abs(exact - unshifted).max() > 5e-4


def test_shifted_increments_compose_as_scipys_rotations():
    rng = np.random.default_rng(4)
    increments = Rotation.from_rotvec(rng.normal(size=(30, 3)) * 0.05)
    rate_start, rate_end = rng.normal(size=(30, 3)), rng.normal(size=(30, 3))
    offsets = np.array([-0.04, 0.0, 0.012])
    shifted = shifted_increments(increments.as_quat(), rate_start, rate_end, offsets)
    for k, offset in enumerate(offsets):
        expected = (
            Rotation.from_rotvec(-offset * rate_start) * increments * Rotation.from_rotvec(offset * rate_end)
        ).as_rotvec()
        assert np.allclose(shifted[k], expected, rtol=0.0, atol=1e-15)


def test_fit_finds_the_mounting_and_the_clock_offset():
    """Noise-free: the IMU yawed 90 deg and upside down, 20 ms late; the fit returns exactly that."""
    stamps, lidar, imu = imu_and_lidar(30.0, mount_rpy=(180.0, 0.0, 90.0), offset=0.02)
    track = GyroTrack(imu['stamps'], imu['rates'])
    poses = Rotation.from_matrix(lidar)
    turns = (poses[:-1].inv() * poses[1:]).as_rotvec()
    fit = fit_alignment(turns, lambda offsets: track.increments(stamps[:-1], stamps[1:], offsets))
    error = Rotation.from_matrix(fit.rotation.T @ rpy_to_matrix((180.0, 0.0, 90.0))).magnitude()
    assert math.degrees(error) < 0.01 and fit.offset == pytest.approx(0.02, abs=2e-4)
    assert fit.explained > 0.999 and fit.rms_after_deg < 0.01


def test_the_rotation_about_an_axis_the_sensor_never_turns_about_stays_unknown():
    """Turning about z only (a car on a flat road), with 0.05 deg of lidar noise: the rotation about z is not
    determined; about x and y it is, by the big yaw turns."""
    stamps, lidar, imu = imu_and_lidar(30.0, tilt=0.0, lidar_noise_deg=0.05)
    track = GyroTrack(imu['stamps'], imu['rates'])
    poses = Rotation.from_matrix(lidar)
    fit = fit_alignment(
        (poses[:-1].inv() * poses[1:]).as_rotvec(), lambda offsets: track.increments(stamps[:-1], stamps[1:], offsets)
    )
    assert abs(fit.rotation_axes[-1][2]) > 0.99  # the weakest axis is z
    assert fit.rotation_sigma_deg[-1] > 20 * fit.rotation_sigma_deg[0]


# ------------------------------------------------------------------------------------------- the online check


def feed(
    monitor: ImuAlignmentMonitor,
    duration: float,
    mount_rpy=(0.0, 0.0, 0.0),
    offset: float = 0.0,
    start: float = 0.0,
    tilt: float = 1.0,
    interval: float = 0.4,
):
    """Intervals of a mapOptimization-like cadence to ``monitor``; returns the events."""
    times = np.arange(start, start + duration + 1.0, 1.0 / RATE)
    lidar_track = GyroTrack(times, wobbly_rates(times, tilt))
    mount = rpy_to_matrix(mount_rpy)
    imu_track = GyroTrack(times + offset, wobbly_rates(times, tilt) @ mount)
    events = []
    for a in np.arange(start + 0.5, start + duration, interval):
        b = a + interval
        lidar_turn = Rotation.from_rotvec(lidar_track.increments([a], [b], [0.0])[0, 0]).as_matrix()
        imu_turn = Rotation.from_rotvec(imu_track.increments([a], [b], [0.0])[0, 0]).as_matrix()
        rates = wobbly_rates(np.array([a - offset, b - offset]), tilt) @ mount
        event = monitor.add(a, b, lidar_turn, imu_turn, rates[0], rates[1])
        if event is not None:
            events.append(event)
    return events


def monitor(**overrides) -> ImuAlignmentMonitor:
    params = Params().replace(**overrides)
    imu = params.imu
    return ImuAlignmentMonitor(
        params, ImuMounting.from_rpy(imu.rotation_rpy, imu.translation, imu.orientation_rpy, imu.time_offset), 'test'
    )


def test_an_aligned_imu_is_never_doubted():
    check = monitor()
    assert feed(check, 60.0) == [] and check.trusted and check.evaluations > 50


def test_a_yawed_imu_is_found_within_one_window_and_named():
    check = monitor()
    events = feed(check, 30.0, mount_rpy=(0.0, 0.0, 90.0))
    # A full window (5 s, from 0.5 s) and three evaluations in a row (0.4 s apart) that agree on it.
    assert not check.trusted and events and events[0].stamp < 0.5 + 5.0 + 3 * 0.4 + 0.05
    assert 'imu.rotation_rpy [0.0, 0.0, 90.0]' in events[0].message and 'likely [0.0, 0.0, 90.0]' in events[0].message
    # The check sees the IMU as the buffer gives it, the configured mounting applied: an IMU at yaw 180 deg
    # configured at yaw 90 turns as if yawed 90 more, and the advice is the whole mounting.
    check = monitor(imu__rotation_rpy=[0.0, 0.0, 90.0])
    events = feed(check, 30.0, mount_rpy=(0.0, 0.0, 90.0))
    assert events and 'likely [0.0, 0.0, 180.0]), not [0.0, 0.0, 90.0]' in events[0].message


def test_a_correction_that_explains_less_than_the_floor_per_interval_condemns_no_imu():
    """A few degrees about an axis the sensor hardly turns about: material, significant and all of the
    disagreement, but 0.21 deg per interval, within what a window of noisy mapping steps lets a fit explain with a
    right IMU (0.39 deg with an aligned IMU in the simulated corridor): not a reason to drop the IMU. The same
    4 degrees about an axis it turns about (1.06 deg per interval) are."""
    check = monitor()
    assert feed(check, 30.0, mount_rpy=(0.0, 0.0, 4.0)) == [] and check.trusted
    fit = check.last_fit
    assert fit.angle_deg > 3.0 and fit.rotation_significance > SIGNIFICANCE and fit.explained > 0.99
    assert fit.explained_deg == pytest.approx(0.21, abs=0.01) and fit.explained_deg < MIN_EXPLAINED_DEG
    check = monitor()
    events = feed(check, 30.0, mount_rpy=(4.0, 0.0, 0.0), tilt=0.3)
    assert events and not check.trusted and check.last_fit.explained_deg > 2 * MIN_EXPLAINED_DEG


def test_a_late_clock_is_found_and_the_offset_named():
    check = monitor()
    events = feed(check, 30.0, offset=0.05)
    assert events and not check.trusted and 'stamps are 50 ms late (imu.time_offset 0.050 s' in events[0].message


def test_the_imu_is_used_again_once_it_agrees():
    """A distrusted IMU (here: the check was shown a wrong mounting at first) comes back after a window of
    agreement with turns about every axis."""
    check = monitor()
    events = feed(check, 10.0, mount_rpy=(0.0, 0.0, 90.0))
    assert not check.trusted
    events = feed(check, 20.0, start=20.0)
    assert check.trusted and events[-1].trusted and 'used again' in events[-1].message


def feed_quick(monitor: ImuAlignmentMonitor, duration: float, mount_rpy=(0.0, 0.0, 0.0)) -> list:
    """Sweeps (0.1 s) of featureAssociation's probation to ``monitor.add_quick``; returns the events."""
    times = np.arange(0.0, duration + 1.0, 1.0 / RATE)
    lidar_track = GyroTrack(times, wobbly_rates(times))
    mount = rpy_to_matrix(mount_rpy)
    imu_track = GyroTrack(times, wobbly_rates(times) @ mount)
    events = []
    for a in np.arange(0.5, duration, 0.1):
        b = a + 0.1
        lidar_turn = Rotation.from_rotvec(lidar_track.increments([a], [b], [0.0])[0, 0]).as_matrix()
        imu_turn = Rotation.from_rotvec(imu_track.increments([a], [b], [0.0])[0, 0]).as_matrix()
        rates = wobbly_rates(np.array([a, b])) @ mount
        event = monitor.add_quick(a, b, lidar_turn, imu_turn, rates[0], rates[1])
        events += [] if event is None else [event]
    return events


def test_the_probation_passes_an_imu_that_agrees_and_drops_one_that_does_not():
    """featureAssociation's probation: sweeps whose turns agree end it (the IMU is then used on every sweep); a
    grossly rotated IMU is distrusted."""
    check = monitor()
    assert feed_quick(check, 3.0) == [] and check.probation_passed and check.trusted
    check = monitor()
    events = feed_quick(check, 3.0, mount_rpy=(10.0, -20.0, 130.0))
    assert events and not check.trusted and not check.probation_passed
    assert 'over the last 2 s' in events[0].message


def test_only_fast_turning_sweeps_are_held_without_the_imu_on_probation():
    """featureAssociation registers a sweep without the IMU (and compares) only when the IMU turned
    PROBATION_TURN_DEG or more since the last sweep (the first sweep: over itself; not known: held too), for the
    first PROBATION_SWEEPS such sweeps, and not once the probation has passed."""
    last = SimpleNamespace(t_start=0.0, r_start=np.eye(3))

    def turned(deg: float) -> SimpleNamespace:  # (the IMU over a sweep, as featureAssociation has it)
        return SimpleNamespace(t_start=0.1, r_start=Rotation.from_rotvec([0.0, math.radians(deg), 0.0]).as_matrix())

    check = SweepImuCheck(Params(), ImuBuffer)  # (an empty buffer: the first sweep's turn is not known)
    assert check.on_probation(turned(0.0), None)
    assert not check.on_probation(turned(0.9 * PROBATION_TURN_DEG), last)
    assert all(check.on_probation(turned(2 * PROBATION_TURN_DEG), last) for _ in range(PROBATION_SWEEPS - 1))
    assert not check.on_probation(turned(2 * PROBATION_TURN_DEG), last)  # the probation is over
    check = SweepImuCheck(Params(), ImuBuffer)
    check.monitor.probation_passed = True
    assert not check.on_probation(turned(2 * PROBATION_TURN_DEG), last)
    check = SweepImuCheck(Params().replace(imu__alignment_check=False), ImuBuffer)
    assert not check.on_probation(turned(2 * PROBATION_TURN_DEG), last)


def test_the_mapping_blends_the_imu_only_once_a_window_check_passed_it():
    """mapOptimization's probation: no roll and pitch from the IMU until three windows found nothing against it,
    or MAPPING_PROBATION_MAX seconds when no window could judge; never from a distrusted IMU."""
    check = MappingImuCheck(Params(), lambda: None)
    assert not check.blending(100.0) and not check.blending(100.0 + MAPPING_PROBATION_MAX - 0.1)
    assert check.blending(100.0 + MAPPING_PROBATION_MAX)
    check = MappingImuCheck(Params(), lambda: None)
    assert not check.blending(0.0)
    feed(check.monitor, 10.0)  # an aligned IMU: a full window (from 0.5 s to 5.5 s) and three evaluations
    assert check.monitor.vetted and check.blending(6.8)
    check = MappingImuCheck(Params(), lambda: None)
    feed(check.monitor, 30.0, mount_rpy=(0.0, 0.0, 90.0))
    assert not check.monitor.vetted and not check.blending(30.0 + MAPPING_PROBATION_MAX)
    check = MappingImuCheck(Params().replace(imu__alignment_check=False), lambda: None)
    assert check.blending(0.0)  # the check off: blended from the start, as the original does


def test_an_upside_down_imu_is_caught_by_gravity_before_any_motion():
    check = monitor()
    up = np.array([0.0, 0.0, 1.0])
    assert check.check_gravity(0.0, up, rpy_to_matrix((5.0, -8.0, 0.0)) @ up) is None  # a slope
    event = check.check_gravity(0.0, up, rpy_to_matrix((180.0, 0.0, 0.0)) @ up)
    assert event is not None and not check.trusted and '180 deg from the ground' in event.message


def test_nearest_right_angle_rotation():
    assert nearest_right_angle_rotation(rpy_to_matrix((3.0, -2.0, 88.0))) == pytest.approx(
        rpy_to_matrix((0.0, 0.0, 90.0)), abs=1e-12
    )
    assert nearest_right_angle_rotation(rpy_to_matrix((10.0, -20.0, 130.0))) is None
