"""kinematic-fixture with one plate the operator moves between placements (``move_by: operator``), on the
in-process simulated cell with the service and its panel: the routine waits at home with the waiting lamp
lit and the placement in its register, the simulated operator moves the plate (to where it really lies at
that placement) and presses confirm; abort during the wait, the wait's timeout, and a confirm pressed
when nothing waits. Simulated time: the arm's motion costs no wall time, the waits do."""
from __future__ import annotations

import time

import numpy as np
import pytest

from support.cell_edits import edited_cell
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.daemon.service import ResultCode, Service
from cellcal.daemon.store import Store
from support.service_panel import SELECT

WAIT_S = 60.0  # a bound for a run that hangs, far above any case's real duration


def operator_cell(folder, timeout_s: float = 60.0):
    """sim with one plate moved by the operator between two of its placements, 4 seats per socket (the
    fewest the section takes: 16 seats, which the solver identifies with every gate passed); the arm's
    limits raised (less simulated motion to compute)."""
    def plate(doc):
        doc["limits"].update(tcp_speed_m_s=1.0, tcp_accel_m_s2=10.0, joint_speed_rad_s=3.0, joint_accel_rad_s2=10.0)
        section = doc["kinematic_fixture"]
        section.update(placements=section["placements"][:2], orientations=4, wrist_flip=False, move_by="operator",
                       confirm_timeout_s=timeout_s)
    return load_cell(edited_cell(folder, "sim", plate, name="plate-by-hand.yaml"))


