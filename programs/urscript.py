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
from array import array
from dataclasses import dataclass
from typing import NamedTuple

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

_NUMBER = r"(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_SPACE = r"[ \t\f\v\r\n\ufeff]+|\\[ \t]*(?:\r\n|\r|\n)"
# what may stand between the values of a literal list: spaces, line continuations and comments, taken whole
# (possessive: a comment never gives back the ']' it holds)
_GAP = r"(?:[ \t\f\v\r\n\ufeff]++|\\[ \t]*+(?:\r\n|\r|\n)|\#[^\r\n]*+)*+"
_SIGNED = rf"[+-]?{_GAP}(?>{_NUMBER}){_GAP}"
_TOKEN = re.compile(rf"""
    (?P<space>{_SPACE})
  | (?P<comment>\#[^\r\n]*)
  | (?P<list>\[{_GAP}{_SIGNED}(?:,{_GAP}{_SIGNED})*\])
  | (?P<number>{_NUMBER})
  | (?P<name>[A-Za-z_][A-Za-z0-9_]*)
  | (?P<string>"(?:[^"\\\r\n]|\\[^\r\n])*"|'(?:[^'\\\r\n]|\\[^\r\n])*')
  | (?P<open_string>["'])
  | (?P<op>==|!=|<=|>=|.)
""", re.VERBOSE | re.DOTALL)
_IN_LIST = re.compile(rf"(?P<gap>(?:{_SPACE}|\#[^\r\n]*)+)|(?P<sign>[+-])|(?P<number>{_NUMBER})|[,\[\]]")
_KIND_CODES = {"number": 0, "name": 1, "string": 2, "op": 3, "list": 4}
_NUMBER_KIND, _NAME, _STRING, _OP, _LIST = range(5)
_KIND_NAMES = tuple(_KIND_CODES)
_CALLS = frozenset(MOTIONS) | {SET_TCP}
_CLOSES = {")": "(", "]": "["}


class ProgramError(Exception):
    """A program that cannot be read as URScript: the message names the file, line and column."""


class Token(NamedTuple):
    kind: str  # number, name, string, op, list (a literal list of numbers ``[1, -2.5]``, brackets included)
    text: str
    start: int  # offsets in the program's text
    end: int


class Number(NamedTuple):
    """One value of a literal: its characters (sign included) and what they say."""

    start: int
    end: int
    text: str
    value: float


@dataclass(frozen=True, slots=True)
class SetTcp:
    """A ``set_tcp`` call: the tool pose it sets (m, rad), or None when computed at run time."""

    line: int
    column: int
    source: str  # the argument as written
    pose: tuple[float, ...] | None


@dataclass(frozen=True, slots=True)
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
    """The program's tokens (no spaces or comments; a literal list of numbers is one token of kind
    ``list``); ProgramError for a string left open or a bracket that is not closed by its own kind."""
    scan = _Scan(text, name)
    return [scan.token(i) for i in range(len(scan))]


def parse(text: str, name: str = "<program>") -> Program:
    """Every motion target and set_tcp of the program, in the order they are written.
    ProgramError, naming file:line:column, for a literal number no double holds (``1e400``)."""
    scan = _Scan(text, name)
    if scan.beyond is not None:
        start, number = scan.beyond
        raise ProgramError(f"{name}:{scan.lines.where(start)}: {number} is beyond any number the "
                           "controller holds (a double's largest is about 1.8e308)")
    lines, n = scan.lines, len(scan)
    targets: list[Target] = []
    tcps: list[SetTcp] = []
    tcp: SetTcp | None = None
    for i in scan.calls:  # the names of the calls looked for, in the order they are written
        if i + 1 >= n or scan.kinds[i + 1] != _OP or scan.text_of(i + 1) != "(":
            continue  # the name alone (a value, or a variable of that name)
        if i > 0 and scan.text_of(i - 1) in ("def", "."):
            continue  # a definition of a function of that name, or a member
        call = scan.text_of(i)
        args = scan.arguments(i + 1)
        if call == SET_TCP:
            value = scan.argument(args, 0, "pose")
            line, column = lines.line_column(scan.starts[value[0]] if value else scan.starts[i])
            literal = scan.literal(value) if value else None
            pose = literal[1] if literal and literal[0] == POSE and len(literal[1]) == POSE_VALUES else None
            tcp = SetTcp(line, column, scan.source(value), None if pose is None else tuple(n.value for n in pose))
            tcps.append(tcp)
            continue
        for position, role in enumerate(MOTIONS[call]):
            value = scan.argument(args, position, role)
            line, column = lines.line_column(scan.starts[value[0]] if value else scan.starts[i])
            targets.append(_target(scan, call, role, value, line, column, tcp))
    return Program(name, text, tuple(targets), tuple(tcps))


