"""Least-squares fits of the kinematic model a block of rows at a time.

The fit over any subset of the unknowns (``fit``: Levenberg-Marquardt on normal equations
accumulated over row blocks, the L2 prior toward nominal as extra rows, robust losses as
scipy applies them), the start for base and target offsets from the data alone, the
covariance of a fit, and the registration of a kinematic result on other data.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.estimation import lsq
from cellcal.solvers.geometry import se3
from cellcal.solvers.estimation.fit_result import FitResult, from_solver
from cellcal.solvers.geometry.chain import forward
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian_chunks, predict, predict_base


@dataclass(frozen=True)
class Fit(FitResult):
    """status, message, success and nfev as
    :func:`cellcal.solvers.estimation.lsq.levenberg_marquardt` (scipy's "lm") reports them; no
    covariance (:func:`covariance` makes it for the fits that need it)."""

    x: np.ndarray  # full unknown vector, units as in Identification.x
    residuals_mm: np.ndarray  # (N, 3) predicted - measured

    @property
    def errors(self) -> np.ndarray:
        """Distance of each prediction from its measurement, mm."""
        return np.linalg.norm(self.residuals_mm, axis=1)

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residuals_mm**2, axis=1))))


def scales(layout: Layout, x: np.ndarray, obs: Observations) -> np.ndarray:
    """Per-unknown scale: 1 for mm, 1/reach for rad (one unit moves a target ~1 mm)."""
    reach = float(np.median(np.linalg.norm(predict_base(layout, x, obs), axis=1)))
    reach = max(reach, 1.0)
    return np.where(layout.is_angle, 1.0 / reach, 1.0)


def _problem(layout, obs, x_full, free, lam, scale, loss="linear", f_scale=1.0, cache=None):
    """The least-squares problem over the free entries of x: (unpack, evaluate) for
    ``lsq.levenberg_marquardt``, the L2 prior on kinematic parameters as extra rows.
    cache: x.tobytes() -> Gram matrix of [J | r] over every unknown at x, made earlier
    (least squares only)."""
    idx = np.flatnonzero(free)
    kinematic = bool(np.any(idx < layout.n_kin))  # else only base and target columns are needed
    kin = idx[idx < layout.n_kin]
    at = np.searchsorted(idx, kin)
    centre = layout.model.nominal[kin]
    w = np.sqrt(lam) / scale[kin] if lam > 0 else None

    def unpack(z):
        x = x_full.copy()
        x[idx] = z
        return x

    def evaluate(z, jac):
        x = unpack(z)
        ne = lsq.NormalEquations(len(idx), loss, f_scale)
        gram = cache.get(x.tobytes()) if jac and cache is not None and loss == "linear" else None
        if gram is not None:
            ne.a, ne.g, ne.cost = gram[np.ix_(idx, idx)].copy(), gram[idx, -1].copy(), 0.5 * float(gram[-1, -1])
        elif jac:
            for rows, p, j in jacobian_chunks(layout, x, obs, kinematic=kinematic):
                ne.add(j.reshape(-1, layout.size)[:, idx], (p - obs.xyz_mm[rows]).ravel())
        else:
            ne.add(None, (predict(layout, x, obs) - obs.xyz_mm).ravel())
        if w is not None:
            prior = np.zeros((len(kin), len(idx)))
            prior[np.arange(len(kin)), at] = w
            ne.add(prior if jac else None, w * (x[kin] - centre))
        return ne

    return unpack, evaluate


def fit(layout: Layout, obs: Observations, x_start: np.ndarray, free: np.ndarray, lam: float = 0.0,
        scale: np.ndarray | None = None, loss: str = "linear", f_scale: float = 1.0, cache=None) -> Fit:
    """Least squares over the free entries of x, starting from x_start (Levenberg-Marquardt on
    normal equations accumulated over blocks of rows: the Jacobian never exists whole)."""
    if scale is None:
        scale = scales(layout, x_start, obs)
    unpack, evaluate = _problem(layout, obs, x_start, free, lam, scale, loss, f_scale, cache)
    sol = lsq.levenberg_marquardt(evaluate, x_start[free], scale[free], ftol=1e-12, xtol=1e-12, gtol=1e-12,
                                  max_nfev=None if loss == "linear" else 200)
    x = unpack(sol.x)
    return Fit(x=x, residuals_mm=predict(layout, x, obs) - obs.xyz_mm, **from_solver(sol))


def initial_base_and_targets(layout: Layout, obs: Observations, x: np.ndarray | None = None) -> np.ndarray:
    """Start for base and target offsets from the data alone (nominal kinematics).

    Rigid fit of the nominal end-frame origins to the measured points (offsets
    are small against the workspace), then alternate: offsets by linear least
    squares given the base, base by a rigid fit given the offsets.
    """
    x = layout.initial() if x is None else x.copy()
    x[layout.base] = 0.0
    for i in range(len(layout.target_names)):
        x[layout.target(i)] = 0.0
    for _ in range(20):
        pb = predict_base(layout, x, obs)
        r, t = se3.rigid_fit(pb, obs.xyz_mm)
        x[layout.base] = np.concatenate([t, se3.matrix_to_rotvec(r)])
        # offsets: R_end @ off = R^T (m - t) - o_end, solved per target
        k = x[: layout.n_kin]
        local = (obs.xyz_mm - t) @ r
        change = 0.0
        for ti in range(len(layout.target_names)):
            rows = np.flatnonzero(obs.target == ti)
            if not len(rows):
                continue
            chain = layout.model.chains[layout.model.chain_for(layout.target_names[ti])]
            ata, atb = np.zeros((3, 3)), np.zeros(3)  # normal equations over blocks of rows
            for block in lsq.chunks(len(rows)):
                rot, org = forward(chain, k, obs.q[rows[block]])
                a = rot.reshape(-1, 3)
                ata += a.T @ a
                atb += a.T @ (local[rows[block]] - org).ravel()
            off = np.linalg.lstsq(ata, atb, rcond=None)[0]
            change = max(change, float(np.linalg.norm(off - x[layout.target(ti)])))
            x[layout.target(ti)] = off
        if change < 1e-6:
            break
    return x


def covariance(layout, obs, x, free, lam, scale) -> tuple[np.ndarray, float]:
    """Covariance of the free entries of x (x's units) from the final Jacobian and the
    residual variance (sandwich form, so a prior shrinks it only as far as it really does),
    and the residual standard deviation per coordinate."""
    idx = np.flatnonzero(free)
    data = lsq.NormalEquations(len(idx))
    for rows, p, j in jacobian_chunks(layout, x, obs):
        data.add(j.reshape(-1, layout.size)[:, idx], (p - obs.xyz_mm[rows]).ravel())
    a = data.a.copy()
    if lam > 0:
        kin = np.flatnonzero(idx < layout.n_kin)
        a[kin, kin] += lam / scale[idx[kin]] ** 2
    dof = max(3 * len(obs) - len(idx), 1)
    s2 = 2.0 * data.cost / dof
    a_inv = np.linalg.pinv(a)
    cov = a_inv @ data.a @ a_inv * s2
    return cov, float(np.sqrt(s2))


def at_start(layout, x, obs, scale) -> tuple[np.ndarray, np.ndarray]:
    """R factor of the scaled Jacobian over every unknown (same singular values and subsets),
    and the Gram matrix of [J | r] (unscaled) for the fits that start here."""
    acc = lsq.RFactor(layout.size)
    gram = np.zeros((layout.size + 1, layout.size + 1))
    for rows, p, j in jacobian_chunks(layout, x, obs):
        j = j.reshape(-1, layout.size)
        acc.add(j * scale)
        a = np.concatenate([j, (p - obs.xyz_mm[rows]).reshape(-1, 1)], axis=1)
        gram += a.T @ a
    return acc.r, gram


def f_scale_of(residuals: np.ndarray) -> float:
    mad = np.median(np.abs(residuals - np.median(residuals)))
    return max(2.5 * 1.4826 * mad, 1e-6)


def register(layout: Layout, x: np.ndarray, obs: Observations) -> Fit:
    """Fit only base and target offsets to obs, kinematics held as in x.

    How a kinematic result is scored on data from another instrument set-up (Liu et al.,
    "L2-Regularization-Based Kinematic Parameter Identification for Industrial Robots in
    Limited Measurement Space", Actuators 2025, validate with a laser tracker after a
    calibration with an R-test): the
    frames are registered anew, the geometry is what is being judged.
    """
    start = initial_base_and_targets(layout, obs, x)
    free = np.zeros(layout.size, bool)
    free[layout.n_kin:] = True
    return fit(layout, obs, start, free)
