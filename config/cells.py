"""Cell files: which robot, which drivers with which options, the beam, the safety box.

A cell file is the one place that says what hardware a cell has. It is checked
completely when read (:mod:`.reader`): the first problem stops the load with one
message naming the file, the section and the key (an unknown key, a wrong type, a
value out of range), because a typo in a safety limit must not be silently ignored.

Sections::

    cell:       name, robot (model file or shipped name), home_q_rad
    drivers:    robot, trigger, tracker, panel: {driver: NAME, ...options}
    beam:       point_m, direction, radius_m, channel, level_when_blocked
    workspace:  min_m, max_m (the TCP's box, base frame)
    limits:     tcp_speed_m_s, tcp_accel_m_s2, joint_speed_rad_s, joint_accel_rad_s2
    trigger_timing: latency_s, jitter_s (the simulated sensor; ignored by real ones)
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .reader import ConfigError, Section, read_yaml, resolve, shipped
from .robot_files import ModelError, load_robot

DEVICE_KINDS = ("robot", "trigger", "tracker", "panel")
_SECTIONS = {"cell", "drivers", "beam", "workspace", "limits", "trigger_timing"}
_REQUIRED = ("cell", "drivers", "beam", "workspace", "limits")


class CellFileError(ConfigError):
    """A cell file that cannot be used, with the file, section and key in the message."""


def shipped_cells() -> dict[str, Path]:
    """Cell files that ship with cellcal, by stem (``sim``, ``sim-net``)."""
    return shipped("cells")


def resolve_cell(name_or_path: str | Path) -> Path:
    """A path as given, or the name of a shipped cell (``sim``, ``sim-net``)."""
    return resolve(name_or_path, "cells", "cell", CellFileError)


@dataclass(frozen=True)
class DriverSpec:
    """One device of the cell: a registered driver name and the options it is built with."""

    name: str
    options: dict = field(default_factory=dict)


@dataclass
class Cell:
    """A validated cell file."""

    path: str
    name: str
    robot: str
    home_q_rad: tuple
    drivers: dict  # kind -> DriverSpec
    beam: dict  # the beam in the fake UR controller's model form ({"kind": "beam", ...})
    workspace_min_m: np.ndarray
    workspace_max_m: np.ndarray
    limits: dict
    trigger_timing: dict

    def on_host(self, host: str) -> "Cell":
        """The same cell with every networked driver pointed at another address (parallel test cells)."""
        other = copy.deepcopy(self)
        for spec in other.drivers.values():
            if "host" in spec.options:
                spec.options["host"] = host
        return other


def read_cell(name_or_path: str | Path) -> Cell:
    """Read and check a cell file's structure; raises CellFileError naming file, section and key.

    Which drivers exist and which options they take is the driver registry's to say
    (``cellcal.daemon.cells.load_cell`` checks both at load).
    """
    path = resolve_cell(name_or_path)
    where = str(path)
    doc = read_yaml(path, CellFileError)
    top = Section(where, None, doc, CellFileError)
    for section in _REQUIRED:
        if section not in doc:
            top.fail(None, f"section [{section}] is missing")
    for section in doc:
        if section not in _SECTIONS:
            top.fail(section, f"unknown section (sections: {', '.join(sorted(_SECTIONS))})")

    s = top.section("cell")
    name = s.text("name", path.stem)
    robot = s.text("robot", required=True)
    if "/" in robot or robot.endswith((".yaml", ".yml")):  # a model file next to the cell file
        robot = str(path.parent / robot)
    try:
        model = load_robot(robot)
    except ModelError as exc:
        s.fail("robot", str(exc))
    home_q = s.vector("home_q_rad", model.n_joints, required=True)
    if model.joint_limits is not None:
        for i, (v, (lo, hi)) in enumerate(zip(home_q, model.joint_limits)):
            if not lo <= v <= hi:
                s.fail("home_q_rad", f"joint {i} at {v:g} rad is outside its limits {lo:g}..{hi:g}")
    s.done()

    d = top.section("drivers")
    drivers = {}
    for kind in list(d.mapping):
        if kind not in DEVICE_KINDS:
            d.fail(kind, f"unknown device kind (kinds: {', '.join(DEVICE_KINDS)})")
        spec = d.section(kind)
        driver = spec.text("driver", required=True)
        drivers[kind] = DriverSpec(driver, {k: v for k, v in spec.mapping.items() if k != "driver"})
    if "robot" not in drivers:
        d.fail("robot", "missing (required)")

    b = top.section("beam")
    beam = {"kind": "beam", "point_m": b.vector("point_m", 3, required=True).tolist(),
            "direction": b.vector("direction", 3, required=True, nonzero=True).tolist(),
            "radius_m": b.number("radius_m", 0.0005, above=0.0, high=0.05),
            "channel": b.number("channel", 0, low=0, high=17, integer=True),
            "level_when_blocked": b.flag("level_when_blocked", True)}
    b.done()

    w = top.section("workspace")
    low, high = w.vector("min_m", 3, required=True), w.vector("max_m", 3, required=True)
    if np.any(low >= high):
        w.fail("max_m", f"{high.tolist()} must be above min_m {low.tolist()} on every axis")
    w.done()

    lim = top.section("limits")
    limits = {"tcp_speed_m_s": lim.number("tcp_speed_m_s", required=True, above=0.0, high=5.0),
              "tcp_accel_m_s2": lim.number("tcp_accel_m_s2", 2.5, above=0.0, high=50.0),
              "joint_speed_rad_s": lim.number("joint_speed_rad_s", required=True, above=0.0, high=6.3),
              "joint_accel_rad_s2": lim.number("joint_accel_rad_s2", 4.0, above=0.0, high=100.0)}
    lim.done()

    t = top.section("trigger_timing")
    timing = {"latency_s": t.number("latency_s", 0.0, low=0.0, high=1.0),
              "jitter_s": t.number("jitter_s", 0.0, low=0.0, high=0.1)}
    t.done()

    return Cell(where, name, robot, tuple(home_q.tolist()), drivers, beam, low, high, limits, timing)
