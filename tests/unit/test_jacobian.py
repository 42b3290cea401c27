"""The analytic Jacobian of the measurement model against central finite differences.

Checked: d p / d x for every unknown (kinematic parameters, base translation and
rotation vector, per-target offsets) and, with ``with_joints``, d p / d q, for a
classic DH arm, an MDH arm with Hayati betas, and an arm with Fanuc J2/J3 coupling;
always with a base rotation of norm ~2 rad, non-zero base translation, perturbed
(non-nominal) kinematic parameters and two targets with different offsets.

Tolerance, per column k of the Jacobian (all N x 3 entries of d p / d x_k):
    max |J_analytic - J_fd| <= 1e-6 * ||J_fd[:, :, k]||_F   (plus 1e-9 mm absolute floor)
Central differences with step 1e-5 (mm for lengths, rad for angles): truncation error
~h^2 |p'''| / 6 ~ 1e-7 mm at 2 m lever arms and rounding ~eps |p| / h ~ 1e-7 mm, both far
below the bound for every column (column norms are >= ~1).
"""
import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.solvers.geometry.chain import forward
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian, predict
from cellcal.config.robot_files import model_from_mapping

REL_TOL = 1e-6
ABS_FLOOR_MM = 1e-9
STEP = 1e-5

FANUC_LIKE = {
    "name": "coupled-test-arm",
    "convention": "dh",
    "length_unit": "mm",
    "angle_unit": "deg",
    "joint_coupling": "fanuc_j2_j3",
    "joints": [
        {"a": 150, "alpha": -90, "d": 450, "theta": 0},
        {"a": 600, "alpha": 0, "d": 0, "theta": -90},
        {"a": 200, "alpha": -90, "d": 0, "theta": 0},
        {"a": 0, "alpha": 90, "d": 640, "theta": 0},
        {"a": 0, "alpha": -90, "d": 0, "theta": 0},
        {"a": 0, "alpha": 0, "d": 100, "theta": 0},
    ],
}


def coupled_model():
    return model_from_mapping(FANUC_LIKE, source="<fanuc-like>")


MODELS = {
    "dh-ur5e": lambda: load_robot("ur5e"),
    "mdh-beta-epson": lambda: load_robot("epson-c4-a901s"),
    "dh-fanuc_j2_j3": coupled_model,
}


def perturbed(model, rng):
    """Nominal parameters moved off their special values (0, +/-90 deg) so no term vanishes by accident."""
    noise = np.where(model.param_is_angle, rng.normal(0, 0.02, model.n_params), rng.normal(0, 2.0, model.n_params))
    return model.nominal + noise


def setup(model_key, seed=0, n=40, target_names=("a", "b")):
    rng = np.random.default_rng(seed)
    model = MODELS[model_key]()
    layout = Layout(model, tuple(target_names))
    axis = np.array([0.3, -0.5, 0.8])
    base = np.concatenate([[1500.0, -300.0, 250.0], 2.0 * axis / np.linalg.norm(axis)])
    offsets = np.array([[30.0, -20.0, 150.0], [-50.0, 40.0, 80.0]])[: len(target_names)]
    x = layout.initial(base=base, offsets=offsets)
    x[: layout.n_kin] = perturbed(model, rng)
    q = rng.uniform(-np.pi, np.pi, (n, model.n_joints))
    target = np.arange(n) % len(target_names)
    obs = Observations(q=q, xyz_mm=np.zeros((n, 3)), target=target, target_names=tuple(target_names))
    return model, layout, x, obs


def fd_wrt_x(layout, x, obs):
    out = np.zeros((len(obs), 3, layout.size))
    for k in range(layout.size):
        xp, xm = x.copy(), x.copy()
        xp[k] += STEP
        xm[k] -= STEP
        out[:, :, k] = (predict(layout, xp, obs) - predict(layout, xm, obs)) / (2 * STEP)
    return out


def fd_wrt_q(layout, x, obs):
    nj = layout.model.n_joints
    out = np.zeros((len(obs), 3, nj))
    for j in range(nj):
        qp, qm = obs.q.copy(), obs.q.copy()
        qp[:, j] += STEP
        qm[:, j] -= STEP
        op = Observations(qp, obs.xyz_mm, obs.target, obs.target_names)
        om = Observations(qm, obs.xyz_mm, obs.target, obs.target_names)
        out[:, :, j] = (predict(layout, x, op) - predict(layout, x, om)) / (2 * STEP)
    return out


def assert_columns_close(analytic, numeric, names):
    assert analytic.shape == numeric.shape
    for k, name in enumerate(names):
        norm = np.linalg.norm(numeric[:, :, k])
        err = np.abs(analytic[:, :, k] - numeric[:, :, k]).max()
        assert err <= REL_TOL * norm + ABS_FLOOR_MM, (
            f"column {name}: max error {err:.3e} vs column norm {norm:.3e}")


@pytest.mark.parametrize("model_key", sorted(MODELS))
def test_jacobian_wrt_unknowns_matches_central_differences(model_key):
    model, layout, x, obs = setup(model_key)
    p, jac = jacobian(layout, x, obs)
    np.testing.assert_allclose(p, predict(layout, x, obs), rtol=0, atol=1e-9)
    assert jac.shape == (len(obs), 3, layout.size)
    assert_columns_close(jac, fd_wrt_x(layout, x, obs), layout.names)


