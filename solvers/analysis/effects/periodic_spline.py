"""A periodic error of one joint as a smooth function of its angle: a periodic cubic spline.

For errors that are periodic but not a few sinusoids (a worn tooth, an encoder's bump), the
``cyclic_joint_error`` cause offers, per joint, Delta q_j = sum_k c_k B_k(q_j) with K cubic
B-splines on K knots evenly spaced over the turn (wrapping round at 2 pi). K is the spline's
effective degrees of freedom; it is chosen from KNOTS (at most twice the joint's order bound:
knots closer than the sampled angles are not resolved) by grouped cross-validation on the
joint's own problem: the residual of the geometric fit along the joint's direction of effect,
folds of neighbouring configurations kept together (path data: each fold's training also
leaves out the rows next to it, ``crossval.FoldIds.exclude``). Inside the analysis' nested
selection the count is chosen again on each fold's training rows alone. The analysis then scores the chosen
spline against the rigid model and every other candidate as it scores them all.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.estimation.crossval import inner_fold_ids

# 96 and 128: on a tracker-measured UR10 (11 911 poses) every moving joint's held-out choice was 64, the
# grid's edge (a choice at the edge of its grid is no choice); with 128 the search reached 0.109 mm held-out
# mean instead of 0.129. Twice the joint's order bound still caps the count where the angles are sparse.
KNOTS = (8, 12, 16, 24, 32, 48, 64, 96, 128)
RIDGE = 1e-9  # relative: keeps a knot interval without data from making the fit singular


def basis(qj: np.ndarray, knots: int) -> np.ndarray:
    """(N, knots) periodic cubic B-splines at the angles qj (rad)."""
    t = np.mod(np.asarray(qj, dtype=float), 2.0 * np.pi) / (2.0 * np.pi / knots)
    u = np.mod(t[:, None] - np.arange(knots)[None, :], knots)
    out = np.zeros_like(u)
    for lo, poly in ((0, lambda x: x**3), (1, lambda x: -3 * x**3 + 12 * x**2 - 12 * x + 4),
                     (2, lambda x: 3 * x**3 - 24 * x**2 + 60 * x - 44), (3, lambda x: (4 - x) ** 3)):
        piece = (u >= lo) & (u < lo + 1)
        out[piece] = poly(u[piece]) / 6.0
    return out


def _fold_normals(qj, projected, weight, folds, knots, block_rows: int = 8192):
    """Per fold: B^T W B and B^T s over its rows, a block of rows at a time."""
    ids = np.unique(folds)
    normal, rhs = np.zeros((len(ids), knots, knots)), np.zeros((len(ids), knots))
    index = np.searchsorted(ids, folds)
    for start in range(0, len(qj), block_rows):
        rows = slice(start, start + block_rows)
        b = basis(qj[rows], knots)
        for k in np.unique(index[rows]):
            mine = index[rows] == k
            normal[k] += b[mine].T @ (b[mine] * weight[rows][mine, None])
            rhs[k] += b[mine].T @ projected[rows][mine]
    return normal, rhs


def choose_knots(qj: np.ndarray, projected: np.ndarray, weight: np.ndarray, folds: np.ndarray,
                 max_knots: int) -> int | None:
    """The knot count with the largest held-out drop of the joint's residual sum of squares, or None
    when no count lowers it. projected, weight as for ``cyclic_joint_error.periodogram``; the drop
    on a fold's rows, 2 c.(B^T s) - c.(B^T W B) c with c fitted on the other folds, needs only each
    fold's normal equations."""
    exclude = getattr(folds, "exclude", None)  # path data: rows each fold's training also leaves out
    best, best_drop = None, 0.0
    for knots in (k for k in KNOTS if k <= max_knots):
        normal, rhs = _fold_normals(qj, projected, weight, folds, knots)
        all_normal, all_rhs = normal.sum(axis=0), rhs.sum(axis=0)
        drop = 0.0
        for k in range(len(normal)):
            train, train_rhs = all_normal - normal[k], all_rhs - rhs[k]
            if exclude is not None and len(exclude[k]):
                gap = exclude[k]
                b = basis(qj[gap], knots)
                train = train - b.T @ (b * weight[gap, None])
                train_rhs = train_rhs - b.T @ projected[gap]
            train = train + RIDGE * np.trace(train) / knots * np.eye(knots)
            c = np.linalg.solve(train, train_rhs)
            drop += float(2.0 * c @ rhs[k] - c @ normal[k] @ c)
        if drop > best_drop:
            best, best_drop = knots, drop
    return best


