"""The hardened HTTP layer under the status page (:mod:`.status_server` holds its routes).

The standard library's :class:`http.server.ThreadingHTTPServer`, bounded: GET and HEAD only
(405), no request body (413), a request line of at most :data:`MAX_REQUEST_LINE` bytes (414)
and headers of at most :data:`MAX_HEADER_BYTES` (431), at most ``max_connections`` connections
at once (503 beyond), a token bucket per client address of ``rate_per_s`` requests a second, as
many in a burst (429), :data:`TIMEOUT_S` on every socket read and write, :data:`MAX_CONNECTION_S`
for a connection's whole life. Every refusal is a 4xx (or a 503) with a small JSON body
``{"error": {"status", "message"}}``, changes nothing, and logs at most one line per client a
minute (:class:`Guard`). Served beyond loopback only when asked, and then said (:func:`exposure_warning`).
"""
from __future__ import annotations

import ipaddress
import json
import logging
import socket
import threading
import time
from http import HTTPStatus
from http.client import LineTooLong
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

log = logging.getLogger("cellcal.daemon.status")

MAX_REQUEST_LINE = 2048  # bytes, the method and the HTTP version included (414 beyond)
MAX_HEADER_BYTES = 8192  # all header lines together (431 beyond)
TIMEOUT_S = 5.0  # each socket read or write of a connection: a slow or idle client lets go of its thread
MAX_CONNECTION_S = 30.0  # a connection's whole life: one that drips bytes (slowloris) is cut off then
LOG_EVERY_S = 60.0  # at most one log line per client address this often about its bad requests
ERROR_CSP = "default-src 'none'; frame-ancestors 'none'"


class Unavailable(RuntimeError):
    """What a route raises when what it answers from cannot be read now: a 503, the message as given."""


def is_loopback(host: str) -> bool:
    """Whether `host` (an address or ``localhost``) is only reachable from this PC."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def exposure_warning(host: str, port: int) -> str | None:
    """The log line for a status page served beyond this PC, or None on a loopback address."""
    return None if is_loopback(host) else f"the status page is served on {host}:{port}, beyond this PC"


class _TokenBuckets:
    """One token bucket per client address: `rate` tokens a second, at most `rate` kept (the
    burst). Addresses idle long enough to have a full bucket are forgotten (bounded memory)."""

    def __init__(self, rate: float):
        self.rate = float(rate)
        self.capacity = max(1.0, self.rate)
        self._buckets: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def take(self, client: str) -> bool:
        now = time.monotonic()
        with self._lock:
            tokens, at = self._buckets.get(client, (self.capacity, now))
            tokens = min(self.capacity, tokens + (now - at) * self.rate)
            allowed = tokens >= 1.0
            self._buckets[client] = (tokens - 1.0 if allowed else tokens, now)
            if len(self._buckets) > 1024:
                full_after = self.capacity / self.rate
                self._buckets = {c: (t, a) for c, (t, a) in self._buckets.items() if now - a < full_after}
            return allowed


class _BoundedReader:
    """The connection's input as parse_request reads the headers: LineTooLong (so a 431) once
    more than `budget` bytes have been read."""

    def __init__(self, raw, budget: int):
        self.raw, self.left = raw, budget

    def readline(self, limit: int = -1) -> bytes:
        want = self.left + 1 if limit < 0 else min(limit, self.left + 1)
        line = self.raw.readline(want)
        self.left -= len(line)
        if self.left < 0:
            raise LineTooLong(f"headers longer than {MAX_HEADER_BYTES} bytes")
        return line

    def __getattr__(self, name):
        return getattr(self.raw, name)


class Guard:
    """The bounds of one server's clients: at most `max_connections` connections at once, a
    token bucket of `rate_per_s` requests a second per client address, and one log line per
    client a minute about its refused requests."""

    def __init__(self, max_connections: int, rate_per_s: float):
        self.max_connections, self.rate_per_s = max_connections, rate_per_s
        self.buckets = _TokenBuckets(rate_per_s)
        self._logged: dict[str, float] = {}
        self._log_lock = threading.Lock()

    def note_bad(self, client: str, what: str) -> None:
        """One log line per client a minute about its refused requests."""
        now = time.monotonic()
        with self._log_lock:
            if now - self._logged.get(client, -LOG_EVERY_S) < LOG_EVERY_S:
                return
            self._logged[client] = now
            if len(self._logged) > 1024:
                self._logged = {c: t for c, t in self._logged.items() if now - t < LOG_EVERY_S}
        log.info("status page: refused a request from %s (%s); more from it this minute are not logged",
                 client, what[:200])


class BoundedServer(ThreadingHTTPServer):
    """The threading server held to its `guard`; `owner` is for the handler's routes."""

    daemon_threads = True
    block_on_close = False  # stop() does not wait for a slow client
    allow_reuse_address = True
    request_queue_size = 16

    def __init__(self, address, handler, owner, guard: Guard):
        self.owner, self.guard = owner, guard
        self.slots = threading.BoundedSemaphore(guard.max_connections)
        self.open_since: dict[socket.socket, float] = {}  # the connections being served, since when
        self.open_lock = threading.Lock()
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        super().__init__(address, handler)

    def process_request(self, request, client_address):
        if not self.slots.acquire(blocking=False):
            self.guard.note_bad(client_address[0], "503: too many connections")
            _refuse_busy(request, self.guard.max_connections)
            self.shutdown_request(request)
            return
        with self.open_lock:
            self.open_since[request] = time.monotonic()
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._done(request)
            raise

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._done(request)

    def _done(self, request) -> None:
        with self.open_lock:
            self.open_since.pop(request, None)
        self.slots.release()

    def service_actions(self):
        """Every poll of the accepting thread: cut off the connections older than MAX_CONNECTION_S
        (their handler's read or write then ends at once, and its slot is free)."""
        limit = time.monotonic() - MAX_CONNECTION_S
        with self.open_lock:
            old = [r for r, since in self.open_since.items() if since < limit]
        for request in old:
            try:
                request.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def handle_error(self, request, client_address):  # a reset connection: one line, no traceback on stderr
        log.debug("status page: connection from %s ended with an error", client_address[0], exc_info=True)


