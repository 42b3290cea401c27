"""The drift history and the drift alarm in the service, in process on the simulated cell
(SimPanel, a real store in the test's folder): a check before any calibration (never
calibrated here), a tcp-npoint calibration, a check ok, a check corrected (the real tool
knocked 0.15 mm), then the real tool bent 0.4 mm: the drift alarm.

The numbers: tcp-npoint finds the tip to about 0.03 mm (its design's target 0.05 mm), the
check to about 0.02 mm (1 sigma, tests/e2e/test_tcp_check.py), so a tool that did not move is
within 0.1 mm of its calibration (well inside the drift alarm of 0.2 mm), and a tool moved
0.4 mm is at least 0.25 mm from it (beyond 0.2 mm by more than 3 sigma of the two together).
"""
from __future__ import annotations

import numpy as np

from cellcal.daemon import outcome
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.daemon.drift import NEVER_CALIBRATED
from cellcal.daemon.service import ResultCode, Service
from cellcal.daemon.store import Store
from cellcal.reports.run import write_run_report
from cellcal.reports.trend import write_trend_page
from support.cell_edits import edited_cell  # tests/support/cell_edits.py
from support.service_panel import press

DRAWN_TIP_M = np.array([0.0, 0.0, 0.150])  # sim.yaml's [tool]
CROSSING_MM = [-691.4, -174.1, 450.0]  # sim.yaml's [beams]: both beams' point
KNOWN_BEAMS = {"beams": [{"channel": 0, "point_mm": CROSSING_MM}, {"channel": 1, "point_mm": CROSSING_MM}]}
DRIFT_MM = 0.2
BENT_MM = 0.4
KNOCK_MM = 0.15


def cell_with_tool_moved(folder, shift_mm: float):
    """The sim cell with a drift alarm of DRIFT_MM, its real tool `shift_mm` along x from the drawing."""
    folder.mkdir(parents=True, exist_ok=True)
    tcp = (DRAWN_TIP_M + [shift_mm / 1e3, 0.0, 0.0]).tolist()
    return load_cell(edited_cell(folder, "sim", {
        "sim_truth": {"seed": 11, "tool_tcp_m": tcp, "tool_axis": [0.0, 0.0, 1.0], "fixture_error_mm": 0.0},
        "tool": {"bands": {"drift_mm": DRIFT_MM}}, "tcp_check": KNOWN_BEAMS}))


def service_on(cell, drivers, store, folder) -> Service:
    return Service(cell, drivers, store, out_dir=folder / "datasets",
                   report=lambda run_id, result, st, ending: write_run_report(folder / "reports", run_id, result,
                                                                              ending=ending),
                   trend=lambda tool_id, t: write_trend_page(folder / "reports" / f"tool-{tool_id}", t))


