"""A simulated laser tracker server on loopback, with the instrument's noise model.

Speaks the line protocol of :mod:`cellcal.drivers.tracker_socket`. The true
target position comes from a callback, so the simulated cell can plug in the
simulated arm: ``position_fn(target) -> (3,) m`` in the instrument frame
(``None`` or ``KeyError`` when the target is not there); each measurement adds
normal noise with the per-axis sigma of :class:`~cellcal.sims.physics.kinematic_arm.TrackerNoise`.
Its timestamps and reply delay are on a simulated clock (``clock``: in a networked cell
the fake controller's, so the instrument's time is the robot's; alone, its own).
Attributes and methods let tests break the beam, delay or withhold replies,
corrupt them and cut connections.
"""
from __future__ import annotations

import socket
import socketserver
import threading
from collections import deque
from typing import Callable

import numpy as np

from cellcal.drivers.interfaces import ProtocolError
from cellcal.drivers.tracker_socket import (MAX_LINE_BYTES, TARGET_NAME, strip_checksum,
                                      with_checksum)
from cellcal.sims.physics.clock import SimClock
from cellcal.sims.physics.kinematic_arm import TrackerNoise

BEAM_BROKEN, TARGET_NOT_FOUND, BAD_REQUEST = 1, 2, 5
POLL_S = 0.05  # how often an idle connection looks whether the server is stopping


class TrackerServer:
    """Threaded TCP server; one thread per client connection."""

    def __init__(self, position_fn: Callable[[str], np.ndarray | None], *,
                 orientation_fn: Callable[[str], np.ndarray | None] | None = None,
                 noise: TrackerNoise = TrackerNoise(), rng: np.random.Generator | None = None,
                 host: str = "127.0.0.1", port: int = 0, clock: SimClock | None = None):
        self.position_fn = position_fn
        self.orientation_fn = orientation_fn
        self.noise = noise
        self.rng = rng if rng is not None else np.random.default_rng()
        self.host = host
        self.port = port
        # fault injection, read by the connection threads
        self.beam_broken = False
        self.status = "ok"  # the status word of OK replies
        self.reply_delay_s = 0.0  # simulated time
        self.silent = False  # read requests, never answer
        self._injected: deque[bytes] = deque()
        self.requests: list[str] = []  # request bodies as received
        self._lock = threading.Lock()
        self._connections: set[socket.socket] = set()
        self._server: socketserver.ThreadingTCPServer | None = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self.clock = clock if clock is not None else SimClock()
        self._measuring = threading.Lock()  # a position and its time from one look at the clock's source

    # -- life cycle ------------------------------------------------------------------

    def start(self) -> "TrackerServer":
        tracker = self

        class Connection(socketserver.BaseRequestHandler):
            def handle(self):
                tracker._serve(self.request)

        server = socketserver.ThreadingTCPServer((self.host, self.port), Connection,
                                                 bind_and_activate=False)
        server.daemon_threads = True
        server.allow_reuse_address = True
        server.server_bind()
        server.server_activate()
        self._server = server
        self.port = server.server_address[1]
        self._thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": POLL_S},
                                        name=f"tracker-server-{self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._server is None:
            return
        self._stopping.set()
        self._server.shutdown()
        self._server.server_close()
        self.drop_connections()
        self._thread.join(5.0)
        self._server = None

    def __enter__(self) -> "TrackerServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- fault injection -------------------------------------------------------------

    def inject_reply(self, raw: bytes) -> None:
        """Send these bytes instead of the next reply (a corrupt or truncated line)."""
        self._injected.append(raw)

    def drop_connections(self) -> None:
        """Cut every client connection, as a crashing instrument server would."""
        with self._lock:
            connections, self._connections = self._connections, set()
        for connection in connections:
            try:
                connection.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            connection.close()

    # -- the instrument --------------------------------------------------------------

    def measure(self, target: str) -> tuple[float, np.ndarray, np.ndarray | None, float]:
        """Instrument time, noisy position (m), orientation, per-axis sigma (m)."""
        with self._measuring:
            true_m = self.position_fn(target)
            t_s = self.clock.now()
        if true_m is None:
            raise KeyError(target)
        true_m = np.asarray(true_m, dtype=float).reshape(3)
        sigma_m = float(self.noise.sigma(true_m[None, :] * 1000.0)[0]) / 1000.0
        measured_m = true_m + self.rng.normal(0.0, sigma_m, 3)
        orientation = None if self.orientation_fn is None else self.orientation_fn(target)
        return t_s, measured_m, orientation, sigma_m

    def reply_to(self, line: bytes) -> bytes:
        """The reply line for one request line (without terminator)."""
        try:
            fields = strip_checksum(line, "tracker server").split(" ")
        except ProtocolError as exc:
            return with_checksum(f"ERR - {BAD_REQUEST} {exc.what}")
        seq = fields[-1] if fields[-1].isdigit() and len(fields[-1]) <= 9 else "-"
        if len(fields) != 3 or fields[0] != "MEAS" or not TARGET_NAME.fullmatch(fields[1]) \
                or seq == "-":
            return with_checksum(f"ERR {seq} {BAD_REQUEST} expected MEAS <target> <seq>")
        with self._lock:
            self.requests.append(" ".join(fields))
        target = fields[1]
        if self.beam_broken:
            return with_checksum(f"ERR {seq} {BEAM_BROKEN} beam interrupted, target lost")
        try:
            t_s, position_m, orientation, sigma_m = self.measure(target)
        except KeyError:
            return with_checksum(f"ERR {seq} {TARGET_NOT_FOUND} no target {target} in view")
        numbers = [f"{v:.7f}" for v in position_m]
        if orientation is not None:
            numbers += [f"{v:.9f}" for v in np.asarray(orientation, dtype=float)]
        return with_checksum(f"OK {seq} {self.status} {t_s:.6f} {' '.join(numbers)} "
                             f"{sigma_m:.3e}")

    def _serve(self, connection: socket.socket) -> None:
        with self._lock:
            self._connections.add(connection)
        connection.settimeout(POLL_S)
        buffer = bytearray()
        try:
            while not self._stopping.is_set():
                end = buffer.find(b"\n")
                if end < 0:
                    if len(buffer) > MAX_LINE_BYTES:
                        buffer.clear()
                        connection.sendall(with_checksum(f"ERR - {BAD_REQUEST} line too long"))
                    try:
                        data = connection.recv(4096)
                    except socket.timeout:
                        continue
                    if not data:
                        return
                    buffer += data
                    continue
                line = bytes(buffer[:end]).removesuffix(b"\r")
                del buffer[:end + 1]
                if len(line) > MAX_LINE_BYTES:  # the protocol's limit holds for a terminated line too
                    connection.sendall(with_checksum(f"ERR - {BAD_REQUEST} line too long"))
                    continue
                reply = self.reply_to(line)
                if self.silent:
                    continue
                if self._injected:
                    reply = self._injected.popleft()
                if self.reply_delay_s:
                    self.clock.sleep(self.reply_delay_s)
                connection.sendall(reply)
        except OSError:
            return  # the client went away, or drop_connections() cut it
        finally:
            with self._lock:
                self._connections.discard(connection)
            connection.close()
