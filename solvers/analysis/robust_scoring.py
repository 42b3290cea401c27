"""The discrepancy analysis under a robust loss: row weights for the linearised fits, and a score
that gross outliers do not decide.

A few gross outliers (a tracker that locked onto a reflection, a pose measured while the arm still
moved) would otherwise pull every fit and, worse, dominate every held-out mean alike: the gain of
the right explanation would drown in errors no model can explain. Under a robust loss:

- the fits weight each measured coordinate by the loss' IRLS weight rho'((r / C)^2) at the
  geometric fit's residual r, C = 2.5 x the residuals' robust standard deviation (as ``identify``);
- a model's held-out score is the mean of its held-out errors without its largest TRIM fraction,
  so that up to that fraction of outliers never enters a comparison.
With the linear loss every weight is 1 and the score is the plain mean.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.identification.kinematic_fit import f_scale_of
from cellcal.solvers.estimation.lsq import _loss

TRIM = 0.10  # gross outliers up to 10% of the measurements stay out of every held-out score


@dataclass(frozen=True)
class RobustScoring:
    loss: str
    f_scale_mm: float
    sqrt_weight: np.ndarray | None  # (N, 3), None for the linear loss
    trim: float

    @classmethod
    def of(cls, loss: str, residuals_mm: np.ndarray) -> "RobustScoring":
        if loss == "linear":
            return cls(loss, 1.0, None, 0.0)
        f_scale = f_scale_of(residuals_mm)
        z = (np.asarray(residuals_mm) / f_scale) ** 2
        return cls(loss, f_scale, np.sqrt(_loss(loss, z)[1]), TRIM)

    def weighted(self, rows, j: np.ndarray, r: np.ndarray):
        """Jacobian rows (n, 3, p) and residuals (n, 3) of these rows, weighted."""
        if self.sqrt_weight is None:
            return j, r
        w = self.sqrt_weight[rows]
        return j * w[:, :, None], r * w

    def mean_mm(self, errors: np.ndarray) -> np.ndarray:
        return trimmed_mean(errors, self.trim)


def trimmed_mean(errors: np.ndarray, trim: float) -> np.ndarray:
    """Score of held-out errors along the last axis: the mean without the largest `trim` fraction."""
    errors = np.asarray(errors)
    if trim == 0.0:
        return errors.mean(axis=-1)
    keep = max(1, int(round((1.0 - trim) * errors.shape[-1])))
    return np.sort(errors, axis=-1)[..., :keep].mean(axis=-1)


LINEAR = RobustScoring("linear", 1.0, None, 0.0)
