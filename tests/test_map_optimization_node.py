"""The mapOptimization node in this process, fed featureAssociation's outputs for the first 3 s of the campus:
what it reports about each mapping step, and its occupancy grid on /map."""

from __future__ import annotations

import numpy as np
import pytest

from lego_loam_py.testing.messages import restamped, stamp_of
from tests.support.inprocess import make_node, mapping_inputs, pipeline_outputs


def map_campus(context, tmp_path, **overrides):
    """(node, recorder) after every campus mapping input went through a mapOptimization node."""
    from lego_loam_py.ros.map_optimization_node import MapOptimizationNode

    outputs = pipeline_outputs(context, tmp_path)
    node, recorder = make_node(context, MapOptimizationNode, tmp_path, **overrides)
    for parts in mapping_inputs(outputs):
        stamp = stamp_of(parts[0])
        for name, msg in zip(('corner', 'surf', 'outlier', 'odometry'), parts):
            node.on_part(name, restamped(msg, stamp))
    return node, recorder


def test_each_mapping_step_reports_how_well_the_map_held_it(context, tmp_path):
    """The condition of every registration (smallest eigenvalue of its normal matrix: the full-weight
    correspondences holding the worst direction) is in the statistics and on /diagnostics; the campus holds
    every direction with hundreds of them, so no step is degenerate. A threshold above that makes every
    registration degenerate: counted and warned about (the log throttles the repeats)."""
    node, recorder = map_campus(context, tmp_path)
    steps = node.counters['mapping_steps']
    measures = node.statistics()['measures']
    assert steps >= 4
    # The first step has no map to register against: no condition.
    assert measures['condition']['count'] == steps - 1 and measures['condition']['median'] > 100
    keys = {value.key: value.value for value in node.diagnostic_status().values}
    assert float(keys['condition_last']) > 100 and float(keys['condition_median']) > 100
    assert 'degenerate' not in node.counters and not any(key == 'degenerate' for key, _ in recorder.warnings)
    node.destroy_node()

    node, recorder = map_campus(context, tmp_path, **{'map_optimization.degeneracy_threshold': 1e9})
    assert node.counters['mapping_degenerate'] == node.counters['mapping_steps'] - 1
    warnings = [text for key, text in recorder.warnings if key == 'degenerate']
    assert len(warnings) == node.counters['mapping_degenerate']  # (the recorder sees every call; the log is throttled)
    assert 'held by fewer than 1e+09 correspondences' in warnings[0]
    node.destroy_node()


def grid_listener(context, name: str):
    """A node subscribed to /map as nav2's map users are (transient local, reliable): (node, received messages)."""
    from nav_msgs.msg import OccupancyGrid
    from rclpy.node import Node

    from lego_loam_py.ros import qos

    node = Node(name, context=context)
    received = []
    node.create_subscription(OccupancyGrid, '/map', received.append, qos.latched())
    return node, received


