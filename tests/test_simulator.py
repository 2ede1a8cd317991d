"""The lidar + IMU simulator: sensor model, motion, IMU consistency, ground truth, labels, outputs, CLI, bags."""

from __future__ import annotations

import ast
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lego_loam_py.bag.io import BagReader, cloud_msg_to_array
from lego_loam_py.core.params import SENSOR_PRESETS
from lego_loam_py.core.pointcloud import VELODYNE_PACKED_DTYPE, VELODYNE_POINT_DTYPE
from lego_loam_py.formats import read_tum
from lego_loam_py.inputs import sidecars
from lego_loam_py.sim import output as sim_output
from lego_loam_py.sim.imu import GRAVITY, ImuModel, ImuNoise
from lego_loam_py.sim.lidar import VLP16_FIRING_ELEVATIONS, LidarModel, column_of_azimuth, simulate_sweep
from lego_loam_py.sim.scenarios import SCENARIOS, build_world
from lego_loam_py.sim.simulator import START_STAMP_NS, SimConfig, cached_scenario, simulate

REPO = Path(__file__).resolve().parents[1]
CLI = str(Path(sys.executable).parent / 'lego_loam_py')
BAGS = REPO / 'bags'
SCAN_NS = 100_000_000
SIGMA = 0.015  # VLP-16 range noise [m]


# ------------------------------------------------------------------------------------------------ helpers


