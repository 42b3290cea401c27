"""One model-selection procedure for every cause with places, nested inside the folds.

Every cause with places (compliance and backlash at joints, a periodic error at joints and
orders) is offered as the result of the same forward search, several places together where
the data support it, and a second effect of another cause is searched the same way. Every
choice that looks at the data is made again inside each fold's training rows, and the held-out
errors a cause is judged by are those of each fold's own choice: on effect-free data the
choice made on all rows can look like an effect, the nested one does not. The analysis sees
only the measured data; the checks use the simulation's truth.
"""
import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.sims.physics.physical_arm import HiddenEffect
from cellcal.sims.physics.workspace import full_workspace, joint_sweeps
from cellcal.solvers.estimation import crossval
from cellcal.solvers.analysis import selection
from cellcal.solvers.analysis.analyze import AnalyzeOptions, analyze
from cellcal.solvers.analysis.naming import MIN_GAIN
from support.hidden_cases import SWEEP_SPAN_DEG, _arm, make_case


def _cyclic(finding):
    return next(c for c in finding.candidates if c.cause == "cyclic_joint_error")


def test_effect_free_data_named_by_the_choice_on_all_rows_are_none_when_the_choice_is_nested():
    # 24 random poses of a heavy arm, no effect: the periodic error's joints and orders picked on all
    # rows and scored on the same folds gain 26% (a false alarm); scored by each fold's own choice, nothing
    model = load_robot("abb-irb4600")
    case = make_case(model, [], [], n=24, seed=5)
    optimistic = analyze(model, case.campaign.obs, case.campaign.ctx, AnalyzeOptions(nested=False))
    honest = analyze(model, case.campaign.obs, case.campaign.ctx)
    assert optimistic.cause == "cyclic_joint_error", optimistic.notes
    assert honest.cause == "none" and honest.undecided is None, (honest.candidates[0].label, honest.notes)
    # the same term chosen on all rows, only its score differs
    assert _cyclic(honest).label == _cyclic(optimistic).label
    assert _cyclic(honest).heldout_mean_mm > (1.0 - MIN_GAIN) ** -1 * _cyclic(optimistic).heldout_mean_mm


EFFECT_FREE = [("abb-irb4600", 30, 1), ("abb-irb4600", 30, 10), ("ur10e", 30, 11), ("elite-ec66", 30, 0),
               ("elite-ec66", 60, 1), ("ur10e", 120, 2), ("abb-irb4600", 300, 3),
               ("abb-irb4600", "sweeps", 6), ("ur10e", "sweeps", 12)]


@pytest.mark.parametrize("robot,n,seed", EFFECT_FREE)
def test_no_false_alarm_on_effect_free_data_of_several_sizes(robot, n, seed):
    # random poses (30 to 300) and one-joint-at-a-time sweeps (6 and 12 angles a joint); among the seeds with
    # 30 random poses, some where the choice on all rows, scored on the same folds, names a periodic error
    model = load_robot(robot)
    if n == "sweeps":
        run = _arm(model, 2000 + seed, (), 1.0).campaign(joint_sweeps(model, seed, SWEEP_SPAN_DEG))
        obs, ctx = run.obs, run.ctx
    else:
        case = make_case(model, [], [], n=n, seed=seed)
        obs, ctx = case.campaign.obs, case.campaign.ctx
    finding = analyze(model, obs, ctx)
    assert finding.cause == "none" and finding.undecided is None, (finding.candidates[0].label, finding.notes)


def test_compliance_of_two_joints_together_is_named_at_both():
    model = load_robot("abb-irb4600")
    effects = [HiddenEffect("joint_compliance", 1), HiddenEffect("joint_compliance", 2)]
    case = make_case(model, effects, [4.0, 4.0], n=120, seed=1)
    finding = analyze(model, case.campaign.obs, case.campaign.ctx)
    assert (finding.cause, finding.where) == ("joint_compliance", {"joints": [2, 3]}), \
        [c.label for c in finding.candidates[:3]]
    # both joints explained: what is left is the noise (20% over its mean length: a held-out fit's own spread)
    assert finding.extended.heldout_mean_mm < 1.2 * case.noise_mean_mm
    # each joint's deflection determined by the data, and as large as the truth (20%: the size tolerance of
    # every hidden-effect test, a few standard errors at this visibility)
    entries = {tuple(e["places"]): e for e in finding.magnitude["places"]}
    for j in (1, 2):
        entry = entries[(f"joint{j + 1}",)]
        true_deg = np.rad2deg(np.std(case.campaign.true_joint_delta[:, j]))
        assert entry["kind"] == "determined" and entry["deflection_std_deg"] == pytest.approx(true_deg, rel=0.2)


def test_compliance_of_two_joints_and_a_periodic_error_of_a_third_are_two_effects_each_with_its_share():
    model = load_robot("abb-irb4600")
    effects = [HiddenEffect("joint_compliance", 1), HiddenEffect("joint_compliance", 2),
               HiddenEffect("cyclic_joint_error", 4, order=2)]
    case = make_case(model, effects, [4.0, 4.0, 3.0], n=200, seed=1)
    finding = analyze(model, case.campaign.obs, case.campaign.ctx)
    assert (finding.cause, finding.where) == ("joint_compliance", {"joints": [2, 3]})
    assert finding.second is not None
    assert (finding.second.cause, finding.second.where) == ("cyclic_joint_error", {"joint": 5, "order": 2})
    # both fitted reach the noise (20% over its mean length, as above); each effect has its share of the gain
    assert finding.both.heldout_mean_mm < 1.2 * case.noise_mean_mm
    first, second = finding.shares_pct
    assert first + second == pytest.approx(100.0, abs=1e-9)
    # the compliance is the larger effect (4x against 3x the noise, on two joints): the larger share
    assert first > second > 100 * MIN_GAIN


