"""The drift history: the store's measured frames per tool, the trend arithmetic (changes and
rates from constructed histories with known slopes), the drift alarm's decision, the verdict
register, and ``cellcal tool trend`` (text, JSON, page, bad input).

Tolerances: the histories are built from exact steps (mm and deg), so what the arithmetic
gives back differs from them only by float rounding: a frame stored in metres (0.15 m plus a
1e-5 m step, relative rounding 1e-16: 1e-14 mm), and an axis angle taken back through arccos
of a cosine near 1 (rounding 1e-16 of the cosine over sin(1e-4 rad) is 1e-12 rad, 1e-10 deg).
The rates are straight-line fits to such values, so 1e-9 (absolute, in mm or deg per week or
per 1000 runs, values of 0.01 to 1) is far above the rounding and far below any real error.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cellcal.cli.main import main
from cellcal.config.cells import Bands
from cellcal.daemon import drift, outcome
from cellcal.daemon.store import SCHEMA_VERSION, Store
from cellcal.routines.framework.base import Result
from cellcal.solvers.geometry import se3
from cellcal.solvers.tool_frames.tcp_laser import axis_pair

ROUNDING = 1e-9  # see the module's doc
DAY = 86400.0
T0 = 1.7e9  # any time: the fits are of time since the calibration
TIP_M = np.array([0.0, 0.0, 0.150])


def frame(dx_mm=0.0, tilt_deg=0.0) -> list[float]:
    """The drawn tool's frame, its tip moved dx_mm along x, its axis tilted tilt_deg about y."""
    return [*(TIP_M + [dx_mm / 1e3, 0.0, 0.0]), 0.0, math.radians(tilt_deg), 0.0]


@pytest.fixture
def store(tmp_path):
    s = Store.open(tmp_path)
    yield s
    s.close()


def history(store, points, tool_id=1, runs_apart=1):
    """`points`: (day, kind, dx_mm, tilt_deg, written, determines), each a run of its own, `runs_apart`
    run ids after the one before (the cell's other runs between)."""
    for day, kind, dx, tilt, written, determines in points:
        for _ in range(runs_apart - 1):
            store.begin_run("tcp-npoint", "sim")
        run_id = store.begin_run("tcp-check" if kind == "check" else "tcp-laser", "sim")
        store.record_measured_frame(run_id, tool_id, kind, "tcp-check" if kind == "check" else "tcp-laser",
                                    frame(dx, tilt), determines, written=written, at=T0 + day * DAY)
    return store.measured_frames(tool_id)


BOTH = ("tip", "axis")


def test_the_store_keeps_every_measured_frame_per_tool(store):
    assert store.db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION >= 6  # 6: measured_frames
    run = store.begin_run("tcp-npoint", "sim")
    store.record_measured_frame(run, 1, "calibration", "tcp-npoint", frame(0.2), ["tip"], at=T0)
    store.record_measured_frame(run, 2, "check", "tcp-check", frame(), BOTH, at=T0 + 1)
    rows = store.measured_frames(1)
    assert [(r["run_id"], r["kind"], r["routine"], r["determines"], r["written"]) for r in rows] == \
        [(run, "calibration", "tcp-npoint", ["tip"], False)]
    np.testing.assert_array_equal(rows[0]["frame"], frame(0.2))  # JSON of floats: exact
    store.measured_frame_written(run)
    assert all(r["written"] for r in store.measured_frames(1) + store.measured_frames(2))
    assert store.measured_tools() == [1, 2] and store.measured_frames(3) == []
    with pytest.raises(ValueError, match="kind 'guess'"):
        store.record_measured_frame(run, 1, "guess", "tcp-check", frame(), BOTH)


