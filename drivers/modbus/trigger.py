"""Light barrier / touch trigger events from a Modbus TCP IO module, through pymodbus.

Modbus has no push: the module timestamps each edge with its own microsecond
clock and keeps the last N edges in a ring of input registers; the client polls
an event counter and reads the records it has not seen. Polling latency then
does not matter, because the time of an edge is the device's, not the arrival's.

Register layout (input registers, function code 4; ``B`` = ``base_register``,
default 100; all values unsigned 16-bit):

=================  ==============  ==============================================
address            name            meaning
=================  ==============  ==============================================
B + 0              event_counter   edges recorded since power-up, modulo 65536
B + 1              ring_size       N, records in the ring; a power of two <= 4096
B + 2              layout_version  1 for this layout
B + 3              reserved        0
B + 4 + 4k + 0     seq             event number of the record in slot k (mod 65536)
B + 4 + 4k + 1     channel_edge    channel << 8 | edge (edge: 1 blocked, 2 cleared)
B + 4 + 4k + 2     t_us_high       device time in us, bits 31..16
B + 4 + 4k + 3     t_us_low        device time in us, bits 15..0
=================  ==============  ==============================================

Event number i (counted from 0 at power-up, modulo 65536) is stored in slot
i mod N, and the device writes the record before it increments the counter. N
divides 65536, so slots stay in step across the counter's wrap. The ``seq`` word
lets the client see a slot that was overwritten between reading the counter and
reading the record.

Faults (each a :class:`ProtocolError` naming the device): the counter advanced
by more than N since the last poll (events missed: poll faster or use a larger
ring); a slot holds another event than expected (ring overrun while reading); an
unknown edge code; the device time going backwards; a header that is not this
layout. Edges recorded before the adapter connected are history and are skipped.
"""
from __future__ import annotations

import time
from typing import Iterator

from cellcal.drivers.interfaces import ProtocolError
from cellcal.config.reader import Section
from cellcal.drivers.modbus.panel import ModbusLink
from cellcal.drivers.registry import DriverConfigError
from cellcal.drivers.triggers.stream import EDGES_BY_CODE, RecordTrigger, TriggerRecord

LAYOUT_VERSION = 1
HEADER_REGISTERS = 4
RECORD_REGISTERS = 4
MAX_RING_SIZE = 4096
SEQ_MODULUS = 65536
MAX_RECORDS_PER_READ = 31  # 124 registers; a Modbus read returns at most 125


def encode_record(seq: int, channel: int, edge_code: int, t_us: int) -> list[int]:
    """The four registers of one ring slot (used by the simulated IO module)."""
    return [seq % SEQ_MODULUS, (channel & 0xFF) << 8 | (edge_code & 0xFF),
            (t_us >> 16) & 0xFFFF, t_us & 0xFFFF]


class ModbusTrigger(RecordTrigger):
    """Device-timestamped trigger events polled from a Modbus TCP IO module."""

    @staticmethod
    def check_options(**options) -> None:
        """Refuse an option out of range, naming it (also run by the registry at cell load)."""
        o = Section.of_options(DriverConfigError, **options)
        o.port()
        o.integer("unit_id", low=0, high=255)
        o.integer("base_register", low=0, high=0xFFFF - HEADER_REGISTERS)
        o.timeout("timeout_s")
        o.timeout("poll_interval_s", high=1.0)

    def __init__(self, host: str = "127.0.0.1", port: int = 502, *, unit_id: int = 1,
                 base_register: int = 100, timeout_s: float = 1.0,
                 poll_interval_s: float = 0.005, name: str = "trigger"):
        self.check_options(port=port, unit_id=unit_id, base_register=base_register, timeout_s=timeout_s,
                           poll_interval_s=poll_interval_s)
        self.name = name
        super().__init__(f"{name} (Modbus TCP {host}:{port}, unit {unit_id})", SEQ_MODULUS)
        self.base_register = base_register
        self.poll_interval_s = poll_interval_s
        self._link = ModbusLink(self.device, host, port, unit_id, timeout_s)
        self._link.connect()
        counter, ring_size, version, _ = self._link.read_input_registers(
            base_register, HEADER_REGISTERS)
        if version != LAYOUT_VERSION:
            raise ProtocolError(self.device, f"trigger layout version {version} at input "
                                             f"register {base_register + 2}, expected "
                                             f"{LAYOUT_VERSION}")
        if not 1 <= ring_size <= MAX_RING_SIZE or ring_size & (ring_size - 1):
            raise ProtocolError(self.device, f"ring size {ring_size} is not a power of two "
                                             f"in 1..{MAX_RING_SIZE}")
        self.ring_size = ring_size
        self._next_event = counter

    def _records(self, wait_until: float) -> Iterator[TriggerRecord]:
        while True:
            counter = self._link.read_input_registers(self.base_register)[0]
            new = (counter - self._next_event) % SEQ_MODULUS
            if new:
                break
            remaining = wait_until - time.monotonic()
            if remaining <= 0:
                return
            time.sleep(min(self.poll_interval_s, remaining))
        if new > self.ring_size:
            self._resync(counter)
            raise ProtocolError(self.device, f"missed {new - self.ring_size} event(s): "
                                             f"counter advanced by {new} since the last poll, "
                                             f"the ring holds {self.ring_size}")
        while new:
            slot = self._next_event % self.ring_size
            run = min(new, self.ring_size - slot, MAX_RECORDS_PER_READ)
            registers = self._link.read_input_registers(
                self.base_register + HEADER_REGISTERS + RECORD_REGISTERS * slot,
                RECORD_REGISTERS * run)
            for k in range(run):
                seq, channel_edge, t_high, t_low = registers[RECORD_REGISTERS * k:
                                                             RECORD_REGISTERS * (k + 1)]
                expected = self._next_event
                self._next_event = (expected + 1) % SEQ_MODULUS
                new -= 1
                if seq != expected:
                    self._resync(counter)
                    raise ProtocolError(self.device, f"ring overrun while reading: slot "
                                                     f"{slot + k} holds event {seq}, expected "
                                                     f"{expected}")
                edge = EDGES_BY_CODE.get(channel_edge & 0xFF)
                if edge is None:
                    self._sequencer.restart()
                    raise ProtocolError(self.device, f"event {seq}: unknown edge code "
                                                     f"{channel_edge & 0xFF}")
                yield TriggerRecord(seq=seq, channel=channel_edge >> 8, edge=edge,
                                    t_us=t_high << 16 | t_low)

    def _resync(self, counter: int) -> None:
        self._next_event = counter
        self._sequencer.restart()

    def close(self) -> None:
        self._link.close()
