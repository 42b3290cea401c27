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

from cellcal.programs.urscript import JOINT_VALUES, JOINTS, POSE, RUNTIME, Program, ProgramError, SetTcp, Target
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
class _Row:
    index: int  # into the program's targets
    tool_mm: tuple[float, ...]  # the tool point in the flange frame
    tool_rot: np.ndarray  # flange -> tool rotation
    position_mm: np.ndarray  # the desired tool point, controller's base frame
    flange_rot: np.ndarray  # the desired flange orientation, controller's base frame
    q: np.ndarray | None  # the joints the controller reaches it at (nominal model); None until solved


def compensate_program(program: Program, nominal, calibrated, *, default_tcp_mm, seed_rad=None,
                       tool_map=None) -> ProgramCompensation:
    """Every literal target of `program` compensated with `calibrated` (a ``CalibratedModel``);
    `nominal` is the controller's model, `default_tcp_mm` (3,) the tool point where the program
    sets no tool, `seed_rad` the joints the program starts from (needed only when a pose target
    comes before any target the joints are known at), `tool_map` the model's
    ``solvers.compensation.tool_map.ToolMap`` (how the controller's tool points map into the
    calibrated end frame, and each target's bound; None: tool points taken as given in that frame,
    no bound). ProgramError for a robot model that is not a six-joint arm (URScript's joint lists
    have six values) or a pose whose branch nothing says."""
    started = time.perf_counter()
    if nominal.n_joints != JOINT_VALUES:
        raise ProgramError(f"{program.name}: URScript moves {JOINT_VALUES} joints; the robot model "
                           f"{nominal.name} has {nominal.n_joints}")
    per_target: list[TargetCompensation | None] = [None] * len(program.targets)
    rows: list[_Row] = []
    frames: dict[tuple, object] = {}
    for k, target in enumerate(program.targets):
        if target.kind == RUNTIME:
            per_target[k] = TargetCompensation(target, COMPUTED_AT_RUN_TIME, f"not compensated: {target.reason}")
            continue
        if target.tcp is not None and target.tcp.pose is None:
            per_target[k] = TargetCompensation(target, TOOL_AT_RUN_TIME, f"not compensated: the tool is set at run time on "
                                                            f"line {target.tcp.line} (set_tcp({target.tcp.source}))")
            continue
        tool_mm, tool_rot = _tool(target.tcp, default_tcp_mm)
        if tool_mm not in frames:
            frames[tool_mm] = solver.rigid_frames(nominal, nominal.nominal, np.array(tool_mm))
        if target.kind == JOINTS:
            q = np.array(target.values, dtype=float)
            outside = _outside_limits(nominal, q)
            if outside:
                per_target[k] = TargetCompensation(target, "joint_limits", f"not compensated: {outside}")
                continue
            rot, p = frames[tool_mm](q[None], None)[:2]
            position, flange = p[0], rot[0]
        else:
            if not rows and seed_rad is None:
                raise ProgramError(
                    f"{program.name}:{target.line}:{target.column}: {target.call}'s {target.role} is a pose and "
                    "comes before any joint target: the controller solves it from the joints the arm is at when "
                    "the program starts, which the program does not say; give them with --seed-deg")
            q = None
            position = np.array(target.values[:3]) * 1000.0
            flange = se3.rotvec_to_matrix(np.array(target.values[3:])) @ tool_rot.T
        rows.append(_Row(k, tool_mm, tool_rot, position, flange, q))
    reached = _controller_joints(rows, frames, seed_rad, nominal.n_joints)
    for row, q in zip(rows, reached):
        row.q = q
        if not np.isfinite(q).all():
            per_target[row.index] = TargetCompensation(program.targets[row.index], CONTROLLER_CANNOT_REACH,
                                          "not compensated: the controller's own model does not reach this pose "
                                          "from the previous target's joints")
    rows = [r for r in rows if np.isfinite(r.q).all()]
    # one controller frame for the whole program, fitted at the tool the calibration knows (module docstring)
    default = np.asarray(default_tcp_mm, dtype=float)
    at_model, at_controller = (default, default) if tool_map is None else tool_map.frame_points(default)
    controller = solver.controller_frame(calibrated, nominal, offset_mm=at_model, nominal_offset_mm=at_controller)
    _compensate_rows(program, rows, per_target, nominal, calibrated, controller, tool_map)
    return ProgramCompensation(tuple(per_target), time.perf_counter() - started)


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


