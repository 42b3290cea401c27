"""Calibrated model files: what identify/analyze write is what every --robot reads back, effects included."""
import hashlib
import json

import numpy as np
import pytest
import yaml

from cellcal.config.model_files import load_calibrated, write_calibrated
from cellcal.config.robot_files import ModelError, load_robot
from cellcal.cli.main import main
from cellcal.sims.physics.physical_arm import HiddenEffect, PhysicalArm
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.analysis.analyze import AnalyzeOptions, analyze
from cellcal.solvers.compensation.calibrated_model import CalibratedModel, Effect, from_fit
from cellcal.solvers.analysis.effects import Context, approach_directions

PROVENANCE = {"written_by": "cellcal test", "date_utc": "2026-01-01T00:00:00Z"}


@pytest.fixture(scope="module")
def compliance_finding():
    model = load_robot("ur10e")
    rng = np.random.default_rng(11)
    arm = PhysicalArm(model, rng, [HiddenEffect("joint_compliance", 1, rms_mm=0.4)], target_offsets=[[0, 0, 100.0]])
    campaign = arm.campaign(full_workspace(model, 160, rng))
    finding = analyze(model, campaign.obs, campaign.ctx, AnalyzeOptions(causes=("joint_compliance", "backlash")))
    return model, campaign, finding


def test_analyze_finding_round_trips_through_the_file_to_1e9_mm(compliance_finding, tmp_path):
    model, campaign, finding = compliance_finding
    assert finding.cause == "joint_compliance" and finding.where == {"joint": 2}
    s = finding.extended
    calibrated = from_fit(model, campaign.obs.target_names, s.x, s.terms, s.theta)
    # the calibrated model predicts what the analysis' fit predicted (bases at the final geometry: < 1 um)
    predicted = calibrated.predict(campaign.obs.q, campaign.obs.target, campaign.ctx)
    assert np.abs(predicted - (s.residuals + campaign.obs.xyz_mm)).max() < 1e-3
    path = write_calibrated(tmp_path / "cal.yaml", calibrated, "ur10e", PROVENANCE, {s.cause: s.magnitude})
    loaded = load_calibrated(path)
    assert np.abs(loaded.predict(campaign.obs.q, campaign.obs.target, campaign.ctx) - predicted).max() < 1e-9
    # without the effect the same geometry misses by the deflection: the effect is really applied
    rigid = CalibratedModel(loaded.model, loaded.k, loaded.base, loaded.target_names, loaded.offsets)
    assert np.abs(rigid.predict(campaign.obs.q, campaign.obs.target) - predicted).max() > 0.1
    # a plain reader of the robot file gets the calibrated geometry
    assert np.allclose(load_robot(path).nominal, calibrated.k, atol=1e-12)
    doc = yaml.safe_load(path.read_text())
    assert doc["effects"][0]["cause"] == "joint_compliance" and doc["effects"][0]["where"] == {"joint": 2}
    assert doc["calibration"]["base"]["xyz_mm"] == pytest.approx(list(calibrated.base[:3]), abs=1e-9)


def test_joint_effects_and_a_tilt_are_applied_as_their_causes_define_them(tmp_path):
    """Cyclic error a sin(n q) + b cos(n q), backlash b/2 times the approach sign, and a Hayati beta
    on DH parallel axes, written and read back."""
    model = load_robot("ur5e")
    effects = (Effect("cyclic_joint_error", {"joint": 2, "order": 2}, ("s2_2", "c2_2"), np.array([2e-4, -1e-4]),
                      ("rad", "rad")),
               Effect("backlash", {"joint": 3}, ("b3",), np.array([6e-4]), ("rad",)),
               Effect("parallel_axis_tilt", {"joints": [2, 3]}, ("beta2",), np.array([3e-4]), ("rad",)))
    base = np.array([1500.0, -200.0, 30.0, 0.1, -0.2, 0.3])
    calibrated = CalibratedModel(model, model.nominal, base, ("tcp", "smr2"), np.array([[0, 0, 80.0], [40, 0, 60.0]]),
                                 effects)
    path = write_calibrated(tmp_path / "cyc.yaml", calibrated, "ur5e", PROVENANCE)
    loaded = load_calibrated(path)
    assert "beta2" in loaded.model.param_names and loaded.k[loaded.model.index("beta2")] == pytest.approx(3e-4)
    q = full_workspace(model, 40, np.random.default_rng(3))
    ctx = Context(direction=approach_directions(q))
    delta = loaded.joint_delta(q, ctx)
    assert np.allclose(delta[:, 1], 2e-4 * np.sin(2 * q[:, 1]) - 1e-4 * np.cos(2 * q[:, 1]), atol=1e-15)
    assert np.allclose(delta[:, 2], 3e-4 * ctx.direction[:, 2], atol=1e-15)
    assert np.allclose(delta[:, [0, 3, 4, 5]], 0.0)
    target = np.arange(40) % 2
    flat = CalibratedModel(load_robot("ur5e"), model.nominal, base, loaded.target_names, loaded.offsets)
    moved = np.linalg.norm(loaded.predict(q, target, ctx) - flat.predict(q, target), axis=1)
    assert moved.mean() > 0.05  # the effects move the targets by tenths of a mm
    rewritten = load_calibrated(write_calibrated(tmp_path / "again.yaml", loaded, path, PROVENANCE))
    assert np.abs(rewritten.predict(q, target, ctx) - loaded.predict(q, target, ctx)).max() < 1e-9


