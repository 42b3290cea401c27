"""Backends chosen by name from the cell file, as python-can's ``can.Bus(interface=...)``.

Each adapter module registers its factory under (kind, name); the cell file says
e.g. ``robot: {driver: ur_rtde, host: 10.0.0.2}`` and :func:`create` builds it.
Simulated backends register the same way as hardware ones. Modules are imported
lazily, so a cell that does not use CAN never imports python-can.

A family of backends that must share one object per cell (the in-process simulated
devices share one simulated world) registers a *shared* factory under its name: it is
called once per cell with the cell description, and its result is passed to every
device of that family as the option ``world``. The cell loader needs to know nothing
about what a backend family shares.
"""
from __future__ import annotations

import importlib
import inspect
from typing import Callable

from cellcal.config.cells import DEVICE_KINDS
from cellcal.config.reader import ConfigError

KINDS = DEVICE_KINDS

# (kind, name) -> "module:factory", imported on first use
_BUILTIN: dict[tuple[str, str], str] = {
    ("panel", "modbus"): "cellcal.drivers.modbus.panel:ModbusPanel",
    ("trigger", "modbus"): "cellcal.drivers.modbus.trigger:ModbusTrigger",
    ("trigger", "serial"): "cellcal.drivers.triggers.serial_line:SerialTrigger",
    ("trigger", "can"): "cellcal.drivers.triggers.can_bus:CanTrigger",
    ("tracker", "socket"): "cellcal.drivers.tracker_socket:TrackerSocket",
    ("robot", "ur_rtde"): "cellcal.drivers.ur.robot:UrRtdeRobot",
    ("robot", "franka"): "cellcal.drivers.franka.robot:FrankaRobot",
    ("trigger", "ur_digital_input"): "cellcal.drivers.ur.trigger:UrDigitalInputTrigger",
    ("robot", "sim"): "cellcal.sims.inproc.devices:SimRobot",
    ("trigger", "sim"): "cellcal.sims.inproc.devices:SimTrigger",
    ("tracker", "sim"): "cellcal.sims.inproc.devices:SimTracker",
    ("panel", "sim"): "cellcal.sims.inproc.devices:SimPanel",
}
_FACTORIES: dict[tuple[str, str], Callable] = {}
# backend name -> "module:callable"(cell) building the one object its devices share
_SHARED: dict[str, str] = {
    "sim": "cellcal.sims.inproc.world:world_of_cell",
}


class DriverConfigError(ConfigError):
    """A driver that does not exist, or options it cannot take; names the option."""


def register(kind: str, name: str, target: str | Callable) -> None:
    """Register a factory (a callable, or "package.module:callable" imported lazily)."""
    if kind not in KINDS:
        raise ValueError(f"unknown driver kind {kind!r} (kinds: {', '.join(KINDS)})")
    if isinstance(target, str):
        _BUILTIN[(kind, name)] = target
    else:
        _FACTORIES[(kind, name)] = target


def available(kind: str) -> list[str]:
    return sorted({n for k, n in (*_BUILTIN, *_FACTORIES) if k == kind})


def _load(target: str) -> Callable:
    module, _, attr = target.partition(":")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def factory(kind: str, name: str) -> Callable:
    key = (kind, name)
    if key not in _FACTORIES:
        if key not in _BUILTIN:
            raise DriverConfigError(f"no {kind} driver named {name!r} (available: {', '.join(available(kind))})",
                                    key="driver")
        _FACTORIES[key] = _load(_BUILTIN[key])
    return _FACTORIES[key]


def check(kind: str, name: str, options: dict) -> None:
    """Refuse an option the driver does not take, or a required one left out, naming it."""
    parameters = inspect.signature(factory(kind, name)).parameters
    named = {p: v for p, v in parameters.items()
             if v.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)}
    if name in _SHARED:
        named.pop("world", None)  # comes from the cell, not from the file
    for option in options:
        if option not in named:
            raise DriverConfigError(f"unknown option (options of the {name} {kind} driver: "
                                    f"{', '.join(sorted(named)) or 'none'})", key=option)
    for option, p in named.items():
        if p.default is inspect.Parameter.empty and option not in options:
            raise DriverConfigError(f"missing (required by the {name} {kind} driver)", key=option)
    check_values = getattr(factory(kind, name), "check_options", None)
    if check_values is not None:  # the driver's own range checks, without opening anything
        check_values(**{p: options.get(p, v.default) for p, v in named.items()})


# the hidden truth of a simulated cell, for scoring a simulated run's report (never its solving)
_SIM_TRUTH = "cellcal.sims.physics.truth:truth_of_cell"


def simulated_truth(cell, model):
    """The hidden truth of a cell whose file has a ``sim_truth`` section, else None."""
    return _load(_SIM_TRUTH)(cell, model) if getattr(cell, "sim_truth", None) is not None else None


def shared_context(name: str, cell):
    """The object every device of backend family `name` shares in `cell`, or None."""
    return _load(_SHARED[name])(cell) if name in _SHARED else None


def create(kind: str, name: str, options: dict | None = None, *, shared: dict | None = None, cell=None,
           robot: str | None = None):
    """Build the driver `name` of `kind` with the cell file's options.

    `shared` (a dict kept by the caller for one cell) holds the objects of backend
    families that share one per cell (see the module docstring), built from `cell`.
    `robot` names which robot of a two-robot cell the device is; a shared object that
    holds one per robot gives it through ``of_robot(robot)``.
    """
    options = dict(options or {})
    check(kind, name, options)
    if name in _SHARED:
        if shared is None:
            shared = {}
        if name not in shared:
            shared[name] = shared_context(name, cell)
        options["world"] = shared[name] if robot in (None, "a") else shared[name].of_robot(robot)
    return factory(kind, name)(**options)