def _controller_joints(rows: list[_Row], frames, seed, nj: int) -> np.ndarray:
    """(N, nj): the joints the controller reaches each row at (NaN where its nominal inverse fails): a joint
    target's own, a pose's nominal inverse from the previous row's joints (the seed before the first).

    That chain is sequential, but only through the branch: a pose solved from joints near the previous
    row's converges to the same solution. So all poses are solved at once, each from the previous row's
    latest joints, again for the rows whose seed moved by more than SEED_MOVED_RAD, until none does
    (two or three sweeps on a path); what has not settled after MAX_SWEEPS is finished row by row, the
    controller's own order. The answer is the row-by-row one."""
    n = len(rows)
    q = np.full((n, nj), np.nan)
    for i, r in enumerate(rows):
        if r.q is not None:
            q[i] = r.q
    poses = np.flatnonzero([r.q is None for r in rows])
    if not len(poses):
        return q
    start = np.full(nj, np.nan) if seed is None else np.asarray(seed, dtype=float)
    position = np.array([r.position_mm for r in rows])
    flange = np.array([r.flange_rot for r in rows])
    tools = list(dict.fromkeys(r.tool_mm for r in rows))
    tool_of = np.array([tools.index(r.tool_mm) for r in rows])
    is_pose = np.zeros(n, bool)
    is_pose[poses] = True
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
            q[these] = _nominal_inverse(frames[tools[tool]], position[these], flange[these], before[these])
            used[these] = before[these]
    todo, before = stale()
    if len(todo):  # row by row from the first pose still moving
        last = before[todo[0]]
        for i in range(todo[0], n):
            if is_pose[i]:
                q[i] = _nominal_inverse(frames[tools[tool_of[i]]], position[i:i + 1], flange[i:i + 1], last[None])[0]
            if np.isfinite(q[i]).all():
                last = q[i]
    return q


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
    if has_seed.any():
        q, done = solver.solve(frames, position[has_seed], flange[has_seed], seed[has_seed],
                               max_iter=IK_ITERATIONS)[:2]
        out[np.flatnonzero(has_seed)[done]] = q[done]
    return out


def _compensate_rows(program, rows, per_target, nominal, calibrated, controller, tool_map=None) -> None:
    if not rows:
        return
    direction = approach_directions(np.array([r.q for r in rows]))  # joints in program order: backlash
    for tool_mm in dict.fromkeys(r.tool_mm for r in rows):
        group = [j for j, r in enumerate(rows) if r.tool_mm == tool_mm]
        position = np.array([rows[j].position_mm for j in group])
        flange = np.array([rows[j].flange_rot for j in group])
        q_controller = np.array([rows[j].q for j in group])
        in_model = solver.targets_in_model_frame(calibrated, nominal, position, flange, "base", controller=controller)
        group_direction = direction[group]

        def ctx_at(q, which, d=group_direction):
            return Context(direction=d[which])

        tool = np.array(tool_mm)  # as the controller knows it; in the calibrated end frame through the tool map
        result = solver.compensate(nominal, calibrated, in_model[0], in_model[1], q_controller,
                                   offset_mm=tool if tool_map is None else tool_map.to_model(tool),
                                   nominal_offset_mm=tool, ctx_at=ctx_at, controller=controller)
        bound = None if tool_map is None else tool_map.bound_mm(result.q, tool)
        for g, j in enumerate(group):
            row, status = rows[j], str(result.status[g])
            target = program.targets[row.index]
            if status != OK:
                per_target[row.index] = TargetCompensation(target, status, f"left as written: "
                                              f"{WORDS.get(status, status.replace('_', ' '))}")
                continue
            q = result.q[g]
            if target.kind == POSE:
                tool_rotation = result.rotation[g] @ row.tool_rot
                values = (*(result.position_mm[g] / 1000.0),
                          *_rotvec_near(tool_rotation, np.array(target.values[3:])))
            else:
                values = tuple(q)
            turn = se3.matrix_to_rotvec(result.rotation[g] @ row.flange_rot.T)
            per_target[row.index] = TargetCompensation(
                target, OK, values=tuple(float(v) for v in values),
                shift_mm=float(np.linalg.norm(result.position_mm[g] - row.position_mm)),
                turn_deg=float(np.rad2deg(np.linalg.norm(turn))),
                joint_deg=float(np.rad2deg(np.abs(q - row.q).max())),
                bound_mm=None if bound is None else float(bound[g]))


def _rotvec_near(rotation: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The rotation vector of `rotation` nearest `reference`: of the two that describe a turn
    (angle a about u, or a - 2 pi about u), the one the program's own value is closer to, so a
    pose written near half a turn does not flip its sign."""
    r = se3.matrix_to_rotvec(rotation)
    angle = float(np.linalg.norm(r))
    if angle < 1e-12:
        return r
    other = r * (1.0 - 2.0 * np.pi / angle)
    return r if np.linalg.norm(r - reference) <= np.linalg.norm(other - reference) else other
