"""The one reader of what people write: cell files, robot model files, driver options.

Klipper style: each reader of a section validates every option where it reads it, with
bounds, and the first problem stops the load with one :class:`ConfigError` whose
message names the file, the section and the key (``cell.yaml: [limits.tcp_speed_m_s]:
7.0 is out of range (must be above 0)``). Keys nobody read are unknown keys
(:meth:`Section.done`), because a typo in a safety limit must not be silently ignored.

Driver options arrive as keyword arguments, not from a file: a driver reads them
through a :class:`Section` without a file (``Section.of_options``), and whoever built
the driver from a cell file re-raises the error with the file and section in front
(:meth:`ConfigError.located`).
"""
from __future__ import annotations

import math
import os
import re
import stat
from pathlib import Path

import numpy as np
import yaml


_KEY_LIKE = re.compile(r"[A-Za-z_][A-Za-z0-9_.\-]{0,63}")  # what a key of ours, or a typo of one, looks like


class ConfigError(ValueError):
    """A file or option that cannot be used; the message names file, section and key.

    ``problem`` is the bare complaint, ``section`` and ``key`` where it is (either may
    be None), ``source`` the file (None for options passed in code).
    """

    def __init__(self, problem: str, *, source: str | None = None, section: str | None = None,
                 key: str | None = None):
        self.problem, self.source, self.section, self.key = problem, source, section, key
        super().__init__(self._text())

    def _text(self) -> str:
        place = _join(self.section, self.key)
        parts = [self.source] if self.source else []
        if place:
            parts.append(f"[{place}]")
        parts.append(self.problem)
        return ": ".join(parts)

    def located(self, source: str, section: str, error: type["ConfigError"] | None = None) -> "ConfigError":
        """The same complaint, placed in `section` of the file `source`, as `error` (default: this class)."""
        inner = _join(section, self.section)
        return (error or type(self))(self.problem, source=source, section=inner, key=self.key)


