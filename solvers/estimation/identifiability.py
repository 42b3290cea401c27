"""Which parameters can this data separate?

Works on the *scaled* Jacobian: lengths in mm, angles multiplied by a
characteristic reach so that one unit of every column moves the target by
about one millimetre. Base and target-offset columns are always kept (they are
nuisance unknowns every calibration must estimate); the kinematic columns are
projected onto their orthogonal complement, the numerical rank of what remains
is read off its singular values, and the parameters to keep are chosen by the
subset selection of Golub, Klema and Stewart (pivoted QR of the leading right
singular vectors). Everything else is held at nominal and reported by name.

After a fit, the second half judges the estimates themselves from the fit's
covariance: which lie outside the bounds a person can trust (``failures``), which
geometric parameter to hold so that they come back inside (``to_hold``), and which
estimates the data sees only in combination (``correlated_groups``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import qr, svd

STRUCTURAL_RTOL = 1e-7
TIE_RTOL = 1e-6  # column norms this close count as a tie in the subset selection


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
    """Indices of `rank` columns that best span the dominant subspace (rows of vt).

    QR with column pivoting, written out so that a tie is settled the same way every
    time: parameters the data sees only as a sum (offsets along parallel axes) have
    equal norms here up to rounding, and the first of them in parameter order is kept.
    """
    if rank == 0:
        return np.array([], dtype=int)
    a = np.array(vt[:rank], dtype=float)
    chosen: list[int] = []
    for _ in range(rank):
        norms = np.linalg.norm(a, axis=0)
        norms[chosen] = -1.0
        pick = int(np.flatnonzero(norms >= norms.max() * (1.0 - TIE_RTOL))[0])
        chosen.append(pick)
        u = a[:, pick] / norms[pick]
        a -= np.outer(u, u @ a)
    return np.sort(chosen)


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
            with_condition: bool = True, n_rows: int | None = None) -> Identifiability:
    """Decide which candidate columns to estimate.

    j_scaled: (m, n) scaled Jacobian; nuisance: bool mask of columns always kept
    (base, targets); candidates: bool mask of kinematic columns that may be kept.
    With noise_mm, a direction whose estimate would scatter more than prior_mm
    (its singular value below noise_mm / prior_mm) counts as not identifiable:
    estimating it would add more error than it removes. basis: a precomputed
    ``nuisance_basis`` of the same nuisance columns.

    j_scaled may be the R factor of the scaled Jacobian instead (J = Q R with orthonormal
    Q: the same singular values, subsets and projections); n_rows then gives J's row
    count, on which the structural tolerance depends.
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
    rows = k.shape[0] if n_rows is None else n_rows
    structural = int(np.sum(s > STRUCTURAL_RTOL * top * np.sqrt(rows))) if top > 0 else 0
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


# --- after the fit: which estimates can a person trust? ---------------------------------
#
# The analysis above judges directions before the fit, against the noise. A cross-validated
# prior weight of 0 (or plain least squares) still estimates every structurally identifiable
# direction, and a direction the data hardly sees lets strongly correlated parameters move
# together by centimetres and degrees while the predicted target positions barely change.
# The validation error is then fine and the table of values is not: these functions find
# such estimates from the fit's covariance so that the fit can hold them at nominal.

CORRELATED_R = 0.95  # |r| above which two estimates are reported as one group


@dataclass(frozen=True)
class HeldParameter:
    """A parameter the fit moved where a person could not trust it, held at nominal instead."""

    name: str
    reason: str  # in words, with the bound it broke
    value: float  # what the fit gave before it was held (mm or rad, as x)
    std: float  # its standard deviation in that fit (mm or rad)
    nominal: float  # what it is held at (mm or rad)
    is_angle: bool
    partners: tuple[str, ...]  # estimates it moved together with (|r| > CORRELATED_R) in that fit
    rms_rise_mm: float  # how much the calibration rms error rose when it was held


@dataclass(frozen=True)
class CorrelatedGroup:
    """Estimates the data sees mostly as one combination (|r| > CORRELATED_R between them)."""

    names: tuple[str, ...]
    max_abs_r: float
    effect_mm: float  # rms change of the predicted target positions from the group's joint move off nominal
    single_effect_mm: float  # the same for the member whose move alone changes them most


@dataclass(frozen=True)
class Failure:
    index: int  # into x
    ratio: float  # how far past its bound (> 1)
    reason: str
    spread: bool  # True: its standard deviation broke the bound; False: its distance from nominal


