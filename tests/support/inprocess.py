"""Nodes run inside the test process: their message handlers called directly with crafted messages, what they
publish and log recorded. Shared by the reliability and the never-silent tests."""

from __future__ import annotations

from pathlib import Path

from lego_loam_py.testing.messages import stamp_of

REPO = Path(__file__).resolve().parents[2]
CAMPUS = REPO / 'bags' / 'campus_8s'


class Recorder:
    """Installed on a node: records its warnings and errors, and what its publishers publish."""

    def __init__(self, node):
        from rclpy.serialization import deserialize_message

        self.node = node
        self.warnings: list[tuple[str, str]] = []
        self.errors: list[tuple[str, str]] = []  # unexpected exceptions
        self.resets: list[tuple[str, str]] = []  # poisoned state found and reset
        self.published: dict[str, list] = {}
        warn = node.warn

        def record_warn(key, text, period=None, level='warning'):
            if key == 'state_reset':
                self.resets.append((key, text))
            elif level == 'error':
                self.errors.append((key, text))
            else:
                self.warnings.append((key, text))
            warn(key, text, period, level)

        node.warn = record_warn
        for publisher in node.publishers:
            if publisher.topic_name in ('/tf', '/tf_static', '/rosout', '/parameter_events'):
                continue
            store = self.published.setdefault(publisher.topic_name, [])
            original = publisher.publish

            def publish(msg, _store=store, _original=original, _type=publisher.msg_type):
                # Clouds go out serialized: kept as the message a subscriber receives.
                _store.append(deserialize_message(msg, _type) if isinstance(msg, bytes) else msg)
                _original(msg)

            publisher.publish = publish

    def out(self, topic: str) -> list:
        return self.published.get(topic, [])

    def mark(self):
        return len(self.warnings), len(self.errors), {t: len(v) for t, v in self.published.items()}


def make_node(context, cls, tmp_path=None, **overrides):
    from rclpy.parameter import Parameter

    values = dict(overrides)
    if tmp_path is not None:
        values.setdefault('map_optimization.file_directory', str(tmp_path))
    node = cls(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])
    return node, Recorder(node)


# ------------------------------------------------------------------------------------------- sample inputs

_CACHE: dict = {}


def campus_messages(seconds: float = 3.0) -> list[tuple[str, object]]:
    """(topic, rclpy message) of the first seconds of bags/campus_8s, in recording order."""
    key = ('campus', seconds)
    if key not in _CACHE:
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import Imu, PointCloud2

        from lego_loam_py.bag.io import BagReader

        out = []
        with BagReader(CAMPUS) as reader:
            end = reader.start_time + int(seconds * 1e9)
            for m in reader.messages():
                if m.timestamp > end:
                    break
                cls = PointCloud2 if m.topic == '/velodyne_points' else Imu
                out.append((m.topic, deserialize_message(bytes(m.data), cls)))
        _CACHE[key] = out
    return _CACHE[key]


def pipeline_outputs(context, tmp_path) -> dict:
    """imageProjection's and featureAssociation's messages for the first 3 s of the campus bag."""
    if 'outputs' in _CACHE:
        return _CACHE['outputs']
    from lego_loam_py.ros.feature_association_node import FeatureAssociationNode
    from lego_loam_py.ros.image_projection_node import ImageProjectionNode

    ip, ip_rec = make_node(context, ImageProjectionNode)
    fa, fa_rec = make_node(context, FeatureAssociationNode)
    for topic, msg in campus_messages():
        if topic == '/imu/data':
            fa.on_imu(msg)
            continue
        before = len(ip_rec.out('/segmented_cloud'))
        ip.on_cloud(msg)
        if len(ip_rec.out('/segmented_cloud')) > before:
            fa.on_part('cloud', ip_rec.out('/segmented_cloud')[-1])
            fa.on_part('info', ip_rec.out('/segmented_cloud_info')[-1])
            fa.on_part('outlier', ip_rec.out('/outlier_cloud')[-1])
    outputs = dict(
        clouds=[m for t, m in campus_messages() if t == '/velodyne_points'],
        imu=[m for t, m in campus_messages() if t == '/imu/data'],
        segmented=list(ip_rec.out('/segmented_cloud')),
        info=list(ip_rec.out('/segmented_cloud_info')),
        outlier=list(ip_rec.out('/outlier_cloud')),
        odometry=list(fa_rec.out('/laser_odom_to_init')),
        corner_last=list(fa_rec.out('/laser_cloud_corner_last')),
        surf_last=list(fa_rec.out('/laser_cloud_surf_last')),
        outlier_last=list(fa_rec.out('/outlier_cloud_last')),
        fa_statistics=fa.statistics(),
        fa_diagnostics=fa.diagnostic_status(),
    )
    assert len(outputs['segmented']) == len(outputs['clouds']) and not ip_rec.errors and not fa_rec.errors
    assert len(outputs['corner_last']) >= 10
    ip.destroy_node()
    fa.destroy_node()
    _CACHE['outputs'] = outputs
    return outputs


def mapping_inputs(outputs: dict) -> list[tuple]:
    """(corner, surf, outlier, odometry) messages of every scan featureAssociation handed to mapping, from
    :func:`pipeline_outputs`."""
    odometry = {stamp_of(m): m for m in outputs['odometry']}
    return [
        (c, s, o, odometry[stamp_of(c)])
        for c, s, o in zip(outputs['corner_last'], outputs['surf_last'], outputs['outlier_last'])
        if stamp_of(c) in odometry
    ]


def mapping_publishers(node) -> dict:
    """Publishers of mapOptimization's four inputs on ``node``, by part name."""
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    from lego_loam_py.ros import qos

    return {
        name: node.create_publisher(cls, topic, qos.reliable(10))
        for name, cls, topic in (
            ('corner', PointCloud2, '/laser_cloud_corner_last'),
            ('surf', PointCloud2, '/laser_cloud_surf_last'),
            ('outlier', PointCloud2, '/outlier_cloud_last'),
            ('odometry', Odometry, '/laser_odom_to_init'),
        )
    }
