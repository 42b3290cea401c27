"""The status page's cost to the service: a run's cycle time and the panel's response time with
the page open and the API polled at 10 Hz, against the same without, in the same run (issue 23).

``cellcal daemon`` on the networked simulated cell (the suite's harness: fakes on a loopback
address of their own, the short tcp-laser section, ``--poll-s 0.02``) serves its status page
there. Each repetition is one button-started tcp-laser run, timed from the outside:

- panel response: the start press (the start coil set on the IO module, as the button does)
  until the busy lamp coil reads 1 through a plain Modbus client, polled as fast as it answers;
- cycle time: the start press until the panel's run counter moves (the run has ended).

Repetitions alternate between the two conditions (quiet, loaded, quiet, ...) so a drift of the
machine's load falls on both alike. Loaded: a client thread GETs /api/v1/state and
/api/v1/runs ten times a second, and a headless Chromium keeps the page itself open (its own
polling: every 1 s during a run); without Chromium on PATH only the client thread loads it (the
report says so). The cell's ``status_page.rate_per_s`` is raised to 50 so that load is served,
not refused with 429s. Every number goes to bench/results/status_page.json.

    python -m bench.status_page_bench               # 5 repetitions each, about two minutes
    python -m bench.status_page_bench --reps 3      # quicker
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support import daemon_harness  # noqa: E402  (the suite's harness)
from support.cell_edits import edited_cell  # noqa: E402
from support.daemon_harness import SHORT_SECTIONS, Daemon, Net, SELECT, until_the_run_ends  # noqa: E402
from pymodbus.client import ModbusTcpClient  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "status_page.json"
POLL_HZ = 10.0
RATE_PER_S = 50  # the cell's status_page.rate_per_s here: the 10 Hz poller (20 requests/s) plus the page's
LAMP_TIMEOUT_S = 10.0
SERVED_TIMEOUT_S = 10.0
TROUBLE = ("lost", "timed out", "reconnect", "not respond", "status page:")  # daemon log lines worth printing


def log(msg: str) -> None:
    print(f"[status-page-bench] {msg}", file=sys.stderr, flush=True)


def bench_cell(folder: Path, host: str) -> Path:
    """sim-net with the harness's short routine sections, the shipped drivers' timeouts (the
    harness's 0.3 s panel timeout, there to show a fault quickly, would measure the machine's
    load instead) and its status page allowing the bench's request rate."""
    return edited_cell(folder, "sim-net", {**SHORT_SECTIONS, "status_page": {"rate_per_s": RATE_PER_S}},
                       name="sim-net-bench.yaml", host=host)


class Poller:
    """GET /api/v1/state and /api/v1/runs `hz` times a second in a thread; counts the answers
    and times them."""

    def __init__(self, url: str, hz: float):
        self.urls = (url + "api/v1/state", url + "api/v1/runs")
        self.period = 1.0 / hz
        self.statuses: dict[str, int] = {}
        self.latencies_ms: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="api-poller", daemon=True)

    def _get(self, url: str) -> None:
        t0 = time.perf_counter()
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                r.read()
                status = str(r.status)
        except urllib.error.HTTPError as exc:
            status = str(exc.code)
        except OSError as exc:
            status = type(exc).__name__
        self.latencies_ms.append((time.perf_counter() - t0) * 1e3)
        self.statuses[status] = self.statuses.get(status, 0) + 1

    def _loop(self) -> None:
        next_at = time.monotonic()
        while not self._stop.is_set():
            for url in self.urls:
                self._get(url)
            next_at += self.period
            self._stop.wait(max(0.0, next_at - time.monotonic()))

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(10.0)


class OpenPage:
    """The status page open in a headless Chromium (its own polling runs as in a person's
    browser), in a process group of its own, ended by that group's id. Nothing without Chromium."""

    def __init__(self, url: str, folder: Path):
        self.url, self.folder, self.proc = url, folder, None
        self.chromium = shutil.which("chromium")

    def __enter__(self):
        if self.chromium is not None:
            self.proc = subprocess.Popen(
                [self.chromium, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                 f"--user-data-dir={self.folder / 'chromium-profile'}", self.url],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
            time.sleep(3.0)  # the browser up and the page loaded before the run is timed
        return self

    def __exit__(self, *exc):
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10.0)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()


def served(url: str) -> None:
    deadline = time.monotonic() + SERVED_TIMEOUT_S
    while True:
        try:
            with urllib.request.urlopen(url + "api/v1/state", timeout=2) as r:
                r.read()
            return
        except OSError as exc:
            if time.monotonic() > deadline:
                raise RuntimeError(f"the status page at {url} did not answer within {SERVED_TIMEOUT_S:g} s: "
                                   f"{exc}") from None
            time.sleep(0.1)


