"""``cellcal analyze --data A.csv --validate B.csv``: does the named effect last?

The effect and the kinematics are fitted on A; on B only its frame (instrument -> base) and
target offsets are fitted. Two campaigns of the same hidden robot must show on B about the
gain A showed; a B without the effect (or of another robot) must show none.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.measurements.writer import write_measurements
from cellcal.sims.physics.physical_arm import HiddenEffect
from cellcal.sims.physics.workspace import full_workspace
from support.cli_run import refused, run_cli  # tests/support/cli_run.py
from support.hidden_cases import make_case  # tests/support/hidden_cases.py

ROBOT = "ur5e"
VISIBILITY = 4.0  # the effect 4x the noise after a geometric calibration, as test_analyze's cases (3-6x)
N_A, N_B = 200, 150


def _write(path, obs):
    write_measurements(path, q_rad=obs.q, xyz_mm=obs.xyz_mm, target_names=obs.target_names, target=obs.target)
    return path


@pytest.fixture(scope="module")
def model():
    return load_robot(ROBOT)


def _campaigns(model, folder, effect, seed):
    """A (with the effect), B: the same hidden robot at another pose set, and the same robot
    (same hidden geometry: same seed) with no effect at B's poses."""
    case = make_case(model, [effect], [VISIBILITY], n=N_A, seed=seed)
    q_b = full_workspace(model, N_B, np.random.default_rng(seed + 1000))
    same = case.arm.campaign(q_b)
    no_effect = make_case(model, [], [], n=N_B, seed=seed).arm.campaign(q_b)
    return (_write(folder / "a.csv", case.campaign.obs), _write(folder / "b.csv", same.obs),
            _write(folder / "b_without.csv", no_effect.obs))


EFFECTS = {  # an effect of each kind of basis: a function of a joint angle, rebuilt from B's rows (sign, torque)
    "cyclic_joint_error": HiddenEffect("cyclic_joint_error", 1, order=2, phase_rad=0.7),
    "backlash": HiddenEffect("backlash", 2),
    "joint_compliance": HiddenEffect("joint_compliance", 1),
}


@pytest.fixture(scope="module", params=sorted(EFFECTS))
def campaigns(request, model, tmp_path_factory):
    return request.param, _campaigns(model, tmp_path_factory.mktemp(request.param), EFFECTS[request.param], seed=3)


def _analyze(capsys, a, b, *extra):
    code, out, err = run_cli(capsys, "analyze", "--robot", ROBOT, "--data", str(a), "--validate", str(b), "--json",
                             *extra)
    assert code == 0, err
    return json.loads(out)


def test_the_effect_carries_to_another_pose_set_of_the_same_robot(campaigns, capsys, tmp_path):
    cause, (a, b, _) = campaigns
    doc = _analyze(capsys, a, b, "--report", str(tmp_path / "report"))
    assert doc["cause"] == cause
    v = doc["validate"]
    assert v["rows"] == N_B and v["effect"].startswith(cause)
    # "within 20% of the in-sample gain" read relative to A's gain: |gain_B - gain_A| <= 0.2 gain_A (A's gain is
    # its held-out gain, what the analysis claims for new poses). Both are ~75% here (effect 4x the noise)
    assert abs(v["gain_pct"] - doc["gain_pct"]) <= 0.2 * doc["gain_pct"], (v, doc["gain_pct"])
    assert v["extended_mean_mm"] == pytest.approx(v["baseline_mean_mm"] * (1 - v["gain_pct"] / 100))
    # B's poses are drawn from the same workspace as A's: nearly all of them lie inside A's ranges
    assert len(v["coverage"]["per_joint"]) == 6 and min(v["coverage"]["per_joint"]) > 0.9
    assert 0.5 < v["coverage"]["all_joints"] <= min(v["coverage"]["per_joint"])
    assert (tmp_path / "report" / "validate.png").stat().st_size > 1000
    assert "validate on" in (tmp_path / "report" / "report.md").read_text()
    assert v["overlap_rows"] == 0  # B's poses are its own


def test_validating_on_the_data_analysed_is_counted_and_said_first(campaigns, capsys):
    """--validate A on A: every row is a pose of the analysed data; the JSON counts them and stderr says,
    before the result, that this is no validation."""
    cause, (a, _, _) = campaigns
    code, out, err = run_cli(capsys, "analyze", "--robot", ROBOT, "--data", str(a), "--validate", str(a), "--json")
    assert code == 0, err
    doc = json.loads(out)
    assert doc["validate"]["overlap_rows"] == doc["validate"]["rows"] > 0, doc["validate"]
    assert "validation rows are poses the calibration rows" in err and "not a validation" in err, err


def test_an_effect_the_second_campaign_lacks_gives_no_gain(campaigns, capsys):
    # the same hidden geometry without the effect: carrying A's effect (4x the noise) over can only add error,
    # so no gain at all (bound 0)
    cause, (a, _, b_without) = campaigns
    v = _analyze(capsys, a, b_without)["validate"]
    assert v["effect"] is not None and v["gain_pct"] < 0.0, v


