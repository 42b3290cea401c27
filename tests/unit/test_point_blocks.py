"""The point form's least squares by blocks (solvers/fixtures/point_blocks.py) against the dense Jacobian
(``PointProblem.evaluate``) on small campaigns: sockets, stylus contacts, and sockets with measured
positions beside them (the instrument frame shared by every row).

Every quantity compared is an exact identity in exact arithmetic (the normal equations, their damped
solve, (J^T J)^-1, R^T R = J^T J); the two ways of computing it differ by rounding alone. A linear solve
with a matrix of condition number kappa is accurate to about kappa * eps relative, so each tolerance is a
small multiple of that, kappa taken from the scaled problem itself.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from support.point_data import plate_placements, seat  # tests/support/point_data.py

from cellcal.config.robot_files import load_robot
from cellcal.sims.physics.kinematic_arm import SimulatedArm
from cellcal.solvers.estimation import crossval, identifiability
from cellcal.solvers.fixtures.point_problem import FixtureOptions, PointData, PointProblem, _frames
from cellcal.solvers.geometry import se3

UR10E = load_robot("ur10e")
EPS = np.finfo(float).eps
SLACK = 100.0  # rounding of a few hundred accumulated products each step, over the kappa * eps of one solve


def _campaign(kind: str, seed: int = 2) -> tuple[PointData, FixtureOptions]:
    """Three placements of a 200 mm bar, 6 seats per socket (sockets or 4 mm balls, 10 contacts each);
    'positions': sockets with 12 tracker positions besides."""
    rng = np.random.default_rng(seed)
    arm = SimulatedArm(UR10E, rng, repeatability_mm=0.03, target_offsets=[[0.0, 0.0, 100.0]])
    radius = 4.0 if kind == "contacts" else None
    plate = seat(arm, plate_placements(rng, 3), 10 if radius else 6, rng, max_tilt_deg=45.0,
                 wrists=("normal", "flipped"), spacing_mm=200.0, stylus_radius_mm=radius)
    keys = list(dict.fromkeys(zip(plate.setup, plate.point)))
    point = np.array([keys.index(k) for k in zip(plate.setup, plate.point)])
    q, xyz = plate.q, np.full((len(plate.q), 3), np.nan)
    if kind == "positions":
        extra = plate.q[rng.choice(len(plate.q), 12, replace=False)] + rng.normal(scale=0.3, size=(12, 6))
        q = np.vstack([q, extra])
        xyz = np.vstack([xyz, arm.measure(extra).xyz_mm])
        point = np.r_[point, np.full(12, -1)]
    distances = tuple((keys.index((s, "hole_0")), keys.index((s, "hole_1")), 200.0, 0.01)
                      for s in dict.fromkeys(plate.setup))
    data = PointData(q, np.zeros(len(q), int), ("tcp",), point, tuple(keys), xyz, distances)
    return data, FixtureOptions(seating_sd_mm=0.03, stylus_radius_mm=radius)


@pytest.fixture(scope="module", params=["sockets", "contacts", "positions"])
def problem(request):
    data, options = _campaign(request.param)
    prob = PointProblem(UR10E, data, options, with_base=bool((~data.is_point).any()))
    z = prob.start()
    z[: prob.u.n_kin] += np.random.default_rng(1).normal(scale=1e-3, size=prob.u.n_kin)  # off the minimum
    return prob, z


def _free(prob):
    """Every unknown but two kinematic parameters the data cannot see (the first joint's zero and height),
    and one point coordinate held: a mask with holes in both parts."""
    free = np.ones(prob.u.size, bool)
    free[[0, 1]] = False
    free[prob.u.point(1).start + 2] = False
    return free


def test_the_blocks_give_the_dense_normal_equations(problem):
    prob, z = problem
    free = _free(prob)
    res, jac = prob.evaluate(z)
    j = jac[:, free]
    system = prob.system(z, free)
    scale = prob.scale()[free]
    js = j * scale  # one unit of each column moves a target about 1 mm: the problem's own units
    kappa = np.linalg.cond(js)
    size = np.linalg.norm(js, axis=0)
    assert system.cost == pytest.approx(0.5 * res @ res, rel=1e-12)
    # J^T r and J^T J s: sums of products, exact but for rounding relative to the columns' size
    np.testing.assert_allclose(system.g * scale, js.T @ res, rtol=0, atol=SLACK * EPS * size.max() * np.abs(res).sum())
    np.testing.assert_allclose(system.diagonal(), np.sum(j * j, axis=0), rtol=SLACK * EPS)
    s = np.random.default_rng(3).normal(size=len(scale))  # a step in the scaled unknowns
    want = js.T @ (js @ s)
    np.testing.assert_allclose(system.product(s * scale) * scale, want, rtol=0,
                               atol=SLACK * EPS * kappa * np.linalg.norm(want))
    # the damped step, the points eliminated, against the dense solve of the same damped system
    d = 1.0 / scale
    for mu in (1e-3, 1e-9):
        a = js.T @ js + mu * np.eye(len(scale))
        dense = -np.linalg.solve(a, js.T @ res)
        step = system.damped_step(mu, d) * d  # in the scaled unknowns
        np.testing.assert_allclose(step, dense, rtol=0, atol=SLACK * EPS * np.linalg.cond(a) * np.abs(dense).max())


def test_the_blocks_give_the_covariance_and_the_r_factor(problem):
    prob, z = problem
    free = _free(prob)
    res, jac = prob.evaluate(z)
    scale = prob.scale()[free]
    js = jac[:, free] * scale
    system = prob.system(z, free)
    dense = np.linalg.inv(js.T @ js)
    kappa2 = np.linalg.cond(js) ** 2  # of J^T J
    cov = system.covariance() / np.outer(scale, scale)
    np.testing.assert_allclose(cov, dense, rtol=0, atol=SLACK * EPS * kappa2 * np.abs(dense).max())
    # R^T R = J^T J, and with the residual's column R^T c = J^T r, c^T c = r^T r
    r = system.r_factor(with_residual=True)
    rs = r[:, :-1] * scale
    gram = js.T @ js
    np.testing.assert_allclose(rs.T @ rs, gram, rtol=0, atol=SLACK * EPS * np.abs(gram).max())
    np.testing.assert_allclose(rs.T @ r[:, -1], js.T @ res, rtol=0,
                               atol=SLACK * EPS * np.linalg.norm(js, axis=0).max() * np.linalg.norm(res))
    assert r[:, -1] @ r[:, -1] <= res @ res * (1 + SLACK * EPS)
    # the same singular values: what the rank analyses and the condition number read
    np.testing.assert_allclose(np.linalg.svd(rs, compute_uv=False), np.linalg.svd(js, compute_uv=False), rtol=0,
                               atol=SLACK * EPS * kappa2 * np.linalg.norm(js, 2))


def test_the_fit_by_blocks_reaches_the_dense_least_squares_minimum(problem):
    """``PointProblem.fit`` (Levenberg-Marquardt, points eliminated) against scipy's MINPACK on the dense
    Jacobian, both to ftol = xtol = gtol = 1e-12. Both stop within a relative 1e-12 of the minimum's cost
    0.5 s^2 dof; a step of delta standard deviations off the minimum raises that cost by 0.5 delta^2 s^2,
    so each estimate is within sqrt(2 * 1e-12 * dof) of its standard deviation of the minimum, and the two
    within twice that."""
    prob, z = problem
    nuisance = np.arange(prob.u.size) >= prob.u.n_kin
    res, jac = prob.evaluate(z)
    # the kinematic parameters the data determine above the seating noise, as identify_points chooses them
    free = identifiability.analyse(jac * prob.scale(), nuisance, ~nuisance, noise_mm=0.03).keep
    # theta1 turns the arm about the first joint's axis, which the points (and the instrument frame) follow
    # exactly: a direction no data see, which rounding may leave above the rank threshold (identify_points
    # then holds it by its trust bounds); the two solvers would stop anywhere along it
    free[UR10E.index("theta1")] = False
    idx = np.flatnonzero(free)
    tol = 1e-12
    mine, _ = prob.fit(z, free, tol)

    def full(v):
        out = z.copy()
        out[idx] = v
        return out

    ref = least_squares(lambda v: prob.evaluate(full(v), with_jac=False), z[idx],
                        jac=lambda v: prob.evaluate(full(v))[1][:, idx], method="lm", x_scale=prob.scale()[idx],
                        ftol=tol, xtol=tol, gtol=tol)
    dense = full(ref.x)
    res, jac = prob.evaluate(dense)
    dof = prob.n_res - len(idx)
    s2 = res @ res / dof
    std = np.sqrt(np.diag(np.linalg.inv(jac[:, idx].T @ jac[:, idx])) * s2)
    bound = 2 * np.sqrt(2 * tol * dof)
    assert np.max(np.abs(mine[idx] - dense[idx]) / std) <= bound
    assert 0.5 * prob.evaluate(mine, with_jac=False) @ prob.evaluate(mine, with_jac=False) <= 0.5 * res @ res * (1 + 1e-9)


def test_the_start_by_blocks_is_the_dense_linear_least_squares():
    """The targets and points of ``PointProblem.start``: the pivot calibration's linear least squares, here
    solved on its block R factor, against the dense lstsq of the same rows (condition of that system)."""
    data, options = _campaign("positions")
    prob = PointProblem(UR10E, data, options, with_base=True)
    z = prob.start(fixed_points={0: np.array([600.0, 0.0, 100.0])})
    u = prob.u
    x = prob.layout.initial()
    x[: u.n_kin] = UR10E.nominal
    rot, org = _frames(UR10E, prob.layout, x, data, np.arange(len(data)))
    rot_b = se3.rotvec_to_matrix(z[u.base][3:])
    a = np.zeros((3 * len(data), 3 + 3 * (u.n_points - 1)))
    b = np.zeros(3 * len(data))
    for i in range(len(data)):
        a[3 * i: 3 * i + 3, :3] = rot[i]
        p = data.point[i]
        if p > 0:
            a[3 * i: 3 * i + 3, 3 * p: 3 * p + 3] = -np.eye(3)
        goal = -org[i] if p >= 0 else (data.xyz_mm[i] - z[u.base][:3]) @ rot_b - org[i]
        b[3 * i: 3 * i + 3] = goal + (np.array([600.0, 0.0, 100.0]) if p == 0 else 0.0)
    sol = np.linalg.lstsq(a, b, rcond=None)[0]
    tol = SLACK * EPS * np.linalg.cond(a) * np.abs(sol).max()
    np.testing.assert_allclose(z[u.target(0)], sol[:3], rtol=0, atol=tol)
    np.testing.assert_allclose(z[u.points_slice][3:], sol[3:], rtol=0, atol=tol)
    np.testing.assert_array_equal(z[u.point(0)], [600.0, 0.0, 100.0])


# -- the analysis' folds: crossval.PointFoldFactors against the points as columns of their own ---------------


def _fold_problem(path: bool):
    """90 rows of a random linearised model (4 columns) at 9 points, 3 folds: with sub-folds, or path-ordered
    with gaps (rows each fold's training also leaves out). Point 8 lies in fold 0 alone (no training row in
    that fold: it must stay where it is); the rows of points 6 and 7 are contacts (one direction measured)."""
    rng = np.random.default_rng(4)
    n, p, n_points = 90, 4, 9
    point = np.arange(n) % 8
    fold = rng.integers(0, 3, n)
    where = np.flatnonzero(fold == 0)[:6]
    point[where] = 8
    j = rng.normal(size=(n, 3, p))
    r = rng.normal(size=(n, 3)) * 0.1
    pj = -np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    contact = np.isin(point, (6, 7))
    proj = normal[:, :, None] * normal[:, None, :]
    j[contact] = proj[contact] @ j[contact]
    r[contact] = np.einsum("nij,nj->ni", proj[contact], r[contact])
    pj[contact] = -proj[contact]
    ids = fold.view(crossval.FoldIds)
    if path:
        ids.exclude = tuple(np.flatnonzero((fold != k) & (rng.random(n) < 0.15)) for k in range(3))
    else:
        ids.sub = rng.integers(0, 2, n)
    return ids, j, r, pj, point, n_points


def _held_out_sse(train, held) -> float:
    """The held-out sum of squares of one training over point columns, with the columns of a point no
    training row measures left at zero (the point stays where it is, as the eliminated form has it). The
    dense Gram of a training is a difference of Grams: such columns are not zero but rounding residue, and
    solving for them gives whatever the residue says, differently on every BLAS kernel."""
    a, b = train[:-1, :-1], train[:-1, -1]
    seen = np.abs(np.diag(a)) > 1e-9 * np.abs(np.diag(a)).max()  # a measured column's is of order 1
    w = np.zeros(len(b) + 1)
    w[:-1][seen] = -np.linalg.lstsq(a[np.ix_(seen, seen)], b[seen], rcond=None)[0]
    w[-1] = 1.0
    return float(w @ held @ w)


@pytest.mark.parametrize("path", [False, True])
def test_the_points_eliminated_in_every_fold_give_the_steps_and_errors_of_point_columns(path):
    """Against ``FoldFactors`` over [J | P] (each point's three columns as columns): the model's steps,
    the held-out errors, the inner folds' sums of squares, the R factor of all rows. Each is one solve of
    the training's normal equations, so each agrees to a small multiple of kappa * eps of those."""
    folds, j, r, pj, point, n_points = _fold_problem(path)
    n, p = len(r), j.shape[2]
    columns = np.zeros((n, 3, 3 * n_points))
    for c in range(3):
        columns[np.arange(n), :, 3 * point + c] = pj[:, :, c]
    dense = crossval.FoldFactors(folds, p + 3 * n_points)
    dense.add(slice(None), np.concatenate([j, columns], axis=2), r)
    mine = crossval.PointFoldFactors(folds, p, point, n_points)
    mine.add(slice(None), j, r, pj)
    mine.add_projected(slice(None), j, r, pj)
    kappa = max(np.linalg.cond(dense.training(k)[0][np.ix_(keep, keep)])
                for k in range(3) for keep in [np.linalg.norm(dense.training(k)[0], axis=0) > 0])
    tol = SLACK * EPS * kappa
    steps_dense = dense.steps(np.arange(p + 3 * n_points))
    steps = mine.steps(np.arange(p))
    np.testing.assert_allclose(steps[0], steps_dense[0, :, :p], rtol=0, atol=tol * np.abs(steps_dense).max())
    errors_dense = crossval.heldout_errors([(slice(None), np.concatenate([j, columns], axis=2))], r, dense,
                                           steps_dense)
    errors = mine.heldout_errors([(slice(None), j, pj)], r, steps)
    np.testing.assert_allclose(errors, errors_dense, rtol=0, atol=tol * errors_dense.max())
    for k in range(3):  # every inner fold's held-out sum of squares: the nested selections' scores
        assert mine.inner_sse(k) == pytest.approx(sum(_held_out_sse(t, h) for t, h in dense.inner(k)), rel=tol)
    for (t, h), (td, hd) in zip(mine.outer(), dense.outer()):  # the outer folds, as the selection scores them
        w = np.append(-np.linalg.lstsq(t[:p, :p], t[:p, p], rcond=None)[0], 1.0)
        assert w @ h @ w == pytest.approx(_held_out_sse(td, hd), rel=tol)
    # R of all rows with the points projected out: R^T R is the Schur complement of the points' block
    full = dense.r_all()
    gram = full.T @ full
    keep = np.r_[np.arange(p), p + 3 * n_points]
    pts = np.arange(p, p + 3 * n_points)
    schur = gram[np.ix_(keep, keep)] - gram[np.ix_(keep, pts)] @ np.linalg.pinv(gram[np.ix_(pts, pts)]) @ \
        gram[np.ix_(pts, keep)]
    r_all = mine.r_all()
    np.testing.assert_allclose(r_all.T @ r_all, schur, rtol=0, atol=tol * np.abs(gram).max())
