"""Least squares over many measurements without the whole Jacobian in memory.

A calibration file may hold hundreds of thousands of rows while the unknowns are a few
dozen, so everything the solvers need from a Jacobian J (3N x p) is accumulated a block
of rows at a time:

- ``RFactor``: the R factor of J (J = Q R, R p x p), updated with each block by a QR of
  [R; block] (the tall-skinny QR). Singular values, right singular vectors, column subsets
  and least-squares residual norms of J are those of R, as accurate as from J itself.
- ``NormalEquations``: J^T W J, J^T W f and the cost for Levenberg-Marquardt, with the
  weights of a robust loss as scipy.optimize.least_squares applies them.
- ``levenberg_marquardt``: the damped Gauss-Newton iteration on those normal equations,
  with scipy's termination tests, status codes and messages.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve

CHUNK_ROWS = 8192  # measurements per block: a few MB of Jacobian, large enough for whole-array operations


def chunks(n: int, size: int | None = None):
    """Slices covering range(n) in blocks of at most `size` (default CHUNK_ROWS)."""
    size = size or CHUNK_ROWS
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))


class RFactor:
    """R factor (p x p, upper triangular) of a tall matrix given a block of rows at a time."""

    def __init__(self, p: int):
        self.p = p
        self._r = np.zeros((0, p))

    def add(self, block: np.ndarray) -> None:
        if len(block):
            self._r = np.linalg.qr(np.vstack([self._r, block]), mode="r")

    @property
    def r(self) -> np.ndarray:
        out = np.zeros((self.p, self.p))
        out[: len(self._r)] = self._r
        return out


def stacked_r(factors) -> np.ndarray:
    """R factor of the rows of several R factors (or matrices) stacked."""
    factors = [np.asarray(f) for f in factors]
    p = factors[0].shape[1]
    acc = RFactor(p)
    acc.add(np.vstack(factors))
    return acc.r


# -- robust losses, as scipy.optimize.least_squares defines them: rho(z), z = (f / C)^2 --------------------

def _loss(name: str, z: np.ndarray):
    """rho, rho', rho'' at z."""
    if name == "soft_l1":
        t = 1.0 + z
        return 2.0 * (np.sqrt(t) - 1.0), t**-0.5, -0.5 * t**-1.5
    if name == "huber":
        small = z <= 1.0
        zs = np.where(small, 1.0, z)
        return (np.where(small, z, 2.0 * np.sqrt(zs) - 1.0), np.where(small, 1.0, zs**-0.5),
                np.where(small, 0.0, -0.5 * zs**-1.5))
    if name == "cauchy":
        t = 1.0 + z
        return np.log1p(z), 1.0 / t, -1.0 / t**2
    raise ValueError(f"unknown loss {name!r}")


class NormalEquations:
    """Cost 0.5 sum rho(f^2), gradient J^T rho' f and the Gauss-Newton matrix J^T W J of a
    least-squares problem given a block of rows at a time (loss "linear": rho(s) = s)."""

    def __init__(self, p: int, loss: str = "linear", f_scale: float = 1.0):
        self.loss, self.c2 = loss, float(f_scale) ** 2
        self.cost = 0.0
        self.a = np.zeros((p, p))
        self.g = np.zeros(p)

    def add(self, j: np.ndarray | None, f: np.ndarray) -> None:
        """Rows j (n x p; None for the cost alone) with residuals f (n)."""
        if self.loss == "linear":
            self.cost += 0.5 * float(f @ f)
            if j is not None:
                self.a += j.T @ j
                self.g += j.T @ f
            return
        z = f * f / self.c2
        rho, d1, d2 = _loss(self.loss, z)
        self.cost += 0.5 * self.c2 * float(rho.sum())
        if j is not None:
            w = np.maximum(d1 + 2.0 * d2 * z, np.finfo(float).eps)
            self.a += j.T @ (j * w[:, None])
            self.g += j.T @ (d1 * f)

    def diagonal(self) -> np.ndarray:
        return np.diag(self.a)

    def product(self, s: np.ndarray) -> np.ndarray:
        return self.a @ s

    def damped_step(self, mu: float, d: np.ndarray) -> np.ndarray:
        """-(A + mu D^2)^-1 g, D = diag(d), solved in the scaled variables D s."""
        return _solve_damped(self.a / np.outer(d, d), self.g / d, mu) / d


