"""The routines by name, as ``cellcal run ROUTINE`` and the operator panel select them.

The routines cellcal ships are the rows of :mod:`.table` (name -> module and class, the
section of the cell file it owns, its panel selector number or None); a plug-in or a test
adds one with :func:`register`. A routine's module is imported the first time that routine
is asked for (:func:`routine_class`), so importing the registry, listing the routines and
the panel's selector map (and ``cellcal --help``) import none; its class must declare the
name, section and selector of its row. Two routines that claim one name, section or selector
are refused. Everything else asks the registry: the cell file's routine sections
(:func:`sections`, read at cell load by :func:`check_sections`), the panel's selector values
(:func:`panel_selectors`), ``cellcal run``'s list (:func:`available`).
"""
from __future__ import annotations

import importlib
import importlib.util
import inspect
import threading
from dataclasses import dataclass
from typing import Iterable

from cellcal.config.cells import CELL_SECTIONS, Cell, CellFileError
from cellcal.routines.framework import table
from cellcal.routines.framework.base import Routine

SELECTOR_RANGE = (1, 65535)  # a holding register; 0 selects nothing

_listed: dict[str, "_Claim"] | None = None  # the table's rows whose module is installed, checked once
_imported: dict[str, type[Routine]] = {}  # the listed routines asked for so far
_added: dict[str, type[Routine]] = {}  # by register()
_lock = threading.RLock()


class RoutineDeclarationError(ValueError):
    """A routine that declares no name or section, a selector the panel cannot send, a name,
    section or selector another routine has already, or a class that differs from its row
    of the routine table."""


@dataclass(frozen=True)
class _Claim:
    """What one routine claims, and where it is (module.Class)."""

    name: str
    section: str
    selector: int | None
    where: str


def _declared(cls: type[Routine]) -> _Claim:
    return _Claim(cls.name, cls.section, cls.selector, f"{cls.__module__}.{cls.__qualname__}")


def _check(claim: _Claim, known: Iterable[_Claim]) -> None:
    """Refuse `claim` when it is incomplete or clashes with one of `known`."""
    where = claim.where
    if not isinstance(claim.name, str) or not claim.name:
        raise RoutineDeclarationError(f"routine class {where} declares no name")
    if not isinstance(claim.section, str) or not claim.section.isidentifier():
        raise RoutineDeclarationError(f"routine {claim.name!r} ({where}) declares no cell file section "
                                      f"(section = {claim.section!r})")
    if claim.section in CELL_SECTIONS:
        raise RoutineDeclarationError(f"routine {claim.name!r} ({where}) claims section [{claim.section}], one of "
                                      "the cell file's own")
    low, high = SELECTOR_RANGE
    if claim.selector is not None and (isinstance(claim.selector, bool) or not isinstance(claim.selector, int)
                                       or not low <= claim.selector <= high):
        raise RoutineDeclarationError(f"routine {claim.name!r} ({where}) declares panel selector "
                                      f"{claim.selector!r}: a number in {low}..{high}, or None")
    for other in known:
        if other == claim:  # the same routine, known already
            continue
        for what, mine, theirs in (("name", claim.name, other.name), ("section", claim.section, other.section),
                                   ("panel selector", claim.selector, other.selector)):
            if mine is not None and mine == theirs:
                raise RoutineDeclarationError(
                    f"routine {claim.name!r} ({where}) claims {what} {mine!r}, which routine {other.name!r} "
                    f"({other.where}) has already")


def _claims() -> dict[str, _Claim]:
    """Every routine's claim by name, in panel selector order (those without one last, by
    name); the table's rows are checked on the first call, and a row whose module is not
    installed is left out."""
    global _listed
    with _lock:
        if _listed is None:
            listed: dict[str, _Claim] = {}
            for name, row in table.ROUTINES.items():
                if importlib.util.find_spec(row.module) is None:  # a routine that is not installed
                    continue
                claim = _Claim(name, row.section, row.selector, row.where)
                _check(claim, listed.values())
                listed[name] = claim
            _listed = listed
        claims = {**_listed, **{name: _declared(cls) for name, cls in _added.items()}}
        return dict(sorted(claims.items(), key=lambda item: (item[1].selector is None, item[1].selector or 0,
                                                             item[0])))


