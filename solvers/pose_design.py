"""Pose-set design: which N of M candidate configurations to measure.

D-optimal design on the scaled identification Jacobian: maximise
log det(sum_i J_i^T J_i) over the chosen poses, i.e. shrink the volume of the
parameter confidence ellipsoid, so fewer measurements reach the same accuracy.
A greedy pass (rank-3 updates of the information matrix) is followed by
Fedorov exchanges until no swap improves the determinant.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import identifiability
from .identify import scales
from .measurement_model import Layout, Observations, jacobian
from .robot_model import KinematicModel


@dataclass(frozen=True)
class PoseDesign:
    chosen: np.ndarray  # indices into the candidates, in the order chosen
    log_det: float  # of the information matrix of the chosen set (scaled units)
    estimated: tuple[str, ...]  # the unknowns the design is for


def _blocks(model, q, target_offsets, target):
    names = tuple(f"t{i}" for i in range(len(target_offsets)))
    layout = Layout(model, names)
    x = layout.initial(base=np.zeros(6), offsets=np.asarray(target_offsets, dtype=float))
    obs = Observations(q, np.zeros((len(q), 3)), target, names)
    _, j = jacobian(layout, x, obs)
    j = j * scales(layout, x, obs)
    nuisance = np.zeros(layout.size, bool)
    nuisance[layout.n_kin:] = True
    candidates = ~nuisance
    keep = identifiability.analyse(j.reshape(-1, layout.size), nuisance, candidates).keep
    return j[:, :, keep], tuple(np.array(layout.names)[keep])


def select_poses(model: KinematicModel, q_candidates: np.ndarray, n: int, *,
                 target_offsets=((0.0, 0.0, 100.0),), exchange_passes: int = 3) -> PoseDesign:
    """Choose n of the candidate joint configurations for identification.

    target_offsets: nominal flange -> target offsets (mm); each candidate pose
    measures every target. Uses the nominal model only (what a planner has).
    """
    q = np.asarray(q_candidates, dtype=float)
    if n > len(q):
        raise ValueError(f"cannot choose {n} poses from {len(q)} candidates")
    n_targets = len(target_offsets)
    q_rows = np.repeat(q, n_targets, axis=0)
    target = np.tile(np.arange(n_targets), len(q))
    rows, names = _blocks(model, q_rows, target_offsets, target)
    p = rows.shape[-1]
    blocks = rows.reshape(len(q), 3 * n_targets, p)
    ridge = 1e-6 * np.eye(p)
    info = ridge.copy()
    chosen: list[int] = []
    free = np.ones(len(q), bool)

    def gains(m):
        s = np.einsum("nip,pq,njq->nij", blocks, np.linalg.inv(m), blocks)
        return np.linalg.slogdet(np.eye(3 * n_targets) + s)[1]

    for _ in range(n):
        g = np.where(free, gains(info), -np.inf)
        best = int(np.argmax(g))
        chosen.append(best)
        free[best] = False
        info = info + blocks[best].T @ blocks[best]
    for _ in range(exchange_passes):
        improved = False
        for slot in range(n):
            out = chosen[slot]
            without = info - blocks[out].T @ blocks[out]
            g = np.where(free, gains(without), -np.inf)
            best = int(np.argmax(g))
            if g[best] > _gain_of(blocks[out], without) + 1e-9:
                free[out], free[best] = True, False
                chosen[slot] = best
                info = without + blocks[best].T @ blocks[best]
                improved = True
        if not improved:
            break
    return PoseDesign(chosen=np.array(chosen), log_det=float(np.linalg.slogdet(info)[1]), estimated=names)


def _gain_of(block, m):
    s = block @ np.linalg.inv(m) @ block.T
    return float(np.linalg.slogdet(np.eye(len(s)) + s)[1])