def read_bag(path: Path) -> dict:
    """Clouds (stamp, points) and IMU arrays of a simulated bag."""
    clouds, imu = [], {'stamp': [], 'bag_time': [], 'gyro': [], 'accel': [], 'quat': [], 'frame': set(), 'cov': None}
    with BagReader(path) as reader:
        topics = reader.topics()
        for message in reader.messages():
            msg = reader.deserialize(message)
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            if message.topic == '/velodyne_points':
                clouds.append(
                    (stamp, cloud_msg_to_array(msg).copy(), msg.header.frame_id, bool(msg.is_dense), message.timestamp)
                )
            else:
                imu['stamp'].append(stamp)
                imu['bag_time'].append(message.timestamp)
                imu['gyro'].append([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
                imu['accel'].append([msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z])
                imu['quat'].append([msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w])
                imu['frame'].add(msg.header.frame_id)
                imu['cov'] = (
                    np.array(msg.orientation_covariance),
                    np.array(msg.angular_velocity_covariance),
                    np.array(msg.linear_acceleration_covariance),
                )
    for key in ('stamp', 'bag_time', 'gyro', 'accel', 'quat'):
        imu[key] = np.array(imu[key])
    return {'topics': topics, 'clouds': clouds, 'imu': imu}


def world_pose_of_first(path: Path) -> np.ndarray:
    first = sidecars.load_scenario(path)['ground_truth']['world_T_first']
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(first['quaternion_xyzw']).as_matrix()
    pose[:3, 3] = first['translation']
    return pose


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses at ``query`` [ns]: linear in position, slerp in rotation, between dense GT samples."""
    i = np.clip(np.searchsorted(stamps, query, side='right') - 1, 0, len(stamps) - 2)
    f = ((query - stamps[i]) / (stamps[i + 1] - stamps[i]).astype(float))[:, None]
    out = np.tile(np.eye(4), (len(query), 1, 1))
    out[:, :3, 3] = poses[i, :3, 3] + f * (poses[i + 1, :3, 3] - poses[i, :3, 3])
    step = Rotation.from_matrix(np.einsum('nji,njk->nik', poses[i, :3, :3], poses[i + 1, :3, :3])).as_rotvec()
    out[:, :3, :3] = np.einsum('nij,njk->nik', poses[i, :3, :3], Rotation.from_rotvec(step * f).as_matrix())
    return out


def points_in_world(path: Path, stamp: int, points: np.ndarray, own_time: bool = True) -> np.ndarray:
    """Cloud points in the simulator world using the dense ground truth beside the bag, each point with the
    pose at its own firing time (``own_time``) or all with the sweep-start pose."""
    stamps, poses = sidecars.load_ground_truth(path, dense=True)
    xyz = np.column_stack([points['x'], points['y'], points['z']]).astype(float)
    times = np.full(len(points), stamp, dtype=np.int64)
    if own_time:
        times += np.round(points['time'].astype(np.float64) * 1e9).astype(np.int64)
    pose = interpolate_poses(stamps, poses, times)
    local = np.einsum('nij,nj->ni', pose[:, :3, :3], xyz) + pose[:, :3, 3]
    first = world_pose_of_first(path)
    return local @ first[:3, :3].T + first[:3, 3]


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """1 s of every scenario (default sensors, noise on) and 2 s of aggressive and campus without noise."""
    root = tmp_path_factory.mktemp('sim')
    out = {}
    for name in SCENARIOS:
        out[name] = simulate(SimConfig(name, duration=1.0), root / name).bag_path
    for name in ('aggressive', 'campus'):
        out[f'{name}_ideal'] = simulate(SimConfig(name, duration=2.0, ideal=True), root / f'{name}_ideal').bag_path
    out['aggressive_3s'] = simulate(SimConfig('aggressive', duration=3.0), root / 'aggressive_3s').bag_path
    return out


@pytest.fixture(scope='module')
def contents(bags):
    cache = {}

    def get(name: str) -> dict:
        if name not in cache:
            cache[name] = read_bag(bags[name])
        return cache[name]

    return get


# ------------------------------------------------------------------------------------ outputs and parsing


@pytest.mark.parametrize('name', list(SCENARIOS))
def test_every_scenario_generates_a_bag_that_parses_with_ground_truth_and_labels(name, bags, contents):
    path = bags[name]
    data = contents(name)
    assert data['topics'] == {'/velodyne_points': 'sensor_msgs/msg/PointCloud2', '/imu/data': 'sensor_msgs/msg/Imu'}
    clouds = data['clouds']
    assert len(clouds) == 10 and len(data['imu']['stamp']) == 201
    assert [c[0] for c in clouds] == [START_STAMP_NS + k * SCAN_NS for k in range(10)]
    assert [c[4] for c in clouds] == [START_STAMP_NS + (k + 1) * SCAN_NS for k in range(10)]  # recorded at sweep end
    labels = sidecars.load_labels(path)
    gt_stamps, gt_poses = sidecars.load_ground_truth(path)
    assert np.array_equal(gt_stamps, [c[0] for c in clouds])
    assert np.allclose(gt_poses[0], np.eye(4), atol=1e-12)
    assert np.array_equal(labels.stamps, gt_stamps)
    for k, (_, points, frame_id, is_dense, _) in enumerate(clouds):
        assert points.dtype == VELODYNE_POINT_DTYPE and frame_id == 'velodyne' and is_dense
        assert len(points) > 15000, f'{name} scan {k}: only {len(points)} points'
        for field in ('x', 'y', 'z', 'intensity', 'time'):
            assert np.isfinite(points[field]).all()
        assert len(labels[k]) == len(points) and labels[k].dtype == np.uint32
    all_labels = np.concatenate([labels[k] for k in range(10)])
    assert 0.02 < np.mean(all_labels == 1) < 0.8  # ground is there, and not everything
    assert len(np.unique(all_labels[all_labels >= 2])) >= 5  # several objects
    assert max(all_labels) < len(labels.classes) and labels.classes[:2] == ['none', 'ground']
    for name_ in (sidecars.GROUND_TRUTH_DENSE, sidecars.SCENARIO, sidecars.NOTE):
        assert sidecars.sidecar_path(path, name_).is_file()
    note = sidecars.sidecar_path(path, sidecars.NOTE).read_text()
    assert f'lego_loam_py simulate {name} -o {path.name} --duration 1 --seed 0' in note
    labels.close()


def test_firing_order_and_clockwise_azimuth(contents):
    model = LidarModel.from_preset('VLP-16')
    _, points, *_ = contents('campus_ideal')['clouds'][3]
    # Lasers fire within the first 62 % of a column period: +0.2 finds the column despite float32 rounding.
    column = np.floor(points['time'].astype(np.float64) / model.column_period + 0.2).astype(int)
    azimuth = np.arctan2(points['y'].astype(float), points['x'].astype(float))
    # Every point lies on its column's azimuth, which decreases with time (clockwise spin from +x).
    assert np.array_equal(column_of_azimuth(azimuth, model.columns), column)
    assert np.all(np.diff(column) >= 0)
    unwrapped = np.unwrap(azimuth)
    assert np.all(np.diff(unwrapped) <= 1e-6) and unwrapped[0] - unwrapped[-1] > np.radians(358.0)
    # Within a column the lasers fire in laser-id order: -15, 1, -13, 3, ... deg.
    firing_index = {ring: i for i, ring in enumerate(model.firing_rings)}
    index = np.array([firing_index[r] for r in points['ring']])
    same = np.diff(column) == 0
    assert np.all(np.diff(index)[same] > 0)
    first_column = points['ring'][column == column[0]]
    assert list(first_column) == [r for r in model.firing_rings if r in set(first_column)]
    # LeGO-LOAM's start/end orientation (reference 6.1 step 2) sees a full sweep.
    start = -math.atan2(points['y'][0], points['x'][0])
    end = -math.atan2(points['y'][-1], points['x'][-1]) + 2 * math.pi
    assert abs(end - start - 2 * math.pi) < math.radians(1.0)


def test_time_field_is_the_firing_time_since_the_sweep_start(contents):
    model = LidarModel.from_preset('VLP-16')
    for _, points, *_ in contents('aggressive')['clouds']:
        t = points['time'].astype(np.float64)
        assert t[0] >= 0.0 and np.all(np.diff(t) > 0)
        assert 0.099 < t[-1] - t[0] < 0.1
        column = np.floor(t / model.column_period + 0.2)
        laser = np.array([list(model.firing_rings).index(r) for r in points['ring']])
        expected = (column * model.column_period + laser * 2.304e-6).astype(np.float32)
        assert np.array_equal(points['time'], expected)


def test_sixteen_rings_at_the_vlp16_elevations(contents):
    assert VLP16_FIRING_ELEVATIONS[:4] == (-15, 1, -13, 3)
    _, points, *_ = contents('corridor')['clouds'][0]  # indoors every beam hits something
    assert set(points['ring'].tolist()) == set(range(16))
    elevation = np.degrees(np.arctan2(points['z'], np.hypot(points['x'], points['y'])).astype(float))
    for ring in range(16):
        # Range noise moves a point along its beam only: the elevation stays the beam's.
        assert np.allclose(elevation[points['ring'] == ring], -15.0 + 2.0 * ring, atol=2e-3)


@pytest.mark.parametrize('preset', [p for p in SENSOR_PRESETS if p != 'VLP-16'])
def test_other_presets_use_their_geometry(preset):
    world = build_world('corridor', 0)
    model = LidarModel.from_preset(preset)
    geometry = SENSOR_PRESETS[preset]
    assert model.n_rings == geometry['n_scan'] and model.columns == geometry['horizon_scan']
    if geometry.get('beam_elevations'):  # a preset with a beam table (HDL-64E): those beams, or evenly spaced
        assert model.ring_elevations == pytest.approx(geometry['beam_elevations'])
        uniform = LidarModel.from_preset(preset, uniform_beams=True)
        assert np.allclose(np.diff(uniform.ring_elevations), geometry['ang_res_y'], atol=1e-5)
    else:
        assert np.allclose(np.diff(model.ring_elevations), geometry['ang_res_y'], atol=1e-5)
    sweep = simulate_sweep(model, world.scene, world.trajectory, 0.0, np.random.default_rng(0))
    points = sweep.points
    assert points['ring'].max() == geometry['n_scan'] - 1 and points['ring'].min() == 0
    elevation = np.degrees(np.arctan2(points['z'], np.hypot(points['x'], points['y'])).astype(float))
    assert np.allclose(elevation, np.asarray(model.ring_elevations)[points['ring']], atol=2e-3)
    assert np.all(np.diff(points['time']) >= 0)


def test_dropped_returns_make_fewer_points_never_nan(bags, contents):
    noisy = contents('campus')['clouds']
    ideal = contents('campus_ideal')['clouds']
    noisy_labels, ideal_labels = sidecars.load_labels(bags['campus']), sidecars.load_labels(bags['campus_ideal'])
    model = LidarModel.from_preset('VLP-16')
    ratios = []
    far_ground, near_ground = [], []
    for k, ((_, a, _, dense, _), (_, b, *_)) in enumerate(zip(noisy, ideal)):
        ratios.append(len(a) / len(b))
        assert dense and all(np.isfinite(a[f]).all() for f in ('x', 'y', 'z', 'intensity', 'time'))
        r = np.linalg.norm(np.column_stack([a['x'], a['y'], a['z']]).astype(float), axis=1)
        assert r.min() >= model.min_range and r.max() <= model.max_range
        # The ground seen at grazing incidence (ring 6, -3 deg, ~34 m; dark asphalt) loses far more returns
        # than the ground near the car (ring 0, -15 deg, ~7 m), which only sees the random dropout.
        ground_a, ground_b = noisy_labels[k] == 1, ideal_labels[k] == 1
        far_ground.append(np.sum(ground_a & (a['ring'] == 6)) / np.sum(ground_b & (b['ring'] == 6)))
        near_ground.append(np.sum(ground_a & (a['ring'] == 0)) / np.sum(ground_b & (b['ring'] == 0)))
    assert 0.75 < np.mean(ratios) < 0.99, ratios
    assert np.mean(near_ground) > 0.98 and np.mean(far_ground) < np.mean(near_ground) - 0.05, (near_ground, far_ground)


def test_range_noise_is_gaussian_along_the_beam_with_the_documented_sigma(contents):
    noisy = contents('campus')['clouds']
    ideal = contents('campus_ideal')['clouds']
    differences = []
    for (_, a, *_), (_, b, *_) in zip(noisy, ideal):
        # The time field identifies a firing (column, laser): pair the same firings.
        common, ia, ib = np.intersect1d(a['time'], b['time'], return_indices=True)
        ra = np.linalg.norm(np.column_stack([a['x'], a['y'], a['z']])[ia].astype(float), axis=1)
        rb = np.linalg.norm(np.column_stack([b['x'], b['y'], b['z']])[ib].astype(float), axis=1)
        differences.append(ra - rb)
    d = np.concatenate(differences)
    assert len(d) > 100000
    assert abs(d.mean()) < 1e-3 and 0.9 * SIGMA < d.std() < 1.1 * SIGMA
    assert np.mean(np.abs(d) > 3 * SIGMA) < 0.005  # Gaussian tails, no outliers


def test_intensity_follows_the_surface_material(bags, contents):
    labels = sidecars.load_labels(bags['campus'])
    by_class: dict[str, list] = {}
    for k, (_, points, *_) in enumerate(contents('campus')['clouds']):
        names = labels.class_names(labels[k])
        for c in ('ground', 'car', 'building', 'tree'):
            by_class.setdefault(c, []).append(points['intensity'][names == c])
        assert np.all((points['intensity'] >= 0) & (points['intensity'] <= 255))
        assert np.array_equal(points['intensity'], np.round(points['intensity']))
    median = {c: float(np.median(np.concatenate(v))) for c, v in by_class.items()}
    assert median['car'] > 60 > median['building'] > median['tree'] > median['ground'], median
    labels.close()


# ---------------------------------------------------------------------------------- motion and ground truth


@pytest.mark.parametrize('ideal', [True, False], ids=['ideal', 'noisy'])
def test_points_reprojected_at_their_firing_time_land_on_the_mesh_they_hit(bags, contents, ideal):
    """Aggressive drive (up to 90 deg/s): each point, moved into the world with the ground-truth pose at its own
    firing time (dense ground truth beside the bag, interpolated), lies on the mesh: within 3 cm, plus the
    range noise (3 sigma) for the noisy sensor. With the sweep-start pose for every point it would not."""
    name = 'aggressive_ideal' if ideal else 'aggressive_3s'
    world = build_world('aggressive', 0)
    labels = sidecars.load_labels(bags[name])
    bound = 0.03 + (0.0 if ideal else 3 * SIGMA)
    distances, skewed, agree = [], [], []
    for k, (stamp, points, *_) in enumerate(contents(name)['clouds']):
        world_points = points_in_world(bags[name], stamp, points)
        distances.append(world.scene.distance(world_points))
        skewed.append(world.scene.distance(points_in_world(bags[name], stamp, points, own_time=False)))
        # The nearest triangle belongs to the object the point is labelled with.
        agree.append(np.mean(world.scene.closest_instance(world_points) == labels[k]))
    d = np.concatenate(distances)
    if ideal:
        assert d.max() < bound, d.max()
    else:
        assert np.quantile(d, 0.997) < bound and d.max() < 0.03 + 6 * SIGMA, (np.quantile(d, 0.997), d.max())
    assert np.mean(np.concatenate(skewed) > bound) > 0.2  # the motion is large: deskewing matters
    assert np.mean(agree) > 0.99
    labels.close()


def test_ground_truth_matches_the_trajectory_and_the_dense_file(bags):
    path = bags['forest']
    world = build_world('forest', 0)
    stamps, poses = sidecars.load_ground_truth(path)
    dense_stamps, dense = sidecars.load_ground_truth(path, dense=True)
    truth = world.trajectory.matrices((stamps - START_STAMP_NS) / 1e9)
    expected = np.einsum('ij,njk->nik', np.linalg.inv(truth[0]), truth)
    assert np.allclose(poses, expected, atol=1e-8)
    assert np.allclose(world_pose_of_first(path), truth[0], atol=1e-8)
    # Sweep starts are IMU stamps too: the dense file holds the same poses there.
    index = np.searchsorted(dense_stamps, stamps)
    assert np.array_equal(dense_stamps[index], stamps) and np.allclose(dense[index], poses, atol=1e-8)
    # Forest: the robot rolls and pitches with the terrain.
    t = np.linspace(0.0, 60.0, 601)
    rpy = Rotation.from_matrix(world.trajectory.pose(t)[0]).as_euler('xyz', degrees=True)
    assert np.ptp(rpy[:, 0]) > 3.0 and np.ptp(rpy[:, 1]) > 3.0


def test_campus_loop_returns_to_its_start():
    world = build_world('campus', 0)
    trajectory = world.trajectory
    assert trajectory.lap_time is not None and 180.0 < world.default_duration < 300.0
    assert 300.0 < world.facts['path_length_m'] < 500.0 and 1.0 < world.facts['mean_speed_mps'] < 2.0
    last_sweep = math.floor(world.default_duration / 0.1 + 1e-9) - 1
    start, end = trajectory.matrices([0.0, last_sweep * 0.1])
    assert np.linalg.norm(end[:3, 3] - start[:3, 3]) < 0.5
    # ... after going around: the farthest point of the lap is far away.
    t = np.linspace(0.0, trajectory.lap_time, 500)
    assert np.linalg.norm(trajectory.pose(t)[1] - start[:3, 3], axis=1).max() > 80.0


def test_aggressive_reaches_90_deg_per_second_in_the_imu(contents):
    gyro = contents('aggressive_3s')['imu']['gyro']
    assert np.degrees(np.abs(gyro[:, 2]).max()) >= 80.0
    world = build_world('aggressive', 0)
    t = np.linspace(0.0, world.trajectory.lap_time, 20000)
    yaw_rate = np.degrees(np.abs(world.trajectory.angular_velocity(t)[:, 2]))
    assert 85.0 < yaw_rate.max() < 95.0


def test_in_place_turns_stop_spin_at_the_peak_rate_and_walk_on_where_they_left_off():
    base = build_world('corridor', 0)
    world = build_world('corridor', 0, turn_rate=150.0)
    turns = world.trajectory
    assert world.facts['turns'] == len(turns.starts) >= 3
    # A whole turn at a quintic yaw profile: 360 deg * 15/8 / 150 deg/s = 4.5 s, plus 1 s of braking.
    assert turns.turn_time == pytest.approx(4.5) and turns.pause == pytest.approx(5.5)
    assert world.default_duration == pytest.approx(base.default_duration + 5.5 * len(turns.starts), abs=0.11)
    t = np.arange(0.0, 70.0, 0.01)
    yaw_rate = np.degrees(turns.angular_velocity(t)[:, 2])
    speed = np.linalg.norm(turns.velocity(t), axis=1)
    assert 149.0 < np.abs(yaw_rate).max() < 151.0 and world.facts['turn_peak_rate_deg_s'] == 150.0
    # The first turn: standing still at its middle (base time 10 s), left; the second one turns right.
    first_middle = turns.starts[0] + 1.0 + 0.5 * turns.turn_time
    standing = np.abs(t - first_middle) < 0.5 * turns.turn_time
    assert speed[standing].max() < 1e-6 and yaw_rate[np.argmin(np.abs(t - first_middle))] > 149.0
    assert yaw_rate[np.argmin(np.abs(t - (turns.starts[1] + 1.0 + 0.5 * turns.turn_time)))] < -149.0
    rotation, position = turns.pose(np.array([first_middle]))
    assert np.allclose(position, base.trajectory.pose(np.array([10.0]))[1], atol=1e-9)
    # Smooth: braking and walking on are no harder than the walk itself.
    assert (
        np.linalg.norm(turns.acceleration(t), axis=1).max()
        < 1.2 * np.linalg.norm(base.trajectory.acceleration(t), axis=1).max()
    )
    # After the turns, the pose is the base one, 5.5 s later per turn; before the first, the base one.
    for later, turns_before in ((5.0, 0), (30.0, 1), (67.0, 2)):
        assert np.allclose(turns.matrices([later]), base.trajectory.matrices([later - 5.5 * turns_before]), atol=1e-9)
    # Recordings without turns keep the configuration (and cache key) they had before the option existed.
    assert 'turn_rate' not in SimConfig('corridor').to_dict()
    assert SimConfig('corridor', turn_rate=150).command('out').endswith('--turn-rate 150')
    with pytest.raises(ValueError, match='turn rate'):
        SimConfig('corridor', turn_rate=-1.0).validate()


def test_another_route_drives_the_same_path_through_the_same_scene_from_another_start_and_the_other_way():
    base = build_world('campus', 0)
    path = base.trajectory.path
    s = np.linspace(0.0, path.length, 997)
    backwards = path.reversed()
    # The reversed path is the same curve (the periodic interpolant is unique), run the other way round.
    assert backwards.length == pytest.approx(path.length, rel=1e-9)
    assert np.abs(backwards.xy(path.length - s) - path.xy(s)).max() < 1e-9
    assert np.abs(backwards.tangent(path.length - s) + path.tangent(s)).max() < 1e-9
    route = build_world('campus', 0, route_start=100.0, reverse=True)
    assert route.facts['reverse'] and route.facts['route_start_m'] == 100.0
    assert route.scene.distance(np.array([[10.0, -37.0, 1.0], [40.0, 0.0, 1.0]])) == pytest.approx(
        base.scene.distance(np.array([[10.0, -37.0, 1.0], [40.0, 0.0, 1.0]]))
    )  # the same scenery
    # It starts where asked (the lidar sits 1.8 m above the road, tilted with the car: within a few cm of the
    # path) and heads the other way: along -tangent at s = 100 m, then back along the path.
    rotation, position = route.trajectory.pose(np.array([0.0, 10.0]))
    start_xy, start_tangent = path.xy(np.array([100.0]))[0], path.tangent(np.array([100.0]))[0]
    assert np.linalg.norm(position[0, :2] - start_xy) < 0.1
    assert rotation[0, :2, 0] @ start_tangent < -0.99
    travelled = route.trajectory.speed(np.array([10.0]))[0] - route.trajectory.speed.start
    assert np.linalg.norm(position[1, :2] - path.xy(np.array([100.0 - travelled]))[0]) < 0.1
    # Forward from another start: the same motion as the scenario's own route, shifted in time.
    forward = build_world('campus', 0, route_start=50.0).trajectory
    assert np.linalg.norm(forward.pose(np.array([0.0]))[1][0, :2] - path.xy(np.array([50.0]))[0]) < 0.1
    # Recordings on the scenario's own route keep their configuration and cache key.
    assert not {'route_start', 'reverse'} & set(SimConfig('campus').to_dict())
    assert SimConfig('campus', route_start=100, reverse=True).command('out').endswith('--route-start 100 --reverse')
    assert SimConfig('campus', route_start=100).cache_key() != SimConfig('campus').cache_key()


# ------------------------------------------------------------------------------------------------------- IMU


def _integrate_gyro(rotation0: np.ndarray, gyro: np.ndarray, dt: float) -> np.ndarray:
    rotation = rotation0.copy()
    for k in range(len(gyro) - 1):
        rotation = rotation @ Rotation.from_rotvec(0.5 * (gyro[k] + gyro[k + 1]) * dt).as_matrix()
    return rotation


@pytest.mark.parametrize('scenario', ['aggressive', 'forest'])
def test_gyro_integrated_over_10_s_stays_within_the_bias_and_noise_bound(scenario):
    """Bound: |b_g| T + 4 sigma_c sqrt(T) + 1e-4 rad (integration), i.e. about 0.35 deg for the default unit
    (0.02 deg/s bias per axis, 0.01 deg/s/sqrt(Hz)); noise-free the error is < 1e-4 rad."""
    world = build_world(scenario, 0)
    model = ImuModel()
    t = np.arange(2001) / 200.0 + 0.5  # 10 s through the hairpin / over bumps
    truth = world.trajectory.pose(t)[0]
    ideal = model.ideal().measure(world.trajectory, t, model.ideal().draw_biases(np.random.default_rng(0)), None)
    error = Rotation.from_matrix(truth[-1].T @ _integrate_gyro(truth[0], ideal.angular_velocity, 0.005)).magnitude()
    assert error < 1e-4, error
    biases = model.draw_biases(np.random.default_rng(7))
    noisy = model.measure(world.trajectory, t, biases, np.random.default_rng(8))
    error = Rotation.from_matrix(truth[-1].T @ _integrate_gyro(truth[0], noisy.angular_velocity, 0.005)).magnitude()
    bound = np.linalg.norm(biases.gyro) * 10.0 + 4 * model.noise.gyro_noise_density * math.sqrt(10.0) + 1e-4
    assert error < bound, (math.degrees(error), math.degrees(bound))
    assert bound < math.radians(1.0)


def _integrate_specific_force(bag: Path, data: dict, window: int) -> tuple[float, float]:
    """Worst position error [m] and its bound when integrating the bag's specific force over ``window``
    samples (gravity removed with the true orientation, start velocity from the dense ground truth)."""
    stamps, dense = sidecars.load_ground_truth(bag, dense=True)
    imu = data['imu']
    assert np.array_equal(stamps, imu['stamp'])
    first = world_pose_of_first(bag)
    rotation = np.einsum('ij,njk->nik', first[:3, :3], dense[:, :3, :3])
    position = dense[:, :3, 3] @ first[:3, :3].T + first[:3, 3]
    r_li = np.array(sidecars.load_scenario(bag)['imu']['rotation_lidar_imu'])
    accel = np.einsum('nij,jk,nk->ni', rotation, r_li, imu['accel']) + [0.0, 0.0, -GRAVITY]
    h = 0.005
    worst = 0.0
    for start in range(2, len(stamps) - window - 1, 50):
        velocity = (position[start - 2] - 8 * position[start - 1] + 8 * position[start + 1] - position[start + 2]) / (
            12 * h
        )
        p = position[start].copy()
        for k in range(start, start + window):
            p = p + velocity * h + (2 * accel[k] + accel[k + 1]) / 6 * h * h
            velocity = velocity + 0.5 * (accel[k] + accel[k + 1]) * h
        worst = max(worst, float(np.linalg.norm(p - position[start + window])))
    biases = sidecars.load_scenario(bag)['imu']['biases']['accel']
    seconds = window * h
    bound = 0.5 * np.linalg.norm(biases) * seconds**2 + 4 * ImuNoise().accel_noise_density * seconds**1.5 + 1e-3
    return worst, bound


def test_specific_force_integrated_over_1_s_matches_the_ground_truth(bags, contents):
    """Bound: 0.5 |b_a| T^2 + 4 sigma_c T^1.5 + 1 mm, about 2 cm for the default unit (2 mg bias per axis);
    noise-free the error is < 1 mm."""
    worst, _ = _integrate_specific_force(bags['aggressive_ideal'], contents('aggressive_ideal'), 200)
    assert worst < 1e-3, worst
    worst, bound = _integrate_specific_force(bags['aggressive_3s'], contents('aggressive_3s'), 200)
    assert worst < bound < 0.05, (worst, bound)


def test_imu_messages_carry_the_documented_noise_and_bias(bags, contents):
    data = contents('aggressive_3s')['imu']
    world = build_world('aggressive', 0)
    t = (data['stamp'] - START_STAMP_NS) / 1e9
    assert np.allclose(np.diff(t), 0.005) and data['frame'] == {'imu_link'}
    info = sidecars.load_scenario(bags['aggressive_3s'])['imu']
    model = ImuModel()
    rotation = world.trajectory.pose(t)[0]
    gyro_error = data['gyro'] - world.trajectory.angular_velocity(t)
    accel_truth = np.einsum('nji,nj->ni', rotation, world.trajectory.acceleration(t) + [0.0, 0.0, GRAVITY])
    accel_error = data['accel'] - accel_truth
    n = len(t)
    for error, bias, sigma in (
        (gyro_error, info['biases']['gyro'], model.gyro_sigma),
        (accel_error, info['biases']['accel'], model.accel_sigma),
    ):
        assert np.allclose(error.mean(axis=0), bias, atol=5 * sigma / math.sqrt(n))
        assert np.allclose(error.std(axis=0), sigma, rtol=0.15)
    orientation_error = (Rotation.from_quat(data['quat']) * Rotation.from_matrix(rotation).inv()).magnitude()
    assert orientation_error.max() < math.radians(3.0)
    orientation_cov, gyro_cov, accel_cov = data['cov']
    assert np.allclose(gyro_cov, np.eye(3).ravel() * model.gyro_sigma**2)
    assert np.allclose(accel_cov, np.eye(3).ravel() * model.accel_sigma**2)
    assert np.all(orientation_cov[[0, 4, 8]] > 0)
    # At (nearly) constant velocity on a flat road the accelerometer reads about +g on z.
    straight = np.abs(data['gyro'][:, 2]) < math.radians(1.0)
    if straight.any():
        assert abs(np.median(data['accel'][straight, 2]) - GRAVITY) < 0.5


def test_imu_extrinsic_rotation(tmp_path):
    path = simulate(
        SimConfig('aggressive', duration=2.0, ideal=True, imu_extrinsic_rpy=(0.0, 0.0, 90.0)), tmp_path / 'rotated'
    ).bag_path
    data = read_bag(path)['imu']
    world = build_world('aggressive', 0)
    t = (data['stamp'] - START_STAMP_NS) / 1e9
    omega = world.trajectory.angular_velocity(t)
    # IMU yawed +90 deg in the lidar frame: its x axis is the lidar's y, its y axis the lidar's -x.
    assert np.allclose(data['gyro'][:, 0], omega[:, 1], atol=1e-6)
    assert np.allclose(data['gyro'][:, 1], -omega[:, 0], atol=1e-6)
    assert np.allclose(data['gyro'][:, 2], omega[:, 2], atol=1e-6)
    rotation = world.trajectory.pose(t)[0]
    r_li = Rotation.from_euler('z', 90, degrees=True).as_matrix()
    assert np.allclose(Rotation.from_quat(data['quat']).as_matrix(), rotation @ r_li, atol=1e-9)
    scenario = sidecars.load_scenario(path)
    assert np.allclose(scenario['imu']['rotation_lidar_imu'], r_li, atol=1e-12)
    assert '--imu-extrinsic-rpy 0 0 90' in scenario['command']


def test_the_straight_scenario_drives_straight_for_50_s():
    """A drive that cannot show how an IMU is mounted (the calibration must refuse it): no turn, only the road's
    undulations, at 8 m/s."""
    trajectory = build_world('straight').trajectory
    t = np.arange(0.0, 50.0, 0.05)
    rates = np.degrees(np.abs(trajectory.angular_velocity(t)))
    assert rates[:, 2].max() < 1.0 and rates.max() < 2.0
    speed = np.linalg.norm(trajectory.velocity(t), axis=1)
    assert 7.5 < speed.min() and speed.max() < 8.1


def test_imu_lever_arm_orientation_frame_and_time_offset(tmp_path):
    """The IMU 0.3 m from the lidar, its orientation output in a frame yawed 90 deg and upside down, its clock
    20 ms ahead: the accelerometer feels the rotation's centripetal and tangential acceleration at its own
    position, the orientation is that frame's, the stamps are 20 ms late against the bag time (the time of
    measurement, when a recorder receives the sample)."""
    lever_arm, orientation_rpy = np.array([0.2, 0.1, -0.2]), (180.0, 0.0, 90.0)
    config = SimConfig(
        'aggressive',
        duration=3.0,
        ideal=True,
        imu_lever_arm=tuple(lever_arm),
        imu_orientation_rpy=orientation_rpy,
        imu_time_offset=0.02,
    )
    path = simulate(config, tmp_path / 'mounted').bag_path
    data = read_bag(path)['imu']
    assert np.all(data['stamp'] - data['bag_time'] == 20_000_000)
    t = (data['bag_time'] - START_STAMP_NS) / 1e9
    trajectory = build_world('aggressive', 0).trajectory
    rotation, _ = trajectory.pose(t)
    omega = trajectory.angular_velocity(t)
    h = 1e-3
    alpha = (trajectory.angular_velocity(t + h) - trajectory.angular_velocity(t - h)) / (2 * h)
    at_lidar = np.einsum('nji,nj->ni', rotation, trajectory.acceleration(t) - [0.0, 0.0, -GRAVITY])
    lever = np.cross(alpha, lever_arm) + np.cross(omega, np.cross(omega, lever_arm))
    assert np.abs(lever).max() > 0.3  # the hairpin: up to 90 deg/s, enough to feel at 0.3 m
    assert np.allclose(data['accel'], at_lidar + lever, atol=2e-3)
    orientation = rotation @ Rotation.from_euler('xyz', orientation_rpy, degrees=True).as_matrix()
    assert np.allclose(Rotation.from_quat(data['quat']).as_matrix(), orientation, atol=1e-9)
    scenario = sidecars.load_scenario(path)
    assert scenario['imu']['lever_arm_m'] == list(lever_arm) and scenario['imu']['time_offset_s'] == 0.02
    for option in ('--imu-lever-arm 0.2 0.1 -0.2', '--imu-orientation-rpy 180 0 90', '--imu-time-offset 0.02'):
        assert option in scenario['command']
    # Recordings without the options keep their cache keys (the options are left out of the configuration).
    assert 'imu_time_offset' not in SimConfig('campus').to_dict() and 'imu_time_offset' in config.to_dict()


# ------------------------------------------------------------------------------------- determinism, outputs


def _messages(path: Path) -> list[tuple]:
    with BagReader(path) as reader:
        return [(m.topic, m.timestamp, m.data) for m in reader.messages()]


def test_same_seed_gives_identical_messages_and_sidecars(tmp_path):
    config = SimConfig('forest', duration=0.5, seed=3)
    a = simulate(config, tmp_path / 'a').bag_path
    b = simulate(config, tmp_path / 'b').bag_path
    assert _messages(a) == _messages(b)
    for name in (sidecars.GROUND_TRUTH, sidecars.GROUND_TRUTH_DENSE, sidecars.LABELS):
        assert sidecars.sidecar_path(a, name).read_bytes() == sidecars.sidecar_path(b, name).read_bytes(), name
    # scenario.yaml differs only in the output name of the command.
    text_a, text_b = (sidecars.sidecar_path(p, sidecars.SCENARIO).read_text() for p in (a, b))
    assert text_a.replace(' -o a ', ' -o b ') == text_b
    other = simulate(SimConfig('forest', duration=0.5, seed=4), tmp_path / 'c').bag_path
    clouds_a = [m for m in _messages(a) if m[0] == '/velodyne_points']
    clouds_c = [m for m in _messages(other) if m[0] == '/velodyne_points']
    assert len(clouds_a) == len(clouds_c) and all(x[2] != y[2] for x, y in zip(clouds_a, clouds_c))


def test_ros1_bag_and_packed_layout(tmp_path):
    result = simulate(SimConfig('corridor', duration=0.3, ros1=True, layout='packed'), tmp_path / 'walk')
    assert result.bag_path == tmp_path / 'walk.bag' and result.bag_path.is_file()
    for name in ('ground_truth.tum', 'ground_truth_dense.tum', 'labels.npz', 'scenario.yaml', 'README.md'):
        assert (tmp_path / f'walk.{name}').is_file()
    data = read_bag(result.bag_path)
    assert len(data['clouds']) == 3 and len(data['imu']['stamp']) == 61
    assert all(c[1].dtype == VELODYNE_PACKED_DTYPE for c in data['clouds'])
    with BagReader(result.bag_path) as reader:
        assert reader.is_ros1
    assert len(sidecars.load_ground_truth(result.bag_path)) == 3
    assert len(sidecars.load_labels(result.bag_path)[2]) == len(data['clouds'][2][1])


@pytest.mark.parametrize('storage,compress', [('sqlite3', False), ('mcap', True)], ids=['db3', 'mcap_zstd'])
def test_ros2_storage_options(tmp_path, storage, compress):
    path = simulate(SimConfig('corridor', duration=0.3, storage=storage, compress=compress), tmp_path / 'bag').bag_path
    assert list(path.glob('*.db3' if storage == 'sqlite3' else '*.mcap'))
    data = read_bag(path)
    assert len(data['clouds']) == 3 and len(data['imu']['stamp']) == 61
    reference = simulate(SimConfig('corridor', duration=0.3), tmp_path / 'reference').bag_path
    assert _messages(path) == _messages(reference)  # the same messages whatever the storage


def test_sidecar_paths_and_missing_ground_truth(tmp_path):
    assert sidecars.sidecar_path(tmp_path / 'run.bag', 'ground_truth.tum') == tmp_path / 'run.ground_truth.tum'
    assert sidecars.sidecar_path(tmp_path / 'run', 'labels.npz') == tmp_path / 'run' / 'labels.npz'
    assert sidecars.load_ground_truth(tmp_path / 'nothing_here') is None
    assert sidecars.load_labels(tmp_path / 'nothing_here') is None
    stamps = np.array([1_700_000_000_000_000_001, 1_700_000_000_100_000_000])
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[1, :3, :3] = Rotation.from_euler('xyz', [0.1, -0.2, 3.0]).as_matrix()
    poses[1, :3, 3] = [1.5, -2.25, 0.125]
    sim_output.write_tum(tmp_path / 'x.tum', stamps, poses)
    read_stamps, read_poses = read_tum(tmp_path / 'x.tum')
    assert np.array_equal(read_stamps, stamps) and np.allclose(read_poses, poses, atol=1e-9)


def test_cached_scenario_generates_once(tmp_path, monkeypatch):
    monkeypatch.setenv('LEGO_LOAM_CACHE', str(tmp_path / 'cache'))
    first = cached_scenario('corridor', duration=0.3, seed=1)
    assert first.parent == tmp_path / 'cache' / 'sim' and first.name.startswith('corridor-')
    mtime = (first / 'metadata.yaml').stat().st_mtime_ns
    assert cached_scenario('corridor', duration=0.3, seed=1) == first
    assert (first / 'metadata.yaml').stat().st_mtime_ns == mtime
    assert cached_scenario('corridor', duration=0.3, seed=2) != first
    assert not [p for p in (tmp_path / 'cache' / 'sim').iterdir() if p.name.startswith('.')]
    # The command line finds the same entry (and does not regenerate it).
    run = subprocess.run(
        [CLI, 'simulate', 'corridor', '--cached', '--duration', '0.3', '--seed', '1', '--no-progress'],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, 'LEGO_LOAM_CACHE': str(tmp_path / 'cache')},
    )
    assert run.returncode == 0 and run.stdout.strip() == str(first), run.stderr
    assert (first / 'metadata.yaml').stat().st_mtime_ns == mtime


# ------------------------------------------------------------------------------------------ CLI and viewer


def test_cli_lists_simulates_and_refuses_to_overwrite(tmp_path):
    listing = subprocess.run([CLI, 'simulate', '--list'], capture_output=True, text=True, timeout=120)
    assert listing.returncode == 0 and all(name in listing.stdout for name in SCENARIOS)
    assert 'VLP-16' in listing.stdout and 'OS1-64' in listing.stdout
    out = tmp_path / 'corridor'
    args = [CLI, 'simulate', 'corridor', '-o', str(out), '--duration', '0.2', '--seed', '5', '--no-progress']
    run = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert 'wrote' in run.stderr and len(sidecars.load_ground_truth(out)) == 2
    assert (
        sidecars.load_scenario(out)['command'] == 'lego_loam_py simulate corridor -o corridor --duration 0.2 --seed 5'
    )
    again = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert again.returncode == 1 and 'exists' in again.stderr
    unknown = subprocess.run(
        [CLI, 'simulate', 'moon', '-o', str(tmp_path / 'm')], capture_output=True, text=True, timeout=120
    )
    assert unknown.returncode == 1 and "unknown scenario 'moon'" in unknown.stderr


def test_view_writes_png_for_simulated_and_real_bags(bags, tmp_path):
    for color in ('label', 'intensity'):
        png = tmp_path / f'{color}.png'
        run = subprocess.run(
            [CLI, 'view', str(bags['campus']), '--scan', '4', '--color', color, '-o', str(png)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert run.returncode == 0, run.stderr
        assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 20000
    bad = subprocess.run(
        [CLI, 'view', str(bags['campus']), '--scan', '99', '-o', str(tmp_path / 'x.png')],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 1 and 'out of range' in bad.stderr and not (tmp_path / 'x.png').exists()
    real = REPO.parent / 'shared' / 'data' / 'golden' / 'vlp16_single_rotation.bag'
    if real.is_file():  # a real VLP-16 scan (ROS 1 bag, no labels beside it)
        png = tmp_path / 'real.png'
        run = subprocess.run([CLI, 'view', str(real), '-o', str(png)], capture_output=True, text=True, timeout=120)
        assert run.returncode == 0 and png.stat().st_size > 20000, run.stderr
        run = subprocess.run(
            [CLI, 'view', str(real), '--color', 'label', '-o', str(png)], capture_output=True, text=True, timeout=120
        )
        assert run.returncode == 1 and 'labels.npz' in run.stderr


def test_simulator_package_imports_no_ros():
    roots = ('rclpy', 'sensor_msgs', 'std_msgs', 'geometry_msgs', 'nav_msgs', 'builtin_interfaces', 'rosgraph_msgs')
    for path in sorted((REPO / 'lego_loam_py' / 'sim').glob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module]
                if isinstance(node, ast.ImportFrom) and node.module
                else []
            )
            for name in names:
                assert name.split('.')[0] not in roots and not name.startswith('lego_loam_py.ros'), (path, name)


# ------------------------------------------------------------------------------------------- committed bags

COMMITTED = sorted(p for p in BAGS.iterdir() if p.is_dir()) if BAGS.is_dir() else []


def test_committed_bags_exist_and_fit_the_budget():
    names = {p.name for p in COMMITTED}
    assert any(n.startswith('campus') for n in names) and any(n.startswith('aggressive') for n in names), names
    total = sum(f.stat().st_size for f in BAGS.rglob('*') if f.is_file())
    assert total <= 60 * 2**20, f'bags/ holds {total / 2**20:.1f} MiB'
    listing = (BAGS / 'README.md').read_text()
    for bag in COMMITTED:
        assert bag.name in listing


# Regenerating a recording on another machine gives the same messages, but not always the same bits, and the
# reproducibility check below says exactly how far apart they may be and why:
# * The trajectory is a periodic quintic spline whose coefficients come from a LAPACK solve, and the IMU's
#   accelerations are its second derivatives: another BLAS/LAPACK kernel (the CPU decides which) or another
#   numpy/scipy build moves them in the last bits (seen: 2e-8 m/s^2 between scipy releases). IMU_TOLERANCE is
#   far below the simulated IMU's own noise (gyro 2.5e-3 rad/s, accelerometer 8e-3 m/s^2 per sample).
# * The rays are cast by Embree (open3d) in float32, on the SIMD path the CPU offers (SSE, AVX2, AVX-512,
#   NEON); a hit distance can then differ by a float32 ulp or two. The range is quantised to the sensor's
#   resolution, so such a ulp can move a point by one whole range step along its beam.
# * A ray that grazes an edge can hit the surface behind it on another CPU: at most GRAZING_SHARE of a scan.
# Counts, stamps, frames, rings and firing times come from integer and exact arithmetic: they must be equal.
IMU_TOLERANCE = 1e-6  # [rad, rad/s, m/s^2] per component
RANGE_STEP = 0.002  # the VLP-16's range resolution [m] (sim.lidar.LIDAR_SPECS)
POINT_TOLERANCE = RANGE_STEP + 1e-4  # one range step, plus float32 rounding of x, y, z at 100 m
GRAZING_SHARE = 1e-3  # points of a scan allowed beyond POINT_TOLERANCE
MOVED_SHARE = 0.02  # points of a scan allowed to move at all (by one range step at most)


def imu_vector(msg) -> np.ndarray:
    return np.array(
        [
            msg.orientation.x,
            msg.orientation.y,
            msg.orientation.z,
            msg.orientation.w,
            msg.angular_velocity.x,
            msg.angular_velocity.y,
            msg.angular_velocity.z,
            msg.linear_acceleration.x,
            msg.linear_acceleration.y,
            msg.linear_acceleration.z,
        ]
    )


def recording_differences(expected: list, actual: list) -> list[str]:
    """What differs between two recordings, given as [(topic, bag timestamp, deserialized message)], beyond the
    tolerances above (empty when they are the same recording)."""
    problems = []
    if [(t, s) for t, s, _ in expected] != [(t, s) for t, s, _ in actual]:
        return [
            f'topics and bag stamps differ: {[(t, s) for t, s, _ in expected][:5]} ... vs '
            f'{[(t, s) for t, s, _ in actual][:5]} ... ({len(expected)} vs {len(actual)} messages)'
        ]
    for index, ((topic, stamp, a), (_, _, b)) in enumerate(zip(expected, actual)):
        where = f'message {index} ({topic} at {stamp})'
        if (a.header.stamp.sec, a.header.stamp.nanosec, a.header.frame_id) != (
            b.header.stamp.sec,
            b.header.stamp.nanosec,
            b.header.frame_id,
        ):
            problems.append(f'{where}: header {a.header} vs {b.header}')
        elif topic == '/imu/data':
            difference = np.abs(imu_vector(a) - imu_vector(b)).max()
            if difference > IMU_TOLERANCE or list(a.orientation_covariance) != list(b.orientation_covariance):
                problems.append(f'{where}: IMU values differ by {difference:.3g} (tolerance {IMU_TOLERANCE})')
        else:
            pa, pb = cloud_msg_to_array(a), cloud_msg_to_array(b)
            if pa.dtype != pb.dtype or len(pa) != len(pb):
                problems.append(f'{where}: {len(pa)} points {pa.dtype} vs {len(pb)} points {pb.dtype}')
                continue
            moved = np.sqrt(sum((pa[k].astype(float) - pb[k].astype(float)) ** 2 for k in 'xyz'))
            exact = all(np.array_equal(pa[k], pb[k]) for k in ('ring', 'time'))
            beyond = int((moved > POINT_TOLERANCE).sum())
            changed = int((moved > 0).sum())
            if not exact or beyond > GRAZING_SHARE * len(pa) or changed > MOVED_SHARE * len(pa):
                problems.append(
                    f'{where}: rings/times equal {exact}; {changed} of {len(pa)} points moved, '
                    f'{beyond} by more than {POINT_TOLERANCE} m (max {moved.max():.4f} m)'
                )
    return problems


def read_messages(path: Path, stop: int | None = None) -> list:
    with BagReader(path) as reader:
        return [(m.topic, m.timestamp, reader.deserialize(m)) for m in reader.messages(stop=stop)]


@pytest.mark.parametrize('bag', COMMITTED, ids=lambda p: p.name)
def test_committed_bag_has_ground_truth_and_is_reproducible_from_its_note(bag, tmp_path):
    scenario = sidecars.load_scenario(bag)
    stamps, poses = sidecars.load_ground_truth(bag)
    with BagReader(bag) as reader:
        counts = reader.topic_counts()
    assert counts['/velodyne_points'] == len(stamps) == scenario['recording']['scans']
    first = read_messages(bag, stop=START_STAMP_NS + 3 * SCAN_NS + 1)
    assert np.allclose(poses[0], np.eye(4)) and len(sidecars.load_labels(bag)) == len(stamps)
    note = (bag / 'README.md').read_text()
    assert scenario['command'] in note and f'-o {bag.name}' in scenario['command']
    # Regenerate the first 0.3 s with the recorded configuration: the same messages, within the tolerances
    # that another CPU or library build needs (see above).
    config = SimConfig(
        **{**scenario['config'], 'duration': 0.3, 'imu_extrinsic_rpy': tuple(scenario['config']['imu_extrinsic_rpy'])}
    )
    again = read_messages(simulate(config, tmp_path / 'again').bag_path)
    assert sum(topic == '/velodyne_points' for topic, _, _ in first) == 3
    assert recording_differences(first, again) == []


def test_recording_comparison_sees_a_moved_point_a_lost_point_and_a_changed_imu():
    """The tolerant comparison above still fails on a real difference."""
    import copy

    bag = COMMITTED[0]
    first = read_messages(bag, stop=START_STAMP_NS + SCAN_NS + 1)
    assert recording_differences(first, first) == []
    index = next(i for i, (topic, _, _) in enumerate(first) if topic == '/velodyne_points')
    topic, stamp, cloud = first[index]
    points = cloud_msg_to_array(cloud)
    stride = cloud.point_step

    def with_points(changed: np.ndarray):
        msg = copy.copy(cloud)
        raw = np.frombuffer(bytes(cloud.data), np.uint8).reshape(-1, stride).copy()
        if len(changed) < len(points):
            raw = raw[: len(changed)]
        view = raw.view(np.uint8)
        offsets = {f.name: f.offset for f in cloud.fields}
        for name in 'xyz':
            view[:, offsets[name] : offsets[name] + 4] = changed[name].astype('<f4').view(np.uint8).reshape(-1, 4)
        msg.data = raw.reshape(-1)
        msg.width = len(changed)
        msg.row_step = len(changed) * stride
        return first[:index] + [(topic, stamp, msg)] + first[index + 1 :]

    same = points.copy()
    assert recording_differences(first, with_points(same)) == []
    one_step = points.copy()
    one_step['x'][:10] += RANGE_STEP * 0.9  # a few points one range step away: another CPU's rounding
    assert recording_differences(first, with_points(one_step)) == []
    moved = points.copy()
    moved['x'][: int(len(points) * 0.01)] += 0.005  # 1 % of a scan 5 mm away: a different recording
    assert 'moved' in ' '.join(recording_differences(first, with_points(moved)))
    assert 'points' in ' '.join(recording_differences(first, with_points(points[:-1])))
    imu_index = next(i for i, (topic, _, _) in enumerate(first) if topic == '/imu/data')
    topic, stamp, imu = first[imu_index]
    changed = copy.deepcopy(imu)
    changed.linear_acceleration.x += 1e-4
    altered = first[:imu_index] + [(topic, stamp, changed)] + first[imu_index + 1 :]
    assert 'IMU values differ' in ' '.join(recording_differences(first, altered))


def test_committed_bag_plays_over_dds(rclpy_context, processes):
    import rclpy
    from sensor_msgs.msg import Imu, PointCloud2

    from lego_loam_py.ros import qos
    from lego_loam_py.ros.conversions import cloud_msg_to_array as ros_cloud_to_array
    from lego_loam_py.ros.conversions import stamp_to_ns
    from lego_loam_py.testing.nodes import release, spin_until

    bag = next(p for p in COMMITTED if p.name.startswith('aggressive'))
    stamps, _ = sidecars.load_ground_truth(bag)
    n_imu = sidecars.load_scenario(bag)['recording']['imu_messages']
    node = rclpy.create_node('sim_listener', context=rclpy_context)
    clouds, imus = [], []
    node.create_subscription(PointCloud2, '/velodyne_points', clouds.append, qos.reliable(100))
    node.create_subscription(Imu, '/imu/data', imus.append, qos.reliable(2000))
    player = processes.start([CLI, 'play', str(bag), '--rate', '4', '--wait-for-subscribers', '20', '--no-progress'])
    done = spin_until(
        rclpy_context,
        node,
        lambda: len(clouds) == len(stamps) and len(imus) == n_imu and player.poll() is not None,
        timeout=90,
    )
    _, err = player.communicate(timeout=10)
    assert done, f'clouds {len(clouds)}/{len(stamps)}, imu {len(imus)}/{n_imu}: {err}'
    assert [stamp_to_ns(m.header.stamp) for m in clouds] == stamps.tolist()
    points = ros_cloud_to_array(clouds[5])
    labels = sidecars.load_labels(bag)
    assert len(points) == len(labels[5]) and set(points.dtype.names) >= {'x', 'y', 'z', 'intensity', 'ring', 'time'}
    assert imus[0].header.frame_id == 'imu_link' and abs(imus[0].linear_acceleration.z - GRAVITY) < 1.0
    release(node)


def test_map_distance_to_scene_places_the_map_with_the_estimated_first_pose():
    """Surface points seen from the first pose, expressed in a 'map' frame where that pose is a known
    transform, are on the scene (distance ~0); the same points with a pose that is 1 m off are not."""
    world = build_world('campus', 0)
    world_from_lidar = world.trajectory.matrices(np.array([2.0]))[0]
    azimuth = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    directions = np.column_stack([np.cos(azimuth), np.sin(azimuth), np.full(720, -0.15)])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    directions = directions @ world_from_lidar[:3, :3].T
    origins = np.repeat(world_from_lidar[None, :3, 3], 720, axis=0)
    distance = world.scene.cast(origins, directions)[0]
    hits = origins + directions * distance[:, None]
    hits = hits[np.isfinite(hits).all(axis=1)]
    lidar_in_map = np.eye(4)
    lidar_in_map[:3, :3] = Rotation.from_euler('z', 30, degrees=True).as_matrix()
    lidar_in_map[:3, 3] = [5.0, -2.0, 0.3]
    map_from_world = lidar_in_map @ np.linalg.inv(world_from_lidar)
    in_map = hits @ map_from_world[:3, :3].T + map_from_world[:3, 3]
    stamp = START_STAMP_NS + 2_000_000_000
    assert np.median(sim_output.map_distance_to_scene(BAGS / 'campus_8s', in_map, stamp, lidar_in_map)) < 1e-3
    shifted = lidar_in_map.copy()
    shifted[:3, 3] += [0.0, 0.0, 1.0]
    assert np.median(sim_output.map_distance_to_scene(BAGS / 'campus_8s', in_map, stamp, shifted)) > 0.3
    assert sim_output.map_distance_to_scene(REPO / 'tests', in_map, stamp, lidar_in_map) is None
