"""A cell, loaded and opened: the cell file (:mod:`cellcal.config.cell_files`) checked against
the driver registry, and every device it names built through the registry.

The file's structure is checked where it is read; here each device's driver name and
options are checked by the driver registry, and each routine reads its own section, at
load: a typo in a driver option or a routine option fails at start-up with the file,
the section and the key, like the rest of the cell file.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from cellcal.config.cell_files import read_cell, shipped_cells
from cellcal.config.cells import Cell, CellFileError
from cellcal.drivers import registry
from cellcal.drivers.interfaces import OperatorPanel, Robot, Tracker, TriggerInput
from cellcal.drivers.registry import DriverConfigError
from cellcal.routines.framework import registry as routines

__all__ = ["Cell", "CellDrivers", "CellFileError", "NoToolMounted", "load_cell", "mounted_tool", "open_drivers",
           "shipped_cells"]


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
    if cell.mounted_source.kind == "panel" and "panel" not in cell.drivers:
        raise CellFileError("`panel`: the mounted tool is to be read from the panel, and this cell has no "
                            "panel (drivers.panel)", source=cell.path, section="mounted")
    return cell


class NoToolMounted(Exception):
    """The mounted-tool source names no tool of the table (or none at all)."""


def mounted_tool(cell: Cell, drivers: "CellDrivers") -> int:
    """The id of the tool on robot a's flange now, from the cell file's source
    (:class:`~cellcal.config.cells.MountedSource`); 0 for a cell that describes no tool.
    Raises DeviceError when the source cannot be read, NoToolMounted when it reads no tool
    or one the table lacks."""
    source = cell.mounted_source
    if source.kind == "file":
        return source.tool
    if source.kind == "panel":
        tool = int(drivers.panel.mounted_tool())
    else:
        bits = int(drivers.robot.digital_inputs())
        tool = sum(1 << i for i, bit in enumerate(source.bits) if bits >> bit & 1)
    if tool == 0:
        raise NoToolMounted(f"no tool is mounted ({source.describe()} reads 0)")
    if tool not in cell.tools:
        have = ", ".join(f"{t.id} {t.name}" for t in cell.tools.values())
        raise NoToolMounted(f"{source.describe()} reads tool {tool}, which this cell file's tool table lacks "
                            f"(its tools: {have})")
    return tool


@dataclass
class CellDrivers:
    """The cell's devices, each behind its interface; None for a device the cell lacks."""

    robot: Robot | None = None
    trigger: TriggerInput | None = None
    tracker: Tracker | None = None
    panel: OperatorPanel | None = None
    world: object | None = None  # what in-process simulated devices share (their world), else None
    robots: dict[str, Robot] = field(default_factory=dict)  # every robot by name; "a" is `robot`

    def device(self, kind: str) -> Robot | TriggerInput | Tracker | OperatorPanel | None:
        """The device of a kind a routine needs (``Routine.needs``: robot, trigger, tracker, panel)."""
        return {"robot": self.robot, "trigger": self.trigger, "tracker": self.tracker, "panel": self.panel}.get(kind)

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
