"""What `analyze` reports is what it decided (issue 20, section 3).

- The candidates are listed best (lowest held-out mean) first, in the JSON and the text; a
  preference of the naming rule (a single place over several) is said in the grounds.
- A tie that decides the finding is in `indistinguishable` with its grounds, and a gain of
  MIN_GAIN or more that no cause wins is "an effect, cause undecided" with the experiment
  that decides, never a plain `none`.
- Data logged along a path (consecutive rows a degree or so apart) are cross-validated in
  blocks of neighbouring configurations with a neighbour gap, not chained into one neighbour group.
"""
import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cellcal.cli.main import main
from cellcal.config.robot_files import load_robot
from cellcal.measurements.writer import write_measurements
from cellcal.sims.physics.kinematic_arm import TrackerNoise
from cellcal.sims.physics.physical_arm import HiddenEffect, PhysicalArm
from cellcal.sims.physics.workspace import full_workspace, joint_sweeps
from cellcal.solvers.estimation import crossval
from cellcal.solvers.analysis.analyze import NEIGHBOUR_RAD, analyze
from cellcal.solvers.analysis.naming import MIN_GAIN, MIN_MARGIN, MULTI_GAIN, name_cause
from cellcal.solvers.analysis.effects import Term
from cellcal.solvers.analysis.ties import tied_explanations
from support.hidden_cases import BASE_REPEATABILITY_MM, SWEEP_ROBOT, SWEEP_SPAN_DEG, sweep_case  # tests/support/hidden_cases.py
from support.naming_stubs import StubScorer, scored  # tests/support/naming_stubs.py


def _multi(cause: str, heldout_mean_mm: float):
    """A made-up candidate of `cause` at two joints at once."""
    one = scored(cause, heldout_mean_mm, size=2)
    term = Term(cause, {"joints": [2, 3]}, ("p0", "p1"), multi=True)
    return dataclasses.replace(one, label=term.label(), where=term.where, terms=(term,))


def _decide(candidates, baseline_mm: float):
    baseline = scored("none", baseline_mm)
    naming = name_cause(candidates, baseline, StubScorer(pair_mean_mm=baseline_mm))
    return tied_explanations(naming, baseline, StubScorer(pair_mean_mm=baseline_mm), MIN_GAIN, MIN_MARGIN,
                             lambda s: {})


def test_the_issue_tie_behind_a_lower_multi_place_candidate_is_reported_and_the_list_stays_in_order():
    # the issue's numbers: geometry 0.170 mm; a cyclic error at two joints 0.0911 (less than MULTI_GAIN below
    # its single place, so the single place competes), compliance 0.0990, the cyclic single place 0.1002.
    # Before: the single cyclic place was listed first, the tie reference was the multi-place 0.0911 and
    # neither single place lay within 8% of it: `none` with an empty `indistinguishable`.
    multi, compliance, cyclic = (_multi("cyclic_joint_error", 0.0911), scored("joint_compliance", 0.0990),
                                 scored("cyclic_joint_error", 0.1002))
    assert multi.heldout_mean_mm > (1.0 - MULTI_GAIN) * cyclic.heldout_mean_mm  # the premise: parsimony applies
    report = _decide([cyclic, multi, compliance], 0.170)
    means = [c.heldout_mean_mm for c in report.naming.candidates]
    assert means == sorted(means)
    assert report.naming.named is None
    assert [t.scored for t in report.entries] == [compliance, cyclic]  # the two that decide, best first
    assert all("within the 8% margin" in t.why for t in report.entries)


def test_a_named_single_place_over_a_lower_multi_place_candidate_says_so_in_the_grounds_not_by_the_order():
    multi, single, other = (_multi("cyclic_joint_error", 0.46), scored("cyclic_joint_error", 0.50),
                            scored("backlash", 0.80))
    naming = name_cause([single, other, multi], scored("none", 1.0), StubScorer())
    assert naming.named is single and naming.candidates == (multi, single, other)
    assert f"{100 * MULTI_GAIN:.0f}%" in naming.grounds and multi.label in naming.grounds


def test_a_tie_named_on_plausibility_or_simplicity_keeps_the_list_best_first():
    larger, simpler = scored("joint_compliance", 0.50, size=3), scored("cyclic_joint_error", 0.52, size=2)
    naming = name_cause([simpler, larger], scored("none", 1.0), StubScorer(nested=True))
    assert naming.named is simpler and naming.candidates == (larger, simpler)


