"""`cellcal identify` as the command-line contract says: JSON keys, exit codes, messages."""
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from support.cli_run import run_cli  # tests/support/cli_run.py
from cellcal.config.robot_files import load_robot
from cellcal.measurements.writer import write_measurements
from cellcal.sims.physics.kinematic_arm import SimulatedArm
from cellcal.sims.physics.workspace import full_workspace


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    model = load_robot("ur5e")
    rng = np.random.default_rng(11)
    arm = SimulatedArm(model, rng, target_offsets=[[0.0, 0.0, 80.0]])
    cal = arm.measure(full_workspace(model, 40, rng))
    val = arm.measure(full_workspace(model, 60, rng))
    folder = tmp_path_factory.mktemp("campaign")
    write_measurements(folder / "cal.csv", q_rad=cal.q, xyz_mm=cal.xyz_mm)
    write_measurements(folder / "val.csv", q_rad=val.q, xyz_mm=val.xyz_mm)
    both = np.concatenate([cal.q, val.q]), np.concatenate([cal.xyz_mm, val.xyz_mm])
    split = np.array(["cal"] * len(cal) + ["val"] * len(val))
    write_measurements(folder / "split.csv", q_rad=both[0], xyz_mm=both[1], split=split)
    return folder, arm, val


def test_json_has_every_key_the_contract_names(campaign, capsys):
    folder, arm, val = campaign
    code, out, _ = run_cli(capsys, "identify", "--robot", "ur5e", "--data", str(folder / "cal.csv"),
                           "--validate", str(folder / "val.csv"), "--json")
    assert code == 0
    doc = json.loads(out)  # stdout is one JSON object and nothing else
    for key in ("train", "validate"):
        assert set(doc[key]) >= {"mean_mm", "rms_mm", "max_mm", "n"}
    assert doc["train"]["n"] == 40 and doc["validate"]["n"] == 60
    assert set(doc["before"]) >= {"train_mean_mm", "validate_mean_mm"}
    assert {"name", "nominal", "identified", "std"} <= set(doc["parameters"][0])
    assert "theta1" in doc["unidentifiable"] and doc["seconds"] > 0
    # the numbers are the real ones: validation close to the simulation's floor
    floor = arm.oracle_errors(val).mean()
    assert doc["validate"]["mean_mm"] < 1.3 * floor
    assert doc["before"]["validate_mean_mm"] > 3 * doc["validate"]["mean_mm"]


def test_a_validation_on_the_calibration_rows_is_counted_and_said_first(campaign, capsys):
    """--validate with the calibration file itself scores the fit on its own data: every row overlaps,
    the JSON says so and stderr says first that it is no validation. A held-out file overlaps nowhere."""
    folder, _, _ = campaign
    code, out, err = run_cli(capsys, "identify", "--robot", "ur5e", "--data", str(folder / "cal.csv"),
                             "--validate", str(folder / "cal.csv"), "--json")
    assert code == 0 and json.loads(out)["validate"]["overlap_rows"] == 40
    assert "40 of 40 validation rows are poses the calibration rows" in err and "not a validation" in err, err
    code, out, err = run_cli(capsys, "identify", "--robot", "ur5e", "--data", str(folder / "cal.csv"),
                             "--validate", str(folder / "val.csv"), "--json")
    assert code == 0 and json.loads(out)["validate"]["overlap_rows"] == 0 and "validation rows are" not in err


def test_split_column_reserves_validation_rows(campaign, capsys):
    folder, _, _ = campaign
    code, out, _ = run_cli(capsys, "identify", "--robot", "ur5e", "--data", str(folder / "split.csv"),
                           "--regularize", "none", "--json")
    assert code == 0
    doc = json.loads(out)
    assert doc["train"]["n"] == 40 and doc["validate"]["n"] == 60
    assert doc["regularize"]["lambda"] == 0.0


def test_text_report_shows_before_and_after(campaign, capsys):
    folder, _, _ = campaign
    code, out, err = run_cli(capsys, "identify", "--robot", "ur5e", "--data", str(folder / "cal.csv"),
                             "--validate", str(folder / "val.csv"))
    assert code == 0
    assert "validation data" in out and "not identifiable" in out
    assert "cross-validation" in err  # progress goes to stderr


HEADER = "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,x_mm,y_mm,z_mm"
ROW = "10,20,30,40,50,60,1,2,3"


