"""Deterministic sample data shared by test processes."""

from __future__ import annotations

import numpy as np


def cloud_info_arrays(n: int = 20000, seed: int = 7) -> dict:
    rng = np.random.default_rng(seed)
    return dict(
        start_ring_index=rng.integers(-5, 20000, 16).astype(np.int32),
        end_ring_index=rng.integers(-5, 20000, 16).astype(np.int32),
        start_orientation=np.float32(-3.0),
        end_orientation=np.float32(3.25),
        orientation_diff=np.float32(6.25),
        segmented_cloud_ground_flag=rng.random(n) < 0.3,
        segmented_cloud_col_ind=rng.integers(0, 1800, n).astype(np.uint32),
        segmented_cloud_range=rng.uniform(1, 100, n).astype(np.float32),
    )
