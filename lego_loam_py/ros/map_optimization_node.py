"""The ``mapOptimization`` node: scan-to-map refinement, keyframe pose graph, loop closure, saved maps.

Subscribes /laser_cloud_corner_last, /laser_cloud_surf_last, /outlier_cloud_last (reliable, depth 2),
/laser_odom_to_init (depth 5), synchronised by stamp within ``map_optimization.sync_tolerance``, and
/imu/data for the roll/pitch blend (not used while the IMU check finds it disagrees with the mapped poses, see
:mod:`lego_loam_py.core.imu.monitor`). Processes at most every ``mapping_process_interval`` and publishes:

* /aft_mapped_to_init (nav_msgs/Odometry, camera_init -> aft_mapped) and its TF; as in the original its
  twist fields carry the odometry pose the step started from (angular = rx, ry, rz; linear = tx, ty, tz),
  which transformFusion needs;
* while subscribed: /key_pose_origin (keyframe positions, intensity = index), /recent_cloud (surface map
  around the robot), /registered_cloud (the current scan in the map), /laser_cloud_surround (global map,
  every ``global_map_publish_period`` s), /history_cloud and /corrected_cloud (loop closure);
* /loop_closures (visualization_msgs/MarkerArray, latched): a line between the two keyframes of every accepted
  loop and a sphere at each end, at their current optimised positions (camera_init), for RViz;
* /map (nav_msgs/OccupancyGrid, latched: transient local, reliable, depth 1; frame ``map``) with
  ``occupancy_grid.enabled``: the 2D occupancy grid for nav2 (:mod:`lego_loam_py.core.mapping.occupancy_grid`),
  kept current on a worker thread of its own (each new keyframe added, everything redrawn from the corrected poses
  after a loop closure) and published at most every ``occupancy_grid.publish_period`` s while subscribed; in
  localization, the saved map's grid (its occupancy files, or drawn from its keyframes). A failure of the grid is
  a throttled warning and the counter ``occupancy_grid_failures``; mapping goes on.

Loop closure (``loop_closure.loop_closure_enable_flag``) runs every ``loop_closure.period`` s on a worker
thread of its own, so the ICP does not hold up the mapping steps. The service ``save_map``
(std_srvs/Trigger) and the shutdown hook write the maps and the keyframe trajectory to
``map_optimization.file_directory``, also on a worker thread (see :mod:`lego_loam_py.ros.services`). The IMU
samples are taken with each mapping input (a polled subscription: no wake-up per sample).

With ``map_optimization.mode: localization`` the core is :class:`~lego_loam_py.core.localization.localizer.Localization`
in the saved map of ``map_optimization.map_path`` (never modified; no loop closure, no map saved): the same topics come
out, in that map's frame, once a place is verified; /initialpose and /localization_status are
:mod:`lego_loam_py.ros.localization`'s.

Robustness: inputs older than the previous ones are dropped; a jump of more than a second is believed once
later inputs continue the new timeline (forward the next one, back three in a row). Back to before the current
timeline began (a bag restarted or looped) the map built so far is saved, then mapping starts afresh (the IMU
samples stay). An odometry that jumps further
than any vehicle moves between two inputs (featureAssociation restarted or reset) is re-anchored at the last
optimised pose instead of dragging the map along. Inputs with non-finite or absurd values are dropped with a
throttled warning; a mapping step that fails or yields a non-finite pose is skipped and the map is kept.
"""

from __future__ import annotations

import dataclasses
import sys
import threading
import time

