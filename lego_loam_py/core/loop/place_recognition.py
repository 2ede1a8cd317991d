"""Place recognition over keyframes: a Scan Context descriptor and a database that finds revisited places.

Scan Context (Kim & Kim, IROS 2018) describes the scene around a sensor by a polar grid seen from above:
``rings`` annuli out to ``max_radius`` times ``sectors`` angular slices, each cell holding the height of the
highest point in it (0 for an empty cell). Implemented here from the paper's description:

* the cloud is levelled first (the caller passes gravity-aligned points: roll and pitch removed, yaw kept),
  so a slope or a tilted mount does not change the heights;
* heights are measured from ``height_offset`` below the sensor (about the ground), so that an empty cell (0)
  and a cell of ground differ little and a wall stands out;
* the **ring key** (the share of occupied cells of each ring) does not change when the sensor turns: a
  database of ring keys gives a short list of candidate places cheaply;
* the distance between two descriptors is the mean cosine distance of their sector columns, at the circular
  shift of sectors that minimises it; that shift is the yaw between the two views (the place is the same
  whatever the heading, e.g. driven the other way).

Everything is numpy over whole grids; no Python loop runs over points. Axes: REP-103 lidar axes of the
levelled keyframe (x forward, y left, z up), metres and radians. The database is independent of the mapper
(it stores descriptors under caller-chosen keys), so localization in a saved map can reuse it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ['ScanContextConfig', 'scan_context', 'ring_key', 'descriptor_distance', 'PlaceMatch', 'PlaceDatabase']


@dataclass(frozen=True)
class ScanContextConfig:
    """Geometry of the descriptor."""

    rings: int = 20  # annuli from the sensor out to max_radius
    sectors: int = 60  # angular slices (6 deg each)
    max_radius: float = 50.0  # [m]
    height_offset: float = 2.0  # heights measured from this far below the sensor [m]
    min_range: float = 1.0  # nearer points (the vehicle itself) are ignored [m]


def scan_context(points: np.ndarray, config: ScanContextConfig = ScanContextConfig()) -> np.ndarray:
    """(rings, sectors) float32 descriptor of (N, >=3) levelled points (lidar axes, metres): per cell the height
    [m] of its highest point above ``height_offset`` below the sensor, clipped at 0; empty cells 0. Sector 0
    starts at azimuth -pi and sectors run counter-clockwise (the yaw direction)."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    radius = np.hypot(xyz[:, 0], xyz[:, 1])
    keep = (radius >= config.min_range) & (radius < config.max_radius) & np.isfinite(radius)
    xyz, radius = xyz[keep], radius[keep]
    ring = np.minimum((radius / config.max_radius * config.rings).astype(np.int64), config.rings - 1)
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    sector = np.minimum(((azimuth + math.pi) / (2 * math.pi) * config.sectors).astype(np.int64), config.sectors - 1)
    height = np.maximum(xyz[:, 2] + config.height_offset, 0.0)
    descriptor = np.zeros(config.rings * config.sectors)
    np.maximum.at(descriptor, ring * config.sectors + sector, height)
    return descriptor.reshape(config.rings, config.sectors).astype(np.float32)


def ring_key(descriptor: np.ndarray) -> np.ndarray:
    """(rings,) share of occupied cells per ring: invariant to the sensor's yaw."""
    return (np.asarray(descriptor) > 0).mean(axis=1).astype(np.float32)


