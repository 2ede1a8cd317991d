"""The Gauss-Newton step with degeneracy projection that the odometry and the mapping share (docs/original.md
§6.2 step 7, §6.3, quirk 8.10; Zhang et al., "On degeneracy of optimization-based state estimation problems",
ICRA 2016).

A step solves the normal equations ``AᵀA x = Aᵀb``. On the first iteration of a problem the eigenvectors of
``AᵀA`` whose eigenvalues lie below a threshold, counted from the smallest up to the first that does not,
are the degenerate directions; from then on every step is projected onto the well-constrained ones, so a
corridor or a flat floor does not move the estimate along what the points cannot see.
"""

from __future__ import annotations

import numpy as np

__all__ = ['normal_equations_step', 'DegeneracyProjection', 'residual_information']


def residual_information(
    jtj: np.ndarray,
    squared_residuals: float,
    residuals: int,
    parameters: int,
    min_sigma: float,
    prior: np.ndarray | None = None,
) -> np.ndarray:
    """The Fisher information ``(JᵀJ + prior) / σ²`` of a least-squares estimate at convergence (``jtj``: of its
    weighted residuals, ``prior``: a prior's share in the residuals' units): ``σ²`` is the weighted residuals' mean
    square over their degrees of freedom (``residuals`` - ``parameters``), at least ``min_sigma`` squared (units of
    the residuals, e.g. [m]). Its inverse is the covariance of the estimate when the residuals are independent."""
    sigma2 = max(squared_residuals / max(residuals - parameters, 1), min_sigma**2)
    return (jtj if prior is None else jtj + prior) / sigma2


def normal_equations_step(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the least-squares step x of ``a x = b`` from the normal equations, ``aᵀa``); a singular ``aᵀa`` falls
    back to the minimum-norm least-squares solution."""
    ata = a.T @ a
    atb = a.T @ b
    try:
        x = np.linalg.solve(ata, atb)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(ata, atb, rcond=None)[0]
    return x, ata


class DegeneracyProjection:
    """The degenerate directions of one least-squares problem, found on its first iteration and kept (across
    scans too, as the original's members) until the next first iteration."""

    def __init__(self, dimensions: int):
        self.projection = np.eye(dimensions)
        self.degenerate = False
        # The smallest eigenvalue of the last normal matrix examined: how well the worst direction is held
        # (the original's degeneracy test compares it with the threshold).
        self.smallest_eigenvalue = float('nan')

    def update(self, ata: np.ndarray, threshold: float) -> None:
        """Find the directions of ``ata`` (the normal matrix) whose eigenvalues are below ``threshold``."""
        values, vectors = np.linalg.eigh(ata)  # ascending
        self.smallest_eigenvalue = float(values[0])
        keep = np.ones(len(values), dtype=bool)
        self.degenerate = False
        for i in range(len(values)):  # from the smallest up to the first >= threshold
            if values[i] < threshold:
                keep[i] = False
                self.degenerate = True
            else:
                break
        self.projection = vectors @ np.diag(keep.astype(float)) @ vectors.T

    def step(self, a: np.ndarray, b: np.ndarray, first: bool, threshold: float) -> np.ndarray:
        """The Gauss-Newton step of ``a x = b``, projected; ``first`` finds the degenerate directions anew."""
        x, ata = normal_equations_step(a, b)
        if first:
            self.update(ata, threshold)
        if self.degenerate:
            x = self.projection @ x
        return x
