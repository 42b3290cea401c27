"""`analyze` must find an effect hidden in generated data, size it, and say `none` when there is none.

Each case draws robot, joint, size (3-6x the noise, as left after a geometric
calibration), noise level and data size from a seeded generator; the analysis
sees only the measured data. Sizes are checked against the simulation's truth.
"""
import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from support.hidden_cases import make_case  # tests/support/hidden_cases.py: a fixture, not part of the package
from support.naming_stubs import BASELINE, StubScorer, scored  # tests/support/naming_stubs.py
from cellcal.sims.physics.physical_arm import HiddenEffect
from cellcal.solvers.analysis.analyze import analyze
from cellcal.solvers.analysis.naming import MIN_GAIN, MIN_MARGIN, name_cause
from cellcal.solvers.geometry.robot_model import parallel_joint_pairs

ROBOTS = ("ur10e", "abb-irb4600", "elite-ec66")
SIZES = (60, 120, 250, 500)
NOISE = (0.5, 1.0, 2.0)


def draw(cause: str, seed: int):
    """The hidden choice: robot, joint, visibility, size of data, noise level."""
    rng = np.random.default_rng(seed)
    model = load_robot(ROBOTS[seed % len(ROBOTS)])
    joint = None
    if cause == "joint_compliance":
        joint = int(rng.choice([1, 2]))  # shoulder and elbow carry the gravity load
    elif cause == "parallel_axis_tilt":
        joint = int(rng.choice(parallel_joint_pairs(model)))
    elif cause in ("backlash", "cyclic_joint_error"):
        joint = int(rng.integers(0, model.n_joints))
    effect = HiddenEffect(cause, joint, order=int(rng.integers(1, 4)), phase_rad=float(rng.uniform(0, 2 * np.pi)),
                          jitter_s=0.0005 if cause == "trigger_latency" else 0.0)
    n = int(rng.choice(SIZES))
    return model, effect, float(rng.uniform(3.0, 6.0)), n, float(rng.choice(NOISE))


def true_size(case, effect, finding_magnitude):
    """(estimated, true) physical size in the units the finding reports."""
    e = effect
    if e.cause == "joint_compliance":
        true = np.rad2deg(np.sqrt(np.mean(case.campaign.true_joint_delta[:, e.joint] ** 2)))
        return finding_magnitude["deflection_rms_deg"], true
    if e.cause == "backlash":
        return finding_magnitude["backlash_deg"], np.rad2deg(abs(e.size))
    if e.cause == "cyclic_joint_error":
        return finding_magnitude["amplitude_deg"], np.rad2deg(abs(e.size))
    if e.cause == "parallel_axis_tilt":
        return finding_magnitude["tilt_deg"], np.rad2deg(abs(e.size))
    if e.cause == "thermal_drift":
        warmup_k = 8.0  # PhysicalArm.campaign's default warm-up
        return finding_magnitude["expansion_ppm_per_K"], e.size / warmup_k * 1e6
    return finding_magnitude["latency_ms"], e.size * 1e3


def where_joint(finding):
    return finding.where.get("joint", (finding.where.get("joints") or [None])[0])


CASES = [(cause, seed) for cause in ("joint_compliance", "backlash", "thermal_drift", "cyclic_joint_error",
                                     "parallel_axis_tilt", "trigger_latency") for seed in (0, 1, 2)]


@pytest.mark.parametrize("cause,seed", CASES)
def test_hidden_effect_is_named_sized_and_removed(cause, seed):
    model, effect, visibility, n, noise = draw(cause, seed)
    case = make_case(model, [effect], [visibility], n=n, noise_scale=noise, seed=seed)
    finding = analyze(model, case.campaign.obs, case.campaign.ctx)
    hidden = case.effects[0]
    label = f"{model.name}, {n} poses, noise x{noise}, {visibility:.1f}x visible"
    assert finding.cause == cause, (label, finding.cause, finding.notes, [c.label for c in finding.candidates[:3]])
    if hidden.joint is not None:
        assert where_joint(finding) == hidden.joint + 1, (label, finding.where)
    if cause == "cyclic_joint_error":
        assert finding.where["order"] == hidden.order
    estimated, true = true_size(case, hidden, finding.magnitude)
    assert estimated == pytest.approx(true, rel=0.20), label
    assert finding.gain_pct >= 50.0, label


@pytest.mark.parametrize("seed", range(6))
def test_no_effect_gives_none(seed):
    rng = np.random.default_rng(100 + seed)
    model = load_robot(ROBOTS[seed % len(ROBOTS)])
    n = int(rng.choice(SIZES))
    case = make_case(model, [], [], n=n, noise_scale=float(rng.choice(NOISE)), seed=100 + seed)
    finding = analyze(model, case.campaign.obs, case.campaign.ctx)
    assert finding.cause == "none", (model.name, n, finding.candidates[0].label, finding.notes)
    assert finding.gain_pct == 0.0


@pytest.mark.parametrize("pair,seed", [
    ((("joint_compliance", 1), ("backlash", 3)), 0),
    ((("cyclic_joint_error", 0), ("joint_compliance", 2)), 1),
    ((("parallel_axis_tilt", 1), ("cyclic_joint_error", 5)), 2),
])
def test_two_effects_dominant_named_second_found_and_both_fitted(pair, seed):
    model = load_robot(ROBOTS[seed])
    effects = [HiddenEffect(c, j, order=2) for c, j in pair]
    case = make_case(model, effects, [6.0, 3.0], n=300, noise_scale=1.0, seed=seed)
    finding = analyze(model, case.campaign.obs, case.campaign.ctx)
    (first, j1), (second, j2) = pair
    assert finding.cause == first and where_joint(finding) == j1 + 1
    assert finding.second is not None
    assert finding.second.cause == second and where_joint(finding.second) == j2 + 1
    # fitting both is better than either alone, and close to the noise
    assert finding.both.heldout_mean_mm < 0.9 * finding.extended.heldout_mean_mm
    assert finding.both.heldout_mean_mm < 1.2 * case.noise_mean_mm


