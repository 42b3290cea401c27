"""The service: its state machine on the simulated cell, the store, systemd's notify protocol.

The state machine runs in process on the sim cell (the operator plays the SimPanel);
what needs a real process (signals, the notify socket, SIGKILL of the store's writer)
runs ``cellcal daemon`` or a writer as a subprocess.
"""
from __future__ import annotations

import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.reports.run import write_run_report
from cellcal.daemon.service import RESULT_MEANINGS, ResultCode, Service
from cellcal.daemon.store import SCHEMA_VERSION, Store
from cellcal.routines.framework import registry
from support.cell_edits import edited_cell  # tests/support/cell_edits.py
from support.daemon_harness import systemd_stop_timeout_s  # tests/support/daemon_harness.py
from support.report_check import assert_page_draws, layer

ROUTINE = "tcp-laser"
needs_routine = pytest.mark.skipif(ROUTINE not in registry.available(), reason=f"{ROUTINE} not installed")
ROOT = Path(__file__).resolve().parents[2]


# -- the store ---------------------------------------------------------------------------

def test_store_records_a_run_with_its_states(tmp_path):
    store = Store.open(tmp_path)
    run = store.begin_run("tcp-laser", "sim.yaml")
    store.record_state(run, "running", "12 moves")
    store.finish_run(run, "done", 0, "written back")
    assert [s for _, s, _ in store.states(run)] == ["checking", "running", "done"]
    assert store.run(run).state == "done" and store.run(run).result_code == 0
    assert store.db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    assert store.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    store.close()


def test_an_open_run_is_marked_interrupted_at_the_next_start(tmp_path):
    store = Store.open(tmp_path)
    run = store.begin_run("tcp-laser", "sim.yaml")
    store.record_state(run, "running")
    store.close()
    store = Store.open(tmp_path)
    assert store.mark_interrupted(int(ResultCode.INTERRUPTED)) == [run]
    assert store.run(run).state == "interrupted" and store.run(run).result_code == ResultCode.INTERRUPTED
    store.close()


WRITER = textwrap.dedent("""
    import sys
    from cellcal.daemon.store import Store
    store = Store.open(sys.argv[1])
    print("ready", flush=True)
    while True:
        run = store.begin_run("tcp-laser", "sim.yaml")
        for state in ("running", "solving", "gates", "writing back"):
            store.record_state(run, state, "x" * 200)
        store.record_tool_frame(run, "write", [0.0] * 6, [0.001, 0.0, 0.15, 0.0, 0.0, 0.0])
        store.finish_run(run, "done", 0, "ok")
""")


def test_the_store_survives_sigkill_in_the_middle_of_writes(tmp_path):
    """Killed many times at random points of a write: integrity ok, every finished run kept."""
    rng = random.Random(7)
    finished_before, cut_short = 0, 0
    for _ in range(25):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(rng.uniform(0.01, 0.15))
        proc.kill()
        proc.wait()
        store = Store.open(tmp_path)
        assert store.integrity() == "ok"
        runs = store.runs(100000)
        finished = [r for r in runs if r.state == "done"]
        assert len(finished) >= finished_before  # nothing recorded before a kill is lost
        finished_before = len(finished)
        cut_short += sum(r.state != "done" for r in runs[:1])  # the kill came in the middle of a run
        store.close()
    assert finished_before >= 1 and cut_short >= 1, (finished_before, cut_short)


# -- the state machine on the simulated cell ----------------------------------------------

class HeldRobot:
    """The sim robot, held at its first move until the test releases it (a run in progress)."""

    def __init__(self, robot):
        self.robot, self.moving, self.release = robot, threading.Event(), threading.Event()

    def __getattr__(self, name):
        return getattr(self.robot, name)

    def _hold(self):
        self.moving.set()
        assert self.release.wait(10.0)

    def move_j(self, *args):
        self._hold()
        return self.robot.move_j(*args)

    def move_l(self, *args):
        self._hold()
        return self.robot.move_l(*args)

    def stop(self):
        self.release.set()
        return self.robot.stop()


@pytest.fixture
def cell():
    return load_cell("sim")


def service_on(cell, drivers, tmp_path) -> Service:
    store = Store.open(tmp_path / "state")
    return Service(cell, drivers, store, out_dir=tmp_path / "datasets")


