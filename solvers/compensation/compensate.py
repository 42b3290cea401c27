"""Target compensation: the joint values at which the calibrated model reaches a desired pose.

A controller keeps its nominal kinematics, so the accuracy a calibration gained is only
real once the robot's targets are corrected. Targets come in one of three frames
(``FRAMES``); ``targets_in_model_frame`` maps them into the calibrated model's base frame:

``base``
    the controller's base frame as its nominal kinematics realise it on this robot: poses
    from a program, a teach pendant or an offline programming system. A calibrated
    model's own base frame is a convention of the calibration (which parameters it held,
    the instrument -> base transform it identified), not the controller's; the
    controller's is defined here as the rigid transform under which the nominal model's
    tool point agrees best (least squares) with the calibrated model's over a fixed
    spread of ``FRAME_SAMPLES`` configurations within the joint limits
    (``controller_frame``). Taught points and an offline system's poses are what the
    nominal kinematics say, and that fit is the frame in which the nominal kinematics
    are right on average: what is left is what calibration corrects.
``instrument``
    the measuring instrument's frame (the cell frame of a tracker): a workpiece measured
    by the tracker. Mapped with the calibration's ``base`` (instrument -> base).
``model``
    the calibrated model's own base frame (what this module took before frames were
    explicit): only for targets computed with the calibrated model itself.

For each target (in the model frame):

1. the nominal inverse: joints at which the *nominal* model reaches the target as the
   controller sees it (in the controller's frame), from the row's seed (the branch the
   program uses): what the controller would command uncorrected;
2. the calibrated inverse: from there (from the seed where the nominal model itself does
   not reach the target), joints at which the *calibrated* model (geometry plus
   joint-space effects, payload where given) reaches the target: position and
   orientation, or the position alone (minimum-norm joint moves: the orientation is left
   to the branch) when the target gives none;
3. the corrected Cartesian target: the nominal forward kinematics of the corrected
   joints (controller frame), for controllers that take Cartesian targets.

Both inverses are Levenberg-Marquardt on all rows at once: (N, 6, nj) Jacobians, batched
damped solves, a step kept only where it lowers the row's error (else that row's damping
grows tenfold), so a solve started on the right branch converges wherever the target is
reachable, near singular configurations included. The Jacobian of the calibrated model
is the rigid one at the deflected joints (the effects' own dependence on q is a few 1e-4
of it), so the last steps converge linearly at that rate.

A row is refused only when its target is out of reach on its branch (the solve stops at
a local minimum of the error: ``unreachable``, with how far off it ended), when the
solution leaves the joint limits (``joint_limits``), or when the solution is at a
singular configuration (``near_singularity``): the smallest singular value of the
Jacobian of what is solved (position rows in mm/rad, orientation rows weighed
ROT_WEIGHT_MM) below SINGULAR_MM_PER_RAD at the solution, or, for a pose the solve does
not reach, at the configuration it ends in while the position alone is reachable (the
pose needs the arm through a singular configuration). A large correction is not
refused: near a singularity a small Cartesian correction needs large joint moves, and
where the Jacobian keeps its rank those moves are the right answer (``correction_rad``
reports them). Nothing is clipped.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.chain import pose_jacobians
from cellcal.solvers.geometry.robot_model import KinematicModel

OK, UNREACHABLE, JOINT_LIMITS, SINGULAR = "ok", "unreachable", "joint_limits", "near_singularity"
FRAMES = ("base", "instrument", "model")  # the frames targets may be given in (module docstring)
ROT_WEIGHT_MM = 1000.0  # orientation error weighed as mm per rad (a 1 m lever)
# A configuration is singular where some joint motion of 1 rad moves the tool less than 1 mm (and turns it less
# than 1 mrad): there the calibration's own remaining error (about 0.02 mm) alone decides more than a degree of
# joint motion, so the joints are no longer determined by the arm's geometry. For a pose target on a UR10e with a
# 100 mm tool this is the wrist within 0.15 deg of aligned (q5 = 0) or the elbow within 0.25 deg of stretched
# (q3 = 0): 1.3 % of configurations drawn uniformly over the joint space. A position target leaves three joint
# directions free, and the wrist's offsets keep the position Jacobian's rank there (none of 100 000 draws).
SINGULAR_MM_PER_RAD = 1.0
MAX_ITER = 100  # Levenberg-Marquardt iterations; well-conditioned rows converge in 3 to 8
DAMPING_START, DAMPING_MIN, DAMPING_MAX = 1e-6, 1e-12, 1e6  # relative to the mean diagonal of J J^T
FRAME_SAMPLES = 1024  # configurations the controller's frame is fitted over (a Halton sequence within the limits)
FIXED_POINT_STEPS, FIXED_POINT_TOL_RAD = 8, 1e-10  # 1e-10 rad: 1e-7 mm at 1 m, the solve's own tolerance


@dataclass(frozen=True)
class Compensation:
    q_nominal: np.ndarray  # (N, nj) rad: the nominal model's solution (the controller's own); NaN where it has none
    q: np.ndarray  # (N, nj) rad: corrected joints, where the calibrated model reaches the target
    position_mm: np.ndarray  # (N, 3): nominal forward kinematics of q (corrected Cartesian targets, controller frame)
    rotation: np.ndarray  # (N, 3, 3): the same, orientation
    correction_rad: np.ndarray  # (N,) largest |q - q_nominal| (NaN where the nominal model has no solution)
    status: np.ndarray  # (N,) one of OK, UNREACHABLE, JOINT_LIMITS, SINGULAR
    sigma_min: np.ndarray  # (N,) mm/rad: smallest singular value of the Jacobian of what is solved, at q
    miss_mm: np.ndarray  # (N,) how far from the target (position) the calibrated solve ended
    iterations: int


def solve(frames, target_mm, target_rot, q0, *, tol_mm=1e-7, tol_rad=1e-10, max_iter=MAX_ITER, max_step_rad=0.3):
    """Levenberg-Marquardt on all rows at once. ``frames(q, rows)`` -> (rot, p, dp/dq, dw/dq) for (N, nj) q.
    target_rot None: position only (minimum-norm joint moves). A row's step is damped by mu times the mean
    diagonal of its J J^T and kept where it lowers the row's squared error; mu follows the gain ratio of the
    step (actual over predicted decrease) as Nielsen's rule has it: a good step lowers mu up to threefold, a
    poor one raises it, a rejected one raises it 2, 4, 8 ... fold. A row whose mu passes DAMPING_MAX sits at
    a local minimum of its error. Returns (q, converged, iterations, position miss mm, orientation miss rad)."""
    q = np.array(q0, dtype=float)
    n = len(q)
    err, jac, miss_p, miss_w = _errors(frames, q, np.arange(n), target_mm, target_rot)
    cost = np.einsum("nm,nm->n", err, err)
    done = (miss_p < tol_mm) & (miss_w < tol_rad)
    damping, growth = np.full(n, DAMPING_START), np.full(n, 2.0)
    it = 0
    for it in range(1, max_iter + 1):
        todo = np.flatnonzero(~done & (damping < DAMPING_MAX))
        if not len(todo):
            break
        j, e = jac[todo], err[todo]
        m = j.shape[1]
        gram = j @ np.swapaxes(j, 1, 2)
        gram += (damping[todo] * np.trace(gram, axis1=1, axis2=2) / m)[:, None, None] * np.eye(m)
        dq = np.einsum("nmj,nm->nj", j, np.linalg.solve(gram, e[:, :, None])[:, :, 0])
        dq /= np.maximum(1.0, np.abs(dq).max(axis=1) / max_step_rad)[:, None]
        left = e - np.einsum("nmj,nj->nm", j, dq)  # the error the linear model predicts after the step
        predicted = cost[todo] - np.einsum("nm,nm->n", left, left)
        q_try = q[todo] + dq
        err_t, jac_t, p_t, w_t = _errors(frames, q_try, todo, target_mm, target_rot)
        cost_t = np.einsum("nm,nm->n", err_t, err_t)
        gain = (cost[todo] - cost_t) / np.maximum(predicted, 1e-300)
        better = cost_t < cost[todo]
        kept, dropped = todo[better], todo[~better]
        q[kept], err[kept], jac[kept], cost[kept] = q_try[better], err_t[better], jac_t[better], cost_t[better]
        miss_p[kept], miss_w[kept] = p_t[better], w_t[better]
        done[kept] = (p_t[better] < tol_mm) & (w_t[better] < tol_rad)
        shrink = np.maximum(1.0 / 3.0, 1.0 - (2.0 * np.minimum(gain[better], 1.0) - 1.0) ** 3)
        damping[kept] = np.maximum(damping[kept] * shrink, DAMPING_MIN)
        growth[kept] = 2.0
        damping[dropped] *= growth[dropped]
        growth[dropped] *= 2.0
    return q, done, it, miss_p, miss_w


def _errors(frames, q, rows, target_mm, target_rot):
    """Error vector (N, 3 or 6: mm, orientation weighed ROT_WEIGHT_MM), its Jacobian, position miss (mm) and
    orientation miss (rad) of the rows at q."""
    rot, p, jp, jw = frames(q, rows)
    e_p = target_mm[rows] - p
    if target_rot is None:
        return e_p, jp, np.linalg.norm(e_p, axis=1), np.zeros(len(rows))
    e_w = se3.matrix_to_rotvec(np.einsum("nij,nkj->nik", target_rot[rows], rot))
    return (np.concatenate([e_p, ROT_WEIGHT_MM * e_w], axis=1), np.concatenate([jp, ROT_WEIGHT_MM * jw], axis=1),
            np.linalg.norm(e_p, axis=1), np.linalg.norm(e_w, axis=1))


def rigid_frames(model: KinematicModel, params: np.ndarray, offset_mm: np.ndarray):
    """``frames`` for ``solve`` on a rigid model: a point offset_mm (3,) in the end frame."""
    chain = model.chains[model.default_chain]

    def frames(q, rows):
        return pose_jacobians(chain, params, q, np.broadcast_to(offset_mm, (len(q), 3)), model.n_joints)
    return frames


def joint_sample(model: KinematicModel, n: int = FRAME_SAMPLES) -> np.ndarray:
    """(n, nj) rad: a fixed, evenly spread set of configurations within the joint limits (each joint within
    one turn about zero): a Halton sequence, the same on every call."""
    limits = np.tile([-np.pi, np.pi], (model.n_joints, 1)) if model.joint_limits is None else model.joint_limits
    lo, hi = np.maximum(limits[:, 0], -np.pi), np.minimum(limits[:, 1], np.pi)
    return lo + halton(n, model.n_joints) * (hi - lo)


def halton(n: int, d: int) -> np.ndarray:
    """(n, d): points 1 .. n of the Halton sequence in [0, 1)^d, the radical inverses of the index in the
    first d prime bases: what ``scipy.stats.qmc.Halton(d, scramble=False).random(n + 1)[1:]`` gives, here
    because importing scipy.stats takes a compensation's command 0.3 s (a third of its start-up)."""
    primes: list[int] = []
    candidate = 2
    while len(primes) < d:
        if all(candidate % p for p in primes):
            primes.append(candidate)
        candidate += 1
    out = np.zeros((n, d))
    for k, base in enumerate(primes):
        index, weight = np.arange(1, n + 1), 1.0
        while index.any():
            weight /= base
            out[:, k] += weight * (index % base)
            index //= base
    return out