def _refuse_busy(request: socket.socket, limit: int) -> None:
    """A 503 written straight on the socket, by the accepting thread (so never blocking it long)."""
    body = json.dumps({"error": {"status": 503, "message": f"too many connections (at most {limit}); try again"}})
    head = (f"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\nContent-Length: {len(body)}\r\n"
            "Retry-After: 1\r\nCache-Control: no-store\r\nX-Content-Type-Options: nosniff\r\nConnection: close\r\n\r\n")
    try:
        request.settimeout(0.5)
        request.sendall(head.encode("ascii") + body.encode("utf-8"))
    except OSError:
        pass


class BoundedHandler(BaseHTTPRequestHandler):
    """Reads one request within the bounds and refuses what is not a plain GET or HEAD; the
    answer is :meth:`route`'s, a subclass's."""

    server_version = "cellcal"
    sys_version = ""
    protocol_version = "HTTP/1.0"  # one request per connection: no idle keep-alive holds a slot
    default_request_version = "HTTP/1.0"  # an answer to anything, garbage included, has a status line
    timeout = TIMEOUT_S
    error_content_type = "application/json"

    # -- the request, bounded ---------------------------------------------------------------------------

    def handle_one_request(self):
        self.close_connection = True
        try:
            self.raw_requestline = self.rfile.readline(MAX_REQUEST_LINE + 1)
        except (TimeoutError, OSError):
            return
        if not self.raw_requestline:
            return
        self.requestline, self.request_version, self.command = "", "HTTP/1.0", ""
        if not self.server.guard.buckets.take(self.client_address[0]):  # every request counts, bad ones too
            rate = self.server.guard.rate_per_s
            self.send_error(HTTPStatus.TOO_MANY_REQUESTS, f"more than {rate:g} requests a second from "
                            f"{self.client_address[0]}; slow down", headers={"Retry-After": "1"})
            return
        if len(self.raw_requestline) > MAX_REQUEST_LINE:
            self.send_error(HTTPStatus.REQUEST_URI_TOO_LONG, f"request line longer than {MAX_REQUEST_LINE} bytes")
            return
        raw, self.rfile = self.rfile, _BoundedReader(self.rfile, MAX_HEADER_BYTES)
        try:
            parsed = self.parse_request()
        except (TimeoutError, OSError):
            return
        finally:
            self.rfile = raw
        if not parsed:  # parse_request sent the error (400, 431, 505)
            return
        self.close_connection = True
        if len(self.requestline.split()) != 3:  # HTTP/0.9: no version, no headers
            self.send_error(HTTPStatus.BAD_REQUEST, "not an HTTP/1.x request line (METHOD PATH HTTP/1.1)")
            return
        if self.command not in ("GET", "HEAD"):
            self.send_error(HTTPStatus.METHOD_NOT_ALLOWED, f"{self.command[:16]} is not served: the status page "
                            "is read-only (GET and HEAD only)", headers={"Allow": "GET, HEAD"})
            return
        if self.headers.get("Transfer-Encoding"):
            self.send_error(HTTPStatus.BAD_REQUEST, "a request body is not taken (Transfer-Encoding)")
            return
        length = self.headers.get("Content-Length", "0").strip()
        if not length.isdigit():
            self.send_error(HTTPStatus.BAD_REQUEST, "Content-Length is not a whole number")
            return
        if int(length):
            self.send_error(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, "a request body is not taken: GET and HEAD only")
            return
        try:
            self.route()
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            pass
        except Unavailable as exc:
            self.send_error(HTTPStatus.SERVICE_UNAVAILABLE, str(exc), headers={"Retry-After": "5"})
        except Exception:  # a bug here must not end the server thread nor show a traceback to the client
            log.exception("status page: %s %s failed", self.command, self.path[:200])
            self.send_error(HTTPStatus.INTERNAL_SERVER_ERROR, "the status page failed on this request (see the log)")
        try:
            self.wfile.flush()
        except OSError:
            pass

    def send_error(self, code, message=None, explain=None, headers: dict | None = None):
        """Every refusal: the status and a small JSON body; one log line per client a minute."""
        code = int(code)
        message = message or HTTPStatus(code).phrase
        self.server.guard.note_bad(self.client_address[0], f"{code}: {message}")
        body = json.dumps({"error": {"status": code, "message": message}}).encode("utf-8")
        self.close_connection = True
        try:
            self.send_response(code, HTTPStatus(code).phrase)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Connection", "close")
            for name, value in (headers or {}).items():
                self.send_header(name, value)
            self._common_headers(ERROR_CSP)
            self.end_headers()
            if getattr(self, "command", "") != "HEAD":
                self.wfile.write(body)
        except OSError:
            pass

    def log_message(self, format, *args):  # no access log on stderr: refusals are logged by note_bad
        pass

    def route(self) -> None:
        """Answer the request read (its checks passed): a subclass's routes."""
        raise NotImplementedError

    def _common_headers(self, csp: str) -> None:
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("Content-Security-Policy", csp)

    def _send(self, status, content_type: str, body: bytes, csp: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Connection", "close")
        self._common_headers(csp)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

