"""A laser tracker behind a TCP line protocol: one request, one reply, a deadline on each.

Instrument SDKs differ per maker; the cell talks to a small server next to the
instrument (or the instrument's own, where it speaks this) with ASCII lines.
Every line ends in ``*XX``: two hex digits, the XOR of all bytes before the
``*``. Lines end in ``\\r\\n`` (a bare ``\\n`` is accepted) and are at most 512
bytes. Default port 5025, the usual one for line protocols of instruments.

Request::

    MEAS <target> <seq>*XX

``target`` is ``[A-Za-z0-9_.-]{1,32}`` (e.g. ``smr1``); ``seq`` is the client's
request number, decimal, 0..999999999, +1 per request, wrapping.

Replies (one per request, carrying its ``seq``)::

    OK <seq> <status> <t_s> <x_m> <y_m> <z_m> <sigma_m>*XX                   3-DoF
    OK <seq> <status> <t_s> <x_m> <y_m> <z_m> <qw> <qx> <qy> <qz> <sigma_m>*XX  6-DoF
    ERR <seq> <code> <text>*XX

``status`` is ``ok`` or a lower-case word saying why the value is doubtful
(``unstable``: the target moved while measured; ``env``: weather sensors out of
range); it is passed on in :attr:`TrackerMeasurement.status`. ``t_s`` is the
instrument's clock; positions are metres in the instrument frame; ``sigma_m``
is the instrument's expected standard deviation per axis. ``ERR`` codes are in
:data:`ERROR_CODES`; ``seq`` is ``-`` when the request itself was unreadable.

A reply to an earlier request (one that timed out) arriving late is recognised
by its ``seq`` and skipped. Faults: no reply by the deadline
(:class:`DeviceTimeout`), connection refused or lost (:class:`DeviceError`,
re-opened by the next request), a malformed, over-long or badly checksummed
reply or an unexpected ``seq`` (:class:`ProtocolError`), an ``ERR`` reply
(:class:`TrackerStatusError`).
"""
from __future__ import annotations

import math
import re
import socket
import time
from dataclasses import dataclass

import numpy as np

from cellcal.drivers.checksum_lines import checked_body, framed
from cellcal.drivers.interfaces import DeviceError, DeviceTimeout, ProtocolError, Tracker, TrackerMeasurement
from cellcal.config.reader import Section
from cellcal.drivers.registry import DriverConfigError

DEFAULT_PORT = 5025
MAX_LINE_BYTES = 512
SEQ_MODULUS = 1_000_000_000
STALE_WINDOW = 1000  # replies this many requests old are late answers, not faults

ERROR_CODES = {
    1: "beam broken",  # beam interrupted, target lost: re-lock and repeat
    2: "target not found",  # unknown target name, or not in view
    3: "not ready",  # warming up, not initialised, no compensation
    4: "busy",  # another measurement is running
    5: "bad request",  # malformed or badly checksummed request
    6: "out of range",  # target beyond the instrument's range
    9: "instrument fault",
}

TARGET_NAME = re.compile(r"[A-Za-z0-9_.-]{1,32}")
_NUMBER = re.compile(r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]{1,3})?")
_SEQ = re.compile(r"[0-9]{1,9}")
_STATUS = re.compile(r"[a-z_]{1,16}")


class TrackerStatusError(DeviceError):
    """The instrument answered, but with an error code instead of a value."""

    def __init__(self, device: str, what: str, code: int):
        super().__init__(device, what)
        self.code = code


def with_checksum(body: str) -> bytes:
    """One protocol line: body, ``*XX`` and the terminator."""
    return framed(body.encode("ascii"))


def strip_checksum(line: bytes, device: str) -> str:
    """The body of a line (without terminator) whose checksum is right."""
    body = checked_body(line, 0, device, "line", 32)
    try:
        return body.decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError(device, f"non-ASCII bytes in line {line[:32]!r}") from None


