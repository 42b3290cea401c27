"""Pose-set design: which N of M candidate configurations to measure.

D-optimal design on the scaled identification Jacobian: maximise
log det(sum_i J_i^T J_i) over the chosen poses, i.e. shrink the volume of the
parameter confidence ellipsoid, so fewer measurements reach the same accuracy.
A greedy pass (rank-3 updates of the information matrix) is followed by
Fedorov exchanges until no swap improves the determinant.

The candidates a tracker campaign chooses from (:func:`sighted_candidates`): random
configurations on the nominal model that keep the arm in the cell's box and the
target in the instrument's sight, facing it, with the beam clear of the arm; and a
short round trip through the chosen ones (:func:`tour`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.estimation import identifiability
from cellcal.solvers.identification.identify import scales
from cellcal.solvers.geometry.chain import forward
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian
from cellcal.solvers.geometry.robot_model import KinematicModel


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
        s = (blocks @ np.linalg.inv(m)) @ blocks.transpose(0, 2, 1)  # B_n M^-1 B_n^T for every candidate
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


# -- poses a tracker can see, and a short way through them ------------------------------------

@dataclass(frozen=True)
class Sight:
    """Where a tracker stands and what it sees (robot base frame, mm and rad)."""

    instrument_mm: np.ndarray
    axis: np.ndarray  # unit: the centre of the instrument's view cone
    half_angle_rad: float  # the view cone's half angle
    acceptance_rad: float  # the target faces the instrument within this (a reflector's acceptance angle)
    clearance_mm: float  # the line of sight passes at least this far from the arm's skeleton (0: not checked)
    max_range_mm: float


def _skeleton(model: KinematicModel, q: np.ndarray):
    """End rotations, end origins and the arm's skeleton: every frame origin along the chain
    from the base to the end frame, (N, F, 3) mm."""
    rot, org, frames = forward(model.chains[model.default_chain], model.nominal, q, keep_frames=True)
    return rot, org, np.stack([f[1] for f in frames] + [org], axis=1)


def _in_box(points: np.ndarray, box_mm) -> np.ndarray:
    low, high = box_mm
    return np.all((points >= low - 1e-6) & (points <= high + 1e-6), axis=-1)


def _moving(model: KinematicModel) -> np.ndarray:
    """Which skeleton points the joints move (the base column's do not, and may stand below the box)."""
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (3, model.n_joints))
    pts = _skeleton(model, q)[2]
    return np.ptp(pts, axis=0).max(axis=-1) > 1e-6


def _arm_in_box(model, q, box_mm, tool_mm, skeleton=None) -> np.ndarray:
    """The TCP and every moving frame origin of the arm inside the box, per row of q."""
    rot, org, pts = _skeleton(model, q) if skeleton is None else skeleton
    tcp = org + rot @ np.asarray(tool_mm, dtype=float)
    return _in_box(tcp, box_mm) & np.all(_in_box(pts[:, _moving(model)], box_mm), axis=1)


def clear_of_mount(model: KinematicModel, q: np.ndarray, min_height_mm: float = 0.0) -> np.ndarray:
    """Whether every moving frame origin of the arm stays on the robot's side of its mounting plane
    (base z at least min_height_mm; the base frame's z points away from the mounting surface), per row:
    what a design without a cell model can check of configurations that are to be measured."""
    pts = _skeleton(model, np.atleast_2d(q))[2][:, _moving(model)]
    return np.all(pts[..., 2] >= min_height_mm, axis=1)


PATH_SAMPLES = 47  # along a joint move; a superset of the motion guard's 24 points


def paths_clear(model: KinematicModel, q_from, q_to, box_mm, tool_mm) -> np.ndarray:
    """Whether straight joint paths keep the TCP and the arm's skeleton inside the box, per row."""
    q_from, q_to = np.atleast_2d(q_from), np.atleast_2d(q_to)
    if not len(q_to):
        return np.zeros(0, bool)
    q_from = np.broadcast_to(q_from, q_to.shape) if len(q_from) == 1 else q_from
    s = np.linspace(0.0, 1.0, PATH_SAMPLES)[None, :, None]
    path = (q_from[:, None] + s * (q_to - q_from)[:, None]).reshape(-1, q_to.shape[1])
    return _arm_in_box(model, path, box_mm, tool_mm).reshape(len(q_to), PATH_SAMPLES).all(axis=1)


def path_clear(model: KinematicModel, q_from, q_to, box_mm, tool_mm) -> bool:
    return bool(paths_clear(model, q_from, q_to, box_mm, tool_mm)[0])


def _sight_clear(pts: np.ndarray, target: np.ndarray, sight: Sight) -> np.ndarray:
    """Whether the line from each target to the instrument, the target included, keeps
    `clearance_mm` from the skeleton `pts` (N, F, 3): an arm folded back onto its tool
    blocks the beam, and touches the tool."""
    c = sight.clearance_mm
    if c <= 0 or not len(target):
        return np.ones(len(target), bool)
    a, b = pts[:, :-1], pts[:, 1:]  # (N, F-1, 3) segments of the skeleton
    ab = b - a
    ll = np.maximum(np.einsum("nfi,nfi->nf", ab, ab), 1e-12)
    # only the part of the line near the arm can pass it: up to radius `reach` around the base
    reach = float(np.linalg.norm(pts, axis=-1).max()) + c
    d = sight.instrument_mm - target
    dist = np.linalg.norm(d, axis=1)
    u = d / dist[:, None]
    tu = np.einsum("ni,ni->n", target, u)
    along = -tu + np.sqrt(np.maximum(tu**2 - np.einsum("ni,ni->n", target, target) + reach**2, 0.0))
    along = np.clip(along, 0.0, dist)
    s = np.linspace(0.0, 1.0, int(np.ceil(2 * reach / (c / 2))) + 1)
    points = target[:, None] + (s[None, :] * along[:, None])[:, :, None] * u[:, None]  # (N, S, 3)
    ok = np.ones(len(target), bool)
    for lo in range(0, len(target), 128):
        sl = slice(lo, lo + 128)
        ap = points[sl, :, None] - a[sl, None]  # (n, S, F-1, 3)
        t = np.clip(np.einsum("nsfi,nfi->nsf", ap, ab[sl]) / ll[sl, None], 0.0, 1.0)
        gap = np.linalg.norm(ap - t[..., None] * ab[sl, None], axis=-1)
        ok[sl] = gap.min(axis=(1, 2)) >= c
    return ok


