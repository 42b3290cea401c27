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
from scipy.linalg import qr

STRUCTURAL_RTOL = 1e-7


@dataclass(frozen=True)
class Identifiability:
    keep: np.ndarray  # bool mask over the candidate columns
    singular_values: np.ndarray  # of the projected kinematic block, scaled units
    rank: int
    structural_rank: int
    condition: float  # of the kept scaled Jacobian


def _select(block: np.ndarray, rank: int) -> np.ndarray:
    """Indices of `rank` columns of block that best span its dominant subspace."""
    if rank == 0:
        return np.array([], dtype=int)
    _, _, vt = np.linalg.svd(block, full_matrices=False)
    _, _, piv = qr(vt[:rank], pivoting=True, mode="economic")
    return np.sort(piv[:rank])


def analyse(j_scaled: np.ndarray, nuisance: np.ndarray, candidates: np.ndarray,
            noise_mm: float | None = None, prior_mm: float = 1.0) -> Identifiability:
    """Decide which candidate columns to estimate.

    j_scaled: (m, n) scaled Jacobian; nuisance: bool mask of columns always kept
    (base, targets); candidates: bool mask of kinematic columns that may be kept.
    With noise_mm, a direction whose estimate would scatter more than prior_mm
    (its singular value below noise_mm / prior_mm) counts as not identifiable:
    estimating it would add more error than it removes.
    """
    keep = nuisance.copy()
    b = j_scaled[:, nuisance]
    # nuisance columns that are themselves degenerate (e.g. one orientation only) are dropped
    if b.shape[1]:
        qb, rb, pb = qr(b, pivoting=True, mode="economic")
        diag = np.abs(np.diag(rb))
        ok = diag > STRUCTURAL_RTOL * max(diag[0], 1e-300)
        idx = np.flatnonzero(nuisance)
        keep[idx[pb[~ok]]] = False
        qb = qb[:, ok]
    else:
        qb = np.zeros((j_scaled.shape[0], 0))
    cand = np.flatnonzero(candidates & ~nuisance)
    k = j_scaled[:, cand]
    k = k - qb @ (qb.T @ k)
    s = np.linalg.svd(k, compute_uv=False) if k.size else np.zeros(0)
    top = s[0] if len(s) else 0.0
    structural = int(np.sum(s > STRUCTURAL_RTOL * top * np.sqrt(k.shape[0]))) if top > 0 else 0
    rank = structural
    if noise_mm is not None and rank:
        rank = min(rank, int(np.sum(s >= noise_mm / prior_mm)))
    chosen = cand[_select(k, rank)]
    keep[chosen] = True
    kept = j_scaled[:, keep]
    sv = np.linalg.svd(kept, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if len(sv) and sv[-1] > 0 else float("inf")
    return Identifiability(keep=keep, singular_values=s, rank=rank, structural_rank=structural,
                           condition=cond)
