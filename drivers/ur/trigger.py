"""A light barrier or touch trigger wired to the UR controller's own digital inputs.

The controller samples its inputs every cycle and reports them in the RTDE stream
(``actual_digital_input_bits`` with the cycle's ``timestamp``), so an edge is timed on
the controller's clock: the same clock as the joint positions it will be matched with,
to one cycle (2 ms on e-Series) and without network jitter. The stream is read without
losing packages (:mod:`.state`), so edges are found between consecutive
controller cycles; the event time is that of the first cycle showing the new level.

Bits are the controller's: standard inputs 0-7, configurable inputs 8-15, tool inputs
16-17. ``level_when_blocked`` is the sensor's polarity (True: the input goes high when
the beam is interrupted or the contact closes).

Register in the driver registry::

    register("trigger", "ur_digital_input", "cellcal.drivers.ur.trigger:UrDigitalInputTrigger")
"""
from __future__ import annotations

import threading
import time

from cellcal.drivers.interfaces import DeviceError, Edge, RobotSample, TriggerEvent, TriggerInput
from cellcal.drivers.ur.state import INPUT_VARIABLES, UrStateStream

MAX_CHANNEL = 17


class UrDigitalInputTrigger(TriggerInput):
    def __init__(self, host: str | None = None, *, channels=(0,), level_when_blocked: bool = True,
                 frequency_hz: float = -1.0, connect_timeout_s: float = 5.0, stale_after_s: float = 0.5,
                 stream: UrStateStream | None = None):
        """Open its own RTDE stream to ``host``, or share a robot's (``UrRtdeRobot.state_stream``)."""
        channels = tuple(int(c) for c in channels)
        if not channels or any(not 0 <= c <= MAX_CHANNEL for c in channels):
            raise ValueError(f"channels must be controller input bits 0..{MAX_CHANNEL}, got {channels!r}")
        if (host is None) == (stream is None):
            raise ValueError("give either host (own connection) or stream (a robot's), not both")
        self.channels = channels
        self.level_when_blocked = bool(level_when_blocked)
        self.name = f"digital inputs {list(channels)} of UR controller at {host or stream.host}"
        self._own_stream = stream is None
        self._stream = stream or UrStateStream(host, device=self.name, variables=INPUT_VARIABLES,
                                               frequency_hz=frequency_hz, connect_timeout_s=connect_timeout_s,
                                               stale_after_s=stale_after_s)
        self._cond = threading.Condition()
        self._events: list[TriggerEvent] = []
        self._last_bits: int | None = None
        self._closed = False
        self._stream.add_listener(self._on_sample)

    def _on_sample(self, sample: RobotSample) -> None:
        if self._closed:
            return
        bits, last = sample.digital_inputs, self._last_bits
        self._last_bits = bits
        if last is None or bits == last:
            return
        new = []
        for channel in self.channels:
            mask = 1 << channel
            if (bits ^ last) & mask:
                blocked = bool(bits & mask) == self.level_when_blocked
                new.append(TriggerEvent(sample.t_s, channel, Edge.BLOCKED if blocked else Edge.CLEARED, True))
        if new:
            with self._cond:
                self._events.extend(new)
                self._cond.notify_all()

    def events(self, timeout_s: float = 0.0) -> list[TriggerEvent]:
        """Edges since the last call, waiting up to timeout_s for the first; raises if the stream ended."""
        deadline = time.monotonic() + max(timeout_s, 0.0)
        with self._cond:
            while not self._events:
                left = deadline - time.monotonic()
                if left <= 0 or self._closed:
                    break
                self._cond.wait(min(left, 0.05))
                if self._stream.failure() is not None:
                    break
            events, self._events = self._events, []
        if not events:
            what = self._stream.failure()
            if what is not None:
                raise DeviceError(self.name, what)
        return events

    def levels(self) -> dict[int, bool]:
        """Current level of each channel (True = blocked)."""
        bits = self._stream.latest().digital_inputs
        return {c: bool(bits & (1 << c)) == self.level_when_blocked for c in self.channels}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with self._cond:
            self._cond.notify_all()
        if self._own_stream:
            self._stream.close()