def up_to_wrist(model: KinematicModel) -> int:
    """How many skeleton points lead up to the wrist: the frames before the last two joints
    move. The links after them carry the target and sit behind it (it faces away from them)."""
    return model.joint_elements[-2] + 1 if len(model.joint_elements) >= 2 else 0


def _last_joint_sees(model: KinematicModel, target_mm) -> bool:
    """False when the target lies on the last joint's axis, so that joint cannot move it."""
    if not model.joint_elements:
        return True
    chain = model.chains[model.default_chain]
    el = chain.elements[model.joint_elements[-1]]
    if not el.is_rotation:
        return True
    rot, org, frames = forward(chain, model.nominal, np.zeros((1, model.n_joints)), keep_frames=True)
    r, o = frames[model.joint_elements[-1]]
    axis = r[0, :, el.axis]
    p = org[0] + rot[0] @ np.asarray(target_mm, dtype=float)
    return float(np.linalg.norm(np.cross(p - o[0], axis))) > 1e-6


def sighted_candidates(model: KinematicModel, n: int, rng: np.random.Generator, *, target_mm, normal, sight: Sight,
                       box_mm, tool_mm, home_q, batch: int = 4000, max_batches: int = 100) -> np.ndarray:
    """Up to n random configurations (nominal model) in which the TCP and the whole arm are in
    the box, the target is in the instrument's view cone and range, faces it within the
    acceptance angle, the line of sight passes clear of the arm, and the straight joint path
    from and to `home_q` stays in the box. A joint that cannot move the target (the last one,
    when the target is on its axis) is held at its home value, so no move time is spent on it."""
    home = np.asarray(home_q, dtype=float)
    lim = np.clip(model.joint_limits, -np.pi, np.pi) if model.joint_limits is not None else \
        np.tile([-np.pi, np.pi], (model.n_joints, 1))
    target_mm, normal = np.asarray(target_mm, dtype=float), np.asarray(normal, dtype=float)
    hold_last = not _last_joint_sees(model, target_mm)
    cos_view, cos_accept = np.cos(sight.half_angle_rad), np.cos(sight.acceptance_rad)
    found: list[np.ndarray] = []
    for _ in range(max_batches):
        q = rng.uniform(lim[:, 0], lim[:, 1], (batch, model.n_joints))
        if hold_last:
            q[:, -1] = home[-1]
        rot, org, pts = _skeleton(model, q)
        target = org + rot @ target_mm
        d = target - sight.instrument_mm
        dist = np.linalg.norm(d, axis=1)
        u = d / dist[:, None]
        ok = (_arm_in_box(model, q, box_mm, tool_mm, (rot, org, pts)) & _in_box(target, box_mm) & (dist <= sight.max_range_mm)
              & (u @ sight.axis >= cos_view) & (-np.einsum("ni,ni->n", rot @ normal, u) >= cos_accept))
        idx = np.flatnonzero(ok)
        wrist = up_to_wrist(model) or pts.shape[1]
        idx = idx[_sight_clear(pts[idx, :wrist], target[idx], sight)]
        idx = idx[paths_clear(model, home, q[idx], box_mm, tool_mm)]
        found.append(q[idx])
        total = sum(len(f) for f in found)
        if total >= n or (total == 0 and len(found) >= 5):  # none in 5 batches: the instrument sees nothing
            break
    return np.concatenate(found)[:n]


def move_time_s(dq_rad: np.ndarray, speed: float, accel: float) -> np.ndarray:
    """Time of a joint move (trapezoidal profile) over the largest joint change `dq_rad`."""
    dq = np.abs(np.asarray(dq_rad, dtype=float))
    return np.where(dq >= speed**2 / accel, dq / speed + speed / accel, 2.0 * np.sqrt(dq / accel))


def tour(q: np.ndarray, home, speed: float, accel: float) -> np.ndarray:
    """An order of the configurations q for a short round trip from home and back: nearest
    neighbour, then 2-opt, on the joint-move time between them."""
    pts = np.vstack([np.asarray(home, dtype=float)[None], np.asarray(q, dtype=float)])
    if len(pts) <= 2:
        return np.arange(len(q))
    cost = move_time_s(np.abs(pts[:, None] - pts[None]).max(axis=-1), speed, accel)
    route, free = [0], np.ones(len(pts), bool)
    free[0] = False
    while free.any():
        nxt = int(np.argmin(np.where(free, cost[route[-1]], np.inf)))
        route.append(nxt)
        free[nxt] = False
    route = np.array(route + [0])
    improved = True
    while improved:
        improved = False
        for i in range(1, len(route) - 2):
            a, b = route[i - 1], route[i]
            c, d = route[i + 1:-1], route[i + 2:]
            gain = cost[a, b] + cost[c, d] - cost[a, c] - cost[b, d]
            j = int(np.argmax(gain)) if len(gain) else 0
            if len(gain) and gain[j] > 1e-9:
                route[i:i + j + 2] = route[i:i + j + 2][::-1]
                improved = True
    return route[1:-1] - 1