def test_the_occupancy_grid_is_kept_current_and_latched_on_map_for_a_late_subscriber(context, tmp_path):
    """/map (nav_msgs/OccupancyGrid, frame map): the grid follows the keyframes on the worker without anyone
    subscribed, and nothing is converted or published then; once subscribed, the worker publishes it (once per change);
    a subscriber that comes after that receives the published grid from the latched topic; the save writes the same
    grid as nav2 map_server files."""
    from lego_loam_py.core.mapping import FREE, OCCUPIED, UNKNOWN, read_occupancy_files
    from lego_loam_py.testing.nodes import spin_until

    node, recorder = map_campus(context, tmp_path, **{'occupancy_grid.publish_period': 0.01})
    node.grid_updates.request().result(timeout=60)  # (the updates the keyframes asked for are done with this one)
    keyframes = node.counters['keyframes']
    assert keyframes >= 3 and node.grid.keyframes_added == keyframes and node.grid.version >= 1
    assert recorder.out('/map') == [] and 'occupancy_grids_published' not in node.counters  # (nobody listens)
    first, first_received = grid_listener(context, 'first_map_listener')
    assert spin_until(context, first, lambda: node.pub_grid.get_subscription_count() == 1, 10.0)
    node.grid_updates.request().result(timeout=60)
    assert len(recorder.out('/map')) == 1 and node.counters['occupancy_grids_published'] == 1
    msg = recorder.out('/map')[0]
    expected = node.grid.ternary()
    assert msg.header.frame_id == 'map' and msg.info.resolution == pytest.approx(0.1, abs=1e-6)  # (float32 field)
    assert (msg.info.width, msg.info.height) == (expected.width, expected.height)
    assert (msg.info.origin.position.x, msg.info.origin.position.y) == pytest.approx(expected.origin, abs=1e-9)
    assert msg.info.origin.orientation.w == 1.0
    cells = np.frombuffer(bytes(msg.data), np.int8).reshape(msg.info.height, msg.info.width)
    assert np.array_equal(cells, expected.cells) and set(np.unique(cells)) == {OCCUPIED, FREE, UNKNOWN}
    assert spin_until(context, first, lambda: len(first_received) == 1, 10.0)
    node.grid_updates.request().result(timeout=60)  # (no change: nothing new goes out)
    assert len(recorder.out('/map')) == 1
    late, late_received = grid_listener(context, 'late_map_listener')
    assert spin_until(context, late, lambda: len(late_received) == 1, 10.0), 'the latched grid did not reach it'
    assert bytes(late_received[0].data) == bytes(msg.data) and len(recorder.out('/map')) == 1
    success, _ = node._save_now()
    saved = read_occupancy_files(tmp_path / 'occupancy.yaml')
    assert success and np.array_equal(saved.cells, expected.cells)
    for listener in (first, late):
        listener.destroy_node()
    node.destroy_node()


def test_a_failing_occupancy_grid_is_a_warning_and_a_counter_and_mapping_goes_on(context, tmp_path):
    node, recorder = map_campus(context, tmp_path)
    node.grid_updates.request().result(timeout=60)

    def broken(keyframes):
        raise ValueError('occupancy grid: a test broke it')

    node.grid.sync = broken
    node.grid_updates.request().result(timeout=60)  # (the worker never raises)
    assert node.counters['occupancy_grid_failures'] == 1
    assert [key for key, _ in recorder.warnings if key == 'occupancy_grid'] == ['occupancy_grid']
    assert 'a test broke it' in recorder.warnings[-1][1] and not recorder.errors
    steps = node.counters['mapping_steps']
    outputs = pipeline_outputs(context, tmp_path)
    parts = mapping_inputs(outputs)[-1]
    stamp = stamp_of(parts[0]) + 10**9  # (one more input, a second later: still mapped)
    for name, msg in zip(('corner', 'surf', 'outlier', 'odometry'), parts):
        node.on_part(name, restamped(msg, stamp))
    assert node.counters['mapping_steps'] == steps + 1
    node.destroy_node()


def test_localization_publishes_the_saved_maps_grid(context, tmp_path):
    """In map_optimization.mode localization /map is the grid of the saved map (its occupancy files)."""
    from lego_loam_py.core.mapping import read_occupancy_files
    from lego_loam_py.ros.map_optimization_node import MapOptimizationNode
    from lego_loam_py.testing.nodes import spin_until

    mapper, _ = map_campus(context, tmp_path)
    assert mapper._save_now()[0]
    mapper.destroy_node()
    saved = read_occupancy_files(tmp_path / 'occupancy.yaml')
    node, recorder = make_node(
        context,
        MapOptimizationNode,
        tmp_path / 'unused',
        **{'map_optimization.mode': 'localization', 'map_optimization.map_path': str(tmp_path)},
    )
    assert node.grid is None
    listener, received = grid_listener(context, 'localization_map_listener')
    assert spin_until(context, listener, lambda: node.pub_grid.get_subscription_count() == 1, 10.0)
    node.grid_updates.request().result(timeout=60)
    assert spin_until(context, listener, lambda: len(received) == 1, 10.0)
    cells = np.frombuffer(bytes(received[0].data), np.int8).reshape(received[0].info.height, received[0].info.width)
    assert np.array_equal(cells, saved.cells) and received[0].header.frame_id == 'map'
    listener.destroy_node()
    node.destroy_node()


