"""Periodic joint errors of any order: several orders from 1 to 60 on several joints are found, the
model reaches what the true structure reaches on held-out data, and the wider search raises no alarm
on effect-free data. The analysis sees only the measured data; the checks use the simulation's truth.
"""
import json

import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.sims.physics.physical_arm import HiddenEffect
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.analysis import selection
from cellcal.solvers.analysis.analyze import analyze, heldout_with_terms
from cellcal.solvers.analysis.effects import periodic_spline
from cellcal.solvers.estimation import crossval
from cellcal.solvers.analysis.effects import JointBasis, Term
from cellcal.solvers.analysis.effects.cyclic_joint_error import fitted_errors, harmonics, order_bound, periodogram, pursuit
from support.hidden_cases import _arm, make_case

ROBOTS = ("ur10e", "abb-irb4600", "elite-ec66")


def draw_cyclic(seed: int):
    """Two joints, each with three orders drawn from 1-60 (relative amplitudes 1, 0.5, 0.3)."""
    rng = np.random.default_rng(500 + seed)
    model = load_robot(ROBOTS[seed % len(ROBOTS)])
    effects = []
    for j in rng.choice(model.n_joints, 2, replace=False):
        orders = rng.choice(np.arange(1, 61), 3, replace=False)
        effects.append(HiddenEffect("cyclic_joint_error", int(j), harmonics=tuple(
            (int(n), w, float(rng.uniform(0, 2 * np.pi))) for n, w in zip(orders, (1.0, 0.5, 0.3)))))
    return model, effects, [float(v) for v in rng.uniform(4.0, 6.0, 2)]


def joint_orders(where) -> dict:
    if "joints" in where:
        return dict(zip(where["joints"], where["orders"]))
    return {where["joint"]: where.get("orders", [where.get("order")])}


def dominant_order(magnitude: dict, joint: int) -> int:
    amplitudes = {int(k.split("_order")[1].split("_")[0]): v for k, v in magnitude.items()
                  if k.startswith(f"joint{joint}_order")}
    return max(amplitudes, key=amplitudes.get)


def true_terms(case, n_joints: int):
    q = case.campaign.obs.q
    return [Term("cyclic_joint_error", {"joint": e.joint + 1}, tuple(f"p{i}" for i in range(2 * len(e.harmonics))),
                 joint_basis=JointBasis.single(harmonics(q[:, e.joint], [n for n, _, _ in e.harmonics]), e.joint,
                                               n_joints))
            for e in case.effects]


@pytest.fixture(scope="module", params=range(3))
def high_order_case(request):
    model, effects, visibility = draw_cyclic(request.param)
    case = make_case(model, effects, visibility, n=300, seed=500 + request.param)
    return model, case, analyze(model, case.campaign.obs, case.campaign.ctx)


@pytest.mark.slow
def test_high_order_cyclic_errors_on_several_joints_are_named_with_their_orders(high_order_case):
    model, case, finding = high_order_case
    assert finding.cause == "cyclic_joint_error", ([c.label for c in finding.candidates[:3]], finding.notes)
    found = joint_orders(finding.where)
    assert sorted(found) == sorted(e.joint + 1 for e in case.effects), finding.where
    for e in case.effects:
        true_dominant = e.harmonics[0][0]
        found_dominant = dominant_order(finding.magnitude, e.joint + 1)
        assert abs(found_dominant - true_dominant) <= 1, (e.harmonics, finding.magnitude)
        # its amplitude, against the truth (degrees), within 20%
        amplitude = finding.magnitude[f"joint{e.joint + 1}_order{true_dominant}_amplitude_deg"]
        assert amplitude == pytest.approx(np.rad2deg(abs(e.size)), rel=0.2)
    truth_mm = heldout_with_terms(model, case.campaign.obs, true_terms(case, model.n_joints)).mean()
    assert finding.extended.heldout_mean_mm <= 1.2 * truth_mm, (finding.extended.heldout_mean_mm, truth_mm)
    assert finding.gain_pct >= 50.0


@pytest.mark.slow
def test_fitted_cyclic_error_carries_its_coverage_and_is_rigid_outside(high_order_case):
    model, case, finding = high_order_case
    q = case.campaign.obs.q
    errors = fitted_errors(finding.extended.terms[0], finding.extended.theta, q)
    assert sorted(e.joint for e in errors) == sorted(e.joint + 1 for e in case.effects)
    for err in errors:
        lo, hi = err.coverage_rad[0][0], err.coverage_rad[-1][1]
        assert (lo, hi) == (q[:, err.joint - 1].min(), q[:, err.joint - 1].max())
        inside = np.concatenate([np.linspace(a, b, 50) for a, b in err.coverage_rad])
        hidden = next(e for e in case.effects if e.joint + 1 == err.joint)
        truth = hidden.size * sum(w * np.sin(n * inside + ph) for n, w, ph in hidden.harmonics)
        # the fitted function follows the hidden one within 25% of its amplitude inside the coverage
        assert np.sqrt(np.mean((err.delta_rad(inside) - truth) ** 2)) < 0.25 * abs(hidden.size)
        assert np.all(err.delta_rad(np.array([lo - 0.1, hi + 0.1])) == 0.0)


