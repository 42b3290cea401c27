"""URScript programs: every motion target, the tool in force at it, and a rewrite that touches
nothing but the targets' numbers.

A scanner, not an interpreter. It tokenizes the program (comments ``# ...`` to the end of
the line, strings in double or single quotes with backslash escapes, numbers, names,
operators, a backslash at the end of a line as a continuation), checks that every bracket
``( [`` is closed by its own kind and that every string ends on its line, and then finds
every call of ``movej``, ``movel``, ``movep``, ``movec`` and ``set_tcp`` -- inside ``def`` /
``end`` blocks, across lines, with keyword arguments (``a=``, ``v=``, ``t=``, ``r=``,
``mode=``) -- in the order the lines are written. Names inside comments and strings are
never calls; ``def movel(...)`` defines a function, it does not call one.

A target is compensable when it is written as a literal: a pose ``p[x, y, z, rx, ry, rz]``
(m, rotation vector in rad) or a joint list ``[q1, ..., q6]`` (rad, as URScript takes
joints), each value a number with an optional sign. Anything else -- a variable,
``pose_trans(...)``, ``get_inverse_kin(...)``, arithmetic -- is computed at run time and is
reported as such (``kind`` :data:`RUNTIME`), never guessed. ``movec`` has two targets, the
via point and the end point. The tool at each target is the last ``set_tcp`` written
before it; a ``set_tcp`` whose pose is not a literal makes the tool unknown from its line on.

:func:`rewrite` replaces the numbers of the literals it is given, each number's own
characters (sign included) and nothing else: code, comments, speeds, blends, spacing
inside the brackets and line endings stay byte for byte. Values are written with
:data:`DECIMALS` decimals (0.1 nm, 1e-10 rad), trailing zeros dropped.
"""
from __future__ import annotations

import bisect
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

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
