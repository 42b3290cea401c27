"""The rigid model extended with linear effect terms, and its joint fit.

A term (``effects.Term``) adds a joint-space, a Cartesian or a parameter-space
displacement linear in its own parameters theta; here several terms are stacked into
one basis, and geometry (the free entries of the identification's x) and theta are
fitted together by nonlinear least squares. Term parameters the data cannot separate
from the geometry are held at 0 (the identifiability rule of ``identify``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.linalg import solve_triangular

from cellcal.solvers.estimation import identifiability, lsq
from cellcal.solvers.analysis.effects import JointBasis, Term
from cellcal.solvers.analysis.effects.base import part_penalty, penalised_parts
from cellcal.solvers.estimation.fit_result import FitResult, from_solver
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian, predict


class TermBases(NamedTuple):
    """Several terms' bases side by side, one column per term parameter (m in all)."""

    joint: JointBasis  # (N, nj, m)
    cartesian: np.ndarray | None  # (N, 3, m), None without Cartesian terms
    param: tuple | None  # (kinematic parameter indices, (N, P, m)), or None without parameter-space terms

    def rows(self, rows) -> "TermBases":
        return TermBases(self.joint[rows], None if self.cartesian is None else self.cartesian[rows],
                         None if self.param is None else (self.param[0], self.param[1][rows]))


def combine_bases(terms: tuple[Term, ...], n_rows: int, n_joints: int) -> TermBases:
    m = sum(t.size for t in terms)
    joint = JointBasis.side_by_side([(t.joint_basis, t.size) for t in terms], n_rows, n_joints)
    cartesian = np.zeros((n_rows, 3, m)) if any(t.cart_basis is not None for t in terms) else None
    param: dict[int, np.ndarray] = {}
    col = 0
    for t in terms:
        if t.cart_basis is not None:
            cartesian[:, :, col: col + t.size] = t.cart_basis
        for p, basis in (t.param_basis or {}).items():
            param.setdefault(p, np.zeros((n_rows, m)))[:, col: col + t.size] += basis
        col += t.size
    return TermBases(joint, cartesian, stack_param_bases(param) if param else None)


def stack_param_bases(param_bases: dict):
    """Parameter bases as (parameter indices, (N, P, m)) for one matrix product."""
    params = list(param_bases)
    return params, np.stack([param_bases[p] for p in params], axis=1)


def param_columns(jacobian_x: np.ndarray, stacked) -> np.ndarray:
    """d p / d theta of parameter-space terms: sum_p (d p / d k_p) * basis_p."""
    params, basis = stacked
    return np.matmul(jacobian_x[:, :, params], basis)


class ParamBlocks:
    """Parameter bases kept as their non-zero column span per parameter: a term of many places (every
    axis of a tree, a few columns each) then costs what its non-zero entries cost, not a product over
    every column of every parameter."""

    def __init__(self, stacked):
        params, basis = stacked
        self.blocks = []  # (parameter index, column slice, (N, width) basis)
        for i, p in enumerate(params):
            cols = np.flatnonzero(np.any(basis[:, i, :] != 0, axis=0))
            if len(cols):
                span = slice(int(cols[0]), int(cols[-1]) + 1)
                self.blocks.append((p, span, np.ascontiguousarray(basis[:, i, span])))

    def columns(self, jacobian_x: np.ndarray, rows, m: int) -> np.ndarray:
        """``param_columns`` of the rows (n, 3, m)."""
        out = np.zeros(jacobian_x.shape[:2] + (m,))
        for p, span, b in self.blocks:
            out[:, :, span] += jacobian_x[:, :, p, None] * b[rows, None, :]
        return out

    def moved(self, jacobian_x: np.ndarray, rows, theta: np.ndarray) -> np.ndarray:
        """``param_columns(...) @ theta`` of the rows (n, 3): each parameter moved by its basis @ theta."""
        out = np.zeros(jacobian_x.shape[:2])
        for p, span, b in self.blocks:
            out += jacobian_x[:, :, p] * (b[rows] @ theta[span])[:, None]
        return out


def norm_scale(norms: np.ndarray, n_rows: int) -> np.ndarray:
    """RMS target displacement (mm) per unit of each column, from the columns' norms over n_rows
    measurements (3 coordinates each); 1 for empty columns."""
    scale = np.asarray(norms, dtype=float) / np.sqrt(max(n_rows, 1))
    scale[scale == 0] = 1.0
    return scale


