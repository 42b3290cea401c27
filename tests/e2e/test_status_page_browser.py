"""The status page as a person uses it (issue 23): ``cellcal daemon`` on the networked simulated
cell with its status page on a free port, a calibration and a check started from the operator
panel, then the page opened in a real headless Chromium (Debian's ``chromium`` package; ``make
test`` installs it where it can, else these tests skip and say so).

Chromium runs the page's own JavaScript against the daemon's API (``--virtual-time-budget``
lets its polling and drawing finish) and ``--dump-dom`` gives the DOM as rendered: what it shows
is compared with what ``cellcal runs list/show --json`` read from the store. A screenshot of the
page is kept as an artefact of the test run: ``out/test-artifacts/status-page.png`` (git-ignored).
"""
from __future__ import annotations

import json
import re
import shutil
import socket
import struct
import subprocess
import time
import urllib.request
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import urljoin

import pytest

from support.cell_edits import edited_cell
from cellcal.daemon.service import ResultCode
from support.daemon_harness import Net, press_start, until_the_run_ends

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
ARTEFACTS = REPO / "out" / "test-artifacts"
SCREENSHOT = ARTEFACTS / "status-page.png"
BROWSER_TIMEOUT_S = 60.0
WINDOW = (1280, 1000)


def chromium_or_skip() -> str:
    """The path of a Chromium that starts, or the test skips naming what is missing."""
    path = shutil.which("chromium")
    if path is None:
        pytest.skip("no `chromium` on PATH: the browser test needs Debian's chromium package "
                    "(`apt-get install --no-install-recommends chromium`, which `make test` does as root)")
    try:
        version = subprocess.run([path, "--version"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        pytest.skip(f"{path} does not start ({exc}): the browser test needs a working chromium")
    if version.returncode != 0:
        pytest.skip(f"`{path} --version` failed (exit {version.returncode}): {version.stderr.strip()[:200]}")
    return path


class Browser:
    """Headless Chromium, one process per page load, with a profile of the test's own."""

    def __init__(self, path: str, folder: Path):
        self.path, self.profile = path, folder / "chromium-profile"

    def _run(self, url: str, *what: str) -> str:
        args = [self.path, "--headless", "--no-sandbox", "--disable-gpu", f"--user-data-dir={self.profile}",
                "--no-first-run", "--virtual-time-budget=8000", *what, url]
        out = subprocess.run(args, capture_output=True, text=True, timeout=BROWSER_TIMEOUT_S)
        assert out.returncode == 0, f"chromium ended with {out.returncode} on {url}:\n{out.stderr[-2000:]}"
        return out.stdout

    def dom(self, url: str) -> "Node":
        """The page's DOM once its scripts have run (eight seconds of virtual time)."""
        return parse(self._run(url, "--dump-dom"))

    def screenshot(self, url: str, path: Path) -> None:
        path.unlink(missing_ok=True)
        self._run(url, f"--screenshot={path}", f"--window-size={WINDOW[0]},{WINDOW[1]}", "--hide-scrollbars")


# -- the DOM Chromium dumps, as a small tree ----------------------------------------------------------

VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"}


class Node:
    def __init__(self, tag: str, attrs: dict, parent: "Node | None"):
        self.tag, self.attrs, self.parent, self.children, self.parts = tag, attrs, parent, [], []

    @property
    def text(self) -> str:
        return " ".join("".join(p if isinstance(p, str) else p.text for p in self.parts).split())

    @property
    def classes(self) -> set[str]:
        return set((self.attrs.get("class") or "").split())

    def all(self, tag: str | None = None, cls: str | None = None, **attrs) -> list["Node"]:
        """Every node below this one with that tag, class and attribute values, in document order."""
        found = []
        for child in self.children:
            if ((tag is None or child.tag == tag) and (cls is None or cls in child.classes)
                    and all(child.attrs.get(k.replace("_", "-")) == v for k, v in attrs.items())):
                found.append(child)
            found.extend(child.all(tag, cls, **attrs))
        return found

    def one(self, tag: str | None = None, cls: str | None = None, **attrs) -> "Node":
        found = self.all(tag, cls, **attrs)
        assert len(found) == 1, f"{len(found)} <{tag or '*'} class={cls} {attrs}> on the page, expected one"
        return found[0]


class _TreeBuilder(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.root = self.node = Node("#document", {}, None)

    def handle_starttag(self, tag, attrs):
        node = Node(tag, {k: v or "" for k, v in attrs}, self.node)
        self.node.children.append(node)
        self.node.parts.append(node)
        if tag not in VOID:
            self.node = node

    def handle_startendtag(self, tag, attrs):  # <path ... /> in SVG
        node = Node(tag, {k: v or "" for k, v in attrs}, self.node)
        self.node.children.append(node)
        self.node.parts.append(node)

    def handle_endtag(self, tag):
        node = self.node
        while node is not None and node.tag != tag:
            node = node.parent
        if node is not None and node.parent is not None:
            self.node = node.parent

    def handle_data(self, data):
        self.node.parts.append(data)


def parse(html: str) -> Node:
    builder = _TreeBuilder()
    builder.feed(html)
    builder.close()
    return builder.root


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk; AssertionError when the file is not a PNG."""
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR", f"{path} is not a PNG"
    return struct.unpack(">II", head[16:24])


def get(url: str) -> tuple[str, bytes]:
    """(Content-Type, body) of a plain GET."""
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.headers.get("Content-Type", ""), r.read()


def served(url: str, daemon, timeout_s: float = 10.0) -> None:
    """Wait until `url` answers 200 (the page starts once the service is ready)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            get(url)
            return
        except OSError as exc:
            assert time.monotonic() < deadline, f"{url} not served within {timeout_s:g} s ({exc}):\n{daemon.log()}"
            time.sleep(0.1)


# -- the cell -------------------------------------------------------------------------------------------


def free_port(host: str) -> int:
    """A TCP port free on `host` (the test's own loopback address, so nobody else takes it after)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def page_cell(folder, host):
    """sim-net with the shipped tcp-laser section (the harness's short one decides too little to
    pass its gates: no frame written, so no drift to plot), the panel's short timeout, and the
    status page on a free port of the cell's own loopback address."""
    changes = {"drivers": {"panel": {"timeout_s": 0.3}}, "status_page": {"port": free_port(host)}}
    return edited_cell(folder, "sim-net", changes, name="sim-net-page.yaml", host=host)


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    return Browser(chromium_or_skip(), tmp_path_factory.mktemp("chromium"))


@pytest.fixture(scope="module")
def net_cell(browser):  # the browser first: without chromium the module skips before a fake starts
    return page_cell


def press(net: Net, routine: str) -> None:
    counter = net.panel.run_counter()
    press_start(net, routine)
    until_the_run_ends(net, counter)


def test_the_page_shows_what_the_store_holds_in_a_real_browser(net, browser, cellcal_daemon):
    """A calibration and a check from the panel; then the page, as Chromium renders it: the state
    idle with the last run's result, each run's row with its result code, a report that opens with
    its pictures, the mounted tool's drift drawn (two points: the calibration and the check). The
    screenshot is kept at out/test-artifacts/status-page.png."""
    url = f"http://{net.host}:{net.cell.status_page.port}/"
    daemon = cellcal_daemon(net)
    served(urljoin(url, "/api/v1/state"), daemon)
    assert f"status page and JSON API (read-only): {url}" in daemon.log()
    press(net, "tcp-laser")
    press(net, "tcp-check")

    listed = daemon.cli("runs", "list")["runs"]
    assert [r["routine"] for r in listed] == ["tcp-check", "tcp-laser"], daemon.log()
    shown = {r["id"]: daemon.cli("runs", "show", str(r["id"])) for r in listed}
    calibration, check = shown[listed[1]["id"]], shown[listed[0]["id"]]
    assert calibration["result_code"] == ResultCode.OK and calibration["written_back"], daemon.log()
    assert check["result_code"] == ResultCode.OK and check["result"]["verdict"] == "ok", daemon.log()

    page = browser.dom(url)
    assert page.one(id="error").attrs.get("hidden") is not None, page.one(id="error").text  # the API answered

    # the service's state, as the page shows it: idle, the last run's end and code from the store
    state = page.one(id="state")
    assert state.attrs["data-state"] == "idle" and state.attrs["data-level"] == "ok" and state.text == "idle", \
        state.text
    ended = page.one(id="reason").text
    assert ended.startswith(f"last run {check['id']} (tcp-check, ") and \
        f") ended done: code {check['result_code']} OK, verdict ok" in ended, ended
    assert re.search(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC[+-]\d\d:\d\d", ended), ended  # with its time zone
    assert page.one(id="cell-name").text == f": {net.cell.name}"
    devices = {row.attrs["data-device"]: row.one("td").text for row in page.one(id="devices").all("tr")}
    assert devices["panel"] == "ok" and devices["robot"] not in ("", "unknown", "reconnecting"), devices
    assert devices["trigger"] == devices["tracker"] == "open", devices  # sim-net has both
    tool_id = check["tool_id"]
    assert page.one(id="mounted-tool").text.startswith(f"tool {tool_id}")
    assert page.one(id="mounted-tool").text.endswith("as the cell file says")  # sim-net's tool is fixed

    # every run of the store in the table, newest first, with its result code and name
    rows = page.one(id="runs").one("tbody").all("tr")
    assert [row.attrs["data-run-id"] for row in rows] == [str(r["id"]) for r in listed]
    for row, run in zip(rows, listed):
        cells = [td.text for td in row.all("td")]
        assert cells[:4] == [str(run["id"]), run["routine"], str(run["tool_id"]), run["state"]], cells
        assert row.one("td", cls="result").text == f"{run['result_code']} {ResultCode(run['result_code']).name}"
        assert row.one("td", cls="verdict").text == (shown[run["id"]]["result"].get("verdict") or "-")

    # the check's report: the link the page drew opens the report the store names
    link = rows[0].one("a", cls="report").attrs["href"]
    assert link.startswith("/reports/") and Path(check["report"]).as_posix().endswith(link[len("/reports/"):])
    report = browser.dom(urljoin(url, link))
    assert report.one("title").text == "cellcal run"
    assert report.one("h1").text == f"Run {check['id']}: tcp-check"
    pictures = [urljoin(urljoin(url, link), img.attrs["src"]) for img in report.all("img")]
    assert pictures, "the report shows no picture"
    for picture in pictures:
        kind, body = get(picture)
        assert kind == "image/png" and body.startswith(b"\x89PNG"), (picture, kind)

    # the mounted tool's drift: one line per series, the tip's through both measured frames
    # two plots, each in its own unit with the tool's bands from the cell file (no drift alarm set in sim-net)
    plots = {svg.attrs["aria-label"]: svg for svg in page.one(id="drift-plot-box").all("svg", cls="drift-plot")}
    assert set(plots) == {"tip change (mm)", "axis change (deg)"}, plots
    paths = {p.attrs["data-series"]: p for svg in plots.values() for p in svg.all("path")}
    assert set(paths) == {"tip_mm", "axis_deg"}, paths
    tip = paths["tip_mm"].attrs
    assert tip["data-points"] == "2" and tip["d"].startswith("M") and " L" in tip["d"], tip
    assert len(plots["tip change (mm)"].all("circle", cls="point-tip")) == 2
    bands = net.cell.tool.bands
    for label, unit in (("tip change (mm)", "mm"), ("axis change (deg)", "deg")):
        drawn = {line.attrs["data-band"]: float(line.attrs["data-value"]) for line in plots[label].all("line", cls="band")}
        assert drawn == {"inner": getattr(bands, f"inner_{unit}"), "outer": getattr(bands, f"outer_{unit}")}, drawn
    history = json.loads(get(urljoin(url, f"/api/v1/tools/{tool_id}/history"))[1])
    assert [p["run_id"] for p in history["trend"]["points"]] == [calibration["id"], check["id"]]
    frames = page.one(id="frames").one("tbody").all("tr")
    assert [row.all("td")[2].text for row in frames] == [str(calibration["id"])]  # the one frame written

    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    browser.screenshot(url, SCREENSHOT)
    assert png_size(SCREENSHOT) == WINDOW

    # the tool bent 2 mm: the check's alarm lights the fault lamp. After a restart of the service the
    # page says what the panel shows, from the store: not a green "idle"
    assert net.control.request(cmd="bend_tool", shift_m=[0.0, 0.002, 0.0])["ok"]
    press(net, "tcp-check")
    alarm = daemon.cli("runs", "list")["runs"][0]
    assert alarm["result_code"] == ResultCode.CHECK_ALARM and alarm["verdict"] == "alarm", daemon.log()
    assert daemon.stop() == 0, daemon.log()
    daemon = cellcal_daemon(net)
    served(urljoin(url, "/api/v1/state"), daemon)
    api = json.loads(get(urljoin(url, "/api/v1/state"))[1])
    assert api["last_run_id"] == alarm["id"] and api["result_code"] == ResultCode.CHECK_ALARM, api
    assert api["health"]["level"] == "fault", api["health"]
    page = browser.dom(url)
    state = page.one(id="state")
    assert state.attrs["data-level"] == "fault", state.attrs
    assert state.text == f"idle; the last run ({alarm['id']}, tcp-check) ended fault: 33 CHECK_ALARM", state.text
    assert ") ended fault: code 33 CHECK_ALARM, verdict alarm: " in page.one(id="reason").text
    assert daemon.stop() == 0, daemon.log()