def test_checks_build_the_history_and_a_drifted_tool_ends_in_the_drift_alarm(tmp_path):
    state = tmp_path / "state"
    store = Store.open(state)
    trend_page = state / "reports" / "tool-1" / "trend.html"
    cell = cell_with_tool_moved(tmp_path / "a", 0.0)
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, store, state)
        assert not np.any(drivers.robot.tool_frame())  # the simulated controller starts on the bare flange
        first = press(service, drivers.panel, "tcp-check")
        assert first.code == ResultCode.OK and first.result.verdict == "ok", first.reason
        assert NEVER_CALIBRATED in first.reason and first.result.extra["never_calibrated"]
        # a controller holding no frame: the check compares with the tool's drawing (the real tool is the
        # drawn one here: within the inner band), never with the bare flange; nothing written
        assert not np.any(drivers.robot.tool_frame())
        change = outcome.decoded(drivers.panel.outcome)
        assert all(abs(change[k]) < 0.1 for k in ("x_mm", "y_mm", "z_mm")), change

        calibration = press(service, drivers.panel, "tcp-npoint")
        assert calibration.code == ResultCode.OK, calibration.reason
        calibrated = np.asarray(drivers.robot.tool_frame(), dtype=float)

        ok = press(service, drivers.panel, "tcp-check")
        assert (ok.code, ok.result.verdict) == (ResultCode.OK, "ok"), ok.reason
        assert NEVER_CALIBRATED not in ok.reason

        # the real tool knocked 0.15 mm along x: beyond the inner band (0.1 mm), within the outer band and
        # the drift alarm (0.2 mm) since the calibration
        drivers.world.bend_tool([KNOCK_MM / 1e3, 0.0, 0.0])
        corrected = press(service, drivers.panel, "tcp-check")
        assert (corrected.code, corrected.result.verdict) == (ResultCode.OK, "corrected"), corrected.reason
        assert drivers.panel.lamps["done"]
        written = np.asarray(drivers.robot.tool_frame(), dtype=float)
        assert abs((written - calibrated)[0] * 1e3 - KNOCK_MM) < 0.1  # the frame written follows the knock

    rows = store.measured_frames(1)
    assert [(r["run_id"], r["kind"], r["written"]) for r in rows] == [
        (first.run_id, "check", False), (calibration.run_id, "calibration", True), (ok.run_id, "check", False),
        (corrected.run_id, "check", True)]
    # the corrected check measured the tool where it was knocked to: within the calibration's and the check's
    # noise (0.03 and 0.02 mm, 1 sigma) of the calibration plus the knock
    off_mm = np.subtract(rows[-1]["frame"][:3], rows[1]["frame"][:3]) * 1e3 - [KNOCK_MM, 0.0, 0.0]
    assert np.linalg.norm(off_mm) < 0.1, off_mm
    assert trend_page.is_file() and f"<td>{corrected.run_id}</td>" in trend_page.read_text()
    # the run's report shows the tool's trend and links its page
    assert "../tool-1/trend.html" in (state / "reports" / f"run-{corrected.run_id}" / "report.html").read_text()

    # the tool bent by 0.4 mm: the routine alone would correct it (within the outer band of 1 mm), but it is
    # beyond the drift alarm since the last full calibration: nothing written, its own code, the fault lamp
    bent = cell_with_tool_moved(tmp_path / "b", BENT_MM)
    with open_drivers(bent) as drivers:
        drivers.robot.set_tcp(written)  # the controller holds what the service wrote last
        service = service_on(bent, drivers, store, state)
        alarm = press(service, drivers.panel, "tcp-check")
        assert (alarm.state, alarm.code) == ("fault", ResultCode.DRIFT_ALARM), alarm.reason
        assert alarm.result.verdict == "drift"
        assert "beyond the drift alarm 0.2 mm" in alarm.reason and f"run {calibration.run_id}" in alarm.reason
        np.testing.assert_array_equal(drivers.robot.tool_frame(), written)  # nothing written
        assert drivers.panel.lamps == {"busy": False, "done": False, "fault": True}
        assert drivers.panel.result_code == ResultCode.DRIFT_ALARM and drivers.panel.outcome["verdict"] == 4
    last = store.measured_frames(1)[-1]
    assert (last["run_id"], last["kind"], last["written"]) == (alarm.run_id, "check", False)
    assert store.run(alarm.run_id).result_code == ResultCode.DRIFT_ALARM
    store.close()


def test_a_frame_changed_on_the_controller_is_set_back_to_the_last_one_written_before_the_check(tmp_path, caplog):
    """Between runs the controller's frame changed behind the service's back (on the pendant, or a
    restart without it): at the next start the service sets the last frame it wrote for the mounted
    tool first, and says so; the check then compares the tool with that frame (ok, nothing written)."""
    store = Store.open(tmp_path / "state")
    cell = cell_with_tool_moved(tmp_path / "a", 0.0)
    with open_drivers(cell) as drivers:
        service = service_on(cell, drivers, store, tmp_path / "state")
        calibration = press(service, drivers.panel, "tcp-npoint")
        assert calibration.code == ResultCode.OK, calibration.reason
        written = np.asarray(drivers.robot.tool_frame(), dtype=float)
        drivers.robot.set_tcp(written + [0.0, 0.0, 0.001, 0.0, 0.0, 0.0])  # 1 mm longer, typed in on the pendant
        with caplog.at_level("INFO", logger="cellcal.daemon"):
            checked = press(service, drivers.panel, "tcp-check")
        assert (checked.code, checked.result.verdict) == (ResultCode.OK, "ok"), checked.reason
        np.testing.assert_array_equal(drivers.robot.tool_frame(), written)
        said = [r.getMessage() for r in caplog.records if "before anything moves" in r.getMessage()]
        assert len(said) == 1 and "1.000 mm from it" in said[0] and \
            f"tool 1's frame set to the last frame written for it (run {calibration.run_id})" in said[0], said
        # the frame before the run, in its dataset, is the one set: what the check compared with
        assert checked.result.extra["compared_with"] == "the controller's tool frame from before the run"
    store.close()