NONE_SEEDS = range(200, 220)


@pytest.mark.parametrize("seed", NONE_SEEDS)
def test_wider_order_search_raises_no_alarm_on_effect_free_data(seed):
    rng = np.random.default_rng(seed)
    model = load_robot(ROBOTS[seed % len(ROBOTS)])
    n = int(rng.choice((60, 90)))
    case = make_case(model, [], [], n=n, noise_scale=float(rng.choice((0.5, 1.0, 2.0))), seed=seed)
    finding = analyze(model, case.campaign.obs, case.campaign.ctx)
    assert finding.cause == "none", (model.name, n, finding.candidates[0].label, finding.notes)


def test_order_bound_is_nyquist_in_the_spacing_of_the_sampled_angles():
    q = np.linspace(-np.pi, np.pi, 201)  # even spacing 2 pi / 200: half-period pi / n resolved up to n = 100
    assert order_bound(q) == 100
    assert order_bound(q[::4]) == 25
    assert order_bound(np.full(50, 0.3)) == 0  # a joint that does not move has no periods to resolve


def test_periodogram_finds_each_order_and_its_amplitude():
    rng = np.random.default_rng(1)
    q = rng.uniform(-3.0, 3.0, 400)
    weight = rng.uniform(0.5, 2.0, 400)  # |d p / d q|^2 differs from pose to pose
    delta = 2e-3 * np.sin(37 * q + 0.4) + 1e-3 * np.cos(5 * q)
    orders, amplitude, power = periodogram(q, weight * delta, weight, 60)
    assert set(orders[np.argsort(power)[-2:]]) == {5, 37}
    assert amplitude[36] == pytest.approx(2e-3, rel=0.1) and amplitude[4] == pytest.approx(1e-3, rel=0.15)


