"""The status page and its JSON API (docs/api.md), served read-only by ``cellcal daemon``.

The standard library's :class:`http.server.ThreadingHTTPServer` in a thread of its own: nothing
to install on a cell PC, and the load is a few readers. It never touches the service's
objects: the service's live state comes from a callable ``status()`` (``Service.status()``,
a fresh dict built without the run's or the panel's locks), the store's rows from a read-only
SQLite connection of each request's own (:mod:`.status_api`), the files from STATE/reports only.
Here are the routes and the server's life; the bounds every request is held to (sizes, time,
connections, rate, the refusals' JSON and log) are :mod:`.status_http`'s.
"""
from __future__ import annotations

import json
import logging
import re
import shutil
import threading
from dataclasses import asdict
from http import HTTPStatus
from importlib import resources
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from cellcal.daemon import status_api
from cellcal.daemon.status_http import ERROR_CSP, BoundedHandler, BoundedServer, Guard, Unavailable
from cellcal.daemon.store import StoreError

log = logging.getLogger("cellcal.daemon.status")

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


class StatusPageError(OSError):
    """The status page cannot be served: its address is taken or is none of this PC's (an
    OSError, as the bind's own failure is, with a message naming the address and the fix)."""


class _Handler(BoundedHandler):
    """The status page's routes: the page, its static files, the run reports and the API."""

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
        if query and parts != ["runs"]:  # only the run list takes one (limit); docs/api.md
            return self.send_error(HTTPStatus.BAD_REQUEST, f"/api/v1{path[:100]} takes no query parameters "
                                   "(only /api/v1/runs takes limit)")
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
                if not parts[1].isdigit():
                    return self.send_error(HTTPStatus.BAD_REQUEST, "a run id is a whole number (/api/v1/runs/12)")
                if len(parts[1]) > 18:  # beyond SQLite's integers, and any store's runs
                    return self.send_error(HTTPStatus.NOT_FOUND, f"no run {parts[1][:30]}: a run id has at most 18 "
                                           "digits")
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
                return self._json(status_api.tool_history(store, tool_id, names.get(tool_id),
                                                          owner.tool_bands().get(tool_id)))
        return self.send_error(HTTPStatus.NOT_FOUND, f"no such endpoint /api/v1{path[:100]} (docs/api.md)")

    # -- answers ---------------------------------------------------------------------------------------

    def _json(self, obj) -> None:
        body = json.dumps(obj, allow_nan=False, default=str).encode("utf-8")
        self._send(HTTPStatus.OK, "application/json", body, ERROR_CSP)

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
            raise Unavailable(f"the results store cannot be read now: {exc}") from None
        return self.store

    def __exit__(self, *exc):
        if self.store is not None:
            self.store.close()
        return False


class StatusServer:
    """The status page and API of one service: ``start()``, ``url``, ``stop()``.

    `status`: a callable returning the service's state as a fresh dict (``Service.status()``);
    `state_dir`: the service's state folder (its store and STATE/reports); `spec`: the cell
    file's ``status_page`` (``enabled``, ``host``, ``port``, ``max_connections``, ``rate_per_s``);
    `tool_names`: id -> name of the cell's tools, `tool_bands`: id -> the tool's bands (``Bands`` as a
    dict: what the drift plot draws) (else both read from the cell file ``status()["cell"]["path"]``
    names, when it names one)."""

    def __init__(self, status, state_dir: str | Path, spec, tool_names: dict[int, str] | None = None,
                 tool_bands: dict[int, dict] | None = None):
        self.status = status
        self._fixed_names = None if tool_names is None else {int(k): str(v) for k, v in tool_names.items()}
        self._fixed_bands = None if tool_bands is None else {int(k): dict(v) for k, v in tool_bands.items()}
        self.state_dir = Path(state_dir)
        self.enabled = bool(getattr(spec, "enabled", True))
        self.host = str(spec.host)
        self.port = int(spec.port)
        max_connections, rate_per_s = int(spec.max_connections), float(spec.rate_per_s)
        if max_connections < 1 or rate_per_s <= 0:
            raise ValueError("status_page: max_connections must be at least 1 and rate_per_s above 0")
        self.guard = Guard(max_connections, rate_per_s)
        self._server: BoundedServer | None = None
        self._thread: threading.Thread | None = None
        self._names: tuple[object, dict[int, str], dict[int, dict]] = (None, {}, {})
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
            self._server = BoundedServer((self.host, self.port), _Handler, self, self.guard)
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
        return self._cell_tools()[0]

    def tool_bands(self) -> dict[int, dict]:
        """id -> the bands (and drift alarm) of the tools in the running service's cell file."""
        if self._fixed_bands is not None:
            return self._fixed_bands
        return self._cell_tools()[1]

    def _cell_tools(self) -> tuple[dict[int, str], dict[int, dict]]:
        cell = (self.current_status(quiet=True).get("cell") or {})
        path = cell.get("path") if isinstance(cell, dict) else None
        if not path:
            return {}, {}
        try:
            key = (path, Path(path).stat().st_mtime_ns)
        except OSError:
            return self._names[1:]
        if self._names[0] != key:
            from cellcal.daemon.cells import load_cell
            try:
                tools = getattr(load_cell(path), "tools", None) or {}
                self._names = (key, {int(i): t.name for i, t in tools.items()},
                               {int(i): asdict(t.bands) for i, t in tools.items()})
            except Exception:  # a file edited into something unreadable: keep what was known
                self._names = (key, *self._names[1:])
        return self._names[1:]

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