@needs_routine
def test_a_button_press_writes_back_a_frame_that_matches_the_truth(cell, tmp_path):
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        service.report = lambda run_id, result, store, ending: write_run_report(tmp_path / "reports", run_id,
                                                                                 result, ending=ending)
        panel = drivers.panel
        panel.select_routine(1)
        panel.press_start()
        service.poll_panel()
        outcome = service.wait(60)
        assert outcome.state == "done" and outcome.code == ResultCode.OK, outcome.reason
        frame = drivers.robot.tool_frame()
        np.testing.assert_allclose(frame, outcome.result.tool_frame, atol=1e-12)
        score = drivers.world.truth.score_tool_frame(frame)
        assert score["position_error_mm"] <= 0.03 and score["axis_error_deg"] <= 0.03, score
        assert panel.lamps == {"busy": False, "done": True, "fault": False}
        assert panel.result_code == 0 and panel.run_counter == 1
        states = [s for _, s, _ in service.store.states(outcome.run_id)]
        assert states == ["checking", "running", "solving", "gates", "writing back", "done"]
        writes = service.store.tool_frames()
        assert len(writes) == 1 and writes[0]["frame_after"] == pytest.approx(list(frame))
        stored = drivers.robot.stored_tool_frame()  # what the robot program applies at its next start
        assert stored.generation == outcome.run_id and np.array_equal(stored.tool_frame, frame)
        assert writes[0]["stored_before"]["generation"] == 0
    report = Path(service.store.run(outcome.run_id).report_path)
    assert report.parent == tmp_path / "reports" / f"run-{outcome.run_id}"
    assert_page_draws(report, "beam 0, looking along it", "beam 1, looking along it", "each edge off the reach circle")
    edge_residuals = np.sort(np.asarray(outcome.result.residuals_mm))
    drawn = np.sort(np.concatenate([layer(outcome.result, "each edge off the reach circle", f"beam {ch}")[:, 1]
                                    for ch in (0, 1)]))
    np.testing.assert_allclose(drawn, edge_residuals, atol=1e-9)  # the dots off the circle are the fit's residuals


@needs_routine
def test_a_start_after_a_run_left_the_wrist_beyond_a_turn_unwinds_it_and_runs(cell, tmp_path):
    """An aborted run can leave joint 6 a little beyond a full turn (its stop ramp past -360 deg):
    the next start plans from there, turns the wrist back by a turn first, and runs to its end;
    a move checked from where the arm is is never a service fault."""
    from cellcal.config.robot_files import load_robot

    low = load_robot(cell.robot).joint_limits[5, 0]
    with open_drivers(cell) as drivers:
        q = np.asarray(cell.home_q_rad, dtype=float).copy()
        q[5] = low - np.deg2rad(0.02)
        arm = drivers.world.arm  # put there as a stop ramp leaves it (a controller refuses such a target)
        arm.q = q
        arm.set_tcp(arm.tcp_offset)
        service = service_on(cell, drivers, tmp_path)
        drivers.panel.select_routine(1)  # tcp-laser
        drivers.panel.press_start()
        service.poll_panel()
        outcome = service.wait(60)
        assert (outcome.state, outcome.code) == ("done", ResultCode.OK), outcome.reason
        assert low <= drivers.robot.actual_q()[5] <= -low


@needs_routine
def test_a_press_while_running_is_ignored_and_abort_stops_without_write_back(cell, tmp_path):
    with open_drivers(cell) as drivers:
        held = HeldRobot(drivers.robot)
        drivers.robot = held
        service = service_on(cell, drivers, tmp_path)
        before = held.robot.tool_frame()
        service.start(ROUTINE)
        assert held.moving.wait(10)
        drivers.panel.press_start()
        service.poll_panel()  # ignored, and the request cleared
        assert not drivers.panel.start_requested() and service.busy()
        drivers.panel.press_abort()
        service.poll_panel()
        outcome = service.wait(10)
        assert outcome.state == "aborted" and outcome.code == ResultCode.ABORTED, outcome.reason
        np.testing.assert_array_equal(held.robot.tool_frame(), before)
        assert service.store.tool_frames() == []
        assert len(service.store.runs()) == 1  # the ignored press started nothing


