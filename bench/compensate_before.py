"""Baseline for ``compensate_bench``: target compensation as it was before issue 22 (commit 7db1367).

Kept verbatim but for this docstring so the bench measures the old behaviour in the same
run: targets taken in the calibrated model's own base frame, damped Newton with 40
iterations, the orientation of the nominal solution imposed on position targets, and a
correction above ``max_correction_rad`` (1 deg) refused as ``near_singularity``. Not used
by cellcal itself.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.chain import pose_jacobians
from cellcal.solvers.geometry.robot_model import KinematicModel

OK, UNREACHABLE, JOINT_LIMITS, SINGULAR = "ok", "unreachable", "joint_limits", "near_singularity"
ROT_WEIGHT_MM = 1000.0  # orientation error weighed as mm per rad (a 1 m lever)
STALLED_MM = 1.0  # a solve that ends closer than this without converging stalled at a singularity
FIXED_POINT_STEPS, FIXED_POINT_TOL_RAD = 8, 1e-10  # 1e-10 rad: 1e-7 mm at 1 m, the solve's own tolerance


@dataclass(frozen=True)
class Compensation:
    q_nominal: np.ndarray  # (N, nj) rad: the nominal model's solution (the controller's own)
    q: np.ndarray  # (N, nj) rad: corrected joints, where the calibrated model reaches the target
    position_mm: np.ndarray  # (N, 3): nominal forward kinematics of q (corrected Cartesian targets)
    rotation: np.ndarray  # (N, 3, 3): the same, orientation
    correction_rad: np.ndarray  # (N,) largest |q - q_nominal|
    status: np.ndarray  # (N,) one of OK, UNREACHABLE, JOINT_LIMITS, SINGULAR
    iterations: int


def solve(frames, target_mm, target_rot, q0, *, tol_mm=1e-7, tol_rad=1e-10, max_iter=40, max_step_rad=0.3):
    """Damped Newton on all rows at once. ``frames(q)`` -> (rot, p, dp/dq, dw/dq) for (N, nj) q.
    target_rot None: position only (minimum-norm joint moves). Returns (q, converged, iterations)."""
    q = np.array(q0, dtype=float)
    n, nj = q.shape
    done = np.zeros(n, bool)
    it = 0
    for it in range(1, max_iter + 1):
        todo = np.flatnonzero(~done)
        if not len(todo):
            break
        rot, p, jp, jw = frames(q[todo], todo)
        e_p = target_mm[todo] - p
        if target_rot is None:
            err, jac = e_p, jp
            small = np.linalg.norm(e_p, axis=1) < tol_mm
        else:
            e_w = se3.matrix_to_rotvec(np.einsum("nij,nkj->nik", target_rot[todo], rot))
            err = np.concatenate([e_p, ROT_WEIGHT_MM * e_w], axis=1)
            jac = np.concatenate([jp, ROT_WEIGHT_MM * jw], axis=1)
            small = (np.linalg.norm(e_p, axis=1) < tol_mm) & (np.linalg.norm(e_w, axis=1) < tol_rad)
        done[todo[small]] = True
        move = ~small
        if not move.any():
            continue
        jac, err = jac[move], err[move]
        m = jac.shape[1]
        gram = jac @ np.swapaxes(jac, 1, 2) + 1e-9 * np.eye(m)
        dq = np.einsum("nmj,nm->nj", jac, np.linalg.solve(gram, err[:, :, None])[:, :, 0])
        scale = np.maximum(1.0, np.abs(dq).max(axis=1) / max_step_rad)
        q[todo[move]] += dq / scale[:, None]
    return q, done, it


def rigid_frames(model: KinematicModel, params: np.ndarray, offset_mm: np.ndarray):
    """``frames`` for ``solve`` on a rigid model: a point offset_mm (3,) in the end frame."""
    chain = model.chains[model.default_chain]

    def frames(q, rows):
        return pose_jacobians(chain, params, q, np.broadcast_to(offset_mm, (len(q), 3)), model.n_joints)
    return frames


def compensate(nominal: KinematicModel, calibrated, target_mm: np.ndarray, target_rot: np.ndarray | None,
               seed_q: np.ndarray, *, offset_mm: np.ndarray, nominal_offset_mm: np.ndarray | None = None,
               ctx_at=None, max_correction_rad: float = np.deg2rad(1.0), max_iter: int = 40) -> Compensation:
    """Corrected joints for every target row (see the module docstring).

    calibrated: a ``CalibratedModel``; ctx_at(q, rows) -> effects ``Context`` for those rows
    (approach directions, payload) or None; seed_q (N, nj) rad: the branch of each row.
    """
    target_mm = np.atleast_2d(np.asarray(target_mm, dtype=float))
    n = len(target_mm)
    nominal_offset = offset_mm if nominal_offset_mm is None else nominal_offset_mm
    nominal_frames = rigid_frames(nominal, nominal.nominal, np.asarray(nominal_offset, float))
    q_nom, ok_nom, it1 = solve(nominal_frames, target_mm, target_rot, seed_q, max_iter=max_iter)
    rot_goal = target_rot
    if rot_goal is None:
        rot_goal = nominal_frames(q_nom, np.arange(n))[0]

    model, chain = calibrated.model, calibrated.model.chains[calibrated.model.default_chain]
    offset = np.asarray(offset_mm, dtype=float)

    if calibrated.joint_effects_only:
        q, ok, it2 = _joint_space_solve(calibrated, offset, target_mm, rot_goal, q_nom, ctx_at, max_iter)
    else:
        def calibrated_frames(q, rows):
            ctx = ctx_at(q, rows) if ctx_at is not None else None
            rot, p, qm = calibrated.deflected_frames(q, offset, ctx)
            _, _, jq, jw = pose_jacobians(chain, calibrated.k, qm, np.broadcast_to(offset, (len(q), 3)),
                                          model.n_joints)
            return rot, p, jq, jw

        q, ok, it2 = solve(calibrated_frames, target_mm, rot_goal, q_nom, max_iter=max_iter)
    rot_cmd, p_cmd = nominal_frames(q, np.arange(n))[:2]
    correction = np.abs(q - q_nom).max(axis=1)
    status = np.full(n, OK, dtype=object)
    limits = nominal.joint_limits
    if limits is not None:
        outside = ((q < limits[:, 0]) | (q > limits[:, 1]) | (q_nom < limits[:, 0]) | (q_nom > limits[:, 1])).any(1)
        status[outside] = JOINT_LIMITS
    status[ok_nom & ok & (correction > max_correction_rad)] = SINGULAR
    failed = np.flatnonzero(~(ok_nom & ok))
    if len(failed):  # out of reach ends far off; near a singularity Newton stalls close to the point
        p_end = nominal_frames(q_nom[failed], failed)[1]  # where the stage that failed ended
        late = ok_nom[failed]
        if late.any():
            ctx = ctx_at(q[failed[late]], failed[late]) if ctx_at is not None else None
            p_end[late] = calibrated.end_frames(q[failed[late]], offset, ctx)[1]
        stalled = np.linalg.norm(p_end - target_mm[failed], axis=1) < STALLED_MM
        status[failed] = np.where(stalled, SINGULAR, UNREACHABLE)
    return Compensation(q_nom, q, p_cmd, rot_cmd, correction, status.astype(str), it1 + it2)


def _joint_space_solve(calibrated, offset, target_mm, target_rot, q_nom, ctx_at, max_iter):
    """Effects that act through the joint values alone: the rigid calibrated geometry reaches the
    pose at q_model (one batched solve), and the commanded q solves q + delta(q) = q_model by
    fixed-point steps (delta changes with q by a few 1e-4 of q's change, so each step gains
    three to four digits)."""
    frames = rigid_frames(calibrated.model, calibrated.k, offset)
    rows = np.arange(len(q_nom))
    ctx = ctx_at(q_nom, rows) if ctx_at is not None else None
    delta = calibrated.joint_delta(q_nom, ctx)
    q_model, ok, iterations = solve(frames, target_mm, target_rot, q_nom + delta, max_iter=max_iter)
    q = q_model - delta
    for _ in range(FIXED_POINT_STEPS):
        ctx = ctx_at(q, rows) if ctx_at is not None else None
        q_next = q_model - calibrated.joint_delta(q, ctx)
        change = np.abs(q_next - q).max(initial=0.0)
        q = q_next
        if change < FIXED_POINT_TOL_RAD:
            break
    return q, ok, iterations


def compensate_each(nominal, calibrated, target_mm, target_rot, seed_q, **kwargs) -> Compensation:
    """The same, one target at a time in a Python loop: the baseline the batched solve is measured against."""
    parts = [compensate(nominal, calibrated, target_mm[i: i + 1],
                        None if target_rot is None else target_rot[i: i + 1], seed_q[i: i + 1], **kwargs)
             for i in range(len(target_mm))]
    return Compensation(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                          ("q_nominal", "q", "position_mm", "rotation", "correction_rad", "status")),
                        max(p.iterations for p in parts))
