"""The service against a hostile operator and a bad morning, in process on the simulated cell.

The operator plays the SimPanel; the store is a real one in the test's folder. What needs
the networked cell and the daemon as a process (Ctrl-C, a restart with a stop still on,
the Modbus coils written together) is in test_service_reliability_net.py.
"""
from __future__ import annotations

import sqlite3
import threading

import numpy as np
import pytest

from cellcal.daemon import outcome as outcome_registers
from cellcal.daemon import tool_custody
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.daemon.service import ResultCode, Service
from cellcal.daemon.store import Store
from cellcal.drivers.interfaces import RobotState
from cellcal.routines.framework import registry
from support.service_panel import press

CALIBRATED = np.array([0.0004, -0.0003, 0.1496, 0.004, -0.003, 0.0])  # a previous calibration's frame


@pytest.fixture
def cell():
    return load_cell("sim")


def service_on(cell, drivers, folder, store=None) -> Service:
    return Service(cell, drivers, store or Store.open(folder / "state"), out_dir=folder / "state" / "datasets")


def test_start_pressed_together_with_abort_starts_nothing(cell, tmp_path):
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        q = drivers.robot.actual_q()
        press(service, drivers.panel, "tcp-laser", abort=True)
        assert not service.busy() and service.store.runs() == []
        np.testing.assert_array_equal(drivers.robot.actual_q(), q)
        # the press is answered (counted, so a PLC sees it): abort won
        assert drivers.panel.result_code == ResultCode.ABORTED and drivers.panel.run_counter == 1
        assert not drivers.panel.lamps["busy"]
        assert [kind for _, kind, _ in service.store.events()] == ["start_discarded"]


def test_a_routine_the_cell_cannot_run_is_refused_at_once_with_the_lamps_right(cell, tmp_path):
    """handshake (selector 4) on a one-robot cell: refused, not a traceback and a stuck busy lamp."""
    assert registry.unavailable("handshake", cell) is not None
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        outcome = press(service, drivers.panel, "handshake")
        assert (outcome.state, outcome.code) == ("refused", ResultCode.NO_SUCH_ROUTINE), outcome.reason
        assert "two robots" in outcome.reason
        assert drivers.panel.lamps == {"busy": False, "done": False, "fault": True}
        assert drivers.panel.result_code == ResultCode.NO_SUCH_ROUTINE
        assert service.store.run(outcome.run_id).state == "refused"


def test_a_blocked_datasets_folder_is_refused_before_anything_moves(cell, tmp_path):
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        service.out_dir.parent.mkdir(parents=True, exist_ok=True)
        service.out_dir.write_text("x")  # a file where the datasets folder belongs
        q, frame = drivers.robot.actual_q(), drivers.robot.tool_frame()
        outcome = press(service, drivers.panel, "tcp-npoint")
        assert (outcome.state, outcome.code) == ("refused", ResultCode.SERVICE_FAULT), outcome.reason
        assert str(service.out_dir) in outcome.reason
        np.testing.assert_array_equal(drivers.robot.actual_q(), q)
        np.testing.assert_array_equal(drivers.robot.tool_frame(), frame)
        assert drivers.panel.lamps == {"busy": False, "done": False, "fault": True}
        assert service.store.owed_frame() is None


class FailingStore(Store):
    """A store that stops taking writes once the run has measured (a disk that filled up, a
    state folder someone made read-only under the running service)."""

    def record_result(self, run_id, result):
        raise sqlite3.OperationalError("attempt to write a readonly database")


def test_the_service_s_own_fault_mid_run_ends_in_fault_with_its_code_and_the_old_frame(cell, tmp_path):
    with open_drivers(cell) as drivers:
        drivers.robot.set_tcp(CALIBRATED)
        store = FailingStore(tmp_path / "state" / "cellcal.db")
        service = service_on(cell, drivers, tmp_path, store)
        outcome = press(service, drivers.panel, "tcp-npoint")
        assert (outcome.state, outcome.code) == ("fault", ResultCode.SERVICE_FAULT), outcome.reason
        assert "readonly database" in outcome.reason
        assert drivers.panel.lamps == {"busy": False, "done": False, "fault": True}
        assert drivers.panel.result_code == ResultCode.SERVICE_FAULT and not service.busy()
        np.testing.assert_array_equal(drivers.robot.tool_frame(), CALIBRATED)  # never the drawing
        assert store.run(outcome.run_id).state == "fault"  # not left open for the next start