@pytest.mark.parametrize("name,text,needles", [
    ("missing.csv", "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,x_mm,y_mm\n10,20,30,40,50,60,1,2\n",
     ["missing.csv", "z_mm"]),
    ("joints.csv", "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,q7_deg,x_mm,y_mm,z_mm\n"
                   "10,20,30,40,50,60,70,1,2,3\n", ["joints.csv", "7", "6"]),
    ("text.csv", f"{HEADER}\n{ROW}\n10,20,30,40,50,60,1,abc,3\n", ["text.csv:3", "y_mm", "abc"]),
    ("nan.csv", f"{HEADER}\n{ROW}\n10,20,30,40,50,nan,1,2,3\n", ["nan.csv:3", "q6_deg"]),
    ("units.csv", "q1_deg,q2_rad,q3_deg,q4_deg,q5_deg,q6_deg,x_mm,y_mm,z_mm\n" + ROW + "\n",
     ["units.csv", "q2_rad"]),
    ("dup.csv", "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,x_mm,y_mm,z_mm,x_mm\n" + ROW + ",4\n",
     ["dup.csv", "x_mm"]),
    ("empty.csv", "", ["empty.csv"]),
])
def test_bad_files_get_one_clear_message_and_exit_2(tmp_path, capsys, name, text, needles):
    path = tmp_path / name
    path.write_text(text)
    code, out, err = run_cli(capsys, "identify", "--robot", "ur5e", "--data", str(path))
    assert code == 2
    assert out == ""
    assert len(err.strip().splitlines()) == 1
    for needle in needles:
        assert needle in err


def test_bad_usage_exits_2_naming_what_to_fix(campaign, tmp_path, capsys):
    folder, _, _ = campaign
    cal = str(folder / "cal.csv")
    code, _, err = run_cli(capsys, "identify", "--robot", "ur55", "--data", cal)
    assert code == 2 and "ur55" in err and "ur5e" in err
    code, _, err = run_cli(capsys, "identify", "--robot", "ur5e", "--data", cal, "--fix", "d9")
    assert code == 2 and "d9" in err
    bad_model = tmp_path / "bad.yaml"
    bad_model.write_text("name: x\nconvention: dh\nlength_unit: inch\nangle_unit: deg\njoints: []\n")
    code, _, err = run_cli(capsys, "identify", "--robot", str(bad_model), "--data", cal)
    assert code == 2 and "bad.yaml" in err and "length_unit" in err


def test_console_script_shows_no_traceback(tmp_path):
    script = shutil.which("cellcal") or str(__import__("pathlib").Path(sys.executable).parent / "cellcal")
    path = tmp_path / "bad.csv"
    path.write_text(f"{HEADER}\n10,20,30,40,50,60,1,2,inf\n")
    proc = subprocess.run([script, "identify", "--robot", "ur5e", "--data", str(path), "--json"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "bad.csv:2" in proc.stderr and "z_mm" in proc.stderr
    # with --json, scripts that read stdout get one error object (docs/cli.md)
    error = __import__("json").loads(proc.stdout)["error"]
    assert error["code"] == 2 and "bad.csv:2" in error["message"]


def test_sim_campaign_writes_its_datasets_and_scores_against_truth(tmp_path, capsys):
    code, out, _ = run_cli(capsys, "sim-campaign", "--robot", "ur5e", "--poses", "40", "--candidates", "200",
                           "--validate-poses", "100", "--regularize", "none", "--out", str(tmp_path), "--json")
    assert code == 0
    doc = json.loads(out)
    truth = doc["sim_truth"]
    assert doc["after_over_floor"] < 1.2
    # against the hidden true positions the calibrated model is far better than the nominal one
    assert truth["validation_vs_truth"]["after"]["mean_mm"] < 0.2 * truth["validation_vs_truth"]["before"]["mean_mm"]
    assert (tmp_path / "cal.csv").exists() and (tmp_path / "val.csv").exists()
    # the dataset on disk is the seam: identify re-run from it gives the same validation error
    code, out2, _ = run_cli(capsys, "identify", "--robot", "ur5e", "--data", str(tmp_path / "cal.csv"), "--validate",
                            str(tmp_path / "val.csv"), "--regularize", "none", "--json")
    assert code == 0
    rerun = json.loads(out2)
    assert rerun["validate"]["mean_mm"] == pytest.approx(truth["validation_measured"]["after"]["mean_mm"], rel=1e-6)