def occupied_cells(grid) -> set[tuple[int, int]]:
    """The lattice indices (x, y) of a grid's occupied cells in the map frame."""
    return {tuple(c) for c in np.round(grid.cell_centres() / grid.resolution - 0.5).astype(int).tolist()}


def test_the_grid_is_redrawn_from_the_corrected_poses_after_a_loop_closure(context, tmp_path):
    """A stiff loop factor 1 m off the mapped relative pose of the newest and the first keyframe bends the
    trajectory (the poses move, as after a loop closure); the next grid update redraws every keyframe at its
    corrected pose: the obstacles of a grid drawn afresh from them, not those of before."""
    from lego_loam_py.core.frames import pose6_to_matrix
    from lego_loam_py.core.mapping import OccupancyGrid

    node, _ = map_campus(context, tmp_path)
    node.grid_updates.request().result(timeout=60)
    before = node.grid.ternary()
    core = node.core
    first, last = core.keyframes[0], core.keyframes[-1]
    newest_before = last.pose6.copy()
    # The first keyframe seen from the newest, 1 m further along camera x (the map's y) than mapped.
    relative = np.linalg.inv(pose6_to_matrix(last.pose6)) @ pose6_to_matrix(first.pose6)
    relative[0, 3] += 1.0
    core.add_loop_factor(last.index, first.index, relative, np.array([1e-12, 1e-12, 1e-12, 1e-12, 1e-12, 1e-12]))
    assert np.linalg.norm(core.keyframes[-1].pose6[3:] - newest_before[3:]) > 0.1  # (the poses did move)
    node.grid_updates.request().result(timeout=60)
    assert node.grid.redraws == 1
    redrawn = node.grid.ternary()
    fresh = OccupancyGrid(node.params.occupancy_grid)
    fresh.sync(core.keyframes_now())
    fresh = fresh.ternary()
    # The obstacles where a grid drawn afresh from the corrected keyframes has them, to the cell but for a few: the
    # redraw reuses each keyframe's ground classification, made with an up axis less than reclassify_tilt_deg away
    # (2 of 1127 occupied cells differ on this input); most are not where they were before the correction.
    redrawn_cells, fresh_cells, before_cells = occupied_cells(redrawn), occupied_cells(fresh), occupied_cells(before)
    assert len(redrawn_cells) > 500 and len(redrawn_cells ^ fresh_cells) <= 0.01 * len(fresh_cells)
    assert len(redrawn_cells & before_cells) < 0.5 * len(redrawn_cells)
    assert abs(redrawn.counts()['free'] - fresh.counts()['free']) <= 0.01 * fresh.counts()['free']
    node.destroy_node()


_FIRST_INPUT = """
import json, sys
import rclpy
from sensor_msgs.msg import PointCloud2

from lego_loam_py.ros.map_optimization_node import MapOptimizationNode

rclpy.init()
node = MapOptimizationNode()
waiting = 'gtsam' in sys.modules
subscription = next(s for s in node.subscriptions if s.topic_name == '/laser_cloud_corner_last')
subscription.callback(PointCloud2())  # the first input (an empty cloud: dropped with a warning, as any bad input)
thread = node.deferred_imports
thread.join(60)
subscription.callback(PointCloud2())
print(json.dumps({'waiting': waiting, 'after': 'gtsam' in sys.modules, 'same': node.deferred_imports is thread}))
node.destroy_node()
rclpy.shutdown()
"""


def test_the_pose_graph_library_is_imported_with_the_first_input_not_at_start_up(ros_domain):
    """gtsam (0.1 s of CPU to import) is loaded on a thread when the first message arrives, once: a node waiting
    for data has not paid for it (benchmarks/bench_startup.py)."""
    import json
    import subprocess
    import sys

    done = subprocess.run([sys.executable, '-c', _FIRST_INPUT], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    assert seen == {'waiting': False, 'after': True, 'same': True}
