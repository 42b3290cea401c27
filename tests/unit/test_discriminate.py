"""Ties said as such, and the experiment that breaks them (`analyze --discriminate N -o POSES.csv`).

End to end: a heavy arm measured one joint at a time hides compliance, or a first-order
cyclic error, at the elbow; the first analysis must say it cannot tell the two apart,
the proposed poses are measured on the same simulated arm, and the second analysis
must name the hidden one. This suite runs one seed each way; `bench/discriminate_bench.py`
runs 10 each way and prints the count.
"""
import csv
import json

import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.cli.main import main
from cellcal.measurements.writer import write_measurements
from cellcal.solvers.analysis.analyze import analyze
from cellcal.solvers.analysis.naming import MIN_GAIN, MIN_MARGIN, Naming
from cellcal.solvers.analysis.ties import DECIDE_LAMBDA, MEAN_PER_SIGMA, TYPICAL_MAX, tied_explanations
from support.hidden_cases import SWEEP_ROBOT, elbow_pair, sweep_case  # tests/support/hidden_cases.py: a fixture
from support.naming_stubs import BASELINE, StubScorer, scored  # tests/support/naming_stubs.py



def ties(candidates, tie="ambiguous", named=None, nested=False, sizes=None, margin=0.01, separation_mm2=1e6):
    naming = Naming(named=named, candidates=tuple(candidates), margin=margin, tie=tie)
    sizes = sizes or {}
    return tied_explanations(naming, BASELINE, StubScorer(nested=nested, separation_mm2=separation_mm2), MIN_GAIN,
                             MIN_MARGIN, lambda s: sizes.get(s.cause, {}))


def test_a_tie_within_the_margin_is_reported_with_its_reason_and_nothing_is_named():
    a, b, far = scored("joint_compliance", 0.50), scored("cyclic_joint_error", 0.51), scored("backlash", 0.60)
    sizes = {"joint_compliance": {"deflection_rms_deg": 0.02}, "cyclic_joint_error": {"amplitude_deg": 0.02}}
    report = ties([a, b, far], sizes=sizes)
    assert [t.scored for t in report.entries] == [a, b]  # backlash is 20% behind: not tied
    assert "2.0% from" in report.entries[0].why and "within the 8% margin" in report.entries[0].why
    assert [t.plausible for t in report.entries] == [True, True]
    assert report.naming.named is None and report.grounds == ""
    assert report.entries[1].json()["size_needed"] == {"amplitude_deg": 0.02}


def test_a_tie_is_settled_on_physical_plausibility_and_says_so():
    a, b = scored("joint_compliance", 0.50), scored("cyclic_joint_error", 0.51)
    limit = TYPICAL_MAX["joint_compliance"][1]
    sizes = {"joint_compliance": {"deflection_rms_deg": 3.0 * limit}, "cyclic_joint_error": {"amplitude_deg": 0.02}}
    report = ties([a, b], sizes=sizes)
    assert report.naming.named is b and report.naming.candidates[0] is a  # the list stays best first
    assert report.grounds.startswith("named on physical plausibility") and f"beyond the {limit:g}" in report.grounds
    assert report.grounds in report.naming.notes


def test_nested_explanations_are_a_tie_named_on_simplicity():
    larger, simpler = scored("joint_compliance", 0.50, size=3), scored("cyclic_joint_error", 0.52, size=2)
    report = ties([simpler, larger], tie="nested", named=simpler, nested=True)
    assert [t.scored for t in report.entries] == [simpler, larger]
    assert all(t.why.startswith("same column span") for t in report.entries)
    assert "simpler explanation" in report.grounds and report.naming.named is simpler


def test_two_effects_present_or_nothing_to_explain_are_no_tie():
    a, b = scored("joint_compliance", 0.50), scored("cyclic_joint_error", 0.51)
    assert ties([a, b], tie="both", named=a).entries == ()
    small = scored("joint_compliance", 1.0 - 0.5 * MIN_GAIN), scored("cyclic_joint_error", 0.96)
    assert ties(small).entries == ()


