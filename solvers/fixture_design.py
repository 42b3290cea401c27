"""Seat design for fixture calibration: which seats of which sockets to measure.

A socket (or stylus) row says only that the target was at the point, wherever the point is:
each point's position is an unknown of its own. Eliminating it leaves, of a point's rows,
only how they differ from the point's mean row: with J_i the scaled Jacobian of row i
(kinematic parameters and target offset), the information a point's n rows carry is

    sum_i (J_i - mean J)^T (J_i - mean J)

so one seat tells nothing, and a seat adds what it differs from the point's other seats.
Adding row c to a point whose n rows have mean mu adds  n/(n+1) (J_c - mu)^T (J_c - mu):
a rank-3 update, which the greedy D-optimal selection of :mod:`pose_design` (maximise
log det of the information over the chosen seats) takes in the same way. The design is
balanced: every point gets the same number of seats, chosen in turn; a Fedorov exchange
within each point follows. The known distances between points fix the arm's scale,
which no seat can: that direction is the same for every design and carried by a ridge.

Everything here uses the nominal model only (what a planner has).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers import identifiability
from cellcal.solvers.identify import scales
from cellcal.solvers.measurement_model import Layout, Observations, jacobian
from cellcal.solvers.robot_model import KinematicModel

RIDGE = 1e-6  # information of a direction no seat sees (the arm's scale), scaled units


@dataclass(frozen=True)
class SeatDesign:
    chosen: np.ndarray  # indices into the candidates, grouped by point in the order of `groups`
    log_det: float  # of the information of the chosen seats (scaled units, points eliminated)
    estimated: tuple[str, ...]  # the kinematic parameters the design is for (structurally seen)
    log_det_of: dict  # log det of other selections given to ``information`` (for comparison), by label


def seat_rows(model: KinematicModel, q: np.ndarray, target_offset) -> tuple[np.ndarray, tuple[str, ...]]:
    """(M, 3, p) scaled Jacobian of each candidate seat: the kinematic parameters and the target
    offset (no base frame: with points only, the points carry it)."""
    layout = Layout(model, ("t",))
    x = layout.initial(base=np.zeros(6), offsets=np.asarray([target_offset], dtype=float))
    obs = Observations(np.asarray(q, dtype=float), np.zeros((len(q), 3)), np.zeros(len(q), int), ("t",))
    _, j = jacobian(layout, x, obs)
    j = j * scales(layout, x, obs)
    cols = np.r_[np.arange(layout.n_kin), np.arange(layout.size)[layout.target(0)]]
    return j[:, :, cols], tuple(np.array(layout.names)[cols])


def _centred(rows: np.ndarray, group: np.ndarray) -> np.ndarray:
    out = rows.copy()
    for g in np.unique(group):
        at = group == g
        out[at] -= rows[at].mean(axis=0)
    return out


def estimable(model: KinematicModel, rows: np.ndarray, group: np.ndarray, names) -> np.ndarray:
    """Mask over the columns of ``rows``: the target offset, and the kinematic parameters the
    candidate seats can see at all (points eliminated; the same structural rule as identify)."""
    c = _centred(rows, group).reshape(-1, rows.shape[2])
    nuisance = np.zeros(rows.shape[2], bool)
    nuisance[model.n_params:] = True
    return identifiability.analyse(c, nuisance, ~nuisance, with_condition=False).keep


def information(rows: np.ndarray, group: np.ndarray, chosen) -> np.ndarray:
    """Information of the chosen seats with every point eliminated (scaled units)."""
    chosen = np.asarray(chosen, dtype=int)
    p = rows.shape[2]
    info = RIDGE * np.eye(p)
    for g in np.unique(group[chosen]):
        r = rows[chosen[group[chosen] == g]].reshape(-1, 3, p)
        d = r - r.mean(axis=0)
        info += np.einsum("nip,niq->pq", d, d)
    return info


def select_seats(model: KinematicModel, q_candidates: np.ndarray, group: np.ndarray, per_point: int, *,
                 target_offset=(0.0, 0.0, 100.0), exchange_passes: int = 2, compare: dict | None = None) -> SeatDesign:
    """Choose per_point seats of each point (group: the point of each candidate) for identification.

    compare: label -> other selections (indices) whose log det is reported next to the design's.
    """
    q = np.asarray(q_candidates, dtype=float)
    group = np.asarray(group)
    points = list(dict.fromkeys(group.tolist()))
    short = [g for g in points if np.count_nonzero(group == g) < per_point]
    if short:
        raise ValueError(f"point {short[0]!r} has {np.count_nonzero(group == short[0])} candidate seats; "
                         f"{per_point} are to be chosen")
    rows_all, names = seat_rows(model, q, target_offset)
    keep = estimable(model, rows_all, group, names)
    rows = rows_all[:, :, keep]
    p = rows.shape[2]
    info = RIDGE * np.eye(p)
    sums = {g: np.zeros((3, p)) for g in points}
    counts = {g: 0 for g in points}
    free = np.ones(len(q), bool)
    chosen: dict = {g: [] for g in points}

    def gains(g, m):
        at = np.flatnonzero((group == g) & free)
        n = counts[g]
        d = rows[at] - (sums[g] / n if n else 0.0)
        s = (d @ np.linalg.inv(m)) @ d.transpose(0, 2, 1) * (n / (n + 1.0))
        return at, np.linalg.slogdet(np.eye(3) + s)[1]

    for _ in range(per_point):
        for g in points:
            at, gain = gains(g, info)
            # the first seat of a point carries nothing alone: take the one farthest from the rest
            best = int(at[np.argmax(gain)]) if counts[g] else int(at[np.argmax(
                np.linalg.norm(rows[at] - rows[at].mean(axis=0), axis=(1, 2)))])
            n = counts[g]
            if n:
                d = rows[best] - sums[g] / n
                info = info + (n / (n + 1.0)) * d.T @ d
            sums[g] += rows[best]
            counts[g] += 1
            free[best] = False
            chosen[g].append(best)
    for _ in range(exchange_passes):
        improved = False
        for g in points:
            for slot in range(per_point):
                out = chosen[g][slot]
                rest = [c for c in chosen[g] if c != out]
                without = information(rows, group, [c for h in points if h != g for c in chosen[h]] + rest)
                sums[g], counts[g] = rows[rest].sum(axis=0), len(rest)
                free[out] = True
                at, gain = gains(g, without)
                best = int(at[np.argmax(gain)])
                chosen[g][slot] = best
                free[best] = False
                sums[g], counts[g] = rows[chosen[g]].sum(axis=0), per_point
                improved |= best != out
        info = information(rows, group, [c for g in points for c in chosen[g]])
        if not improved:
            break
    picked = np.array([c for g in points for c in chosen[g]], dtype=int)
    log_det = float(np.linalg.slogdet(information(rows, group, picked))[1])
    others = {label: float(np.linalg.slogdet(information(rows, group, sel))[1])
              for label, sel in (compare or {}).items()}
    return SeatDesign(chosen=picked, log_det=log_det, estimated=tuple(np.array(names)[keep][: int(keep[:model.n_params].sum())]),
                      log_det_of=others)
