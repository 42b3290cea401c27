"""The service against a hostile operator and a bad morning, end to end on sim-net.

The fakes run once for the module on a loopback address of their own
(tests/support/daemon_harness.py); before each case the controller holds a previous
calibration's tool frame (``net.previous``), so a frame lost to the drawing would show.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from cellcal.daemon import outcome
from cellcal.daemon.service import ResultCode
from cellcal.daemon.store import Store
from support.daemon_harness import RUN_TIMEOUT_S, SELECT, Net, press_start, sim_sleep, until_the_run_ends

pytestmark = pytest.mark.slow

FRAME_ATOL = 1e-12  # the controller reports the doubles it was given (daemon/frame_writer.py TOLERANCE is 1e-9)


def frame_on_controller(net: Net) -> np.ndarray:
    net.at_rest(0.0)
    return np.asarray(net.state()["tcp_offset"], dtype=float)


def test_ctrl_c_on_cellcal_run_gives_back_the_frame_from_before_the_run(cell_net, tmp_path):
    net = cell_net
    # SIGINT as a terminal delivers it: a suite started in the background of a shell without job control
    # inherits SIGINT ignored, and Python keeps an ignored SIGINT ignored (the run would go on to the end)
    run = subprocess.Popen([sys.executable, "-m", "cellcal.cli.main", "run", "tcp-npoint", "--cell", str(net.path),
                            "--out", str(tmp_path / "runs")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while not net.state()["moving"]:
        assert time.monotonic() < deadline and run.poll() is None, run.stderr.read()
        time.sleep(0.01)
    sim_sleep(net.control, 0.3)  # mid-move: a controller that is moving does not take a new tool frame
    run.send_signal(signal.SIGINT)
    _, err = run.communicate(timeout=30)
    assert run.returncode != 0 and "Traceback" not in err, err
    np.testing.assert_allclose(frame_on_controller(net), net.previous, rtol=0, atol=FRAME_ATOL)


def test_a_frame_a_stopped_run_owes_comes_back_after_a_restart_of_the_service(cell_net, cellcal_daemon):
    """A protective stop mid-run leaves the drawing on the controller (it takes no frame while
    stopped); the service is stopped before the stop is unlocked, then started again: it
    gives the old frame back once the robot is ready, not the drawing."""
    net = cell_net
    daemon = cellcal_daemon(net)
    counter = net.panel.run_counter()
    net.control.request(cmd="fault", kind="protective_stop", after_motion_s=0.15)
    press_start(net, "tcp-npoint")
    until_the_run_ends(net, counter)
    assert net.panel.result_code() == ResultCode.ROBOT_FAULT
    assert daemon.stop() == 0
    np.testing.assert_allclose(frame_on_controller(net), net.cell.tool.tcp_pose, rtol=0, atol=FRAME_ATOL)
    net.dashboard("unlock protective stop")
    again = cellcal_daemon(net)  # the same state folder
    deadline = time.monotonic() + 20.0
    # the frame goes back, then the service logs it: on a loaded machine the line can follow a moment later
    while np.abs(frame_on_controller(net) - net.previous).max() > FRAME_ATOL or \
            "tool frame from before it is back" not in again.log():
        assert time.monotonic() < deadline, again.log()
        time.sleep(0.05)
    assert again.stop() == 0


def test_start_and_abort_written_together_start_nothing(cell_net, cellcal_daemon):
    net = cell_net
    daemon = cellcal_daemon(net)
    counter, q = net.panel.run_counter(), net.state()["q"]
    net.panel.select_routine(SELECT["tcp-laser"])
    with ModbusTcpClient(net.host, port=net.sim.addresses.modbus[1]) as client:
        client.write_coils(0, [True, True], device_id=net.sim.addresses.unit_id)
    until_the_run_ends(net, counter)
    assert net.panel.result_code() == ResultCode.ABORTED
    time.sleep(0.3)
    assert not net.state()["moving"] and net.state()["q"] == q
    assert daemon.stop() == 0
    store = Store.open(daemon.state_dir)
    assert store.runs() == []
    store.close()


def test_a_routine_the_cell_cannot_run_is_refused_at_once(cell_net, cellcal_daemon):
    net = cell_net
    daemon = cellcal_daemon(net)
    counter = net.panel.run_counter()
    net.panel.select_routine(SELECT["handshake"])
    net.panel.press_start()
    until_the_run_ends(net, counter)
    assert net.panel.result_code() == ResultCode.NO_SUCH_ROUTINE
    assert net.panel.lamps() == {"busy": False, "done": False, "fault": True}
    run = daemon.cli("runs", "show", "1")
    assert (run["state"], run["result_code"]) == ("refused", ResultCode.NO_SUCH_ROUTINE), run
    assert "Traceback" not in daemon.log()
    assert daemon.stop() == 0


def test_a_blocked_datasets_folder_then_a_good_run_and_a_restart_keep_the_newest_frame(cell_net, cellcal_daemon,
                                                                                         tmp_path):
    net = cell_net
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "datasets").write_text("x")  # a file where the datasets folder belongs
    daemon = cellcal_daemon(net)
    counter = net.panel.run_counter()
    net.panel.select_routine(SELECT["tcp-npoint"])
    net.panel.press_start()
    until_the_run_ends(net, counter)
    assert net.panel.result_code() == ResultCode.SERVICE_FAULT
    assert net.panel.lamps() == {"busy": False, "done": False, "fault": True}
    (tmp_path / "state" / "datasets").unlink()
    counter = net.panel.run_counter()
    press_start(net, "tcp-npoint")
    until_the_run_ends(net, counter)
    assert net.panel.result_code() == ResultCode.OK, daemon.log()
    assert net.panel.lamps() == {"busy": False, "done": True, "fault": False}
    written = frame_on_controller(net)
    # what a PLC reads with a plain Modbus client: registers 20..26, the outcome (docs/panel.md)
    with ModbusTcpClient(net.host, port=net.sim.addresses.modbus[1]) as client:
        raw = client.read_holding_registers(20, count=7, device_id=net.sim.addresses.unit_id).registers
    seen = outcome.decoded(dict(zip(("verdict", "tool_id", "change_x", "change_y", "change_z", "tilt_x", "tilt_y"),
                                    raw)))
    assert seen["verdict"] is None and seen["tool_id"] == 1
    assert seen["tilt_x_deg"] is None and seen["tilt_y_deg"] is None  # tcp-npoint determines the tip only
    for k, key in enumerate(("x_mm", "y_mm", "z_mm")):  # whole thousandths: within half of one
        assert seen[key] == pytest.approx((written[k] - net.previous[k]) * 1e3, abs=5e-4), seen
    assert daemon.stop() == 0
    again = cellcal_daemon(net)
    time.sleep(1.0)  # a second of the idle loop: nothing may come back over run 2's frame
    np.testing.assert_allclose(frame_on_controller(net), written, rtol=0, atol=FRAME_ATOL)
    runs = again.cli("runs", "list")
    assert again.stop() == 0
    states = sorted((r["id"], r["state"]) for r in (runs["runs"] if isinstance(runs, dict) else runs))
    assert states == [(1, "refused"), (2, "done")], states
