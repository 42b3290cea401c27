"""Simulated time: every fake of one cell reports one clock that runs `time_scale` times
faster than the wall (1: real time, as the demo runs). The wall only paces it: a fake
sleeps `wall_s(sim_s)` for a stretch of simulated time and reports `now()`, never the
wall clock itself, so what it reports is the same at every scale."""
from __future__ import annotations

import threading
import time
from typing import Callable

MAX_TIME_SCALE = 50.0  # beyond it a 500 Hz cycle in Python cannot keep up on any machine


def checked_time_scale(value) -> float:
    """`value` as a time scale, or ValueError saying what is allowed."""
    try:
        scale = float(value)
    except (TypeError, ValueError):
        scale = float("nan")
    if not 0.0 < scale <= MAX_TIME_SCALE:  # also refuses nan
        raise ValueError(f"time scale {value!r}: a number with 0 < K <= {MAX_TIME_SCALE:g} "
                         "(simulated seconds per wall second; 1: real time)")
    return scale


class SimClock:
    """A cell's simulated clock: `now()` from `source` (the fake controller's cycle clock) or,
    standing alone, the wall since the clock was made, scaled; waits paced in wall time."""

    def __init__(self, time_scale: float = 1.0, source: Callable[[], float] | None = None):
        self.time_scale = checked_time_scale(time_scale)
        self._source = source
        self._t0 = time.monotonic()

    def now(self) -> float:
        """Simulated seconds."""
        if self._source is not None:
            return float(self._source())
        return (time.monotonic() - self._t0) * self.time_scale

    def wall_s(self, sim_s: float) -> float:
        """The wall time a stretch of simulated time takes."""
        return sim_s / self.time_scale

    def sleep(self, sim_s: float) -> None:
        time.sleep(self.wall_s(sim_s))

    def wait(self, event: threading.Event, sim_s: float) -> bool:
        """`event.wait` for a stretch of simulated time; True once it is set."""
        return event.wait(self.wall_s(sim_s))