import numpy as np
from nav_msgs.msg import OccupancyGrid as OccupancyGridMsg
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from lego_loam_py.core import validation
from lego_loam_py.core.frames import (
    AFT_MAPPED_FRAME,
    CAMERA_INIT_FRAME,
    matrix_to_pose6,
    pose6_to_matrix,
    transform_cloud,
)
from lego_loam_py.core.guard import (
    KEYFRAMES,
    MAPPING_DEGENERATE,
    MAPPING_STEPS,
    MAPPING_STEPS_FAILED,
    ODOMETRY_RESTARTS,
)
from lego_loam_py.core.mapping.map_optimization import MapOptimization
from lego_loam_py.core.mapping.occupancy_grid import OccupancyGrid, TernaryGrid, message_fields
from lego_loam_py.core.mapping.odometry_continuity import OdometryContinuity
from lego_loam_py.ros import qos
from lego_loam_py.ros.coalescing import CoalescingRunner
from lego_loam_py.ros.conversions import (
    cloud_msg_to_xyzi,
    make_header,
    occupancy_grid_msg,
    odometry_covariance,
    odometry_to_pose,
    serialized_odometry,
    serialized_stamp_ns,
    serialized_xyzi_cloud,
    stamp_to_ns,
)
from lego_loam_py.ros.localization import LocalizationFrontEnd
from lego_loam_py.ros.node_base import LegoLoamNode
from lego_loam_py.ros.runtime import run_node
from lego_loam_py.ros.services import create_deferred_service
from lego_loam_py.ros.sync import StampOrder, StampSynchronizer
from lego_loam_py.ros.tf import TransformBroadcaster

__all__ = ['MapOptimizationNode', 'main']

RESET_JUMP_NS = 1_000_000_000
IMU_QUEUE_DEPTH = 200  # IMU samples kept between two mapping inputs (1 s at 200 Hz)
MAP_FILE_STEMS = ('global_map', 'corner_map', 'surface_map', 'trajectory', 'trajectory_camera_init', 'occupancy')
INPUT_TOPICS = {
    'corner': '/laser_cloud_corner_last',
    'surf': '/laser_cloud_surf_last',
    'outlier': '/outlier_cloud_last',
    'odometry': '/laser_odom_to_init',
}


