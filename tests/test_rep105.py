"""The REP-105 frames (``frames.rep105``): map -> odom -> base_link -> lidar beside the original's tree.

Geometry checked by hand on a lidar mounted 1 m above base_link (and yawed on it), then transformFusion in the test
process: what it sends on /tf and /tf_static, its odometry and pose topics, in mapping and in localization without a
fix, with the mounting from parameters and from /tf_static.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lego_loam_py.core.frames import Rep105Frames, body_twist, lidar_pose_to_camera, make_pose, rot_z

TOL = 1e-9


def lidar_motion(x=0.0, y=0.0, z=0.0, yaw_deg=0.0) -> np.ndarray:
    """The LOAM pose (camera in camera_init) of a lidar that moved by (x, y, z) [m] and yawed, in its start axes."""
    return lidar_pose_to_camera(make_pose(rot_z(math.radians(yaw_deg)), [x, y, z]))


def test_odom_starts_at_base_link_and_map_at_the_lidar():
    frames = Rep105Frames.from_mount(translation=(0.2, 0.0, 1.0))
    start = lidar_motion()
    assert np.allclose(frames.odom_to_base(start), np.eye(4), atol=TOL)
    # base_link is 0.2 m behind and 1 m below the lidar that defines map: map -> odom is the mounting inverted.
    assert np.allclose(frames.map_to_odom(start, start), make_pose(None, [-0.2, 0.0, -1.0]), atol=TOL)
    assert np.allclose(frames.base_in(start)[:3, 3], [-0.2, 0.0, -1.0], atol=TOL)


def test_base_link_follows_the_lidar_through_a_yawed_mounting():
    # The lidar looks left on the robot (its x along base_link's y): driving 2 m along the lidar's x moves
    # base_link 2 m along its own y; a turn of the lidar turns base_link by the same angle, about its own origin
    # when the lidar sits above it.
    frames = Rep105Frames.from_mount(translation=(0.0, 0.0, 1.0), rotation_rpy=(0.0, 0.0, 90.0))
    assert np.allclose(frames.odom_to_base(lidar_motion(x=2.0))[:3, 3], [0.0, 2.0, 0.0], atol=TOL)
    turned = frames.odom_to_base(lidar_motion(yaw_deg=30.0))
    assert np.allclose(turned[:3, :3], rot_z(math.radians(30.0)), atol=TOL)
    assert np.allclose(turned[:3, 3], 0.0, atol=TOL)


def test_map_to_odom_is_the_mappings_correction_in_base_link_terms():
    frames = Rep105Frames.from_mount(translation=(0.0, 0.0, 1.0))
    odometry = lidar_motion(x=10.0)
    mapped = lidar_motion(x=10.5, y=-0.3)  # the mapping moved the pose by 0.5 m forward, 0.3 m right
    map_T_odom = frames.map_to_odom(mapped, odometry)
    assert np.allclose(map_T_odom, make_pose(None, [0.5, -0.3, -1.0]), atol=TOL)
    # The chain map -> odom -> base_link is the mapped pose of base_link.
    assert np.allclose(map_T_odom @ frames.odom_to_base(odometry), frames.base_in(mapped), atol=TOL)


def test_body_twist_is_in_the_body_frame_at_the_later_pose():
    previous = np.eye(4)
    current = make_pose(rot_z(math.pi / 2), [1.0, 0.0, 0.0])
    twist = body_twist(previous, current, 0.5)
    # 1 m along the old x in 0.5 s is 2 m/s along the new frame's -y; a quarter turn in 0.5 s is pi rad/s about z.
    assert np.allclose(twist, [0.0, -2.0, 0.0, 0.0, 0.0, math.pi], atol=TOL)


class _Node:
    """Just enough of a node for a listener fed by hand."""

    def create_subscription(self, *args, **kwargs):
        return None


def _transform(parent: str, child: str, xyz, yaw_deg: float = 0.0):
    from lego_loam_py.ros.conversions import pose_to_transform

    return pose_to_transform(make_pose(rot_z(math.radians(yaw_deg)), xyz), 0, parent, child)


def test_static_listener_composes_a_chain_and_waits_for_a_missing_link():
    from tf2_msgs.msg import TFMessage

    from lego_loam_py.ros.tf import StaticTransformListener

    listener = StaticTransformListener(_Node())
    listener._on_transforms(TFMessage(transforms=[_transform('mast', 'velodyne', [0.0, 0.0, 0.5], 90.0)]))
    assert listener.lookup('base_link', 'velodyne') is None
    listener._on_transforms(TFMessage(transforms=[_transform('/base_link', 'mast', [0.3, 0.0, 1.0])]))
    pose = listener.lookup('base_link', 'velodyne')
    assert np.allclose(pose, make_pose(rot_z(math.pi / 2), [0.3, 0.0, 1.5]), atol=1e-12)
    assert np.allclose(listener.lookup('velodyne', 'velodyne'), np.eye(4))


# ----------------------------------------------------------------------------------- transformFusion in process


class _TfRecorder:
    """Every transform a node sends on /tf, serialized or not."""

    def __init__(self, node):
        from rclpy.serialization import deserialize_message
        from tf2_msgs.msg import TFMessage

        self.sent: list = []
        send, send_serialized = node.tf.send, node.tf.send_serialized

        def record(transforms):
            self.sent.extend([transforms] if hasattr(transforms, 'child_frame_id') else list(transforms))
            send(transforms)

        def record_serialized(data):
            self.sent.extend(deserialize_message(data, TFMessage).transforms)
            send_serialized(data)

        node.tf.send, node.tf.send_serialized = record, record_serialized

    def edges(self) -> set[tuple[str, str]]:
        return {(t.header.frame_id, t.child_frame_id) for t in self.sent}

    def last(self, parent: str, child: str) -> np.ndarray:
        from lego_loam_py.ros.conversions import transform_to_pose

        return transform_to_pose([t for t in self.sent if (t.header.frame_id, t.child_frame_id) == (parent, child)][-1])


def _odometry(pose: np.ndarray, stamp_ns: int):
    from lego_loam_py.core.frames import CAMERA_INIT_FRAME, LASER_ODOM_FRAME
    from lego_loam_py.ros.conversions import make_header, pose_to_odometry

    return pose_to_odometry(pose, make_header(stamp_ns, CAMERA_INIT_FRAME), LASER_ODOM_FRAME)


def _static_edges(node) -> set[tuple[str, str]]:
    return {(t.header.frame_id, t.child_frame_id) for t in node.static_tf._by_child.values()}


def _fusion(context, **overrides):
    from lego_loam_py.ros.transform_fusion_node import TransformFusionNode
    from tests.support.inprocess import make_node

    node, recorder = make_node(context, TransformFusionNode, **overrides)
    return node, recorder, _TfRecorder(node)


def _drive(node, seconds: float = 1.0, speed: float = 2.0):
    """Odometry of a lidar driving straight along its x at ``speed`` [m/s], 10 Hz."""
    for k in range(int(seconds * 10) + 1):
        node.on_odometry(_odometry(lidar_motion(x=speed * 0.1 * k), 10**9 + k * 10**8))


def test_default_tree_is_the_originals(rclpy_context):
    node, recorder, tf = _fusion(rclpy_context)
    try:
        _drive(node)
        assert tf.edges() == {('camera_init', 'camera')}
        assert _static_edges(node) == {('map', 'camera_init'), ('camera', 'base_link')}
        assert '/lego_loam/odometry' not in recorder.published and not recorder.warnings
    finally:
        node.destroy_node()


def test_rep105_publishes_map_odom_base_link_and_the_lidar_mount(rclpy_context):
    node, recorder, tf = _fusion(rclpy_context, **{'frames.rep105': True, 'frames.lidar_translation': [0.0, 0.0, 1.0]})
    try:
        _drive(node, seconds=1.0, speed=2.0)
        assert tf.edges() == {('camera_init', 'camera'), ('odom', 'base_link'), ('map', 'odom')}
        # base_link's parent is odom: the original's static camera -> base_link is left out.
        assert _static_edges(node) == {('map', 'camera_init'), ('base_link', 'velodyne')}
        assert np.allclose(tf.last('odom', 'base_link'), make_pose(None, [2.0, 0.0, 0.0]), atol=1e-6)
        assert np.allclose(tf.last('map', 'odom'), make_pose(None, [0.0, 0.0, -1.0]), atol=1e-6)
        odometry = recorder.out('/lego_loam/odometry')
        assert len(odometry) == 11 and odometry[-1].header.frame_id == 'odom'
        assert odometry[-1].child_frame_id == 'base_link'
        velocity = odometry[-1].twist.twist.linear
        assert (velocity.x, velocity.y, velocity.z) == pytest.approx((2.0, 0.0, 0.0), abs=1e-6)
        pose = recorder.out('/lego_loam/pose')[-1]
        assert pose.header.frame_id == 'map'
        assert (pose.pose.pose.position.x, pose.pose.pose.position.z) == pytest.approx((2.0, -1.0), abs=1e-6)
        assert len(recorder.out('/integrated_to_init')) == 11  # the original's topics as before
    finally:
        node.destroy_node()


def test_localization_without_a_fix_keeps_odom_and_withholds_map(rclpy_context, tmp_path):
    localization = {'map_optimization.mode': 'localization', 'map_optimization.map_path': str(tmp_path)}
    node, recorder, tf = _fusion(rclpy_context, **{'frames.rep105': True, **localization})
    try:
        _drive(node)
        assert ('odom', 'base_link') in tf.edges() and ('map', 'odom') not in tf.edges()
        assert len(recorder.out('/lego_loam/odometry')) == 11 and not recorder.out('/lego_loam/pose')
    finally:
        node.destroy_node()


def test_mount_from_tf_static_is_waited_for_then_used(rclpy_context):
    from tf2_msgs.msg import TFMessage

    node, recorder, tf = _fusion(
        rclpy_context, **{'frames.rep105': True, 'frames.lidar_mount': 'tf_static', 'frames.lidar_frame': 'os_sensor'}
    )
    try:
        _drive(node, seconds=0.2)
        assert ('odom', 'base_link') not in tf.edges()
        assert node.counters['rep105_waiting_for_mount'] == 3
        assert any(key == 'no_mount' for key, _ in recorder.warnings)
        assert ('base_link', 'os_sensor') not in _static_edges(node)  # a robot_state_publisher's to send
        node._mount_listener._on_transforms(
            TFMessage(transforms=[_transform('base_link', 'os_sensor', [0.5, 0.0, 0.8])])
        )
        node.on_odometry(_odometry(lidar_motion(x=1.0), 2 * 10**9))
        assert np.allclose(tf.last('map', 'odom'), make_pose(None, [-0.5, 0.0, -0.8]), atol=1e-6)
        assert np.allclose(tf.last('odom', 'base_link'), make_pose(None, [1.0, 0.0, 0.0]), atol=1e-6)
    finally:
        node.destroy_node()


@pytest.mark.parametrize(
    'key, value',
    [('frames.odom_frame', 'map'), ('frames.base_frame', '/base_link'), ('frames.lidar_translation', [0.0, 1.0])],
)
def test_bad_frame_parameters_are_refused_by_name(key, value):
    from lego_loam_py.core.params import ParameterError, params_from_mapping

    with pytest.raises(ParameterError, match=key.split('.')[0]):
        params_from_mapping({key: value})


# ------------------------------------------------------------------------------------------------ covariance


def _perturbed(pose: np.ndarray, error: np.ndarray) -> np.ndarray:
    """``pose`` with a parent-frame error (δp, δφ) applied (the convention of core.frames.pose_error)."""
    from scipy.spatial.transform import Rotation

    out = pose.copy()
    out[:3, :3] = Rotation.from_rotvec(error[3:]).as_matrix() @ pose[:3, :3]
    out[:3, 3] += error[:3]
    return out


def test_a_covariance_follows_a_frame_change_as_its_errors_do():
    """The Jacobian of transformed_covariance against finite differences of the errors themselves: for each
    direction of the input error, the error it makes in ``left @ pose @ right`` (to 1e-6 of a 1e-6 step)."""
    from lego_loam_py.core.frames import pose_error, transformed_covariance

    rng = np.random.default_rng(3)
    frames = Rep105Frames.from_mount(translation=(0.4, -0.1, 1.2), rotation_rpy=(2.0, -3.0, 90.0))
    pose = lidar_pose_to_camera(make_pose(rot_z(0.7), [5.0, -2.0, 0.3]))
    left = frames.base_T_lidar @ lidar_pose_to_camera(np.eye(4)).T  # camera axes into base_link's
    right = np.linalg.inv(left)
    step = 1e-6
    jacobian = np.column_stack(
        [pose_error(left @ pose @ right, left @ _perturbed(pose, step * e) @ right) / step for e in np.eye(6)]
    )
    covariance = rng.normal(size=(6, 6))
    covariance = covariance @ covariance.T
    assert np.allclose(
        transformed_covariance(covariance, left, pose, right), jacobian @ covariance @ jacobian.T, atol=1e-5
    )


def test_the_odometry_covariance_lands_on_base_link_in_odom():
    """A yaw variance of the lidar (its LOAM y axis) is base_link's yaw variance in odom; a lidar 0.5 m ahead of
    base_link turning about its own axis swings base_link sideways by 0.5 m per radian."""
    frames = Rep105Frames.from_mount(translation=(0.5, 0.0, 1.0))
    variance = 1e-4
    covariance = np.zeros((6, 6))
    covariance[4, 4] = variance  # rotation about camera y = the lidar's z
    out = frames.odom_to_base_covariance(lidar_motion(), covariance)
    assert out[5, 5] == pytest.approx(variance, rel=1e-12)
    assert out[1, 1] == pytest.approx(0.25 * variance, rel=1e-9)  # 0.5 m lever, sideways (y)
    assert abs(out[0, 0]) < 1e-18 and abs(out[2, 2]) < 1e-18


def test_rep105_messages_carry_the_covariance_of_their_own_frames(rclpy_context):
    from lego_loam_py.core.frames import CAMERA_INIT_FRAME, LASER_ODOM_FRAME
    from lego_loam_py.ros.conversions import make_header, pose_to_odometry

    node, recorder, _ = _fusion(rclpy_context, **{'frames.rep105': True, 'frames.lidar_translation': [0.0, 0.0, 1.0]})
    try:
        for k in range(5):
            covariance = np.diag([1e-4, 1e-4, 4e-4, 1e-6, 1e-6, 1e-6]) * (k + 1)  # growing along the chain
            pose = lidar_motion(x=0.2 * k)
            node.on_odometry(
                pose_to_odometry(
                    pose,
                    make_header(10**9 + k * 10**8, CAMERA_INIT_FRAME),
                    LASER_ODOM_FRAME,
                    pose_covariance=covariance,
                )
            )
        last = recorder.out('/lego_loam/odometry')[-1]
        pose_covariance = np.asarray(last.pose.covariance).reshape(6, 6)
        # camera z (the lidar's x) variance 4e-4 per step -> base_link's x in odom, five steps in, and the lidar's
        # pitch variance (1e-6 rad^2 a step) swinging base_link, 1 m below it, along x.
        assert pose_covariance[0, 0] == pytest.approx(5 * (4e-4 + 1.0**2 * 1e-6), rel=1e-9)
        twist_covariance = np.asarray(last.twist.covariance).reshape(6, 6)
        # what one step added (4e-4 along x) over 0.1 s squared: (0.02 m/s)^2.
        assert twist_covariance[0, 0] == pytest.approx(4e-4 / 0.01, rel=1e-6)
        assert np.linalg.eigvalsh(twist_covariance).min() > 0.0
    finally:
        node.destroy_node()
