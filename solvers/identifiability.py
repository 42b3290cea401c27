"""Which parameters can this data separate?

Works on the *scaled* Jacobian: lengths in mm, angles multiplied by a
characteristic reach so that one unit of every column moves the target by
about one millimetre. Base and target-offset columns are always kept (they are
nuisance unknowns every calibration must estimate); the kinematic columns are
projected onto their orthogonal complement, the numerical rank of what remains
is read off its singular values, and the parameters to keep are chosen by the
subset selection of Golub, Klema and Stewart (pivoted QR of the leading right
singular vectors). Everything else is held at nominal and reported by name.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import qr, svd

STRUCTURAL_RTOL = 1e-7


@dataclass(frozen=True)
class Identifiability:
    keep: np.ndarray  # bool mask over the candidate columns
    singular_values: np.ndarray  # of the projected kinematic block, scaled units
    rank: int
    structural_rank: int
    condition: float  # of the kept scaled Jacobian


def _svd(a: np.ndarray):
    """Singular values and right vectors; LAPACK's fast divide-and-conquer driver can fail
    to converge on nearly rank-deficient triangles, the QR-iteration driver does not."""
    try:
        _, s, vt = np.linalg.svd(a, full_matrices=False)
    except np.linalg.LinAlgError:
        _, s, vt = svd(a, full_matrices=False, lapack_driver="gesvd")
    return s, vt


def _select(vt: np.ndarray, rank: int) -> np.ndarray:
    """Indices of `rank` columns that best span the dominant subspace (rows of vt)."""
    if rank == 0:
        return np.array([], dtype=int)
    _, _, piv = qr(vt[:rank], pivoting=True, mode="economic")
    return np.sort(piv[:rank])


def nuisance_basis(j_scaled: np.ndarray, nuisance: np.ndarray):
    """Orthonormal basis of the nuisance columns' span, and which of them are independent.

    Computed once, it lets many candidate column sets be analysed against the same
    nuisance block (as the discrepancy analysis does for every candidate effect).
    """
    idx = np.flatnonzero(nuisance)
    ok_cols = np.zeros(len(nuisance), bool)
    if not len(idx):
        return np.zeros((j_scaled.shape[0], 0)), ok_cols
    qb, rb, pb = qr(j_scaled[:, idx], pivoting=True, mode="economic")
    diag = np.abs(np.diag(rb))
    ok = diag > STRUCTURAL_RTOL * max(diag[0], 1e-300)
    ok_cols[idx[pb[ok]]] = True
    return qb[:, ok], ok_cols


def analyse(j_scaled: np.ndarray, nuisance: np.ndarray, candidates: np.ndarray,
            noise_mm: float | None = None, prior_mm: float = 1.0, basis=None,
            with_condition: bool = True) -> Identifiability:
    """Decide which candidate columns to estimate.

    j_scaled: (m, n) scaled Jacobian; nuisance: bool mask of columns always kept
    (base, targets); candidates: bool mask of kinematic columns that may be kept.
    With noise_mm, a direction whose estimate would scatter more than prior_mm
    (its singular value below noise_mm / prior_mm) counts as not identifiable:
    estimating it would add more error than it removes. basis: a precomputed
    ``nuisance_basis`` of the same nuisance columns.
    """
    qb, keep = nuisance_basis(j_scaled, nuisance) if basis is None else basis
    keep = keep.copy()
    cand = np.flatnonzero(candidates & ~nuisance)
    k = j_scaled[:, cand]
    k = k - qb @ (qb.T @ k)
    if k.size:  # singular values and right vectors of the tall block via its small R factor
        s, vt = _svd(qr(k, mode="r")[0][: k.shape[1]])
    else:
        s, vt = np.zeros(0), np.zeros((0, 0))
    top = s[0] if len(s) else 0.0
    structural = int(np.sum(s > STRUCTURAL_RTOL * top * np.sqrt(k.shape[0]))) if top > 0 else 0
    rank = structural
    if noise_mm is not None and rank:
        rank = min(rank, int(np.sum(s >= noise_mm / prior_mm)))
    chosen = cand[_select(vt, rank)]
    keep[chosen] = True
    cond = float("nan")
    if with_condition:
        sv = np.linalg.svd(j_scaled[:, keep], compute_uv=False)
        cond = float(sv[0] / sv[-1]) if len(sv) and sv[-1] > 0 else float("inf")
    return Identifiability(keep=keep, singular_values=s, rank=rank, structural_rank=structural,
                           condition=cond)