def test_rates_come_back_from_a_history_with_known_slopes(store):
    """A calibration, then a check a day (run ids 20 apart) drifting 0.01 mm and 0.01 deg a day:
    0.07 mm and 0.07 deg a week; per run 0.0005, so 0.5 per 1000 runs."""
    rows = history(store, [(0, "calibration", 0.0, 0.0, True, BOTH)]
                   + [(d, "check", 0.01 * d, 0.01 * d, False, BOTH) for d in range(1, 8)], runs_apart=20)
    t = drift.trend(rows, 1)
    assert t["rate"]["points"] == 8 and t["rate"]["why_none"] is None
    assert t["rate"]["tip_mm_per_week"] == pytest.approx(0.07, abs=ROUNDING)
    assert t["rate"]["axis_deg_per_week"] == pytest.approx(0.07, abs=ROUNDING)
    assert t["rate"]["tip_mm_per_1000_runs"] == pytest.approx(0.5, abs=ROUNDING * 1000)
    assert t["rate"]["axis_deg_per_1000_runs"] == pytest.approx(0.5, abs=ROUNDING * 1000)
    assert t["latest"]["since_last_calibration"]["tip_mm"] == pytest.approx(0.07, abs=ROUNDING)
    assert t["latest"]["since_first_calibration"]["axis_deg"] == pytest.approx(0.07, abs=ROUNDING)
    assert not t["never_calibrated"] and t["first_calibration"]["run_id"] == rows[0]["run_id"]
    json.dumps(t)  # one JSON object, as `tool trend --json` prints it


def test_minutes_and_a_few_runs_of_history_give_no_rate_and_say_why(store):
    """Five checks two minutes after a calibration, runs 1 apart: a rate per week or per 1000 runs
    from them would extrapolate their noise (a straight line through 0.5 mm in five runs is 100
    mm per 1000 runs)."""
    rows = history(store, [(0, "calibration", 0.0, 0.0, True, BOTH)]
                   + [(k * 30 / DAY, "check", 0.1 * k, 0.0, False, BOTH) for k in range(1, 5)])
    rate = drift.trend(rows, 1)["rate"]
    assert rate["points"] == 5
    assert all(rate[k] is None for k in ("tip_mm_per_week", "axis_deg_per_week", "tip_mm_per_1000_runs",
                                         "axis_deg_per_1000_runs")), rate
    assert "no rate per week" in rate["why_none"] and "no rate per 1000 runs" in rate["why_none"]
    assert f"{drift.MIN_RATE_SPAN_RUNS} runs or more apart" in rate["why_none"]


def test_a_new_full_calibration_restarts_the_change_since_the_last_but_not_since_the_first(store):
    rows = history(store, [(0, "calibration", 0.0, 0.0, True, BOTH), (7, "check", 0.5, 0.0, False, BOTH),
                           (8, "calibration", 0.6, 0.0, True, BOTH), (9, "calibration", 2.0, 0.0, False, BOTH),
                           (15, "check", 0.9, 0.0, False, ["tip"])])
    t = drift.trend(rows, 1)
    # the failed (unwritten) calibration of day 9 is no baseline: the last full one is day 8's
    assert t["last_calibration"]["run_id"] == rows[2]["run_id"]
    latest = t["latest"]
    assert latest["since_last_calibration"]["tip_mm"] == pytest.approx(0.3, abs=ROUNDING)
    assert latest["since_first_calibration"]["tip_mm"] == pytest.approx(0.9, abs=ROUNDING)
    assert latest["since_last_calibration"]["axis_deg"] is None  # the check saw the tip only
    # since day 8: 0 (day 8), 1.4 (day 9), 0.3 (day 15): a least-squares line, not the end points
    weeks = np.array([0.0, 1.0, 7.0]) / 7
    expected = np.polyfit(weeks, [0.0, 1.4, 0.3], 1)[0]
    assert t["rate"]["tip_mm_per_week"] == pytest.approx(expected, abs=ROUNDING)


def test_a_tool_never_calibrated_has_no_rate_and_says_so(store):
    t = drift.trend(history(store, [(0, "check", 0.0, 0.0, False, BOTH), (1, "check", 0.1, 0.0, False, BOTH)]), 1)
    assert t["never_calibrated"] and t["last_calibration"] is None
    assert t["rate"]["tip_mm_per_week"] is None and "no full calibration" in t["rate"]["why_none"]
    assert t["latest"]["since_first_calibration"] == {"tip_mm": None, "axis_deg": None}


