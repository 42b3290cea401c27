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

A stylus contact says less: one residual, the target's distance from the ball's centre
along the ball's normal n there, d residual / d point = -n^T. Its rows are given with
their own point Jacobian (``point_jacobian``, (M, k, 3): -I for a socket's three rows,
-n^T for a contact's one), and a point is eliminated exactly: with the point's rows J
and point columns P stacked, its information is the Schur complement

    J^T J - J^T P (P^T P)^+ P^T J

(for sockets, P = -I, the centring above; a contact's first three rows carry nothing).
To first order a ball touched again and again at one spot is best (its centre is then
unknown only along that spot's normal), but the real contacts land off that spot by the
arm's error and the centre's other directions are left to the ball's curvature: on the
simulated UR10e such a plan made the arm worse than nominal. So the caller spreads the
spots over each ball and gives each contact's spot as its ``slot``: a ball's contacts take
distinct slots, the design choosing the tool's orientation and wrist at each.

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
PINV_RCOND = 1e-10  # a point direction the contacts see less than this (relative) is one they do not see


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


def _eliminated(rows: np.ndarray, group: np.ndarray, point_jacobian: np.ndarray) -> np.ndarray:
    """Each point's stacked rows with the point's columns projected out (I - P P^+) J."""
    out = rows.copy()
    for g in np.unique(group):
        at = group == g
        j, pj = rows[at].reshape(-1, rows.shape[2]), point_jacobian[at].reshape(-1, 3)
        out[at] = (j - pj @ (np.linalg.pinv(pj, rcond=PINV_RCOND) @ j)).reshape(rows[at].shape)
    return out


def estimable(model: KinematicModel, rows: np.ndarray, group: np.ndarray, names,
              point_jacobian: np.ndarray | None = None) -> np.ndarray:
    """Mask over the columns of ``rows``: the target offset, and the kinematic parameters the
    candidate seats can see at all (points eliminated; the same structural rule as identify)."""
    c = (_centred(rows, group) if point_jacobian is None else
         _eliminated(rows, group, point_jacobian)).reshape(-1, rows.shape[2])
    nuisance = np.zeros(rows.shape[2], bool)
    nuisance[model.n_params:] = True
    return identifiability.analyse(c, nuisance, ~nuisance, with_condition=False).keep


def contact_rows(rows: np.ndarray, normals) -> tuple[np.ndarray, np.ndarray]:
    """Seat rows (M, 3, p) of contacts made along `normals` (M, 3: the ball's outward unit normal at
    each contact, base frame) as contact rows: (M, 1, p) rows n^T J and their point Jacobian -n^T."""
    n = np.asarray(normals, dtype=float)
    n = n / np.linalg.norm(n, axis=1)[:, None]
    return np.einsum("mc,mcp->mp", n, rows)[:, None, :], -n[:, None, :]


def _schur(a, b, c):
    """a - b c^+ b^T for (..., p, p), (..., p, 3), (..., 3, 3): a point's rows with the point eliminated."""
    return a - b @ np.linalg.pinv(c, rcond=PINV_RCOND, hermitian=True) @ np.swapaxes(b, -1, -2)


def information(rows: np.ndarray, group: np.ndarray, chosen, point_jacobian: np.ndarray | None = None) -> np.ndarray:
    """Information of the chosen seats with every point eliminated (scaled units). point_jacobian
    (M, k, 3): each row block's derivative over its point (None: -I, sockets)."""
    chosen = np.asarray(chosen, dtype=int)
    p = rows.shape[2]
    info = RIDGE * np.eye(p)
    if point_jacobian is not None:
        for g in np.unique(group[chosen]):
            at = chosen[group[chosen] == g]
            j, pj = rows[at].reshape(-1, p), point_jacobian[at].reshape(-1, 3)
            info += _schur(j.T @ j, j.T @ pj, pj.T @ pj)
        return info
    for g in np.unique(group[chosen]):
        r = rows[chosen[group[chosen] == g]].reshape(-1, 3, p)
        d = r - r.mean(axis=0)
        info += np.einsum("nip,niq->pq", d, d)
    return info


def select_seats(model: KinematicModel, q_candidates: np.ndarray, group: np.ndarray, per_point: int, *,
                 target_offset=(0.0, 0.0, 100.0), exchange_passes: int = 2, compare: dict | None = None,
                 normals: np.ndarray | None = None, slots: np.ndarray | None = None) -> SeatDesign:
    """Choose per_point seats of each point (group: the point of each candidate) for identification.

    compare: label -> other selections (indices) whose log det is reported next to the design's.
    normals: (M, 3) for stylus contacts: the ball's outward unit normal where each candidate touches
    (one residual per contact, each ball's centre eliminated exactly); None for sockets.
    slots: (M,) with normals: a point's chosen contacts take distinct slots (e.g. each its own spot of
    the ball, so the spots the planner spread over the ball all place its centre).
    """
    q = np.asarray(q_candidates, dtype=float)
    group = np.asarray(group)
    points = list(dict.fromkeys(group.tolist()))
    short = [g for g in points if np.count_nonzero(group == g) < per_point]
    if short:
        raise ValueError(f"point {short[0]!r} has {np.count_nonzero(group == short[0])} candidate seats; "
                         f"{per_point} are to be chosen")
    rows_all, names = seat_rows(model, q, target_offset)
    if normals is not None:
        return _select_contacts(model, rows_all, names, normals, group, points, per_point, exchange_passes,
                                compare, np.arange(len(q)) if slots is None else np.asarray(slots))
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


def _select_contacts(model, rows_all, names, normals, group, points, per_point, exchange_passes, compare,
                     slots) -> SeatDesign:
    """select_seats for stylus contacts: rows with their point Jacobian -n^T, each ball's centre
    eliminated by its Schur complement. A ball's first three contacts carry nothing (they only place
    its centre): while no candidate adds information, the one whose normal is the most unlike those
    already chosen is taken; the exchange passes then revise every choice on the full information."""
    rows_c, pj = contact_rows(rows_all, normals)
    keep = estimable(model, rows_c, group, names, pj)
    rows = rows_c[:, :, keep]
    p = rows.shape[2]
    free = np.ones(len(rows), bool)
    chosen: dict = {g: [] for g in points}

    def sums(at):
        j, q = rows[at].reshape(-1, p), pj[at].reshape(-1, 3)
        return j.T @ j, j.T @ q, q.T @ q

    def best_of(g, without):
        """The free candidate of point g whose addition gives the largest log det (the information
        `without` holds everything but point g's chosen rows)."""
        at = np.flatnonzero((group == g) & free & ~np.isin(slots, slots[chosen[g]]))
        if not len(at):
            raise ValueError(f"point {g!r}: fewer distinct slots among its candidates than contacts to choose")
        a, b, c = sums(chosen[g])
        ja, pa = rows[at], pj[at]  # (m, 1, p), (m, 1, 3)
        s = _schur(a + np.swapaxes(ja, 1, 2) @ ja, b + np.swapaxes(ja, 1, 2) @ pa, c + np.swapaxes(pa, 1, 2) @ pa)
        logdet = np.linalg.slogdet(without + s)[1]
        base = np.linalg.slogdet(without + _schur(a, b, c))[1]
        if logdet.max() - base > 1e-9:
            return int(at[np.argmax(logdet)])
        spread = np.linalg.slogdet(c + np.swapaxes(pa, 1, 2) @ pa + 1e-3 * np.eye(3))[1]
        return int(at[np.argmax(spread)])

    def info_without(g):
        return information(rows, group, [c for h in points if h != g for c in chosen[h]], pj)

    for _ in range(per_point):
        for g in points:
            best = best_of(g, info_without(g))
            free[best] = False
            chosen[g].append(best)
    for _ in range(exchange_passes):
        improved = False
        for g in points:
            without = info_without(g)
            for slot in range(per_point):
                out = chosen[g].pop(slot)
                free[out] = True
                best = best_of(g, without)
                chosen[g].insert(slot, best)
                free[best] = False
                improved |= best != out
        if not improved:
            break
    picked = np.array([c for g in points for c in chosen[g]], dtype=int)
    log_det = float(np.linalg.slogdet(information(rows, group, picked, pj))[1])
    others = {label: float(np.linalg.slogdet(information(rows, group, sel, pj))[1])
              for label, sel in (compare or {}).items()}
    return SeatDesign(chosen=picked, log_det=log_det, estimated=tuple(np.array(names)[keep][: int(keep[:model.n_params].sum())]),
                      log_det_of=others)
