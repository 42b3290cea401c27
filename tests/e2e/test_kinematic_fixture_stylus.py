"""kinematic-fixture with a stylus plate: two balls 200 mm apart the tool tip touches (one contact per spot
spread over each ball's upper half), end to end on the in-process simulated cell, scored against the arm's
hidden geometry over the whole workspace."""
from __future__ import annotations

import json

import pytest
import yaml

from cellcal.routines.framework.records import read_dataset
from support.cell_edits import cell_document, edited_cell  # tests/support/cell_edits.py
from support.cli_run import run_cli_captured

BALL_AND_TIP_MM = 9.0  # the sim cell's tip rounding is 3 mm: balls of 6 mm


def _stylus(doc, **section):
    """The sim cell's arm with the issue's hidden errors (0.5 mm, 0.05 deg), its bar a stylus bar: balls at
    the socket bar's drawing (200 mm apart, the scale), 6 contacts per ball, a short approach."""
    doc["sim_truth"].update(arm_length_error_mm=0.5, arm_angle_error_deg=0.05)
    s = doc["kinematic_fixture"]
    s["fixture"]["stylus_radius_mm"] = BALL_AND_TIP_MM
    s.update(orientations=6, approach_mm=3, **section)


@pytest.fixture(scope="module")
def stylus_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("kinematic_fixture_stylus")
    cell = edited_cell(folder, "sim", _stylus)
    code, out, err = run_cli_captured("run", "kinematic-fixture", "--cell", str(cell), "--json", "--out", str(folder))
    assert code == 0, err
    return folder, cell, json.loads(out), next(folder.glob("kinematic-fixture-*.csv"))


@pytest.mark.slow  # the run they share: 48 contacts on the in-process sim, about 16 s
def test_the_stylus_routine_records_one_contact_per_spot_in_the_point_form(stylus_run):
    _, _, result, dataset = stylus_run
    assert result["passed_gates"] and "tool_frame" not in result
    assert (result["setups"], result["points"], result["seats"]) == (4, 8, 48)  # 4 placements x 2 balls x 6
    data = read_dataset(dataset, "kinematic-fixture", ("setup", "point", "target"))
    assert sorted(set(data["point"])) == ["s0", "s1"] and len(set(data["setup"])) == 4
    # each ball's contacts at spots of its own, spread low to high over the upper half (default 30..80 deg)
    for setup in set(data["setup"]):
        at = (data["setup"] == setup) & (data["point"] == "s0")
        assert len(set(zip(data["elevation_deg"][at], data["spot_azimuth_deg"][at]))) == 6
        assert sorted(set(data["elevation_deg"][at])) == [30.0, 55.0, 80.0]


@pytest.mark.slow  # the run they share: 48 contacts on the in-process sim, about 16 s
def test_the_stylus_calibrated_arm_keeps_the_plans_promise_over_the_workspace(stylus_run):
    result = stylus_run[2]
    truth, design = result["sim_truth"], result["design"]
    assert truth["workspace_poses"] >= 100 and truth["workspace_nominal_mean_mm"] > 0.3  # ~1 mm to correct
    # The plan's 1-sigma promise (first order, what is estimated above the noise); the mean of a 3-D error
    # is ~0.9 of its rms and what is held at nominal adds a bias the promise leaves out: within 2x of it.
    # 48 contacts say less than 48 seats (one residual each, not three), so the promise is wider than the
    # socket bar's (0.4 mm here); the calibrated arm must also be better than the nominal one.
    assert 0 < design["expected_error_mm"]
    assert truth["workspace_mean_mm"] < min(2.0 * design["expected_error_mm"], truth["workspace_nominal_mean_mm"])


@pytest.mark.slow  # the run they share: 48 contacts on the in-process sim, about 16 s
def test_the_stylus_dataset_re_solves_offline_to_the_same_model(stylus_run):
    folder, cell, result, dataset = stylus_run
    plate = folder / "balls.yaml"
    plate.write_text(yaml.safe_dump(cell_document(cell)["kinematic_fixture"]["fixture"]))
    code, out, err = run_cli_captured("identify", "--robot", "ur10e", "--data", str(dataset), "--fixture", str(plate),
                              "--json")
    assert code == 0, err
    doc = json.loads(out)
    assert doc["contact"]
    offline = {p["name"]: p["value"] for p in doc["parameters"]}
    online = {p["name"]: p["value"] for p in result["parameters"] if p["name"] in offline}
    assert set(online) == set(offline)
    # the same solver on the same rows (the CSV's full-precision joints): agreement far below what one
    # contact resolves (0.03 mm)
    for name, value in online.items():
        assert offline[name] == pytest.approx(value, abs=1e-6), name


@pytest.mark.parametrize("edit, says", [
    (lambda s: s.update(elevation_deg=[80, 30]), "elevation_deg"),  # not lowest < highest
    (lambda s: s.update(elevation_deg=[30, 95]), "elevation_deg"),  # beyond the top of the ball
    (lambda s: s["fixture"].update(stylus_radius_mm=2.5), "stylus_radius_mm 2.5"),  # inside the tip's 3 mm
    (lambda s: s.update(elevation=[30, 80]), "unknown key"),
    (lambda s: s.update(orientations=4), "at least 6 contacts per ball"),  # three only place a ball's centre
])
def test_bad_stylus_keys_are_refused_naming_the_key(tmp_path, edit, says):
    cell = edited_cell(tmp_path, "sim", lambda doc: (_stylus(doc), edit(doc["kinematic_fixture"])))
    code, _, err = run_cli_captured("run", "kinematic-fixture", "--cell", str(cell), "--dry-run")
    assert code == 2 and "kinematic_fixture" in err and says in err and "Traceback" not in err
    assert err.count("error") == 1  # one message


def test_spots_on_sockets_are_refused(tmp_path):
    cell = edited_cell(tmp_path, "sim", lambda doc: doc["kinematic_fixture"].update(elevation_deg=[30, 80]))
    code, _, err = run_cli_captured("run", "kinematic-fixture", "--cell", str(cell), "--dry-run")
    assert code == 2 and "elevation_deg" in err and "only with a stylus fixture" in err


def test_a_spot_no_tool_orientation_reaches_is_refused_before_anything_moves(tmp_path):
    # placement p4 (0.60 m up, 0.4 m from the base): a spot 20 deg up on the side facing the robot
    # needs the tool turned back toward the base, beyond the 40 deg tilt and the wrist's reach
    cell = edited_cell(tmp_path, "sim", lambda doc: _stylus(doc, elevation_deg=[20, 80],
                                                            placements=doc["kinematic_fixture"]["placements"][3:]))
    code, _, err = run_cli_captured("run", "kinematic-fixture", "--cell", str(cell), "--out", str(tmp_path))
    assert code == 2 and "plan refused, nothing moved" in err and "cannot be touched" in err and "placement p4" in err
    assert not list(tmp_path.glob("kinematic-fixture-*.csv"))
