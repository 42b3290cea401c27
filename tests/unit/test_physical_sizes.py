"""Physical sizes: a joint's deflection and stiffness only where the data determine them."""
import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.sims.physics.physical_arm import HiddenEffect
from cellcal.solvers.analysis.analyze import AnalyzeOptions, _fit_in_full, analyze
from cellcal.solvers.analysis.effects import CAUSES
from cellcal.solvers.analysis.physical_sizes import DETERMINED_SIGMAS, place_sizes
from support.hidden_cases import make_case


@pytest.fixture(scope="module")
def two_joint_compliance():
    """UR10e (link masses in its file): compliance hidden at the shoulder and the elbow."""
    model = load_robot("ur10e")
    case = make_case(model, [HiddenEffect("joint_compliance", 1), HiddenEffect("joint_compliance", 2)],
                     [5.0, 5.0], n=300, seed=0)
    return case, analyze(model, case.campaign.obs, case.campaign.ctx, AnalyzeOptions(causes=("joint_compliance",)))


def test_determined_stiffnesses_match_the_hidden_ones(two_joint_compliance):
    case, finding = two_joint_compliance
    places = {tuple(e["places"]): e for e in finding.magnitude["places"]}
    for effect in case.effects:
        entry = places[(f"joint{effect.joint + 1}",)]
        assert entry["kind"] == "determined"
        true_stiffness = 1.0 / effect.size
        assert entry["stiffness_Nm_per_rad"] == pytest.approx(true_stiffness, rel=0.03)
        # the stated error is honest: the truth lies within 4 of them
        assert abs(entry["stiffness_Nm_per_rad"] - true_stiffness) < 4 * entry["stiffness_standard_error_Nm_per_rad"]
        true_std_deg = np.rad2deg(np.std(case.campaign.true_joint_delta[:, effect.joint]))
        assert entry["deflection_std_deg"] == pytest.approx(true_std_deg, rel=0.03)


def every_joint_fitted(case, finding):
    """Compliance at every joint fitted to the same data (the analysis names only the joints its forward
    search chose): the sizes of the places the data show no deflection at."""
    model, scorer = load_robot("ur10e"), finding.scorer
    fit, obs = scorer.geometric_fit, case.campaign.obs
    compliance = CAUSES["joint_compliance"]
    every = compliance.combine(tuple(compliance.terms(model, fit.layout, fit.x, obs, case.campaign.ctx)), len(obs),
                               model.n_joints)
    return _fit_in_full(model, fit, obs, scorer.folds, (every,), 1.0, every.label(), scorer.robust)


def test_joints_without_compliance_get_no_stiffness_only_a_bound(two_joint_compliance):
    case, finding = two_joint_compliance
    finding = every_joint_fitted(case, finding)
    hidden = {f"joint{e.joint + 1}" for e in case.effects}
    others = [e for e in finding.magnitude["places"] if e["places"][0] not in hidden]
    assert others, "the multi-joint term covers more than the two hidden joints"
    for e in others:
        assert e["kind"] != "determined" and "stiffness_Nm_per_rad" not in e
        assert e["below_deg"] < 0.02 and e["stiffness_above_Nm_per_rad"] > 1e3
    assert not any(k.startswith(e["places"][0]) for e in others for k in finding.magnitude if k != "places")


