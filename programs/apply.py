"""Compensate a parsed URScript program with a calibrated model, each target read as the
controller will read it.

The controller keeps its nominal kinematics, so the program means what the nominal model
makes of it:

* a pose target ``p[...]`` is the pose of the tool centre point in the controller's base
  frame, the tool being the ``set_tcp`` in force at that line (without one: the tool point
  given to :func:`compensate_program`, ``--tcp-mm`` or the calibrated target, with the
  flange's orientation). The controller reaches it at the nominal inverse from the joints
  it is at: the previous target's joints in program order (or the seed given, for a pose
  that comes before every other target);
* a joint target ``[q1..q6]`` puts the tool where the nominal forward kinematics of those
  joints says.

A tool is the controller's, a point in the flange frame of the drawing; the calibrated model
takes it through the model's ``solvers.compensation.tool_map.ToolMap`` (through the nearest
measured target, as drawn and as calibrated), which also states where each compensated target
lands (``bound_mm``, 95 %).

That pose, mapped from the controller's base frame into the calibrated model's frame
(``solvers.compensation.compensate.targets_in_model_frame``, frame ``base``: the controller's frame fitted
once per program at the tool point the calibration knows, the calibrated target or
``--tcp-mm``), is what the arm should reach. The calibrated model gives the joints that
reach it (``solvers.compensation.compensate.compensate``, all targets of one tool in one batch); a
joint target gets those joints, a pose target the nominal forward kinematics of those
joints with the same tool, which the controller turns back into exactly those joints. So
the program keeps its own conventions.

Targets the scanner found computed at run time, or under a tool set at run time, are not
attempted (:data:`NOT_ATTEMPTED`); targets the arm cannot reach, outside the joint limits or
at a singularity keep their status from the solver and are left as written.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from cellcal.programs.urscript import JOINT_VALUES, POSE, RUNTIME, Program, ProgramError, SetTcp, Target
from cellcal.solvers.compensation import compensate as solver
from cellcal.solvers.geometry import se3
from cellcal.solvers.analysis.effects import Context, approach_directions

OK = "ok"
COMPUTED_AT_RUN_TIME = "runtime"
TOOL_AT_RUN_TIME = "tcp_unknown"
NOT_ATTEMPTED = (COMPUTED_AT_RUN_TIME, TOOL_AT_RUN_TIME)  # what the program leaves open, not a failure
CONTROLLER_CANNOT_REACH = "unreachable"
IK_ITERATIONS = 100  # damped Newton steps of at most 0.3 rad: room for a move across the workspace
# A pose is solved again when the joints it is solved from moved by more than this since its last solve: a
# seed that moved less cannot change the branch the solve converges to (the solve's own tolerance is 1e-10 rad).
SEED_MOVED_RAD = 1e-6
MAX_SWEEPS = 6  # batched sweeps over all poses before the rest is solved row by row
# Rows a solve takes at once (the controller's inverse and the calibrated one): its (rows, 6, 6) Jacobians,
# the chain's frames and the effects' bases stay a few MB, and a row's answer does not depend on the rows
# it is solved with.
CHUNK_ROWS = 4096
WORDS = {  # the solver's statuses, said
    "unreachable": "out of reach",
    "joint_limits": "outside the joint limits",
    "near_singularity": "at a singular configuration",
}


@dataclass(frozen=True)
class TargetCompensation:
    """What became of one target."""

    target: Target
    status: str  # OK, one of NOT_ATTEMPTED, or the solver's status
    reason: str = ""  # why it was not compensated, in words
    values: tuple[float, ...] | None = None  # OK: the compensated literal (m and rad, as the target's)
    shift_mm: float | None = None  # OK: how far the written tool point moved (nominal kinematics)
    turn_deg: float | None = None  # OK: how far the written tool orientation turned
    joint_deg: float | None = None  # OK: the largest joint correction
    bound_mm: float | None = None  # OK: 95 % bound of where the tool point lands (None: not known)

    def as_dict(self) -> dict:
        t = self.target
        return {"line": t.line, "column": t.column, "call": t.call, "role": t.role, "kind": t.kind,
                "source": t.source, "tcp_line": None if t.tcp is None else t.tcp.line, "status": self.status,
                "reason": self.reason, "shift_mm": self.shift_mm, "turn_deg": self.turn_deg,
                "joint_deg": self.joint_deg, "bound_mm": self.bound_mm}


@dataclass(frozen=True)
class ProgramCompensation:
    per_target: tuple[TargetCompensation, ...]
    seconds: float

    @property
    def replacements(self) -> dict[Target, tuple[float, ...]]:
        """The compensated targets and their new values, for ``urscript.rewrite``."""
        return {o.target: o.values for o in self.per_target if o.status == OK}

    @property
    def failed(self) -> tuple[TargetCompensation, ...]:
        """Literal targets the compensation tried and could not compensate."""
        return tuple(o for o in self.per_target if o.status != OK and o.status not in NOT_ATTEMPTED)


@dataclass
class _Rows:
    """The literal targets the compensation attempts, in program order, as arrays of N rows."""

    index: np.ndarray  # (N,) into the program's targets
    tool_mm: list[tuple[float, ...]]  # the distinct tool points (mm, flange frame), in order of first use
    tool_of: np.ndarray  # (N,) into tool_mm
    tool_rot: np.ndarray  # (N, 3, 3) flange -> tool rotation
    position_mm: np.ndarray  # (N, 3) the desired tool point, controller's base frame
    flange_rot: np.ndarray  # (N, 3, 3) the desired flange orientation, controller's base frame
    is_pose: np.ndarray  # (N,) a pose target (else joints)
    q: np.ndarray  # (N, nj) the joints the controller reaches it at (nominal model); NaN until solved

    def take(self, keep: np.ndarray) -> "_Rows":
        return _Rows(self.index[keep], self.tool_mm, self.tool_of[keep], self.tool_rot[keep], self.position_mm[keep],
                     self.flange_rot[keep], self.is_pose[keep], self.q[keep])


def compensate_program(program: Program, nominal, calibrated, *, default_tcp_mm, seed_rad=None,
                       tool_map=None) -> ProgramCompensation:
    """Every literal target of `program` compensated with `calibrated` (a ``CalibratedModel``);
    `nominal` is the controller's model, `default_tcp_mm` (3,) the tool point where the program
    sets no tool, `seed_rad` the joints the program starts from (needed only when a pose target
    comes before any target the joints are known at), `tool_map` the model's
    ``solvers.compensation.tool_map.ToolMap`` (how the controller's tool points map into the
    calibrated end frame, and each target's bound; None: tool points taken as given in that frame,
    no bound). ProgramError for a robot model that is not a six-joint arm (URScript's joint lists
    have six values) or a pose whose branch nothing says.

    Every step works on all targets at once (one tool's at a time where the tool matters); what
    is per target in Python is reading the targets and writing their reports."""
    started = time.perf_counter()
    if nominal.n_joints != JOINT_VALUES:
        raise ProgramError(f"{program.name}: URScript moves {JOINT_VALUES} joints; the robot model "
                           f"{nominal.name} has {nominal.n_joints}")
    per_target: list[TargetCompensation | None] = [None] * len(program.targets)
    rows = _literal_rows(program, per_target, nominal, default_tcp_mm, seed_rad)
    frames = [solver.rigid_frames(nominal, nominal.nominal, np.array(t)) for t in rows.tool_mm]
    rows.q = _controller_joints(rows.q, rows.is_pose, rows.tool_of, rows.position_mm, rows.flange_rot, frames,
                                seed_rad, nominal.n_joints)
    reached = np.isfinite(rows.q).all(axis=1)
    for k in rows.index[~reached]:
        per_target[k] = TargetCompensation(program.targets[k], CONTROLLER_CANNOT_REACH,
                                           "not compensated: the controller's own model does not reach this pose "
                                           "from the previous target's joints")
    rows = rows.take(reached)
    # one controller frame for the whole program, fitted at the tool the calibration knows (module docstring)
    default = np.asarray(default_tcp_mm, dtype=float)
    at_model, at_controller = (default, default) if tool_map is None else tool_map.frame_points(default)
    controller = solver.controller_frame(calibrated, nominal, offset_mm=at_model, nominal_offset_mm=at_controller)
    _compensate_rows(program, rows, per_target, nominal, calibrated, controller, tool_map)
    return ProgramCompensation(tuple(per_target), time.perf_counter() - started)


def _literal_rows(program: Program, per_target: list, nominal, default_tcp_mm, seed_rad) -> _Rows:
    """The targets to compensate as rows: a pose's desired tool point and flange orientation, a joint
    target's own joints and where the nominal model puts its tool. What is not attempted (computed at
    run time, under a tool set at run time) and joint targets outside the limits get their report in
    `per_target` here."""
    tcps: dict = {}  # the set_tcp in force (None: the default tool) -> its number among the distinct ones
    index, tcp_of, values, is_pose = [], [], [], []
    for k, target in enumerate(program.targets):
        if target.kind == RUNTIME:
            per_target[k] = TargetCompensation(target, COMPUTED_AT_RUN_TIME, f"not compensated: {target.reason}")
            continue
        if target.tcp is not None and target.tcp.pose is None:
            per_target[k] = TargetCompensation(target, TOOL_AT_RUN_TIME, f"not compensated: the tool is set at run time on "
                                                            f"line {target.tcp.line} (set_tcp({target.tcp.source}))")
            continue
        index.append(k)
        tcp_of.append(tcps.setdefault(target.tcp, len(tcps)))
        values.append(target.values)
        is_pose.append(target.kind == POSE)
    nj = nominal.n_joints
    index, tcp_of = np.array(index, dtype=int), np.array(tcp_of, dtype=int)
    values, is_pose = np.array(values, dtype=float).reshape(-1, JOINT_VALUES), np.array(is_pose, dtype=bool)
    inside = is_pose.copy()
    limits = getattr(nominal, "joint_limits", None)
    if limits is None:
        inside[:] = True
    else:
        low, high = np.asarray(limits, dtype=float).T
        inside |= ((values >= low) & (values <= high)).all(axis=1)
    for j in np.flatnonzero(~inside):  # joint targets the controller refuses
        target = program.targets[index[j]]
        per_target[index[j]] = TargetCompensation(target, "joint_limits",
                                                  f"not compensated: {_outside_limits(nominal, values[j])}")
    index, tcp_of, values, is_pose = index[inside], tcp_of[inside], values[inside], is_pose[inside]
    if len(index) and is_pose[0] and seed_rad is None:
        target = program.targets[index[0]]
        raise ProgramError(
            f"{program.name}:{target.line}:{target.column}: {target.call}'s {target.role} is a pose and "
            "comes before any joint target: the controller solves it from the joints the arm is at when "
            "the program starts, which the program does not say; give them with --seed-deg")
    tools = [_tool(tcp, default_tcp_mm) for tcp in tcps]  # (tool_mm, tool_rot) of each set_tcp in force
    tool_mm = list(dict.fromkeys(t[0] for t in tools))
    tool_of = np.array([tool_mm.index(t[0]) for t in tools], dtype=int)[tcp_of] if tools else tcp_of
    tool_rot = np.array([t[1] for t in tools]).reshape(-1, 3, 3)[tcp_of]
    n = len(index)
    q = np.full((n, nj), np.nan)
    position, flange = np.empty((n, 3)), np.empty((n, 3, 3))
    joints = ~is_pose
    q[joints] = values[joints]
    for t, tool in enumerate(tool_mm):  # a joint target's tool point and flange: the nominal forward kinematics
        these = np.flatnonzero(joints & (tool_of == t))
        if len(these):
            rot, p = solver.rigid_frames(nominal, nominal.nominal, np.array(tool))(q[these], None)[:2]
            position[these], flange[these] = p, rot
    position[is_pose] = values[is_pose, :3] * 1000.0
    flange[is_pose] = se3.rotvec_to_matrix(values[is_pose, 3:]) @ np.swapaxes(tool_rot[is_pose], 1, 2)
    return _Rows(index, tool_mm, tool_of, tool_rot, position, flange, is_pose, q)


def _outside_limits(model, q: np.ndarray) -> str:
    """Why joint target `q` (rad) is not one the controller moves to (a joint outside the model's
    limits: the controller refuses it), or "" when it is."""
    limits = getattr(model, "joint_limits", None)
    if limits is None:
        return ""
    for i, (value, (low, high)) in enumerate(zip(q, np.asarray(limits, dtype=float))):
        if not low <= value <= high:
            return (f"joint {i + 1} at {np.degrees(value):.6g} deg is outside its limits "
                    f"{np.degrees(low):.1f}..{np.degrees(high):.1f} deg")
    return ""


def _tool(tcp: SetTcp | None, default_tcp_mm) -> tuple[tuple[float, ...], np.ndarray]:
    """The tool point (mm, flange frame) and the flange -> tool rotation in force."""
    if tcp is None:
        return tuple(float(v) for v in np.asarray(default_tcp_mm, dtype=float)), np.eye(3)
    return tuple(float(v) * 1000.0 for v in tcp.pose[:3]), se3.rotvec_to_matrix(np.array(tcp.pose[3:]))


def _controller_joints(q: np.ndarray, is_pose: np.ndarray, tool_of: np.ndarray, position: np.ndarray,
                       flange: np.ndarray, frames: list, seed, nj: int) -> np.ndarray:
    """(N, nj): the joints the controller reaches each row at (NaN where its nominal inverse fails): a joint
    target's own (`q`'s rows that are not poses), a pose's nominal inverse from the previous row's joints (the
    seed before the first); `frames[tool_of[i]]` the nominal model's at row i's tool.

    That chain is sequential, but only through the branch: a pose solved from joints near the previous
    row's converges to the same solution. So all poses are solved at once, each from the previous row's
    latest joints (at first the last joint target's), again for the rows whose seed moved by more than
    SEED_MOVED_RAD, until none does (two or three sweeps on a path); what has not settled after
    MAX_SWEEPS is finished in the controller's own order, row by row (``_row_by_row``). The answer is
    the row-by-row one."""
    n = len(q)
    q = q.copy()
    poses = np.flatnonzero(is_pose)
    if not len(poses):
        return q
    start = np.full(nj, np.nan) if seed is None else np.asarray(seed, dtype=float)
    used = np.full((n, nj), np.nan)  # the seed each pose was last solved from

    def stale():
        before = _previous(q, start)
        moved = ~(np.abs(before[poses] - used[poses]) <= SEED_MOVED_RAD).all(axis=1)  # NaN: never solved
        return poses[moved], before

    for _ in range(MAX_SWEEPS):
        todo, before = stale()
        if not len(todo):
            return q
        for tool in np.unique(tool_of[todo]):
            these = todo[tool_of[todo] == tool]
            q[these] = _nominal_inverse(frames[tool], position[these], flange[these], before[these])
            used[these] = before[these]
    todo, _ = stale()
    if len(todo):
        _row_by_row(q, used, todo, is_pose, start, lambda i, last: _nominal_inverse(
            frames[tool_of[i]], position[i:i + 1], flange[i:i + 1], last[None])[0])
    return q


def _row_by_row(q: np.ndarray, used: np.ndarray, stale: np.ndarray, is_pose: np.ndarray, start: np.ndarray,
                solve_row) -> None:
    """Finish `q` in place as the controller goes, row by row from the first stale pose (one whose
    seed moved since its last solve): each pose from the joints of the last row before it that has any,
    solved again (`solve_row(i, seed)`) where that seed moved by more than SEED_MOVED_RAD from the one
    it was solved from. Where a row keeps its joints (a joint target, or a pose that did not move) the
    rows after it stand as the sweeps left them up to the next stale pose, which is where the walk goes
    on: its cost is that of the rows that change."""
    n = len(q)
    finite = np.isfinite(q).all(axis=1)
    last_known = np.maximum.accumulate(np.where(finite, np.arange(n), -1))  # the last row with joints, up to i
    i, last, k = int(stale[0]), None, 0
    while i < n:
        if last is None:  # the seed: the joints of the last row before i that has any, as the sweeps left them
            before = last_known[i - 1] if i else -1
            last = q[before] if before >= 0 else start
        kept = True
        if is_pose[i] and not (np.abs(last - used[i]) <= SEED_MOVED_RAD).all():
            new = solve_row(i, last)
            used[i] = last
            both_nan = not np.isfinite(new).any() and not np.isfinite(q[i]).any()
            kept = both_nan or bool((np.abs(new - q[i]) <= SEED_MOVED_RAD).all())
            q[i] = new
        if np.isfinite(q[i]).all():
            last = q[i]
            if kept:  # the rows after i see what they were solved from: on at the next stale pose
                while k < len(stale) and stale[k] <= i:
                    k += 1
                if k == len(stale):
                    return
                i, last = int(stale[k]), None
                continue
        i += 1


def _previous(q: np.ndarray, start: np.ndarray) -> np.ndarray:
    """(N, nj): for each row the joints of the last row before it that has any (else `start`)."""
    valid = np.isfinite(q).all(axis=1)
    last = np.maximum.accumulate(np.where(valid, np.arange(len(q)), -1))
    before = np.concatenate([[-1], last[:-1]])
    return np.where((before >= 0)[:, None], q[np.maximum(before, 0)], start)


def _nominal_inverse(frames, position, flange, seed) -> np.ndarray:
    """(N, nj): the nominal model's joints for the poses, each from its seed (as the controller solves a
    pose from the joints it is at); NaN rows where the solve does not converge (or has no seed)."""
    seed = np.asarray(seed, dtype=float)
    has_seed = np.isfinite(seed).all(axis=1)
    out = np.full(seed.shape, np.nan)
    rows = np.flatnonzero(has_seed)
    for chunk in np.array_split(rows, -(-len(rows) // CHUNK_ROWS)) if len(rows) else ():
        q, done = solver.solve(frames, position[chunk], flange[chunk], seed[chunk], max_iter=IK_ITERATIONS)[:2]
        out[chunk[done]] = q[done]
    return out


def _compensate_rows(program, rows: _Rows, per_target, nominal, calibrated, controller, tool_map=None) -> None:
    """The calibrated joints of every row (``solver.compensate``, one batch per tool point, at most
    CHUNK_ROWS rows at a time; the tool point as the controller knows it, in the calibrated model
    through `tool_map`), and each target's report with its bound."""
    if not len(rows.index):
        return
    direction = approach_directions(rows.q)  # joints in program order: backlash
    for t, tool_mm in enumerate(rows.tool_mm):
        group = np.flatnonzero(rows.tool_of == t)
        for chunk in np.array_split(group, -(-len(group) // CHUNK_ROWS)) if len(group) else ():
            in_model = solver.targets_in_model_frame(calibrated, nominal, rows.position_mm[chunk],
                                                     rows.flange_rot[chunk], "base", controller=controller)
            chunk_direction = direction[chunk]

            def ctx_at(q, which, d=chunk_direction):
                return Context(direction=d[which])

            tool = np.array(tool_mm)
            result = solver.compensate(nominal, calibrated, in_model[0], in_model[1], rows.q[chunk],
                                       offset_mm=tool if tool_map is None else tool_map.to_model(tool),
                                       nominal_offset_mm=tool, ctx_at=ctx_at, controller=controller)
            bound = None if tool_map is None else tool_map.bound_mm(result.q, tool)
            _report(program, rows.take(chunk), result, per_target, bound)


def _report(program, rows: _Rows, result, per_target, bound=None) -> None:
    """Each row's TargetCompensation from the solver's `result` for those rows: the new literal (a pose's
    as the nominal forward kinematics of the calibrated joints with the target's own tool), how far its
    tool point moved and turned, and the largest joint correction; a refused row's status in words."""
    ok = result.status == OK
    turn_deg, shift_mm, joint_deg = np.full(len(ok), np.nan), np.full(len(ok), np.nan), np.full(len(ok), np.nan)
    if ok.any():
        turn_deg[ok] = np.rad2deg(np.linalg.norm(se3.matrix_to_rotvec(
            result.rotation[ok] @ np.swapaxes(rows.flange_rot[ok], 1, 2)), axis=1))
        shift_mm[ok] = np.linalg.norm(result.position_mm[ok] - rows.position_mm[ok], axis=1)
        joint_deg[ok] = np.rad2deg(np.abs(result.q[ok] - rows.q[ok]).max(axis=1))
    values = result.q.copy()
    poses = np.flatnonzero(rows.is_pose & ok)
    if len(poses):
        written = np.array([program.targets[k].values[3:] for k in rows.index[poses]], dtype=float)
        values[poses, :3] = result.position_mm[poses] / 1000.0
        values[poses, 3:] = _rotvec_near(result.rotation[poses] @ rows.tool_rot[poses], written)
    for g, k in enumerate(rows.index):
        target, status = program.targets[k], str(result.status[g])
        if status != OK:
            per_target[k] = TargetCompensation(target, status, f"left as written: "
                                               f"{WORDS.get(status, status.replace('_', ' '))}")
            continue
        per_target[k] = TargetCompensation(target, OK, values=tuple(values[g].tolist()), shift_mm=float(shift_mm[g]),
                                           turn_deg=float(turn_deg[g]), joint_deg=float(joint_deg[g]),
                                           bound_mm=None if bound is None else float(bound[g]))


def _rotvec_near(rotation: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(N, 3): the rotation vector of each `rotation` (N, 3, 3) nearest its `reference` (N, 3): of the two
    that describe a turn (angle a about u, or a - 2 pi about u), the one the program's own value is closer
    to, so a pose written near half a turn does not flip its sign."""
    r = se3.matrix_to_rotvec(rotation)
    angle = np.linalg.norm(r, axis=1, keepdims=True)
    other = r * (1.0 - 2.0 * np.pi / np.where(angle < 1e-12, 1.0, angle))
    nearer = np.linalg.norm(r - reference, axis=1) <= np.linalg.norm(other - reference, axis=1)
    return np.where((nearer | (angle[:, 0] < 1e-12))[:, None], r, other)
