"""The guard of a stage's step, one policy for the offline pipeline and the nodes, and the counters every report
names the same way.

After each step of featureAssociation or mapOptimization the core checks its own state (``health_problem()``: a
non-finite or impossible value). A poisoned state is healed at once — the odometry restarts from the next scan at
the pose reached so far, the mapping resets what is poisoned and keeps its map — and counted (``state_resets``).
A step that raised instead (the nodes catch what the offline run lets through) counts as a failure; so many in a
row (``reliability.reset_after_failures``) are taken for a poisoned state even when no check names it.
:class:`StepGuard` keeps that count and says when to heal; the caller heals and reports.

The counters (:data:`COUNTERS`) are the run's summary's, the nodes' statistics and /diagnostics', the demo's and
the batch reports': a scan that went through featureAssociation is ``scans_processed`` everywhere.
"""

from __future__ import annotations

__all__ = [
    'StepGuard',
    'COUNTERS',
    'SCANS_IN',
    'SCANS_PROCESSED',
    'SCANS_DROPPED',
    'SCANS_WITH_IMU',
    'STATE_RESETS',
    'MAPPING_STEPS',
    'MAPPING_STEPS_FAILED',
    'MAPPING_DEGENERATE',
    'KEYFRAMES',
    'ODOMETRY_RESTARTS',
]

SCANS_IN = 'scans_in'  # clouds that came in
SCANS_PROCESSED = 'scans_processed'  # scans featureAssociation processed
SCANS_DROPPED = 'scans_dropped'  # scans dropped (a bad cloud, a failed or poisoned step)
SCANS_WITH_IMU = 'scans_with_imu'  # scans the IMU was used on
STATE_RESETS = 'state_resets'  # poisoned states healed
MAPPING_STEPS = 'mapping_steps'  # steps mapOptimization made
MAPPING_STEPS_FAILED = 'mapping_steps_failed'  # steps that raised or left a poisoned state
MAPPING_DEGENERATE = 'mapping_degenerate'  # steps with a direction held by too few correspondences
KEYFRAMES = 'keyframes'  # keyframes added
ODOMETRY_RESTARTS = 'odometry_restarts'  # times the mapping followed an odometry that started again
COUNTERS = (
    SCANS_IN,
    SCANS_PROCESSED,
    SCANS_DROPPED,
    SCANS_WITH_IMU,
    STATE_RESETS,
    MAPPING_STEPS,
    MAPPING_STEPS_FAILED,
    MAPPING_DEGENERATE,
    KEYFRAMES,
    ODOMETRY_RESTARTS,
)


class StepGuard:
    """Says when a stage's state is to be healed (see the module docstring)."""

    def __init__(self, reset_after_failures: int):
        self.reset_after_failures = int(reset_after_failures)
        self.failures_in_a_row = 0

    def after_failure(self, problem: str | None) -> str | None:
        """A step raised; ``problem`` is the core's health check after it. The reason to heal, or None."""
        self.failures_in_a_row += 1
        if problem is None and self.failures_in_a_row >= self.reset_after_failures:
            problem = f'{self.reset_after_failures} steps in a row failed'
        return self._healing(problem)

    def after_step(self, problem: str | None) -> str | None:
        """A step ended; ``problem`` is the core's health check. The reason to heal, or None (a success)."""
        if problem is None:
            self.failures_in_a_row = 0
        return self._healing(problem)

    def _healing(self, problem: str | None) -> str | None:
        if problem is not None:
            self.failures_in_a_row = 0
        return problem