def descriptor_distance(query: np.ndarray, others: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scan Context distance of ``query`` (rings, sectors) to each of ``others`` (M, rings, sectors): the mean
    cosine distance (0 same, 1 unrelated) over the sector columns that are not empty in both, at the best
    circular shift of sectors. Returns (distances (M,), shifts (M,)): ``others[m]`` rolled by ``shifts[m]``
    sectors along its last axis matches ``query``, i.e. the query's sensor is turned by ``-shift * 2 pi /
    sectors`` [rad] counter-clockwise from the other's (a scene seen turned left shows at smaller azimuths)."""
    query = np.asarray(query, dtype=np.float64)
    others = np.asarray(others, dtype=np.float64).reshape(-1, *query.shape)
    sectors = query.shape[1]

    def unit_columns(grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        norm = np.linalg.norm(grid, axis=-2, keepdims=True)
        filled = norm > 0
        return np.where(filled, grid / np.where(filled, norm, 1.0), 0.0), filled[..., 0, :].astype(np.float64)

    def correlate(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """sum_s a[..., s] b[m, ..., (s - k) % sectors] for every shift k, by FFT along the sectors."""
        spectrum = np.fft.rfft(a, axis=-1)[None] * np.conj(np.fft.rfft(b, axis=-1))
        if spectrum.ndim == 3:  # (M, rings, bins): sum over the rings
            spectrum = spectrum.sum(axis=1)
        return np.fft.irfft(spectrum, n=sectors, axis=-1)

    query_unit, query_filled = unit_columns(query)
    others_unit, others_filled = unit_columns(others)
    # Per shift: the summed cosine of the column pairs, over the number of pairs filled in both.
    cosine_sum = correlate(query_unit, others_unit)
    counted = np.rint(correlate(query_filled, others_filled))
    similarity = np.where(counted > 0, cosine_sum / np.maximum(counted, 1.0), 0.0)
    best = np.argmax(similarity, axis=1)
    distance = 1.0 - similarity[np.arange(len(others)), best]
    return distance, best


@dataclass(frozen=True)
class PlaceMatch:
    """A stored place that looks like the query."""

    key: int  # the key the place was stored under (e.g. a keyframe index)
    distance: float  # Scan Context distance (0 same, 1 unrelated)
    yaw: float  # the query's heading minus the place's [rad], from the best sector shift


class PlaceDatabase:
    """Descriptors stored under integer keys; :meth:`query` returns the closest places among those allowed.

    Candidates are the ``ring_key_candidates`` places nearest in ring key (yaw-invariant, cheap), then ranked by
    the full descriptor distance. Memory: rings x sectors float32 per place (4.8 kB with the defaults)."""

    def __init__(self, config: ScanContextConfig = ScanContextConfig(), ring_key_candidates: int = 10):
        self.config = config
        self.ring_key_candidates = ring_key_candidates
        self._keys: list[int] = []
        self._descriptors: list[np.ndarray] = []
        self._ring_keys = np.zeros((0, config.rings), np.float32)

    def __len__(self) -> int:
        return len(self._keys)

    def add(self, key: int, descriptor: np.ndarray) -> None:
        self._keys.append(int(key))
        self._descriptors.append(np.asarray(descriptor, np.float32))
        self._ring_keys = np.vstack([self._ring_keys, ring_key(descriptor)[None]])

    def descriptor(self, key: int) -> np.ndarray | None:
        try:
            return self._descriptors[self._keys.index(int(key))]
        except ValueError:
            return None

    def query(self, descriptor: np.ndarray, allowed: np.ndarray | None = None, count: int = 1) -> list[PlaceMatch]:
        """The ``count`` best places for ``descriptor`` among the stored ones whose keys pass ``allowed`` (a
        boolean mask over the stored places in insertion order; None: all), best first."""
        if not self._keys:
            return []
        candidates = np.arange(len(self._keys)) if allowed is None else np.flatnonzero(allowed[: len(self._keys)])
        if not len(candidates):
            return []
        gap = np.abs(self._ring_keys[candidates] - ring_key(descriptor)[None]).sum(axis=1)
        nearest = candidates[np.argsort(gap, kind='stable')[: self.ring_key_candidates]]
        distance, shift = descriptor_distance(descriptor, np.stack([self._descriptors[i] for i in nearest]))
        order = np.argsort(distance, kind='stable')[:count]
        step = 2 * math.pi / self.config.sectors
        return [
            PlaceMatch(
                self._keys[int(nearest[i])], float(distance[i]), float(math.remainder(-shift[i] * step, 2 * math.pi))
            )
            for i in order
        ]
