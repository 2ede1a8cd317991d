"""mapOptimization's ROS side in localization mode (``map_optimization.mode: localization``).

* The saved map is loaded at start-up; a bundle that cannot be used (missing, corrupt, another sensor) is an error
  in the log and on /localization_status, the node keeps running without output and tries again every
  ``RETRY_PERIOD`` s (the map may be copied there later).
* ``/initialpose`` (geometry_msgs/PoseWithCovarianceStamped, what RViz's "2D Pose Estimate" sends; frame ``map``,
  REP-103 axes, or ``camera_init``): the robot's x, y and heading in the saved map, searched within
  max(``localization.initial_pose_radius``, 3 sigma of its x/y covariance); height, roll and pitch come from the
  map and the odometry. A bad message is dropped with a throttled warning.
* ``/localization_status`` (diagnostic_msgs/DiagnosticStatus, latched): OK while localized, WARN while not (with
  why), ERROR when the map is not loaded; sent after every step and once a second. While there is no fix, a
  throttled log line says so; fixes and losses are logged as they happen.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.clock import Clock, ClockType

from lego_loam_py.core.frames import CAMERA_INIT_FRAME, MAP_FRAME, camera_pose_to_lidar, quaternion_to_matrix
from lego_loam_py.core.mapping.map_bundle import MapBundleError
from lego_loam_py.core.validation import MAX_POSITION
from lego_loam_py.ros import qos

if TYPE_CHECKING:  # (the localizer is imported when a map is loaded: a mapping node never needs it)
    from lego_loam_py.core.localization.localizer import Localization, LocalizationStatus

__all__ = ['LocalizationFrontEnd', 'initial_pose_of', 'status_message', 'STATUS_TOPIC', 'INITIAL_POSE_TOPIC']

STATUS_TOPIC, INITIAL_POSE_TOPIC = '/localization_status', '/initialpose'
RETRY_PERIOD = 10.0  # [s] between attempts to load a map that could not be loaded
LOG_PERIOD = 5.0  # [s] between two 'no pose yet' log lines
MAX_RADIUS = 100.0  # [m] a covariance wider than this says "anywhere": the search radius stops here


def initial_pose_of(msg: PoseWithCovarianceStamped, default_radius: float) -> tuple[float, float, float, float]:
    """(x [m], y [m], yaw [deg], search radius [m]) of an /initialpose message in the saved map's ``map`` frame;
    ValueError naming what is wrong with it."""
    frame = msg.header.frame_id.lstrip('/')
    if frame not in (MAP_FRAME, CAMERA_INIT_FRAME, ''):
        raise ValueError(f"frame '{msg.header.frame_id}' is neither '{MAP_FRAME}' nor '{CAMERA_INIT_FRAME}'")
    p = msg.pose.pose
    q = np.array([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w], dtype=float)
    t = np.array([p.position.x, p.position.y, p.position.z], dtype=float)
    if not (np.isfinite(q).all() and np.isfinite(t).all()):
        raise ValueError('the pose is not finite')
    if not (np.abs(t) <= MAX_POSITION).all():
        raise ValueError(f'the position is beyond {MAX_POSITION:g} m')
    scale = float(np.abs(q).max())
    norm = scale * float(np.linalg.norm(q / scale)) if scale > 0 else 0.0  # (no overflow for huge values)
    if abs(norm - 1.0) > 0.1:
        raise ValueError(f'the orientation is no unit quaternion (norm {norm:.3g})')
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = quaternion_to_matrix(q), t
    if frame == CAMERA_INIT_FRAME:  # (LOAM camera axes: the same frame as map, its axes turned)
        pose = camera_pose_to_lidar(pose)
    yaw = math.degrees(math.atan2(pose[1, 0], pose[0, 0]))
    covariance = np.asarray(msg.pose.covariance, dtype=float)
    spread = max(covariance[0], covariance[7]) if len(covariance) == 36 else float('nan')
    radius = default_radius
    if math.isfinite(spread) and spread > 0:
        radius = min(max(default_radius, 3.0 * math.sqrt(spread)), MAX_RADIUS)
    return float(pose[0, 3]), float(pose[1, 3]), yaw, radius


def status_message(node_name: str, status: LocalizationStatus | None, error: str | None = None) -> DiagnosticStatus:
    """/localization_status of ``status`` (or, without one, of a map that could not be loaded: ``error``)."""
    if status is None:
        return DiagnosticStatus(
            level=DiagnosticStatus.ERROR,
            name=f'{node_name}/localization',
            message=f'no map loaded: {error}',
            hardware_id='lego_loam_py',
            values=[KeyValue(key='state', value='no_map')],
        )
    level = DiagnosticStatus.OK if status.localized else DiagnosticStatus.WARN
    return DiagnosticStatus(
        level=level,
        name=f'{node_name}/localization',
        message=status.message,
        hardware_id='lego_loam_py',
        values=[KeyValue(key=k, value=str(v)) for k, v in status.values.items()],
    )


class LocalizationFrontEnd:
    """The ROS side of :class:`~lego_loam_py.core.localization.localizer.Localization` for a mapOptimization node (see
    the module docstring). ``core`` is the localization once the map is loaded, else None."""

    def __init__(self, node):
        self.node = node
        self.core: Localization | None = None
        self.error: str | None = None
        self._events_seen = 0
        node.create_subscription(PoseWithCovarianceStamped, INITIAL_POSE_TOPIC, self.on_initial_pose, qos.reliable(5))
        self.pub_status = node.create_publisher(DiagnosticStatus, STATUS_TOPIC, qos.latched())
        wall = Clock(clock_type=ClockType.STEADY_TIME)  # (with use_sim_time and no /clock, ROS time stands still)
        node.create_timer(1.0, self.publish_status, clock=wall)
        self.load()
        self._retry = None if self.core is not None else node.create_timer(RETRY_PERIOD, self._load_again, clock=wall)

    def load(self) -> Localization | None:
        """Load the saved map of ``map_optimization.map_path``; logs and keeps the error when it cannot."""
        node, path = self.node, self.node.params.map_optimization.map_path
        try:
            from lego_loam_py.core.localization.localizer import Localization

            self.core = Localization.load(node.params)
        except (MapBundleError, OSError, ValueError) as exc:
            self.error = str(exc)
            node.count('map_load_failures')
            node.warn(
                'map_load',
                f'localization: {exc}; no pose will be published (trying again every {RETRY_PERIOD:g} s)',
                level='error',
            )
        else:
            self.error = None
            for warning in self.core.warnings:
                node.get_logger().warning(warning)
            node.get_logger().info(f'localization in the saved map {path} ({len(self.core.prior)} keyframes)')
        self.publish_status()
        return self.core

    def _load_again(self) -> None:
        if self.core is None and self.load() is not None and self._retry is not None:
            self._retry.cancel()

    def on_initial_pose(self, msg: PoseWithCovarianceStamped) -> None:
        node = self.node
        if self.core is None:
            node.count('initial_pose_dropped')
            node.warn('initial_pose', f'{INITIAL_POSE_TOPIC} dropped: no map loaded ({self.error})')
            return
        try:
            x, y, yaw, radius = initial_pose_of(msg, node.params.localization.initial_pose_radius)
        except ValueError as exc:
            node.count('initial_pose_dropped')
            node.warn('initial_pose', f'{INITIAL_POSE_TOPIC} dropped: {exc}')
            return
        self.core.set_initial_pose(x, y, None, yaw, radius=radius, origin=INITIAL_POSE_TOPIC)
        node.count('initial_poses')
        node.get_logger().info(
            f'{INITIAL_POSE_TOPIC}: x {x:.2f} m, y {y:.2f} m, yaw {yaw:.1f} deg; looking for the '
            f'place within {radius:.1f} m of it'
        )
        self.publish_status()

    def after_step(self, published: bool) -> None:
        """After each step: fixes and losses into the log, the status out, and while there is no pose a throttled
        line saying why."""
        core, node = self.core, self.node
        new, self._events_seen = core.event_count - self._events_seen, core.event_count
        for event in list(core.events)[-new:] if new > 0 else []:
            if event.kind in ('fix', 'lost'):
                log = node.get_logger().info if event.kind == 'fix' else node.get_logger().warning
                log(f'localization {event.kind}: {event.detail}')
        status = self.publish_status()
        if not published and status is not None:
            node.warn('not_localized', status.message, period=LOG_PERIOD)

    def publish_status(self):
        status = self.core.status() if self.core is not None else None
        self.pub_status.publish(status_message(self.node.get_name(), status, self.error))
        return status
