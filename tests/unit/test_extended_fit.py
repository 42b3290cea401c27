"""The full fit of geometry and terms: parameter bases by their non-zero spans, constant columns solved in
closed form at each step (variable projection), the same results as the plain products and iteration."""
import sys
from pathlib import Path

import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.sims.physics.physical_arm import HiddenEffect
from cellcal.solvers.analysis.effects import CAUSES
from cellcal.solvers.analysis.extended_model import ExtendedModel, ParamBlocks, fit_extended, param_columns
from cellcal.solvers.identification.identify import IdentifyOptions, identify

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from support.hidden_cases import make_case  # noqa: E402  (tests/support/hidden_cases.py: a fixture)


def test_parameter_blocks_give_the_dense_products():
    rng = np.random.default_rng(0)
    n, p_all, m = 40, 9, 12
    basis = np.zeros((n, 3, m))  # three moved parameters, each on its own span of columns (one shared)
    basis[:, 0, 0:4] = rng.normal(size=(n, 4))
    basis[:, 1, 4:9] = rng.normal(size=(n, 5))
    basis[:, 2, 8:12] = rng.normal(size=(n, 4))
    stacked = ([2, 5, 7], basis)
    jx = rng.normal(size=(n, 3, p_all))
    theta = rng.normal(size=m)
    blocks = ParamBlocks(stacked)
    rows = slice(5, 31)
    dense = param_columns(jx[rows], ([2, 5, 7], basis[rows]))
    # the same sums in another order: equal to rounding (1e-12 of numbers of order 1)
    assert blocks.columns(jx[rows], rows, m) == pytest.approx(dense, abs=1e-12)
    assert blocks.moved(jx[rows], rows, theta) == pytest.approx(dense @ theta, abs=1e-12)


@pytest.fixture(scope="module")
def drift_case():
    model = load_robot("ur10e")
    case = make_case(model, [HiddenEffect("thermal_drift")], [5.0], n=120, seed=3)
    fit = identify(model, case.campaign.obs, IdentifyOptions(regularize="none"))
    term = CAUSES["thermal_drift"].terms(model, fit.layout, fit.x, case.campaign.obs, case.campaign.ctx)[0]
    return model, case, fit, term


def test_a_constant_column_solved_at_each_step_reaches_the_joint_fits_optimum(drift_case, monkeypatch):
    model, case, fit, term = drift_case
    obs = case.campaign.obs
    assert ExtendedModel(fit.layout, obs, fit.x, fit.free, (term,)).constant_columns().all()
    projected = fit_extended(fit.layout, obs, fit.x, fit.free, (term,), 1.0)
    monkeypatch.setattr(ExtendedModel, "constant_columns", lambda self: np.zeros(self.n_theta, bool))
    joint = fit_extended(fit.layout, obs, fit.x, fit.free, (term,), 1.0)
    cost = [float(np.sum(f.residuals_mm**2)) for f in (projected, joint)]
    # the same minimum: the projected fit stops when a step gains less than 1e-6 of the cost, the joint one
    # at 1e-10; what is left to gain then is a few such steps
    assert cost[0] == pytest.approx(cost[1], rel=1e-5)
    # the expansion coefficient alike, to far below its own spread (the effect is 5x the noise: ~20%)
    assert projected.theta[0] == pytest.approx(joint.theta[0], rel=1e-3)
    assert projected.nfev < joint.nfev or projected.nfev <= 10  # no slower than the joint fit
