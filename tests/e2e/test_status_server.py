"""The status page and JSON API (docs/api.md) over plain HTTP, as a PLC gateway or a script reads it.

The store is a real one: the in-process simulated cell runs a calibration and a check through
the service, with the run reports and the trend page the daemon writes. A StatusServer serves
that state folder on a loopback address of the test's own; the client is a raw socket (so a
request goes out exactly as written, hostile ones included) or urllib. Every documented
endpoint, the JSON shapes, the refusals (405, 413, 400, 431, 414, 404), the path-escape
attempts, the connection and rate limits, and that nothing in the store changed.
"""
from __future__ import annotations

import json
import logging
import select
import socket
import sqlite3
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import pytest

from support import loopback
from support.service_panel import press
from cellcal.daemon import status_http, status_server
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.daemon.service import ResultCode, Service
from cellcal.daemon.status_server import StatusPageError, StatusServer
from cellcal.daemon.store import Store
from support.cell_edits import edited_cell
from cellcal.reports.run import write_run_report
from cellcal.reports.trend import write_trend_page

SECRET = "cellcal-test-secret-outside-the-reports-folder"


def spec(**over):
    values = dict(enabled=True, host="127.0.0.1", port=0, max_connections=8, rate_per_s=1000.0)
    values.update(over)
    return SimpleNamespace(**values)


@pytest.fixture(scope="module")
def cell_run(tmp_path_factory):
    """A state folder as the daemon leaves it after a tcp-npoint (written back) and a tcp-check:
    the store, the run reports, tool 1's trend page; plus a secret file beside it and symlinks
    inside STATE/reports pointing at it and at the state folder (what no request may reach)."""
    root = tmp_path_factory.mktemp("status")
    folder = root / "state"
    # the check on [beams] as installed, said so (beam_std_mm): no tcp-laser here to find them
    cell = load_cell(edited_cell(root, "sim", {"tcp_check": {"beam_std_mm": 0.5}}))
    with open_drivers(cell) as drivers:
        store = Store.open(folder)
        service = Service(cell, drivers, store, out_dir=folder / "datasets",
                          report=lambda run_id, result, st, ending: write_run_report(
                              folder / "reports", run_id, result, tool_id=st.run(run_id).tool_id, ending=ending),
                          trend=lambda tool_id, trend: write_trend_page(folder / "reports" / f"tool-{tool_id}", trend))
        outcomes = []
        for routine in ("tcp-npoint", "tcp-check"):
            outcomes.append(press(service, drivers.panel, routine))
        store.close()
    assert [o.code for o in outcomes] == [ResultCode.OK, ResultCode.OK], [o.reason for o in outcomes]
    (root / "secret.txt").write_text(SECRET)
    (folder / "reports" / "leak.txt").symlink_to(root / "secret.txt")
    (folder / "reports" / "up").symlink_to(folder)
    return folder, service


@pytest.fixture(scope="module")
def cell_state(cell_run):
    return cell_run[0]


STATUS = {"state": "idle", "run_id": None, "routine": None, "progress": None, "since": 1.0e9, "reason": None,
          "result_code": None, "mounted_tool": {"id": 1, "name": "tool"},
          "devices": {"robot": "ok", "panel": "ok", "trigger": "ok"}, "cell": {"name": "sim", "path": None}}


@pytest.fixture(scope="module")
def server(cell_state):
    with loopback.held() as host:
        srv = StatusServer(status=lambda: dict(STATUS), state_dir=cell_state, spec=spec(host=host)).start()
        try:
            yield srv
        finally:
            srv.stop()


def request(srv_or_address, raw: bytes, timeout: float = 5.0):
    """(status, headers, body) of one request sent exactly as `raw`; the server closes the connection."""
    address = srv_or_address.address if isinstance(srv_or_address, StatusServer) else srv_or_address
    with socket.create_connection(address, timeout=timeout) as s:
        s.sendall(raw)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:])}
    return int(lines[0].split()[1]), headers, body


def get(srv, path: str, method: str = "GET", extra: str = ""):
    return request(srv, f"{method} {path} HTTP/1.1\r\nHost: cell\r\n{extra}\r\n".encode("latin-1"))


def get_json(srv, path: str):
    status, headers, body = get(srv, path)
    assert status == 200, body
    assert headers["content-type"] == "application/json"
    assert headers["cache-control"] == "no-store" and headers["x-content-type-options"] == "nosniff"
    return json.loads(body)


def store_contents(folder: Path) -> list[str]:
    db = sqlite3.connect(f"file:{folder / 'cellcal.db'}?mode=ro", uri=True)
    try:
        return list(db.iterdump())
    finally:
        db.close()


