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
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np


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
