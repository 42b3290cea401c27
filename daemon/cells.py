"""A cell, loaded and opened: the cell file (:mod:`cellcal.config.cells`) checked against
the driver registry, and every device it names built through the registry.

The file's structure is checked where it is read; here each device's driver name and
options are checked by the driver registry, and each routine reads its own section, at
load: a typo in a driver option or a routine option fails at start-up with the file,
the section and the key, like the rest of the cell file.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from cellcal.config.cells import Cell, CellFileError, read_cell, shipped_cells
from cellcal.drivers import registry
from cellcal.drivers.registry import DriverConfigError
from cellcal.routines import registry as routines

__all__ = ["Cell", "CellDrivers", "CellFileError", "load_cell", "open_drivers", "shipped_cells"]


def _placed(exc: DriverConfigError, cell: Cell, kind: str) -> CellFileError:
    return exc.located(cell.path, f"drivers.{kind}", CellFileError)


def load_cell(name_or_path: str | Path) -> Cell:
    """Load and check a cell file, drivers, their options and the routines' sections
    included; raises CellFileError naming file, section and key."""
    cell = read_cell(name_or_path, routines.sections())
    for kind, spec in cell.drivers.items():
        try:
            registry.check(kind, spec.name, spec.options)
        except DriverConfigError as exc:
            raise _placed(exc, cell, kind) from None
    for name, spec in _other_robots(cell).items():
        try:
            registry.check("robot", spec.driver.name, spec.driver.options)
        except DriverConfigError as exc:
            raise exc.located(cell.path, f"robots.{name}.driver", CellFileError) from None
    routines.check_sections(cell)
    return cell


@dataclass
class CellDrivers:
    robot: object = None
    trigger: object = None
    tracker: object = None
    panel: object = None
    world: object = None  # what in-process simulated devices share (their world), else None
    robots: dict = field(default_factory=dict)  # every robot by name; "a" is `robot`

    def close(self) -> None:
        """Close every device, even when one fails; the first failure is raised afterwards."""
        errors = []
        others = [r for name, r in self.robots.items() if r is not self.robot]
        for device in (self.trigger, self.tracker, self.panel, *others, self.robot):
            if device is None:
                continue
            try:
                device.close()
            except Exception as exc:
                errors.append(exc)
        if errors:
            raise errors[0]

    def __enter__(self) -> "CellDrivers":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_drivers(cell: Cell) -> CellDrivers:
    """Create every device of the cell through the registry.

    A device that fails to open closes the ones already opened, so a half-built cell
    holds no connection; a driver that refuses an option is reported in the cell file.
    """
    shared: dict = {}
    built: dict = {}
    others: dict = {}  # robots besides a, by name
    try:
        for kind in registry.KINDS:
            spec = cell.drivers.get(kind)
            if spec is None:
                continue
            try:
                built[kind] = registry.create(kind, spec.name, spec.options, shared=shared, cell=cell)
            except DriverConfigError as exc:
                raise _placed(exc, cell, kind) from None
        for name, spec in _other_robots(cell).items():
            try:
                others[name] = registry.create("robot", spec.driver.name, spec.driver.options, shared=shared,
                                               cell=cell, robot=name)
            except DriverConfigError as exc:
                raise exc.located(cell.path, f"robots.{name}.driver", CellFileError) from None
    except BaseException:
        for device in [*built.values(), *others.values()]:
            device.close()
        raise
    world = next(iter(shared.values()), None)
    return CellDrivers(world=world, robots={"a": built["robot"], **others}, **built)


def _other_robots(cell: Cell) -> dict:
    """The robots of the cell besides robot a (whose driver is ``drivers.robot``)."""
    return {name: spec for name, spec in cell.robots.items() if name != "a"}