def test_a_tree_round_trips_with_its_movable_mounts(tmp_path):
    model = load_robot("agile-justin")
    rng = np.random.default_rng(2)
    k = model.nominal + rng.normal(size=model.n_params) * np.where(model.param_is_angle, 1e-3, 0.5)
    names = tuple(model.target_chains)
    calibrated = CalibratedModel(model, k, np.zeros(6), names, rng.normal(size=(len(names), 3)) * 20)
    loaded = load_calibrated(write_calibrated(tmp_path / "justin.yaml", calibrated, "agile-justin", PROVENANCE))
    q = rng.uniform(-1, 1, (30, model.n_joints))
    target = np.arange(30) % len(names)
    assert np.abs(loaded.predict(q, target) - calibrated.predict(q, target)).max() < 1e-9


def test_a_bad_effects_entry_is_refused_naming_the_key(tmp_path):
    model = load_robot("ur5e")
    calibrated = CalibratedModel(model, model.nominal, np.zeros(6), ("tcp",), np.zeros((1, 3)),
                                 (Effect("backlash", {"joint": 3}, ("b3",), np.array([6e-4]), ("rad",)),))
    path = write_calibrated(tmp_path / "m.yaml", calibrated, "ur5e", PROVENANCE)
    doc = yaml.safe_load(path.read_text())
    doc["effects"][0]["cause"] = "gremlins"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ModelError, match=r"effects\[0\].*cause.*gremlins"):
        load_calibrated(path)


def test_identify_and_analyze_write_models_with_provenance(compliance_finding, tmp_path, capsys):
    from cellcal.measurements.writer import write_measurements

    model, campaign, _ = compliance_finding
    data = tmp_path / "data.csv"
    write_measurements(data, q_rad=campaign.obs.q, xyz_mm=campaign.obs.xyz_mm)
    sha = hashlib.sha256(data.read_bytes()).hexdigest()
    assert main(["identify", "--robot", "ur10e", "--data", str(data), "--regularize", "none",
                 "--write-model", str(tmp_path / "geo.yaml")]) == 0
    assert main(["analyze", "--robot", "ur10e", "--data", str(data), "--causes", "joint_compliance",
                 "--write-model", str(tmp_path / "ext.yaml")]) == 0
    for name, command in (("geo.yaml", "identify"), ("ext.yaml", "analyze")):
        record = yaml.safe_load((tmp_path / name).read_text())["calibration"]
        assert record["command"] == command and record["dataset"] == {"path": str(data), "sha256": sha, "rows": 160}
        assert record["written_by"].startswith("cellcal ") and record["date_utc"].endswith("Z")
    heldout = yaml.safe_load((tmp_path / "ext.yaml").read_text())["calibration"]["heldout"]["mean_mm"]
    assert 0.0 < heldout < 0.2
    # every --robot reads it: identify starts from the calibrated geometry
    assert main(["identify", "--robot", str(tmp_path / "ext.yaml"), "--data", str(data), "--regularize", "none"]) == 0
    capsys.readouterr()
    assert main(["identify", "--robot", "ur10e", "--data", str(data), "--write-model", str(tmp_path / "no" / "x.yaml")]) == 2
    assert "--write-model" in capsys.readouterr().err


