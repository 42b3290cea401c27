"""Light barrier / touch trigger events over a serial line, through pyserial.

The device timestamps each edge with its own microsecond clock and sends one
ASCII sentence per edge, NMEA 0183 style (8N1, 115200 baud by default)::

    $TRG,<seq>,<channel>,<edge>,<t_us>*<checksum>\\r\\n

========  ==================================================================
field     meaning
========  ==================================================================
seq       sentence number, decimal 0..65535, +1 per sentence, wraps to 0
channel   input number, decimal 0..255
edge      ``B`` beam blocked / contact made, ``C`` cleared / released
t_us      device time of the edge in us, decimal 0..4294967295, wraps
checksum  two hex digits: XOR of every byte between ``$`` and ``*``
========  ==================================================================

A sentence is at most 82 bytes including ``\\r\\n`` (a bare ``\\n`` is accepted).
Sentences of another type with a good checksum are skipped, so a device may add
e.g. a heartbeat without breaking this client.

Every fault raises :class:`ProtocolError` naming the port, rather than being
logged and counted: a lost or corrupt edge makes the sweep it belongs to
useless, and the routine must know to repeat it. Faults are: a bad checksum, a
truncated sentence (no ``*checksum``, or a new ``$`` before the line ended), an
over-long line, a line not starting with ``$``, a malformed field, a sequence
gap or repeat, and a device time going backwards. The bytes before the first
``$`` after opening are skipped silently: the port may open mid-sentence.
"""
from __future__ import annotations

import re
import time
from typing import Iterator

import serial

from cellcal.config.reader import Section
from cellcal.drivers.checksum_lines import checked_body, framed
from cellcal.drivers.interfaces import DeviceError, Edge, ProtocolError
from cellcal.drivers.registry import DriverConfigError
from cellcal.drivers.triggers.stream import RecordTrigger, TriggerRecord

MAX_SENTENCE_BYTES = 82
SEQ_MODULUS = 65536
EDGE_LETTERS = {"B": Edge.BLOCKED, "C": Edge.CLEARED}
LETTERS_BY_EDGE = {edge: letter for letter, edge in EDGE_LETTERS.items()}
_DECIMAL = re.compile(r"[0-9]{1,10}")


def format_trigger_sentence(seq: int, channel: int, edge: Edge, t_us: int) -> bytes:
    """One ``$TRG`` sentence, as the device sends it."""
    body = f"TRG,{seq % SEQ_MODULUS},{channel},{LETTERS_BY_EDGE[edge]},{t_us % 2**32}".encode()
    return b"$" + framed(body)


def parse_trigger_sentence(line: bytes, device: str) -> TriggerRecord | None:
    """A record from one line (without its terminator); None for another sentence type."""
    if not line.startswith(b"$"):
        raise ProtocolError(device, f"line does not start with '$': {line[:24]!r}")
    body = checked_body(line, 1, device, "sentence", 24)
    try:
        fields = body.decode("ascii").split(",")
    except UnicodeDecodeError:
        raise ProtocolError(device, f"non-ASCII bytes in sentence {line[:24]!r}") from None
    if fields[0] != "TRG":
        return None
    if len(fields) != 5:
        raise ProtocolError(device, f"malformed TRG sentence: {len(fields)} fields, expected 5")
    _, seq, channel, edge, t_us = fields
    if edge not in EDGE_LETTERS:
        raise ProtocolError(device, f"malformed TRG sentence: edge {edge[:8]!r}, expected B or C")
    return TriggerRecord(seq=_field(device, "seq", seq, SEQ_MODULUS - 1),
                         channel=_field(device, "channel", channel, 255),
                         edge=EDGE_LETTERS[edge],
                         t_us=_field(device, "t_us", t_us, 2**32 - 1))


def _field(device: str, name: str, text: str, high: int) -> int:
    if not _DECIMAL.fullmatch(text) or int(text) > high:
        raise ProtocolError(device, f"malformed TRG sentence: {name} {text[:12]!r} is not "
                                    f"a decimal in 0..{high}")
    return int(text)


