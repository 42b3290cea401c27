"""A UR controller's RTDE state stream, every package of it, as timestamped samples.

ur_rtde's RTDEReceiveInterface keeps only the newest package: when two packages wait
in its socket it drops the older, and what it holds is overwritten every cycle whether
or not anyone read it. On a busy cell PC that loses samples silently (measured: 16 % of
them with two busy processes on two cores), and a lost sample is a trigger edge timed
a cycle or more late. So the state stream is read here from the RTDE socket itself:
TCP keeps every package until this reader gets to it, and each one becomes a sample
stamped with the controller's ``timestamp``. Control and IO still go through ur_rtde.

The reader also watches the stream: the connection closing, or no package for
``stale_after_s`` (a controller that stalls keeps its TCP connection open).
"""
from __future__ import annotations

import select
import socket
import struct
import threading
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable

import numpy as np

from cellcal.drivers.interfaces import DeviceError, DeviceTimeout, RobotSample

RTDE_PORT = 30004
PROTOCOL_VERSION = 2
HEADER = struct.Struct(">HB")
TYPE_FORMATS = {"BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
                "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I"}

# safety_status_bits (RTDE guide)
PROTECTIVE_STOPPED_BIT = 1 << 2
EMERGENCY_STOPPED_BITS = (1 << 5) | (1 << 6) | (1 << 7)  # system, robot, any emergency stop
RUNTIME_PLAYING = 2

# output_int_register_2: the ur_rtde control script's async progress word
ROBOT_VARIABLES = ("timestamp", "actual_q", "actual_TCP_pose", "actual_digital_input_bits",
                   "actual_digital_output_bits", "safety_status_bits", "runtime_state", "output_int_register_2")
INPUT_VARIABLES = ("timestamp", "actual_digital_input_bits")


@dataclass(frozen=True)
class ControllerStatus:
    """Safety, program and async-operation state from the latest sample."""

    safety_status_bits: int = 0
    runtime_state: int = 0
    async_progress: int = 0  # bit 15 running, bits 24-30 operation id
    digital_outputs: int = 0  # actual_digital_output_bits

    @property
    def protective_stopped(self) -> bool:
        return bool(self.safety_status_bits & PROTECTIVE_STOPPED_BIT)

    @property
    def emergency_stopped(self) -> bool:
        return bool(self.safety_status_bits & EMERGENCY_STOPPED_BITS)

    @property
    def program_running(self) -> bool:
        return self.runtime_state == RUNTIME_PLAYING

    @property
    def async_operation_id(self) -> int:
        return (self.async_progress >> 24) & 0x7F

    @property
    def async_operation_running(self) -> bool:
        return bool(self.async_progress & 0x8000)


class _Wire:
    """RTDE packets on a socket; a read timeout keeps partial data for the next call."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.buffer = bytearray()

    def send(self, kind: str, payload: bytes = b"") -> None:
        self.sock.sendall(HEADER.pack(HEADER.size + len(payload), ord(kind)) + payload)

    def receive(self) -> tuple[str, bytes]:
        while True:
            if len(self.buffer) >= HEADER.size:
                size, kind = HEADER.unpack_from(self.buffer)
                if size < HEADER.size:
                    raise ConnectionError(f"malformed RTDE packet header (size {size})")
                if len(self.buffer) >= size:
                    payload = bytes(self.buffer[HEADER.size:size])
                    del self.buffer[:size]
                    return chr(kind), payload
            chunk = self.sock.recv(65536)  # socket.timeout leaves the buffer as it was
            if not chunk:
                raise ConnectionError("closed by the controller")
            self.buffer += chunk

    def request(self, kind: str, payload: bytes = b"") -> bytes:
        """Send a request and return the payload of its reply (text messages skipped)."""
        self.send(kind, payload)
        while True:
            reply_kind, reply = self.receive()
            if reply_kind == kind:
                return reply


def rtde_connect(host: str, device: str, timeout_s: float) -> socket.socket:
    """A TCP connection to the controller's RTDE port, with `timeout_s` on every later read."""
    what = f"RTDE port {RTDE_PORT}"
    try:
        sock = socket.create_connection((host, RTDE_PORT), timeout=timeout_s)
    except ConnectionRefusedError:
        raise DeviceError(device, f"connection refused on {what}") from None
    except socket.timeout:
        raise DeviceTimeout(device, f"no answer on {what} within {timeout_s:g} s") from None
    except OSError as exc:
        raise DeviceError(device, f"cannot connect to {what}: {exc}") from None
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