def rewrite(text: str,
            replacements: Mapping[Target, Sequence[float]] | Iterable[tuple[Target, Sequence[float]]]) -> str:
    """``text`` with the numbers of each given literal target replaced by the new values
    (same count and units: m and rad), every other character as it was."""
    pairs = replacements.items() if isinstance(replacements, Mapping) else replacements
    edits = []  # per target: where its first number starts, the target, its new values
    for target, values in pairs:
        if target.kind not in (POSE, JOINTS):
            raise ValueError(f"line {target.line}: {target.call} {target.role} is computed at run time; "
                             "only literal targets are rewritten")
        if len(values) != len(target.numbers):
            raise ValueError(f"line {target.line}: {len(values)} values for a literal of {len(target.numbers)}")
        for number in target.numbers:
            if text[number.start:number.end] != number.text:
                raise ValueError(f"line {target.line}: the text is not the one this target was parsed from")
        if target.numbers:
            edits.append((target.numbers[0].start, len(edits), target, values))
    edits.sort()
    done, pieces, at = [], [], 0  # the pieces joined a few thousand at a time: no list of them all
    for _, _, target, values in edits:
        for number, value in zip(target.numbers, values):
            if number.start < at:
                raise ValueError("two replacements overlap (the same target given twice?)")
            pieces += [text[at:number.start], format_number(value)]
            at = number.end
        if len(pieces) > 4096:
            done.append("".join(pieces))
            pieces = []
    return "".join(done + pieces + [text[at:]])


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


class _Scan:
    """The tokens of a program (no spaces or comments), kept as their kinds and offsets only, each
    opening bracket's closing one, and where the names of the calls looked for are: a long program
    is read in one pass without an object per token. ProgramError as :func:`tokenize` says."""

    def __init__(self, text: str, name: str):
        self.text, self.lines = text, _LineIndex(text)
        kinds, starts, ends = array("b"), array("q"), array("q")
        self.partner: dict[int, int] = {}  # index of each opening bracket -> index of its closing one
        self.calls: list[int] = []  # the names in _CALLS
        self.beyond: tuple[int, str] | None = None  # the first number no double holds: (offset, its text)
        stack: list[int] = []
        for m in _TOKEN.finditer(text):
            kind = m.lastgroup
            if kind == "space" or kind == "comment":
                continue
            start, end = m.span()
            i = len(kinds)
            if kind == "op":
                op = m.group()
                if op == "(" or op == "[":
                    stack.append(i)
                elif op == ")" or op == "]":
                    if not stack:
                        raise ProgramError(f"{name}:{self.lines.where(start)}: {op!r} closes nothing")
                    opened = stack.pop()
                    if text[starts[opened]] != _CLOSES[op]:
                        raise ProgramError(f"{name}:{self.lines.where(start)}: {op!r} closes the "
                                           f"{text[starts[opened]]!r} opened at {self.lines.where(starts[opened])}")
                    self.partner[opened] = i
            elif kind == "name":
                if m.group() in _CALLS:
                    self.calls.append(i)
            elif kind == "number":
                if self.beyond is None and not math.isfinite(float(m.group())):
                    self.beyond = (start, m.group())
            elif kind == "list":
                if self.beyond is None and _MAY_OVERFLOW.search(text, start, end):
                    self.beyond = next(((n.start(), n.group()) for n in _IN_LIST.finditer(text, start, end)
                                        if n.lastgroup == "number" and not math.isfinite(float(n.group()))), None)
            elif kind == "open_string":
                raise ProgramError(f"{name}:{self.lines.where(start)}: a string opened here is not closed on its line")
            kinds.append(_KIND_CODES[kind])
            starts.append(start)
            ends.append(end)
        if stack:
            raise ProgramError(f"{name}:{self.lines.where(starts[stack[-1]])}: {text[starts[stack[-1]]]!r} is "
                               "never closed")
        self.kinds, self.starts, self.ends = kinds, starts, ends

    def __len__(self) -> int:
        return len(self.kinds)

    def text_of(self, i: int) -> str:
        return self.text[self.starts[i]:self.ends[i]]

    def token(self, i: int) -> Token:
        return Token(_KIND_NAMES[self.kinds[i]], self.text_of(i), self.starts[i], self.ends[i])

    def arguments(self, open_at: int) -> list[range]:
        """The arguments of the call whose '(' is token `open_at` (token ranges), split at the commas
        of its own level; a bracketed group is one piece of an argument."""
        close_at = self.partner[open_at]
        args, first, k = [], open_at + 1, open_at + 1
        while k < close_at:
            if self.kinds[k] == _OP and self.text[self.starts[k]] == ",":  # no other operator starts with ',
                args.append(range(first, k))
                first = k = k + 1
                continue
            k = self.partner.get(k, k) + 1
        if first < close_at or args:
            args.append(range(first, close_at))
        return args

    def argument(self, args: list[range], position: int, keyword: str) -> range | None:
        """The value of a parameter given by keyword or by position (keywords come after positions)."""
        positional = []
        for arg in args:
            if len(arg) >= 2 and self.kinds[arg[0]] == _NAME and self.kinds[arg[1]] == _OP \
                    and self.text_of(arg[1]) == "=":
                if self.text_of(arg[0]) == keyword:
                    return arg[2:] or None
                continue
            positional.append(arg)
        return positional[position] if position < len(positional) and positional[position] else None

    def source(self, tokens: range | None) -> str:
        """The tokens as written, whitespace runs (and what the scanner skips) shown as one space."""
        return " ".join(self.text[self.starts[tokens[0]]:self.ends[tokens[-1]]].split()) if tokens else ""

    def literal(self, tokens: range) -> tuple[str, list[Number]] | None:
        """(POSE or JOINTS, its numbers) when the tokens are ``p[n, ...]`` or ``[n, ...]``, else None."""
        kind, body = JOINTS, tokens
        if self.kinds[tokens[0]] == _NAME and self.text_of(tokens[0]) == "p":
            kind, body = POSE, tokens[1:]
        if len(body) == 1 and self.kinds[body[0]] == _LIST:
            return kind, _list_numbers(self.text, self.starts[body[0]], self.ends[body[0]])
        # a list the list token does not take holds no number: the empty one ``[]``, or not a literal
        if len(body) == 2 and self.text_of(body[0]) == "[" and self.text_of(body[1]) == "]" \
                and self.kinds[body[0]] == _OP:
            return kind, []
        return None