def test_another_robot_gives_no_gain(model, capsys, tmp_path):
    a, _, _ = _campaigns(model, tmp_path, EFFECTS["backlash"], seed=3)
    other = _write(tmp_path / "other.csv", make_case(model, [], [], n=N_B, seed=11).campaign.obs)
    v = _analyze(capsys, a, other)["validate"]
    # another hidden geometry leaves B ~1 mm (s_r) with A's kinematics; the carried effect (s_e ~0.26 mm rms) is
    # unrelated to it, so it lowers the error only by chance correlation rho: 3 sigma over 3 x 150 coordinates is
    # 3 / sqrt(450) = 0.14, a drop of at most rho s_e / s_r ~ 4%: bound 5%
    assert v["gain_pct"] < 5.0 and v["baseline_mean_mm"] > 0.5, v


def test_nothing_named_reports_the_geometry_only(model, capsys, tmp_path):
    case = make_case(model, [], [], n=N_A, seed=21)
    a = _write(tmp_path / "a.csv", case.campaign.obs)
    b = _write(tmp_path / "b.csv", case.arm.campaign(full_workspace(model, N_B, np.random.default_rng(5))).obs)
    doc = _analyze(capsys, a, b)
    assert doc["cause"] == "none"
    v = doc["validate"]
    assert v["extended_mean_mm"] is None and v["gain_pct"] is None and v["effect"] is None
    assert "nothing to carry" in v["note"]
    # the same robot: A's geometry holds on B to the noise (mean noise vector ~0.09 mm here, x2 for margin)
    assert v["baseline_mean_mm"] < 2 * case.noise_mean_mm, v
    code, out, _ = run_cli(capsys, "analyze", "--robot", ROBOT, "--data", str(a), "--validate", str(b))
    assert code == 0 and "nothing to carry" in out and "validate on" in out


# -- bad --validate input: one message, exit 2, nothing printed on stdout --------------------------------------


def _seven_joints(path, model):
    q = full_workspace(model, 20, np.random.default_rng(0))
    write_measurements(path, q_rad=np.hstack([q, np.zeros((20, 1))]), xyz_mm=np.ones((20, 3)))


def _point_form(path, model):
    q = full_workspace(model, 20, np.random.default_rng(0))
    write_measurements(path, q_rad=q, xyz_mm=np.full((20, 3), np.nan), point=np.array(["p1", "p2"] * 10))


def _few_rows(path, model):
    q = full_workspace(model, 5, np.random.default_rng(0))
    write_measurements(path, q_rad=q, xyz_mm=np.ones((5, 3)))


BAD_VALIDATE = [  # (what is wrong, writes B or leaves it missing, words the message must hold)
    ("another joint count", _seven_joints, ["b.csv"]),
    ("point-form rows", _point_form, ["b.csv", "point"]),
    ("empty file", lambda path, model: path.write_text(""), ["b.csv", "empty"]),
    ("missing file", lambda path, model: None, ["b.csv"]),
    ("too few rows for its frame and targets", _few_rows, ["b.csv", "--validate needs at least"]),
]


@pytest.fixture(scope="module")
def good_a(model, tmp_path_factory):
    return _write(tmp_path_factory.mktemp("a") / "a.csv", make_case(model, [], [], n=N_A, seed=3).campaign.obs)


@pytest.mark.parametrize("what,make,needles", BAD_VALIDATE, ids=[row[0] for row in BAD_VALIDATE])
def test_bad_validate_input_is_refused_with_one_message(what, make, needles, good_a, model, capsys, tmp_path):
    a, b = good_a, tmp_path / "b.csv"
    make(b, model)
    refused(capsys, ["analyze", "--robot", ROBOT, "--data", a, "--validate", b, "--report", tmp_path / "r"], 2,
            needles)
    assert not (tmp_path / "r" / "report.html").exists()  # refused before anything was written


def test_a_second_campaign_without_the_motion_the_effect_needs_scores_the_geometry_only(model, capsys, tmp_path):
    # compliance of joint 2 follows its gravity torque, which only joints 2 .. 6 change: a B that holds them all
    # (joint 1 alone swept) cannot show the effect; the geometry alone is scored and the note says why
    a, _, _ = _campaigns(model, tmp_path, EFFECTS["joint_compliance"], seed=3)
    case = make_case(model, [EFFECTS["joint_compliance"]], [VISIBILITY], n=N_A, seed=3)
    q_b = full_workspace(model, 60, np.random.default_rng(7))
    q_b[:, 1:] = q_b[0, 1:]
    b = _write(tmp_path / "held.csv", case.arm.campaign(q_b).obs)
    doc = _analyze(capsys, a, b)
    v = doc["validate"]
    assert doc["cause"] == "joint_compliance" and v["extended_mean_mm"] is None and v["effect"] is None
    assert "joint_compliance (joint 2) cannot be evaluated" in v["note"] and v["baseline_mean_mm"] > 0
