"""Baseline for ``program_bench``: ``compensate --program``'s reading and compensation of a program as
they were at commit 9a240ae, before they worked on whole arrays.

Kept verbatim but for this docstring and the imports, the two modules one after the other, so
the bench measures the old code in the same run: ``programs/urscript.py`` (a Token object per
token of the program, every call's arguments split again from a copy of its tokens) and
``programs/apply.py`` (a row object per target, its pose, tool and forward kinematics one at a
time; the controller's joints in batched sweeps and then row by row from the first pose still
moving to the end of the program; each target's report and rotation vector one at a time).
The solver (``solvers.compensation.compensate``) is the package's own, which the faster path did
not change. Not used by cellcal itself.
"""
from __future__ import annotations

import bisect
import math
import re
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from cellcal.solvers.compensation import compensate as solver
from cellcal.solvers.geometry import se3
from cellcal.solvers.analysis.effects import Context, approach_directions

# -- programs/urscript.py --------------------------------------------------------------------------------------

MOTIONS = {  # motion command -> its target parameters, in order (URScript's names, usable as keywords)
    "movej": ("q",),
    "movel": ("pose",),
    "movep": ("pose",),
    "movec": ("pose_via", "pose_to"),
}
SET_TCP = "set_tcp"
POSE, JOINTS, RUNTIME = "pose", "joints", "runtime"
POSE_VALUES = 6  # x, y, z (m), rx, ry, rz (rad)
JOINT_VALUES = 6  # URScript's joint vectors: the six joints of a UR arm
DECIMALS = 10  # 1e-10 m and 1e-10 rad: a thousand times finer than any arm repeats

_TOKEN = re.compile(r"""
    (?P<space>[ \t\f\v\r\n\ufeff]+|\\[ \t]*(?:\r\n|\r|\n))
  | (?P<comment>\#[^\r\n]*)
  | (?P<number>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)
  | (?P<name>[A-Za-z_][A-Za-z0-9_]*)
  | (?P<string>"(?:[^"\\\r\n]|\\[^\r\n])*"|'(?:[^'\\\r\n]|\\[^\r\n])*')
  | (?P<open_string>["'])
  | (?P<op>==|!=|<=|>=|.)
""", re.VERBOSE | re.DOTALL)
_CLOSES = {")": "(", "]": "["}


class ProgramError(Exception):
    """A program that cannot be read as URScript: the message names the file, line and column."""


@dataclass(frozen=True)
class Token:
    kind: str  # number, name, string, op
    text: str
    start: int  # offsets in the program's text
    end: int


@dataclass(frozen=True)
class Number:
    """One value of a literal: its characters (sign included) and what they say."""

    start: int
    end: int
    text: str
    value: float


@dataclass(frozen=True)
class SetTcp:
    """A ``set_tcp`` call: the tool pose it sets (m, rad), or None when computed at run time."""

    line: int
    column: int
    source: str  # the argument as written
    pose: tuple[float, ...] | None


@dataclass(frozen=True)
class Target:
    """One target of a motion call, as written."""

    line: int  # 1-based, of the target's first character
    column: int
    call: str  # movej, movel, movep, movec
    role: str  # the URScript parameter: q, pose, pose_via, pose_to
    kind: str  # POSE, JOINTS or RUNTIME
    source: str  # the argument as written (whitespace runs shown as one space)
    values: tuple[float, ...] | None  # POSE: x, y, z (m), rx, ry, rz (rad); JOINTS: rad; RUNTIME: None
    numbers: tuple[Number, ...]  # the literal's values, where they are written
    tcp: SetTcp | None  # the set_tcp in force (None: the program has set none before this line)
    reason: str = ""  # RUNTIME: why it is not a literal


@dataclass(frozen=True)
class Program:
    name: str
    text: str
    targets: tuple[Target, ...]
    tcps: tuple[SetTcp, ...]


def read_program(path) -> Program:
    """Read and parse a URScript file. Its bytes are kept exactly (UTF-8, any byte that is not
    UTF-8 kept as it was), so :func:`encode` gives them back unchanged."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise ProgramError(f"{path}: cannot read the program: {exc.strerror or exc}") from None
    if b"\x00" in raw:  # no text file holds a NUL byte; every binary format does
        line = raw.count(b"\n", 0, raw.index(b"\x00")) + 1
        raise ProgramError(f"{path}: not a text program (a NUL byte on line {line}: a binary file?)")
    return parse(raw.decode("utf-8", errors="surrogateescape"), str(path))


def encode(text: str) -> bytes:
    """The bytes of a program's text as :func:`read_program` read them."""
    return text.encode("utf-8", errors="surrogateescape")