def _import(name: str) -> type[Routine]:
    """The class of the listed routine `name`, its module imported; RoutineDeclarationError
    when it is not a concrete Routine or declares other than its row."""
    row = table.ROUTINES[name]
    cls = getattr(importlib.import_module(row.module), row.class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Routine)) or inspect.isabstract(cls):
        raise RoutineDeclarationError(f"the routine table lists {row.where} for {name!r}: no concrete Routine "
                                      "class of that name there")
    for what, declared, listed in (("name", cls.name, name), ("section", cls.section, row.section),
                                   ("panel selector", cls.selector, row.selector)):
        if declared != listed:
            raise RoutineDeclarationError(f"routine class {row.where} declares {what} {declared!r}; the routine "
                                          f"table ({table.__name__}) lists {listed!r} for {name!r}")
    return cls


def register(cls: type[Routine]) -> type[Routine]:
    """Add a routine class defined elsewhere (a plug-in, a test); RoutineDeclarationError
    when it clashes with a routine already known. Returns the class (usable as a decorator)."""
    if not (isinstance(cls, type) and issubclass(cls, Routine)) or inspect.isabstract(cls):
        raise RoutineDeclarationError(f"{cls!r} is not a concrete Routine subclass")
    with _lock:
        _check(_declared(cls), _claims().values())
        _added[cls.name] = cls
    return cls


def unregister(name: str) -> None:
    """Forget a routine added with :func:`register` (KeyError when none is of that name)."""
    with _lock:
        del _added[name]


def available() -> list[str]:
    """The routines' names, in panel selector order."""
    return list(_claims())


def routine_class(name: str) -> type[Routine]:
    """The routine's class (a listed routine's module imported on the first ask); KeyError
    for a name no routine has."""
    with _lock:
        claims = _claims()
        if name not in claims:
            raise KeyError(f"no routine named {name!r} (routines: {', '.join(claims)})")
        if name in _added:
            return _added[name]
        if name not in _imported:
            _imported[name] = _import(name)
        return _imported[name]


def sections() -> tuple[str, ...]:
    """The cell file sections the routines own, for :func:`cellcal.config.cell_files.read_cell`."""
    return tuple(claim.section for claim in _claims().values())


def panel_selectors() -> dict[int, str]:
    """The operator panel's routine selector values -> routine names, in selector order."""
    return {claim.selector: name for name, claim in _claims().items() if claim.selector is not None}


def unavailable(name: str, cell: Cell) -> str | None:
    """Why `cell` cannot run the routine `name` at all (a device kind it needs is not among the
    cell's drivers, or its section cannot be read for this cell, e.g. the handshake on a
    one-robot cell), or None when it can."""
    why_not = missing_devices(name, cell)
    if why_not is not None:
        return why_not
    try:
        read_options(name, cell)
    except CellFileError as exc:
        return str(exc)
    return None


def missing_devices(name: str, cell: Cell) -> str | None:
    """Why `cell` cannot run the routine `name`: a device kind it needs is not among the cell's
    drivers; None when it has them all."""
    missing = [k for k in routine_class(name).needs if k not in cell.drivers]
    if missing:
        return f"{cell.path}: routine {name} needs a {' and a '.join(missing)} in [drivers]"
    return None


def runnable(cell: Cell) -> list[str]:
    """The routines `cell` can run, in panel selector order."""
    return [name for name in available() if unavailable(name, cell) is None]


def read_options(name: str, cell: Cell):
    """The routine's options from its section of the cell file; CellFileError naming the key."""
    cls = routine_class(name)
    return cls.read_options(cell.routine_section(cls.section), cell)


def check_sections(cell: Cell) -> None:
    """Read every routine section the cell file has, so a bad option fails at load."""
    by_section = {claim.section: name for name, claim in _claims().items()}
    for section in cell.routines:
        if section not in by_section:
            raise CellFileError("a routine section of no known routine", source=cell.path, section=section)
        read_options(by_section[section], cell)