class ExtendedModel:
    """Geometry (free entries of x) plus linear effect terms, on one layout.

    Unknowns z = (x[free], theta). Residuals and Jacobian are computed a block of rows
    at a time (``jacobian_chunks``); the whole Jacobian is never needed.
    """

    def __init__(self, layout: Layout, obs: Observations, x: np.ndarray, free: np.ndarray,
                 terms: tuple[Term, ...]):
        self.layout, self.obs, self.x_start, self.free = layout, obs, x, free
        self.bases = combine_bases(terms, len(obs), layout.model.n_joints)
        self.n_free = int(free.sum())
        self.n_theta = self.bases.joint.shape[2]
        self.param_blocks = None if self.bases.param is None else ParamBlocks(self.bases.param)

    def constant_columns(self) -> np.ndarray:
        """bool (n_theta,): term parameters that move the targets through Cartesian columns alone, the same
        at every value of the unknowns (no joint or parameter-space part)."""
        b = self.bases
        if b.cartesian is None:
            return np.zeros(self.n_theta, bool)
        moved = np.any(b.joint.mix != 0, axis=(0, 1))
        if b.param is not None:
            moved |= np.any(b.param[1] != 0, axis=(0, 1))
        return np.any(b.cartesian != 0, axis=(0, 1)) & ~moved

    def joint_delta(self, theta: np.ndarray) -> np.ndarray:
        """(N, nj) joint-space part of the terms, rad."""
        return self.bases.joint.delta(theta)

    def unpack(self, z):
        x = self.x_start.copy()
        x[self.free] = z[: self.n_free]
        return x, z[self.n_free:]

    def _block(self, theta, rows):
        obs, bases = self.obs.subset(rows), self.bases.rows(rows)
        shifted = Observations(obs.q + bases.joint.delta(theta), obs.xyz_mm, obs.target, obs.target_names)
        return shifted, bases

    def residuals_mm(self, z) -> np.ndarray:
        x, theta = self.unpack(z)
        out = np.empty((len(self.obs), 3))
        for rows in lsq.chunks(len(self.obs)):
            obs, bases = self._block(theta, rows)
            predicted = predict(self.layout, x, obs)
            if bases.cartesian is not None:
                predicted += bases.cartesian @ theta
            if bases.param is not None:
                _, jacobian_x = jacobian(self.layout, x, obs)
                predicted += self.param_blocks.moved(jacobian_x, rows, theta)
            out[rows] = predicted - obs.xyz_mm
        return out

    def jacobian_chunks(self, z, with_residuals: bool = False):
        """(rows slice, d p / d z (n, 3, len(z))[, residuals (n, 3)]) over all rows in blocks."""
        x, theta = self.unpack(z)
        for rows in lsq.chunks(len(self.obs)):
            obs, bases = self._block(theta, rows)
            predicted, jacobian_x, jacobian_q = jacobian(self.layout, x, obs, with_joints=True)
            term_columns = bases.joint.columns(jacobian_q)
            if bases.cartesian is not None:
                term_columns += bases.cartesian
            if bases.param is not None:
                param_part = self.param_blocks.columns(jacobian_x, rows, self.n_theta)
                term_columns += param_part
            j = np.concatenate([jacobian_x[:, :, self.free], term_columns], axis=2)
            if not with_residuals:
                yield rows, j
                continue
            if bases.cartesian is not None:
                predicted = predicted + bases.cartesian @ theta
            if bases.param is not None:
                predicted = predicted + param_part @ theta
            yield rows, j, predicted - obs.xyz_mm

    def jacobian(self, z) -> np.ndarray:
        return np.concatenate([j for _, j in self.jacobian_chunks(z)])


