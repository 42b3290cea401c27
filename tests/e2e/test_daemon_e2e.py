"""The service end to end over loopback, on the networked simulated cell (sim-net).

The fakes (the fake UR controller in its own process, the Modbus IO module serving the
panel and the trigger ring, the tracker server) run once for the module on a loopback
address of their own. The operator is played on the IO module: select a routine, press
start. Each driver fault runs the service in process (``Service`` with the cell's real
drivers: ur_rtde, pymodbus, the tracker socket) so the test can drive its main loop's
panel poll; what needs a process of its own (SIGTERM, SIGKILL, the count of its sockets,
threads and file descriptors) runs ``cellcal daemon`` (tests/support/daemon_harness.py has the
fakes, the short cell and the daemon process; tests/e2e/conftest.py's cellcal_daemon stops
every daemon a test started).

The cell is sim-net with short routine sections (tcp-laser with one turn and one tilt,
a small tracker campaign), so a run reaches its first motion, and its fault, quickly.
Before each case the controller is given a previous calibration's tool frame (the
drawing moved by 0.4 mm): the routines set the drawing while they measure, so a frame
left behind by a fault would show.
"""
from __future__ import annotations

import logging
import signal
import threading
import time

import numpy as np
import pytest

from cellcal.daemon.cells import open_drivers
from cellcal.daemon.service import ResultCode, Service
from cellcal.daemon.store import Store
from cellcal.sims.fake_ur.process import ControlClient
from support.daemon_harness import (RUN_TIMEOUT_S, SELECT, Net, one_run, press_start, resources,  # tests/support/daemon_harness.py
                            settled, sim_sleep, systemd_stop_timeout_s, until_the_run_ends)

pytestmark = pytest.mark.slow

INJECT_AFTER_MOTION_S = 0.15  # a fault of the controller once the arm has moved this long


def when_moving(net: Net, action, delay_s: float = 0.1) -> threading.Thread:
    """Run `action` once the fake arm has moved `delay_s` of its time (a fault of a device other than the arm)."""
    def watch():
        control = ControlClient(net.host)
        try:
            deadline = time.monotonic() + RUN_TIMEOUT_S
            while not control.request(cmd="state")["moving"] and time.monotonic() < deadline:
                time.sleep(0.01)
            sim_sleep(control, delay_s)
            action()
        finally:
            control.close()
    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


def press_and_serve(service: Service, net: Net, routine: str):
    """The operator selects `routine` and presses start; the main loop's poll runs until the run ends."""
    counter = net.panel.run_counter()
    net.panel.select_routine(SELECT[routine])
    net.panel.press_start()
    until_the_run_ends(net, counter, service.poll_panel)
    return service.wait(10.0)


def controller_fault(kind: str):
    return lambda net: net.control.request(cmd="fault", kind=kind, after_motion_s=INJECT_AFTER_MOTION_S)


def io_module_fault(**change):
    def inject(net):
        return when_moving(net, lambda: [setattr(net.panel, k, v) for k, v in change.items()])
    return inject


def tracker_silent(net):
    net.sim.tracker.silent = True


def clear_io_faults(net):
    net.panel.clear_faults()
    net.sim.tracker.silent = False


