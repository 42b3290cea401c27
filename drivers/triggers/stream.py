"""What every device-timestamped trigger transport has in common.

A light barrier or touch probe with its own clock sends *records*: a sequence
number, the input channel, the edge and the device time in microseconds as an
unsigned 32-bit counter. Modbus, the serial line and CAN carry the same record in
different framing, so the checks that make a sweep trustworthy live here once:

* the sequence number must advance by exactly one (modulo its width), otherwise
  events were lost or repeated on the way;
* the device time must not go backwards; it wraps every 2**32 us (71.6 min), so
  steps are taken modulo 2**32 and a "step" of 2**31 us or more is read as going
  backwards (serial-number arithmetic, RFC 1982).

A fault raises :class:`ProtocolError` naming the device (a lost line or
connection, :class:`DeviceError`). The record that revealed it is dropped and
the stream restarts: the next good record is taken as the first one (new
sequence and time reference). A sweep that saw a fault is compromised either
way; restarting gives one error per fault, not one more for the gap a corrupt
sentence leaves, and keeps a rebooted device from failing every later record.
Events accepted before the fault are not lost: the next ``events()`` returns them.
"""
from __future__ import annotations

import abc
import time
from dataclasses import dataclass
from typing import Iterator

from cellcal.drivers.interfaces import DeviceError, Edge, ProtocolError, TriggerEvent, TriggerInput

DEVICE_CLOCK_MODULUS = 2**32  # device time in us, unsigned 32-bit

MAX_EVENTS_PER_CALL = 4096  # the rest stays with the transport for the next call

EDGE_CODES = {Edge.BLOCKED: 1, Edge.CLEARED: 2}  # numeric edge code on binary transports
EDGES_BY_CODE = {code: edge for edge, code in EDGE_CODES.items()}


@dataclass(frozen=True)
class TriggerRecord:
    """One edge as the device reported it, before sequence and clock checks."""

    seq: int
    channel: int
    edge: Edge
    t_us: int  # device clock, wraps at 2**32


class TriggerSequencer:
    """Checks sequence continuity and clock order, and unwraps the device clock.

    ``seq_modulus`` is the width of the transport's sequence field (256 for one
    byte on CAN, 65536 for a Modbus register or the serial line's counter).
    """

    def __init__(self, device: str, seq_modulus: int):
        self.device = device
        self.seq_modulus = seq_modulus
        self.restart()

    def restart(self) -> None:
        """Forget the reference; the next record starts a new stream."""
        self._last_seq: int | None = None
        self._last_t_us: int | None = None
        self._unwrapped_us = 0

    def accept(self, record: TriggerRecord) -> TriggerEvent:
        if self._last_seq is not None:
            expected = (self._last_seq + 1) % self.seq_modulus
            if record.seq != expected:
                lost = (record.seq - expected) % self.seq_modulus
                self.restart()
                if lost == self.seq_modulus - 1:
                    raise ProtocolError(self.device, f"event {record.seq} repeated")
                raise ProtocolError(
                    self.device,
                    f"sequence gap: expected event {expected}, got {record.seq} "
                    f"({lost} event(s) lost)")
            step_us = (record.t_us - self._last_t_us) % DEVICE_CLOCK_MODULUS
            if step_us >= DEVICE_CLOCK_MODULUS // 2:
                previous = self._last_t_us
                self.restart()
                raise ProtocolError(
                    self.device,
                    f"timestamp out of order: event {record.seq} at {record.t_us} us "
                    f"after {previous} us (channel {record.channel})")
            self._unwrapped_us += step_us
        else:
            self._unwrapped_us = record.t_us
        self._last_seq = record.seq
        self._last_t_us = record.t_us
        return TriggerEvent(t_s=self._unwrapped_us * 1e-6, channel=record.channel,
                            edge=record.edge, device_time=True)


class RecordTrigger(TriggerInput):
    """A trigger whose transport delivers :class:`TriggerRecord` s.

    Subclasses implement :meth:`_records`; this class owns the sequence checks
    and keeps events accepted before a fault for the next call.
    """

    def __init__(self, device: str, seq_modulus: int):
        self.device = device
        self._sequencer = TriggerSequencer(device, seq_modulus)
        self._pending: list[TriggerEvent] = []

    @abc.abstractmethod
    def _records(self, wait_until: float) -> Iterator[TriggerRecord]:
        """Records as they arrive: wait until ``wait_until`` (time.monotonic) for
        the first, then yield only what is already there. Consume lazily, so
        whatever is not yet yielded stays with the transport when a fault stops
        the iteration."""

    def events(self, timeout_s: float = 0.0) -> list[TriggerEvent]:
        if timeout_s < 0:
            raise ValueError(f"timeout_s must be >= 0, got {timeout_s}")
        events, self._pending = self._pending, []
        # do not wait when there is already something to hand over
        wait_until = time.monotonic() + (0.0 if events else timeout_s)
        try:
            for record in self._records(wait_until):
                events.append(self._sequencer.accept(record))
                if len(events) >= MAX_EVENTS_PER_CALL:
                    break  # a device that never pauses must not keep the caller here
        except DeviceError:
            self._sequencer.restart()
            self._pending = events
            raise
        return events
