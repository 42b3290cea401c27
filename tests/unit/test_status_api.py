"""The status API's JSON builders (cellcal/daemon/status_api.py) on a store made here, row by row.

No service and no server: a Store written as the service writes it, read back through the
read-only connection the server uses, and every builder's answer checked against what went in.
"""
from __future__ import annotations

import json
import math
import sqlite3
from types import SimpleNamespace

import numpy as np
import pytest

from cellcal.cli.runs import _run_summary, _written_back
from cellcal.daemon import status_api
from cellcal.daemon.service import ResultCode
from cellcal.daemon.store import Store, StoreError
from cellcal.routines.framework.base import Gate, Parameter, Result

FRAME_A = [0.0004, -0.0003, 0.1496, 0.004, -0.003, 0.0]
FRAME_B = [0.0006, -0.0003, 0.1496, 0.004, -0.003, 0.0]  # tip 0.2 mm along x from FRAME_A


def _result(routine: str, *, verdict=None, passed=True) -> Result:
    return Result(routine=routine, parameters=[Parameter("tcp_x", 0.4, 0.001, "mm")],
                  residuals_mm=np.full(4, 0.01), expected_noise_mm=0.01, condition=3.0,
                  gates=[Gate("residual", passed, 0.01, 0.05, "within" if passed else "too large")],
                  tool_frame=np.array(FRAME_A), determines=frozenset({"tip", "axis"}), verdict=verdict)


@pytest.fixture
def state(tmp_path):
    """A state folder with three runs of tool 1 (a calibration written back, a check in alarm,
    one still running) and one refused run of tool 2, each recorded as the service records it."""
    folder = tmp_path / "state"
    store = Store.open(folder)
    report = folder / "reports" / "run-1" / "report.html"
    report.parent.mkdir(parents=True)
    report.write_text("<p>run 1</p>")

    cal = store.begin_run("tcp-npoint", "/cells/sim.yaml", tool_id=1)
    store.record_state(cal, "running")
    store.record_result(cal, _result("tcp-npoint"))
    store.record_report(cal, str(report))
    store.record_tool_frame(cal, "write", [0.0] * 6, FRAME_A)
    store.record_measured_frame(cal, 1, "calibration", "tcp-npoint", FRAME_A, ["axis", "tip"], written=True)
    store.finish_run(cal, "done", int(ResultCode.OK), "tool frame written back")

    check = store.begin_run("tcp-check", "/cells/sim.yaml", tool_id=1)
    store.record_result(check, _result("tcp-check", verdict="alarm", passed=False))
    store.record_measured_frame(check, 1, "check", "tcp-check", FRAME_B, ["tip"])
    store.finish_run(check, "fault", int(ResultCode.CHECK_ALARM), "tool check alarm: tip 0.2 mm off")

    refused = store.begin_run("tcp-laser", "/cells/sim.yaml", tool_id=2)
    store.finish_run(refused, "refused", int(ResultCode.TOOL_NOT_MOUNTED), "tool 2 is not mounted")

    open_run = store.begin_run("tcp-npoint", "/cells/sim.yaml", tool_id=1)
    store.record_state(open_run, "running")
    store.close()
    return folder


@pytest.fixture
def ro(state):
    store = status_api.open_store(state)
    yield store
    store.close()


def test_no_store_yet_reads_as_no_runs_and_no_run(tmp_path):
    assert status_api.open_store(tmp_path) is None
    assert status_api.runs(None, 20, tmp_path) == {"runs": []}
    assert status_api.run_detail(None, 1, tmp_path) is None
    assert status_api.tools(None, {"mounted_tool": None}, {}) == {"tools": []}


def test_the_read_only_store_cannot_write(ro):
    with pytest.raises(sqlite3.Error, match="readonly|read-only|query_only|attempt to write"):
        ro.event("written by the status page")


def test_a_store_of_another_schema_version_is_refused_with_what_to_do(state):
    db = sqlite3.connect(state / "cellcal.db")
    db.execute("PRAGMA user_version = 99")
    db.commit()
    db.close()
    with pytest.raises(StoreError, match="schema version 99.*brings it up to date"):
        status_api.open_store(state)


def test_runs_newest_first_with_the_cli_s_keys_and_the_api_s_own(state, ro):
    out = status_api.runs(ro, 20, state)
    assert [r["id"] for r in out["runs"]] == [4, 3, 2, 1]
    # every key of `cellcal runs list --json` is there with the same value (one source of truth)
    full = Store.open(state, create=False)
    try:
        written = _written_back(full)
        for api_row, row in zip(out["runs"], full.runs(20)):
            cli = _run_summary(row, written)
            assert {k: api_row[k] for k in cli} == cli
    finally:
        full.close()
    cal, check, refused, running = out["runs"][3], out["runs"][2], out["runs"][1], out["runs"][0]
    assert (cal["result_code"], cal["result_name"], cal["verdict"], cal["written_back"]) == (0, "OK", None, True)
    assert cal["report_url"] == "/reports/run-1/report.html"
    assert (check["result_name"], check["verdict"], check["written_back"]) == ("CHECK_ALARM", "alarm", False)
    assert (refused["tool_id"], refused["result_name"]) == (2, "TOOL_NOT_MOUNTED")
    assert (running["state"], running["result_code"], running["result_name"]) == ("running", None, None)
    assert status_api.runs(ro, 2, state)["runs"][-1]["id"] == 3  # the limit keeps the newest
    json.dumps(out, allow_nan=False)  # plain JSON, what a browser's JSON.parse takes


