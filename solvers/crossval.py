"""Grouped k-fold cross-validation on a linearised model.

Rows measured at the same or at neighbouring joint configurations carry nearly
the same information, so they go into one fold: held-out data must be data the
fit has not effectively seen. Each fold's estimate is one Gauss-Newton step from
a fit to all rows, using only the fold's training rows; near a least-squares
minimum (and the kinematics is very nearly linear over calibration-sized
changes) that step is the fold's own solution to second order.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def groups(q: np.ndarray, radius_rad: float = 0.0) -> np.ndarray:
    """Group id per row: rows within radius_rad (max over joints) of each other are linked."""
    q = np.asarray(q, dtype=float)
    if radius_rad <= 0:
        _, ids = np.unique(np.round(q, 6), axis=0, return_inverse=True)
        return np.asarray(ids).ravel()
    pairs = cKDTree(q).query_pairs(radius_rad, p=np.inf, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(q), len(q)))
    return connected_components(graph, directed=False)[1]


def fold_ids(q: np.ndarray, folds: int, seed: int = 0, radius_rad: float = 0.0) -> np.ndarray:
    """Fold of each row, whole groups at a time, folds of nearly equal group count."""
    group = groups(q, radius_rad)
    n_groups = int(group.max()) + 1
    if n_groups < folds:
        raise ValueError(f"only {n_groups} distinct configurations: too few for {folds}-fold cross-validation")
    order = np.random.default_rng(seed).permutation(n_groups)
    fold_of_group = np.empty(n_groups, dtype=int)
    fold_of_group[order] = np.arange(n_groups) % folds
    return fold_of_group[group]


def one_step_heldout(j: np.ndarray, r: np.ndarray, folds: np.ndarray, penalty: np.ndarray | None = None,
                     deviation: np.ndarray | None = None, lams=(0.0,)) -> np.ndarray:
    """Held-out point errors (len(lams), N) of a linearised least-squares model.

    j: (N, 3, p) Jacobian and r: (N, 3) residuals (predicted - measured) at the
    all-rows fit; penalty (p,) and deviation (p,): an optional L2 prior
    lam * sum(penalty * (deviation + step)^2), evaluated for every lam.
    """
    n, _, p = j.shape
    penalty = np.zeros(p) if penalty is None else penalty
    deviation = np.zeros(p) if deviation is None else deviation
    flat = j.reshape(n * 3, p)
    rows3 = np.repeat(folds, 3)
    normal_all = flat.T @ flat
    grad_all = flat.T @ r.ravel()
    errs = np.empty((len(lams), n))
    for f in np.unique(folds):
        held = folds == f
        jh = flat[rows3 == f]
        normal = normal_all - jh.T @ jh  # training rows only
        grad = grad_all - jh.T @ r[held].ravel()
        for g, lam in enumerate(lams):
            step = -_solve(normal + lam * np.diag(penalty), grad + lam * penalty * deviation)
            pred = r[held] + (jh @ step).reshape(-1, 3)
            errs[g, held] = np.linalg.norm(pred, axis=1)
    return errs


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Normal equations: Cholesky when positive definite, least squares when (near) singular."""
    try:
        c = np.linalg.cholesky(a)
        return np.linalg.solve(c.T, np.linalg.solve(c, b))
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(a, b, rcond=None)[0]
