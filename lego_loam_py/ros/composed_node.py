"""``legoLoam``: the four nodes in one process, their messages to each other handed over in memory.

Topics, frames, messages, parameters and services are those of the four executables, which it replaces as a
whole: ``ros2 run lego_loam_py legoLoam --ros-args --params-file params.yaml``. The pipeline's internal topics
(/segmented_cloud, /laser_odom_to_init, ...) go over DDS only while another process subscribes to them (see
:mod:`lego_loam_py.ros.composition`). One process, one DDS participant and one executor thread instead of four:
less CPU at start-up and per scan, and no copy of a message through DDS between the stages.
"""

from __future__ import annotations

import sys

from lego_loam_py.ros.feature_association_node import FeatureAssociationNode
from lego_loam_py.ros.image_projection_node import ImageProjectionNode
from lego_loam_py.ros.map_optimization_node import MapOptimizationNode
from lego_loam_py.ros.runtime import run_nodes
from lego_loam_py.ros.transform_fusion_node import TransformFusionNode

__all__ = ['PIPELINE', 'main']

PIPELINE = (ImageProjectionNode, FeatureAssociationNode, MapOptimizationNode, TransformFusionNode)


def main(args=None) -> int:
    return run_nodes(PIPELINE, args)


if __name__ == '__main__':
    sys.exit(main())
