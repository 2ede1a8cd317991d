"""A plain, loop-by-loop transcription of the original's labelComponents BFS, as a test reference."""

from __future__ import annotations

import math
from collections import deque

import numpy as np

OUTLIER = 999999


def reference_labels(
    range_image: np.ndarray,
    empty_or_ground: np.ndarray,
    alpha_x: float,
    alpha_y: float,
    theta: float,
    min_cluster: int = 30,
    valid_points: int = 5,
    valid_lines: int = 3,
) -> np.ndarray:
    """labelMat after segmentation: -1 for ground/empty, 999999 for small clusters, 1.. for segments."""
    n, h = range_image.shape
    label = np.where(empty_or_ground, -1, 0).astype(np.int64)
    count = 1
    for row in range(n):
        for col in range(h):
            if label[row, col] != 0:
                continue
            queue = deque([(row, col)])
            pushed = [(row, col)]
            line_flag = [False] * n
            label[row, col] = count
            while queue:
                fr, fc = queue.popleft()
                for dr, dc in ((-1, 0), (0, 1), (0, -1), (1, 0)):
                    r, c = fr + dr, fc + dc
                    if r < 0 or r >= n:
                        continue
                    c %= h
                    if label[r, c] != 0:
                        continue
                    d1 = max(range_image[fr, fc], range_image[r, c])
                    d2 = min(range_image[fr, fc], range_image[r, c])
                    alpha = alpha_x if dr == 0 else alpha_y
                    if math.atan2(d2 * math.sin(alpha), d1 - d2 * math.cos(alpha)) > theta:
                        queue.append((r, c))
                        label[r, c] = count
                        line_flag[r] = True
                        pushed.append((r, c))
            feasible = len(pushed) >= min_cluster or (len(pushed) >= valid_points and sum(line_flag) >= valid_lines)
            if feasible:
                count += 1
            else:
                for r, c in pushed:
                    label[r, c] = OUTLIER
    return label