def poll_until(service: Service, condition, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not condition():
        assert time.monotonic() < deadline, what
        service.poll_panel()
        time.sleep(0.05)


def start(service: Service, panel) -> None:
    panel.select_routine(SELECT["kinematic-fixture"])
    panel.press_start()
    service.poll_panel()
    assert service.busy()


def test_pressing_confirm_moves_the_simulated_plate_to_the_placement_asked_for(tmp_path):
    """The simulated operator: the plate is at the first placement as the run starts, and a confirm
    while the waiting lamp asks for placement 2 first puts it where placement 2 really is."""
    cell = operator_cell(tmp_path)
    with open_drivers(cell) as drivers:
        panel, world = drivers.panel, drivers.world
        truth = {(setup, point): where for setup, point, where in world.truth.sockets}
        at = lambda: [tuple(s.seat_m[:2]) for s in world.sockets]  # noqa: E731 (a seat is the point, a tip radius up)
        assert world.truth.plate_moved and at() == [tuple(truth[("p1", p)][:2]) for p in ("s0", "s1")]
        panel.press_confirm()  # nothing waits: the plate stays
        assert at() == [tuple(truth[("p1", p)][:2]) for p in ("s0", "s1")]
        panel.set_waiting(2)
        panel.press_confirm()
        assert at() == [tuple(truth[("p2", p)][:2]) for p in ("s0", "s1")] and panel.confirm_requested()


def test_confirming_without_moving_the_plate_misses_the_next_placement(tmp_path):
    """The plate really is at one placement at a time: confirmed but not moved, the seats of the next
    placement find no socket, and the run says so (nothing written)."""
    cell = operator_cell(tmp_path)
    with open_drivers(cell) as drivers:
        panel = drivers.panel
        service = Service(cell, drivers, Store.open(tmp_path / "state"), out_dir=tmp_path / "datasets")
        # a confirm with nothing waiting is cleared and forgotten: it confirms no later wait
        panel.press_confirm()
        service.poll_panel()
        assert not panel.confirm_requested() and not service.busy()
        refused = service.run("no-such-routine")  # a run that ended before this one: kept apart from it
        assert refused.code == ResultCode.NO_SUCH_ROUTINE
        start(service, panel)
        poll_until(service, lambda: panel.waiting == 1, "the routine never asked for placement 1")
        for _ in range(5):  # it keeps waiting, parked at home, until confirmed
            service.poll_panel()
        assert panel.waiting == 1
        np.testing.assert_allclose(drivers.robot.actual_q(), cell.home_q_rad, atol=1e-9)
        # the status page's headline says what the operator is to do, and how long is left to confirm
        status = service.status()
        assert status["health"]["level"] == "waiting", status["health"]
        assert status["health"]["says"].startswith("waiting for the operator: ") and \
            "placement p1" in status["health"]["says"], status["health"]
        # operator_cell's confirm_timeout_s is 60 s
        assert status["waiting"]["step"] == 1 and 0.0 < status["waiting"]["time_left_s"] <= 60.0, status
        # the run under way and the last finished one, apart
        assert status["run_id"] == refused.run_id + 1 and status["last_run_id"] == refused.run_id, status
        assert status["result_code"] == ResultCode.NO_SUCH_ROUTINE and status["reason"] == refused.reason, status
        panel.press_confirm()
        poll_until(service, lambda: panel.waiting == 2, "the routine never asked for placement 2")
        np.testing.assert_allclose(drivers.robot.actual_q(), cell.home_q_rad, atol=1e-9)  # placement 1 done: home
        panel.world = None  # the operator presses confirm and leaves the plate where it was
        panel.press_confirm()
        poll_until(service, lambda: not service.busy(), "the run did not end")
        run = service.wait(WAIT_S)
        assert (run.state, run.code) == ("fault", ResultCode.COMPUTATION_FAILED), run.reason
        assert "placement p2" in run.reason and "without touching the socket" in run.reason
        assert not list((tmp_path / "datasets").glob("kinematic-fixture-*.csv"))


def test_abort_during_the_wait_ends_the_run_aborted(tmp_path):
    cell = operator_cell(tmp_path)
    with open_drivers(cell) as drivers:
        panel = drivers.panel
        service = Service(cell, drivers, Store.open(tmp_path / "state"), out_dir=tmp_path / "datasets")
        start(service, panel)
        poll_until(service, lambda: panel.waiting == 1, "the routine never asked for placement 1")
        panel.press_abort()
        panel.press_confirm()  # pressed together: abort wins
        service.poll_panel()
        run = service.wait(WAIT_S)
        assert (run.state, run.code) == ("aborted", ResultCode.ABORTED), run.reason
        assert "waiting for the operator" in run.reason and panel.waiting == 0
        np.testing.assert_allclose(drivers.robot.actual_q(), cell.home_q_rad, atol=1e-9)  # nothing moved
        assert not list((tmp_path / "datasets").glob("kinematic-fixture-*.csv"))


def test_no_confirm_within_the_timeout_ends_the_run_with_its_code(tmp_path):
    cell = operator_cell(tmp_path, timeout_s=0.2)
    with open_drivers(cell) as drivers:
        panel = drivers.panel
        service = Service(cell, drivers, Store.open(tmp_path / "state"), out_dir=tmp_path / "datasets")
        start(service, panel)
        poll_until(service, lambda: not service.busy(), "the run did not end")
        run = service.wait(WAIT_S)
        assert (run.state, run.code) == ("fault", ResultCode.CONFIRM_TIMEOUT), run.reason
        assert "no confirm within 0.2 s" in run.reason and "placement p1" in run.reason
        assert panel.lamps["fault"] and not panel.lamps["busy"] and panel.waiting == 0
        assert panel.result_code == int(ResultCode.CONFIRM_TIMEOUT)
        assert not list((tmp_path / "datasets").glob("kinematic-fixture-*.csv"))


@pytest.mark.parametrize("edit, says", [
    ({"move_by": "robot"}, "move_by"),
    ({"move_by": "operator", "confirm_timeout_s": 0}, "confirm_timeout_s"),
    ({"confirm_timeout_s": 30}, "only with move_by: operator"),
])
def test_bad_move_by_keys_are_refused_naming_the_key(tmp_path, edit, says):
    from cellcal.config.cells import CellFileError
    with pytest.raises(CellFileError) as error:
        load_cell(edited_cell(tmp_path, "sim", {"kinematic_fixture": edit}))
    assert "kinematic_fixture" in str(error.value) and says in str(error.value)


def test_cellcal_run_without_a_terminal_to_ask_on_is_refused_before_anything_moves(tmp_path, monkeypatch):
    import io

    from support.cli_run import run_cli_captured
    cell = operator_cell(tmp_path)
    monkeypatch.setattr("sys.stdin", io.StringIO(""))  # a pipe or /dev/null: no terminal
    code, _, err = run_cli_captured("run", "kinematic-fixture", "--cell", str(cell.path),
                                    "--out", str(tmp_path / "out"))
    assert code == 2 and "move_by: operator" in err and "nothing moved" in err
    assert "cellcal daemon" in err and "move_by: fixed" in err
    assert not (tmp_path / "out").exists()
    dry_run = run_cli_captured("run", "kinematic-fixture", "--cell", str(cell.path), "--dry-run")
    assert dry_run[0] == 0  # the plan still checks


def test_the_terminal_operator_confirms_with_enter_and_times_out_without(capsys):
    import os

    from cellcal.cli.run import TerminalOperator
    from cellcal.drivers.interfaces import OperatorTimeout
    read, write = os.pipe()
    with os.fdopen(read) as stream, os.fdopen(write, "w") as keyboard:
        operator = TerminalOperator(stream)
        keyboard.write("\n")
        keyboard.flush()
        operator.confirm("move the plate to placement p2", step=2, timeout_s=5.0)  # returns: Enter was pressed
        assert "move the plate to placement p2; press Enter" in capsys.readouterr().err
        with pytest.raises(OperatorTimeout, match="no Enter within 0.05 s"):
            operator.confirm("move the plate to placement p3", step=3, timeout_s=0.05)