class MapOptimizationNode(LegoLoamNode):
    POLL_CLOCK = False  # the global map and loop-closure timers run on ROS time: every /clock tick counts

    def __init__(self, **kwargs):
        super().__init__('mapOptimization', **kwargs)
        mo, lc = self.params.map_optimization, self.params.loop_closure
        self.localization = LocalizationFrontEnd(self) if mo.mode == 'localization' else None
        # (In localization, None until the saved map could be loaded.)
        self.core = MapOptimization(self.params) if self.localization is None else self.localization.core
        self.sync = StampSynchronizer(['corner', 'surf', 'outlier', 'odometry'], int(mo.sync_tolerance * 1e9))
        depth2 = qos.reliable(2)
        # Serialized clouds, read from their bytes (cloud_from_serialized).
        for name in ('corner', 'surf', 'outlier'):
            self.create_subscription(
                PointCloud2, INPUT_TOPICS[name], lambda m, name=name: self.on_part(name, m), depth2, raw=True
            )
        self.create_subscription(Odometry, '/laser_odom_to_init', self._on_odometry_message, qos.reliable(5), raw=True)
        # The same topic again, serialized and polled, for the publisher of each message (the executor's callbacks
        # get no message info): a restarted featureAssociation is another publisher.
        self._odometry_senders = self.create_polled_subscription(
            Odometry, '/laser_odom_to_init', qos.reliable(20), raw=True
        )
        self.imu_subscription = None
        if self.params.sensor.imu_topic:  # taken with each mapping input (1 s of samples wait at 200 Hz)
            self.imu_subscription = self.create_polled_subscription(
                Imu, self.params.sensor.imu_topic, qos.sensor_input(IMU_QUEUE_DEPTH), raw=True
            )
        self.pub_aft_mapped = self.create_publisher(Odometry, '/aft_mapped_to_init', qos.reliable(5))
        self.tf = TransformBroadcaster(self)
        self.pub_key_poses = self.create_publisher(PointCloud2, '/key_pose_origin', depth2)
        self.pub_surround = self.create_publisher(PointCloud2, '/laser_cloud_surround', depth2)
        self.pub_recent = self.create_publisher(PointCloud2, '/recent_cloud', depth2)
        self.pub_registered = self.create_publisher(PointCloud2, '/registered_cloud', depth2)
        self.pub_history = self.create_publisher(PointCloud2, '/history_cloud', depth2)
        self.pub_corrected = self.create_publisher(PointCloud2, '/corrected_cloud', depth2)
        self.pub_loops = self.create_publisher(MarkerArray, '/loop_closures', qos.latched())
        self._loops_counted = 0  # accepted loops counted so far (a verified loop may be accepted later)
        # Saves run on a worker thread, one at a time; callers during a save share the next one (see services.py).
        self.saves = CoalescingRunner(self._save_now, 'save_map')
        create_deferred_service(self, Trigger, 'save_map', self._save_requested, _fill_save_response)
        self.order = StampOrder(RESET_JUMP_NS)
        self.continuity = OdometryContinuity()  # the odometry poses taken, to see a restarted odometry
        self._odometry_publisher: dict[int, object] = {}  # stamp -> publisher of recent odometry messages
        self.last_step_stamp = None
        self.create_timer(mo.global_map_publish_period, self.publish_global_map)
        # Loop closure (an ICP can take seconds) on a worker thread of its own, so that mapping steps go on; the
        # timer only wakes it (the original's 1 Hz thread).
        self._loop_wanted = threading.Event()
        self._stopping = threading.Event()
        if lc.loop_closure_enable_flag and self.localization is None:
            self.create_timer(lc.period, self._loop_wanted.set)
            threading.Thread(target=self._loop_worker, name='loop closure', daemon=True).start()
        self._setup_occupancy_grid()
        self._remove_stale_temporaries()
        if self.localization is None:
            self.get_logger().info(
                f'mapOptimization: every {mo.mapping_process_interval} s, loop closure '
                f'{"on" if lc.loop_closure_enable_flag else "off"}, maps saved to {mo.file_directory}'
            )

    def _setup_occupancy_grid(self) -> None:
        """/map and the worker that keeps the grid current (mapping) or loads the saved map's (localization)."""
        og = self.params.occupancy_grid
        self.grid: OccupancyGrid | None = None  # (mapping: drawn from the keyframes; None in localization)
        self.pub_grid = None
        if not og.enabled:
            return
        if self.localization is None:
            self.grid = OccupancyGrid(og)
        self._saved_grid: TernaryGrid | None = None  # (localization: the saved map's, once read)
        self._saved_grid_tried = False
        self._grid_published: tuple | None = None  # (grid, version) last published
        self._grid_published_at = -float('inf')  # [s, monotonic]
        self.pub_grid = self.create_publisher(OccupancyGridMsg, '/map', qos.latched())
        self.grid_updates = CoalescingRunner(self._update_grid, 'occupancy_grid')
        self.create_timer(og.publish_period, self._grid_timer)

    def _grid_timer(self) -> None:
        """Every publish_period: the worker publishes what changed meanwhile, if anyone listens (a late subscriber
        of a grid nobody wanted before gets it now)."""
        if self.pub_grid.get_subscription_count() and (self.localization is not None or self.core.keyframes):
            self.grid_updates.request()

    def _update_grid(self) -> None:
        """The grid worker: bring the grid to the keyframes (or read the saved map's), then publish it when due.
        Never raises: a failure is counted and warned about, and the map goes on."""
        start = time.perf_counter()
        try:
            if self.grid is not None:
                core, grid = self.core, self.grid
                if core is not None and core.builds_map:
                    grid.sync(core.keyframes_now())
            elif not self._saved_grid_tried:
                self._saved_grid_tried = True  # (once: a map without grid or keyframes will not get one)
                from lego_loam_py.core.mapping.occupancy_files import saved_occupancy_grid

                self._saved_grid = saved_occupancy_grid(
                    self.params.map_optimization.map_path, self.params.occupancy_grid
                )
        except Exception as exc:
            self.count('occupancy_grid_failures')
            self.warn('occupancy_grid', f'the occupancy grid could not be updated ({exc}); mapping goes on')
            return
        self.record_time('occupancy_grid', time.perf_counter() - start)
        try:
            self._publish_grid()
        except Exception as exc:
            self.count('occupancy_grid_failures')
            self.warn('occupancy_grid', f'the occupancy grid could not be published ({exc}); mapping goes on')

    def _publish_grid(self) -> None:
        """/map, when someone subscribes, the grid changed since it was last published and publish_period passed
        (on the grid worker; its failures are the worker's to report)."""
        if self.pub_grid.get_subscription_count() == 0:
            return
        grid = self.grid if self.grid is not None else self._saved_grid
        if grid is None:
            return
        version = (id(grid), grid.version if isinstance(grid, OccupancyGrid) else 0)
        now = time.monotonic()
        if version == self._grid_published or now - self._grid_published_at < self.params.occupancy_grid.publish_period:
            return
        if isinstance(grid, OccupancyGrid):
            with grid.lock:  # (the version of the cells taken)
                version = (id(grid), grid.version)
                ternary = grid.ternary()
        else:
            ternary = grid
        if ternary.width == 0 or ternary.height == 0:  # (nothing seen yet)
            return
        stamp = self.last_step_stamp if self.last_step_stamp is not None else self.get_clock().now().to_msg()
        fields = dataclasses.replace(message_fields(ternary), frame_id=self.params.frames.map_frame)
        self.pub_grid.publish(occupancy_grid_msg(fields, stamp))
        self._grid_published, self._grid_published_at = version, now
        self.count('occupancy_grids_published')

    def _remove_stale_temporaries(self) -> None:
        """A predecessor killed while saving left temporary files (its saved files are complete): remove them."""
        from lego_loam_py.formats import remove_stale_temporaries

        removed = remove_stale_temporaries(self.params.map_optimization.file_directory, stems=MAP_FILE_STEMS)
        if removed:
            self.get_logger().info(
                f'removed {len(removed)} temporary file(s) of an interrupted save in '
                f'{self.params.map_optimization.file_directory}'
            )

    # ------------------------------------------------------------------------------------------ inputs
    def on_part(self, name: str, msg, decoded=None) -> None:
        """One of the four inputs: checked on its own (size first, then content) before it may join a set, so
        that a bad message can never take a valid input's place among its partners."""
        if decoded is None and name == 'odometry':
            self.on_odometry(msg, None)
            return
        ok, msg = self.take_cloud(msg, 'inputs_dropped', f'{INPUT_TOPICS[name]} dropped unread', 'bad_input')
        if not ok:
            return
        if decoded is None:
            # A cloud derived from the range image holds at most one point per pixel: anything bigger is rejected
            # on its header, before it is decoded.
            ok, _ = self.take(
                lambda: validation.check_count(
                    f'{INPUT_TOPICS[name]} points',
                    int(msg.width) * int(msg.height),
                    validation.derived_points_limit(self.params),
                    'pixels of the range image',
                ),
                'inputs_dropped',
                'mapping input dropped unread',
                'oversized',
                msg,
            )
            if not ok:
                return
            ok, decoded = self.take(lambda: self._decode_cloud(name, msg), 'inputs_dropped', 'mapping input dropped')
            if not ok:
                return
        complete = self.add_part(self.sync, name, msg, item=(msg, decoded))
        if complete is not None:
            self.on_inputs(complete)

    def _decode_cloud(self, name: str, msg):
        cloud = cloud_msg_to_xyzi(msg)
        validation.check_cloud(INPUT_TOPICS[name], cloud)
        return cloud

    def _on_odometry_message(self, msg: Odometry | bytes) -> None:
        self.drain(self._odometry_senders, self._note_sender, with_info=True, count=False)
        ok, msg = self.take_odometry(msg, 'inputs_dropped', 'mapping input dropped', 'bad_input')
        if not ok:
            return
        self.on_odometry(msg, {'publisher_gid': self._odometry_publisher.get(stamp_to_ns(msg.header.stamp))})

    def _note_sender(self, data: bytes, info) -> None:
        """Which publisher sent the odometry of a stamp (from the serialized message's header)."""
        gid = info.get('publisher_gid') if isinstance(info, dict) else None
        sender = gid.get('data') if isinstance(gid, dict) else gid
        stamp = serialized_stamp_ns(data)
        if sender is None or stamp is None:
            return
        self._odometry_publisher[stamp] = bytes(sender)
        while len(self._odometry_publisher) > 64:
            self._odometry_publisher.pop(next(iter(self._odometry_publisher)))

    def on_odometry(self, msg: Odometry | bytes, info=None) -> None:
        """/laser_odom_to_init (or its bytes); the publisher's id tells a restarted featureAssociation (a new
        odometry frame)."""
        ok, msg = self.take_odometry(msg, 'inputs_dropped', 'mapping input dropped', 'bad_input')
        if not ok:
            return
        ok, pose = self.take(lambda: odometry_to_pose(msg), 'inputs_dropped', 'mapping input dropped')
        if not ok:
            return
        gid = info.get('publisher_gid') if isinstance(info, dict) else None
        if gid is not None:
            data = gid.get('data') if isinstance(gid, dict) else gid
            self._odometry_publisher[stamp_to_ns(msg.header.stamp)] = bytes(data) if data is not None else None
            while len(self._odometry_publisher) > 64:
                self._odometry_publisher.pop(next(iter(self._odometry_publisher)))
        self.on_part('odometry', msg, pose)

    def on_imu(self, msg) -> None:
        """A sensor_msgs/Imu, or its serialized bytes (see :meth:`LegoLoamNode.take_imu`)."""
        if self.core is not None:
            self.take_imu(msg, self.core.imu.add)

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the last input processed [ns]."""
        return self.order.last_ns

    def on_inputs(self, parts: dict) -> None:
        self.count('inputs_in')
        self.drain(self.imu_subscription, self.on_imu)  # the IMU samples up to this input first
        stamp = stamp_to_ns(parts['odometry'][0].header.stamp)
        decision = self.check_order(
            self.order,
            stamp,
            parts,
            lambda held: stamp_to_ns(held['odometry'][0].header.stamp),
            'input',
            'inputs_dropped',
        )
        if decision is None:
            return
        if decision.action == 'reset':
            self._reset_after_time_jump(-decision.jump_ns)
        for held in decision.held:
            self._process(held)
        self._process(parts)

    def _process(self, parts: dict) -> None:
        """One synchronised input: each part is (message, decoded content), checked on arrival."""
        if self.localization is not None and self.core is None:
            self.core = self.localization.core  # (loaded meanwhile, or still None: no map, no output)
            if self.core is None:
                self.count('inputs_without_map')
                return
        start = time.perf_counter()
        odometry, odometry_pose = parts['odometry']
        stamp = stamp_to_ns(odometry.header.stamp)
        transform_sum = matrix_to_pose6(odometry_pose)
        clouds = {name: parts[name][1] for name in ('corner', 'surf', 'outlier')}
        self.order.processed(stamp)
        self._check_odometry_continuity(stamp, odometry_pose, transform_sum, self._odometry_publisher.get(stamp))
        try:
            step = self.core.process(
                stamp,
                transform_sum,
                clouds['corner'],
                clouds['surf'],
                clouds['outlier'],
                odometry_covariance=odometry_covariance(odometry),
            )
        except Exception:
            self.input_valid()
            self.count(MAPPING_STEPS_FAILED)
            self.error('process_exception', 'unexpected error in mapOptimization; step skipped, map kept')
            heal = self.guard.after_failure(self.core.health_problem())
            if heal is not None:
                self._heal(heal)
            return
        if step is None and self.localization is not None and self.core.withheld:
            self.count('steps_not_localized')  # (no fix in the saved map: nothing to publish, and it says so)
            self.localization.after_step(published=False)
            return
        if step is None:  # (not due: the original maps every mapping_process_interval; no output expected)
            self.count('inputs_skipped_by_interval')
            return
        self.input_valid()
        heal = self.guard.after_step(self.core.health_problem())
        if heal is not None:
            self.count(MAPPING_STEPS_FAILED)
            self._heal(heal)
            return
        self.count(MAPPING_STEPS)
        if step.keyframe_added:
            self.count(KEYFRAMES)
        self._report_conditioning(step)
        self.report_imu_alignment(step.imu_alignment)
        self._publish(step, odometry.header.stamp)
        if step.keyframe_added and self.grid is not None:
            self.grid_updates.request()
        self.output_published()
        self.record_time('step', time.perf_counter() - start)
        if self.localization is not None:
            self.localization.after_step(published=True)

    def _report_conditioning(self, step) -> None:
        """How well the step held the map pose: its condition (smallest eigenvalue of the registration's normal
        matrix, in full-weight correspondences) in the statistics and on /diagnostics, a counter of degenerate
        steps and a throttled warning for them."""
        if step.condition == step.condition:  # NaN: no registration (no map yet, too few correspondences)
            self.record_value('condition', step.condition)
        if step.degenerate:
            self.count(MAPPING_DEGENERATE)
            self.warn(
                'degenerate',
                'scan-to-map: a direction is held by fewer than '
                f'{self.params.map_optimization.degeneracy_threshold:g} correspondences (degenerate '
                'surroundings, e.g. a featureless tunnel); the odometry is kept along it',
            )

    def _heal(self, problem: str) -> None:
        """The mapping state is poisoned: reset what is, keep the map and the trajectory."""
        done = self.core.heal()
        self.continuity.forget()
        self.state_reset(problem, done)
        if self.grid is not None:  # (keyframes may have been dropped: the grid is redrawn without them)
            self.grid_updates.request()

    def _check_odometry_continuity(
        self, stamp: int, pose: np.ndarray, transform_sum: np.ndarray, publisher=None
    ) -> None:
        """Re-anchor when the odometry restarted (see :mod:`lego_loam_py.core.mapping.odometry_continuity`)."""
        jump = self.continuity.check(stamp, pose, publisher)
        if jump is not None:
            self.count(ODOMETRY_RESTARTS)
            self.warn('odometry_jump', jump.describe(), period=0.0)
            self.core.reanchor(jump, pose, transform_sum)

    def _reset_after_time_jump(self, jump_ns: int) -> None:
        """A bag restarted: keep the map built so far on disk, then start a new one (the IMU samples stay)."""
        mo = self.params.map_optimization
        jump = jump_ns * 1e-9
        if self.localization is not None:  # the saved map stays; where the robot is must be found again
            self.warn('reset', f'time jumped back by {jump:.1f} s (bag restarted?): relocalizing', period=0.0)
            if self.core is not None:
                self.core.restart()
            self.order.reset()
            self.continuity.forget()
            self.count('resets')
            return
        saved = ''
        if self.core.builds_map and self.core.keyframes and mo.save_map_on_shutdown:
            try:
                self.core.save(mo.file_directory)
                saved = f'; the previous map was saved to {mo.file_directory}'
            except Exception as exc:
                saved = f'; saving the previous map failed: {exc}'
        self.warn('reset', f'time jumped back by {jump:.1f} s (bag restarted?): mapping reset{saved}', period=0.0)
        imu = self.core.imu
        self.core = MapOptimization(self.params)
        self.core.imu = imu
        if self.grid is not None:  # (a new map, a new grid)
            self.grid = OccupancyGrid(self.params.occupancy_grid)
        self.order.reset()
        self.continuity.forget()
        self.count('resets')

    # ----------------------------------------------------------------------------------------- outputs
    def _publish(self, step, stamp) -> None:
        pose = pose6_to_matrix(step.transform_aft)
        header = make_header(stamp, CAMERA_INIT_FRAME)
        bef = step.transform_bef
        odometry, transform = serialized_odometry(
            pose,
            header,
            AFT_MAPPED_FRAME,
            twist_angular=bef[:3],
            twist_linear=bef[3:],
            pose_covariance=step.pose_covariance,
        )
        self.pub_aft_mapped.publish(odometry)
        self.tf.send_serialized(transform)
        self.last_step_stamp = stamp
        if self.pub_key_poses.get_subscription_count():
            poses = self.core.keyframe_poses()
            key = np.concatenate([poses[:, 3:], np.arange(len(poses))[:, None]], axis=1)
            self.pub_key_poses.publish(serialized_xyzi_cloud(key, header))
        if self.pub_recent.get_subscription_count():
            self.pub_recent.publish(serialized_xyzi_cloud(self.core.last_maps[1], header))
        if self.pub_registered.get_subscription_count():
            corner, surf = self.core.last_scan
            registered = transform_cloud(np.concatenate([corner, surf]), step.transform_aft)
            self.pub_registered.publish(serialized_xyzi_cloud(registered, header))

    def publish_global_map(self) -> None:
        if self.core is None or self.last_step_stamp is None or not self.pub_surround.get_subscription_count():
            return
        try:
            cloud = self.core.global_map()
        except Exception:
            self.error('global_map', 'building the global map failed')
            return
        self.pub_surround.publish(serialized_xyzi_cloud(cloud, make_header(self.last_step_stamp, CAMERA_INIT_FRAME)))

    def _loop_worker(self) -> None:
        while not self._stopping.is_set():
            if self._loop_wanted.wait(0.5):
                self._loop_wanted.clear()
                self.loop_closure()

    def loop_closure(self) -> None:
        if not self.core.builds_map:  # (localization: the saved map is not changed)
            return
        try:
            candidate = self.core.detect_loop()
            if candidate is None:
                return
            result = self.core.close_loop(candidate)
        except Exception:
            self.error('loop_exception', 'loop closure failed')
            return
        stamp = self.last_step_stamp
        if stamp is not None and self.pub_history.get_subscription_count():
            self.pub_history.publish(
                serialized_xyzi_cloud(
                    loop_cloud_in_world(candidate, self.core.loop_method, 'target'),
                    make_header(stamp, CAMERA_INIT_FRAME),
                )
            )
        accepted = sum(loop.accepted for loop in self.core.loops)
        if accepted > self._loops_counted:
            self.count('loops_closed', accepted - self._loops_counted)
            self._loops_counted = accepted
            self.get_logger().info(
                f'loop closed: keyframe {result.latest} -> {result.candidate} ({result.detector}, '
                f'fit {result.fitness:.3f}, correction {result.correction_m:.2f} m / '
                f'{result.correction_deg:.2f} deg); {accepted} loops in the graph'
            )
            self.publish_loop_markers()
            if self.grid is not None:  # (redrawn from the corrected poses)
                self.grid_updates.request()
            if stamp is not None and self.pub_corrected.get_subscription_count():
                self.pub_corrected.publish(
                    serialized_xyzi_cloud(
                        loop_cloud_in_world(candidate, self.core.loop_method, 'corrected', result),
                        make_header(stamp, CAMERA_INIT_FRAME),
                    )
                )
        if not result.accepted:
            self.count('loops_pending' if result.reason == 'pending' else 'loops_rejected')

    def publish_loop_markers(self) -> None:
        """/loop_closures: every accepted loop as a line between its keyframes' current positions."""
        with self.core.lock:
            positions = self.core.keyframe_poses()[:, 3:]
            index = {kf.stamp_ns: kf.index for kf in self.core.keyframes}
            pairs = [
                (index[loop.latest_stamp_ns], index[loop.candidate_stamp_ns])
                for loop in self.core.loops
                if loop.accepted and loop.latest_stamp_ns in index and loop.candidate_stamp_ns in index
            ]
        if self.last_step_stamp is not None:
            self.pub_loops.publish(loop_markers(make_header(self.last_step_stamp, CAMERA_INIT_FRAME), positions, pairs))

    def _save_requested(self, request):
        self.count('save_requests')
        return self.saves.request()

    def _save_now(self) -> tuple[bool, str]:
        """Write the maps and the trajectory now (the save_map service's job): (success, message)."""
        core = self.core
        directory = self.params.map_optimization.file_directory
        if self.localization is not None:
            return True, (
                f'localization: the saved map in {self.params.map_optimization.map_path} is never modified; '
                'nothing new to save'
            )
        if not core.keyframes:  # nothing to write (and the files of an earlier run stay as they are)
            return False, 'no keyframe yet: nothing to save'
        try:
            written = core.save(directory, grid=self.grid)
        except Exception as exc:  # report, never crash the node
            self.warn('save_failed', f'saving the map to {directory} failed: {exc}')
            return False, f'saving to {directory} failed: {exc}'
        if core.occupancy_problem is not None:  # (the rest of the map is saved)
            self.count('occupancy_grid_failures')
            self.warn('occupancy_grid', f'{core.occupancy_problem}; the other map files are saved')
        self.count('saves')
        return True, f'saved {len(core.keyframes)} keyframes: ' + ', '.join(str(p) for p in written.values())

    def statistics(self) -> dict:
        """The base statistics plus the size of the map held in memory (keyframe clouds)."""
        out = super().statistics()
        if self.localization is not None:
            status = self.core.status() if self.core is not None else None
            out['localization'] = (
                dict(state='no_map', error=self.localization.error)
                if status is None
                else dict(
                    status.values,
                    message=status.message,
                    events=[dict(stamp_ns=e.stamp_ns, kind=e.kind, detail=e.detail) for e in self.core.events],
                )
            )
            return out
        with self.core.lock:
            keyframes = list(self.core.keyframes)
        points = sum(len(kf.corner) + len(kf.surf) + len(kf.outlier) for kf in keyframes)
        nbytes = sum(kf.corner.nbytes + kf.surf.nbytes + kf.outlier.nbytes for kf in keyframes)
        out['map'] = dict(keyframes=len(keyframes), points=int(points), bytes=int(nbytes))
        if self.params.loop_closure.loop_closure_enable_flag and keyframes:
            from dataclasses import asdict

            from lego_loam_py.results import LoopClosures

            out['loop_closures'] = asdict(LoopClosures.of(list(self.core.loops), keyframes[0].stamp_ns))
        return out

    def diagnostic_status(self):
        """The base status plus, in localization, the state (localized, relocalizing, ... or no_map)."""
        status = super().diagnostic_status()
        if self.localization is not None:
            from diagnostic_msgs.msg import KeyValue

            state = self.core.status().state if self.core is not None else 'no_map'
            status.values.append(KeyValue(key='localization_state', value=state))
        return status

    def on_shutdown(self) -> None:
        self._stopping.set()
        mo = self.params.map_optimization
        if mo.save_map_on_shutdown and self.core.builds_map and self.core.keyframes:
            # Through the runner: a save_map call in progress finishes first, then the final map is written.
            success, message = self.saves.request().result()
            if success:
                self.get_logger().info(f'map {message}')
            else:
                self.get_logger().error(message)
        super().on_shutdown()