def test_a_lead_beyond_the_margin_is_a_tie_when_the_data_do_not_separate_the_two_predictions():
    a, b = scored("cyclic_joint_error", 0.50), scored("joint_compliance", 0.50 * (1 + MIN_MARGIN) + 0.005)
    sigma_mm = 0.50 / MEAN_PER_SIGMA
    sizes = {"joint_compliance": {"deflection_rms_deg": 0.02}, "cyclic_joint_error": {"amplitude_deg": 0.02}}
    close = ties([a, b], tie="", named=a, margin=0.09, sizes=sizes, separation_mm2=0.5 * DECIDE_LAMBDA * sigma_mm**2)
    assert [t.scored for t in close.entries] == [a, b] and close.naming.named is None
    assert close.naming.tie == "unseparated"
    assert f"{np.sqrt(0.5 * DECIDE_LAMBDA):.1f} noise standard deviations apart" in close.entries[0].why
    assert "needed to tell them apart" in close.naming.notes[-1]
    # the same lead with predictions 1.5 x the decision distance apart: named as before
    far = ties([a, b], tie="", named=a, margin=0.09, sizes=sizes, separation_mm2=2.25 * DECIDE_LAMBDA * sigma_mm**2)
    assert far.entries == () and far.naming.named is a
    # a runner-up that explains too little against geometry alone is no rival, however close
    weak = scored("joint_compliance", 1.0 - 0.5 * MIN_GAIN)
    alone = ties([a, weak], tie="", named=a, margin=0.9, separation_mm2=0.0)
    assert alone.entries == () and alone.naming.named is a