def one_run(net: Net, plc: ModbusTcpClient) -> dict:
    """One tcp-laser from the panel: {"response_ms", "cycle_s"} (see the module's doc)."""
    unit, busy = net.sim.addresses.unit_id, net.panel.panel_map.busy_lamp_coil
    net.panel.select_routine(SELECT["tcp-laser"])
    counter = net.panel.run_counter()
    t0 = time.perf_counter()
    net.panel.press_start()
    deadline = time.monotonic() + LAMP_TIMEOUT_S
    while not plc.read_coils(busy, count=1, device_id=unit).bits[0]:
        if time.monotonic() > deadline:
            raise RuntimeError(f"the busy lamp did not light within {LAMP_TIMEOUT_S:g} s of the start press")
    response = time.perf_counter() - t0
    until_the_run_ends(net, counter)
    return {"response_ms": response * 1e3, "cycle_s": time.perf_counter() - t0}


def summary(values: list[float]) -> dict:
    return {"median": statistics.median(values), "min": min(values), "max": max(values), "n": len(values)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=5, help="runs per condition, 1 .. 50 (default 5)")
    args = parser.parse_args(argv)
    if not 1 <= args.reps <= 50:
        parser.error("--reps must be from 1 to 50")
    runs: dict[str, list[dict]] = {"without": [], "with": []}
    polled = {"statuses": {}, "latencies_ms": []}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        daemon_harness.short_cell = bench_cell  # this process's harness: the bench's cell file
        net = Net(folder)
        try:
            net.reset()
            url = f"http://{net.host}:{net.cell.status_page.port}/"
            daemon = Daemon(net, folder)
            try:
                served(url)
                chromium = shutil.which("chromium")
                log(f"daemon ready, status page at {url}; page load: API at {POLL_HZ:g} Hz"
                    + (" + the page in headless Chromium" if chromium else " only (no chromium on PATH)"))
                with ModbusTcpClient(net.host, port=net.sim.addresses.modbus[1]) as plc:
                    one_run(net, plc)  # warm-up: what a first run opens for good
                    t_start = time.monotonic()
                    for k in range(args.reps):
                        for condition in ("without", "with"):
                            if condition == "without":
                                runs[condition].append(one_run(net, plc))
                            else:
                                with OpenPage(url, folder), Poller(url, POLL_HZ) as poller:
                                    runs[condition].append(one_run(net, plc))
                                for status, n in poller.statuses.items():
                                    polled["statuses"][status] = polled["statuses"].get(status, 0) + n
                                polled["latencies_ms"] += poller.latencies_ms
                            r = runs[condition][-1]
                            log(f"rep {k + 1}/{args.reps} {condition:7s} page: response {r['response_ms']:6.1f} ms, "
                                f"cycle {r['cycle_s']:6.2f} s")
                    took_s = time.monotonic() - t_start
            finally:
                code = daemon.stop()
                daemon_log = daemon.log().splitlines()
        finally:
            net.close()
    trouble = [line for line in daemon_log if any(w in line for w in TROUBLE)]
    stats = {c: {k: summary([r[k] for r in runs[c]]) for k in ("response_ms", "cycle_s")} for c in runs}
    ratios = {k: stats["with"][k]["median"] / stats["without"][k]["median"] for k in ("response_ms", "cycle_s")}
    lat = sorted(polled["latencies_ms"])
    report = {"reps": args.reps, "took_s": round(took_s, 1), "poll_hz": POLL_HZ, "page_in_chromium": bool(chromium),
              "stats": stats, "ratio_with_to_without": ratios, "runs": runs,
              "api": {"statuses": polled["statuses"], "requests": len(lat),
                      "latency_ms": {"median": statistics.median(lat), "p95": lat[int(0.95 * (len(lat) - 1))],
                                     "max": lat[-1]} if lat else None},
              "daemon_exit": code, "daemon_log_trouble": trouble, "daemon_log": daemon_log,
              "cpus": os.cpu_count(), "load_avg": os.getloadavg(), "python": platform.python_version()}
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(report, indent=1))
    print(f"{'':28s}{'without page':>14s}{'with page':>14s}{'ratio':>8s}")
    for key, label, unit in (("response_ms", "panel response (median)", "ms"), ("cycle_s", "cycle time (median)", "s")):
        a, b = stats["without"][key]["median"], stats["with"][key]["median"]
        print(f"{label:28s}{a:11.3f} {unit:2s}{b:11.3f} {unit:2s}{ratios[key]:8.3f}")
    if lat:
        print(f"API while loaded: {len(lat)} requests, answers {polled['statuses']}, latency median "
              f"{report['api']['latency_ms']['median']:.1f} ms, p95 {report['api']['latency_ms']['p95']:.1f} ms")
    for line in trouble:
        print(f"daemon log: {line}")
    print(f"every number: {RESULTS}")
    return 0 if code == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