def loop_markers(header, positions: np.ndarray, pairs) -> MarkerArray:
    """Markers of loops (pairs of keyframe indices) between keyframe ``positions`` (K, 3, camera_init): one
    LINE_LIST (green) and one SPHERE_LIST (the keyframes, yellow); a DELETEALL first, so that the array replaces
    what was shown."""
    from geometry_msgs.msg import Point

    clear = Marker(header=header, action=Marker.DELETEALL)
    lines = Marker(header=header, ns='loop_closures', id=0, type=Marker.LINE_LIST, action=Marker.ADD)
    ends = Marker(header=header, ns='loop_closures', id=1, type=Marker.SPHERE_LIST, action=Marker.ADD)
    lines.pose.orientation.w = ends.pose.orientation.w = 1.0
    lines.scale.x = 0.3
    ends.scale.x = ends.scale.y = ends.scale.z = 1.0
    lines.color.g, lines.color.a = 1.0, 1.0
    ends.color.r, ends.color.g, ends.color.a = 1.0, 1.0, 1.0
    for a, b in pairs:
        for k in (a, b):
            x, y, z = (float(v) for v in positions[k])
            lines.points.append(Point(x=x, y=y, z=z))
            ends.points.append(Point(x=x, y=y, z=z))
    return MarkerArray(markers=[clear, lines, ends])