@dataclass(frozen=True)
class TrackerReply:
    seq: int | None  # None: the instrument could not read the request's seq
    measurement: TrackerMeasurement | None  # for OK
    error_code: int = 0  # for ERR
    error_text: str = ""


def parse_reply(line: bytes, device: str) -> TrackerReply:
    """One reply line (without terminator); ProtocolError for anything malformed."""
    fields = strip_checksum(line, device).split(" ")
    kind = fields[0]
    if kind == "ERR":
        if len(fields) < 3:
            raise ProtocolError(device, f"malformed ERR reply: {len(fields)} fields")
        seq = None if fields[1] == "-" else _seq(device, fields[1])
        if not _SEQ.fullmatch(fields[2]):
            raise ProtocolError(device, f"malformed ERR reply: code {fields[2][:12]!r}")
        return TrackerReply(seq, None, int(fields[2]), " ".join(fields[3:]))
    if kind != "OK":
        raise ProtocolError(device, f"unknown reply {kind[:12]!r}, expected OK or ERR")
    if len(fields) not in (8, 12):
        raise ProtocolError(device, f"malformed OK reply: {len(fields)} fields, expected 8 "
                                    f"(3-DoF) or 12 (6-DoF)")
    seq = _seq(device, fields[1])
    status = fields[2]
    if not _STATUS.fullmatch(status):
        raise ProtocolError(device, f"malformed OK reply: status {status[:16]!r}")
    numbers = [_number(device, text) for text in fields[3:]]
    orientation = None
    if len(numbers) == 9:
        orientation = np.array(numbers[4:8])
        norm = float(np.linalg.norm(orientation))
        if abs(norm - 1.0) > 1e-3:
            raise ProtocolError(device, f"orientation quaternion of norm {norm:.4f}, not unit")
    sigma_m = numbers[-1]
    if sigma_m < 0:
        raise ProtocolError(device, f"negative sigma {sigma_m} m")
    return TrackerReply(seq, TrackerMeasurement(
        t_s=numbers[0], position_m=np.array(numbers[1:4]), orientation=orientation,
        status=status, quality=sigma_m))


def _seq(device: str, text: str) -> int:
    if not _SEQ.fullmatch(text):
        raise ProtocolError(device, f"malformed seq {text[:12]!r}")
    return int(text)


def _number(device: str, text: str) -> float:
    if not _NUMBER.fullmatch(text) or not math.isfinite(value := float(text)):
        raise ProtocolError(device, f"malformed number {text[:24]!r}")
    return value


