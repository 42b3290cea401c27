"""Backends chosen by name from the cell file, as python-can's ``can.Bus(interface=...)``.

Each adapter module registers its factory under (kind, name); the cell file says
e.g. ``robot: {driver: ur_rtde, host: 10.0.0.2}`` and :func:`create` builds it.
Simulated backends register the same way as hardware ones. Modules are imported
lazily, so a cell that does not use CAN never imports python-can.
"""
from __future__ import annotations

import importlib
import inspect
from typing import Callable

KINDS = ("robot", "trigger", "tracker", "panel")

# (kind, name) -> "module:factory", imported on first use
_BUILTIN: dict[tuple[str, str], str] = {
    ("panel", "modbus"): "cellcal.drivers.modbus_panel:ModbusPanel",
    ("trigger", "modbus"): "cellcal.drivers.modbus_trigger:ModbusTrigger",
    ("trigger", "serial"): "cellcal.drivers.serial_trigger:SerialTrigger",
    ("trigger", "can"): "cellcal.drivers.can_trigger:CanTrigger",
    ("tracker", "socket"): "cellcal.drivers.tracker_socket:TrackerSocket",
    ("robot", "ur_rtde"): "cellcal.drivers.ur_rtde_robot:UrRtdeRobot",
    ("trigger", "ur_digital_input"): "cellcal.drivers.ur_rtde_trigger:UrDigitalInputTrigger",
    ("robot", "sim"): "cellcal.sims.sim_devices:SimRobot",
    ("trigger", "sim"): "cellcal.sims.sim_devices:SimTrigger",
    ("tracker", "sim"): "cellcal.sims.sim_devices:SimTracker",
    ("panel", "sim"): "cellcal.sims.sim_devices:SimPanel",
}
_FACTORIES: dict[tuple[str, str], Callable] = {}


class DriverConfigError(ValueError):
    """A cell file names a driver that does not exist or gives it bad options."""


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


def create(kind: str, name: str, **options):
    """Build the driver `name` of `kind` with the cell file's options."""
    key = (kind, name)
    if key not in _FACTORIES:
        if key not in _BUILTIN:
            raise DriverConfigError(f"no {kind} driver named {name!r} (available: {', '.join(available(kind))})")
        module, _, attr = _BUILTIN[key].partition(":")
        _FACTORIES[key] = getattr(importlib.import_module(module), attr)
    factory = _FACTORIES[key]
    try:
        inspect.signature(factory).bind(**options)
    except TypeError as exc:  # an option the driver does not take, or one it needs is missing
        raise DriverConfigError(f"{kind} driver {name!r}: {exc}") from None
    return factory(**options)
