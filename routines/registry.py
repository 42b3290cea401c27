"""The routines by name, as ``cellcal run ROUTINE`` and the operator panel select them.

Each entry is "module:class" imported on first use, like the driver registry. A cell
file section named after a routine (``tcp-laser`` -> ``tcp_laser``) is that routine's,
and is read by it when the cell is loaded (:func:`check_sections`).
"""
from __future__ import annotations

import importlib

from cellcal.config.cells import Cell, CellFileError
from cellcal.routines.base import Routine

ROUTINES: dict[str, str] = {
    "tcp-laser": "cellcal.routines.tcp_laser:TcpLaser",
    "tcp-stylus": "cellcal.routines.tcp_stylus:TcpStylus",
    "tcp-npoint": "cellcal.routines.tcp_npoint:TcpNpoint",
    "tcf": "cellcal.routines.tcf:Tcf",
    "tracker": "cellcal.routines.tracker:TrackerCampaign",
    "handshake": "cellcal.routines.handshake:Handshake",
}


def available() -> list[str]:
    """Routines whose module is installed."""
    out = []
    for name, target in ROUTINES.items():
        try:
            importlib.import_module(target.partition(":")[0])
        except ModuleNotFoundError:
            continue
        out.append(name)
    return out


def routine_class(name: str) -> type[Routine]:
    if name not in ROUTINES:
        raise KeyError(f"no routine named {name!r} (routines: {', '.join(available())})")
    module, _, attr = ROUTINES[name].partition(":")
    return getattr(importlib.import_module(module), attr)


def read_options(name: str, cell: Cell):
    """The routine's options from its section of the cell file; CellFileError naming the key."""
    cls = routine_class(name)
    return cls.read_options(cell.routine_section(cls.section), cell)


def check_sections(cell: Cell) -> None:
    """Read every routine section the cell file has, so a bad option fails at load."""
    for section in cell.routines:
        name = section.replace("_", "-")
        if name in ROUTINES and name in available():
            read_options(name, cell)
        elif name not in ROUTINES:
            raise CellFileError("a routine section of no known routine", source=cell.path, section=section)
