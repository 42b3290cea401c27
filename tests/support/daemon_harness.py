"""``cellcal daemon`` on the networked simulated cell, as the end-to-end tests drive it
(tests/e2e/test_daemon_e2e.py) and the soak bench (bench/daemon_soak.py) repeats it.

:class:`Net` runs the sim-net fakes in process on a loopback address of their own, its
cell file with short routine sections (tcp-laser with one turn and one tilt, a small
tracker campaign) so a run reaches its first motion quickly; :class:`Daemon` starts
``python -m cellcal.cli.main daemon`` on that file as systemd would (``NOTIFY_SOCKET``) and
returns once READY=1 arrives. The operator is played on the IO module (:func:`press_start`,
:func:`one_run`); :func:`resources` counts what a process holds.

This is the tests' own way to start the daemon: it does not use ``cellcal demo``'s.
"""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from support import loopback
from support.cell_edits import edited_cell, replaced
from support.service_panel import SELECT
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.sims.fake_ur.controller import DASHBOARD_PORT
from cellcal.sims.fake_ur.process import ControlClient
from cellcal.sims.net.cell import SimCell

RUN_TIMEOUT_S = 60.0
READY_TIMEOUT_S = 60.0
# the end-to-end suite's simulated clock, in simulated seconds per wall second: the largest at which the
# suite passes with both cores also busy with another process. At 4, ur_rtde's control client (whose
# command handshake waits 3 s of the wall for each step) found its script "not running" or a command
# unanswered under that load: the fake's cycle, once the arm moves, then needs more of a core than
# it gets. The same results as real time (tests/e2e/test_time_scale.py)
SUITE_TIME_SCALE = 3.0
SHORT_SECTIONS = {
    "tcp_laser": replaced({"speed_mm_s": 250, "heights_mm": [12, 40], "spins_deg": [0], "tilts": 1}),
    "tracker": replaced({"target": "smr1", "instrument_m": [-2.5, 0.0, 1.0], "poses": 10, "validation_poses": 0,
                         "candidates": 60, "settle_s": 0, "measure_s": 0, "retries": 0}),
}


def short_cell(folder: Path, host: str) -> Path:
    """sim-net on `host`, its tcp-laser and tracker sections short, the panel's and the
    tracker's timeouts short (a fault shows quickly)."""
    drivers = {"panel": {"timeout_s": 0.3}, "tracker": {"measure_timeout_s": 1.0}}
    return edited_cell(folder, "sim-net", {"drivers": drivers, **SHORT_SECTIONS}, name="sim-net-short.yaml",
                       host=host)


class Net:
    """The running fakes (on a loopback address of their own) and what a case needs to reach them."""

    def __init__(self, folder: Path, cell_file=None, time_scale: float = 1.0):
        """`cell_file(folder, host)`: the cell file to serve (default :func:`short_cell`); `time_scale`:
        simulated seconds per wall second (the fakes' clock)."""
        self.host = loopback.allocate()
        try:
            self.path = (cell_file or short_cell)(folder, self.host)
            self.cell = load_cell(self.path)
            self.sim = SimCell(self.cell, time_scale=time_scale).start()
        except BaseException:
            loopback.release(self.host)
            raise
        self.control = ControlClient(self.host)
        self.panel = self.sim.modbus
        self.previous = self.cell.tool.tcp_pose + np.array([0.0004, 0.0, -0.0004, 0.0, 0.0, 0.0])

    def state(self) -> dict:
        return self.control.request(cmd="state")

    def dashboard(self, command: str) -> str:
        with socket.create_connection((self.host, DASHBOARD_PORT), timeout=5) as sock:
            reader = sock.makefile("r")
            reader.readline()
            sock.sendall((command + "\n").encode())
            return reader.readline().strip()

    def at_rest(self, hold_s: float = 0.3) -> tuple[dict, dict]:
        """Two looks at the controller `hold_s` apart (its time), once the arm has come to rest."""
        deadline = time.monotonic() + 10.0
        while self.state()["moving"] and time.monotonic() < deadline:
            time.sleep(0.02)
        first = self.state()
        sim_sleep(self.control, hold_s)
        return first, self.state()

    def reset(self) -> None:
        """The controller healthy, the arm at home with the previous frame, no fault pending."""
        self.panel.clear_faults()
        if self.sim.tracker is not None:
            self.sim.tracker.silent = False
        self.control.request(cmd="fault", kind="resume")
        self.dashboard("restart safety")
        self.at_rest(0.0)
        self.control.request(cmd="set_q", q=list(self.cell.home_q_rad))
        with open_drivers(self.cell) as drivers:
            drivers.robot.set_tcp(self.previous)

    def close(self) -> None:
        try:
            self.control.close()
            self.sim.stop()
        finally:
            loopback.release(self.host)


def sim_sleep(control: ControlClient, sim_s: float) -> None:
    """Wait until the fake controller's clock (`control`: a connection to it) has run `sim_s`."""
    until = control.request(cmd="state")["t_s"] + sim_s
    while control.request(cmd="state")["t_s"] < until:
        time.sleep(0.005)


