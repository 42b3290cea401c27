"""The rigid model extended with linear effect terms, and its joint fit.

A term (``effects.Term``) adds a joint-space, a Cartesian or a parameter-space
displacement linear in its own parameters theta; here several terms are stacked into
one basis, and geometry (the free entries of the identification's x) and theta are
fitted together by nonlinear least squares. Term parameters the data cannot separate
from the geometry are held at 0 (the identifiability rule of ``identify``).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.optimize import least_squares

from . import identifiability
from .effects import Term
from .measurement_model import Layout, Observations, jacobian, predict


class TermBases(NamedTuple):
    """Several terms' bases side by side, one column per term parameter (m in all)."""

    joint: np.ndarray  # (N, nj, m)
    cartesian: np.ndarray  # (N, 3, m)
    param: tuple | None  # (kinematic parameter indices, (N, P, m)), or None without parameter-space terms


def combine_bases(terms: tuple[Term, ...], n_rows: int, n_joints: int) -> TermBases:
    m = sum(t.size for t in terms)
    joint = np.zeros((n_rows, n_joints, m))
    cartesian = np.zeros((n_rows, 3, m))
    param: dict[int, np.ndarray] = {}
    col = 0
    for t in terms:
        if t.joint_basis is not None:
            joint[:, :, col: col + t.size] = t.joint_basis
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


def column_scale(flat: np.ndarray) -> np.ndarray:
    """RMS target displacement (mm) per unit of each column; 1 for empty columns."""
    scale = np.sqrt(np.mean(flat**2, axis=0) * 3)
    scale[scale == 0] = 1.0
    return scale


class ExtendedModel:
    """Geometry (free entries of x) plus linear effect terms, on one layout.

    Unknowns z = (x[free], theta).
    """

    def __init__(self, layout: Layout, obs: Observations, x: np.ndarray, free: np.ndarray,
                 terms: tuple[Term, ...]):
        self.layout, self.obs, self.x_start, self.free = layout, obs, x, free
        self.bases = combine_bases(terms, len(obs), layout.model.n_joints)
        self.n_free = int(free.sum())
        self.n_theta = self.bases.joint.shape[2]

    def joint_delta(self, theta: np.ndarray) -> np.ndarray:
        """(N, nj) joint-space part of the terms, rad."""
        return np.einsum("njm,m->nj", self.bases.joint, theta)

    def _shifted(self, theta) -> Observations:
        return Observations(self.obs.q + self.joint_delta(theta), self.obs.xyz_mm, self.obs.target,
                            self.obs.target_names)

    def unpack(self, z):
        x = self.x_start.copy()
        x[self.free] = z[: self.n_free]
        return x, z[self.n_free:]

    def residuals_mm(self, z):
        x, theta = self.unpack(z)
        obs = self._shifted(theta)
        predicted = predict(self.layout, x, obs) + np.einsum("nim,m->ni", self.bases.cartesian, theta)
        if self.bases.param is not None:
            _, jacobian_x = jacobian(self.layout, x, obs)
            predicted = predicted + np.einsum("nim,m->ni", param_columns(jacobian_x, self.bases.param), theta)
        return predicted - self.obs.xyz_mm

    def jacobian(self, z):
        x, theta = self.unpack(z)
        _, jacobian_x, jacobian_q = jacobian(self.layout, x, self._shifted(theta), with_joints=True)
        term_columns = np.einsum("nij,njm->nim", jacobian_q, self.bases.joint) + self.bases.cartesian
        if self.bases.param is not None:
            term_columns = term_columns + param_columns(jacobian_x, self.bases.param)
        return np.concatenate([jacobian_x[:, :, self.free], term_columns], axis=2)


class ExtendedFit(NamedTuple):
    x: np.ndarray
    theta: np.ndarray  # 0 where this data cannot separate a term parameter from the geometry
    jacobian: np.ndarray  # (N, 3, estimated unknowns), geometry columns first
    residuals_mm: np.ndarray  # (N, 3)
    model: ExtendedModel


def fit_extended(layout, obs, x, free, terms, prior_mm) -> ExtendedFit:
    """Nonlinear least-squares fit of geometry and terms together."""
    model = ExtendedModel(layout, obs, x, free, terms)
    z_start = np.concatenate([x[free], np.zeros(model.n_theta)])
    flat = model.jacobian(z_start).reshape(-1, len(z_start))
    # which term parameters can this data separate from the geometry? (scaled: mm per unit)
    scale = column_scale(flat)
    geometry = np.r_[np.ones(model.n_free, bool), np.zeros(model.n_theta, bool)]
    estimated = identifiability.analyse(flat / scale, geometry, ~geometry, noise_mm=None, prior_mm=prior_mm).keep
    estimated[: model.n_free] = True

    def with_estimated(z_estimated):
        z = z_start.copy()
        z[estimated] = z_estimated
        return z

    sol = least_squares(lambda ze: model.residuals_mm(with_estimated(ze)).ravel(), z_start[estimated],
                        jac=lambda ze: model.jacobian(with_estimated(ze)).reshape(-1, len(z_start))[:, estimated],
                        method="lm", x_scale=1.0 / scale[estimated], xtol=1e-10, ftol=1e-10)
    z = with_estimated(sol.x)
    x_fit, theta = model.unpack(z)
    theta = np.where(~estimated[model.n_free:], 0.0, theta)
    return ExtendedFit(x_fit, theta, model.jacobian(z)[:, :, estimated], model.residuals_mm(z), model)


def embed(x: np.ndarray, n_kin: int, extra: int, fill=0.0) -> np.ndarray:
    """x of a layout with `extra` more kinematic parameters appended (set to fill)."""
    return np.concatenate([x[:n_kin], np.full(extra, fill, dtype=x.dtype), x[n_kin:]])
