"""The routines by name, as ``cellcal run ROUTINE`` and the operator panel select them.

Each routine class declares itself (:class:`~.base.Routine`): its ``name`` (``tcp-laser``),
the ``section`` of the cell file it owns (``tcp_laser``) and its panel ``selector`` number
(None when the panel cannot select it). The registry finds the classes in the modules of
this package (:func:`routine_modules`: a new routine is a new module here and nothing
else), imported the first time it is asked (so importing the registry, and ``cellcal
--help``, imports no routine), and refuses two that claim one name, section or selector. Everything else asks it: the cell file's routine sections (:func:`sections`,
read at cell load by :func:`check_sections`), the panel's selector values
(:func:`panel_selectors`), ``cellcal run``'s list (:func:`available`).
"""
from __future__ import annotations

import importlib
import inspect
import pkgutil
import threading

from cellcal.config.cells import CELL_SECTIONS, Cell, CellFileError
from cellcal.routines.framework.base import Routine

ROUTINES_PACKAGE = __package__.rpartition(".")[0]  # the routines live one level above the framework
SELECTOR_RANGE = (1, 65535)  # a holding register; 0 selects nothing

_found: dict[str, type[Routine]] | None = None  # name -> class, in the order found
_lock = threading.RLock()


class RoutineDeclarationError(ValueError):
    """A routine class that declares no name or section, a selector the panel cannot send,
    or a name, section or selector another routine has already."""


def _described(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def _check(cls: type[Routine], known: dict[str, type[Routine]]) -> None:
    """Refuse `cls` when its declaration is incomplete or clashes with one of `known`."""
    where = _described(cls)
    if not isinstance(cls.name, str) or not cls.name:
        raise RoutineDeclarationError(f"routine class {where} declares no name")
    if not isinstance(cls.section, str) or not cls.section.isidentifier():
        raise RoutineDeclarationError(f"routine {cls.name!r} ({where}) declares no cell file section "
                                      f"(section = {cls.section!r})")
    if cls.section in CELL_SECTIONS:
        raise RoutineDeclarationError(f"routine {cls.name!r} ({where}) claims section [{cls.section}], one of the "
                                      "cell file's own")
    low, high = SELECTOR_RANGE
    if cls.selector is not None and (isinstance(cls.selector, bool) or not isinstance(cls.selector, int)
                                     or not low <= cls.selector <= high):
        raise RoutineDeclarationError(f"routine {cls.name!r} ({where}) declares panel selector {cls.selector!r}: "
                                      f"a number in {low}..{high}, or None")
    for other in known.values():
        if other is cls:
            continue
        for what, mine, theirs in (("name", cls.name, other.name), ("section", cls.section, other.section),
                                   ("panel selector", cls.selector, other.selector)):
            if mine is not None and mine == theirs:
                raise RoutineDeclarationError(
                    f"routine {cls.name!r} ({where}) claims {what} {mine!r}, which routine {other.name!r} "
                    f"({_described(other)}) has already")


def _in_module(module) -> list[type[Routine]]:
    """The concrete Routine subclasses a module defines (not those it imports)."""
    return [obj for obj in vars(module).values()
            if isinstance(obj, type) and issubclass(obj, Routine) and obj.__module__ == module.__name__
            and not inspect.isabstract(obj)]


def routine_modules() -> tuple[str, ...]:
    """Every module of the routines package (the framework is a sub-package of its own)."""
    package = importlib.import_module(ROUTINES_PACKAGE)
    return tuple(f"{ROUTINES_PACKAGE}.{m.name}" for m in sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name)
                 if not m.ispkg)


def _routines() -> dict[str, type[Routine]]:
    """Every routine by name, in panel selector order (those without one last, by name); the
    package's modules are imported on the first call."""
    global _found
    with _lock:
        if _found is None:
            found: dict[str, type[Routine]] = {}
            for module_name in routine_modules():
                try:
                    module = importlib.import_module(module_name)
                except ModuleNotFoundError:  # a routine that is not installed
                    continue
                for cls in _in_module(module):
                    _check(cls, found)
                    found[cls.name] = cls
            order = sorted(found.values(), key=lambda c: (c.selector is None, c.selector or 0, c.name))
            _found = {cls.name: cls for cls in order}
        return _found


def register(cls: type[Routine]) -> type[Routine]:
    """Add a routine class defined elsewhere (a plug-in, a test); RoutineDeclarationError
    when it clashes with a routine already known. Returns the class (usable as a decorator)."""
    if not (isinstance(cls, type) and issubclass(cls, Routine)) or inspect.isabstract(cls):
        raise RoutineDeclarationError(f"{cls!r} is not a concrete Routine subclass")
    with _lock:
        known = _routines()
        _check(cls, known)
        known[cls.name] = cls
    return cls


def unregister(name: str) -> None:
    """Forget a routine added with :func:`register` (KeyError when none is of that name)."""
    with _lock:
        del _routines()[name]


def available() -> list[str]:
    """The routines' names, in panel selector order."""
    return list(_routines())


def routine_class(name: str) -> type[Routine]:
    routines = _routines()
    if name not in routines:
        raise KeyError(f"no routine named {name!r} (routines: {', '.join(routines)})")
    return routines[name]


def sections() -> tuple[str, ...]:
    """The cell file sections the routines own, for :func:`cellcal.config.cells.read_cell`."""
    return tuple(cls.section for cls in _routines().values())


def panel_selectors() -> dict[int, str]:
    """The operator panel's routine selector values -> routine names, in selector order."""
    return {cls.selector: name for name, cls in sorted(_routines().items(), key=lambda item: item[1].selector or 0)
            if cls.selector is not None}


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
    by_section = {cls.section: name for name, cls in _routines().items()}
    for section in cell.routines:
        if section not in by_section:
            raise CellFileError("a routine section of no known routine", source=cell.path, section=section)
        read_options(by_section[section], cell)
