"""The mapOptimization node in this process, fed featureAssociation's outputs for the first 3 s of the campus:
what it reports about each mapping step."""

from __future__ import annotations

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
