"""What a simulated arm can touch and what its digital inputs see (every sim cell's scene).

Two kinds of model, both judged on the TCP (the controller's tool frame, so a routine
sets the TCP to the tip it is measuring with):

* contact surfaces (``ContactPlane``, ``ContactSphere``) end a ``moveUntilContact``;
* input sources drive bits of ``actual_digital_input_bits``: a ``LightBeam`` is a line in
  space that the tool tip interrupts, a ``ContactSphere`` with a channel is a touch
  trigger (a stylus that closes a contact when touched).

An input source is any callable ``(tcp_pose_m, t_s) -> {channel: level}``, so routines
and tests can plug in their own (a rotating beam, a trigger with latency) through
``--plugin module:factory`` or by adding objects to ``Scene.input_sources``.
Bit numbering is the controller's: standard inputs 0-7, configurable 8-15, tool 16-17.

A sensor judged on the real tool (the cell's truth, :mod:`.truth`) switches late: its
edges are timed where the tool crosses the beam, plus the sensor's latency and jitter.
``SwitchingSensors`` holds such edges until their time, so an input sampled once per
controller cycle sees them then, and logs each with its exact time, as an IO module
with its own clock stamps it.
"""
from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from cellcal.drivers.interfaces import Edge, TriggerEvent


class InputSource(Protocol):
    def __call__(self, tcp_pose: np.ndarray, t_s: float) -> dict[int, bool]:
        ...


def _vector(spec: dict, key: str, n: int = 3) -> np.ndarray:
    value = np.asarray(spec[key], dtype=float)
    if value.shape != (n,) or not np.all(np.isfinite(value)):
        raise ValueError(f"cell model {spec.get('kind')!r}: {key} must be {n} finite numbers, got {spec[key]!r}")
    return value


@dataclass(frozen=True)
class ContactPlane:
    """A flat surface; the side the normal points to is free space."""

    point_m: np.ndarray
    normal: np.ndarray

    def distance_m(self, position: np.ndarray) -> float:
        n = self.normal / np.linalg.norm(self.normal)
        return float((position - self.point_m) @ n)


@dataclass(frozen=True)
class ContactSphere:
    """A ball (a stylus tip, a reference sphere); optionally wired to an input as a touch trigger."""

    centre_m: np.ndarray
    radius_m: float
    channel: int | None = None
    level_when_touched: bool = True

    def distance_m(self, position: np.ndarray) -> float:
        return float(np.linalg.norm(position - self.centre_m) - self.radius_m)

    def __call__(self, tcp_pose: np.ndarray, t_s: float) -> dict[int, bool]:
        if self.channel is None:
            return {}
        touched = self.distance_m(tcp_pose[:3]) <= 0.0
        return {self.channel: touched == self.level_when_touched}


@dataclass(frozen=True)
class LightBeam:
    """A light barrier: the beam is the line through ``point_m`` along ``direction``.

    The TCP blocks it when closer to the line than ``radius_m`` (half the beam width plus
    the radius of the tool tip). ``level_when_blocked`` is the sensor's output polarity
    (dark-on sensors switch on when blocked).
    """

    point_m: np.ndarray
    direction: np.ndarray
    radius_m: float = 0.0005
    channel: int = 0
    level_when_blocked: bool = True

    def distance_m(self, position: np.ndarray) -> float:
        d = self.direction / np.linalg.norm(self.direction)
        off = position - self.point_m
        return float(np.linalg.norm(off - (off @ d) * d))

    def __call__(self, tcp_pose: np.ndarray, t_s: float) -> dict[int, bool]:
        blocked = self.distance_m(tcp_pose[:3]) < self.radius_m
        return {self.channel: blocked == self.level_when_blocked}


@dataclass
class Scene:
    """Contact surfaces and input sources around a simulated arm."""

    contacts: list = field(default_factory=list)
    input_sources: list[Callable] = field(default_factory=list)
    fixed_inputs: int = 0  # bits that are on regardless of the sources (wired high)

    def touching(self, position: np.ndarray) -> bool:
        return any(c.distance_m(position) <= 0.0 for c in self.contacts)

    def input_bits(self, tcp_pose: np.ndarray, t_s: float) -> int:
        bits = self.fixed_inputs
        for source in self.input_sources:
            for channel, level in source(tcp_pose, t_s).items():
                bits = bits | (1 << channel) if level else bits & ~(1 << channel)
        return bits

    def add(self, spec: dict) -> None:
        """Add one model from its JSON form (``{"kind": "beam", ...}``)."""
        model = model_from_spec(spec)
        if isinstance(model, (ContactPlane, ContactSphere)) and spec.get("contact", True):
            self.contacts.append(model)
        if callable(model):
            self.input_sources.append(model)


def model_from_spec(spec: dict):
    """A contact or input model from a JSON mapping; raises ValueError naming the problem."""
    kind = spec.get("kind")
    if kind == "plane":
        return ContactPlane(_vector(spec, "point_m"), _vector(spec, "normal"))
    if kind == "sphere":
        channel = spec.get("channel")
        return ContactSphere(_vector(spec, "centre_m"), float(spec["radius_m"]),
                             None if channel is None else int(channel),
                             bool(spec.get("level_when_touched", True)))
    if kind == "beam":
        return LightBeam(_vector(spec, "point_m"), _vector(spec, "direction"),
                         float(spec.get("radius_m", 0.0005)), int(spec.get("channel", 0)),
                         bool(spec.get("level_when_blocked", True)))
    raise ValueError(f"unknown cell model kind {kind!r} (kinds: plane, sphere, beam)")


def scene_from_spec(spec: dict | None) -> Scene:
    """``{"models": [...], "fixed_inputs": 0}`` -> Scene."""
    scene = Scene(fixed_inputs=int((spec or {}).get("fixed_inputs", 0)))
    for model in (spec or {}).get("models", []):
        scene.add(model)
    return scene


class SwitchingSensors:
    """Sensor outputs that switch at given times (edges with the sensor's latency), read by
    inputs that sample them, and the log of every switch with its exact time."""

    def __init__(self, blocked: dict[int, bool], log_size: int = 1024):
        self.blocked = dict(blocked)  # channel -> the sensor's output says blocked
        self.log: deque[tuple[int, TriggerEvent]] = deque(maxlen=log_size)  # (event number, edge)
        self.count = 0  # edges switched since the start
        self._pending: list[TriggerEvent] = []
        self._last_t_s = -np.inf

    def schedule(self, edges) -> None:
        self._pending.extend(edges)

    def advance(self, t_s: float) -> None:
        """Switch every output whose edge is due by `t_s`, in time order. A device clock does
        not run backwards: an edge whose jitter would put it before one already switched (only
        when the jitter exceeds the latency) is stamped at that one's time."""
        due = sorted((e for e in self._pending if e.t_s <= t_s), key=lambda e: e.t_s)
        if not due:
            return
        self._pending = [e for e in self._pending if e.t_s > t_s]
        for edge in due:
            self.blocked[edge.channel] = edge.edge is Edge.BLOCKED
            self._last_t_s = max(edge.t_s, self._last_t_s)
            self.log.append((self.count, dataclasses.replace(edge, t_s=self._last_t_s)))
            self.count += 1

    def reset(self, blocked: dict[int, bool]) -> None:
        """Outputs as they are now, nothing pending (the arm was put somewhere, not moved)."""
        self.blocked = dict(blocked)
        self._pending = []

    def since(self, first: int) -> list[tuple[int, TriggerEvent]]:
        """Logged edges numbered `first` or later (those still kept)."""
        return [(n, e) for n, e in self.log if n >= first]
