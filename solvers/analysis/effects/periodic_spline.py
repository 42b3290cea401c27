"""A periodic error of one joint as a smooth function of its angle: a penalised periodic cubic spline.

For errors that are periodic but not a few sinusoids (a worn tooth, an encoder's bump), the
``cyclic_joint_error`` cause offers, per joint, Delta q_j = sum_k c_k B_k(q_j) with K cubic
B-splines on K knots evenly spaced over the turn (wrapping round at 2 pi), penalised (Eilers and
Marx, "Flexible smoothing with B-splines and penalties"): a fit adds lam * m * |D c|^2, D the
second differences of the coefficients round the turn (``roughness``), m the mean squared length
of the spline's columns over the fit's rows (``base.part_penalty``). Where the rows are dense the
data decide the shape; where they thin out (a knot interval at the edge of the angles a training
holds, or inside a gap of them) the function is carried smoothly across instead of resting on one
or two poses at the tail of a basis function.

K and lam are chosen where every data-driven choice is: by the analysis' forward search, on all
rows and again inside each fold's training rows. K is offered at the finest count the joint's
sampled angles resolve and at a quarter and a sixteenth of it (``knot_counts``), each at every lam
of SMOOTHING: each (K, lam) is a place, the places of one joint alternatives (one slot), a count's
weights sharing its columns. A count is offered only where it lowers the held-out rms residual of
the joint's own problem by SCREEN_GAIN at some weight (``screen``), decided on all rows and again on
each fold's training rows.

Why (measured in docs/causes.md). A spline whose knot count was chosen per joint, its coefficients
free, was fitted in each fold as the search scored it; on a tracker-measured UR10 (1 495 poses)
the held-out errors of the folds' choices were 0.196 mm mean against a median of 0.150: three poses
(a straight elbow no training pose came within 12 deg of, a shoulder angle at the edge of its range)
were predicted 23 to 41 mm off, and the folds, on fewer rows, chose coarser splines than all rows
did. Penalised: 0.119 mm (0.078 on the 11 911-pose series).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.estimation.crossval import _solve, inner_fold_ids

# the knot counts a spline may have (``knot_counts``); 128: 2.8 deg apart, finer than the cyclic content measured
# on real arms (orders to ~40)
KNOTS = (8, 12, 16, 24, 32, 48, 64, 96, 128)
# the penalty weights lam a spline is offered at (module docstring), relative to its mean squared column length:
# from barely bending the data's shape to a function nearly as smooth as its count allows
SMOOTHING = (1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0)
SCREEN_GAIN = 0.07  # the search's GAIN (``selection.GAIN``: a test holds them equal), which a spline must reach
#                     on its joint's own problem to be offered (``screen``)


def knot_counts(order_bound: int) -> tuple[int, ...]:
    """The knot counts a joint's spline is offered at, finest first: the largest of KNOTS up to twice the joint's
    order bound (knots closer than the sampled angles are not resolved), and every fourth count below it
    (a quarter as many knots each), down to KNOTS[0]; () when the bound allows none."""
    fits = [k for k in KNOTS if k <= 2 * order_bound]
    return tuple(fits[::-1][::4]) if fits else ()


def _fold_normals(qj, projected, weight, folds, knots, block_rows: int = 8192):
    """Per fold: B^T W B and B^T s over its rows, a block of rows at a time, and the residual sum of squares
    of the joint's problem with no spline, s^2 / w."""
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
    moved = weight > 0.0
    plain = np.bincount(index[moved], projected[moved] ** 2 / weight[moved], minlength=len(ids))
    return normal, rhs, plain


def roughness(knots: int) -> np.ndarray:
    """(knots, knots) the sum of squared second differences of a periodic spline's coefficients, as a quadratic
    form (D^T D, D the circulant second difference): 0 for a constant, small for a smooth function."""
    d = np.eye(knots) - 2.0 * np.roll(np.eye(knots), 1, axis=1) + np.roll(np.eye(knots), 2, axis=1)
    return d.T @ d


