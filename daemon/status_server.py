"""The status page and its JSON API (docs/api.md), served read-only by ``cellcal daemon``.

The standard library's :class:`http.server.ThreadingHTTPServer` in a thread of its own: nothing
to install on a cell PC, and the load is a few readers. It never touches the service's
objects: the service's live state comes from a callable ``status()`` (``Service.status()``,
a fresh dict built without the run's or the panel's locks), the store's rows from a read-only
SQLite connection of each request's own (:mod:`.status_api`), the files from STATE/reports only.

Bounded: GET and HEAD only (405), no request body (413), a request line of at most
:data:`MAX_REQUEST_LINE` bytes (414) and headers of at most :data:`MAX_HEADER_BYTES` (431), at
most ``max_connections`` connections at once (503 beyond), a token bucket per client address
of ``rate_per_s`` requests a second, as many in a burst (429), :data:`TIMEOUT_S` on every
socket read and write, :data:`MAX_CONNECTION_S` for a connection's whole life. Every refusal is a 4xx (or the 503) with a small JSON body
``{"error": {"status", "message"}}``, changes nothing, and logs at most one line per client a
minute.
"""
from __future__ import annotations

import ipaddress
import json
import logging
import re
import shutil
import socket
import threading
import time
from http import HTTPStatus
from http.client import LineTooLong
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from cellcal.daemon import status_api
from cellcal.daemon.store import StoreError

log = logging.getLogger("cellcal.daemon.status")

MAX_REQUEST_LINE = 2048  # bytes, the method and the HTTP version included (414 beyond)
MAX_HEADER_BYTES = 8192  # all header lines together (431 beyond)
TIMEOUT_S = 5.0  # each socket read or write of a connection: a slow or idle client lets go of its thread
MAX_CONNECTION_S = 30.0  # a connection's whole life: one that drips bytes (slowloris) is cut off then
LOG_EVERY_S = 60.0  # at most one log line per client address this often about its bad requests
STATIC_FILES = {"app.js": "text/javascript; charset=utf-8", "style.css": "text/css; charset=utf-8"}
# report files: the types the service writes there (anything else is served as a download, never run)
REPORT_TYPES = {".html": "text/html; charset=utf-8", ".png": "image/png", ".svg": "image/svg+xml",
                ".json": "application/json", ".csv": "text/csv; charset=utf-8", ".txt": "text/plain; charset=utf-8"}
SAFE_REPORT_PATH = re.compile(r"[A-Za-z0-9_\-]+(?:\.[A-Za-z0-9_\-]+)*(?:/[A-Za-z0-9_\-]+(?:\.[A-Za-z0-9_\-]+)*)*")
PAGE_CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; connect-src 'self'; "
            "frame-ancestors 'none'; base-uri 'none'; form-action 'none'")
# the run reports are the service's own pages, with inline style attributes and no script
REPORT_CSP = ("default-src 'none'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
              "frame-ancestors 'self'; base-uri 'none'; form-action 'none'")
ERROR_CSP = "default-src 'none'; frame-ancestors 'none'"


class StatusPageError(OSError):
    """The status page cannot be served: its address is taken or is none of this PC's (an
    OSError, as the bind's own failure is, with a message naming the address and the fix)."""


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


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    block_on_close = False  # stop() does not wait for a slow client
    allow_reuse_address = True
    request_queue_size = 16

    def __init__(self, address, handler, owner: "StatusServer"):
        self.owner = owner
        self.slots = threading.BoundedSemaphore(owner.max_connections)
        self.open_since: dict[socket.socket, float] = {}  # the connections being served, since when
        self.open_lock = threading.Lock()
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        super().__init__(address, handler)

    def process_request(self, request, client_address):
        if not self.slots.acquire(blocking=False):
            self.owner.note_bad(client_address[0], "503: too many connections")
            _refuse_busy(request, self.owner.max_connections)
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