# (routine, how the fault is injected, the result code it must end with, how the cell recovers)
FAULTS = {
    "robot connection lost": ("tcp-laser", controller_fault("drop"), ResultCode.ROBOT_FAULT, lambda net: None),
    "protective stop": ("tcp-laser", controller_fault("protective_stop"), ResultCode.ROBOT_FAULT,
                        lambda net: net.dashboard("unlock protective stop")),
    "emergency stop": ("tcp-laser", controller_fault("emergency_stop"), ResultCode.ROBOT_FAULT,
                       lambda net: net.dashboard("restart safety")),
    "controller stops answering": ("tcp-laser", controller_fault("stall"), ResultCode.DEVICE_TIMEOUT,
                                   lambda net: net.control.request(cmd="fault", kind="resume")),
    "trigger silent": ("tcp-laser", io_module_fault(silent=frozenset({4})), ResultCode.SENSOR_FAULT, clear_io_faults),
    "Modbus exception": ("tcp-laser", io_module_fault(exceptions={4: 4}), ResultCode.SENSOR_FAULT, clear_io_faults),
    "tracker silent": ("tracker", tracker_silent, ResultCode.SENSOR_FAULT, clear_io_faults),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_a_driver_fault_ends_the_run_in_fault_with_its_code_and_the_old_frame(cell_net, tmp_path, fault):
    """The run ends in fault with the fault's code on the panel and in the store, the arm at
    rest; once the cause is cleared the idle loop gives the controller its old frame back
    (reconnecting a lost robot), and the store says so."""
    net = cell_net
    routine, inject, code, release = FAULTS[fault]
    counter = net.panel.run_counter()
    service = Service(net.cell, open_drivers(net.cell), Store.open(tmp_path / "state"),
                      out_dir=tmp_path / "datasets", reconnect=lambda: open_drivers(net.cell))
    try:
        inject(net)
        outcome = press_and_serve(service, net, routine)
        first, later = net.at_rest()
        assert outcome.state == "fault" and outcome.code == code, outcome.reason
        assert net.panel.result_code() == code and net.panel.run_counter() == counter + 1
        assert net.panel.lamps() == {"busy": False, "done": False, "fault": True}
        row = service.store.run(outcome.run_id)
        assert (row.state, row.result_code) == ("fault", int(code)) and service.store.tool_frames() == []
        assert not first["moving"] and np.array_equal(first["q"], later["q"]), (first, later)
        release(net)
        deadline = time.monotonic() + 10.0
        while not np.allclose(net.state()["tcp_offset"], net.previous, rtol=0, atol=1e-12):
            assert time.monotonic() < deadline, (net.state()["tcp_offset"], net.previous)
            service.poll_panel()
            time.sleep(0.05)
        events = [kind for _, kind, _ in service.store.events()]
        if code in (ResultCode.ROBOT_FAULT, ResultCode.DEVICE_TIMEOUT):  # the routine could not give it back itself
            assert "tool_frame_given_back" in events, events
        if fault == "robot connection lost":
            assert "reconnected" in events, events
        elif code is ResultCode.SENSOR_FAULT:
            assert "reconnected" not in events, events
        assert net.panel.run_counter() == counter + 1 and not net.state()["moving"]  # nothing started meanwhile
    finally:
        service.drivers.close()
        service.store.close()


# -- the service as a process ------------------------------------------------------------

def test_sigterm_mid_routine_stops_the_arm_writes_nothing_and_exits_0_before_systemd_would_kill_it(
        cell_net, cellcal_daemon):
    net = cell_net
    daemon = cellcal_daemon(net)
    try:
        press_start(net, "tcp-laser")
        sim_sleep(net.control, 0.2)  # mid-routine
        daemon.proc.send_signal(signal.SIGTERM)
        # systemd's stop must not have to kill it: exit 0 within the unit's TimeoutStopSec
        assert daemon.proc.wait(timeout=systemd_stop_timeout_s()) == 0, daemon.log()
    finally:
        daemon.stop()
    first, later = net.at_rest()
    assert not first["moving"] and np.array_equal(first["q"], later["q"])
    store = Store.open(daemon.state_dir)
    run = store.runs()[0]
    assert (run.state, run.result_code) == ("aborted", ResultCode.ABORTED), run
    assert store.tool_frames() == []
    store.close()
    assert net.panel.result_code() == ResultCode.ABORTED and not net.panel.lamps()["busy"]
    np.testing.assert_allclose(later["tcp_offset"], net.previous, rtol=0, atol=1e-12)


def test_after_kill_9_mid_run_the_daemon_comes_up_idle_nothing_moves_and_the_run_shows_interrupted(cell_net,
                                                                                                   cellcal_daemon):
    net = cell_net
    daemon = cellcal_daemon(net)
    press_start(net, "tcp-laser")
    sim_sleep(net.control, 0.2)  # mid-run
    daemon.proc.kill()
    daemon.proc.wait()
    net.at_rest(0.0)  # the controller ends the motion it was given
    left = net.state()["tcp_offset"]
    np.testing.assert_allclose(left, net.cell.tool.tcp_pose, rtol=0, atol=1e-12)  # the drawing the run set
    again = cellcal_daemon(net)  # on the same state folder
    try:
        looks = []
        for _ in range(10):  # a second of the arm after the restart
            looks.append(net.state())
            time.sleep(0.1)
        run = again.cli("runs", "show", "1")
        assert (run["state"], run["result_code"]) == ("interrupted", ResultCode.INTERRUPTED), run
        assert not net.panel.lamps()["busy"]
        # the panel says it too, not the code of the run before: a PLC acts on the register
        assert net.panel.result_code() == ResultCode.INTERRUPTED and net.panel.lamps()["fault"]
        frame = net.state()["tcp_offset"]  # the run had set the drawing; the old frame is given back
    finally:
        assert again.stop() == 0
    assert not any(look["moving"] for look in looks)
    assert all(np.array_equal(look["q"], looks[0]["q"]) for look in looks), [look["q"] for look in looks]
    assert "run 1: interrupted" in again.log()
    np.testing.assert_allclose(frame, net.previous, rtol=0, atol=1e-12)
    store = Store.open(again.state_dir)
    assert [r.id for r in store.runs()] == [1]  # and no run started by itself
    store.close()


def test_a_panel_that_drops_and_comes_back_never_starts_a_run_from_an_unconfirmed_request(cell_net, tmp_path,
                                                                                          caplog):
    """The IO module stops answering and its connections are cut; a press made meanwhile is
    cleared when it comes back, not run; the service keeps serving, and said so in its log
    and its store."""
    caplog.set_level(logging.INFO, logger="cellcal.daemon")
    net = cell_net
    service = Service(net.cell, open_drivers(net.cell), Store.open(tmp_path / "state"),
                      out_dir=tmp_path / "datasets")
    try:
        service.poll_panel()
        net.panel.silent = frozenset({1, 3, 5, 6})  # the panel's functions: coils and holding registers
        net.panel.drop_connections()
        service.poll_panel()
        net.panel.select_routine(SELECT["tcp-laser"])
        net.panel.press_start()  # pressed while the daemon cannot see the panel
        service.poll_panel()
        net.panel.clear_faults()
        for _ in range(5):
            service.poll_panel()
        assert not net.panel.start_request_pending() and not service.busy()
        assert service.store.runs() == [] and not net.state()["moving"]
        events = [kind for _, kind, _ in service.store.events()]
        assert events == ["panel_lost", "panel_back", "start_discarded"], events
        assert "panel lost" in caplog.text and "panel back" in caplog.text and "not started" in caplog.text
        net.panel.select_routine(99)  # a press after it came back is taken: a selector no routine has
        net.panel.press_start()
        service.poll_panel()
        outcome = service.wait(10.0)
        assert (outcome.state, outcome.code) == ("refused", ResultCode.NO_SUCH_ROUTINE)
        assert net.panel.result_code() == ResultCode.NO_SUCH_ROUTINE
    finally:
        service.drivers.close()
        service.store.close()


def test_a_hundred_button_started_runs_leak_no_socket_thread_or_file_descriptor(cell_net, cellcal_daemon):
    net = cell_net
    daemon = cellcal_daemon(net)
    try:
        for ending in ("complete", "aborted", "refused"):  # what a first run of each kind opens for good
            one_run(net, ending)
        before = settled(daemon.proc.pid, resources(daemon.proc.pid))
        endings = ["complete" if k == 50 else "aborted" if k % 2 else "refused" for k in range(100)]
        t0 = time.monotonic()
        for ending in endings:
            one_run(net, ending)
        took_s = time.monotonic() - t0
        after = settled(daemon.proc.pid, before)
        store = Store.open(daemon.state_dir)
        runs = store.runs(1000)
        store.close()
    finally:
        assert daemon.stop() == 0
    assert after == before, (before, after)
    states = [r.state for r in runs[:100]][::-1]
    assert states.count("refused") == 49 and states.count("aborted") == 50, states
    assert states[50] == "fault" and runs[49].result_code == ResultCode.GATE_FAILED  # the short plan decides little
    print(f"100 runs in {took_s:.1f} s; daemon holds {before}")