@contextmanager
def setup_errors(device: str, what: str):
    """A failure while talking RTDE set-up as the DeviceError that names it."""
    try:
        yield
    except socket.timeout:
        raise DeviceTimeout(device, f"RTDE stopped answering during {what}") from None
    except (ConnectionError, OSError, struct.error, IndexError) as exc:
        raise DeviceError(device, f"RTDE {what} failed: {exc}") from None


def negotiate(wire: "_Wire", device: str) -> int:
    """Agree on the protocol version; returns the controller's major version."""
    with setup_errors(device, "set-up"):
        if not wire.request("V", struct.pack(">H", PROTOCOL_VERSION))[0]:
            raise DeviceError(device, f"controller refused RTDE protocol version {PROTOCOL_VERSION}")
        return struct.unpack(">IIII", wire.request("v"))[0]


def output_recipe(wire: "_Wire", device: str, frequency_hz: float, variables) -> tuple[int, struct.Struct, list[bool]]:
    """Declare an output recipe: (its id, the data package layout, which fields are vectors)."""
    with setup_errors(device, "output set-up"):
        reply = wire.request("O", struct.pack(">d", frequency_hz) + ",".join(variables).encode())
        recipe_id, types = reply[0], reply[1:].decode(errors="replace").split(",")
    missing = [n for n, t in zip(variables, types) if t not in TYPE_FORMATS]
    if missing or len(types) != len(variables):
        raise DeviceError(device, f"controller does not provide {', '.join(missing) or types}")
    layout = struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in types))
    return recipe_id, layout, [t.startswith("VECTOR") for t in types]