def fit_controller_frame(nominal: KinematicModel, points_at, nominal_offset_mm) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with points_at(q) ~= R p_nominal(q) + t in the least-squares sense over ``joint_sample``:
    where the controller's base frame lies in the frame ``points_at`` answers in. p_nominal is the nominal
    forward kinematics of a point nominal_offset_mm (3,) in the end frame; points_at(q) (N, nj) -> (N, 3) mm
    is where that point really is (a calibrated model; in a simulation, the hidden truth)."""
    q = joint_sample(nominal)
    p_nominal = rigid_frames(nominal, nominal.nominal, np.asarray(nominal_offset_mm, dtype=float))(q, None)[1]
    return se3.rigid_fit(p_nominal, np.asarray(points_at(q), dtype=float))


def controller_frame(calibrated, nominal: KinematicModel, *, offset_mm=None,
                     nominal_offset_mm=None) -> tuple[np.ndarray, np.ndarray]:
    """(R, t): the controller's base frame in the calibrated model's, p_model = R p_controller + t. The rigid
    transform under which the nominal model's tool point (nominal_offset_mm, default offset_mm) agrees best
    with the calibrated model's (offset_mm, default the calibrated first target; its effects applied with
    no payload and no approach direction), over ``joint_sample`` (the module docstring says why)."""
    offset = calibrated.offsets[0] if offset_mm is None else np.asarray(offset_mm, dtype=float)
    nominal_offset = offset if nominal_offset_mm is None else np.asarray(nominal_offset_mm, dtype=float)
    return fit_controller_frame(nominal, lambda q: calibrated.end_frames(q, offset)[1], nominal_offset)


# How far (mm, after the best rigid base frame, over ``joint_sample``) a calibrated arm may be from the
# nominal model of the controller it was calibrated for: a calibration moves a tool point by a few mm
# (a UR10e's by 1-3 mm); another arm's nominal model differs by hundreds (a UR5e from a UR10e: ~200 mm).
NOMINAL_MISMATCH_MM = 20.0


def nominal_mismatch_mm(calibrated, nominal: KinematicModel, offset_mm) -> float:
    """The largest distance, over ``joint_sample``, between the calibrated model's tool point (offset_mm,
    end frame) and the nominal model's moved by the best rigid transform: how unlike the two arms are,
    whatever frame convention the calibration chose for its base."""
    offset = np.asarray(offset_mm, dtype=float)
    q = joint_sample(nominal)
    p_nominal = rigid_frames(nominal, nominal.nominal, offset)(q, None)[1]
    p_model = np.asarray(calibrated.end_frames(q, offset)[1], dtype=float)
    r, t = se3.rigid_fit(p_nominal, p_model)
    return float(np.linalg.norm(p_nominal @ r.T + t - p_model, axis=1).max())


def targets_in_model_frame(calibrated, nominal: KinematicModel, xyz_mm, rot, frame: str, *, offset_mm=None,
                           nominal_offset_mm=None, controller=None):
    """Targets given in ``frame`` (one of FRAMES) as (xyz_mm (N, 3), rot (N, 3, 3) or None) in the calibrated
    model's base frame, the frame ``compensate`` takes. ``base`` goes through ``controller_frame`` (offsets as
    there; ``controller`` (R, t) when already computed), ``instrument`` through the calibration's
    instrument -> base transform, ``model`` is returned as given."""
    xyz = np.atleast_2d(np.asarray(xyz_mm, dtype=float))
    if frame == "model":
        return xyz, rot
    if frame == "instrument":  # p_instrument = R_b p_model + t_b
        r, t = se3.rotvec_to_matrix(calibrated.base[3:]), calibrated.base[:3]
        return (xyz - t) @ r, None if rot is None else np.einsum("ji,njk->nik", r, rot)
    if frame == "base":
        r, t = controller if controller is not None else controller_frame(
            calibrated, nominal, offset_mm=offset_mm, nominal_offset_mm=nominal_offset_mm)
        return xyz @ r.T + t, None if rot is None else np.einsum("ij,njk->nik", r, rot)
    raise ValueError(f"frame {frame!r}: not one of {', '.join(FRAMES)}")


def smallest_singular_value(model: KinematicModel, q: np.ndarray, offset_mm, pose: bool) -> np.ndarray:
    """(N,) mm/rad: the smallest singular value of the tool point's Jacobian at q, position rows in mm/rad and,
    with pose, orientation rows weighed ROT_WEIGHT_MM (what ``solve`` inverts)."""
    _, _, jp, jw = rigid_frames(model, model.nominal, np.asarray(offset_mm, dtype=float))(q, None)
    jac = np.concatenate([jp, ROT_WEIGHT_MM * jw], axis=1) if pose else jp
    smallest = np.linalg.eigvalsh(jac @ np.swapaxes(jac, 1, 2))[:, 0]  # sigma^2 (eigvalsh: faster than svd)
    return np.sqrt(np.maximum(smallest, 0.0))


def compensate(nominal: KinematicModel, calibrated, target_mm: np.ndarray, target_rot: np.ndarray | None,
               seed_q: np.ndarray, *, offset_mm: np.ndarray, nominal_offset_mm: np.ndarray | None = None,
               ctx_at=None, max_iter: int = MAX_ITER, controller=None) -> Compensation:
    """Corrected joints for every target row (see the module docstring).

    target_mm (N, 3), target_rot (N, 3, 3) or None: in the calibrated model's base frame
    (``targets_in_model_frame``). calibrated: a ``CalibratedModel``; ctx_at(q, rows) -> effects ``Context``
    for those rows (approach directions, payload) or None; seed_q (N, nj) rad: the branch of each row;
    offset_mm: the tool point in the calibrated end frame, nominal_offset_mm the controller's (default the
    same); controller: ``controller_frame`` (R, t) when already computed.
    """
    target_mm = np.atleast_2d(np.asarray(target_mm, dtype=float))
    n = len(target_mm)
    rows = np.arange(n)
    offset = np.asarray(offset_mm, dtype=float)
    nominal_offset = offset if nominal_offset_mm is None else np.asarray(nominal_offset_mm, dtype=float)
    seed_q = np.broadcast_to(np.asarray(seed_q, dtype=float), (n, nominal.n_joints))
    r_c, t_c = controller if controller is not None else controller_frame(
        calibrated, nominal, offset_mm=offset, nominal_offset_mm=nominal_offset)
    nominal_frames = rigid_frames(nominal, nominal.nominal, nominal_offset)
    rot_controller = None if target_rot is None else np.einsum("ji,njk->nik", r_c, target_rot)
    q_nom, ok_nom, it1, _, _ = solve(nominal_frames, (target_mm - t_c) @ r_c, rot_controller, seed_q,
                                     max_iter=max_iter)
    start = np.where(ok_nom[:, None], q_nom, seed_q)  # from the branch itself where the nominal model misses

    q, ok, it2, miss_p, _ = _calibrated_inverse(calibrated, offset, target_mm, target_rot, start, ctx_at, max_iter)
    rot_cmd, p_cmd = nominal_frames(q, rows)[:2]
    q_nom = np.where(ok_nom[:, None], q_nom, np.nan)
    correction = np.abs(q - q_nom).max(axis=1)
    sigma = smallest_singular_value(nominal, q, nominal_offset, target_rot is not None)
    status = np.full(n, OK, dtype=object)
    limits = nominal.joint_limits
    if limits is not None:
        status[((q < limits[:, 0]) | (q > limits[:, 1])).any(axis=1)] = JOINT_LIMITS
    status[(status == OK) & (sigma < SINGULAR_MM_PER_RAD)] = SINGULAR
    status[~ok] = UNREACHABLE
    stuck = np.flatnonzero(~ok & (sigma < SINGULAR_MM_PER_RAD)) if target_rot is not None else np.zeros(0, int)
    if len(stuck):  # a pose not reached at a singular configuration: singular if its position alone is reachable
        sub_ctx = None if ctx_at is None else (lambda q_sub, r: ctx_at(q_sub, stuck[r]))
        reached = _calibrated_inverse(calibrated, offset, target_mm[stuck], None, q[stuck], sub_ctx, max_iter)[1]
        status[stuck[reached]] = SINGULAR
    return Compensation(q_nom, q, p_cmd, rot_cmd, correction, status.astype(str), sigma, miss_p, it1 + it2)


def _calibrated_inverse(calibrated, offset, target_mm, target_rot, start, ctx_at, max_iter):
    """``solve`` on the calibrated model (geometry and effects) from start: (q, converged, iterations,
    position miss, orientation miss); ctx_at(q, rows) with rows into these targets, or None."""
    if calibrated.joint_effects_only:
        return _joint_space_solve(calibrated, offset, target_mm, target_rot, start, ctx_at, max_iter)
    model, chain = calibrated.model, calibrated.model.chains[calibrated.model.default_chain]

    def calibrated_frames(q, rows):
        ctx = ctx_at(q, rows) if ctx_at is not None else None
        rot, p, qm = calibrated.deflected_frames(q, offset, ctx)
        _, _, jq, jw = pose_jacobians(chain, calibrated.k, qm, np.broadcast_to(offset, (len(q), 3)), model.n_joints)
        return rot, p, jq, jw

    return solve(calibrated_frames, target_mm, target_rot, start, max_iter=max_iter)


def _joint_space_solve(calibrated, offset, target_mm, target_rot, q_start, ctx_at, max_iter):
    """Effects that act through the joint values alone: the rigid calibrated geometry reaches the
    pose at q_model (one batched solve), and the commanded q solves q + delta(q) = q_model by
    fixed-point steps (delta changes with q by a few 1e-4 of q's change, so each step gains
    three to four digits)."""
    frames = rigid_frames(calibrated.model, calibrated.k, offset)
    rows = np.arange(len(q_start))
    ctx = ctx_at(q_start, rows) if ctx_at is not None else None
    delta = calibrated.joint_delta(q_start, ctx)
    q_model, ok, iterations, miss_p, miss_w = solve(frames, target_mm, target_rot, q_start + delta, max_iter=max_iter)
    q = q_model - delta
    for _ in range(FIXED_POINT_STEPS):  # each row until its own step is below the tolerance
        ctx = ctx_at(q[rows], rows) if ctx_at is not None else None
        q_next = q_model[rows] - calibrated.joint_delta(q[rows], ctx)
        moving = np.abs(q_next - q[rows]).max(axis=1) >= FIXED_POINT_TOL_RAD
        q[rows] = q_next
        rows = rows[moving]
        if not len(rows):
            break
    return q, ok, iterations, miss_p, miss_w


def compensate_each(nominal, calibrated, target_mm, target_rot, seed_q, **kwargs) -> Compensation:
    """The same, one target at a time in a Python loop: the baseline the batched solve is measured against
    (the controller's frame fitted once, as a caller compensating target after target would)."""
    if kwargs.get("controller") is None:
        kwargs["controller"] = controller_frame(calibrated, nominal, offset_mm=kwargs["offset_mm"],
                                                nominal_offset_mm=kwargs.get("nominal_offset_mm"))
    parts = [compensate(nominal, calibrated, target_mm[i: i + 1],
                        None if target_rot is None else target_rot[i: i + 1], seed_q[i: i + 1], **kwargs)
             for i in range(len(target_mm))]
    names = [f.name for f in fields(Compensation) if f.name != "iterations"]
    return Compensation(**{f: np.concatenate([getattr(p, f) for p in parts]) for f in names},
                        iterations=max(p.iterations for p in parts))
