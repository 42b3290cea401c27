"""Cell files: which robot, which drivers with which options, the beam, the safety box.

A cell file is the one place that says what hardware a cell has. It is checked
completely when loaded, Klipper style: the first problem stops the load with one
message naming the file, the section and the key (an unknown key, a wrong type, a
value out of range), because a typo in a safety limit must not be silently ignored.
Driver options are checked by the driver itself when :meth:`Cell.build_drivers`
creates it (each driver knows its own options).

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
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from ..drivers import registry
from ..config.reader import read_yaml
from ..config.robot_files import ModelError, load_robot


class CellFileError(ValueError):
    """A cell file that cannot be used, with the file, section and key in the message."""


_SECTIONS = {"cell", "drivers", "beam", "workspace", "limits", "trigger_timing"}
_REQUIRED = ("cell", "drivers", "beam", "workspace", "limits")


def shipped_cells() -> dict[str, Path]:
    """Cell files that ship with cellcal, by stem (``sim``, ``sim-net``)."""
    folder = resources.files("cellcal.config") / "cells"
    return {Path(str(p)).stem: Path(str(p)) for p in folder.iterdir() if str(p).endswith(".yaml")}


class _Section:
    """Typed reads of one mapping that remember which keys were used, so leftovers are unknown keys."""

    def __init__(self, path: str, name: str, mapping):
        self.path, self.name = path, name
        if not isinstance(mapping, dict):
            self.fail(None, f"expected a mapping, got {type(mapping).__name__}")
        self.mapping = mapping
        self.used: set = set()

    def fail(self, key, what: str):
        where = self.name if key is None else f"{self.name}.{key}"
        raise CellFileError(f"{self.path}: [{where}]: {what}")

    def _get(self, key, default, required: bool):
        self.used.add(key)
        if key not in self.mapping:
            if required:
                self.fail(key, "missing (required)")
            return default
        return self.mapping[key]

    def number(self, key, default=None, *, low=-math.inf, high=math.inf, above=None,
               required=False, integer=False) -> float:
        value = self._get(key, default, required)
        kind = "an integer" if integer else "a number"
        if isinstance(value, bool) or not isinstance(value, int if integer else (int, float)) \
                or not math.isfinite(value):
            self.fail(key, f"{value!r} is not {kind}")
        if not low <= value <= high or (above is not None and value <= above):
            rng = f"above {above:g}" if above is not None else f"in {low:g}..{high:g}"
            self.fail(key, f"{value!r} is out of range (must be {rng})")
        return value if integer else float(value)

    def vector(self, key, n: int, default=None, *, required=False, nonzero=False) -> np.ndarray:
        value = self._get(key, default, required)
        if not isinstance(value, (list, tuple)) or len(value) != n or any(
                isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in value):
            self.fail(key, f"{value!r} is not a list of {n} numbers")
        if nonzero and not any(value):
            self.fail(key, "must not be the zero vector")
        return np.array(value, dtype=float)

    def text(self, key, default=None, *, required=False) -> str:
        value = self._get(key, default, required)
        if not isinstance(value, str) or not value:
            self.fail(key, f"{value!r} is not a non-empty text")
        return value

    def flag(self, key, default: bool) -> bool:
        value = self._get(key, default, False)
        if not isinstance(value, bool):
            self.fail(key, f"{value!r} is not true or false")
        return value

    def done(self) -> None:
        unknown = [k for k in self.mapping if k not in self.used]
        if unknown:
            self.fail(unknown[0], f"unknown key (keys of [{self.name}]: {', '.join(sorted(map(str, self.used)))})")


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

    @property
    def simulated_in_process(self) -> bool:
        return any(spec.name == "sim" for spec in self.drivers.values())

    def on_host(self, host: str) -> "Cell":
        """The same cell with every networked driver pointed at another address (parallel test cells)."""
        other = copy.deepcopy(self)
        for spec in other.drivers.values():
            if "host" in spec.options:
                spec.options["host"] = host
        return other

    def world(self):
        """The simulated world of this cell (arm, beam, clock) for the in-process sim drivers."""
        from ..sims.fake_ur_cell import model_from_spec
        from ..sims.sim_world import BeamTiming, SimWorld, SpeedLimits, Workspace
        return SimWorld(load_robot(self.robot), q0=self.home_q_rad, beams=[model_from_spec(self.beam)],
                        workspace=Workspace(self.workspace_min_m, self.workspace_max_m),
                        limits=SpeedLimits(**self.limits), beam_timing=BeamTiming(**self.trigger_timing))

    def build_drivers(self) -> "CellDrivers":
        """Create every device through the registry; in-process sims share one world.

        A device that fails to open closes the ones already opened, so a half-built cell
        holds no connection.
        """
        world = self.world() if self.simulated_in_process else None
        built: dict = {}
        try:
            for kind in registry.KINDS:
                spec = self.drivers.get(kind)
                if spec is None:
                    continue
                options = dict(spec.options)
                if spec.name == "sim":
                    options["world"] = world
                built[kind] = registry.create(kind, spec.name, **options)
        except Exception:
            for device in built.values():
                device.close()
            raise
        return CellDrivers(world=world, **built)


@dataclass
class CellDrivers:
    robot: object = None
    trigger: object = None
    tracker: object = None
    panel: object = None
    world: object = None  # the SimWorld of an in-process simulated cell, else None

    def close(self) -> None:
        """Close every device, even when one fails; the first failure is raised afterwards."""
        errors = []
        for device in (self.trigger, self.tracker, self.panel, self.robot):
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


def _read(path: Path):
    return read_yaml(path, CellFileError)


def resolve_cell(name_or_path: str | Path) -> Path:
    """A path as given, or the name of a shipped cell (``sim``, ``sim-net``)."""
    path = Path(name_or_path)
    if path.exists() or path.suffix in (".yaml", ".yml") or "/" in str(name_or_path):
        return path
    shipped = shipped_cells()
    if str(name_or_path) in shipped:
        return shipped[str(name_or_path)]
    raise CellFileError(f"{name_or_path}: no such file, and not a shipped cell "
                        f"(shipped: {', '.join(sorted(shipped))})")


def load_cell(name_or_path: str | Path) -> Cell:
    """Load and check a cell file; raises CellFileError naming file, section and key."""
    path = resolve_cell(name_or_path)
    where = str(path)
    doc = _read(path)
    top = _Section(where, "top level", doc)
    for section in _REQUIRED:
        if section not in doc:
            top.fail(None, f"section [{section}] is missing")
    for section in doc:
        if section not in _SECTIONS:
            raise CellFileError(f"{where}: [{section}]: unknown section "
                                f"(sections: {', '.join(sorted(_SECTIONS))})")

    s = _Section(where, "cell", doc["cell"])
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

    d = _Section(where, "drivers", doc["drivers"])
    drivers = {}
    for kind in list(d.mapping):
        if kind not in registry.KINDS:
            d.fail(kind, f"unknown device kind (kinds: {', '.join(registry.KINDS)})")
        spec = _Section(where, f"drivers.{kind}", d.mapping[kind])
        driver = spec.text("driver", required=True)
        if driver not in registry.available(kind):
            spec.fail("driver", f"no {kind} driver named {driver!r} "
                                f"(available: {', '.join(registry.available(kind))})")
        drivers[kind] = DriverSpec(driver, {k: v for k, v in spec.mapping.items() if k != "driver"})
    if "robot" not in drivers:
        d.fail("robot", "missing (required)")

    b = _Section(where, "beam", doc["beam"])
    beam = {"kind": "beam", "point_m": b.vector("point_m", 3, required=True).tolist(),
            "direction": b.vector("direction", 3, required=True, nonzero=True).tolist(),
            "radius_m": b.number("radius_m", 0.0005, above=0.0, high=0.05),
            "channel": b.number("channel", 0, low=0, high=17, integer=True),
            "level_when_blocked": b.flag("level_when_blocked", True)}
    b.done()

    w = _Section(where, "workspace", doc["workspace"])
    low, high = w.vector("min_m", 3, required=True), w.vector("max_m", 3, required=True)
    if np.any(low >= high):
        w.fail("max_m", f"{high.tolist()} must be above min_m {low.tolist()} on every axis")
    w.done()

    lim = _Section(where, "limits", doc["limits"])
    limits = {"tcp_speed_m_s": lim.number("tcp_speed_m_s", required=True, above=0.0, high=5.0),
              "tcp_accel_m_s2": lim.number("tcp_accel_m_s2", 2.5, above=0.0, high=50.0),
              "joint_speed_rad_s": lim.number("joint_speed_rad_s", required=True, above=0.0, high=6.3),
              "joint_accel_rad_s2": lim.number("joint_accel_rad_s2", 4.0, above=0.0, high=100.0)}
    lim.done()

    t = _Section(where, "trigger_timing", doc.get("trigger_timing", {}))
    timing = {"latency_s": t.number("latency_s", 0.0, low=0.0, high=1.0),
              "jitter_s": t.number("jitter_s", 0.0, low=0.0, high=0.1)}
    t.done()

    return Cell(where, name, robot, tuple(home_q.tolist()), drivers, beam, low, high, limits, timing)
