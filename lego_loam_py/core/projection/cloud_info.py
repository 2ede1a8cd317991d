"""The CloudInfo of one scan: what imageProjection tells featureAssociation beside the segmented cloud.

A module of its own, with NumPy only, so that the nodes which read or write cloud_msgs/CloudInfo (every node's
conversions, featureAssociation) need not import the projection itself."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ['CloudInfo']


@dataclass
class CloudInfo:
    """Content of cloud_msgs/CloudInfo for one scan. Arrays are as long as the segmented cloud."""

    start_ring_index: np.ndarray  # int32 (N_SCAN,)
    end_ring_index: np.ndarray  # int32 (N_SCAN,)
    start_orientation: np.float32  # [rad]
    end_orientation: np.float32  # [rad]
    orientation_diff: np.float32  # [rad]
    segmented_cloud_ground_flag: np.ndarray  # bool (M,)
    segmented_cloud_col_ind: np.ndarray  # uint32 (M,)
    segmented_cloud_range: np.ndarray  # float32 (M,) [m]