def _stop(proc: subprocess.Popen) -> int:
    """SIGTERM, then SIGKILL after the unit's TimeoutStopSec, as systemd does; the exit status."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(systemd_stop_timeout_s())
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.wait()


def start_daemon(cell_path: Path, state_dir: Path, notify_path: Path, *, stderr, extra=()) -> subprocess.Popen:
    """``python -m cellcal.cli.main daemon`` on a cell file, returned once it has sent READY=1
    to a notify socket made at `notify_path` (systemd's protocol). RuntimeError, the daemon
    stopped, when it ends or READY does not come within READY_TIMEOUT_S."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as notify:
        notify.bind(str(notify_path))
        try:
            env = dict(os.environ, NOTIFY_SOCKET=str(notify_path))
            proc = subprocess.Popen([sys.executable, "-m", "cellcal.cli.main", "daemon", "--cell", str(cell_path),
                                     "--state-dir", str(state_dir), *extra],
                                    env=env, stdout=subprocess.DEVNULL, stderr=stderr, text=True)
            deadline = time.monotonic() + READY_TIMEOUT_S
            notify.settimeout(0.2)
            while True:
                try:
                    if b"READY=1" in notify.recv(4096):
                        return proc
                except socket.timeout:
                    pass
                if proc.poll() is not None:
                    raise RuntimeError(f"the daemon ended with exit status {proc.returncode} before it was ready")
                if time.monotonic() > deadline:
                    _stop(proc)
                    raise RuntimeError(f"the daemon did not get ready within {READY_TIMEOUT_S:g} s")
        finally:
            Path(notify_path).unlink()


class Daemon:
    """``cellcal daemon`` on the Net's cell, its log in a file; started once systemd's READY arrives."""

    def __init__(self, net: Net, folder: Path):
        self.state_dir, self.log_path = folder / "state", folder / "daemon.log"
        with open(self.log_path, "a") as log:
            try:
                self.proc = start_daemon(net.path, self.state_dir, folder / "notify.sock", stderr=log,
                                         extra=("--poll-s", "0.02"))
            except RuntimeError as exc:
                raise AssertionError(f"{exc}:\n{self.log()}") from None

    def log(self) -> str:
        return self.log_path.read_text()

    def cli(self, *args: str) -> dict:
        out = subprocess.run([sys.executable, "-m", "cellcal.cli.main", *args, "--state-dir", str(self.state_dir),
                              "--json"], capture_output=True, text=True, check=True)
        return json.loads(out.stdout)

    def stop(self) -> int:
        return _stop(self.proc)


def systemd_stop_timeout_s() -> float:
    """TimeoutStopSec of the shipped unit (config/cellcal.service): how long systemd waits after
    SIGTERM before it kills the service. A stop must end within it; how fast it usually is (well
    under a second unloaded) is not a test's to assert on a shared machine."""
    unit = Path(__file__).resolve().parents[2] / "config" / "cellcal.service"
    return float(re.search(r"^TimeoutStopSec=(\d+)", unit.read_text(), re.M).group(1))


OUTCOME = ("verdict", "tool_id", "change_x", "change_y", "change_z", "tilt_x", "tilt_y")  # registers 20-26


def plc_reads(net: Net) -> dict:
    """What a PLC reads after a run, with a plain Modbus client: the result code, the lamps and
    the outcome registers, decoded (docs/panel.md)."""
    from pymodbus.client import ModbusTcpClient

    from cellcal.daemon import outcome
    with ModbusTcpClient(net.host, port=net.sim.addresses.modbus[1]) as client:
        unit = net.sim.addresses.unit_id
        code = client.read_holding_registers(1, count=1, device_id=unit).registers[0]
        raw = client.read_holding_registers(20, count=7, device_id=unit).registers
        lamps = client.read_coils(8, count=3, device_id=unit).bits[:3]
    return {"code": code, "lamps": dict(zip(("busy", "done", "fault"), lamps)),
            **outcome.decoded(dict(zip(OUTCOME, raw)))}


def controller_tcp(net: Net) -> np.ndarray:
    """The controller's tool frame, once the arm is at rest."""
    net.at_rest(0.0)
    return np.asarray(net.state()["tcp_offset"], dtype=float)


def until_the_run_ends(net: Net, counter: int, meanwhile=lambda: None) -> None:
    """Wait for the panel's run counter to move past `counter`, calling `meanwhile` between looks."""
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while net.panel.run_counter() == counter:
        assert time.monotonic() < deadline, "the run did not end"
        meanwhile()
        time.sleep(0.01)


def press_start(net: Net, routine: str) -> None:
    """The operator starts `routine`; returns once the arm moves."""
    net.panel.select_routine(SELECT[routine])
    net.panel.press_start()
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while not net.state()["moving"]:
        assert time.monotonic() < deadline, "the arm never moved"
        time.sleep(0.01)


def one_run(net: Net, ending: str) -> None:
    """One button-started run: "refused" (a selector no routine has), "aborted" (the abort
    button once the arm moves) or "complete" (the short tcp-laser to its verdict)."""
    counter = net.panel.run_counter()
    if ending == "refused":
        net.panel.select_routine(99)
        net.panel.press_start()
    else:
        press_start(net, "tcp-laser")
        if ending == "aborted":
            net.panel.press_abort()
    until_the_run_ends(net, counter)


def resources(pid: int) -> dict[str, int]:
    """What a process holds: file descriptors, sockets among them, threads, child processes."""
    fds = [os.readlink(f"/proc/{pid}/fd/{fd}") for fd in os.listdir(f"/proc/{pid}/fd")]
    children = sum(len(Path(f"/proc/{pid}/task/{task}/children").read_text().split())
                   for task in os.listdir(f"/proc/{pid}/task"))
    return {"fds": len(fds), "sockets": sum(fd.startswith("socket:") for fd in fds),
            "threads": len(os.listdir(f"/proc/{pid}/task")), "children": children}


def settled(pid: int, like: dict[str, int], timeout_s: float = 5.0) -> dict[str, int]:
    """The process's resources once they equal `like`, or as they are after `timeout_s`
    (a run's worker thread ends just after the run counter moves)."""
    deadline = time.monotonic() + timeout_s
    while (now := resources(pid)) != like and time.monotonic() < deadline:
        time.sleep(0.05)
    return now