def test_a_fitted_periodic_error_keeps_its_orders_and_coverage(tmp_path):
    model = load_robot("ur5e")
    rng = np.random.default_rng(8)
    arm = PhysicalArm(model, rng, [HiddenEffect("cyclic_joint_error", 1, rms_mm=0.4, harmonics=((1, 1.0, 0.3),
                                                                                                (4, 0.6, 1.0)))])
    q = full_workspace(model, 200, rng)
    q = q[np.abs(q[:, 1]) < 2.5]  # joint 2 never beyond +-2.5 rad: the fitted error is known only inside
    data = arm.campaign(q)
    finding = analyze(model, data.obs, data.ctx, AnalyzeOptions(causes=("cyclic_joint_error",)))
    assert finding.cause == "cyclic_joint_error"
    s = finding.extended
    calibrated = from_fit(model, data.obs.target_names, s.x, s.terms, s.theta, data.obs.q)
    loaded = load_calibrated(write_calibrated(tmp_path / "cyc.yaml", calibrated, "ur5e", PROVENANCE))
    (effect,) = loaded.effects
    assert {1, 4} <= {int(n.split("_")[1]) for n in effect.names}
    lo, hi = effect.extra["coverage_rad"]["2"][0][0], effect.extra["coverage_rad"]["2"][-1][1]
    assert -2.5 <= lo < -2.3 and 2.3 < hi <= 2.5
    assert np.abs(loaded.predict(data.obs.q, data.obs.target) - calibrated.predict(data.obs.q, data.obs.target)
                  ).max() < 1e-9
    probe = np.zeros((3, 6))
    probe[:, 1] = [0.5, 2.9, -3.0]
    delta = loaded.joint_delta(probe)
    assert abs(delta[0, 1]) > 1e-5 and np.all(delta[1:, 1] == 0.0)  # outside the coverage: the rigid model


def test_an_effect_at_several_places_round_trips_and_compensates_through_the_cli(tmp_path, capsys):
    """Compliance hidden at joints 2 and 3: analyze names it at both (the forward search joins the two
    single places), writes the model; the model loads (its term rebuilt as the search built it) and
    predicts what the analysis' own fit predicts at the calibration rows, and compensate uses it."""
    from cellcal.measurements.reader import read_measurements
    from cellcal.measurements.writer import write_measurements
    from cellcal.solvers.compensation.compensate import rigid_frames

    model = load_robot("ur10e")
    rng = np.random.default_rng(11)
    arm = PhysicalArm(model, rng, [HiddenEffect("joint_compliance", 1, rms_mm=0.4),
                                   HiddenEffect("joint_compliance", 2, rms_mm=0.4)], target_offsets=[[0, 0, 100.0]])
    campaign = arm.campaign(full_workspace(model, 200, rng))
    data, model_file = tmp_path / "cal.csv", tmp_path / "m.yaml"
    write_measurements(data, q_rad=campaign.obs.q, xyz_mm=campaign.obs.xyz_mm)
    assert main(["analyze", "--robot", "ur10e", "--data", str(data), "--causes", "joint_compliance",
                 "--write-model", str(model_file), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert (doc["cause"], doc["where"]) == ("joint_compliance", {"joints": [2, 3]}), doc["where"]
    loaded = load_calibrated(model_file)
    read = read_measurements(data, 6)
    obs, ctx = read.observations(), Context(direction=approach_directions(read.q_rad))
    finding = analyze(model, obs, ctx, AnalyzeOptions(causes=("joint_compliance",)))
    s = finding.extended
    own = from_fit(model, obs.target_names, s.x, s.terms, s.theta, obs.q).predict(obs.q, obs.target, ctx)
    # the file holds each number to 1e-12 relative at most (repr of a float): far below 1e-9 mm here
    assert np.abs(loaded.predict(obs.q, obs.target, ctx) - own).max() < 1e-9
    q = full_workspace(model, 20, rng)
    p = rigid_frames(model, model.nominal, np.array([0.0, 0.0, 100.0]))(q, None)[1]
    targets = tmp_path / "t.csv"
    targets.write_text("x_mm,y_mm,z_mm," + ",".join(f"q{j}_deg" for j in range(1, 7)) + "\n" + "".join(
        ",".join(f"{v:.6f}" for v in [*p[i], *np.rad2deg(q[i])]) + "\n" for i in range(len(q))))
    assert main(["compensate", "--robot", str(model_file), "--targets", str(targets), "-o",
                 str(tmp_path / "o.csv"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ok"] >= 18  # a couple of random targets may be out of reach