@needs_routine
@pytest.mark.parametrize("fault, code", [
    ("protective stop", ResultCode.ROBOT_FAULT),
    ("trigger lost", ResultCode.SENSOR_FAULT),
])
def test_a_fault_mid_run_keeps_the_old_frame_and_says_why(cell, tmp_path, fault, code):
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        before = drivers.robot.tool_frame()
        if fault == "protective stop":
            drivers.world.protective_stop("injected", after_motion_s=0.3)
        else:
            drivers.trigger.close()
        outcome = service.run(ROUTINE)
        assert outcome.state == "fault" and outcome.code == code, outcome.reason
        np.testing.assert_array_equal(drivers.robot.tool_frame(), before)
        assert drivers.robot.stored_tool_frame().generation == 0
        assert drivers.panel.lamps["fault"] and drivers.panel.result_code == code


@needs_routine
def test_a_start_when_the_robot_is_not_ready_is_refused_and_nothing_moves(cell, tmp_path):
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        drivers.world.protective_stop("stopped before the press")
        q = drivers.robot.actual_q()
        outcome = service.run(ROUTINE)
        assert outcome.state == "refused" and outcome.code == ResultCode.NOT_READY
        np.testing.assert_array_equal(drivers.robot.actual_q(), q)


@needs_routine
def test_a_result_failing_a_gate_is_never_written(tmp_path):
    """The real tool 15 mm off its drawing: the plausibility gate fails, the frame stays."""
    cell = load_cell(edited_cell(tmp_path, "sim", {"sim_truth": {"tool_tcp_error_mm": 15.0}}, name="far.yaml"))
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        before = drivers.robot.tool_frame()
        outcome = service.run(ROUTINE)
        assert outcome.code in (ResultCode.GATE_FAILED, ResultCode.COMPUTATION_FAILED), outcome.reason
        np.testing.assert_array_equal(drivers.robot.tool_frame(), before)
        assert drivers.robot.stored_tool_frame().generation == 0
        assert service.store.tool_frames() == []


def test_every_result_code_is_documented_on_the_panel_page():
    page = (ROOT / "docs" / "panel.md").read_text()
    for code in ResultCode:
        assert f"| {int(code)} | `{code.name}` |" in page, code
        assert RESULT_MEANINGS[code]


# -- the service process: systemd's notify protocol, signals ----------------------------

def _daemon(tmp_path, notify_path: Path, extra_env=None):
    env = dict(os.environ, NOTIFY_SOCKET=str(notify_path), WATCHDOG_USEC="200000", **(extra_env or {}))
    env.pop("WATCHDOG_PID", None)
    return subprocess.Popen([sys.executable, "-m", "cellcal.cli.main", "daemon", "--cell", "sim",
                             "--state-dir", str(tmp_path / "state")], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _messages(sock: socket.socket, until: str, timeout_s: float) -> list[str]:
    got, deadline = [], time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        sock.settimeout(max(deadline - time.monotonic(), 0.01))
        try:
            got.append(sock.recv(4096).decode())
        except socket.timeout:
            break
        if until in got[-1]:
            break
    return got


def test_the_daemon_speaks_the_notify_protocol_and_stops_on_sigterm(tmp_path):
    path = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(path))
        proc = _daemon(tmp_path, path)
        try:
            first = _messages(sock, "READY=1", 30)
            assert first and "READY=1" in first[-1], (first, proc.stderr.read() if proc.poll() else "")
            watchdog = _messages(sock, "WATCHDOG=1", 2)
            assert any("WATCHDOG=1" in m for m in watchdog), watchdog
            proc.send_signal(signal.SIGTERM)
            last = _messages(sock, "STOPPING=1", 5)
            assert any("STOPPING=1" in m for m in last), last
            # exit 0 before systemd would kill it (the unit's TimeoutStopSec); not a speed claim
            assert proc.wait(timeout=systemd_stop_timeout_s()) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    order = [m for m in first + watchdog + last]
    ready = next(i for i, m in enumerate(order) if "READY=1" in m)
    stop = next(i for i, m in enumerate(order) if "STOPPING=1" in m)
    assert ready < min(i for i, m in enumerate(order) if "WATCHDOG=1" in m) < stop


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_the_unit_file_verifies(tmp_path):
    unit = (ROOT / "config" / "cellcal.service").read_text()
    exe = Path(sys.executable).parent / "cellcal"
    unit = unit.replace("/opt/cellcal/bin/cellcal", str(exe))
    (tmp_path / "cellcal.service").write_text(unit)
    proc = subprocess.run(["systemd-analyze", "verify", str(tmp_path / "cellcal.service")],
                          capture_output=True, text=True, timeout=60)
    problems = [line for line in proc.stderr.splitlines() if "cellcal.service" in line]
    assert not problems, proc.stderr