def _join(section: str | None, key) -> str:
    """``limits`` + ``speed`` → ``limits.speed``; ``joints`` + ``[2]`` → ``joints[2]``."""
    key = None if key is None else str(key)
    if not section or not key:
        return section or key or ""
    return f"{section}{key}" if key.startswith("[") else f"{section}.{key}"


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class Section:
    """Typed, bounded reads of one mapping that remember which keys were read."""

    def __init__(self, source: str | None, name: str | None, mapping, error: type[ConfigError] = ConfigError):
        self.source, self.name, self.error = source, name or None, error
        if not isinstance(mapping, dict):
            self.fail(None, f"expected a mapping, got {_describe(mapping)}")
        self.mapping = mapping
        self.used: set = set()

    @classmethod
    def of_options(cls, error: type[ConfigError] = ConfigError, **options) -> "Section":
        """Options passed to a driver in code, read through the same checks; whoever built
        the driver from a file places the error there (:meth:`ConfigError.located`)."""
        return cls(None, None, options, error)

    def port(self, key: str = "port") -> int:
        return self.integer(key, low=1, high=65535)

    def timeout(self, key: str, high: float = 60.0) -> float:
        """A time in seconds, above 0 and at most `high`."""
        return self.number(key, above=0.0, high=high)

    def expect(self, allowed, required=()) -> "Section":
        """Refuse at once a key outside `allowed` and a missing `required` one (before any
        read, so a misspelt key is named as such rather than as a missing one)."""
        unknown = [k for k in self.mapping if k not in allowed]
        if unknown:
            self._unknown(unknown[0], f"allowed: {', '.join(sorted(map(str, allowed)))}")
        for key in required:
            if key not in self.mapping:
                self.fail(key, "missing (required)")
        return self

    def fail(self, key, what: str):
        raise self.error(what, source=self.source, section=self.name, key=None if key is None else str(key))

    def __contains__(self, key) -> bool:
        return key in self.mapping

    def _get(self, key, default, required: bool):
        self.used.add(key)
        if key not in self.mapping:
            if required:
                self.fail(key, "missing (required)")
            return default
        return self.mapping[key]

    def raw(self, key, default=None, *, required=False):
        """The value as written (for structures the caller walks itself)."""
        return self._get(key, default, required)

    def number(self, key, default=None, *, low=-math.inf, high=math.inf, above=None, below=None,
               required=False, integer=False) -> float:
        value = self._get(key, default, required)
        kind = "an integer" if integer else "a number"
        if not (isinstance(value, int) and not isinstance(value, bool) if integer else _is_number(value)) \
                or not math.isfinite(value):
            self.fail(key, f"{value!r} is not {kind}")
        if not low <= value <= high or (above is not None and value <= above) \
                or (below is not None and value >= below):
            if above is not None and below is not None:
                rng = f"between {above:g} and {below:g}, exclusive"
            elif above is not None:
                rng = f"above {above:g}" + (f" and at most {high:g}" if high < math.inf else "")
            elif below is not None:
                rng = f"below {below:g}"
            else:
                rng = f"in {low:g}..{high:g}"
            self.fail(key, f"{value!r} is out of range (must be {rng})")
        return int(value) if integer else float(value)

    def integer(self, key, default=None, *, low=-math.inf, high=math.inf, required=False) -> int:
        return self.number(key, default, low=low, high=high, required=required, integer=True)

    def vector(self, key, n: int, default=None, *, required=False, nonzero=False) -> np.ndarray:
        value = self._get(key, default, required)
        if not isinstance(value, (list, tuple)) or len(value) != n or any(
                not _is_number(v) or not math.isfinite(v) for v in value):
            self.fail(key, f"{value!r} is not a list of {n} numbers")
        if nonzero and not any(value):
            self.fail(key, "must not be the zero vector")
        return np.array(value, dtype=float)

    def text(self, key, default=None, *, required=False) -> str:
        value = self._get(key, default, required)
        if not isinstance(value, str) or not value:
            self.fail(key, f"{value!r} is not a non-empty text")
        return value

    def choice(self, key, allowed, default=None, *, required=False):
        value = self._get(key, default, required)
        if value not in allowed:
            self.fail(key, f"expected one of {', '.join(map(str, allowed))}, got {value!r}")
        return value

    def flag(self, key, default: bool) -> bool:
        value = self._get(key, default, False)
        if not isinstance(value, bool):
            self.fail(key, f"{value!r} is not true or false")
        return value

    def sequence(self, key, default=None, *, required=False, nonempty=False) -> list:
        value = self._get(key, default, required)
        if not isinstance(value, list) or (nonempty and not value):
            self.fail(key, f"expected a {'non-empty ' if nonempty else ''}list, got {_describe(value)}")
        return value

    def section(self, key, default=None, *, required=False) -> "Section":
        """The mapping under `key` as a Section of its own (``limits`` → ``limits``, ``joints[2]``…)."""
        value = self._get(key, {} if default is None and not required else default, required)
        return Section(self.source, self.child_name(key), value, self.error)

    def child_name(self, key) -> str:
        return _join(self.name, key)

    def items_of(self, key, *, required=False, nonempty=False) -> list["Section"]:
        """A list of mappings under `key`, each as a Section named ``key[i]``."""
        rows = self.sequence(key, [] if not required else None, required=required, nonempty=nonempty)
        return [Section(self.source, self.child_name(f"{key}[{i}]"), row, self.error) for i, row in enumerate(rows)]

    def done(self) -> None:
        """Refuse keys that no read asked for."""
        unknown = [k for k in self.mapping if k not in self.used]
        if unknown:
            self._unknown(unknown[0], f"keys here: {', '.join(sorted(map(str, self.used)))}")

    def _unknown(self, key, known: str):
        """An unknown key, named when it looks like one (a typo is shown as typed); a "key"
        that is no name is not echoed: the file is likely no file of this kind at all, and
        its first line may be nobody's business (a password file given by mistake)."""
        if isinstance(key, str) and _KEY_LIKE.fullmatch(key):
            self.fail(key, f"unknown key ({known})")
        self.fail(None, f"a key that is no name (not shown): is this the right file? ({known})")


def _describe(value) -> str:
    return f"{value!r}" if isinstance(value, (str, int, float, bool, type(None))) else type(value).__name__


class _Strict:
    """Safe YAML with two fixes for hand-written files: ``1e3`` is a number (as in YAML
    1.2, not a string as in 1.1) and a repeated key is an error instead of silently
    overriding the first."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise _RepeatedKey(f"{self.name}:{key_node.start_mark.line + 1}: {key}: "
                                   "key given twice in the same mapping")
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


class _RepeatedKey(Exception):
    pass


class _StrictPyLoader(_Strict, yaml.SafeLoader):
    """Parsed by PyYAML's own parser."""


