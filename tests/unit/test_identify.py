"""Identification against the simulation's hidden truth and held-out data.

Every accuracy number here is scored on fresh validation poses (never the
training fit) against either the floor the *true* model reaches on the same
noisy data, or a fit started from the truth.
"""
import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.sims.physics.kinematic_arm import SimulatedArm, TrackerNoise
from cellcal.sims.physics.workspace import constrained_volume, full_workspace
from cellcal.solvers.identification.identify import IdentifyOptions, fit, identify
from cellcal.solvers.identification.measurement_model import Observations, predict
from cellcal.solvers.identification.pose_design import select_poses


def mean_error(layout, x, obs):
    return float(np.linalg.norm(predict(layout, x, obs) - obs.xyz_mm, axis=1).mean())


@pytest.fixture(scope="module")
def irb4600():
    return load_robot("abb-irb4600")


@pytest.mark.parametrize("regularize", ["none", "cv"])
@pytest.mark.parametrize("seed", [0, 1])
def test_full_workspace_identification_reaches_the_noise_floor(irb4600, regularize, seed):
    # IRB4600, 150 poses, errors +-0.5 mm / +-0.05 deg, AT960 + 0.05 mm repeatability
    rng = np.random.default_rng(seed)
    arm = SimulatedArm(irb4600, rng)
    cal = arm.measure(full_workspace(irb4600, 150, rng))
    val = arm.measure(full_workspace(irb4600, 300, rng))
    result = identify(irb4600, cal, IdentifyOptions(regularize=regularize))
    floor = arm.oracle_errors(val).mean()
    after = result.errors(val).mean()
    before = result.errors(val, nominal=True).mean()
    assert after <= 1.15 * floor, (after, floor)
    assert before > 5 * after  # the hidden errors were real and were removed


def test_structurally_redundant_parameters_are_held_and_named(irb4600):
    rng = np.random.default_rng(3)
    arm = SimulatedArm(irb4600, rng)
    cal = arm.measure(full_workspace(irb4600, 150, rng))
    result = identify(irb4600, cal, IdentifyOptions(regularize="none"))
    held = set(result.unidentifiable)
    # base absorbs theta1, d1; a point target absorbs all of joint 6; parallel axes 2 and 3
    # leave d2 + d3 as one quantity
    assert {"theta1", "d1", "theta6", "d6", "a6", "alpha6"} <= held
    assert len(held & {"d2", "d3"}) == 1
    assert len(held) == 7
    for name in held:
        i = irb4600.index(name)
        assert result.x[i] == irb4600.nominal[i] and result.std[i] == 0.0


def _small_volume_cell(seed):
    """The set-up of Liu et al., "L2-Regularization-Based Kinematic Parameter Identification for
    Industrial Robots in Limited Measurement Space" (Actuators 2025): Elite EC66, 60 poses of a ball inside a 20 mm cube measured by an
    R-test (a few um), robot repeatability 0.02 mm; validation over the full workspace."""
    model = load_robot("elite-ec66")
    rng = np.random.default_rng(seed)
    arm = SimulatedArm(model, rng, target_offsets=[[0.0, 0.0, 100.0]], repeatability_mm=0.02,
                       tracker=TrackerNoise(constant_mm=0.002, per_m_mm=0.0))
    q = constrained_volume(model, 60, rng, centre_mm=[500.0, 0.0, 100.0], max_tilt_deg=60.0,
                           offset_mm=(0.0, 0.0, 100.0))
    return model, arm, arm.measure(q), arm.measure(full_workspace(model, 300, rng))