def _elbow_sweeps(tmp_path):
    """The issue's case: an IRB4600 with hidden geometric errors, compliance of the elbow hidden, measured one
    joint at a time, 12 angles a joint (72 poses). Seed 0 gives a gain of about 24% shared by compliance and a
    first-order cyclic error of the elbow within the 8% margin. (With 6 angles a joint, 36 poses, the choice of
    joint made inside each fold's training rows is unstable and the nested held-out gain stays below 10%.)"""
    model = load_robot(SWEEP_ROBOT)
    arm, _ = sweep_case(model, "joint_compliance", seed=0)
    q = joint_sweeps(model, 12, SWEEP_SPAN_DEG)
    run = arm.campaign(q)
    data = tmp_path / "sweeps.csv"
    write_measurements(data, q_rad=run.obs.q, xyz_mm=run.obs.xyz_mm)
    return data


def test_sweeps_with_a_tied_gain_report_an_effect_of_undecided_cause_with_the_experiment(tmp_path, capsys):
    data = _elbow_sweeps(tmp_path)
    assert main(["analyze", "--robot", SWEEP_ROBOT, "--data", str(data), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    means = [c["heldout_mean_mm"] for c in doc["candidates"]]
    assert means == sorted(means)
    assert doc["cause"] == "none"  # the contract's id: nothing is named ...
    undecided = doc["undecided"]  # ... but an effect is there, and said so
    assert undecided is not None and undecided["gain_pct"] >= 100 * MIN_GAIN
    assert undecided["heldout_mean_mm"] == pytest.approx(means[0], rel=1e-12)  # the best of the tie leads the list
    tied = doc["indistinguishable"]
    assert {t["cause"] for t in tied} == {"joint_compliance", "cyclic_joint_error"}
    assert all(t["where"].get("joint") == 3 for t in tied)
    assert all("margin" in t["why"] or "column span" in t["why"] or "apart" in t["why"] for t in tied)
    assert set(undecided["causes"]) == {"joint_compliance", "cyclic_joint_error"}
    assert "joint_compliance follows the gravity torque on joint 3" in undecided["experiment"] and "--discriminate" in undecided["experiment"]

    assert main(["analyze", "--robot", SWEEP_ROBOT, "--data", str(data)]) == 0
    text = capsys.readouterr().out
    assert "finding: an effect, cause undecided" in text and "experiment that decides:" in text
    block = text.split("candidates (held-out mean error, mm):\n")[1].split("\n\n")[0]  # up to the time line
    listed = [float(line.split()[0]) for line in block.splitlines() if not line.strip().startswith("...")]
    assert listed == sorted(listed) and len(listed) >= 2


def _heavy_sweeps(seed: int, targets: int):
    """A heavy arm measured joint by joint, simulated: an IRB4600 with hidden geometric errors and compliance hidden
    at joints 2 and 3 (0.3 mm each), measured one joint at a time, 6 angles a joint (36 poses), at 1 or 3
    targets. The elbow's gravity torque is a first harmonic of its angle in its own sweep, so compliance
    of joint 3 and a first-order periodic error of it explain these data alike; joint 2's 30 degree sweep
    shows its compliance too little to add."""
    model = load_robot(SWEEP_ROBOT)
    effects = (HiddenEffect("joint_compliance", 1, rms_mm=0.3), HiddenEffect("joint_compliance", 2, rms_mm=0.3))
    arm = PhysicalArm(model, np.random.default_rng(seed), effects, repeatability_mm=BASE_REPEATABILITY_MM,
                      tracker=TrackerNoise(0.015, 0.006), target_names=tuple(f"t{i}" for i in range(targets)))
    q = np.repeat(joint_sweeps(model, 6, SWEEP_SPAN_DEG), targets, axis=0)
    run = arm.campaign(q, target=np.tile(np.arange(targets), len(q) // targets))
    return model, run


@pytest.mark.parametrize("seed,targets", [(1, 1), (3, 1), (0, 3)])
def test_heavy_arm_sweeps_with_compliance_at_two_joints_report_the_tie_not_a_periodic_error(seed, targets):
    """The elbow's compliance and its first-order periodic error explain these data alike (the nested scores
    within the margin, or the periodic error ahead while the models chosen on all rows lie within it, or
    their predictions too close to tell apart). Naming the periodic error would name the wrong cause; the
    finding is the tie, with the experiment."""
    model, run = _heavy_sweeps(seed, targets)
    finding = analyze(model, run.obs, run.ctx)
    assert finding.cause == "none", (finding.cause, finding.notes)
    assert finding.undecided is not None
    assert 1.0 - finding.undecided.heldout_mean_mm / finding.baseline.heldout_mean_mm >= MIN_GAIN
    tied = {(t.cause, t.scored.where.get("joint")) for t in finding.indistinguishable}
    # the elbow's periodic error against compliance at a joint that has it (the elbow, or the shoulder, whose
    # 30 degree sweep the folds now keep in every training: on three targets it shows its compliance as well)
    assert ("cyclic_joint_error", 3) in tied and {c for c, _ in tied} == {"joint_compliance", "cyclic_joint_error"}
    assert all(j in (2, 3) for c, j in tied if c == "joint_compliance"), tied
    assert "tie" in finding.decided_by and "joint_compliance follows the gravity torque" in finding.decide_by
    # whichever rule finds the tie (the nested lead within the margin, the models chosen on all rows within it,
    # or predictions too close to tell apart), it is said
    assert all(t.why for t in finding.indistinguishable)


def test_effect_free_data_stay_plain_none(tmp_path, capsys):
    model = load_robot(SWEEP_ROBOT)
    arm = PhysicalArm(model, np.random.default_rng(5), (), repeatability_mm=BASE_REPEATABILITY_MM,
                      tracker=TrackerNoise(0.015, 0.006))
    run = arm.campaign(full_workspace(model, 120, np.random.default_rng(6)))
    data = tmp_path / "free.csv"
    write_measurements(data, q_rad=run.obs.q, xyz_mm=run.obs.xyz_mm)
    assert main(["analyze", "--robot", SWEEP_ROBOT, "--data", str(data), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["cause"] == "none" and doc["undecided"] is None and doc["indistinguishable"] == []


# -- data logged along a path ------------------------------------------------------------------------------

def path_campaign(model, n_rows: int, seed: int) -> np.ndarray:
    """A tracker at 10 Hz along a robot program: straight joint-space moves between random workspace
    poses, consecutive rows 0.5-1.5 deg apart (largest joint), n_rows in all."""
    rng = np.random.default_rng(seed)
    rows, here = [], full_workspace(model, 1, rng)[0]
    while sum(len(r) for r in rows) < n_rows:
        there = full_workspace(model, 1, rng)[0]
        span_deg = np.rad2deg(np.abs(there - here).max())
        steps = np.cumsum(rng.uniform(0.5, 1.5, int(span_deg / 0.5) + 2))
        steps = steps[steps < span_deg] / span_deg
        rows.append(here + steps[:, None] * (there - here))
        here = there
    return np.concatenate(rows)[:n_rows]


def test_path_data_are_cut_in_blocks_with_a_neighbour_gap():
    model = load_robot("ur10e")
    q = path_campaign(model, 2000, seed=1)
    step_deg = np.rad2deg(np.abs(np.diff(q, axis=0)).max(axis=1))
    assert step_deg.max() <= 1.5 + 1e-9  # the premise: a path, every row a neighbour of the next
    groups = crossval.groups(q, NEIGHBOUR_RAD)
    assert np.bincount(groups).max() > len(q) / 5  # ... whose neighbour groups chain most of the rows
    folds = crossval.fold_ids(q, 5, 0, NEIGHBOUR_RAD)
    assert sorted(np.unique(folds)) == [0, 1, 2, 3, 4]
    assert np.bincount(folds).min() >= 0.5 * len(q) / 5  # 50 blocks, 10 a fold: nearly equal folds
    for k, left_out in enumerate(folds.exclude):
        own = np.flatnonzero(folds == k)
        training = np.setdiff1d(np.flatnonzero(folds != k), left_out)
        # the gap: no training row within the neighbour radius of a held-out row (max over joints)
        nearest = cKDTree(q[own]).query(q[training], p=np.inf)[0]
        assert nearest.min() > NEIGHBOUR_RAD
        assert len(left_out) < 0.2 * len(q)  # a gap at the blocks' ends (and crossings), not the data
    # scattered poses keep the neighbour grouping, without exclusions
    scattered = full_workspace(model, 200, np.random.default_rng(2))
    assert crossval.fold_ids(scattered, 5, 0, NEIGHBOUR_RAD).exclude is None


def _path_run(model, q, effects, seed):
    """(campaign, mean length of its measurement noise) of a tracker along the path q."""
    arm = PhysicalArm(model, np.random.default_rng(seed), tuple(effects),
                      repeatability_mm=BASE_REPEATABILITY_MM, tracker=TrackerNoise(0.015, 0.006))
    run = arm.campaign(q)
    noise_free = PhysicalArm(model, np.random.default_rng(seed), tuple(effects), repeatability_mm=0.0,
                             tracker=TrackerNoise(0.0, 0.0)).campaign(q)
    return run, float(np.linalg.norm(run.obs.xyz_mm - noise_free.obs.xyz_mm, axis=1).mean())


@pytest.mark.parametrize("cause,joint", [("joint_compliance", 1), ("cyclic_joint_error", 2)])
def test_path_logged_data_with_a_hidden_effect_are_analysed_and_the_effect_named(cause, joint):
    model = load_robot("ur10e")
    q = path_campaign(model, 3000, seed=3)
    effect_rms_mm = 0.3
    run, noise_mean_mm = _path_run(model, q, [HiddenEffect(cause, joint, rms_mm=effect_rms_mm, order=1,
                                                           phase_rad=0.7)], seed=4)
    finding = analyze(model, run.obs, run.ctx)
    assert (finding.cause, finding.where.get("joint")) == (cause, joint + 1), \
        ([c.label for c in finding.candidates[:3]], finding.notes)
    # a sane baseline: what geometry leaves is at most the effect (0.3 mm rms, less what geometry absorbs)
    # plus the noise; a fold whose training chained away from it would leave millimetres
    assert noise_mean_mm < finding.baseline.heldout_mean_mm < effect_rms_mm + noise_mean_mm
    # with the effect modelled, what is left on held-out blocks is the noise (20% for the geometry and
    # effect parameters each fold estimates without its block)
    assert finding.extended.heldout_mean_mm < 1.2 * noise_mean_mm


@pytest.mark.parametrize("robot,seed", [("abb-irb4600", 0), ("elite-ec66", 1)])
def test_effect_free_path_data_give_none(robot, seed):
    model = load_robot(robot)
    run, noise_mean_mm = _path_run(model, path_campaign(model, 3000, seed=10 + seed), (), seed=20 + seed)
    finding = analyze(model, run.obs, run.ctx)
    assert finding.cause == "none" and finding.undecided is None, (finding.candidates[0].label, finding.notes)
    assert finding.baseline.heldout_mean_mm < 1.2 * noise_mean_mm  # geometry alone reaches the noise


@pytest.mark.parametrize("rows,message", [
    # one configuration, logged 40 times: nothing to cross-validate, as before path data had blocks
    (np.tile([0.1, -1.0, 1.0, 0.2, 0.3, 0.4], (40, 1)), "only 1 distinct configurations"),
    # one path driven back and forth three times: every held-out block has its twins in the training
    (np.concatenate([np.linspace(0, 1, 100)[:, None] * [1.0, 0.5, 0.5, 1, 1, 1]] * 2 * 3), "keep returning"),
])
def test_path_data_with_nothing_unseen_to_score_on_are_refused_with_one_message(rows, message, tmp_path, capsys):
    data = tmp_path / "data.csv"
    write_measurements(data, q_rad=rows, xyz_mm=np.random.default_rng(0).normal(size=(len(rows), 3)) + 500.0)
    code = main(["analyze", "--robot", "ur10e", "--data", str(data)])
    err = capsys.readouterr().err
    assert code == 1 and message in err and "Traceback" not in err


def test_the_report_of_an_undecided_effect_draws_it_and_says_so(tmp_path, capsys):
    data = _elbow_sweeps(tmp_path)
    report = tmp_path / "report"
    assert main(["analyze", "--robot", SWEEP_ROBOT, "--data", str(data), "--report", str(report)]) == 0
    capsys.readouterr()
    page = (report / "report.md").read_text(encoding="utf-8")
    assert "finding: an effect, cause undecided" in page and "experiment that decides:" in page
    assert (report / "heldout_histogram.png").stat().st_size > 0 and (report / "candidates.png").exists()