@dataclass(frozen=True)
class ExtendedFit(FitResult):
    """Geometry and terms fitted together; status, message, success and nfev as
    :func:`cellcal.solvers.estimation.lsq.levenberg_marquardt` (scipy's "lm") reports them, no covariance
    (:func:`.physical_sizes.theta_covariance_root` makes the part that is needed)."""

    x: np.ndarray
    theta: np.ndarray  # 0 where this data cannot separate a term parameter from the geometry
    estimated: np.ndarray  # bool over z = (x[free], theta): the unknowns the fit estimated
    z: np.ndarray
    residuals_mm: np.ndarray  # (N, 3)
    model: ExtendedModel

    def jacobian_chunks(self):
        """d p / d (estimated unknowns) at the fit, geometry columns first, in blocks of rows."""
        for rows, j in self.model.jacobian_chunks(self.z):
            yield rows, j[:, :, self.estimated]


def fit_extended(layout, obs, x, free, terms, prior_mm, loss: str = "linear", f_scale: float = 1.0) -> ExtendedFit:
    """Nonlinear least-squares fit of geometry and terms together (robust: ``loss`` with scale
    ``f_scale`` mm, as scipy.optimize.least_squares defines them)."""
    model = ExtendedModel(layout, obs, x, free, terms)
    z_start = np.concatenate([x[free], np.zeros(model.n_theta)])
    # which term parameters can this data separate from the geometry? (scaled: mm per unit)
    start = lsq.RFactor(len(z_start))
    for _, j in model.jacobian_chunks(z_start):
        start.add(j.reshape(-1, len(z_start)))
    r = start.r
    scale = norm_scale(np.linalg.norm(r, axis=0), len(obs))
    geometry = np.r_[np.ones(model.n_free, bool), np.zeros(model.n_theta, bool)]
    estimated = identifiability.analyse(r / scale, geometry, ~geometry, noise_mm=None, prior_mm=prior_mm,
                                        n_rows=3 * len(obs)).keep
    estimated[: model.n_free] = True
    # the terms' own penalties (a spline's: ``base.part_penalty`` of the columns' squared lengths over the rows),
    # and the unknowns' scales with them (a coefficient the rows barely see is scaled by its penalty: else its
    # tiny scale makes the solver's first damping, from the largest scaled diagonal, stall every step)
    penalty = _penalties(terms, model.n_free, np.sum(r * r, axis=0), estimated)
    if penalty.any():
        scale = norm_scale(np.sqrt(np.sum(r * r, axis=0) + np.diagonal(penalty)), len(obs))
    own_penalty = penalty[np.ix_(estimated, estimated)]

    def with_estimated(z_estimated):
        z = z_start.copy()
        z[estimated] = z_estimated
        return z

    def evaluate(z_estimated, jac):
        z = with_estimated(z_estimated)
        ne = lsq.NormalEquations(int(estimated.sum()), loss, f_scale)
        if jac:
            for _, j, residuals in model.jacobian_chunks(z, with_residuals=True):
                ne.add(j[:, :, estimated].reshape(-1, ne.g.size), residuals.ravel())
        else:
            ne.add(None, model.residuals_mm(z).ravel())
        _add_penalty(ne, own_penalty, z_estimated, jac)
        return ne

    constant = estimated & np.r_[np.zeros(model.n_free, bool), model.constant_columns()]
    if loss == "linear" and constant.any():  # the best constant columns are solved for at every step
        sol, z = _fit_projected(model, z_start, estimated, constant, scale, penalty)
    else:
        sol = lsq.levenberg_marquardt(evaluate, z_start[estimated], 1.0 / scale[estimated], ftol=1e-10,
                                      xtol=1e-10, gtol=1e-8)
        z = with_estimated(sol.x)
    x_fit, theta = model.unpack(z)
    theta = np.where(~estimated[model.n_free:], 0.0, theta)
    return ExtendedFit(x_fit, theta, estimated, z, model.residuals_mm(z), model, **from_solver(sol))


def _penalties(terms, n_free: int, squared_lengths: np.ndarray, estimated: np.ndarray) -> np.ndarray:
    """(len(z), len(z)) the penalty on the unknowns: ``base.part_penalty`` of each term's part that carries one,
    over its estimated coefficients (squared_lengths: the columns' over the rows, over z), 0 elsewhere."""
    n = len(squared_lengths)
    out, col = np.zeros((n, n)), n_free
    for t in terms:
        for part, lam in penalised_parts((t,)):
            at = col + np.flatnonzero(np.isin(t.names, part.names))
            kept = np.flatnonzero(estimated[at])
            out[np.ix_(at[kept], at[kept])] += part_penalty(part, lam, squared_lengths[at[kept]], kept)
        col += t.size
    return out