class TrackerSocket(Tracker):
    """A tracker measured over the line protocol above; options as a cell file gives them.

    Connects at construction so that a wrong host or port fails at start-up.
    """

    @staticmethod
    def check_options(**options) -> None:
        """Refuse an option out of range, naming it (also run by the registry at cell load)."""
        o = Section.of_options(DriverConfigError, **options)
        o.text("host")
        o.port()
        o.timeout("connect_timeout_s")
        o.timeout("measure_timeout_s")

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *,
                 connect_timeout_s: float = 2.0, measure_timeout_s: float = 5.0, name: str = "tracker"):
        self.check_options(host=host, port=port, connect_timeout_s=connect_timeout_s,
                           measure_timeout_s=measure_timeout_s)
        self.name = name
        self.device = f"{name} ({host}:{port})"
        self.host = host
        self.port = port
        self.connect_timeout_s = float(connect_timeout_s)
        self.measure_timeout_s = float(measure_timeout_s)  # a tracker silent this long has failed
        self._socket: socket.socket | None = None
        self._buffer = bytearray()
        self._seq = 0
        self._connect(time.monotonic() + self.connect_timeout_s)

    def measure(self, target: str = "smr1", timeout_s: float | None = None) -> TrackerMeasurement:
        timeout_s = self.measure_timeout_s if timeout_s is None else timeout_s
        if not isinstance(target, str) or not TARGET_NAME.fullmatch(target):
            raise ValueError(f"{self.device}: target name {target!r} is not "
                             f"[A-Za-z0-9_.-]{{1,32}}")
        if not timeout_s > 0:
            raise ValueError(f"{self.device}: timeout_s must be > 0, got {timeout_s}")
        deadline = time.monotonic() + timeout_s
        self._seq = (self._seq + 1) % SEQ_MODULUS
        seq = self._seq
        request = f"MEAS {target} {seq}"
        if self._socket is None:
            self._connect(deadline)
        self._send(with_checksum(request), deadline, request)
        while True:
            reply = parse_reply(self._read_line(deadline, request, timeout_s), self.device)
            if reply.seq is not None and reply.seq != seq:
                if 0 < (seq - reply.seq) % SEQ_MODULUS <= STALE_WINDOW:
                    continue  # the late answer to a request that timed out
                raise ProtocolError(self.device, f"reply to request {reply.seq} while waiting "
                                                 f"for {request}")
            if reply.measurement is None:
                name = ERROR_CODES.get(reply.error_code, "unknown error")
                raise TrackerStatusError(
                    self.device, f"{name} (code {reply.error_code}) on {request}: "
                                 f"{reply.error_text}", reply.error_code)
            return reply.measurement

    def _connect(self, deadline: float) -> None:
        timeout = max(1e-3, min(self.connect_timeout_s, deadline - time.monotonic()))
        try:
            self._socket = socket.create_connection((self.host, self.port), timeout=timeout)
        except socket.timeout as exc:
            raise DeviceTimeout(self.device, f"no connection within {timeout:.3g} s") from exc
        except OSError as exc:
            raise DeviceError(self.device, f"cannot connect: {exc.strerror or exc}") from exc
        self._socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buffer.clear()

    def _send(self, data: bytes, deadline: float, request: str) -> None:
        try:
            self._socket.settimeout(max(1e-3, deadline - time.monotonic()))
            self._socket.sendall(data)
        except socket.timeout as exc:
            self._drop_connection()  # a request may be half sent
            raise DeviceTimeout(self.device, f"could not send {request} in time") from exc
        except OSError as exc:
            self._drop_connection()
            raise DeviceError(self.device, f"connection lost sending {request}: "
                                           f"{exc.strerror or exc}") from exc

    def _read_line(self, deadline: float, request: str, timeout_s: float) -> bytes:
        while True:
            end = self._buffer.find(b"\n")
            if end >= 0:
                line = bytes(self._buffer[:end]).removesuffix(b"\r")
                del self._buffer[:end + 1]
                if end + 1 > MAX_LINE_BYTES:
                    raise ProtocolError(self.device, f"reply of {end + 1} bytes, longer "
                                                     f"than {MAX_LINE_BYTES}")
                return line
            if len(self._buffer) > MAX_LINE_BYTES:
                self._drop_connection()  # no way to find the next line start: start afresh
                raise ProtocolError(self.device, f"reply longer than {MAX_LINE_BYTES} bytes "
                                                 f"without terminator")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(self.device, f"no reply to {request} within {timeout_s:g} s")
            try:
                self._socket.settimeout(remaining)
                data = self._socket.recv(4096)
            except socket.timeout as exc:
                raise DeviceTimeout(self.device, f"no reply to {request} within "
                                                 f"{timeout_s:g} s") from exc
            except OSError as exc:
                self._drop_connection()
                raise DeviceError(self.device, f"connection lost waiting for the reply to "
                                               f"{request}: {exc.strerror or exc}") from exc
            if not data:
                self._drop_connection()
                raise DeviceError(self.device, f"connection lost (closed by the instrument) "
                                               f"waiting for the reply to {request}")
            self._buffer += data

    def _drop_connection(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None
        self._buffer.clear()

    def close(self) -> None:
        self._drop_connection()