def tokenize(text: str, name: str = "<program>") -> list[Token]:
    """The program's tokens (no spaces or comments); ProgramError for a string left open or a
    bracket that is not closed by its own kind."""
    lines = _LineIndex(text)
    tokens: list[Token] = []
    stack: list[Token] = []
    for m in _TOKEN.finditer(text):
        kind = m.lastgroup
        if kind in ("space", "comment"):
            continue
        token = Token(kind, m.group(), m.start(), m.end())
        if kind == "open_string":
            raise ProgramError(f"{name}:{lines.where(token.start)}: a string opened here is not closed on its line")
        if token.text in "([" and kind == "op":
            stack.append(token)
        elif token.text in _CLOSES and kind == "op":
            if not stack:
                raise ProgramError(f"{name}:{lines.where(token.start)}: {token.text!r} closes nothing")
            opened = stack.pop()
            if opened.text != _CLOSES[token.text]:
                raise ProgramError(f"{name}:{lines.where(token.start)}: {token.text!r} closes the {opened.text!r} "
                                   f"opened at {lines.where(opened.start)}")
        tokens.append(token)
    if stack:
        raise ProgramError(f"{name}:{lines.where(stack[-1].start)}: {stack[-1].text!r} is never closed")
    return tokens


def parse(text: str, name: str = "<program>") -> Program:
    """Every motion target and set_tcp of the program, in the order they are written.
    ProgramError, naming file:line:column, for a literal number no double holds (``1e400``)."""
    tokens = tokenize(text, name)
    lines = _LineIndex(text)
    for token in tokens:
        if token.kind == "number" and not math.isfinite(float(token.text)):
            raise ProgramError(f"{name}:{lines.where(token.start)}: {token.text} is beyond any number the "
                               "controller holds (a double's largest is about 1.8e308)")
    partner = _partners(tokens)
    targets: list[Target] = []
    tcps: list[SetTcp] = []
    tcp: SetTcp | None = None
    for i, token in enumerate(tokens):
        if token.kind != "name" or (token.text not in MOTIONS and token.text != SET_TCP):
            continue
        if i + 1 >= len(tokens) or tokens[i + 1].text != "(" or tokens[i + 1].kind != "op":
            continue  # the name alone (a value, or a variable of that name)
        if i > 0 and (tokens[i - 1].text in ("def", ".")):
            continue  # a definition of a function of that name, or a member
        args = _arguments(tokens, i + 1, partner[i + 1])
        if token.text == SET_TCP:
            value = _argument(args, 0, "pose")
            line, column = lines.line_column(value[0].start if value else token.start)
            literal = _literal(value, text) if value else None
            pose = literal[1] if literal and literal[0] == POSE and len(literal[1]) == POSE_VALUES else None
            tcp = SetTcp(line, column, _source(value, text), None if pose is None else tuple(n.value for n in pose))
            tcps.append(tcp)
            continue
        for position, role in enumerate(MOTIONS[token.text]):
            value = _argument(args, position, role)
            line, column = lines.line_column(value[0].start if value else token.start)
            targets.append(_target(token.text, role, value, text, line, column, tcp))
    return Program(name, text, tuple(targets), tuple(tcps))


def rewrite(text: str,
            replacements: Mapping[Target, Sequence[float]] | Iterable[tuple[Target, Sequence[float]]]) -> str:
    """``text`` with the numbers of each given literal target replaced by the new values
    (same count and units: m and rad), every other character as it was."""
    pairs = replacements.items() if isinstance(replacements, Mapping) else replacements
    edits = []
    for target, values in pairs:
        if target.kind not in (POSE, JOINTS):
            raise ValueError(f"line {target.line}: {target.call} {target.role} is computed at run time; "
                             "only literal targets are rewritten")
        if len(values) != len(target.numbers):
            raise ValueError(f"line {target.line}: {len(values)} values for a literal of {len(target.numbers)}")
        for number, value in zip(target.numbers, values):
            if text[number.start:number.end] != number.text:
                raise ValueError(f"line {target.line}: the text is not the one this target was parsed from")
            edits.append((number.start, number.end, format_number(value)))
    edits.sort()
    for (_, end, _), (start, _, _) in zip(edits, edits[1:]):
        if start < end:
            raise ValueError("two replacements overlap (the same target given twice?)")
    out, at = [], 0
    for start, end, new in edits:
        out += [text[at:start], new]
        at = end
    out.append(text[at:])
    return "".join(out)


def format_number(value: float) -> str:
    """A URScript number with DECIMALS decimals, trailing zeros dropped (``0.0``, ``-0.4125``)."""
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{value} cannot be written into a program")
    text = f"{value:.{DECIMALS}f}".rstrip("0")
    text = text + "0" if text.endswith(".") else text
    return "0.0" if text == "-0.0" else text


# -- inside the scanner ------------------------------------------------------------------------------------

class _LineIndex:
    def __init__(self, text: str):
        self.starts = [0] + [m.end() for m in re.finditer(r"\r\n|\r|\n", text)]

    def line_column(self, offset: int) -> tuple[int, int]:
        line = bisect.bisect_right(self.starts, offset)
        return line, offset - self.starts[line - 1] + 1

    def where(self, offset: int) -> str:
        return "%d:%d" % self.line_column(offset)