# -- every documented endpoint ----------------------------------------------------------------------


RUN_KEYS = {"id", "routine", "cell", "tool_id", "started_at", "finished_at", "state", "result_code", "result_name",
            "reason", "verdict", "passed_gates", "written_back", "report_url"}


def test_state_is_the_service_s_status_with_the_api_version(server):
    state = get_json(server, "/api/v1/state")
    assert {k: state[k] for k in STATUS} == STATUS
    assert state["api"] == 1 and abs(state["time"] - time.time()) < 60  # the server's clock, not a stale value


def test_runs_and_one_run_are_what_the_store_holds(server, cell_state):
    runs = get_json(server, "/api/v1/runs")["runs"]
    store = Store.open(cell_state, create=False)
    try:
        rows = store.runs(50)
        assert [r["id"] for r in runs] == [r.id for r in rows] == [2, 1]  # newest first
        for api, row in zip(runs, rows):
            assert set(api) == RUN_KEYS
            assert (api["routine"], api["state"], api["result_code"]) == (row.routine, row.state, row.result_code)
        assert runs[1]["result_name"] == "OK" and runs[1]["written_back"] is True
        assert runs[0]["routine"] == "tcp-check" and runs[0]["verdict"] in ("ok", "corrected")
        assert get_json(server, "/api/v1/runs?limit=1")["runs"] == runs[:1]
        one = get_json(server, "/api/v1/runs/1")
        assert set(RUN_KEYS) | {"result_meaning", "states", "gates", "parameters", "result", "tool_frames"} == set(one)
        assert [s["state"] for s in one["states"]] == [s for _, s, _ in store.states(1)]
        assert one["gates"] == store.gates(1) and one["gates"]
        assert one["result"]["routine"] == "tcp-npoint"
        assert [f["action"] for f in one["tool_frames"]] == ["write"]
    finally:
        store.close()


def test_tools_and_a_tool_s_history_with_its_drift_trend(server):
    [tool] = get_json(server, "/api/v1/tools")["tools"]
    assert (tool["id"], tool["name"], tool["mounted"]) == (1, "tool", True)
    assert tool["last_frame"]["action"] == "write" and tool["history_url"] == "/api/v1/tools/1/history"
    history = get_json(server, tool["history_url"])
    assert history["tool_id"] == 1 and len(history["tool_frames"]) >= 1
    points = history["trend"]["points"]
    assert [p["run_id"] for p in points] == [1, 2]
    # the calibration is where the trend starts: its own change is zero
    assert points[0]["since_first_calibration"]["tip_mm"] == 0.0


def test_the_page_its_files_and_a_run_s_report(server):
    status, headers, body = get(server, "/")
    assert status == 200 and headers["content-type"].startswith("text/html")
    csp = headers["content-security-policy"]
    assert "default-src 'none'" in csp and "script-src 'self'" in csp and "connect-src 'self'" in csp
    assert b'src="/static/app.js"' in body and b"http" not in body.replace(b'href="/', b"").split(b"<body")[0]
    for name, kind in (("app.js", "text/javascript"), ("style.css", "text/css")):
        status, headers, body = get(server, f"/static/{name}")
        assert status == 200 and headers["content-type"].startswith(kind) and body
        assert b"https://" not in body and b"http://" not in body.replace(b"http://www.w3.org/2000/svg", b"")
    report = get_json(server, "/api/v1/runs/1")["report_url"]
    status, headers, body = get(server, report)
    assert status == 200 and headers["content-type"].startswith("text/html") and b"Run 1" in body
    status, headers, body = get(server, "/reports/tool-1/trend.html")
    assert status == 200 and b"trend.png" in body
    status, headers, _ = get(server, "/reports/tool-1/trend.png")
    assert status == 200 and headers["content-type"] == "image/png"


def test_head_answers_the_headers_without_a_body(server):
    status, headers, body = get(server, "/api/v1/runs", method="HEAD")
    assert status == 200 and int(headers["content-length"]) > 0 and body == b""


def test_urllib_reads_the_api_as_a_script_would(server):
    with urllib.request.urlopen(server.url + "api/v1/runs?limit=5", timeout=5) as answer:
        assert answer.status == 200 and len(json.load(answer)["runs"]) == 2


# -- refusals -----------------------------------------------------------------------------------------


