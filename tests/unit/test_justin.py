"""The real Agile Justin data: tree model, importer, geometric and elastic findings."""
import json
from pathlib import Path

import numpy as np
import pytest

from cellcal.cli.main import main
from cellcal.measurements.importers import dlr_justin
from cellcal.config.robot_files import load_robot
from cellcal.measurements.reader import read_measurements
from cellcal.measurements.table import DatasetError
from cellcal.solvers.identification.identify import IdentifyOptions, identify

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "dlr-agile-justin" / "measurements.csv"
pytestmark = pytest.mark.skipif(not DATA.exists(), reason="shared data set not beside the repository")


@pytest.fixture(scope="module")
def justin_csv(tmp_path_factory):
    out = tmp_path_factory.mktemp("justin") / "justin.csv"
    assert main(["import", "dlr-justin", str(DATA), "-o", str(out)]) == 0
    return out


def test_import_gives_two_targets_per_measurement_in_mm(justin_csv):
    table = read_measurements(justin_csv, 19)
    assert len(table) == 1000 and table.target_names == ("right", "left")
    assert table.q_rad[0, 0] == pytest.approx(0.966545383)
    assert table.xyz_mm[0] == pytest.approx([-1841.2635, 2226.21393, 1584.26529])
    assert table.xyz_mm[1] == pytest.approx([-3069.54874, 1673.14009, 1809.22059])


def test_import_refuses_a_foreign_file(tmp_path):
    bad = tmp_path / "other.csv"
    bad.write_text("a,b,c\n1,2,3\n")
    with pytest.raises(DatasetError, match="other.csv"):
        dlr_justin(bad)


def test_tree_model_reproduces_the_published_nominal_error(justin_csv):
    model = load_robot("agile-justin")
    obs = read_measurements(justin_csv, 19).observations()
    result = identify(model, obs, IdentifyOptions(regularize="cv"))
    # only base and markers fitted: the authors' "before" figure, 20 mm
    assert result.errors(obs, nominal=True).mean() == pytest.approx(20.0, abs=0.3)
    # 62 of 84 geometric parameters (+ 12 base/marker unknowns: 74 of 96, as published)
    assert model.n_params - len(result.unidentifiable) == 62


@pytest.mark.slow
def test_analyze_names_compliance_with_believable_sizes_below_the_published_held_out(justin_csv, tmp_path, capsys):
    code = main(["analyze", "--robot", "config/robots/agile-justin.yaml" if Path("config/robots").exists()
                 else "agile-justin", "--data", str(justin_csv), "--json", "--report", str(tmp_path)])
    doc = json.loads(capsys.readouterr().out)
    assert code == 0
    assert doc["cause"] == "joint_compliance"
    assert doc["baseline"]["heldout_mean_mm"] < 10.6  # published geometric calibration: 10.6 mm
    # the same 5-fold grouped protocol as the analysis bench, joints and the elastic mount with its pivot
    # shift, without CAD masses, the prior on the effect's 281 parameters weighed inside each fold's
    # training rows: 3.076 mm held-out mean (3.13 with no prior, 3.23 without the shift; published with CAD
    # masses: 3.3 mm). The goal is 3.1 mm; one fold choosing a neighbouring prior weight moves the mean by
    # under 0.01 mm, so 0.02 mm is room for another machine's rounding without hiding a lost prior or shift
    assert doc["extended"]["heldout_mean_mm"] <= 3.1
    assert doc["extended"]["heldout_mean_mm"] == pytest.approx(3.08, abs=0.02)
    assert doc["where"] == {"branches": ["torso", "right", "left"]}
    # sizes a person can believe: deflections only where determined, the rest grouped or bounded
    places = doc["magnitude"]["places"]
    believed = [e for e in places if e["kind"] in ("determined", "group")]
    assert len(believed) >= 5 and max(e["deflection_std_deg"] for e in believed) < 1.0
    assert all(e["deflection_std_deg"] >= 3 * e["standard_error_deg"] for e in believed)
    assert any(e["kind"].startswith("group") and len(e["places"]) >= 2 for e in places)
    assert not any(k.startswith("left.joint5") for k in doc["magnitude"])  # 4.8 deg once: not determined
    assert (tmp_path / "residual_vs_regressor.png").stat().st_size > 10_000


TREE = """name: t
convention: mdh
length_unit: m
angle_unit: rad
joint_count: 2
branches:
  - name: base
    frames:
      - {a: 0, alpha: 0, theta: 0, d: 0.1, joint: 1}
  - name: arm
    parent: base
    mount: {xyz: [0.1, 0, 0]}
    frames:
      - {a: 0.3, alpha: 0, theta: 0, d: 0, joint: {1: -1, 2: 1}}
    end: {xyz: [0.05, 0, 0]}
targets: {tip: arm}
"""


@pytest.mark.parametrize("edit,needles", [
    (("parent: base", "parent: torso"), ["branches[1].parent", "torso"]),
    (("joint: 1}", "joint: 3}"), ["branches[0].frames[0].joint", "1..2"]),
    (("targets: {tip: arm}", "targets: {tip: base}"), ["targets.tip", "leaf"]),
    (("    mount:", "    mounts:"), ["branches[1].mounts", "unknown key"]),
    (("{a: 0.3, alpha: 0, theta: 0, d: 0,", "{a: 0.3, alpha: 0, theta: 0,"), ["frames[0].d", "missing"]),
])
def test_bad_tree_files_name_the_key(tmp_path, edit, needles):
    from cellcal.config.robot_files import ModelError

    path = tmp_path / "tree.yaml"
    path.write_text(TREE.replace(*edit))
    with pytest.raises(ModelError) as err:
        load_robot(path)
    for needle in needles:
        assert needle in str(err.value), str(err.value)


def test_a_good_tree_file_loads_with_shared_and_coupled_joints(tmp_path):
    path = tmp_path / "tree.yaml"
    path.write_text(TREE)
    model = load_robot(path)
    assert model.param_names[:4] == ("base.alpha1", "base.a1", "base.theta1", "base.d1")
    assert "arm.mount.x" in model.param_names and model.target_chains == {"tip": "arm"}
    from cellcal.solvers.geometry.chain import forward

    # q = (0.5, 0.2): base turns 0.5, mount and a = 0.3 lie along that; the coupled arm joint
    # turns -0.5 + 0.2, so the 50 mm end offset points at 0.2 rad
    _, org = forward(model.chains["arm"], model.nominal, np.array([[0.5, 0.2]]))
    expected = np.array([400 * np.cos(0.5) + 50 * np.cos(0.2), 400 * np.sin(0.5) + 50 * np.sin(0.2), 100])
    assert org[0] == pytest.approx(expected, abs=1e-9)
