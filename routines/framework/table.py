"""Every routine cellcal ships, in one table: its name (``cellcal run NAME``, the store's), the
module and class that implement it, the section of the cell file it owns and its operator
panel selector value.

The selector values are a wire contract (docs/panel.md, "Routine selector"): a PLC sends them,
so a number here never changes meaning. None: the panel cannot select the routine. The
registry (:mod:`.registry`) reads this table, imports a routine's module only when that
routine is asked for, and refuses a class whose own ``name``, ``section`` or ``selector``
differs from its row. A new routine is a row here and its module.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Listed:
    """One routine of the table (its name is the row's key)."""

    module: str  # imported the first time the routine is asked for
    class_name: str
    section: str  # of the cell file
    selector: int | None  # the panel's routine selector value

    @property
    def where(self) -> str:
        return f"{self.module}.{self.class_name}"


ROUTINES: dict[str, Listed] = {
    # name               module                                  class               section              selector
    "tcp-laser":         Listed("cellcal.routines.tcp_laser",          "TcpLaser",         "tcp_laser",         1),
    "tcp-stylus":        Listed("cellcal.routines.tcp_stylus",         "TcpStylus",        "tcp_stylus",        2),
    "tcp-npoint":        Listed("cellcal.routines.tcp_npoint",         "TcpNpoint",        "tcp_npoint",        3),
    "handshake":         Listed("cellcal.routines.handshake",          "Handshake",        "handshake",         4),
    "tracker":           Listed("cellcal.routines.tracker",            "TrackerCampaign",  "tracker",           5),
    "tcf":               Listed("cellcal.routines.tcf",                "Tcf",              "tcf",               6),
    "tcp-check":         Listed("cellcal.routines.tcp_check",          "TcpCheck",         "tcp_check",         7),
    "kinematic-fixture": Listed("cellcal.routines.kinematic_fixture",  "KinematicFixture", "kinematic_fixture", 8),
}
