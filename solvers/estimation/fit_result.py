"""The words every fit in solvers reports how it ended with, as scipy.optimize.OptimizeResult has them.

A fit's result class derives from :class:`FitResult` and so carries ``status``, ``message``,
``success`` and ``nfev`` (and ``covariance`` where the fit has one) besides its own numbers.
A fit made by ``scipy.optimize.least_squares`` (or :func:`.lsq.levenberg_marquardt`, which
mimics it) passes on the solver's values (:func:`from_solver`); a closed-form fit reports
status 1 and success with a message saying what was solved, nfev 0 (:func:`solved`); a fit
whose data leave it degenerate reports success False and says why (:func:`degenerate`).

The fields are keyword-only, so a result class keeps its own fields positional in front.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEGENERATE = -1  # status of a fit its data leave undetermined (scipy's -1: improper input)
SOLVED = 1  # status of a closed-form fit that was solved


@dataclass(frozen=True, kw_only=True)
class FitResult:
    status: int  # as scipy.optimize.least_squares: > 0 converged, 0 evaluation limit, < 0 not solvable
    message: str  # how the fit ended, in words
    success: bool  # True when a convergence criterion was met (closed form: solved)
    nfev: int  # residual evaluations (0 for a closed-form fit)
    covariance: np.ndarray | None = None  # of the fit's parameters, None where the fit has none


def from_solver(solution) -> dict:
    """The fields of a least-squares solver's result (scipy's OptimizeResult or :class:`.lsq.Solution`)."""
    status = int(solution.status)
    return {"status": status, "message": str(solution.message), "success": status > 0, "nfev": int(solution.nfev)}


def solved(message: str, nfev: int = 0) -> dict:
    """The fields of a closed-form fit that was solved."""
    return {"status": SOLVED, "message": message, "success": True, "nfev": nfev}


def degenerate(message: str, nfev: int = 0) -> dict:
    """The fields of a fit whose data do not determine it; `message` says why."""
    return {"status": DEGENERATE, "message": message, "success": False, "nfev": nfev}