@pytest.mark.parametrize("robot", ["abb-irb4600", "elite-ec66"])
def test_cyclic_error_is_not_taken_for_compliance_of_the_same_joint(robot):
    # without masses, the shoulder's own link weighs in as a pure sinusoid of q2: the compliance
    # model contains the cyclic one, and the simpler explanation must win the tie
    model = load_robot(robot)
    case = make_case(model, [HiddenEffect("cyclic_joint_error", 1, order=1)], [4.0], n=300, seed=3)
    finding = analyze(model, case.campaign.obs, case.campaign.ctx)
    assert (finding.cause, finding.where) == ("cyclic_joint_error", {"joint": 2, "order": 1})
    assert finding.gain_pct >= 50.0


# -- the naming rule alone, on made-up held-out scores (tests/support/naming_stubs.py) ------------------------------


def test_naming_rule_says_none_when_the_best_gains_too_little():
    best = scored("backlash", 1.0 - 0.5 * MIN_GAIN)
    naming = name_cause([best, scored("thermal_drift", 0.99)], BASELINE, StubScorer())
    assert naming.named is None and "below the 10%" in naming.notes[0]


def test_naming_rule_names_a_clear_winner():
    best, other = scored("backlash", 0.5), scored("thermal_drift", 0.5 * (1.0 + 2 * MIN_MARGIN))
    naming = name_cause([best, other], BASELINE, StubScorer())
    assert naming.named is best and naming.notes == ()
    assert naming.margin == pytest.approx(2 * MIN_MARGIN, rel=1e-12)


def test_naming_rule_names_the_best_of_two_causes_that_add_up():
    best, other = scored("backlash", 0.50), scored("thermal_drift", 0.52)
    naming = name_cause([best, other], BASELINE, StubScorer(pair_mean_mm=0.30))
    assert naming.named is best and "both present" in naming.notes[0]


def test_naming_rule_says_none_for_two_causes_that_explain_the_same():
    best, other = scored("backlash", 0.50), scored("thermal_drift", 0.52)
    naming = name_cause([best, other], BASELINE, StubScorer(pair_mean_mm=0.49))
    assert naming.named is None and "about equally well" in naming.notes[0]


def test_naming_rule_prefers_the_simpler_of_two_nested_explanations():
    larger, simpler = scored("joint_compliance", 0.50, size=3), scored("cyclic_joint_error", 0.52, size=2)
    naming = name_cause([larger, simpler], BASELINE, StubScorer(nested=True))
    assert naming.named is simpler and naming.candidates[:2] == (larger, simpler)  # listed best first all the same
    assert "simpler explanation" in naming.notes[0]


def with_gross_outliers(obs, noise_mm: float, seed: int, fraction: float = 0.05):
    """obs with `fraction` of the measurements moved 40-100x the noise in random directions."""
    from cellcal.solvers.identification.measurement_model import Observations

    rng = np.random.default_rng(900 + seed)
    k = max(1, int(round(fraction * len(obs))))
    rows = rng.choice(len(obs), k, replace=False)
    direction = rng.normal(size=(k, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    xyz = obs.xyz_mm.copy()
    xyz[rows] += direction * rng.uniform(40.0, 100.0, (k, 1)) * noise_mm
    return Observations(obs.q, xyz, obs.target, obs.target_names)


@pytest.mark.slow
@pytest.mark.parametrize("cause,seed", CASES)
def test_hidden_effect_is_named_through_gross_outliers_with_a_robust_loss(cause, seed):
    # the same cases with 5% gross outliers: under the linear loss they halve every gain and one
    # case falls below the naming threshold; the robust loss names every one, at the right place
    from cellcal.solvers.analysis.analyze import AnalyzeOptions

    model, effect, visibility, n, noise = draw(cause, seed)
    case = make_case(model, [effect], [visibility], n=n, noise_scale=noise, seed=seed)
    obs = with_gross_outliers(case.campaign.obs, case.noise_mm, seed)
    finding = analyze(model, obs, case.campaign.ctx, AnalyzeOptions(loss="soft_l1"))
    assert finding.cause == cause, (finding.notes, [c.label for c in finding.candidates[:3]])
    if effect.joint is not None:
        assert where_joint(finding) == case.effects[0].joint + 1, finding.where
    # well clear of the 10% naming threshold: under the linear loss these outliers leave the gains at half or
    # less. Not 50%: with 5% gross outliers a fold's nested search now and then misses the effect (gain 0 on that
    # fold while others gain 60%), so one draw of the folds puts a case at 41%, another at 54% (the one-standard-
    # error spread of five such fold gains is about 13 points)
    assert finding.gain_pct >= 30.0


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(4))
def test_robust_loss_raises_no_alarm_on_effect_free_data_with_gross_outliers(seed):
    from cellcal.solvers.analysis.analyze import AnalyzeOptions

    model = load_robot(ROBOTS[seed % len(ROBOTS)])
    case = make_case(model, [], [], n=60, noise_scale=NOISE[seed % len(NOISE)], seed=300 + seed)
    obs = with_gross_outliers(case.campaign.obs, case.noise_mm, seed)
    finding = analyze(model, obs, case.campaign.ctx, AnalyzeOptions(loss="soft_l1"))
    assert finding.cause == "none", (finding.candidates[0].label, finding.notes)