def trust_bounds(is_angle: np.ndarray, scale: np.ndarray, slack_mm: float, max_std_mm: float,
                 max_std_rad: float, plausible_mm: float, plausible_rad: float):
    """Per entry of x: bound on its standard deviation and on its distance from nominal.

    slack_mm, the nominal model's own error at the targets, widens the plausible
    distance: an error of e mm leaves room for a length e mm off, or an angle e / reach
    off (scale is 1 / reach for angles), so a robot whose drawing is a centimetre off
    keeps that real finding.
    """
    max_std = np.where(is_angle, max_std_rad, max_std_mm)
    plausible = np.where(is_angle, np.maximum(plausible_rad, slack_mm * scale), max(plausible_mm, slack_mm))
    return max_std, plausible


def human(value: float, is_angle: bool) -> str:
    return f"{np.rad2deg(value):.3g} deg" if is_angle else f"{value:.3g} mm"


def failures(names, is_angle, checked, x, ref, std, max_std, plausible, skip=()) -> list[Failure]:
    """Checked entries of x outside their bounds (ref: the nominal values), with the reason in words."""
    out = []
    for i in np.flatnonzero(checked):
        if names[i] in skip:
            continue
        spread, far = std[i] / max_std[i], abs(x[i] - ref[i]) / plausible[i]
        if max(spread, far) <= 1.0:
            continue
        if spread >= far:
            reason = (f"standard deviation {human(std[i], is_angle[i])} above the "
                      f"{human(max_std[i], is_angle[i])} bound")
        else:
            reason = (f"{human(abs(x[i] - ref[i]), is_angle[i])} from nominal, beyond the plausible "
                      f"{human(plausible[i], is_angle[i])}")
        out.append(Failure(int(i), float(max(spread, far)), reason, bool(spread >= far)))
    return out


def correlation(cov: np.ndarray) -> np.ndarray:
    d = np.sqrt(np.clip(np.diag(cov), 0, None))
    d[d == 0] = 1.0
    return cov / np.outer(d, d)


def groups(corr: np.ndarray, threshold: float = CORRELATED_R) -> list[np.ndarray]:
    """Connected groups (two members or more) of the graph |r| > threshold, as index arrays."""
    linked = np.abs(corr) > threshold
    np.fill_diagonal(linked, False)
    seen = np.zeros(len(corr), bool)
    out = []
    for start in range(len(corr)):
        if seen[start] or not linked[start].any():
            continue
        members, todo = [], [start]
        seen[start] = True
        while todo:
            i = todo.pop()
            members.append(i)
            for j in np.flatnonzero(linked[i] & ~seen):
                seen[j] = True
                todo.append(j)
        out.append(np.sort(members))
    return out


def to_hold(cov_scaled: np.ndarray, f: int, holdable: np.ndarray, spread: bool) -> int | None:
    """Which estimate to hold at nominal so that estimate f can be trusted (indices into cov).

    For a spread failure: the eigen-direction of the covariance (in scaled units, mm at
    the target) that contributes most to f's variance is the direction the data hardly
    sees; the holdable estimate with the largest share in it is the one to hold, as in
    subset selection. A well-determined estimate that is merely far from nominal is held
    itself when it may be. None when no holdable estimate takes part (f stays as it is).
    """
    if not spread and holdable[f]:
        return f
    lam, vec = np.linalg.eigh(cov_scaled)
    k = int(np.argmax(np.clip(lam, 0, None) * vec[f] ** 2))
    share = np.where(holdable, np.abs(vec[:, k]), 0.0)
    if share.max() < 0.1:  # the weak direction lives in base and target offsets alone
        return f if holdable[f] else None
    return int(np.argmax(share))


def correlated_groups(names, idx: np.ndarray, cov: np.ndarray, base: np.ndarray,
                      effect_mm) -> tuple[CorrelatedGroup, ...]:
    """The groups of ``groups`` over the estimates idx (cov over them), as records.

    base: mask over x of entries a group may not consist of alone (the instrument
    transform: its correlations say nothing about the robot). effect_mm(members): rms
    change of the predicted targets when these entries of x go back to nominal.
    Small against the members' single effects means the data sees only their sum.
    """
    corr = correlation(cov)
    out = []
    for g in groups(corr):
        members = idx[g]
        if base[members].all():
            continue
        sub = np.abs(corr[np.ix_(g, g)])
        np.fill_diagonal(sub, 0.0)
        out.append(CorrelatedGroup(
            names=tuple(names[m] for m in members), max_abs_r=float(sub.max()),
            effect_mm=effect_mm(members), single_effect_mm=max(effect_mm([m]) for m in members)))
    return tuple(out)