def test_a_report_outside_the_reports_folder_gets_no_url(state):
    assert status_api.report_url(str(state / "cellcal.db"), state) is None
    assert status_api.report_url("/etc/passwd", state) is None
    assert status_api.report_url(None, state) is None
    assert status_api.report_url(str(state / "reports" / "tool-1" / "trend.html"), state) == \
        "/reports/tool-1/trend.html"


def test_one_run_has_its_trail_gates_parameters_result_and_frames(state, ro):
    run = status_api.run_detail(ro, 1, state)
    assert [s["state"] for s in run["states"]] == ["checking", "running", "done"]
    assert run["gates"] == [{"name": "residual", "passed": True, "value": 0.01, "limit": 0.05, "why": "within"}]
    assert run["parameters"] == [{"name": "tcp_x", "value": 0.4, "std": 0.001, "unit": "mm"}]
    assert run["result"]["routine"] == "tcp-npoint" and run["result"]["passed_gates"] is True
    assert run["result_meaning"].startswith("the run passed every gate")
    [frame] = run["tool_frames"]
    assert frame["action"] == "write" and frame["frame_after"] == FRAME_A
    # the same frame in mm and degrees: x 0.4 mm, rx 0.004 rad
    assert frame["tool_frame"]["x_mm"] == pytest.approx(0.4, abs=1e-12)
    assert frame["tool_frame"]["rx_deg"] == pytest.approx(math.degrees(0.004), abs=1e-12)
    assert status_api.run_detail(ro, 3, state)["tool_frames"] == []
    assert status_api.run_detail(ro, 99, state) is None


def test_tools_name_the_mounted_one_its_last_frame_and_the_last_verdict(ro):
    status = {"mounted_tool": {"id": 1, "name": "torch"}}
    out = status_api.tools(ro, status, {1: "torch", 3: "spare"})["tools"]
    assert [t["id"] for t in out] == [1, 2, 3]  # the cell file's tools and the store's
    one, two, three = out
    assert (one["name"], one["mounted"], one["last_frame"]["frame_after"]) == ("torch", True, FRAME_A)
    assert one["last_verdict"]["verdict"] == "alarm" and one["last_verdict"]["run_id"] == 2
    assert one["last_run"]["id"] == 4 and one["history_url"] == "/api/v1/tools/1/history"
    assert (two["name"], two["mounted"], two["last_frame"], two["last_verdict"]) == (None, False, None, None)
    assert two["last_run"]["result_name"] == "TOOL_NOT_MOUNTED"
    assert (three["name"], three["last_run"]) == ("spare", None)


def test_a_tool_s_history_is_its_frames_and_the_trend_the_cli_prints(state, ro):
    from cellcal.daemon.drift import trend

    out = status_api.tool_history(ro, 1, "torch")
    assert [f["run_id"] for f in out["tool_frames"]] == [1]
    full = Store.open(state, create=False)
    try:
        expected = trend(full.measured_frames(1), 1)  # what `cellcal tool trend --json` prints
    finally:
        full.close()
    assert out["trend"] == json.loads(json.dumps(expected))
    check = out["trend"]["points"][1]
    # the check measured the tip 0.2 mm from the calibration's (FRAME_B - FRAME_A along x)
    assert check["since_first_calibration"]["tip_mm"] == pytest.approx(0.2, abs=1e-9)
    assert status_api.tool_history(ro, 2)["trend"] is None  # never measured: no trend, no error


@pytest.mark.parametrize("text, expected", [("1", 1), ("255", 255), ("0", None), ("256", None), ("-1", None),
                                            ("1.0", None), ("x", None), ("", None), ("0001", None)])
def test_tool_ids_from_a_url(text, expected):
    assert status_api.valid_tool_id(text) == expected


def test_non_finite_numbers_become_null_and_the_state_carries_the_api_version():
    out = status_api.state({"state": "idle", "progress": None, "x": [float("nan"), float("inf"), 1.5]})
    assert out["x"] == [None, None, 1.5] and out["api"] == 1 and isinstance(out["time"], float)
    json.dumps(out, allow_nan=False)
    assert status_api.result_name(31) == "GATE_FAILED" and status_api.result_name(77) == "77"
    assert status_api.run_summary(SimpleNamespace(id=1, routine="r", cell="c", tool_id=None, started_at=0.0,
                                                  finished_at=None, state="checking", result_code=None, reason=None,
                                                  result_json="not json", passed_gates=False, verdict=None,
                                                  report_path=None),
                                  set(), "/nowhere")["verdict"] is None
