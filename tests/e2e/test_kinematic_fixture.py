"""kinematic-fixture: the arm's geometry from a two-socket plate at several placements, end to end on the
in-process simulated cell, scored against the arm's hidden geometry over the whole workspace."""
from __future__ import annotations

import json

import pytest
import yaml

from cellcal.routines.framework.records import read_dataset
from support.cell_edits import cell_document, edited_cell  # tests/support/cell_edits.py
from support.cli_run import run_cli_captured

# the arm: hidden geometric errors of up to 0.5 mm and 0.05 deg, repeatability 0.03 mm
ARM_ERRORS = {"sim_truth": {"arm_length_error_mm": 0.5, "arm_angle_error_deg": 0.05}}


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("kinematic_fixture")
    cell = edited_cell(folder, "sim", ARM_ERRORS)
    code, out, err = run_cli_captured("run", "kinematic-fixture", "--cell", str(cell), "--json", "--out", str(folder))
    assert code == 0, err
    return folder, cell, json.loads(out), next(folder.glob("kinematic-fixture-*.csv"))


def test_the_routine_runs_and_records_the_point_form(sim_run):
    _, _, result, dataset = sim_run
    assert result["passed_gates"] and "tool_frame" not in result  # it writes no tool frame
    assert (result["setups"], result["points"], result["seats"]) == (4, 8, 64)  # the sim cell's 4 x 2 x 8
    data = read_dataset(dataset, "kinematic-fixture", ("setup", "point", "target"))
    assert sorted(set(data["point"])) == ["s0", "s1"] and len(set(data["setup"])) == 4
    assert any("base frame" in c for c in result["conventions"])  # named as a convention, never identified


def test_the_calibrated_arm_keeps_the_plans_promise_over_the_workspace(sim_run):
    truth = sim_run[2]["sim_truth"]
    assert truth["workspace_poses"] >= 100
    # Errors of 0.5 mm / 0.05 deg over a ~1.3 m reach leave the nominal arm ~1 mm off (0.05 deg at 1 m is
    # 0.9 mm) even after the best rigid alignment.
    assert truth["workspace_nominal_mean_mm"] > 0.3
    # The plan promised its 1-sigma error over the workspace before anything moved (first order, every
    # direction above the noise estimated); the mean of a 3-D error is ~0.9 of its rms, and what the fit
    # holds at nominal (below the noise) adds a bias the promise leaves out: within 2x of it, and within
    # the goal of 0.15 mm (64 seats on a 200 mm bar; the bench measures more seeds).
    design = sim_run[2]["design"]
    assert design["condition"] > 1 and 0 < design["expected_error_mm"] < 0.15
    assert truth["workspace_mean_mm"] < min(2.0 * design["expected_error_mm"], 0.15)


def test_the_dataset_re_solves_offline_to_the_same_model(sim_run):
    folder, cell, result, dataset = sim_run
    fixture = cell_document(cell)["kinematic_fixture"]["fixture"]
    plate = folder / "plate.yaml"
    plate.write_text(yaml.safe_dump(fixture))
    code, out, err = run_cli_captured("identify", "--robot", "ur10e", "--data", str(dataset), "--fixture", str(plate),
                              "--json")
    assert code == 0, err
    offline = {p["name"]: p["value"] for p in json.loads(out)["parameters"]}
    online = {p["name"]: p["value"] for p in result["parameters"] if p["name"] in offline}
    assert set(online) == set(offline)
    # the same solver on the same rows: only the CSV's text round trip of the joints differs (full
    # precision, ~1e-15 rad), so the model agrees far below anything a seat can resolve (0.03 mm)
    for name, value in online.items():
        assert offline[name] == pytest.approx(value, abs=1e-6), name


def test_a_placement_beyond_reach_is_refused_before_anything_moves(tmp_path):
    def far(doc):
        doc["kinematic_fixture"]["placements"][0]["at_m"] = [-1.15, 0.95, 0.30]  # inside the box, 1.49 m out: beyond reach
    cell = edited_cell(tmp_path, "sim", far)
    code, _, err = run_cli_captured("run", "kinematic-fixture", "--cell", str(cell), "--out", str(tmp_path))
    assert code == 2 and "plan refused, nothing moved" in err and "placement p1" in err
    assert not list(tmp_path.glob("kinematic-fixture-*.csv"))


@pytest.mark.parametrize("edit, says", [
    (lambda s: s.update(orientation=8), "unknown key"),
    (lambda s: s.update(max_tilt_deg=60), "max_tilt_deg"),
    (lambda s: s.pop("placements"), "placements"),
    (lambda s: s["layout_mm"].update(s1=[40, 0]), "disagree"),
    (lambda s: s["fixture"].update(distances_mm=[]), "distances_mm"),
])
def test_bad_section_keys_are_refused_naming_the_key(tmp_path, edit, says):
    cell = edited_cell(tmp_path, "sim", lambda doc: edit(doc["kinematic_fixture"]))
    code, _, err = run_cli_captured("run", "kinematic-fixture", "--cell", str(cell), "--dry-run")
    assert code == 2 and "kinematic_fixture" in err and says in err and "Traceback" not in err
