"""tcp-check on the in-process sim cell: the verdicts against injected shifts of the real tool
(the controller holds the tool as drawn, so the shift injected is the change the check must see),
what it determines with the beams known and as installed, the dry run, bad options.

The noise: the sim's arm repeats to 0.03 mm (1 sigma per axis, per motion) and its trigger
jitters by 0.5 ms; the check reports the tip to about 0.02 mm and the axis to about 0.015 deg
(1 sigma). Beams are where [beams] says (fixture_error_mm 0), and tcp_check.beams gives those
points as a tcp-laser calibration would have found them.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from cellcal.cli import run as run_cmd
from support.cli_run import run_cli  # tests/support/cli_run.py
from cellcal.routines.framework import runner
from support.cell_edits import edited_cell  # tests/support/cell_edits.py

DRAWN_TIP_M = np.array([0.0, 0.0, 0.150])  # sim.yaml's [tool]
CROSSING_MM = [-691.4, -174.1, 450.0]  # sim.yaml's [beams]: both beams' point
KNOWN_BEAMS = {"beams": [{"channel": 0, "point_mm": CROSSING_MM}, {"channel": 1, "point_mm": CROSSING_MM}]}
INNER_MM = 0.1  # the default bands (config.cells.Bands)
MOTION_S = 5.0  # the goal: a check in 5 s of motion or less


def cell_file(tmp_path, shift_mm=(0.0, 0.0, 0.0), axis=(0.0, 0.0, 1.0), check=None, seed=7):
    """The sim cell whose real tool is the drawn one moved by `shift_mm` (flange frame) and
    turned onto `axis`, with the beams exactly where the file says."""
    tcp = (DRAWN_TIP_M + np.asarray(shift_mm) / 1e3).tolist()
    changes = {"sim_truth": {"seed": seed, "tool_tcp_m": tcp, "tool_axis": list(axis), "fixture_error_mm": 0.0},
               "tcp_check": KNOWN_BEAMS if check is None else check}
    return edited_cell(tmp_path, "sim", changes)


def checked(tmp_path, capsys, **kw):
    code, out, err = run_cli(capsys, "run", "tcp-check", "--cell", str(cell_file(tmp_path, **kw)), "--json",
                             "--out", str(tmp_path / "runs"))
    return code, json.loads(out), err


def test_a_tool_where_the_controller_thinks_it_is_is_ok_in_under_5_s(tmp_path, capsys):
    code, result, _ = checked(tmp_path, capsys)
    assert code == 0 and result["verdict"] == "ok", result["notes"]
    assert result["determines"] == ["axis", "tip"]
    assert result["cycle_time_s"] <= MOTION_S
    # the real tool is the drawn one: the change is noise, 0.02 mm / 0.015 deg at 1 sigma: 4 sigma
    assert np.hypot(result["change"]["x_mm"], result["change"]["y_mm"]) < 0.08
    assert abs(result["change"]["z_mm"]) < 0.08 and abs(result["change"]["tilt_x_deg"]) < 0.06
    np.testing.assert_allclose(result["tool_frame"]["pose_m_rad"][:3], DRAWN_TIP_M, atol=1e-12)  # unchanged
    assert "nothing to write" in result["notes"][0]


def test_a_03_mm_shift_is_corrected_to_within_the_inner_band_of_the_truth(tmp_path, capsys):
    code, result, _ = checked(tmp_path, capsys, shift_mm=(0.3, 0.0, -0.1))
    assert code == 0 and result["verdict"] == "corrected", result["notes"]
    assert result["passed_gates"]
    # the corrected frame against the hidden truth: within the inner band (0.1 mm); the
    # check's own error is ~0.02 mm (1 sigma), so 0.1 mm is a 5-sigma margin
    assert result["sim_truth"]["position_error_mm"] <= INNER_MM, result["sim_truth"]
    assert result["change"]["x_mm"] == pytest.approx(0.3, abs=0.08)  # 4 sigma of 0.02 mm
    assert result["change"]["z_mm"] == pytest.approx(-0.1, abs=0.08)


@pytest.mark.parametrize("shift, axis, words", [
    ((0.0, 2.5, 0.0), (0.0, 0.0, 1.0), "tip 2.5"),
    ((0.0, 0.0, 0.0), (np.sin(np.radians(2.0)), 0.0, np.cos(np.radians(2.0))), "axis tilted 2.0"),
])
def test_a_bent_tool_is_an_alarm_that_says_what_it_saw_and_writes_nothing(tmp_path, capsys, shift, axis, words):
    code, result, _ = checked(tmp_path, capsys, shift_mm=shift, axis=axis)
    assert code == 1 and result["verdict"] == "alarm"
    assert words in result["notes"][0] and "bent tool" in result["notes"][0], result["notes"][0]
    assert "beyond the outer band" in result["notes"][0]


def test_a_tool_too_far_off_to_cross_the_beams_is_an_alarm_naming_the_motion(tmp_path, capsys):
    """8 mm longer: the tool already blocks the beams where the approach starts."""
    code, out, err = run_cli(capsys, "run", "tcp-check", "--cell", str(cell_file(tmp_path, shift_mm=(0.0, 0.0, 8.0))),
                             "--out", str(tmp_path / "runs"))
    assert code == 1 and "tcp-check alarm" in err and "bent tool" in err and "Traceback" not in err


def test_a_first_check_before_any_beam_calibration_is_refused_before_moving_saying_what_to_run(tmp_path, capsys,
                                                                                                monkeypatch):
    """The shipped cell as it comes (no tcp_check.beams, no beam_std_mm): [beams] as installed
    are known to 0.5 mm, so a check could not tell a tip that moved from beams that did. Refused
    before the robot is even opened; exit 2."""
    def no_drivers(cell):
        raise AssertionError("a check with nothing to judge against opened the cell's devices")

    monkeypatch.setattr(run_cmd, "open_drivers", no_drivers)
    code, out, err = run_cli(capsys, "run", "tcp-check", "--cell", str(cell_file(tmp_path, check={})),
                             "--out", str(tmp_path / "runs"))
    assert code == 2 and out == "" and err.count("\n") == 1 and "Traceback" not in err, err
    assert "no beam calibration for this cell yet: run tcp-laser first" in err and "nothing moved" in err, err
    assert not (tmp_path / "runs").exists() or list((tmp_path / "runs").iterdir()) == []


def test_with_the_beams_as_installed_the_tip_is_not_determined_and_no_band_applies(tmp_path, capsys):
    """[beams] stated to be known to 0.5 mm (beam_std_mm: a fixture's placement): a 0.3 mm shift of
    the tip cannot be told from a beam that is off; the axis still can (the beams do not enter it)."""
    code, result, _ = checked(tmp_path, capsys, shift_mm=(0.3, 0.0, 0.0), check={"beam_std_mm": 0.5})
    assert result["determines"] == ["axis"] and result["verdict"] == "ok"
    assert result["change"]["x_mm"] is None and result["change"]["tilt_x_deg"] is not None
    assert any("not determined, so no band applies" in n and "[beams] as installed" in n for n in result["notes"])


def test_the_check_runs_at_the_controllers_own_frame_and_compares_with_it(tmp_path):
    """A controller holding a calibrated frame 0.3 mm off the drawing, the real tool there: ok."""
    from cellcal.daemon.cells import load_cell, open_drivers
    path = cell_file(tmp_path, shift_mm=(0.3, 0.0, 0.0))
    cell = load_cell(path)
    stored = cell.tool.tcp_pose.copy()
    stored[0] += 0.3e-3
    prepared = runner.prepare("tcp-check", cell)
    with open_drivers(cell) as drivers:
        drivers.robot.set_tcp(stored)
        dataset = runner.measure(prepared, drivers, tmp_path, lambda m: None)
        back = drivers.robot.tool_frame()
    result = runner.solve("tcp-check", cell, dataset)
    np.testing.assert_allclose(back, stored)  # the controller's frame is left as it was
    assert result.verdict == "ok", result.notes
    assert result.extra["compared_with"] == "the controller's tool frame from before the run"


def test_dry_run_plans_and_checks_but_moves_nothing(tmp_path, capsys, monkeypatch):
    def no_drivers(cell):
        raise AssertionError("--dry-run opened the cell's devices")

    monkeypatch.setattr(run_cmd, "open_drivers", no_drivers)
    code, out, _ = run_cli(capsys, "run", "tcp-check", "--cell", str(cell_file(tmp_path)), "--dry-run", "--json",
                           "--out", str(tmp_path / "runs"))
    summary = json.loads(out)
    labels = [m["label"] for m in summary["plan"]]
    assert code == 0 and summary["within_limits"]
    assert sum(label.startswith("sweep") for label in labels) == 4  # two heights, out and back
    assert not (tmp_path / "runs").exists() or list((tmp_path / "runs").iterdir()) == []


@pytest.mark.parametrize("check, needle", [
    ({"heights_mm": [1]}, "heights_mm"),
    ({"heights_mm": [12, 15]}, "10 mm or more apart"),
    ({"spins_deg": [0, 90]}, "135..225 deg apart"),
    ({"spins_deg": [0, 180, 90]}, "one or two turns"),
    ({"beams": [{"channel": 0, "point_mm": CROSSING_MM}]}, "give every beam"),
    ({"beams": [{"channel": 0, "point_mm": [0, 0, 0]}, {"channel": 1, "point_mm": CROSSING_MM}]}, "mm off the beam"),
    ({"beams": [{"channel": 5, "point_mm": CROSSING_MM}]}, "each beam of [beams]"),
    ({"beam_std_mm": -1}, "beam_std_mm"),
    ({"search_mm": 0}, "search_mm"),
    ({"speed": 40}, "speed"),
])
def test_bad_options_are_one_message_naming_the_key_and_nothing_moves(tmp_path, capsys, check, needle):
    cell = cell_file(tmp_path, check={**KNOWN_BEAMS, **check})
    code, out, err = run_cli(capsys, "run", "tcp-check", "--cell", str(cell), "--out", str(tmp_path / "runs"))
    assert code == 2 and needle in err and "tcp_check" in err and "Traceback" not in err, err
    assert not (tmp_path / "runs").exists() or list((tmp_path / "runs").iterdir()) == []


def test_a_plan_that_determines_nothing_for_a_band_is_refused_saying_why(tmp_path, capsys):
    """One height (no axis) and the beams as installed (no tip): nothing to judge."""
    cell = cell_file(tmp_path, check={"heights_mm": [12], "beam_std_mm": 0.5})
    code, _, err = run_cli(capsys, "run", "tcp-check", "--cell", str(cell), "--out", str(tmp_path / "runs"))
    assert code == 2 and "determines nothing a band can judge" in err and "one height" in err, err
    assert not (tmp_path / "runs").exists() or list((tmp_path / "runs").iterdir()) == []
