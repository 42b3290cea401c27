"""What every robot adapter checks of a motion's arguments before anything moves, and how long a
rest-to-rest trapezoidal move takes (for its deadline)."""
from __future__ import annotations

import math

import numpy as np


def vector(value, n: int, what: str, lengths=None) -> np.ndarray:
    """`value` as finite floats, `n` of them (or one of `lengths`); ValueError naming `what` otherwise."""
    v = np.asarray(value, dtype=float).ravel()
    if len(v) not in (lengths or (n,)) or not np.all(np.isfinite(v)):
        raise ValueError(f"{what} must be {n} finite numbers, got {value!r}")
    return v


def limited(value: float, upper: float, what: str) -> float:
    """A motion argument: positive and within the robot's own bound `upper`."""
    value = float(value)
    if not 0.0 < value <= upper:
        raise ValueError(f"{what} must be in (0, {upper}], got {value}")
    return value


def travel_s(length: float, speed: float, accel: float) -> float:
    """Duration of a rest-to-rest trapezoidal move."""
    if length * accel < speed**2:
        return 2.0 * math.sqrt(length / accel)
    return length / speed + speed / accel


def check_robot_options(o) -> None:
    """The options every networked robot adapter takes, on its option reader `o` (``Section.of_options``):
    its address, its deadlines (connecting, a command, the state stream's silence) and how a motion's
    deadline follows its planned time."""
    o.text("host")
    for key in ("connect_timeout_s", "command_timeout_s", "stale_after_s"):
        o.timeout(key)
    o.number("motion_timeout_factor", low=1.0, high=100.0)
    o.number("motion_timeout_margin_s", low=0.0, high=60.0)
