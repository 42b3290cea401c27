"""ur_rtde's control and IO interfaces in a child process, with deadlines on every call.

:mod:`.host` explains why ur_rtde must not run in the daemon's interpreter.
From here, ``call("control.moveJ", ...)`` returns the value, or raises
:class:`DeviceError` by its deadline, never later. If the child dies (killed, or
crashed inside ur_rtde), pending and later calls fail with the reason. ``close()`` ends
the child at once: nothing inside ur_rtde is worth waiting for.

Before starting the child, :func:`probe_controller` checks with plain sockets and a
deadline that the controller's ports answer. An unreachable controller is then named
in the error, instead of showing up as a child that timed out.
"""
from __future__ import annotations

import itertools
import logging
import socket
import struct
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection

from cellcal.drivers.interfaces import DeviceError, DeviceTimeout

log = logging.getLogger(__name__)

DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT = 29999, 30003, 30004
PORT_NAMES = {DASHBOARD_PORT: "dashboard server", SCRIPT_PORT: "script port", RTDE_PORT: "RTDE"}


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Exactly n bytes from a stream socket; ConnectionError when the peer closes."""
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("peer closed the connection")
        data += chunk
    return data


def probe_controller(host: str, device: str, timeout_s: float, ports=(RTDE_PORT,)) -> None:
    """Raise DeviceError unless every port accepts and answers within timeout_s.

    RTDE must answer a protocol-version request, the dashboard must send its banner;
    the script port only has to accept.
    """
    for port in ports:
        what = f"{PORT_NAMES.get(port, 'port')} port {port}"
        try:
            with socket.create_connection((host, port), timeout=timeout_s) as sock:
                sock.settimeout(timeout_s)
                if port == RTDE_PORT:
                    sock.sendall(struct.pack(">HBH", 5, ord("V"), 2))
                    size, kind = struct.unpack(">HB", recv_exact(sock, 3))
                    recv_exact(sock, size - 3)
                    if kind != ord("V"):
                        raise DeviceError(device, f"{what} answered a version request with packet type {kind}")
                elif port == DASHBOARD_PORT:
                    recv_exact(sock, 1)
        except ConnectionRefusedError:
            raise DeviceError(device, f"connection refused on {what}") from None
        except socket.timeout:
            raise DeviceTimeout(device, f"no answer on {what} within {timeout_s:g} s") from None
        except (ConnectionError, OSError) as exc:
            raise DeviceError(device, f"cannot talk to {what}: {exc}") from None


class UrRtdeProcess:
    """One ur_rtde child process; calls are thread-safe."""

    def __init__(self, host: str, *, device: str, frequency_hz: float = -1.0, connect_timeout_s: float = 5.0,
                 probe_ports=(RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT)):
        self.host, self.device = host, device
        self._cond = threading.Condition()
        self._results: dict[int, tuple] = {}
        self._targets: dict[int, str] = {}  # calls still awaited
        self._ids = itertools.count(1)
        self._failure: str | None = None
        self._closed = False
        probe_controller(host, device, connect_timeout_s, ports=probe_ports)
        parent_sock, child_sock = socket.socketpair()
        self._child = subprocess.Popen(
            [sys.executable, "-m", "cellcal.drivers.ur.host", "--fd", str(child_sock.fileno())],
            pass_fds=[child_sock.fileno()], stdin=subprocess.DEVNULL)
        child_sock.close()
        self._conn = Connection(parent_sock.detach())
        self._send_lock = threading.Lock()
        try:
            self._send({"host": host, "frequency_hz": frequency_hz})
            self._await_ready(connect_timeout_s + 10.0)  # + the child's interpreter start-up
        except BaseException:
            self._end_child()
            raise
        self._reader = threading.Thread(target=self._read, daemon=True, name=f"ur_rtde process {host}")
        self._reader.start()

    def _send(self, message) -> None:
        with self._send_lock:
            self._conn.send(message)

    def _await_ready(self, timeout_s: float) -> None:
        if not self._conn.poll(timeout_s):
            raise DeviceTimeout(self.device, f"ur_rtde did not connect within {timeout_s:g} s")
        try:
            reply = self._conn.recv()
        except (EOFError, OSError):
            raise DeviceError(self.device, f"ur_rtde process ended while connecting "
                                           f"({self._exit_description()})") from None
        if reply[0] != "ready":
            raise DeviceError(self.device, f"ur_rtde could not connect: {reply[1]}")

    def _exit_description(self) -> str:
        try:
            code = self._child.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            return "still running"
        return f"killed by signal {-code}" if code < 0 else f"exit code {code}"

    def _read(self) -> None:
        while True:
            try:
                kind, call_id, value = self._conn.recv()
            except (EOFError, OSError):
                with self._cond:
                    if self._failure is None and not self._closed:
                        self._failure = f"ur_rtde process ended ({self._exit_description()})"
                    self._cond.notify_all()
                return
            with self._cond:
                if call_id in self._targets:  # nobody waits for an abandoned call
                    self._results[call_id] = (kind, value)
                self._cond.notify_all()

    def failure(self) -> str | None:
        with self._cond:
            return "connection closed" if self._closed else self._failure

    def call(self, target: str, *args, timeout_s: float):
        """``target`` is "control.method" or "io.method"; DeviceError unless it returns in time."""
        return self.result(self.start_call(target, *args), timeout_s)

    def start_call(self, target: str, *args) -> int:
        """Send a call and return its id, for :meth:`result` (calls that block for long)."""
        what = self.failure()
        if what is not None:
            raise DeviceError(self.device, f"{target}: {what}")
        call_id = next(self._ids)
        self._targets[call_id] = target  # before sending: the reply may come at once
        try:
            self._send(("call", call_id, target, args))
        except OSError as exc:
            self._targets.pop(call_id, None)
            raise DeviceError(self.device, f"{target}: ur_rtde process unreachable: {exc}") from None
        return call_id

    def result(self, call_id: int, timeout_s: float, keep_waiting: bool = False):
        """The call's return value; DeviceTimeout when it has none by the deadline (with
        ``keep_waiting`` the call may still be collected later), DeviceError if it raised
        or the process ended."""
        target = self._targets.get(call_id, "call")
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while call_id not in self._results:
                left = deadline - time.monotonic()
                what = "connection closed" if self._closed else self._failure
                if what or left <= 0:
                    if what or not keep_waiting:
                        self._targets.pop(call_id, None)
                    if what:
                        raise DeviceError(self.device, f"{target}: {what}")
                    raise DeviceTimeout(self.device, f"{target}: no reply within {timeout_s:g} s")
                self._cond.wait(min(left, 0.05))
            kind, value = self._results.pop(call_id)
            self._targets.pop(call_id, None)
        if kind == "raised":
            raise DeviceError(self.device, f"{target} failed: {value}")
        return value

    def close(self) -> None:
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        self._end_child()

    def _end_child(self) -> None:
        try:
            self._send(("exit",))
        except OSError:
            pass
        try:
            self._child.wait(timeout=1.0)
        except subprocess.TimeoutExpired:  # stuck inside ur_rtde: it has nothing to save
            self._child.kill()
            try:
                self._child.wait(timeout=5.0)
            except subprocess.TimeoutExpired:  # killed, not yet reaped on a starved host: the kernel ends it
                log.warning("ur_rtde's process %d was killed and has not ended within 5 s", self._child.pid)
        self._conn.close()
