"""The loop-closure method, chosen once from ``loop_closure.method`` when mapOptimization is built
(:func:`make_loop_method`): what it detects, how a candidate is closed, and what the map around the robot is while
it runs. The mapper calls it; it calls back only the mapper's graph and keyframes.

* :class:`VerifiedLoops` (default): Scan Context and radius candidates, verified by registration, entered once a
  second loop agrees (:class:`~lego_loam_py.core.loop.closure.LoopCloser`); the map around the robot stays the
  radius map; its clouds are in the keyframes' frames, lidar axes.
* :class:`OriginalLoops` (docs/original.md §6.3): the nearest keyframe within the radius, point-to-point ICP,
  accepted by fitness; with it switched on the map around the robot is the last keyframes, as the original's; its
  clouds are in the world (camera axes).
"""

from __future__ import annotations

from lego_loam_py.core.loop.closure import LoopCandidate, LoopCloser, LoopResult, align_loop, find_loop_candidate
from lego_loam_py.core.params.types import LoopClosureParams

__all__ = ['VerifiedLoops', 'OriginalLoops', 'make_loop_method']


class VerifiedLoops:
    """``loop_closure.method: verified`` (see the module docstring)."""

    name = 'verified'
    recent_keyframes_as_map = False  # the map around the robot: the keyframes within the search radius
    clouds_in_world = False  # candidate clouds: the keyframes' frames, lidar axes

    def __init__(self, params: LoopClosureParams):
        self.closer = LoopCloser(params)

    def detect(self, mapper) -> LoopCandidate | None:
        """A candidate for the mapper's newest keyframe (under its lock)."""
        return self.closer.detect(mapper.keyframes, mapper.keyframe_positions)

    def close(self, mapper, candidate: LoopCandidate) -> LoopResult:
        """Verify (without the mapper's lock: it takes a while), then admit under it; the loops that a second one
        confirmed enter the graph."""
        loop, fit = self.closer.verify(candidate)
        with mapper.lock:
            ready = self.closer.admit(loop, fit, mapper.keyframes, mapper.latest_odometry_ns)
            if ready:
                mapper.add_verified_loops(ready)
            mapper.loops.append(loop)
        return loop


class OriginalLoops:
    """``loop_closure.method: original`` (see the module docstring)."""

    name = 'original'
    recent_keyframes_as_map = True
    clouds_in_world = True

    def __init__(self, params: LoopClosureParams):
        self.params = params

    def detect(self, mapper) -> LoopCandidate | None:
        return find_loop_candidate(
            mapper.keyframes, mapper.keyframe_positions, mapper.current_position, mapper.latest_odometry_ns, self.params
        )

    def close(self, mapper, candidate: LoopCandidate) -> LoopResult:
        loop = align_loop(candidate, self.params)
        if loop.accepted:
            with mapper.lock:
                loop.constrain(mapper.keyframe_pose(candidate.latest), mapper.keyframe_pose(candidate.candidate))
                mapper.add_loop_factor(candidate.latest, candidate.candidate, loop.relative, loop.variances)
        mapper.loops.append(loop)
        return loop


def make_loop_method(params: LoopClosureParams) -> VerifiedLoops | OriginalLoops:
    """The method ``loop_closure.method`` names."""
    return OriginalLoops(params) if params.method == 'original' else VerifiedLoops(params)