def _add_penalty(ne, penalty: np.ndarray, z: np.ndarray, jac: bool) -> None:
    """The penalty 0.5 z^T penalty z added to a NormalEquations' cost (and gradient and matrix with jac)."""
    if not penalty.any():
        return
    moved = penalty @ z
    ne.cost += 0.5 * float(z @ moved)
    if jac:
        ne.a += penalty
        ne.g += moved


def _fit_projected(model: ExtendedModel, z_start: np.ndarray, estimated: np.ndarray, constant: np.ndarray,
                   scale: np.ndarray, penalty: np.ndarray):
    """The fit with the constant columns C (Cartesian columns of theta, the same at every z) eliminated:
    for the other unknowns u the best theta_C is a linear solve, and the residual left is f(u) projected off
    C's span, with Jacobian P J exactly (variable projection, Golub and Pereyra, "The differentiation of
    pseudo-inverses and nonlinear least squares problems whose variables separate"). The same optimum as
    the joint fit; the ill-conditioned directions C shares with the rest no longer slow each step.
    With C = Q R over all rows, only R, C^T J and C^T f are accumulated (a block of rows at a time).
    Returns (solver solution over u, z with theta_C solved)."""
    outer = estimated & ~constant
    outer_penalty = penalty[np.ix_(outer, outer)]
    cols = np.flatnonzero(constant[model.n_free:])
    n_c, n_u = len(cols), int(outer.sum())
    c_scale = scale[constant]
    c_blocks = [(model.bases.cartesian[rows][:, :, cols] / c_scale).reshape(-1, n_c)
                for rows in lsq.chunks(len(model.obs))]  # as many numbers as C itself, one block per chunk
    rc = lsq.RFactor(n_c)
    for c in c_blocks:
        rc.add(c)
    r = rc.r

    def q_t(v):  # Q^T v from C^T v (C scaled)
        return solve_triangular(r, v, trans="T", check_finite=False)

    def with_outer(u):
        z = z_start.copy()
        z[outer] = u
        z[constant] = 0.0
        return z

    def reduced(u, jac):
        z = with_outer(u)
        ne = lsq.NormalEquations(n_u)
        ff, ctf, ctj = 0.0, np.zeros(n_c), np.zeros((n_c, n_u))
        blocks = (model.jacobian_chunks(z, with_residuals=True) if jac else
                  ((rows, None, res[rows]) for res in [model.residuals_mm(z)] for rows in lsq.chunks(len(res))))
        for (rows, j, residuals), c in zip(blocks, c_blocks):
            f = residuals.ravel()
            ff += float(f @ f)
            ctf += c.T @ f
            if jac:
                j = j[:, :, outer].reshape(-1, n_u)
                ne.a += j.T @ j
                ne.g += j.T @ f
                ctj += c.T @ j
        qtf = q_t(ctf)
        ne.cost = 0.5 * max(ff - float(qtf @ qtf), 0.0)
        if jac:
            qtj = q_t(ctj)
            ne.a -= qtj.T @ qtj
            ne.g -= qtj.T @ qtf
        _add_penalty(ne, outer_penalty, u, jac)  # penalised parts are joint-space: never constant
        return ne, qtf

    # ftol: a step that lowers the cost by less than 1e-6 of it changes the mean error by ~5e-7 of it, far
    # below the 4 digits reported; a term of hundreds of barely determined columns crawls there (Justin: 134
    # evaluations to 1e-10, 79 to 1e-6, the same in-sample mean error to 6 digits)
    sol = lsq.levenberg_marquardt(lambda u, jac: reduced(u, jac)[0], z_start[outer], 1.0 / scale[outer],
                                  ftol=1e-6, xtol=1e-10, gtol=1e-8)
    z = with_outer(sol.x)
    z[constant] = -solve_triangular(r, reduced(sol.x, False)[1], check_finite=False) / c_scale
    return sol, z


def embed(x: np.ndarray, n_kin: int, extra: int, fill=0.0) -> np.ndarray:
    """x of a layout with `extra` more kinematic parameters appended (set to fill)."""
    return np.concatenate([x[:n_kin], np.full(extra, fill, dtype=x.dtype), x[n_kin:]])
