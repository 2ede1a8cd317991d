"""Point-to-plane and point-to-line geometry shared by the odometry and the mapping (docs/original.md §6.2
step 7, §6.3), in float32 where the original computes in float.
"""
from __future__ import annotations

import numpy as np

__all__ = ['plane_through', 'plane_distance', 'plane_coefficients', 'line_offsets', 'cross_rows',
           'line_coefficients']

_F32 = np.float32


def plane_through(a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Unit normal (n, 3) and offset (n,) of the planes through a, b, c (float32): ``n · p + offset = 0``."""
    ab, ac = (b - a).astype(_F32), (c - a).astype(_F32)
    pa = ab[:, 1] * ac[:, 2] - ac[:, 1] * ab[:, 2]
    pb = ab[:, 2] * ac[:, 0] - ac[:, 2] * ab[:, 0]
    pc = ab[:, 0] * ac[:, 1] - ac[:, 0] * ab[:, 1]
    pd = -(pa * a[:, 0] + pb * a[:, 1] + pc * a[:, 2])
    with np.errstate(invalid='ignore', divide='ignore'):
        ps = np.sqrt(pa * pa + pb * pb + pc * pc)
        normal = np.stack([pa / ps, pb / ps, pc / ps], axis=1)
        pd = pd / ps
    return normal, pd


def plane_distance(normal: np.ndarray, offset: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Signed distances of points p (n, >= 3) to the planes of :func:`plane_through`."""
    return normal[:, 0] * p[:, 0] + normal[:, 1] * p[:, 1] + normal[:, 2] * p[:, 2] + offset


def plane_coefficients(p_start: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Unit normal (n, 3) and signed distance (n,) of points to the planes through a, b, c (float32)."""
    normal, offset = plane_through(a, b, c)
    return normal, plane_distance(normal, offset, p_start)


def line_offsets(p: np.ndarray, anchor: np.ndarray, along: np.ndarray) -> np.ndarray:
    """(n, 3) perpendicular offsets of points from the lines through ``anchor`` with unit direction ``along``."""
    d = p - anchor
    return d - np.einsum('ni,ni->n', d, along)[:, None] * along


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays, the same operations as ``np.cross`` without its overhead."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def line_coefficients(p: np.ndarray, a: np.ndarray, b: np.ndarray):
    """Unit direction (n, 3) from the line through a, b towards p, and the distance (n,) (float32)."""
    p, a, b = (v[:, :3].astype(_F32) for v in (p, a, b))
    pa, pb, ab = p - a, p - b, a - b
    # Cross product (p - a) x (p - b): its norm is twice the triangle area.
    cross = cross_rows(pa, pb)
    area = np.linalg.norm(cross, axis=1)
    length = np.linalg.norm(ab, axis=1)
    with np.errstate(invalid='ignore', divide='ignore'):
        # The gradient of the distance w.r.t. p: (a - b) x (pa x pb) / (|pa x pb| |a - b|).
        gradient = cross_rows(ab, cross) / (area * length)[:, None]
        distance = area / length
    return gradient.astype(_F32), distance.astype(_F32)


# ----------------------------------------------------------------------------------------- the solver