class _StrictLoader(_Strict, getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """Parsed by libyaml where PyYAML was built with it (PyPI's wheels are: a cell file in a
    tenth of the time), to the same nodes as :class:`_StrictPyLoader`."""


for _loader in (_StrictPyLoader, _StrictLoader):
    _loader.add_implicit_resolver(
        "tag:yaml.org,2002:float",
        re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+$"),
        list("-+0123456789."),
    )

# What a hand-written file may be. The largest shipped file is a few kB; a calibrated model file
# with its effects some tens of kB.
MAX_FILE_BYTES = 4 << 20
# Anchors and aliases (&limits ... *limits) are allowed: people share a block between robots, and
# yaml.safe_dump writes them for a value our model files hold twice. But an alias is expanded by
# whoever walks the data, so nested aliases multiply (a "billion laughs" file of a few hundred
# bytes is 10^9 values): the nodes aliases add on top of those written are capped here, before
# anything is built, and an alias that contains itself is refused.
MAX_ALIAS_NODES = 10_000


def read_yaml(path: str | Path, error: type[ConfigError] = ConfigError):
    """Read a hand-written YAML file strictly; every problem is one `error` whose message
    starts with the file (and line, where YAML knows it). A device, a pipe or a folder, a file
    over MAX_FILE_BYTES, and aliases that expand beyond MAX_ALIAS_NODES are refused."""
    source = str(path)
    try:
        with open(path, "rb") as f:
            info = os.fstat(f.fileno())
            if not stat.S_ISREG(info.st_mode):
                raise error("not a regular file (a device, a pipe or a folder cannot be read as YAML)", source=source)
            if info.st_size > MAX_FILE_BYTES:
                raise error(f"{info.st_size} bytes; a file written by hand is far smaller (at most "
                            f"{MAX_FILE_BYTES >> 20} MiB are read)", source=source)
            text = f.read(MAX_FILE_BYTES + 1).decode("utf-8")
    except FileNotFoundError:
        raise error("no such file", source=source) from None
    except IsADirectoryError:
        raise error("not a regular file (a device, a pipe or a folder cannot be read as YAML)", source=source) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"cannot read: {exc}", source=source) from None
    loader = _StrictLoader(text)
    loader.name = source
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_aliases(node, source, error)
        return loader.construct_document(node)
    except _RepeatedKey as exc:
        raise error(str(exc)) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f":{mark.line + 1}" if mark is not None else ""
        raise error(f"not valid YAML: {getattr(exc, 'problem', exc)}", source=f"{path}{where}") from None
    except RecursionError:
        raise error("nested too deeply to be a file written by hand", source=source) from None
    finally:
        loader.dispose()


def _check_aliases(root: yaml.Node, source: str, error: type[ConfigError]) -> None:
    """Refuse a document whose aliases add more than MAX_ALIAS_NODES nodes when expanded, or
    that contains itself. Counts with each node's size computed once (so a bomb is measured in
    the time of its few written nodes, never expanded), depth first without recursion."""
    size: dict[int, int] = {}
    path: set[int] = set()  # the nodes being counted: a child among them is an alias of an ancestor
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, counted = stack.pop()
        key = id(node)
        children = _children(node)
        if counted:
            path.discard(key)
            size[key] = 1 + sum(size[id(c)] for c in children)
            continue
        if key in size:
            continue
        path.add(key)
        stack.append((node, True))
        for child in children:
            if id(child) in path:
                raise error(f"an alias refers to a node that contains it (line {child.start_mark.line + 1}): the "
                            "value would be infinite", source=source)
            if id(child) not in size:
                stack.append((child, False))
    added = size[id(root)] - len(size)
    if added > MAX_ALIAS_NODES:
        raise error(f"its aliases (*name) expand to {added} more values than the file writes; at most "
                    f"{MAX_ALIAS_NODES} are allowed (a file of nested aliases is a memory bomb, not a cell)",
                    source=source)


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []


def shipped(folder: str) -> dict[str, Path]:
    """Files that ship with cellcal in ``config/<folder>/``, by stem (``ur10e``, ``sim``)."""
    from importlib import resources
    root = resources.files("cellcal.config") / folder
    return {Path(str(p)).stem: Path(str(p)) for p in root.iterdir() if str(p).endswith(".yaml")}


def resolve(name_or_path: str | Path, folder: str, what: str, error: type[ConfigError] = ConfigError) -> Path:
    """A path as given, or the name of a file shipped in ``config/<folder>/``."""
    text = str(name_or_path)
    if not text.strip():
        raise error(f"no {what} given (a file path, or one of: {', '.join(sorted(shipped(folder)))})")
    path = Path(text)
    if path.exists() or path.suffix in (".yaml", ".yml") or "/" in text:
        return path
    files = shipped(folder)
    if text in files:
        return files[text]
    raise error(f"no such file, and not a shipped {what} (shipped: {', '.join(sorted(files))})", source=text)