def _drop(train, train_rhs, held, held_rhs, lam, rough) -> float:
    """Held-out drop of the joint's residual sum of squares, 2 c.(B^T s) - c.(B^T W B) c, with c fitted on the
    training's normal equations under the penalty of weight lam (``base.part_penalty``: lam times the mean
    diagonal times the roughness), and a vanishing ridge (the roughness leaves a constant free)."""
    m = float(np.mean(np.diagonal(train)))
    c = _solve(train + lam * m * rough + 1e-12 * m * np.eye(len(train)), train_rhs)
    return float(2.0 * c @ held_rhs - c @ held @ c)


def _enough(drop: float, plain: float) -> bool:
    """Does a held-out drop of the residual sum of squares from plain lower the rms by SCREEN_GAIN?"""
    return drop > 0.0 and drop >= (1.0 - (1.0 - SCREEN_GAIN) ** 2) * plain


def screen(qj: np.ndarray, projected: np.ndarray, weight: np.ndarray, folds: np.ndarray, knots: int) -> bool:
    """Does the joint's spline lower its own problem's held-out rms residual by SCREEN_GAIN at some weight? The
    joint's own problem: the geometric fit's residual along the joint's direction of effect (projected, weight
    as for ``cyclic_joint_error.periodogram``), the other joints' errors part of its noise. A spline that gains
    less there is not offered: of all it can explain, the search would take it only for what it gains beside
    the others, by the same GAIN; and a spline of many coefficients at every joint of a many-joint arm costs
    the search what it cannot gain. The drop on a fold's rows needs only each fold's normal equations."""
    exclude = getattr(folds, "exclude", None)  # path data: rows each fold's training also leaves out
    normal, rhs, plain = _fold_normals(qj, projected, weight, folds, knots)
    all_normal, all_rhs = normal.sum(axis=0), rhs.sum(axis=0)
    rough = roughness(knots)
    drop = np.zeros(len(SMOOTHING))
    for k in range(len(normal)):
        train, train_rhs = all_normal - normal[k], all_rhs - rhs[k]
        if exclude is not None and len(exclude[k]):
            gap = exclude[k]
            b = basis(qj[gap], knots)
            train = train - b.T @ (b * weight[gap, None])
            train_rhs = train_rhs - b.T @ projected[gap]
        drop += [_drop(train, train_rhs, normal[k], rhs[k], lam, rough) for lam in SMOOTHING]
    return _enough(float(drop.max()), float(plain.sum()))


def screen_nested(qj: np.ndarray, projected: np.ndarray, weight: np.ndarray, folds: np.ndarray,
                  knots: int) -> tuple[bool, frozenset]:
    """(``screen`` on every row, the folds whose training rows alone pass it, the other folds as inner folds):
    whether the spline is offered to the search on all rows, and inside which folds."""
    ids = np.unique(np.asarray(folds))
    exclude = getattr(folds, "exclude", None)
    if exclude is not None and any(len(e) for e in exclude):  # path data: each fold's own problem
        inside = [k for k, (rows, sub) in enumerate(inner_fold_ids(folds, k) for k in range(len(ids)))
                  if screen(qj[rows], projected[rows], weight[rows], sub, knots)]
        return screen(qj, projected, weight, folds, knots), frozenset(inside)
    normal, rhs, plain = _fold_normals(qj, projected, weight, folds, knots)
    all_normal, all_rhs = normal.sum(axis=0), rhs.sum(axis=0)
    rough = roughness(knots)
    n = len(ids)
    drop = np.zeros((n + 1, len(SMOOTHING)))  # [outer fold or all]
    for k in range(n + 1):
        for j in range(n):
            if j == k:
                continue
            train = all_normal - normal[j] - (normal[k] if k < n else 0.0)
            train_rhs = all_rhs - rhs[j] - (rhs[k] if k < n else 0.0)
            drop[k] += [_drop(train, train_rhs, normal[j], rhs[j], lam, rough) for lam in SMOOTHING]
    held = [plain.sum() - (plain[k] if k < n else 0.0) for k in range(n + 1)]  # what each held out, in all
    passed = [_enough(float(d), float(h)) for d, h in zip(drop.max(axis=1), held)]
    return passed[n], frozenset(k for k in range(n) if passed[k])


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