def choose_knots_nested(qj: np.ndarray, projected: np.ndarray, weight: np.ndarray, folds: np.ndarray,
                        max_knots: int) -> tuple[int | None, list[int | None]]:
    """(``choose_knots`` on every row, [``choose_knots`` on each fold's training rows alone, the other
    folds as its inner folds]): the choice the analysis offers, and the one each fold's nested
    selection sees. Without gaps every inner problem is a sum of the same per-fold normal equations."""
    ids = np.unique(np.asarray(folds))
    exclude = getattr(folds, "exclude", None)
    if exclude is not None and any(len(e) for e in exclude):  # path data: each fold's own problem
        return (choose_knots(qj, projected, weight, folds, max_knots),
                [choose_knots(qj[rows], projected[rows], weight[rows], sub, max_knots)
                 for rows, sub in (inner_fold_ids(folds, k) for k in range(len(ids)))])
    n = len(ids)
    best, best_drop = [None] * (n + 1), [0.0] * (n + 1)  # entry n: every row
    for knots in (k for k in KNOTS if k <= max_knots):
        normal, rhs = _fold_normals(qj, projected, weight, folds, knots)
        all_normal, all_rhs = normal.sum(axis=0), rhs.sum(axis=0)
        drop = np.zeros((n + 1, n))  # [outer fold or all, held-out fold]
        for k in range(n + 1):
            for j in range(n):
                if j == k:
                    continue
                train = all_normal - normal[j] - (normal[k] if k < n else 0.0)
                train_rhs = all_rhs - rhs[j] - (rhs[k] if k < n else 0.0)
                train = train + RIDGE * np.trace(train) / knots * np.eye(knots)
                c = np.linalg.solve(train, train_rhs)
                drop[k, j] = float(2.0 * c @ rhs[j] - c @ normal[j] @ c)
        for k, d in enumerate(drop.sum(axis=1)):
            if d > best_drop[k]:
                best[k], best_drop[k] = knots, d
    return best[n], best[:n]


def within(qj: np.ndarray, coverage_rad) -> np.ndarray:
    """Which angles lie in one of the covered intervals (lo, hi)."""
    inside = np.zeros(len(qj), bool)
    for lo, hi in coverage_rad:
        inside |= (qj >= lo) & (qj <= hi)
    return inside


def coverage_json(coverage_rad) -> dict:
    return {"coverage_deg": [[float(np.rad2deg(lo)), float(np.rad2deg(hi))] for lo, hi in coverage_rad],
            "outside_coverage": "rigid model (no correction)"}


@dataclass(frozen=True)
class PeriodicSpline:
    """A fitted spline error on one joint, for use beyond the analysis (compensation)."""

    joint: int  # 1-based
    coef_rad: tuple[float, ...]  # one per knot
    coverage_rad: tuple[tuple[float, float], ...]

    def delta_rad(self, qj: np.ndarray) -> np.ndarray:
        """The joint's error at these angles; 0 (the rigid model) outside the coverage."""
        qj = np.asarray(qj, dtype=float)
        value = basis(qj, len(self.coef_rad)) @ np.asarray(self.coef_rad)
        return np.where(within(qj, self.coverage_rad), value, 0.0)

    def as_dict(self) -> dict:
        return {"joint": self.joint, "spline_knots": len(self.coef_rad), "coef_rad": list(self.coef_rad),
                "basis": "periodic cubic B-splines, knots evenly spaced from 0 over 2 pi",
                **coverage_json(self.coverage_rad)}