@pytest.mark.slow
def test_cli_states_orders_coverage_and_the_rigid_fallback_and_plots_them(tmp_path, capsys):
    from cellcal.cli.main import main
    from cellcal.measurements.writer import write_measurements

    model, effects, visibility = draw_cyclic(0)
    case = make_case(model, effects, visibility, n=200, seed=7)
    path = tmp_path / "cyclic.csv"
    write_measurements(path, q_rad=case.campaign.obs.q, xyz_mm=case.campaign.obs.xyz_mm)
    assert main(["analyze", "--robot", model.name, "--data", str(path), "--json",
                 "--report", str(tmp_path / "report")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["cause"] == "cyclic_joint_error"
    hidden = sorted(e.joint + 1 for e in case.effects)
    assert sorted(e["joint"] for e in doc["effect"]["errors"]) == hidden
    q_deg = np.rad2deg(case.campaign.obs.q)
    for err in doc["effect"]["errors"]:
        cover = err["coverage_deg"]
        assert cover[0][0] == pytest.approx(q_deg[:, err["joint"] - 1].min())
        assert cover[-1][1] == pytest.approx(q_deg[:, err["joint"] - 1].max())
        assert len(err["orders"]) == len(err["amplitude_deg"]) == len(err["sin_rad"])
    assert "rigid model" in doc["effect"]["outside_coverage"]
    search = doc["cyclic_order_search"]["joints"]
    assert {j: v["orders"][1] for j, v in search.items()} == {
        str(j + 1): order_bound(case.campaign.obs.q[:, j]) for j in range(model.n_joints)}
    assert set(doc["joint_coverage_deg"]) == {str(j) for j in range(1, model.n_joints + 1)}
    for j in hidden:
        assert (tmp_path / "report" / f"cyclic_joint{j}.png").stat().st_size > 1000
    assert (tmp_path / "report" / "periodogram.png").stat().st_size > 1000
    text = (tmp_path / "report" / "report.md").read_text()  # the text finding, as printed without --json
    assert "fall back to the rigid model" in text and "cyclic orders scanned" in text


@pytest.mark.slow
def test_periodic_error_that_is_no_few_sinusoids_is_fitted_as_a_periodic_spline():
    # a narrow periodic bump on one joint: thirty orders at once, beyond a few sinusoids
    model = load_robot("ur10e")
    width, centre = 8.0, 0.7
    bump = tuple((n, float(np.exp(-(n / width) ** 2)), float(np.pi / 2 - n * centre)) for n in range(1, 31))
    case = make_case(model, [HiddenEffect("cyclic_joint_error", 2, harmonics=bump)], [5.0], n=300, seed=1)
    finding = analyze(model, case.campaign.obs, case.campaign.ctx)
    assert finding.cause == "cyclic_joint_error" and finding.where["joint"] == 3, finding.where
    assert "spline_knots" in finding.where
    q = case.campaign.obs.q
    truth = Term("cyclic_joint_error", {"joint": 3}, tuple(f"p{i}" for i in range(60)),
                 joint_basis=JointBasis.single(harmonics(q[:, 2], range(1, 31)), 2, model.n_joints))
    truth_mm = heldout_with_terms(model, case.campaign.obs, [truth]).mean()
    assert finding.extended.heldout_mean_mm <= 1.2 * truth_mm, (finding.extended.heldout_mean_mm, truth_mm)
    # the fitted function follows the hidden one (up to the joint offset the geometry holds)
    (spline,) = fitted_errors(finding.extended.terms[0], finding.extended.theta, q)
    inside = np.concatenate([np.linspace(a, b, 200) for a, b in spline.coverage_rad])
    hidden = case.effects[0].size * sum(w * np.sin(n * inside + ph) for n, w, ph in bump)
    fitted = spline.delta_rad(inside)
    miss = (fitted - fitted.mean()) - (hidden - hidden.mean())
    assert np.sqrt(np.mean(miss**2)) < 0.15 * np.ptp(hidden)
    assert finding.magnitude["peak_to_peak_deg"] == pytest.approx(np.rad2deg(np.ptp(hidden)), rel=0.25)
    # a calibrated model made of the fit applies the same function, rigid outside the coverage
    from cellcal.solvers.compensation.calibrated_model import from_fit

    calibrated = from_fit(model, case.campaign.obs.target_names, finding.extended.x, finding.extended.terms,
                          finding.extended.theta, q)
    (kept,) = calibrated.periodic
    outside = np.array([spline.coverage_rad[0][0] - 0.05, spline.coverage_rad[-1][1] + 0.05])
    assert np.allclose(kept.delta_rad(inside), fitted) and np.all(kept.delta_rad(outside) == 0.0)


def test_order_pursuit_from_sums_matches_refitting_on_the_rows():
    rng = np.random.default_rng(3)
    q = rng.uniform(-3.0, 3.0, 1500)
    weight = rng.uniform(0.5, 2.0, 1500)
    delta = 2e-3 * np.sin(33 * q + 0.3) + 1e-3 * np.sin(37 * q + 1.0) + 6e-4 * np.cos(34 * q)
    projected = weight * (delta + rng.normal(0.0, 3e-4, 1500))
    picked, left = [], projected  # the same pursuit, refitting the picked orders on the rows each time
    for _ in range(5):
        orders, _, power = periodogram(q, left, weight, 100)
        power[np.asarray(picked, dtype=int) - 1] = -np.inf
        picked.append(int(orders[np.argmax(power)]))
        b = harmonics(q, picked)
        coef = np.linalg.solve(b.T @ (b * weight[:, None]), b.T @ projected)
        left = projected - weight * (b @ coef)
    assert pursuit(q, projected, weight, 100, 5) == picked
    assert picked[:3] == [33, 37, 34]


@pytest.mark.slow
def test_periodic_errors_that_are_no_few_sinusoids_at_two_joints_are_fitted_as_splines_together():
    # a narrow bump on joints 2 and 3 each (thirty orders at once): a spline at one joint alone leaves the
    # other's; the search combines the two joints' splines
    model = load_robot("ur10e")
    effects = [HiddenEffect("cyclic_joint_error", j, harmonics=tuple(
        (n, float(np.exp(-(n / 8.0) ** 2)), float(np.pi / 2 - n * c)) for n in range(1, 31)))
        for j, c in ((1, 0.7), (2, -1.1))]
    case = make_case(model, effects, [4.0, 4.0], n=300, seed=3)
    finding = analyze(model, case.campaign.obs, case.campaign.ctx)
    assert finding.cause == "cyclic_joint_error", finding.where
    assert finding.where.get("joints") is not None and {2, 3} <= set(finding.where["joints"]), finding.where
    knots = dict(zip(finding.where["joints"], finding.where["spline_knots"]))
    assert knots[2] and knots[3], finding.where
    q = case.campaign.obs.q
    truth = [Term("cyclic_joint_error", {"joint": e.joint + 1}, tuple(f"p{e.joint}_{i}" for i in range(60)),
                  joint_basis=JointBasis.single(harmonics(q[:, e.joint], range(1, 31)), e.joint, model.n_joints))
             for e in case.effects]
    truth_mm = heldout_with_terms(model, case.campaign.obs, truth).mean()
    assert finding.extended.heldout_mean_mm <= 1.3 * truth_mm, (finding.extended.heldout_mean_mm, truth_mm)
    errors = fitted_errors(finding.extended.terms[0], finding.extended.theta, q)
    assert {2, 3} <= {e.joint for e in errors}
    # a calibrated model made of the fit applies each joint's spline (read back from the parameter names)
    from cellcal.solvers.compensation.calibrated_model import from_fit

    calibrated = from_fit(model, case.campaign.obs.target_names, finding.extended.x, finding.extended.terms,
                          finding.extended.theta, q)
    assert sorted((p.joint, type(p).__name__) for p in calibrated.periodic) == sorted(
        (e.joint, type(e).__name__) for e in errors)
    for kept, err in zip(sorted(calibrated.periodic, key=lambda p: (p.joint, type(p).__name__)),
                         sorted(errors, key=lambda p: (p.joint, type(p).__name__))):
        assert np.allclose(kept.delta_rad(q[:, err.joint - 1]), err.delta_rad(q[:, err.joint - 1]))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_a_pose_in_a_gap_of_the_joints_angles_is_not_predicted_wild(seed):
    # a narrow periodic bump on the elbow, 300 random poses none of which puts the elbow between -80 and -50 deg,
    # and one that does: held out, the spline its fold fitted must not step wild across the gap (a spline whose
    # coefficients there rest on the tails of their basis functions did: on a measured UR10 three poses came out
    # 23 to 41 mm off, and here the lone pose worse than with no periodic model at all)
    model = load_robot("ur10e")
    rng = np.random.default_rng(seed)
    q = full_workspace(model, 600, rng)
    q = q[(q[:, 2] < np.deg2rad(-80.0)) | (q[:, 2] > np.deg2rad(-50.0))][:300]
    lone = q[0].copy()
    lone[2] = np.deg2rad(-65.0)
    q = np.vstack([q, lone])
    bump = tuple((n, float(np.exp(-(n / 8.0) ** 2)), float(np.pi / 2 - n * 0.7)) for n in range(1, 31))
    arm = _arm(model, seed, (HiddenEffect("cyclic_joint_error", 2, harmonics=bump, size=np.deg2rad(0.05)),), 1.0)
    run = arm.campaign(q)
    finding = analyze(model, run.obs, run.ctx)
    assert finding.cause == "cyclic_joint_error" and 3 in finding.where.get("joints", [finding.where.get("joint")])
    # the lone pose, held out: no worse than the rigid model there (measured 0.07-0.24 mm against 0.30-0.39;
    # with free coefficients 0.48 against 0.30 on seed 1)
    assert finding.extended.heldout_errors[-1] <= finding.baseline.heldout_errors[-1]
    truth = Term("cyclic_joint_error", {"joint": 3}, tuple(f"p{i}" for i in range(60)),
                 joint_basis=JointBasis.single(harmonics(q[:, 2], range(1, 31)), 2, model.n_joints))
    truth_mm = heldout_with_terms(model, run.obs, [truth]).mean()
    assert finding.extended.heldout_mean_mm <= 1.2 * truth_mm, (finding.extended.heldout_mean_mm, truth_mm)


def test_a_joints_spline_is_offered_where_it_gains_on_the_joints_own_problem_as_a_place_must():
    # the screen asks of a spline on its joint's own problem what the search asks of every place: the held-out
    # rms lowered by the search's GAIN, on all rows and on each fold's training rows
    assert periodic_spline.SCREEN_GAIN == selection.GAIN
    rng = np.random.default_rng(4)
    q = rng.uniform(-3.0, 3.0, 1500)
    weight = rng.uniform(0.5, 2.0, 1500)
    folds = crossval.fold_ids(q[:, None], 5, 0)
    noise = rng.normal(0.0, 3e-4, 1500)
    bump = 2e-3 * np.exp(-(np.angle(np.exp(1j * (q - 0.7))) / 0.1) ** 2)  # a worn tooth: no few sinusoids
    offered, inside = periodic_spline.screen_nested(q, weight * (bump + noise), weight, folds, 128)
    assert offered and inside == frozenset(range(5))
    # noise alone: whatever a weight's fit gains by chance is far below GAIN
    offered, inside = periodic_spline.screen_nested(q, weight * noise, weight, folds, 128)
    assert not offered and not inside
    # the counts offered: the finest the angles resolve, then a quarter as many knots each time
    assert periodic_spline.knot_counts(120) == (128, 32, 8) and periodic_spline.knot_counts(3) == ()