@pytest.mark.parametrize("regularize", ["none", "cv"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_calibration_in_a_20mm_cube_generalises_to_the_full_workspace(regularize, seed):
    model, arm, cal, val = _small_volume_cell(seed)
    assert np.ptp(cal.xyz_mm, axis=0).max() < 35.0  # the cube (plus the tool's true offset error)
    result = identify(model, cal, IdentifyOptions(regularize=regularize))
    before = result.errors(val, nominal=True).mean()
    after = result.errors(val).mean()
    # the same least squares over the same parameters, started at the hidden truth
    oracle = fit(result.layout, cal, arm.truth.x, result.free, lam=result.lam)
    oracle_after = mean_error(result.layout, oracle.x, val)
    assert after <= 0.2 * before, (after, before)
    assert after <= 1.25 * oracle_after, (after, oracle_after)


def test_cv_reports_its_curve_and_picks_its_minimum(irb4600):
    rng = np.random.default_rng(4)
    arm = SimulatedArm(irb4600, rng)
    result = identify(irb4600, arm.measure(full_workspace(irb4600, 80, rng)), IdentifyOptions())
    lams = [lam for lam, _ in result.cv_curve]
    errs = [e for _, e in result.cv_curve]
    assert lams[0] == 0.0 and len(lams) == 22
    assert result.lam == lams[int(np.argmin(errs))]


def test_reported_std_matches_the_scatter_over_repeated_campaigns(irb4600):
    rng = np.random.default_rng(5)
    arm = SimulatedArm(irb4600, rng)
    q = full_workspace(irb4600, 100, rng)
    estimates, stds = [], []
    for _ in range(30):
        result = identify(irb4600, arm.measure(q), IdentifyOptions(regularize="none"))
        estimates.append(result.x[result.free])
        stds.append(result.std[result.free])
    ratio = np.std(estimates, axis=0) / np.mean(stds, axis=0)
    # 30 draws: the sample std is within about +-30% of the true one
    assert 0.65 < np.median(ratio) < 1.35, np.round(ratio, 2)
    assert np.all((ratio > 0.4) & (ratio < 1.8)), np.round(ratio, 2)


def test_robust_loss_ignores_gross_outliers_with_two_targets():
    model = load_robot("ur10e")
    rng = np.random.default_rng(6)
    arm = SimulatedArm(model, rng, target_names=("smr1", "smr2"))
    q = full_workspace(model, 100, rng)
    cal = arm.measure(np.repeat(q, 2, axis=0), np.tile([0, 1], 100))
    bad = rng.choice(len(cal), 10, replace=False)
    xyz = cal.xyz_mm.copy()
    xyz[bad] += rng.normal(size=(10, 3)) * 3.0  # 5% of the points off by several mm
    spoiled = Observations(cal.q, xyz, cal.target, cal.target_names)
    vq = full_workspace(model, 200, rng)
    val = arm.measure(np.repeat(vq, 2, axis=0), np.tile([0, 1], 200))
    floor = arm.oracle_errors(val).mean()
    plain = identify(model, spoiled, IdentifyOptions(regularize="none")).errors(val).mean()
    robust = identify(model, spoiled, IdentifyOptions(regularize="none", loss="soft_l1")).errors(val).mean()
    assert robust <= 1.15 * floor, (robust, floor)
    assert plain > 1.5 * robust  # the outliers do hurt least squares


def test_d_optimal_pose_design_beats_random_choice():
    model = load_robot("ur10e")
    excess = {"design": [], "random": []}
    for seed in range(4):
        rng = np.random.default_rng(seed)
        arm = SimulatedArm(model, rng, target_offsets=[[0.0, 0.0, 100.0]])
        candidates = full_workspace(model, 400, rng)
        val = arm.measure(full_workspace(model, 300, rng))
        floor = arm.oracle_errors(val).mean()
        chosen = select_poses(model, candidates, 25).chosen
        assert len(set(chosen.tolist())) == 25
        for name, q in (("design", candidates[chosen]), ("random", candidates[:25])):
            result = identify(model, arm.measure(q), IdentifyOptions(regularize="none"))
            excess[name].append(result.errors(val).mean() / floor - 1.0)
    # the error above the floor (what the poses can still improve) shrinks by a quarter or more
    assert np.mean(excess["design"]) < 0.75 * np.mean(excess["random"]), excess


def test_linearised_cross_validation_matches_refitting_every_fold():
    from cellcal.solvers.estimation.crossval import fold_ids

    model, arm, cal, _ = _small_volume_cell(0)  # the small-volume case, where the prior matters most
    options = IdentifyOptions(regularize="cv")
    result = identify(model, cal, options)
    folds = fold_ids(cal.q, options.folds, options.seed)
    for lam, curve_err in result.cv_curve[::5]:
        errs = np.empty(len(cal))
        for f in range(options.folds):
            train, test = np.flatnonzero(folds != f), np.flatnonzero(folds == f)
            refit = fit(result.layout, cal.subset(train), result.x_nominal, result.free, lam=lam)
            errs[test] = np.linalg.norm(predict(result.layout, refit.x, cal.subset(test)) - cal.xyz_mm[test], axis=1)
        assert curve_err == pytest.approx(errs.mean(), rel=0.03), lam


def test_result_reads_like_scipy_with_units_in_the_names(irb4600):
    rng = np.random.default_rng(7)
    arm = SimulatedArm(irb4600, rng)
    cal = arm.measure(full_workspace(irb4600, 60, rng))
    result = identify(irb4600, cal, IdentifyOptions(regularize="none"))
    assert result.status in (1, 2, 3, 4) and result.success
    assert "termination condition" in result.message
    assert result.residuals_mm.shape == (60, 3) and result.residuals_nominal_mm.shape == (60, 3)
    assert np.allclose(np.linalg.norm(result.residuals_mm, axis=1), result.errors(cal))
    assert result.structural_rank >= result.noise_rank > 0 and result.first_pass_noise_mm > 0
    assert result.weakly_identifiable == () and result.held_implausible == ()  # a well-posed campaign
    assert set(result.held_at_nominal) == set(result.unidentifiable)
    assert not hasattr(result, "details") and not hasattr(result, "residuals")
    # the fit underneath says the same
    refit = fit(result.layout, cal, result.x_nominal, result.free)
    assert refit.status > 0 and refit.message and refit.residuals_mm.shape == (60, 3)
    assert refit.rms_mm == pytest.approx(np.sqrt(np.mean(refit.errors**2)))