class UrStateStream:
    """Every RTDE output package of one connection as samples; thread-safe."""

    def __init__(self, host: str, *, device: str, variables=ROBOT_VARIABLES, frequency_hz: float = -1.0,
                 connect_timeout_s: float = 5.0, stale_after_s: float = 0.5, buffer_s: float = 120.0):
        self.host, self.device = host, device
        self.variables = tuple(variables)
        self.stale_after_s = stale_after_s
        self._cond = threading.Condition()
        self._listeners: list[Callable[[RobotSample], None]] = []
        self._status = ControllerStatus()
        self._failure: str | None = None
        self._closed = False
        self._sock = self._connect(connect_timeout_s, frequency_hz)
        self._samples: deque[RobotSample] = deque(maxlen=int(buffer_s * self.frequency_hz))
        self._last_arrival = time.monotonic()
        self._thread = threading.Thread(target=self._read, daemon=True, name=f"rtde-state {host}")
        self._thread.start()
        self.next_sample(connect_timeout_s)

    def _connect(self, timeout_s: float, frequency_hz: float) -> socket.socket:
        sock = rtde_connect(self.host, self.device, timeout_s)
        try:
            wire = _Wire(sock)
            major = negotiate(wire, self.device)
            self.frequency_hz = frequency_hz if frequency_hz > 0 else (500.0 if major > 3 else 125.0)
            self._recipe_id, self._layout, self._vector = output_recipe(wire, self.device, self.frequency_hz,
                                                                         self.variables)
            with setup_errors(self.device, "start"):
                started = wire.request("S")[0]
            if not started:
                raise DeviceError(self.device, "controller refused to start the RTDE stream")
        except BaseException:
            sock.close()
            raise
        sock.settimeout(0.1)  # the reader wakes up to notice close() and silence
        self._wire = wire
        return sock

    def _decode(self, payload: bytes) -> tuple[RobotSample, ControllerStatus]:
        flat = self._layout.unpack(payload)[1:]
        values, i = {}, 0
        for name, vector in zip(self.variables, self._vector):
            n = 6 if vector else 1  # VECTOR3D is not among the variables read here
            values[name] = flat[i:i + n] if vector else flat[i]
            i += n
        sample = RobotSample(values["timestamp"], np.array(values.get("actual_q", ())),
                             np.array(values.get("actual_TCP_pose", ())),
                             int(values.get("actual_digital_input_bits", 0)))
        status = ControllerStatus(int(values.get("safety_status_bits", 0)), int(values.get("runtime_state", 0)),
                                  int(values.get("output_int_register_2", 0)),
                                  int(values.get("actual_digital_output_bits", 0)))
        return sample, status

    def _read(self) -> None:
        while not self._closed:
            try:
                kind, payload = self._wire.receive()
            except socket.timeout:
                continue  # silence is judged by failure(), from the last arrival
            except (ConnectionError, OSError) as exc:
                self._fail(f"connection to the controller lost ({exc})")
                return
            if kind != "U" or not payload or payload[0] != self._recipe_id:
                continue
            try:
                sample, status = self._decode(payload)
            except struct.error as exc:
                self._fail(f"malformed RTDE data package: {exc}")
                return
            with self._cond:
                self._samples.append(sample)
                self._status = status
                self._last_arrival = time.monotonic()
                self._cond.notify_all()
            for listener in list(self._listeners):
                listener(sample)

    def _fail(self, what: str) -> None:
        with self._cond:
            if self._failure is None and not self._closed:
                self._failure = what
            self._cond.notify_all()

    def failure(self) -> str | None:
        """Why the stream is unusable (closed, lost, silent for stale_after_s), or None."""
        with self._cond:
            if self._closed:
                return "connection closed"
            if self._failure is not None:
                return self._failure
            silent_s = time.monotonic() - self._last_arrival
        if silent_s > self.stale_after_s and not self._data_waiting():
            return f"no state from the controller for {silent_s:.2f} s (stalled or unreachable)"
        return None

    def stalled(self) -> bool:
        """Open, but nothing from the controller for stale_after_s: it did not answer in time."""
        with self._cond:
            if self._closed or self._failure is not None:
                return False
        return self.failure() is not None

    def _data_waiting(self) -> bool:
        """Packages in the socket mean the reader is late (a busy process), not the controller."""
        try:
            return bool(select.select([self._sock], [], [], 0)[0])
        except (OSError, ValueError):
            return False

    def check(self) -> None:
        what = self.failure()
        if what is not None:
            raise DeviceError(self.device, what)

    @property
    def status(self) -> ControllerStatus:
        with self._cond:
            return self._status

    def latest(self) -> RobotSample:
        self.check()
        with self._cond:
            return self._samples[-1]

    def samples(self, since_t_s: float | None = None) -> list[RobotSample]:
        with self._cond:
            if since_t_s is None:
                return list(self._samples)
            out = []
            for sample in reversed(self._samples):  # recent ones are what callers ask for
                if sample.t_s <= since_t_s:
                    break
                out.append(sample)
            return out[::-1]

    def next_sample(self, timeout_s: float) -> RobotSample:
        """The first sample that arrives after this call."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            last = self._samples[-1] if self._samples else None
            while not (self._samples and self._samples[-1] is not last):
                left = deadline - time.monotonic()
                if self._failure is not None or self._closed or left <= 0:
                    break
                self._cond.wait(min(left, 0.05))
            else:
                return self._samples[-1]
        self.check()
        raise DeviceTimeout(self.device, f"no new state sample within {timeout_s:g} s")

    def current(self, timeout_s: float) -> RobotSample:
        """The state now: a new sample with no older packages still waiting to be read.

        The stream is lossless, so on a busy machine the newest sample read can lag the
        controller; this waits until the reader has caught up.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            sample = self.next_sample(max(deadline - time.monotonic(), 0.0))
            if not self._data_waiting():
                return sample

    def add_listener(self, listener: Callable[[RobotSample], None]) -> None:
        """Call ``listener(sample)`` from the reader thread for every new sample."""
        self._listeners.append(listener)

    def close(self) -> None:
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        try:
            self._wire.send("P")  # polite: the controller stops streaming before the socket closes
        except OSError:
            pass
        self._thread.join(timeout=1.0)
        self._sock.close()