def test_places_that_trade_are_grouped_and_the_group_is_right():
    """Three places; two of them move the measurement almost the same way (parallel axes
    through nearly the same point): each alone is undetermined, their sum is not."""
    rng = np.random.default_rng(3)
    n = 400
    d = rng.normal(size=(n, 3))  # each place's deflection over the poses (rad per unit theta)
    places = [("a", np.c_[d[:, 0], 0 * d[:, 0], 0 * d[:, 0]]), ("b", np.c_[0 * d[:, 0], d[:, 0], 0 * d[:, 0]]),
              ("c", np.c_[0 * d[:, 0], 0 * d[:, 0], d[:, 2]])]
    lever = rng.normal(size=(n, 3, 3)) * 500.0  # mm per rad at each pose
    lever[:, :, 1] = lever[:, :, 0] * 1.001 + rng.normal(size=(n, 3)) * 0.2  # b moves the target as a does
    theta_true = np.array([2e-3, 1e-3, 1.5e-3])
    j = np.stack([lever[:, :, i] * places[i][1][:, i, None] for i in range(3)], axis=2).reshape(-1, 3)
    y = j @ theta_true + rng.normal(size=3 * n) * 0.05
    theta = np.linalg.lstsq(j, y, rcond=None)[0]
    sigma = np.sqrt(np.sum((y - j @ theta) ** 2) / (3 * n - 3))
    cov_root = sigma * np.linalg.inv(np.linalg.qr(j, mode="r"))
    entries, flat = place_sizes(places, theta, cov_root)
    kinds = {tuple(e["places"]): e for e in entries}
    c = kinds[("c",)]
    assert c["kind"] == "determined"
    assert np.deg2rad(c["deflection_std_deg"]) == pytest.approx(theta_true[2] * np.std(d[:, 2]), rel=0.02)
    group = kinds[("a", "b")]
    assert group["kind"] == "group" and group["max_abs_r"] > 0.9
    assert np.deg2rad(group["deflection_std_deg"]) == pytest.approx(theta_true[:2].sum() * np.std(d[:, 0]), rel=0.02)
    assert group["deflection_std_deg"] >= DETERMINED_SIGMAS * group["standard_error_deg"]
    assert "a+b_deflection_std_deg" in flat and "a_deflection_std_deg" not in flat


def test_mount_columns_are_the_whole_robot_turned_about_a_horizontal_axis():
    """A tree on an elastic mount: each column is the targets' motion when the robot turns about a
    horizontal axis through its base, scaled by a link point's gravity moment about that axis."""
    from cellcal.solvers.geometry import se3
    from cellcal.solvers.analysis.effects.elastic_mount import horizontal_axes, mount_columns
    from cellcal.solvers.geometry.gravity import tree_sites
    from cellcal.solvers.identification.measurement_model import Layout, Observations, predict

    model = load_robot("agile-justin")
    layout = Layout(model, ("right", "left"))
    x = layout.initial()
    x[layout.base] = [100.0, -50.0, 20.0, 0.1, -0.2, 0.3]
    q = np.random.default_rng(0).uniform(-1, 1, (6, model.n_joints))
    obs = Observations(np.repeat(q, 2, axis=0), np.zeros((12, 3)), np.tile([0, 1], 6), ("right", "left"))
    points = {}
    for site in tree_sites(model, x[: layout.n_kin], obs.q):
        points.update(zip(site["point_keys"], site["points"]))
    cols, names, places = mount_columns(model, layout, x, obs, list(points.values()))
    assert cols.shape == (12, 3, len(names)) and set(places) == {"mount.tilt1", "mount.tilt2"}
    axes = horizontal_axes(model.gravity)
    assert np.abs(axes @ model.gravity).max() < 1e-12 and np.allclose(axes @ axes.T, np.eye(2))
    for a, label in enumerate(("mount.tilt1", "mount.tilt2")):
        k = int(np.flatnonzero(np.any(places[label] != 0, axis=0))[0])
        moment = places[label][:, k]
        tilted = x.copy()  # the robot turned by a small angle about the axis, in its own base frame
        rot = se3.rotvec_to_matrix(x[layout.base][3:]) @ se3.rotvec_to_matrix(1e-6 * axes[a])
        tilted[layout.base.start + 3: layout.base.stop] = se3.matrix_to_rotvec(rot)
        moved = (predict(layout, tilted, obs) - predict(layout, x, obs)) / 1e-6
        assert cols[:, :, k] == pytest.approx(moved * moment[:, None], rel=1e-4, abs=1e-6)