def test_one_point_since_the_calibration_gives_no_rate_and_says_why(store):
    t = drift.trend(history(store, [(0, "calibration", 0.0, 0.0, True, BOTH)]), 1)
    assert t["rate"]["tip_mm_per_week"] is None and "fewer than two points" in t["rate"]["why_none"]


def test_no_weekly_rate_from_less_than_a_day_of_history(store):
    """A calibration and a check minutes apart: 0.05 mm in 0.01 day would read 35 mm per week,
    the check's noise extrapolated; no weekly rate is given until the points span a day."""
    t = drift.trend(history(store, [(0, "calibration", 0.0, 0.0, True, BOTH), (0.01, "check", 0.05, 0.0, False,
                                                                                 BOTH)]), 1)
    assert t["rate"]["tip_mm_per_week"] is None and "a day or more apart" in t["rate"]["why_none"]
    t = drift.trend(history(store, [(0, "calibration", 0.0, 0.0, True, BOTH), (1, "check", 0.05, 0.0, False,
                                                                              BOTH)]), 1)
    assert t["rate"]["tip_mm_per_week"] == pytest.approx(0.35, abs=1e-6)  # 0.05 mm in a day


@pytest.mark.parametrize("bands, determines, dx, tilt, words", [
    (Bands(drift_mm=0.2), BOTH, 0.3, 0.0, ["tip 0.300 mm", "beyond the drift alarm 0.2 mm"]),
    (Bands(drift_deg=0.1), BOTH, 0.0, 0.15, ["axis 0.150 deg", "beyond the drift alarm 0.1 deg"]),
    (Bands(drift_mm=0.2), BOTH, 0.1, 0.0, None),  # within
    (Bands(), BOTH, 5.0, 3.0, None),  # the drift alarm is off by default
    (Bands(drift_mm=0.2), ["axis"], 0.5, 0.0, None),  # the tip was not determined: no band applies to it
])
def test_the_drift_alarm_compares_what_was_determined_with_the_last_full_calibration(store, bands, determines, dx,
                                                                                     tilt, words):
    rows = history(store, [(0, "calibration", 9.0, 0.0, False, BOTH), (1, "calibration", 0.0, 0.0, True, BOTH)])
    why = _drift_why(frame(dx, tilt), determines, rows, bands)
    if words is None:
        assert why is None
    else:
        assert all(w in why for w in words) and f"run {rows[1]['run_id']}" in why, why


def test_no_full_calibration_means_no_drift_alarm(store):
    rows = history(store, [(0, "check", 0.0, 0.0, False, BOTH)])
    assert _drift_why(frame(3.0), BOTH, rows, Bands(drift_mm=0.1)) is None


def _drift_why(measured, determines, rows, bands) -> str | None:
    """Why a corrected check that measured `measured` ends in the drift alarm, as the service judges it."""
    check = Result("tcp-check", [], np.zeros(0), 0.0, 1.0, [], tool_frame=np.array(measured),
                   determines=frozenset(determines), verdict="corrected")
    judgement = drift.judge(check, drift.measured_frame(check), rows, bands, bool(drift.full_calibrations(rows)))
    assert (judgement.verdict == "drift") == (judgement.why is not None)
    return judgement.why


def test_an_ok_checks_measured_frame_is_the_compared_frame_moved_by_the_change():
    """An ok check carries the frame it compared with; the measured one is that moved by the
    change: tip by x, y, z; axis leaned by the tilts (here 0.05 deg toward x, a turn about y)."""
    compared = np.array(frame())
    result = Result("tcp-check", [], np.zeros(0), 0.0, 1.0, [], tool_frame=compared, determines=frozenset(BOTH),
                    verdict="ok", change={"x_mm": 0.04, "y_mm": -0.02, "z_mm": 0.01, "tilt_x_deg": 0.05,
                                          "tilt_y_deg": 0.0})
    measured = drift.measured_frame(result)
    np.testing.assert_allclose((measured[:3] - compared[:3]) * 1e3, [0.04, -0.02, 0.01], atol=ROUNDING)
    np.testing.assert_allclose(np.degrees(se3.z_axis_lean(measured[3:])), [0.05, 0.0], atol=ROUNDING)
    assert drift.kind_of(result) == "check"
    calibration = Result("tcp-npoint", [], np.zeros(0), 0.0, 1.0, [], tool_frame=compared,
                         determines=frozenset({"tip"}))
    assert drift.kind_of(calibration) == "calibration"
    np.testing.assert_array_equal(drift.measured_frame(calibration), compared)
    assert drift.measured_frame(Result("iso9283", [], np.zeros(0), 0.0, 1.0, [])) is None