def test_inner_folds_hold_out_whole_sub_folds_and_path_gaps():
    # the inner folds of fold k never hold out, nor train on, a row of fold k; with path-ordered data an
    # inner training leaves out both folds' gaps: compared with Gram matrices built row by row
    rng = np.random.default_rng(0)
    steps = np.column_stack([rng.uniform(0.005, 0.015, 400), rng.normal(0.0, 0.005, (400, 2))])
    q = np.cumsum(steps, axis=0)  # a path: consecutive rows about 0.6 deg apart
    folds = crossval.fold_ids(q, 5, 0, crossval.NEIGHBOUR_RAD)
    assert folds.exclude is not None
    j, r = rng.normal(size=(400, 3, 2)), rng.normal(size=(400, 3))
    factors = crossval.FoldFactors(folds, 2)
    factors.add(slice(0, 400), j, r)
    block = np.concatenate([j, r[:, :, None]], axis=2)

    def gram(rows):
        return np.einsum("nia,nib->ab", block[rows], block[rows])

    ids = np.unique(folds)
    for k in range(5):
        train_k = crossval.training_rows(folds, k)
        expected = []
        for i in range(5):
            if i == k:
                continue
            held = np.intersect1d(np.flatnonzero(np.asarray(folds) == ids[i]), train_k)
            train = np.setdiff1d(train_k, np.concatenate([held, folds.exclude[i]]))
            expected.append((gram(train), gram(held)))
        for (train, held), (want_train, want_held) in zip(factors.inner(k), expected):
            # sums of the same products in another order: equal to rounding
            assert np.allclose(train, want_train, rtol=1e-10, atol=1e-9)
            assert np.allclose(held, want_held, rtol=1e-10, atol=1e-9)


def _spread_periodic_errors(seed: int):
    """A collaborative arm as trackers find them: a periodic error of one or two orders (1-4) at every
    joint, each moving the tool 0.15 mm rms, and compliance of joints 2 and 3 (0.15 and 0.1 mm); 200
    random poses, repeatability 0.02 mm."""
    model = load_robot("ur10e")
    rng = np.random.default_rng(seed)
    effects = []
    for j in range(6):
        orders = rng.choice([1, 2, 3, 4], size=int(rng.integers(1, 3)), replace=False)
        effects.append(HiddenEffect("cyclic_joint_error", j, rms_mm=0.15, harmonics=tuple(
            (int(o), float(rng.uniform(0.3, 1.0)), float(rng.uniform(0, 2 * np.pi))) for o in orders)))
    effects += [HiddenEffect("joint_compliance", 1, rms_mm=0.15), HiddenEffect("joint_compliance", 2, rms_mm=0.1)]
    run = _arm(model, seed, tuple(effects), 0.4).campaign(full_workspace(model, 200, np.random.default_rng(seed + 99)))
    return model, run


@pytest.mark.parametrize("seed", [0, 2])
def test_periodic_errors_spread_over_every_joint_are_found_at_every_joint_with_compliance_second(seed):
    # each joint's orders add a few percent: the search must go on past the first places (and past a joint's
    # spline, which leads as a single place on seed 0) to reach the per-joint periodic model the data hold;
    # compliance, the rest, is the second effect
    model, run = _spread_periodic_errors(seed)
    finding = analyze(model, run.obs, run.ctx)
    assert finding.cause == "cyclic_joint_error", (finding.cause, finding.notes)
    assert len(finding.where.get("joints", [])) >= 5, finding.where
    assert finding.second is not None and finding.second.cause == "joint_compliance"
    base = finding.baseline.heldout_mean_mm
    # measured 0.35-0.42 of the baseline with the periodic error, 0.14-0.19 with both (noise ~0.05 mm of ~0.35);
    # a search that stops after one to three joints keeps 0.7-0.9 of it
    assert finding.extended.heldout_mean_mm < 0.5 * base
    assert finding.both.heldout_mean_mm < 0.3 * base


def test_the_second_effect_is_searched_and_scored_with_each_folds_own_choice_of_the_named_one(monkeypatch):
    # the named effect's score is each fold's own choice on that fold; the second effect, searched with the named
    # one in the model, must hold the same choices fold by fold (the all-rows choice in every fold scores the pair
    # on rows that made it: on a measured UR10, 0.128 mm for a pair whose named effect alone scored 0.196)
    model, run = _spread_periodic_errors(0)
    calls = []
    real = selection.select

    def recording(cause, places, alone, scores, base=(), fold_bases=None):
        out = real(cause, places, alone, scores, base, fold_bases)
        calls.append((cause.id, base, fold_bases, out, scores))
        return out

    monkeypatch.setattr(selection, "select", recording)
    finding = analyze(model, run.obs, run.ctx)
    assert finding.cause == "cyclic_joint_error" and finding.second is not None, finding.where
    named = next(c[3] for c in calls if c[3] is not None and c[3].term is finding.extended.terms[0])
    # the choices differ between folds here: which choice each fold holds matters
    assert any(set(map(id, own)) != set(map(id, named.parts)) for own in named.per_fold)
    again = [c for c in calls if c[1] == finding.extended.terms]
    assert again and all(c[2] == named.per_fold for c in again)
    second = next(c for c in again if c[3] is not None and c[3].term is finding.second.terms[0])
    scores = second[4]
    nested = scores.scorer.heldout_errors_of_steps(selection.nested_steps(scores, second[3], named.per_fold))[0]
    # the pair's reported held-out errors are those of each fold's own two choices (the same computation: exact
    # up to rounding of the one pass over the rows)
    assert np.allclose(finding.both.heldout_errors, nested, rtol=1e-9, atol=1e-12)