class _Handler(BaseHTTPRequestHandler):
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
        if not self.server.owner.buckets.take(self.client_address[0]):  # every request counts, bad ones too
            rate = self.server.owner.rate_per_s
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
        except _Unavailable as exc:
            self.send_error(HTTPStatus.SERVICE_UNAVAILABLE, f"the results store cannot be read now: {exc}",
                            headers={"Retry-After": "5"})
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
        self.server.owner.note_bad(self.client_address[0], f"{code}: {message}")
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

    def _common_headers(self, csp: str) -> None:
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("Content-Security-Policy", csp)

    # -- routing ---------------------------------------------------------------------------------------

    def route(self) -> None:
        url = urlsplit(self.path)
        path = url.path
        if path in ("/", "/index.html"):
            return self._static("index.html", "text/html; charset=utf-8")
        if path.startswith("/static/"):
            name = path[len("/static/"):]
            if name not in STATIC_FILES:
                return self.send_error(HTTPStatus.NOT_FOUND, "no such file")
            return self._static(name, STATIC_FILES[name])
        if path.startswith("/reports/"):
            return self._report(path[len("/reports/"):])
        if path == "/api/v1" or path.startswith("/api/v1/"):
            return self._api(path[len("/api/v1"):].rstrip("/") or "/", url.query)
        self.send_error(HTTPStatus.NOT_FOUND, "no such page: the status page is at /, the API under /api/v1/")

    def _api(self, path: str, query: str) -> None:
        owner = self.server.owner
        parts = path.strip("/").split("/")
        if path == "/state":
            return self._json(status_api.state(owner.current_status()))
        if parts[0] not in ("runs", "tools") or len(parts) > 3:
            return self.send_error(HTTPStatus.NOT_FOUND, f"no such endpoint /api/v1{path[:100]} (docs/api.md)")
        with owner.store() as store:
            if parts == ["runs"]:
                limit = _limit(query)
                if limit is None:
                    return self.send_error(HTTPStatus.BAD_REQUEST, "limit must be a whole number from "
                                           f"{status_api.RUNS_LIMIT[0]} to {status_api.RUNS_LIMIT[1]}")
                return self._json(status_api.runs(store, limit, owner.state_dir))
            if parts[0] == "runs" and len(parts) == 2:
                if not parts[1].isdigit() or len(parts[1]) > 18:
                    return self.send_error(HTTPStatus.BAD_REQUEST, "a run id is a whole number (/api/v1/runs/12)")
                detail = status_api.run_detail(store, int(parts[1]), owner.state_dir)
                if detail is None:
                    return self.send_error(HTTPStatus.NOT_FOUND, f"no run {int(parts[1])} in the store")
                return self._json(detail)
            if parts == ["tools"]:
                return self._json(status_api.tools(store, owner.current_status(quiet=True), owner.tool_names()))
            if parts[0] == "tools" and len(parts) == 3 and parts[2] == "history":
                tool_id = status_api.valid_tool_id(parts[1])
                if tool_id is None:
                    return self.send_error(HTTPStatus.BAD_REQUEST, "a tool id is a whole number from 1 to 255 "
                                           "(/api/v1/tools/1/history)")
                names = owner.tool_names()
                known = tool_id in names or (store is not None and tool_id in store.tool_ids())
                if not known:
                    return self.send_error(HTTPStatus.NOT_FOUND, f"no tool {tool_id}: neither the cell file nor "
                                           "the store knows it")
                return self._json(status_api.tool_history(store, tool_id, names.get(tool_id)))
        return self.send_error(HTTPStatus.NOT_FOUND, f"no such endpoint /api/v1{path[:100]} (docs/api.md)")

    # -- answers ---------------------------------------------------------------------------------------

    def _json(self, obj) -> None:
        body = json.dumps(obj, allow_nan=False, default=str).encode("utf-8")
        self._send(HTTPStatus.OK, "application/json", body, ERROR_CSP)

    def _send(self, status, content_type: str, body: bytes, csp: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Connection", "close")
        self._common_headers(csp)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _static(self, name: str, content_type: str) -> None:
        body = self.server.owner.page_file(name)
        self._send(HTTPStatus.OK, content_type, body, PAGE_CSP)

    def _report(self, rel: str) -> None:
        """A file under STATE/reports, never anything else: the raw path must be plain names
        (letters, digits, ``_ - .``, no ``..``, no percent-encoding, no backslash, no NUL), and
        the file it resolves to, symbolic links followed, must lie in that folder."""
        target = self.server.owner.report_file(rel)
        if target is None:
            return self.send_error(HTTPStatus.NOT_FOUND, "no such report")
        content_type = REPORT_TYPES.get(target.suffix.lower(), "application/octet-stream")
        try:
            f = open(target, "rb")
        except OSError:
            return self.send_error(HTTPStatus.NOT_FOUND, "no such report")
        with f:
            size = Path(f.name).stat().st_size
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(size))
            self.send_header("Connection", "close")
            self._common_headers(REPORT_CSP)
            self.end_headers()
            if self.command != "HEAD":
                shutil.copyfileobj(f, self.wfile, 1 << 16)


def _limit(query: str) -> int | None:
    """?limit=N of /api/v1/runs (default 20), None when it is not a whole number in range or
    the query holds anything else."""
    try:
        fields = parse_qs(query, keep_blank_values=True, strict_parsing=bool(query), max_num_fields=4)
    except ValueError:
        return None
    if set(fields) - {"limit"} or len(fields.get("limit", [])) > 1:
        return None
    text = fields.get("limit", [str(status_api.RUNS_DEFAULT)])[0]
    if not text.isdigit() or len(text) > 6:
        return None
    n = int(text)
    low, high = status_api.RUNS_LIMIT
    return n if low <= n <= high else None


class _StoreContext:
    def __init__(self, state_dir: Path):
        self.state_dir, self.store = state_dir, None

    def __enter__(self):
        try:
            self.store = status_api.open_store(self.state_dir)
        except StoreError as exc:
            raise _Unavailable(str(exc)) from None
        return self.store

    def __exit__(self, *exc):
        if self.store is not None:
            self.store.close()
        return False