_PLAIN_NUMBER = re.compile(rf"(?:([+-])[ \t\f\v\r\n\ufeff]*)?({_NUMBER})")  # a value of a list without comments
_MAY_OVERFLOW = re.compile(r"[eE]|\d{300}")  # a number beyond a double's range has an exponent or 309 digits


def _list_numbers(text: str, start: int, end: int) -> list[Number]:
    """The numbers of the list token text[start:end], each with its sign and what stands between them."""
    if text.find("#", start, end) < 0 and text.find("\\", start, end) < 0:  # no comment, no continuation
        return [Number(m.start(), m.end(), m.group(), (-1.0 if m.group(1) == "-" else 1.0) * float(m.group(2)))
                for m in _PLAIN_NUMBER.finditer(text, start, end)]
    out, sign_at, sign = [], -1, 1.0
    for m in _IN_LIST.finditer(text, start, end):
        kind = m.lastgroup
        if kind == "sign":
            sign_at, sign = m.start(), (-1.0 if m.group() == "-" else 1.0)
        elif kind == "number":
            at = m.start() if sign_at < 0 else sign_at
            out.append(Number(at, m.end(), text[at:m.end()], sign * float(m.group())))
            sign_at, sign = -1, 1.0
    return out


def _target(scan: _Scan, call, role, value, line, column, tcp) -> Target:
    source = scan.source(value)
    if not value:
        return Target(line, column, call, role, RUNTIME, "", None, (), tcp, f"no {role} given")
    literal = scan.literal(value)
    if literal is None:
        return Target(line, column, call, role, RUNTIME, source, None, (), tcp, "computed at run time")
    kind, numbers = literal
    wanted = POSE_VALUES if kind == POSE else JOINT_VALUES
    if len(numbers) != wanted:
        what = "a pose" if kind == POSE else "a joint list"
        return Target(line, column, call, role, RUNTIME, source, None, (), tcp,
                      f"{what} of {len(numbers)} values, not {wanted}: not a target the controller takes")
    return Target(line, column, call, role, kind, source, tuple(n.value for n in numbers), tuple(numbers), tcp)