class SentenceFramer:
    """Cuts a byte stream into ``$...`` lines; reports truncated, stray and over-long ones.

    After a fault, bytes up to the next ``$`` are dropped silently, so one broken
    sentence gives one error.
    """

    def __init__(self, device: str, max_bytes: int = MAX_SENTENCE_BYTES):
        self.device = device
        self.max_bytes = max_bytes
        self._buffer = bytearray()
        self._synced = False  # False until the first '$': the port may open mid-sentence

    def feed(self, data: bytes) -> None:
        self._buffer += data

    def next_line(self) -> bytes | None:
        """The next complete line without its terminator, None if none is complete yet."""
        buffer = self._buffer
        if not self._synced:
            start = buffer.find(b"$")
            del buffer[:start if start >= 0 else len(buffer)]
            self._synced = start >= 0
        if not buffer:
            return None
        end = buffer.find(b"\n")
        inner = buffer.find(b"$", 1, len(buffer) if end < 0 else end)
        if buffer[0] != ord("$") or inner > 0:
            if inner < 0 and end < 0:
                return self._wait_or_overflow()
            cut = bytes(buffer[:inner if inner > 0 else end + 1])
            self._fault(len(cut))
            if cut.startswith(b"$"):
                raise ProtocolError(self.device, f"truncated sentence (next '$' before end "
                                                 f"of line): {cut[:24]!r}")
            raise ProtocolError(self.device, f"stray bytes between sentences: {cut[:24]!r}")
        if end < 0:
            return self._wait_or_overflow()
        line = bytes(buffer[:end]).removesuffix(b"\r")
        del buffer[:end + 1]
        if end + 1 > self.max_bytes:
            raise ProtocolError(self.device, f"line of {end + 1} bytes, longer than "
                                             f"{self.max_bytes}")
        return line

    def _wait_or_overflow(self) -> None:
        if len(self._buffer) <= self.max_bytes:
            return None  # the rest of the line is still on its way
        self._fault(len(self._buffer))
        raise ProtocolError(self.device, f"line longer than {self.max_bytes} bytes without "
                                         f"terminator")

    def _fault(self, n_bytes: int) -> None:
        del self._buffer[:n_bytes]
        self._synced = False  # drop the rest of a broken line up to the next '$'


class SerialTrigger(RecordTrigger):
    """Device-timestamped trigger events from a serial line (tty path ``port``)."""

    @staticmethod
    def check_options(**options) -> None:
        """Refuse an option out of range, naming it (also run by the registry at cell load)."""
        o = Section.of_options(DriverConfigError, **options)
        o.text("port")
        o.integer("baudrate", low=50, high=4_000_000)

    def __init__(self, port: str, *, baudrate: int = 115200, name: str = "trigger"):
        self.check_options(port=port, baudrate=baudrate)
        self.name = name
        super().__init__(f"{name} (serial {port})", SEQ_MODULUS)
        self._framer = SentenceFramer(self.device)
        try:
            self._port = serial.Serial(port, baudrate=baudrate, bytesize=serial.EIGHTBITS,
                                       parity=serial.PARITY_NONE, stopbits=serial.STOPBITS_ONE,
                                       timeout=0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(self.device, f"cannot open serial port: {exc}") from exc

    def _records(self, wait_until: float) -> Iterator[TriggerRecord]:
        while True:
            line = self._framer.next_line()
            if line is not None:
                record = parse_trigger_sentence(line, self.device)
                if record is not None:
                    wait_until = 0.0  # something arrived: only drain what is already there
                    yield record
                continue
            data = self._read(wait_until)
            if not data:
                return
            self._framer.feed(data)

    def _read(self, wait_until: float) -> bytes:
        try:
            waiting = self._port.in_waiting
            if waiting:
                return self._port.read(waiting)
            remaining = wait_until - time.monotonic()
            if remaining <= 0:
                return b""
            self._port.timeout = remaining
            return self._port.read(1)
        except (serial.SerialException, OSError) as exc:
            raise DeviceError(self.device, f"serial line lost: {exc}") from exc

    def close(self) -> None:
        self._port.close()
