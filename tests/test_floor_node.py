"""The computation-free stand-ins of benchmarks/floor_node.py are wired as the real nodes are: otherwise the floor
that ``bench_dds.py --floor`` reports would measure other messages than the nodes take and send."""

from __future__ import annotations

import pytest

from benchmarks.floor_node import CAPTURE_TOPICS, WIRING, _qos, _type
from tests.support.inprocess import make_node


def _node_classes():
    from lego_loam_py.ros.feature_association_node import FeatureAssociationNode
    from lego_loam_py.ros.image_projection_node import ImageProjectionNode
    from lego_loam_py.ros.map_optimization_node import MapOptimizationNode
    from lego_loam_py.ros.transform_fusion_node import TransformFusionNode

    return {
        'imageProjection': ImageProjectionNode,
        'featureAssociation': FeatureAssociationNode,
        'mapOptimization': MapOptimizationNode,
        'transformFusion': TransformFusionNode,
    }


def _qos_key(profile) -> tuple:
    return profile.depth, profile.reliability, profile.durability


def _subscriptions(node) -> set[tuple]:
    return {(s.topic_name, s.msg_type.__name__, _qos_key(s.qos_profile), bool(s.raw)) for s in node.subscriptions}


@pytest.mark.parametrize('name', list(WIRING))
def test_the_stand_in_takes_and_sends_what_the_node_does(context, tmp_path, name):
    node, _ = make_node(context, _node_classes()[name], tmp_path, use_sim_time=True)  # (as a bag is replayed)
    try:
        wiring = WIRING[name]
        # Every subscription of the node (with default parameters) is the stand-in's, serialized or not alike.
        expected = {(topic, _type(t).__name__, _qos_key(_qos(q)), raw) for topic, t, q, raw in wiring['subscribe']}
        assert _subscriptions(node) == expected
        # The polled ones (the IMU, taken with each input) too.
        polled = _subscriptions(node._polled_node) if node._polled_node is not None else set()
        assert polled == {(topic, _type(t).__name__, _qos_key(_qos(q)), True) for topic, t, q, _ in wiring['polled']}
        # What the stand-in publishes is published by the node on the same topics, types and QoS.
        publishers = {(p.topic_name, p.msg_type.__name__, _qos_key(p.qos_profile)) for p in node.publishers}
        for topic, t, q, _ in wiring['publish']:
            assert (topic, _type(t).__name__, _qos_key(_qos(q))) in publishers
        assert wiring['trigger'] in {topic for topic, *_ in wiring['subscribe']}
    finally:
        node.destroy_node()


def test_a_capture_records_every_trigger_and_output():
    for wiring in WIRING.values():
        assert wiring['trigger'] in CAPTURE_TOPICS
        assert {topic for topic, *_ in wiring['publish']} <= set(CAPTURE_TOPICS)