def loop_cloud_in_world(candidate, method, which: str, result=None) -> np.ndarray:
    """(n, 4) world points (camera_init) of a loop candidate's target map ('target') or of its source aligned by the
    registration ('corrected'), for /history_cloud and /corrected_cloud."""
    from lego_loam_py.core.frames import camera_pose_to_lidar, lidar_to_camera

    if method.clouds_in_world:  # (the original method's; the verified one's are in the keyframes' frames)
        points = candidate.target if which == 'target' else candidate.source.copy()
        if which == 'corrected':
            points[:, :3] = points[:, :3] @ result.correction[:3, :3].T + result.correction[:3, 3]
        return points
    to_world = camera_pose_to_lidar(candidate.candidate_pose)  # the verified method's are in lidar axes
    if which == 'corrected':  # the source where the registration put it: latest in the candidate's frame
        to_world = to_world @ camera_pose_to_lidar(np.linalg.inv(result.relative))
    points = candidate.target if which == 'target' else candidate.source
    world = points[:, :3] @ to_world[:3, :3].T + to_world[:3, 3]
    return np.concatenate([lidar_to_camera(world), np.zeros((len(world), 1))], axis=1).astype(np.float32)


def _fill_save_response(response, finished) -> None:
    try:
        response.success, response.message = finished.result()
    except Exception as exc:  # (_save_now reports its own failures; this is a bug in it)
        response.success, response.message = False, f'saving failed: {exc!r}'


def main(args=None) -> int:
    return run_node(MapOptimizationNode, args)


if __name__ == '__main__':
    sys.exit(main())