BAD = [
    ("POST", b"POST /api/v1/runs HTTP/1.1\r\nHost: x\r\nContent-Length: 2\r\n\r\n{}", 405),
    ("PUT", b"PUT /api/v1/runs/1 HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n", 405),
    ("DELETE", b"DELETE /api/v1/runs/1 HTTP/1.1\r\nHost: x\r\n\r\n", 405),
    ("PATCH", b"PATCH /api/v1/tools/1/history HTTP/1.1\r\nHost: x\r\n\r\n", 405),
    ("OPTIONS", b"OPTIONS * HTTP/1.1\r\nHost: x\r\n\r\n", 405),
    ("a body on a GET", b"GET /api/v1/runs HTTP/1.1\r\nHost: x\r\nContent-Length: 5\r\n\r\nhello", 413),
    ("a chunked GET", b"GET /api/v1/runs HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n", 400),
    ("a bad Content-Length", b"GET / HTTP/1.1\r\nHost: x\r\nContent-Length: -1\r\n\r\n", 400),
    ("a huge header", b"GET / HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 20000 + b"\r\n\r\n", 431),
    ("many headers", b"GET / HTTP/1.1\r\n" + b"".join(b"X-%d: 1\r\n" % k for k in range(1000)) + b"\r\n", 431),
    ("a long URL", b"GET /api/v1/runs?" + b"a" * 5000 + b" HTTP/1.1\r\nHost: x\r\n\r\n", 414),
    ("garbage", b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03 hello\r\n\r\n", 400),
    ("a bad run id", b"GET /api/v1/runs/abc HTTP/1.1\r\n\r\n", 400),
    ("a negative run id", b"GET /api/v1/runs/-1 HTTP/1.1\r\n\r\n", 400),
    ("a run not there", b"GET /api/v1/runs/999 HTTP/1.1\r\n\r\n", 404),
    ("a bad tool id", b"GET /api/v1/tools/0/history HTTP/1.1\r\n\r\n", 400),
    ("a tool id too big", b"GET /api/v1/tools/300/history HTTP/1.1\r\n\r\n", 400),
    ("a tool nobody knows", b"GET /api/v1/tools/7/history HTTP/1.1\r\n\r\n", 404),
    ("limit 0", b"GET /api/v1/runs?limit=0 HTTP/1.1\r\n\r\n", 400),
    ("limit 501", b"GET /api/v1/runs?limit=501 HTTP/1.1\r\n\r\n", 400),
    ("limit not a number", b"GET /api/v1/runs?limit=ten HTTP/1.1\r\n\r\n", 400),
    ("limit twice", b"GET /api/v1/runs?limit=1&limit=2 HTTP/1.1\r\n\r\n", 400),
    ("an unknown parameter", b"GET /api/v1/runs?sort=id HTTP/1.1\r\n\r\n", 400),
    ("a parameter on the state", b"GET /api/v1/state?foo=1 HTTP/1.1\r\n\r\n", 400),
    ("a parameter on the tools", b"GET /api/v1/tools?foo=1 HTTP/1.1\r\n\r\n", 400),
    ("a parameter on a run", b"GET /api/v1/runs/1?limit=2 HTTP/1.1\r\n\r\n", 400),
    ("a run id of 26 digits", b"GET /api/v1/runs/12345678901234567890123456 HTTP/1.1\r\n\r\n", 404),
    ("an unknown endpoint", b"GET /api/v1/start HTTP/1.1\r\n\r\n", 404),
    ("another API version", b"GET /api/v2/state HTTP/1.1\r\n\r\n", 404),
    ("a static file not served", b"GET /static/index.html HTTP/1.1\r\n\r\n", 404),
    ("a static escape", b"GET /static/../status_api.py HTTP/1.1\r\n\r\n", 404),
]


@pytest.mark.parametrize("raw, expected", [(raw, code) for _, raw, code in BAD], ids=[name for name, _, _ in BAD])
def test_a_bad_request_gets_its_4xx_and_a_json_error(server, raw, expected):
    status, headers, body = request(server, raw)
    assert status == expected, body
    error = json.loads(body)["error"]
    assert error["status"] == expected and error["message"]
    assert "Traceback" not in error["message"]
    if expected == 405:
        assert headers["allow"] == "GET, HEAD"


ESCAPES = ["/reports/../cellcal.db", "/reports/%2e%2e/cellcal.db", "/reports/..%2fcellcal.db",
           "/reports/%2E%2E%2Fcellcal.db", "/reports/run-1/..%5c..%5ccellcal.db", "/reports/..\\cellcal.db",
           "/reports/run-1/report.html%00.png", "/reports/run-1/report.html\x00", "/reports//etc/passwd",
           "/reports/%2fetc%2fpasswd", "/reports/leak.txt", "/reports/up/cellcal.db", "/reports/up/../secret.txt",
           "/reports/./run-1/report.html", "/reports/.hidden", "/reports/run-1/", "/reports/",
           "/reports/%252e%252e/cellcal.db", "/reports/\u2025/cellcal.db".encode("utf-8").decode("latin-1")]


@pytest.mark.parametrize("path", ESCAPES)
def test_no_path_leaves_the_reports_folder(server, path):
    status, _, body = request(server, f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode("latin-1"))
    assert status == 404, body
    assert b"SQLite format" not in body and SECRET.encode() not in body and b"root:" not in body


def test_an_absolute_url_in_the_request_line_reaches_nothing_either(server):
    status, _, body = request(server, b"GET http://evil/../../cellcal.db HTTP/1.1\r\n\r\n")
    assert status == 404 and b"SQLite format" not in body


def test_refusals_flood_no_log(server, caplog):
    caplog.set_level(logging.INFO, logger="cellcal.daemon.status")
    client = ("127.0.0.1", 0)  # a client address of its own, so another test's refusals do not count
    server.guard.note_bad(client[0] + "-flood", "first")
    for _ in range(30):
        server.guard.note_bad(client[0] + "-flood", "again")
    assert len([r for r in caplog.records if "flood" in r.getMessage()]) == 1


# -- limits -----------------------------------------------------------------------------------------


def test_the_connection_limit_refuses_the_next_and_recovers(cell_state):
    with loopback.held() as host, StatusServer(status=lambda: dict(STATUS), state_dir=cell_state,
                                               spec=spec(host=host, max_connections=2)) as srv:
        idle = [socket.create_connection(srv.address, timeout=5) for _ in range(2)]
        try:
            time.sleep(0.3)  # both accepted and waiting in their handler threads for a request line
            try:
                status, headers, body = get(srv, "/api/v1/state")
                assert status == 503 and json.loads(body)["error"]["status"] == 503
                assert headers["retry-after"] == "1"
            except (ConnectionError, socket.timeout):
                pass  # refused outright is the other allowed answer
        finally:
            for s in idle:
                s.close()
        assert answered_again(srv)


def test_the_rate_limit_answers_429_then_again_after_the_bucket_refills(cell_state):
    with loopback.held() as host, StatusServer(status=lambda: dict(STATUS), state_dir=cell_state,
                                               spec=spec(host=host, rate_per_s=2)) as srv:
        answers = [get(srv, "/api/v1/state") for _ in range(6)]
        statuses = [a[0] for a in answers]
        # a burst of 2 (the bucket holds one second's worth), then refused: a token comes back
        # every 0.5 s, and 6 local requests take a few ms each (all 6 would pass only at 0.5 s each)
        assert statuses[:2] == [200, 200] and 429 in statuses[2:], statuses
        _, headers, body = answers[statuses.index(429)]
        assert headers["retry-after"] == "1" and "slow down" in json.loads(body)["error"]["message"]
        assert request(srv, b"POST / HTTP/1.1\r\n\r\n")[0] == 429  # bad requests are counted too
        time.sleep(1.2)  # 2 tokens a second: at least two back, whatever the timer's slack
        assert get(srv, "/api/v1/state")[0] == 200


def test_a_slow_client_lets_go_of_its_thread(cell_state, monkeypatch):
    monkeypatch.setattr(status_server._Handler, "timeout", 0.3)
    with loopback.held() as host, StatusServer(status=lambda: dict(STATUS), state_dir=cell_state,
                                               spec=spec(host=host, max_connections=1)) as srv:
        with socket.create_connection(srv.address, timeout=5) as slow:
            slow.sendall(b"GET /api/v1/sta")  # and never the rest
            time.sleep(0.6)  # beyond the (patched) socket timeout: the server hung up
            assert slow.recv(100) == b""
        assert answered_again(srv)  # its one slot is free again


def test_a_client_dripping_its_request_is_cut_off(cell_state, monkeypatch):
    """Slowloris: a byte every 0.1 s never meets the socket timeout; the connection's life limit cuts it."""
    monkeypatch.setattr(status_http, "MAX_CONNECTION_S", 0.5)
    monkeypatch.setattr(status_server._Handler, "timeout", 60.0)  # only the life limit can cut it
    with loopback.held() as host, StatusServer(status=lambda: dict(STATUS), state_dir=cell_state,
                                               spec=spec(host=host, max_connections=1)) as srv:
        with socket.create_connection(srv.address, timeout=5) as slow:
            started = time.monotonic()
            cut = False
            for byte in b"GET /api/v1/state HTTP/1.1\r\nX-Drip: " + b"a" * 100:
                try:
                    slow.sendall(bytes([byte]))
                    if select.select([slow], [], [], 0.1)[0]:  # readable: the server hung up (b"")
                        cut = slow.recv(100) == b""
                except OSError:  # reset: the server hung up
                    cut = True
                if cut or time.monotonic() - started > 20.0:  # the 0.5 s life limit cuts long before
                    break
            # each byte came within 0.1 s and the socket timeout is 60 s: the life limit cut it, well
            # before the 100 bytes (10 s at least) were sent; 20 s leaves a loaded machine room
            assert cut and time.monotonic() - started < 20.0
        assert answered_again(srv)


def answered_again(srv, within_s: float = 3.0) -> bool:
    """Whether the server answers 200 again within `within_s` (a handler thread ends, and frees
    its slot, a moment after its client's socket closes: on a loaded machine, not at once)."""
    deadline = time.monotonic() + within_s
    while get(srv, "/api/v1/state")[0] != 200:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


# -- life and the store -----------------------------------------------------------------------------


def test_a_taken_port_is_a_clear_error_and_stop_is_quick_and_idempotent(cell_state, monkeypatch):
    monkeypatch.setattr(status_server._Handler, "timeout", 60.0)
    monkeypatch.setattr(status_http, "MAX_CONNECTION_S", 120.0)
    with loopback.held() as host:
        first = StatusServer(status=lambda: dict(STATUS), state_dir=cell_state, spec=spec(host=host)).start()
        port = first.address[1]
        assert first.url == f"http://{host}:{port}/"
        with pytest.raises(StatusPageError, match=rf"cannot listen on {host}:{port}.*status_page"):
            StatusServer(status=dict, state_dir=cell_state, spec=spec(host=host, port=port)).start()
        idle = socket.create_connection(first.address, timeout=5)  # a client that never speaks
        started = time.monotonic()
        first.stop()
        # stop does not wait for the idle client: it would hold its thread for the 60 s socket
        # timeout; half of that leaves a loaded machine room and still tells the two apart
        assert time.monotonic() - started < 30.0
        first.stop()
        idle.close()
        assert first.url is None
        with pytest.raises(OSError):
            socket.create_connection((host, port), timeout=1).close()


def test_a_disabled_page_serves_nothing(cell_state):
    srv = StatusServer(status=dict, state_dir=cell_state, spec=spec(enabled=False)).start()
    assert srv.url is None
    srv.stop()


def test_a_failing_status_is_an_unknown_state_not_a_dead_server(cell_state):
    def broken():
        raise RuntimeError("the service is gone")

    with loopback.held() as host, StatusServer(status=broken, state_dir=cell_state, spec=spec(host=host)) as srv:
        state = get_json(srv, "/api/v1/state")
        assert state["state"] == "unknown" and "the service is gone" not in json.dumps(state)
        assert len(get_json(srv, "/api/v1/runs")["runs"]) == 2


def test_no_store_yet_is_no_runs(tmp_path):
    with loopback.held() as host, StatusServer(status=lambda: dict(STATUS), state_dir=tmp_path / "empty",
                                               spec=spec(host=host)) as srv:
        assert get_json(srv, "/api/v1/runs") == {"runs": []}
        assert get(srv, "/api/v1/runs/1")[0] == 404
        assert get_json(srv, "/api/v1/tools")["tools"][0]["id"] == 1  # the mounted tool, with nothing recorded


def test_nothing_any_request_did_changed_the_store(server, cell_state):
    before = store_contents(cell_state)
    for path in ["/", "/api/v1/state", "/api/v1/runs", "/api/v1/runs/1", "/api/v1/runs/2", "/api/v1/tools",
                 "/api/v1/tools/1/history", *ESCAPES[:8]]:
        get(server, path)
    for _, raw, _ in BAD:
        request(server, raw)
    assert store_contents(cell_state) == before
    assert len(before) > 20  # a real store was compared: its schema and rows


def test_the_service_s_own_status_is_served_as_it_says(cell_run):
    """Service.status() of the service that made the runs, as the daemon hands it over."""
    folder, service = cell_run
    with loopback.held() as host, StatusServer(status=service.status, state_dir=folder,
                                               spec=spec(host=host), tool_names={1: "torch", 3: "spare"}) as srv:
        state = get_json(srv, "/api/v1/state")
        assert state["state"] == "idle" and state["result_code"] == 0 and state["last_run_id"] == 2
        assert state == {**service.status(), "api": 1, "time": state["time"]}
        tools = get_json(srv, "/api/v1/tools")["tools"]
        assert [(t["id"], t["name"]) for t in tools] == [(1, "torch"), (3, "spare")]  # the cell's names given
        spare = get_json(srv, "/api/v1/tools/3/history")
        assert (spare["name"], spare["tool_frames"], spare["trend"]) == ("spare", [], None)