def test_an_ok_checks_tilts_are_taken_back_as_the_check_counts_them_for_a_leaning_tool():
    """A tool drawn 20 deg off the flange's z: the tilts are counted across its own axis
    (axis_pair), and come back from the measured frame exactly so."""
    compared = np.array(frame(tilt_deg=20.0))
    change = {"x_mm": 0.0, "y_mm": 0.0, "z_mm": 0.0, "tilt_x_deg": 0.05, "tilt_y_deg": -0.03}
    result = Result("tcp-check", [], np.zeros(0), 0.0, 1.0, [], tool_frame=compared, determines=frozenset(BOTH),
                    verdict="ok", change=change)
    axis = se3.rotvec_to_matrix(drift.measured_frame(result)[3:])[:, 2]
    before = se3.rotvec_to_matrix(compared[3:])[:, 2]
    tilts = [math.degrees(math.atan2(axis @ e, axis @ before)) for e in axis_pair(before)]
    np.testing.assert_allclose(tilts, [0.05, -0.03], atol=ROUNDING)


def _ok_check(dx_mm: float) -> Result:
    """An ok check that compared with frame() and saw the tip dx_mm along x."""
    return Result("tcp-check", [], np.zeros(0), 0.0, 1.0, [], tool_frame=np.array(frame()), notes=["ok: within"],
                  extra={"tip_shift_mm": dx_mm}, determines=frozenset(BOTH), verdict="ok",
                  change={"x_mm": dx_mm, "y_mm": 0.0, "z_mm": 0.0, "tilt_x_deg": 0.0, "tilt_y_deg": 0.0})


def test_the_drift_judgement_is_a_value_and_leaves_the_checks_result_as_the_routine_gave_it(store):
    rows = history(store, [(0, "calibration", 0.0, 0.0, True, BOTH)])
    result = _ok_check(0.3)
    judgement = drift.judge(result, drift.measured_frame(result), rows, Bands(drift_mm=0.2), calibrated=True)
    assert judgement.verdict == "drift" and "tip 0.300 mm" in judgement.why
    judged = judgement.applied_to(result)
    assert judged.verdict == "drift" and judged.notes[0].startswith("drift alarm: tip 0.300 mm")
    assert judged.notes[1:] == ["ok: within"] and judged.as_json()["verdict"] == "drift"
    assert (result.verdict, result.notes, result.extra) == ("ok", ["ok: within"], {"tip_shift_mm": 0.3})
    within = drift.judge(_ok_check(0.1), drift.measured_frame(_ok_check(0.1)), rows, Bands(drift_mm=0.2), calibrated=True)
    assert (within.verdict, within.why, within.notes) == ("ok", None, ())
    assert within.applied_to(result) is result  # nothing to add: the result as it was


def test_a_check_of_a_tool_never_calibrated_keeps_its_verdict_and_says_so(store):
    result = _ok_check(3.0)
    judgement = drift.judge(result, drift.measured_frame(result), [], Bands(drift_mm=0.2), calibrated=False)
    assert judgement.never_calibrated and judgement.verdict == "ok" and judgement.why is None
    judged = judgement.applied_to(result)
    assert judged.notes == [drift.NEVER_CALIBRATED, "ok: within"] and judged.as_json()["never_calibrated"] is True
    assert "never_calibrated" not in result.extra and result.notes == ["ok: within"]
    calibration = Result("tcp-npoint", [], np.zeros(0), 0.0, 1.0, [], tool_frame=np.array(frame()),
                         determines=frozenset({"tip"}))
    assert drift.judge(calibration, drift.measured_frame(calibration), [], Bands(drift_mm=0.2), calibrated=False) == drift.DriftJudgement(None)


