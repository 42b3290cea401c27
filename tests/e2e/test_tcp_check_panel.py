"""The tool check from the operator panel on sim-net: a calibration, then checks of a tool
that is fine, one that drifted a little, and one that is bent (issue: daily use).

The controller's tool frame is moved behind the service's back (the fake's control port):
for a check that is the same as the tool moving on the flange, since it compares the real
tool with the frame the controller holds.
"""
from __future__ import annotations

import numpy as np
import pytest
from cellcal.daemon.service import ResultCode
from support.cell_edits import edited_cell
from support.daemon_harness import Net, controller_tcp, plc_reads, press_start, until_the_run_ends

pytestmark = pytest.mark.slow


def full_laser_cell(folder, host):
    """sim-net with the shipped tcp-laser section (the harness's short one decides too little to
    pass its gates) and the panel's short timeout."""
    return edited_cell(folder, "sim-net", {"drivers": {"panel": {"timeout_s": 0.3}}}, name="sim-net-check.yaml",
                       host=host)


@pytest.fixture(scope="module")
def net_cell():
    return full_laser_cell


def press(net: Net, routine: str) -> dict:
    """One run from the panel; what a PLC reads afterwards with a plain Modbus client."""
    counter = net.panel.run_counter()
    press_start(net, routine)
    until_the_run_ends(net, counter)
    return plc_reads(net)


def test_check_ok_then_corrected_then_alarm_from_the_panel(net, cellcal_daemon):
    daemon = cellcal_daemon(net)
    calibrated = press(net, "tcp-laser")
    assert calibrated["code"] == ResultCode.OK, daemon.log()
    frame = controller_tcp(net)

    fine = press(net, "tcp-check")
    assert fine["code"] == ResultCode.OK and fine["verdict"] == "ok", daemon.log()
    assert not fine["lamps"]["done"] and not fine["lamps"]["fault"]  # nothing written
    assert "the beams where tcp-laser run 1 found them" in daemon.log()
    np.testing.assert_array_equal(controller_tcp(net), frame)
    # ok means every determined change is within the inner band (0.1 mm, 0.1 deg)
    assert all(abs(fine[k]) <= 0.1 for k in ("x_mm", "y_mm", "z_mm") if fine[k] is not None), fine

    drifted = frame + np.array([0.0004, 0.0, 0.0, 0.0, 0.0, 0.0])  # the frame 0.4 mm off the tool along x
    assert net.control.request(cmd="set_tcp", tcp=drifted.tolist())["ok"]
    corrected = press(net, "tcp-check")
    assert corrected["code"] == ResultCode.OK and corrected["verdict"] == "corrected", daemon.log()
    assert corrected["lamps"]["done"]  # a frame was written
    # the check found the real tool 0.4 mm the other way from the frame it was given; the
    # frame written is back near the calibration's (inner band: what a check can tell)
    assert corrected["x_mm"] == pytest.approx(-0.4, abs=0.1), corrected
    assert np.linalg.norm(controller_tcp(net)[:3] - frame[:3]) * 1e3 <= 0.1

    bent = controller_tcp(net) + np.array([0.0, 0.002, 0.0, 0.0, 0.0, 0.0])  # 2 mm: beyond the outer band
    assert net.control.request(cmd="set_tcp", tcp=bent.tolist())["ok"]
    alarm = press(net, "tcp-check")
    assert alarm["code"] == ResultCode.CHECK_ALARM and alarm["verdict"] == "alarm", daemon.log()
    assert alarm["lamps"]["fault"] and not alarm["lamps"]["done"]
    np.testing.assert_array_equal(controller_tcp(net), bent)  # nothing written
    assert "tool check alarm" in daemon.log()
    history = daemon.cli("tool", "history")
    assert [f["run_id"] for f in history["tool_frames"]] == [1, 3]  # the calibration and the correction
    assert daemon.stop() == 0