def _partners(tokens: list[Token]) -> dict[int, int]:
    """Index of each opening bracket -> index of its closing one (the tokens are balanced)."""
    out, stack = {}, []
    for i, t in enumerate(tokens):
        if t.kind != "op":
            continue
        if t.text in "([":
            stack.append(i)
        elif t.text in _CLOSES:
            out[stack.pop()] = i
    return out


def _arguments(tokens, open_at: int, close_at: int) -> list[list[Token]]:
    """The call's arguments (token lists), split at the commas of its own level."""
    partner = _partners(tokens[open_at:close_at + 1])
    args, current, k = [], [], 1
    inner = tokens[open_at:close_at + 1]
    while k < len(inner) - 1:
        t = inner[k]
        if t.kind == "op" and t.text == ",":
            args.append(current)
            current = []
            k += 1
            continue
        end = partner.get(k, k)  # a bracketed group is one piece of the argument
        current.extend(inner[k:end + 1])
        k = end + 1
    if current or args:
        args.append(current)
    return args


def _argument(args: list[list[Token]], position: int, keyword: str) -> list[Token] | None:
    """The value of a parameter given by keyword or by position (keywords come after positions)."""
    positional = []
    for arg in args:
        if len(arg) >= 2 and arg[0].kind == "name" and arg[1].kind == "op" and arg[1].text == "=":
            if arg[0].text == keyword:
                return arg[2:] or None
            continue
        positional.append(arg)
    return positional[position] if position < len(positional) and positional[position] else None


def _source(tokens: list[Token] | None, text: str) -> str:
    return " ".join(text[tokens[0].start:tokens[-1].end].split()) if tokens else ""


def _literal(tokens: list[Token], text: str) -> tuple[str, list[Number]] | None:
    """(POSE or JOINTS, its numbers) when the tokens are ``p[n, ...]`` or ``[n, ...]``, else None."""
    kind, body = JOINTS, tokens
    if tokens and tokens[0].kind == "name" and tokens[0].text == "p":
        kind, body = POSE, tokens[1:]
    if len(body) < 2 or body[0].text != "[" or body[-1].text != "]" or body[0].kind != "op":
        return None
    numbers, k, inner = [], 0, body[1:-1]
    while k < len(inner):
        sign = 1.0
        start = inner[k].start
        if inner[k].kind == "op" and inner[k].text in "+-":
            sign = -1.0 if inner[k].text == "-" else 1.0
            k += 1
        if k >= len(inner) or inner[k].kind != "number":
            return None
        numbers.append(Number(start, inner[k].end, text[start:inner[k].end], sign * float(inner[k].text)))
        k += 1
        if k < len(inner):
            if inner[k].kind != "op" or inner[k].text != "," or k + 1 == len(inner):
                return None
            k += 1
    return kind, numbers


def _target(call, role, value, text, line, column, tcp) -> Target:
    source = _source(value, text)
    if not value:
        return Target(line, column, call, role, RUNTIME, "", None, (), tcp, f"no {role} given")
    literal = _literal(value, text)
    if literal is None:
        return Target(line, column, call, role, RUNTIME, source, None, (), tcp, "computed at run time")
    kind, numbers = literal
    wanted = POSE_VALUES if kind == POSE else JOINT_VALUES
    if len(numbers) != wanted:
        what = "a pose" if kind == POSE else "a joint list"
        return Target(line, column, call, role, RUNTIME, source, None, (), tcp,
                      f"{what} of {len(numbers)} values, not {wanted}: not a target the controller takes")
    return Target(line, column, call, role, kind, source, tuple(n.value for n in numbers), tuple(numbers), tcp)


# -- programs/apply.py -----------------------------------------------------------------------------------------

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

    def as_dict(self) -> dict:
        t = self.target
        return {"line": t.line, "column": t.column, "call": t.call, "role": t.role, "kind": t.kind,
                "source": t.source, "tcp_line": None if t.tcp is None else t.tcp.line, "status": self.status,
                "reason": self.reason, "shift_mm": self.shift_mm, "turn_deg": self.turn_deg,
                "joint_deg": self.joint_deg}


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


def compensate_program(program: Program, nominal, calibrated, *, default_tcp_mm, seed_rad=None) -> ProgramCompensation:
    """Every literal target of `program` compensated with `calibrated` (a ``CalibratedModel``);
    `nominal` is the controller's model, `default_tcp_mm` (3,) the tool point where the program
    sets no tool, `seed_rad` the joints the program starts from (needed only when a pose target
    comes before any target the joints are known at). ProgramError for a robot model that is not
    a six-joint arm (URScript's joint lists have six values) or a pose whose branch nothing says."""
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
    controller = solver.controller_frame(calibrated, nominal, offset_mm=np.asarray(default_tcp_mm, dtype=float))
    _compensate_rows(program, rows, per_target, nominal, calibrated, controller)
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


def _compensate_rows(program, rows, per_target, nominal, calibrated, controller) -> None:
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

        result = solver.compensate(nominal, calibrated, in_model[0], in_model[1], q_controller,
                                   offset_mm=np.array(tool_mm), ctx_at=ctx_at, controller=controller)
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
                joint_deg=float(np.rad2deg(np.abs(q - row.q).max())))


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