def test_the_drift_verdict_has_its_own_register_value():
    raw = outcome.registers("drift", 1, {"x_mm": 0.3})
    assert raw["verdict"] == 4 and outcome.decoded(raw)["verdict"] == "drift"


# -- cellcal tool trend ----------------------------------------------------------------------------


def test_tool_trend_prints_the_history_as_text_json_and_a_page(store, tmp_path, capsys):
    history(store, [(0, "calibration", 0.0, 0.0, True, BOTH), (7, "check", 0.07, 0.0, False, BOTH)])
    assert main(["tool", "trend", "--state-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "tool 1: 2 measured frames" in out and "0.0700 mm/week" in out
    assert main(["tool", "trend", "--json", "--state-dir", str(tmp_path), "--report", str(tmp_path / "page")]) == 0
    captured = capsys.readouterr()
    t = json.loads(captured.out)
    assert t["tool_id"] == 1 and len(t["points"]) == 2
    assert t["rate"]["tip_mm_per_week"] == pytest.approx(0.07, abs=ROUNDING)
    page = (tmp_path / "page" / "trend.html").read_text()
    assert "trend.png" in page and (tmp_path / "page" / "trend.png").stat().st_size > 0
    assert "trend page" in captured.err


def test_tool_trend_without_a_store_is_one_message_and_makes_nothing(tmp_path, capsys):
    missing = tmp_path / "nothing-here"
    assert main(["tool", "trend", "--state-dir", str(missing)]) == 2
    err = capsys.readouterr().err
    assert "no results store" in err and "Traceback" not in err and not missing.exists()


def test_tool_trend_of_a_tool_never_measured_names_those_that_were(store, tmp_path, capsys):
    history(store, [(0, "calibration", 0.0, 0.0, True, BOTH)])
    assert main(["tool", "trend", "--tool", "7", "--state-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "no measured frame of tool 7" in err and "tools measured there: 1" in err and "Traceback" not in err


def _moved_rows(first_run: int, move_mm) -> list[dict]:
    """A tool's measured frames: a full calibration, then a check with its tip moved by `move_mm`."""
    frame = [0.0, 0.0, 0.15, 0.0, 0.0, 0.0]
    moved = [frame[0] + move_mm[0] / 1e3, frame[1] + move_mm[1] / 1e3, frame[2] + move_mm[2] / 1e3, 0.0, 0.0, 0.0]
    return [{"run_id": first_run, "kind": "calibration", "written": True, "frame": frame, "determines": ["axis", "tip"]},
            {"run_id": first_run + 10, "kind": "check", "written": False, "frame": moved,
             "determines": ["axis", "tip"]}]


def test_every_tool_drifting_the_same_way_is_said_to_be_the_beams():
    """Beams that moved 0.3 mm along x move every tool's checked tip alike; a bent tool moves alone."""
    from types import SimpleNamespace

    from cellcal.daemon.drift import drifting_together
    bands = {1: SimpleNamespace(drift_mm=0.2), 2: SimpleNamespace(drift_mm=0.2)}
    alike = {1: _moved_rows(1, [0.30, 0.02, 0.0]), 2: _moved_rows(2, [0.28, -0.01, 0.01])}
    said = drifting_together(1, alike, bands)
    assert said is not None and "tool 1 0.301 mm (run 11), tool 2 0.280 mm (run 12)" in said and "tcp-laser" in said
    # one tool bent, the other where it was: no word of the beams
    assert drifting_together(1, {1: alike[1], 2: _moved_rows(2, [0.02, 0.0, 0.0])}, bands) is None
    # both beyond the drift alarm but different ways (two tools bent): not the beams either
    assert drifting_together(1, {1: alike[1], 2: _moved_rows(2, [0.0, 0.3, 0.0])}, bands) is None
    # one tool only checked since its calibration: nothing to compare with
    assert drifting_together(1, {1: alike[1], 2: _moved_rows(2, [0.3, 0.0, 0.0])[:1]}, bands) is None