class _Unavailable(RuntimeError):
    pass


class StatusServer:
    """The status page and API of one service: ``start()``, ``url``, ``stop()``.

    `status`: a callable returning the service's state as a fresh dict (``Service.status()``);
    `state_dir`: the service's state folder (its store and STATE/reports); `spec`: the cell
    file's ``status_page`` (``enabled``, ``host``, ``port``, ``max_connections``, ``rate_per_s``);
    `tool_names`: id -> name of the cell's tools (else read from the cell file ``status()["cell"]["path"]``
    names, when it names one)."""

    def __init__(self, status, state_dir: str | Path, spec, tool_names: dict[int, str] | None = None):
        self.status = status
        self._fixed_names = None if tool_names is None else {int(k): str(v) for k, v in tool_names.items()}
        self.state_dir = Path(state_dir)
        self.enabled = bool(getattr(spec, "enabled", True))
        self.host = str(spec.host)
        self.port = int(spec.port)
        self.max_connections = int(spec.max_connections)
        self.rate_per_s = float(spec.rate_per_s)
        if self.max_connections < 1 or self.rate_per_s <= 0:
            raise ValueError("status_page: max_connections must be at least 1 and rate_per_s above 0")
        self.buckets = _TokenBuckets(self.rate_per_s)
        self._server: _Server | None = None
        self._thread: threading.Thread | None = None
        self._logged: dict[str, float] = {}
        self._log_lock = threading.Lock()
        self._names: tuple[object, dict[int, str]] = (None, {})
        self._page: dict[str, bytes] = {}

    # -- life ------------------------------------------------------------------------------------------

    def start(self) -> "StatusServer":
        """Listen and serve in a thread of its own; returns once listening. StatusPageError naming
        the address when it cannot be had (the port taken, an address not of this PC). Does
        nothing when the spec says ``enabled: false``."""
        if not self.enabled or self._server is not None:
            return self
        for name in ("index.html", *STATIC_FILES):
            self.page_file(name)  # a broken install fails here, not at the first browser
        try:
            self._server = _Server((self.host, self.port), _Handler, self)
        except OSError as exc:
            raise StatusPageError(f"the status page cannot listen on {self.host}:{self.port}: "
                                  f"{exc.strerror or exc}; free that port, or set status_page: {{port: ...}} (or "
                                  "enabled: false) in the cell file") from None
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="cellcal-status-page", daemon=True)
        self._thread.start()
        return self

    @property
    def address(self) -> tuple[str, int] | None:
        return None if self._server is None else self._server.server_address[:2]

    @property
    def url(self) -> str | None:
        """``http://HOST:PORT/`` while serving (the port bound, when the spec's is 0), else None."""
        if self._server is None:
            return None
        host, port = self.address
        return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"

    def stop(self) -> None:
        """Stop serving and let go of the port; at once, whatever the clients do. Idempotent."""
        server, self._server = self._server, None
        if server is None:
            return
        server.shutdown()
        server.server_close()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
        return False

    # -- what the handler uses -------------------------------------------------------------------------

    def current_status(self, quiet: bool = False) -> dict:
        try:
            status = self.status()
        except Exception as exc:  # the service's own fault must not end the request's thread quietly
            if not quiet:
                log.warning("status page: the service's status could not be read: %s", exc)
            return {"state": "unknown", "reason": "the service's status could not be read"}
        return status if isinstance(status, dict) else {"state": "unknown"}

    def store(self):
        return _StoreContext(self.state_dir)

    def tool_names(self) -> dict[int, str]:
        """id -> name of the tools in the running service's cell file (read once per change of it)."""
        if self._fixed_names is not None:
            return self._fixed_names
        cell = (self.current_status(quiet=True).get("cell") or {})
        path = cell.get("path") if isinstance(cell, dict) else None
        if not path:
            return {}
        try:
            key = (path, Path(path).stat().st_mtime_ns)
        except OSError:
            return self._names[1]
        if self._names[0] != key:
            from cellcal.daemon.cells import load_cell
            try:
                tools = getattr(load_cell(path), "tools", None) or {}
                self._names = (key, {int(i): t.name for i, t in tools.items()})
            except Exception:  # a file edited into something unreadable: keep what was known
                self._names = (key, self._names[1])
        return self._names[1]

    def page_file(self, name: str) -> bytes:
        if name not in self._page:
            self._page[name] = resources.files("cellcal.daemon").joinpath("status_page", name).read_bytes()
        return self._page[name]

    def report_file(self, rel: str) -> Path | None:
        if len(rel) > 512 or not SAFE_REPORT_PATH.fullmatch(rel):
            return None
        base = (self.state_dir / status_api.REPORTS).resolve()
        try:
            target = (base / rel).resolve(strict=True)
        except (OSError, RuntimeError):
            return None
        if not target.is_relative_to(base) or not target.is_file():
            return None
        return target

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