def test_the_done_lamp_means_a_frame_was_written_and_a_new_run_clears_the_lamps(cell, tmp_path):
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        panel = drivers.panel
        outcome = press(service, panel, 99)  # no routine: refused, fault lamp
        assert outcome.code == ResultCode.NO_SUCH_ROUTINE and panel.lamps["fault"]
        seen = []
        real = panel.set_lamps
        panel.set_lamps = lambda **lamps: (seen.append(dict(lamps)), real(**lamps))[1]
        outcome = press(service, panel, "tcp-npoint")
        assert (outcome.state, outcome.code) == ("done", ResultCode.OK), outcome.reason
        assert seen[0] == {"busy": True, "done": False, "fault": False}  # the start cleared the last run's lamps
        assert panel.lamps == {"busy": False, "done": True, "fault": False}
        assert len(service.store.tool_frames()) == 1


def test_a_run_that_writes_no_frame_does_not_light_the_done_lamp(cell, tmp_path):
    """A routine that determines no tool frame (tracker: the kinematics) ends OK, dark."""
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        drivers.panel.lamps["done"] = True  # left by an earlier run
        outcome = service.run("tracker")
        assert outcome.code in (ResultCode.OK, ResultCode.GATE_FAILED), outcome.reason
        assert outcome.result is not None and outcome.result.tool_frame is None
        assert drivers.panel.lamps["done"] is False
        assert service.store.tool_frames() == []


def test_a_start_during_a_run_answers_busy(cell, tmp_path):
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        release, moving = threading.Event(), threading.Event()
        robot = drivers.robot
        real_move = robot.move_j

        def held_move(*args, **kwargs):
            moving.set()
            release.wait(30)
            return real_move(*args, **kwargs)
        robot.move_j = held_move
        service.start("tcp-npoint")
        assert moving.wait(30)
        drivers.panel.press_start()
        service.poll_panel()
        assert drivers.panel.result_code == ResultCode.BUSY and drivers.panel.run_counter == 0
        assert drivers.panel.lamps["busy"]
        release.set()
        robot.move_j = real_move
        outcome = service.wait(120)
        assert outcome.code == ResultCode.OK, outcome.reason
        assert drivers.panel.result_code == ResultCode.OK and drivers.panel.run_counter == 1


class LostRobot:
    """A robot whose connection is gone: it answers nothing useful."""

    def __init__(self, robot):
        self.robot = robot

    def state(self):
        return RobotState.DISCONNECTED

    def close(self):
        pass

    def __getattr__(self, name):
        return getattr(self.robot, name)


def test_a_reconnection_runs_off_the_main_loop_and_a_start_meanwhile_is_not_ready(cell, tmp_path, monkeypatch):
    """The reconnection blocks (a controller that does not answer the connect): the panel is
    still served, a start is refused NOT_READY, and the swap comes when the connect does."""
    monkeypatch.setattr(tool_custody, "RECONNECT_AFTER_S", 0.0)
    with open_drivers(cell) as drivers:
        real = drivers.robot
        drivers.robot = LostRobot(real)
        drivers.robots = {"a": drivers.robot}
        connecting, go_on = threading.Event(), threading.Event()

        def reconnect():
            connecting.set()
            assert go_on.wait(30)
            fresh = open_drivers(cell)
            fresh.panel = drivers.panel  # the operator's panel in memory stays the same one
            return fresh
        service = Service(cell, drivers, Store.open(tmp_path / "state"), out_dir=tmp_path / "datasets",
                          reconnect=reconnect)
        service.poll_panel()  # the loss is seen
        service.poll_panel()  # the reconnection starts
        assert connecting.wait(10)
        outcome = press(service, drivers.panel, "tcp-npoint")  # the main loop is not blocked by the connect
        assert (outcome.state, outcome.code) == ("refused", ResultCode.NOT_READY), outcome.reason
        assert "reconnecting" in outcome.reason
        go_on.set()
        service._reconnecting.join(30)
        assert service.drivers is not drivers and service.drivers.robot.state() is RobotState.READY
        service.drivers.close()


def test_a_frame_owed_from_before_a_newer_write_never_comes_back(tmp_path):
    store = Store.open(tmp_path)
    one = store.begin_run("tcp-npoint", "sim.yaml")
    store.owe_frame(one, [0.0, 0.0, 0.15, 0.0, 0.0, 0.0])
    assert store.owed_frame() == (one, [0.0, 0.0, 0.15, 0.0, 0.0, 0.0])
    two = store.begin_run("tcp-npoint", "sim.yaml")
    store.owe_frame(two, [0.0, 0.0, 0.149, 0.0, 0.0, 0.0])
    store.record_tool_frame(two, "write", [0.0, 0.0, 0.149, 0.0, 0.0, 0.0], [0.0, 0.0, 0.1491, 0.0, 0.0, 0.0])
    assert store.owed_frame() is None  # run 2 wrote a newer frame: run 1's is stale, and so is run 2's
    three = store.begin_run("tcp-npoint", "sim.yaml")
    store.owe_frame(three, [0.0, 0.0, 0.1491, 0.0, 0.0, 0.0])
    assert store.owed_frame() == (three, [0.0, 0.0, 0.1491, 0.0, 0.0, 0.0])
    store.frame_settled(three)
    assert store.owed_frame() is None
    store.close()