MESSAGES = {
    0: "The maximum number of function evaluations is exceeded.",
    1: "`gtol` termination condition is satisfied.",
    2: "`ftol` termination condition is satisfied.",
    3: "`xtol` termination condition is satisfied.",
    4: "Both `ftol` and `xtol` termination conditions are satisfied.",
}


@dataclass(frozen=True)
class Solution:
    x: np.ndarray
    cost: float
    nfev: int
    njev: int
    status: int  # as scipy.optimize.least_squares: 0 evaluation limit, 1 gtol, 2 ftol, 3 xtol, 4 ftol and xtol
    message: str


def levenberg_marquardt(evaluate, x0: np.ndarray, x_scale: np.ndarray, ftol: float = 1e-12,
                        xtol: float = 1e-12, gtol: float = 1e-12, max_nfev: int | None = None) -> Solution:
    """Minimise a least-squares cost given as normal equations.

    evaluate(x, jac) returns a ``NormalEquations`` at x (with the matrix and gradient
    when jac is true, the cost alone otherwise), or any object with its ``cost``, ``g``,
    ``diagonal``, ``product`` and ``damped_step`` (a structured J^T J that solves its own
    damped steps, as ``fixtures.point_blocks.BlockSystem`` does). Steps solve
    (A + mu D^2) s = -g with D = 1 / x_scale; mu follows the gain ratio (Nielsen's rule).
    Termination as scipy's "lm": ftol on the relative cost reduction, actual and predicted;
    xtol on the scaled step; gtol on the largest cosine between the residual and a column.
    """
    x = np.asarray(x0, dtype=float).copy()
    d = 1.0 / np.asarray(x_scale, dtype=float)
    max_nfev = max_nfev or 100 * (len(x) + 1)
    ne = evaluate(x, True)
    nfev = njev = 1
    mu, nu = None, 2.0
    while True:
        cost, g = ne.cost, ne.g
        diagonal = ne.diagonal()
        col = np.sqrt(np.clip(diagonal, 0.0, None))
        fnorm = np.sqrt(2.0 * cost)
        if cost == 0.0 or len(x) == 0:
            return Solution(x, cost, nfev, njev, 1, MESSAGES[1])
        cosines = np.abs(g[col > 0]) / (col[col > 0] * fnorm)
        if not cosines.size or cosines.max() <= gtol:
            return Solution(x, cost, nfev, njev, 1, MESSAGES[1])
        if mu is None:
            mu = 1e-3 * max(float(np.max(diagonal / d**2)), 1e-300)
        while True:
            step = ne.damped_step(mu, d)
            x_new = x + step
            new = evaluate(x_new, False)
            nfev += 1
            predicted = -(g @ step + 0.5 * step @ ne.product(step))
            actual = cost - new.cost if np.isfinite(new.cost) else -np.inf
            ratio = actual / predicted if predicted > 0 else 0.0
            accepted = ratio > 1e-4
            if accepted:
                mu *= max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3)
                nu = 2.0
                x, cost = x_new, new.cost
            else:
                mu *= nu
                nu *= 2.0
            ftol_ok = abs(actual) <= ftol * ne.cost and predicted <= ftol * ne.cost and ratio <= 2.0
            xtol_ok = np.linalg.norm(d * step) <= xtol * (xtol + np.linalg.norm(d * x))
            if ftol_ok or xtol_ok:
                status = 4 if ftol_ok and xtol_ok else 2 if ftol_ok else 3
                return Solution(x, cost, nfev, njev, status, MESSAGES[status])
            if nfev >= max_nfev:
                return Solution(x, cost, nfev, njev, 0, MESSAGES[0])
            if accepted:
                ne = evaluate(x, True)
                njev += 1
                break


def _solve_damped(a: np.ndarray, g: np.ndarray, mu: float) -> np.ndarray:
    """-(a + mu I)^-1 g; Cholesky, least squares when (near) singular."""
    m = a + mu * np.eye(len(a))
    try:
        return -cho_solve(cho_factor(m, lower=True, check_finite=False), g, check_finite=False)
    except np.linalg.LinAlgError:
        return -np.linalg.lstsq(m, g, rcond=None)[0]