@pytest.mark.parametrize("argv,message", [
    (["--discriminate", "12"], "needs -o"),
    (["-o", "poses.csv"], "belong to --discriminate N"),
    (["--payload-kg", "5"], "belong to --discriminate N"),
    (["--discriminate", "4", "-o", "poses.csv", "--payload-kg", "-1"],
     "argument --payload-kg: must be a number above 0"),
    (["--discriminate", "0", "-o", "poses.csv"], "argument --discriminate: must be a whole number from 1"),
])
def test_discriminate_refuses_bad_usage_before_computing(argv, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    try:
        code = main(["analyze", "--robot", SWEEP_ROBOT, "--data", "missing.csv", *argv])
    except SystemExit as refused:  # bounded numbers are refused by the argument parser
        code = refused.code
    err = capsys.readouterr().err
    assert code == 2 and message in err and not (tmp_path / "poses.csv").exists()


def _analyze(data, capsys, *extra):
    code = main(["analyze", "--robot", SWEEP_ROBOT, "--data", str(data), "--json", *extra])
    assert code == 0
    return json.loads(capsys.readouterr().out)


def _read_poses(path, model, payload=False):
    with open(path, encoding="utf-8") as f:
        rows = list(csv.reader(line for line in f if not line.startswith("#")))
    assert rows[0] == [f"q{j}_rad" for j in range(1, model.n_joints + 1)] + (["payload_kg"] if payload else [])
    return np.array(rows[1:], dtype=float)


@pytest.mark.slow
@pytest.mark.parametrize("cause", ["joint_compliance", "cyclic_joint_error"])
def test_sweeps_tie_and_the_proposed_poses_name_the_hidden_cause(cause, tmp_path, capsys):
    model = load_robot(SWEEP_ROBOT)
    arm, q = sweep_case(model, cause, seed=0)
    first = arm.campaign(q)
    data = tmp_path / "sweeps.csv"
    write_measurements(data, q_rad=first.obs.q, xyz_mm=first.obs.xyz_mm)
    poses = tmp_path / "poses.csv"
    # without link masses the compliance model cannot say what a payload does: offered, not taken
    doc = _analyze(data, capsys, "--discriminate", "12", "-o", str(poses), "--payload-kg", "20")
    assert doc["cause"] == "none", doc["notes"]
    assert elbow_pair(doc["indistinguishable"]), doc["indistinguishable"]
    assert all("margin" in t["why"] or "column span" in t["why"] or "apart" in t["why"]
               for t in doc["indistinguishable"])
    assert doc["discriminate"]["poses"] == 12 and doc["discriminate"]["needed"] <= 12
    plan = doc["discriminate"]
    assert plan["payload_kg"] is None and "payload change not considered" in plan["summary"]

    q_new = _read_poses(poses, model)
    assert q_new.shape == (12, model.n_joints)
    assert np.all(q_new >= model.joint_limits[:, 0]) and np.all(q_new <= model.joint_limits[:, 1])
    second = arm.campaign(q_new)  # the same arm, measured again at the proposed poses
    both = tmp_path / "both.csv"
    write_measurements(both, q_rad=np.concatenate([first.obs.q, second.obs.q]),
                       xyz_mm=np.concatenate([first.obs.xyz_mm, second.obs.xyz_mm]))
    doc = _analyze(both, capsys)
    assert (doc["cause"], doc["where"].get("joint")) == (cause, 3), doc["candidates"][:3]
    assert doc["margin_pct"] >= 100 * MIN_MARGIN


@pytest.mark.slow
def test_a_payload_change_is_proposed_where_it_separates_compliance_from_a_cyclic_error(tmp_path, capsys):
    # every link mass in the robot file: the compliance model predicts what a payload does, the cyclic one
    # predicts nothing, so the design mounts the payload the cell offers on most of the new poses
    model = load_robot("ur10e")
    arm, q = sweep_case(model, "joint_compliance", seed=0)
    first = arm.campaign(q)
    data, poses = tmp_path / "sweeps.csv", tmp_path / "poses.csv"
    write_measurements(data, q_rad=first.obs.q, xyz_mm=first.obs.xyz_mm)
    code = main(["analyze", "--robot", "ur10e", "--data", str(data), "--json", "--discriminate", "6",
                 "-o", str(poses), "--payload-kg", "10"])
    doc = json.loads(capsys.readouterr().out)
    assert code == 0 and doc["cause"] == "none"
    assert {t["cause"] for t in doc["indistinguishable"]} == {"joint_compliance", "cyclic_joint_error"}
    rows = _read_poses(poses, model, payload=True)
    q_new, payload = rows[:, :-1], rows[:, -1]
    assert set(payload) <= {0.0, 10.0} and np.sum(payload == 10.0) >= 4
    second = arm.campaign(q_new, payload_kg=payload)
    both = tmp_path / "both.csv"
    write_measurements(both, q_rad=np.concatenate([first.obs.q, q_new]),
                       xyz_mm=np.concatenate([first.obs.xyz_mm, second.obs.xyz_mm]),
                       payload_kg=np.concatenate([np.zeros(len(q)), payload]))
    code = main(["analyze", "--robot", "ur10e", "--data", str(both), "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert (doc["cause"], doc["where"]) == ("joint_compliance", {"joint": 3}), doc["candidates"][:3]


def test_the_greedy_gain_is_the_rise_of_the_refitted_residual_sum_of_squares():
    # the design's rank-3 update against refitting from scratch with the candidate's rows added
    from cellcal.solvers.analysis.discriminate import _Pair

    rng = np.random.default_rng(3)
    x_old, mean_old = rng.normal(size=(40, 3, 5)), rng.normal(size=(40, 3))
    x_cand, mean_cand = rng.normal(size=(7, 3, 5)), rng.normal(size=(7, 3))
    pair = _Pair(0, 1, x_old, mean_old, x_cand, mean_cand)

    def rss(x, y):
        flat = x.reshape(-1, 5)
        return float(np.sum((flat @ np.linalg.lstsq(flat, y.ravel(), rcond=None)[0] - y.ravel()) ** 2))

    gains, leverage = pair.gains()
    for c in range(7):
        rise = rss(np.concatenate([x_old, x_cand[c:c + 1]]), np.concatenate([mean_old, mean_cand[c:c + 1]])) \
            - rss(x_old, mean_old)
        assert gains[c] == pytest.approx(rise, rel=1e-6)
        flat = x_old.reshape(-1, 5)
        assert leverage[c] == pytest.approx(np.trace(x_cand[c] @ np.linalg.solve(flat.T @ flat, x_cand[c].T)), rel=1e-6)
    pair.add(2, gains[2], 0.0)  # after adding one, the next gains are against the grown fit
    gains_after, _ = pair.gains()
    grown_x, grown_y = np.concatenate([x_old, x_cand[2:3]]), np.concatenate([mean_old, mean_cand[2:3]])
    rise = (rss(np.concatenate([grown_x, x_cand[5:6]]), np.concatenate([grown_y, mean_cand[5:6]]))
            - rss(grown_x, grown_y))
    assert gains_after[5] == pytest.approx(rise, rel=1e-6) and pair.added == pytest.approx(gains[2])


def test_the_separation_is_the_refitted_miss_computed_from_the_whole_jacobian():
    # the R-factor shortcut against least squares on every row's columns
    model = load_robot(SWEEP_ROBOT)
    arm, q = sweep_case(model, "joint_compliance", seed=0)
    run = arm.campaign(q)
    finding = analyze(model, run.obs, run.ctx)
    scorer = finding.scorer
    a, b = (t.scored.terms[0] for t in finding.indistinguishable)
    j = np.concatenate([cols.reshape(-1, scorer.n_columns) for _, cols in scorer._columns()])
    r = scorer.baseline_residuals_mm.ravel()
    for fitted, refitted in ((a, b), (b, a)):
        x, y = j[:, scorer.estimated((fitted,))], j[:, scorer.estimated((refitted,))]
        predicted = x @ np.linalg.lstsq(x, r, rcond=None)[0]
        miss = predicted - y @ np.linalg.lstsq(y, predicted, rcond=None)[0]
        assert scorer.separation_mm2(fitted, refitted) == pytest.approx(float(miss @ miss), rel=1e-6)
    assert scorer.separation_mm2(a, a) == pytest.approx(0.0, abs=1e-9 * float(r @ r))