def test_demo_offers_only_what_the_cell_can_run(capsys):
    from cellcal.cli.main import main
    assert main(["demo", "--routine", "handshake"]) == 2  # at once: nothing was started
    err = capsys.readouterr().err
    assert "cannot run it" in err and "two robots" in err and "tcp-laser" in err


def test_the_outcome_registers_carry_the_change_written_before_the_result(cell, tmp_path):
    """A tcp-npoint run (it determines the tip only): verdict 0, tool 1, the tip's change as
    written, the tilt not determined; written before the result code and the counter."""
    from cellcal.daemon import outcome

    with open_drivers(cell) as drivers:
        drivers.robot.set_tcp(CALIBRATED)
        service = service_on(cell, drivers, tmp_path)
        order = []
        panel = drivers.panel
        real_outcome, real_result = panel.set_outcome, panel.set_result
        panel.set_outcome = lambda registers: (order.append("outcome"), real_outcome(registers))[1]
        panel.set_result = lambda *a, **k: (order.append("result"), real_result(*a, **k))[1]
        result = press(service, panel, "tcp-npoint")
        assert result.code == ResultCode.OK, result.reason
        assert order[-2:] == ["outcome", "result"]
        seen = outcome.decoded(panel.outcome)
        written = drivers.robot.tool_frame()
        assert seen["verdict"] is None  # 0: a calibration, no check verdict
        assert seen["tool_id"] == 1 and seen["tilt_x_deg"] is None and seen["tilt_y_deg"] is None
        for k, key in enumerate(("x_mm", "y_mm", "z_mm")):
            # the register holds whole thousandths of a mm: within half of one of the frame's change
            assert seen[key] == pytest.approx((written[k] - CALIBRATED[k]) * 1e3, abs=5e-4)


def test_an_abort_read_just_after_the_start_still_wins_and_the_press_is_answered(cell, tmp_path):
    """The two coils are read one after the other: an abort that lands between the reads (or
    coils written together and read apart) still starts nothing, and the press is answered."""
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        panel = drivers.panel
        real = panel.routine_selector

        def selector_then_abort():
            panel.press_abort()  # the operator's abort arrives while the start is being confirmed
            return real()
        panel.routine_selector = selector_then_abort
        press(service, panel, "tcp-npoint")
        assert not service.busy() and service.store.runs() == []
        assert panel.result_code == ResultCode.ABORTED and panel.run_counter == 1


def test_a_start_for_a_tool_that_is_not_mounted_is_refused_and_nothing_moves(tmp_path):
    """A cell of two tools, tool 1 mounted: the tool selector naming tool 2, or a tool the cell
    lacks, refuses the start (code 14); 0 or tool 1 runs with tool 1."""
    from support.cell_edits import edited_cell  # tests/support/cell_edits.py

    def two_tools(doc):
        tool = doc.pop("tool")
        doc["tools"] = [{"id": 1, "name": "torch", **tool},
                        {"id": 2, "name": "spare", **tool, "tcp_m": [0.0, 0.0, 0.17]}]
        doc["mounted"] = 1
    cell = load_cell(edited_cell(tmp_path, "sim", two_tools, name="two-tools.yaml"))
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, tmp_path)
        q = drivers.robot.actual_q()
        for tool, words in ((2, "names tool 2 (spare) but tool 1 (torch) is mounted"), (9, "no such tool")):
            drivers.panel.select_tool(tool)
            outcome = press(service, drivers.panel, "tcp-npoint")
            assert (outcome.state, outcome.code) == ("refused", ResultCode.TOOL_NOT_MOUNTED), outcome.reason
            assert words in outcome.reason
            assert drivers.panel.result_code == ResultCode.TOOL_NOT_MOUNTED and drivers.panel.lamps["fault"]
            np.testing.assert_array_equal(drivers.robot.actual_q(), q)
        drivers.panel.select_tool(1)
        outcome = press(service, drivers.panel, "tcp-npoint")
        assert outcome.code == ResultCode.OK, outcome.reason
        assert outcome_registers.decoded(drivers.panel.outcome)["tool_id"] == 1
