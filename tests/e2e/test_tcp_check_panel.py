"""The tool check from the operator panel on sim-net: a calibration, then checks of a tool
that is fine, one that drifted a little, and one that is bent (issue: daily use).

The controller's tool frame is moved behind the service's back (the fake's control port):
for a check that is the same as the tool moving on the flange, since it compares the real
tool with the frame the controller holds.
"""
from __future__ import annotations

import html
import re
from pathlib import Path

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


def headline(daemon, run_id: int) -> str:
    """The first lines of run `run_id`'s report, as text (what the page says before its plots)."""
    page = Path(daemon.cli("runs", "show", str(run_id))["report"]).read_text()
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", page.split("<h2>")[0])).split())


def test_check_ok_then_corrected_then_alarm_from_the_panel(net, cellcal_daemon):
    daemon = cellcal_daemon(net)
    calibrated = press(net, "tcp-laser")
    assert calibrated["code"] == ResultCode.OK, daemon.log()
    frame = controller_tcp(net)
    # each report's headline says what happened: the verdict, and whether (and as which) a frame was written
    assert "Every gate passed" in headline(daemon, 1)
    assert "written to the controller as tool 1's frame" in headline(daemon, 1)

    fine = press(net, "tcp-check")
    assert fine["code"] == ResultCode.OK and fine["verdict"] == "ok", daemon.log()
    assert not fine["lamps"]["done"] and not fine["lamps"]["fault"]  # nothing written
    assert "the beams where tcp-laser run 1 found them" in daemon.log()
    np.testing.assert_array_equal(controller_tcp(net), frame)
    # ok means every determined change is within the inner band (0.1 mm, 0.1 deg)
    assert all(abs(fine[k]) <= 0.1 for k in ("x_mm", "y_mm", "z_mm") if fine[k] is not None), fine
    said = headline(daemon, 2)
    assert "Tool check OK" in said and "Nothing was written" in said and "to be written back" not in said, said

    drifted = frame + np.array([0.0004, 0.0, 0.0, 0.0, 0.0, 0.0])  # the frame 0.4 mm off the tool along x
    assert net.control.request(cmd="set_tcp", tcp=drifted.tolist())["ok"]
    corrected = press(net, "tcp-check")
    assert corrected["code"] == ResultCode.OK and corrected["verdict"] == "corrected", daemon.log()
    assert corrected["lamps"]["done"]  # a frame was written
    # the check found the real tool 0.4 mm the other way from the frame it was given; the
    # frame written is back near the calibration's (inner band: what a check can tell)
    assert corrected["x_mm"] == pytest.approx(-0.4, abs=0.1), corrected
    assert np.linalg.norm(controller_tcp(net)[:3] - frame[:3]) * 1e3 <= 0.1
    said = headline(daemon, 3)
    assert "Tool check CORRECTED" in said and "written to the controller as tool 1's frame" in said, said

    bent = controller_tcp(net) + np.array([0.0, 0.002, 0.0, 0.0, 0.0, 0.0])  # 2 mm: beyond the outer band
    assert net.control.request(cmd="set_tcp", tcp=bent.tolist())["ok"]
    alarm = press(net, "tcp-check")
    assert alarm["code"] == ResultCode.CHECK_ALARM and alarm["verdict"] == "alarm", daemon.log()
    assert alarm["lamps"]["fault"] and not alarm["lamps"]["done"]
    np.testing.assert_array_equal(controller_tcp(net), bent)  # nothing written
    assert "tool check alarm" in daemon.log()
    said = headline(daemon, 4)
    assert "Tool check ALARM" in said and "Nothing was written" in said, said
    # the reason is what the check saw, in the log, the store and runs list alike
    reason = daemon.cli("runs", "list")["runs"][0]["reason"]
    assert re.search(r"tip \d+\.\d{3} mm off \(x [+-]\d", reason) and "a bent tool or a collision?" in reason, reason
    assert "outer band" in reason and reason in daemon.log()

    # a tool 30 mm off its frame (another tool on the flange, or one badly bent): the sweeps miss the
    # beams before anything can be solved. Still an alarm, in the verdict register, the store and runs list
    missed = frame + np.array([0.030, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert net.control.request(cmd="set_tcp", tcp=missed.tolist())["ok"]
    blind = press(net, "tcp-check")
    assert blind["code"] == ResultCode.CHECK_ALARM and blind["verdict"] == "alarm", (blind, daemon.log()[-2000:])
    assert blind["lamps"]["fault"] and not blind["lamps"]["done"]
    np.testing.assert_array_equal(controller_tcp(net), missed)  # nothing written
    assert daemon.cli("runs", "list")["runs"][0]["verdict"] == "alarm"
    history = daemon.cli("tool", "history")
    assert [f["run_id"] for f in history["tool_frames"]] == [1, 3]  # the calibration and the correction
    assert daemon.stop() == 0