@pytest.mark.parametrize("model_key", sorted(MODELS))
def test_jacobian_wrt_joints_matches_central_differences(model_key):
    model, layout, x, obs = setup(model_key, seed=1)
    p, jac, jq = jacobian(layout, x, obs, with_joints=True)
    np.testing.assert_allclose(p, predict(layout, x, obs), rtol=0, atol=1e-9)
    _, jac_plain = jacobian(layout, x, obs)
    np.testing.assert_array_equal(jac, jac_plain)
    assert jq.shape == (len(obs), 3, model.n_joints)
    assert_columns_close(jq, fd_wrt_q(layout, x, obs), [f"q{j + 1}" for j in range(model.n_joints)])


def test_target_offset_columns_belong_to_their_own_target_only():
    """Rows measured on target "a" have zero derivative w.r.t. target "b"'s offset, and vice versa."""
    _, layout, x, obs = setup("dh-ur5e", seed=2)
    _, jac = jacobian(layout, x, obs)
    for i in range(2):
        other = obs.target != i
        assert np.all(jac[other][:, :, layout.target(i)] == 0.0)
        own = jac[obs.target == i][:, :, layout.target(i)]
        # d p / d offset is the rotation instrument <- end frame: orthonormal, det +1
        np.testing.assert_allclose(own @ np.swapaxes(own, 1, 2), np.broadcast_to(np.eye(3), own.shape), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(own), 1.0, atol=1e-12)


def test_single_target_default_name():
    """One target under the default name ("tcp"): same check as above, with all rows on target 0."""
    model, layout, x, obs = setup("mdh-beta-epson", seed=3, target_names=("tcp",))
    assert layout.size == model.n_params + 6 + 3
    _, jac = jacobian(layout, x, obs)
    assert_columns_close(jac, fd_wrt_x(layout, x, obs), layout.names)


def test_coupling_enters_the_joint_jacobian():
    """With fanuc_j2_j3, reported q2 moves both the upper arm and the forearm: d p/d q2 (coupled) equals
    d p/d q2 + d p/d q3 of the same arm uncoupled, at the uncoupled joint values (q3 + q2)."""
    model, layout, x, obs = setup("dh-fanuc_j2_j3", seed=4)
    plain = model_from_mapping({**FANUC_LIKE, "joint_coupling": "none"}, source="<plain>")
    plain_layout = Layout(plain, layout.target_names)
    q_plain = obs.q.copy()
    q_plain[:, 2] += obs.q[:, 1]
    plain_obs = Observations(q_plain, obs.xyz_mm, obs.target, obs.target_names)
    p_c, _, jq_c = jacobian(layout, x, obs, with_joints=True)
    p_u, _, jq_u = jacobian(plain_layout, x, plain_obs, with_joints=True)
    np.testing.assert_allclose(p_c, p_u, rtol=0, atol=1e-9)
    np.testing.assert_allclose(jq_c[:, :, 1], jq_u[:, :, 1] + jq_u[:, :, 2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(jq_c[:, :, [0, 2, 3, 4, 5]], jq_u[:, :, [0, 2, 3, 4, 5]], rtol=0, atol=1e-9)


# --- forward kinematics over a population of parameter sets ----------------------------

@pytest.mark.parametrize("model_key", sorted(MODELS))
def test_batched_parameter_sets_equal_separate_calls(model_key):
    """forward(chain, params (M, P), q (N, n)) returns (M, N, 3, 3), (M, N, 3), each slice equal to a
    separate call with params[m] (to 1e-12 in rotation entries and 1e-9 mm in position)."""
    rng = np.random.default_rng(5)
    model = MODELS[model_key]()
    chain = model.chains["flange"]
    m = 7
    params = np.stack([perturbed(model, rng) for _ in range(m)])
    q = rng.uniform(-np.pi, np.pi, (11, model.n_joints))
    rot, org = forward(chain, params, q)
    assert rot.shape == (m, len(q), 3, 3)
    assert org.shape == (m, len(q), 3)
    for i in range(m):
        r_i, o_i = forward(chain, params[i], q)
        np.testing.assert_allclose(rot[i], r_i, rtol=0, atol=1e-12)
        np.testing.assert_allclose(org[i], o_i, rtol=0, atol=1e-9)
    # the population members really differ (the check above is not vacuous)
    assert np.abs(org[0] - org[1]).max() > 1.0


def test_batched_parameter_sets_single_pose():
    """A single pose (q of shape (n,)) with M parameter sets gives (M, 1, ...) results."""
    rng = np.random.default_rng(6)
    model = MODELS["mdh-beta-epson"]()
    params = np.stack([perturbed(model, rng) for _ in range(4)])
    q = rng.uniform(-np.pi, np.pi, model.n_joints)
    rot, org = forward(model.chains["flange"], params, q)
    assert rot.shape == (4, 1, 3, 3) and org.shape == (4, 1, 3)
    for i in range(4):
        r_i, o_i = forward(model.chains["flange"], params[i], q)
        np.testing.assert_allclose(org[i], o_i, rtol=0, atol=1e-9)
        np.testing.assert_allclose(rot[i], r_i, rtol=0, atol=1e-12)
