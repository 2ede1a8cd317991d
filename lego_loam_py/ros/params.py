"""Parameters on ROS 2 nodes: the typed :class:`Params`, declared as ROS parameters.

Values come from ``--ros-args --params-file FILE`` / ``-p name:=value`` (rclpy parses them); anything
not given takes the default of :class:`Params`. Unknown names and wrong types stop the node with a
:class:`ParameterError` naming the key.
"""

from __future__ import annotations

from rclpy.node import Node

from lego_loam_py.core.params import ParameterError, Params, params_from_mapping

__all__ = ['declare_params', 'ParameterError']

# Parameters rclpy itself declares or reads on every node.
_RCLPY_PARAMETERS = ('use_sim_time', 'start_type_description_service', 'qos_overrides.')


def _is_rclpy_parameter(name: str) -> bool:
    return any(name == p or (p.endswith('.') and name.startswith(p)) for p in _RCLPY_PARAMETERS)


def declare_params(node: Node) -> Params:
    """Validate the node's parameter overrides, declare every parameter and return the typed set.

    The node must be created with ``automatically_declare_parameters_from_overrides=True`` so that the
    overrides are visible here.
    """
    given = {
        name: parameter.value
        for name, parameter in node.get_parameters_by_prefix('').items()
        if not _is_rclpy_parameter(name)
    }
    params = params_from_mapping(given)
    # (in one call: rclpy's per-call work once rather than some 230 times at every start)
    node.declare_parameters(
        '', [(name, value) for name, value in params.to_flat().items() if not node.has_parameter(name)]
    )
    return params
