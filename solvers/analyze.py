"""What is the rigid model getting wrong? Model-discrepancy analysis.

1. Fit the rigid geometric model (``identify``): the baseline.
2. For every candidate term of every named cause (``effects``), fit geometry and
   term jointly; the term's parameters are estimated only where the data can
   separate them from the geometry (same identifiability rule as ``identify``).
3. Score baseline and candidates on held-out data: grouped k-fold
   cross-validation, neighbouring configurations kept in one fold.
4. Name the best candidate only when it beats the baseline by MIN_GAIN and the
   best candidate of any other cause by MIN_MARGIN; else ``none``.
5. With the named term in the model, rank the rest again: a second effect, and a
   fit of both.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from . import crossval, identifiability
from .effects import CAUSES, Context, Term
from .identify import IdentifyOptions, identify
from .measurement_model import Layout, Observations, jacobian, predict

MIN_GAIN = 0.10  # held-out mean error must drop by 10% against geometry alone
MIN_MARGIN = 0.08  # ... and the best other cause must stay 8% above the named one
MULTI_GAIN = 0.10  # a several-joint term must beat its cause's best single joint by this much
NEIGHBOUR_RAD = np.deg2rad(2.0)  # configurations this close share a fold
NESTED_RTOL = 0.02  # one term's columns lie in another's span to this relative residual (2%)


@dataclass(frozen=True)
class AnalyzeOptions:
    folds: int = 5
    seed: int = 0
    causes: tuple[str, ...] = tuple(CAUSES)
    prior_mm: float = 1.0


@dataclass(frozen=True)
class Scored:
    """One model scored on held-out data."""

    label: str
    cause: str
    where: dict
    heldout_errors: np.ndarray  # (N,) per measurement, mm
    theta: np.ndarray
    magnitude: dict
    x: np.ndarray
    terms: tuple[Term, ...] = ()
    residuals: np.ndarray | None = None  # (N, 3) in-sample, predicted - measured, mm
    effect_mm: np.ndarray | None = None  # (N, 3) what the terms move each target by beyond what
    #                                      geometry absorbs (single terms), mm
    joint_delta: np.ndarray | None = None  # (N, nj) joint-space part of the terms, rad

    @property
    def heldout_mean_mm(self) -> float:
        return float(self.heldout_errors.mean())


@dataclass(frozen=True)
class Finding:
    cause: str
    where: dict
    magnitude: dict
    baseline: Scored
    extended: Scored
    candidates: tuple[Scored, ...]  # best first
    margin: float  # how much higher (fraction) the best other cause's held-out error is
    second: Scored | None = None  # second effect, fitted together with the first
    both: Scored | None = None
    seconds: float = 0.0
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def gain_pct(self) -> float:
        return 100.0 * (1.0 - self.extended.heldout_mean_mm / self.baseline.heldout_mean_mm)


def _combine(terms: tuple[Term, ...], n_rows: int, n_joints: int):
    """Stack the bases of several terms into one joint, one Cartesian and one parameter basis."""
    m = sum(t.size for t in terms)
    jb = np.zeros((n_rows, n_joints, m))
    cb = np.zeros((n_rows, 3, m))
    pb: dict[int, np.ndarray] = {}
    col = 0
    for t in terms:
        if t.joint_basis is not None:
            jb[:, :, col: col + t.size] = t.joint_basis
        if t.cart_basis is not None:
            cb[:, :, col: col + t.size] = t.cart_basis
        for p, basis in (t.param_basis or {}).items():
            pb.setdefault(p, np.zeros((n_rows, m)))[:, col: col + t.size] += basis
        col += t.size
    return jb, cb, _stack(pb) if pb else None


def _stack(pb: dict):
    """Parameter bases as (parameter indices, (N, P, m)) for one matrix product."""
    params = list(pb)
    return params, np.stack([pb[p] for p in params], axis=1)


def _param_columns(jx_full: np.ndarray, stacked) -> np.ndarray:
    """d p / d theta of parameter-space terms: sum_p (d p / d k_p) * basis_p."""
    params, basis = stacked
    return np.matmul(jx_full[:, :, params], basis)


class _Extended:
    """Geometry (free entries of x) plus linear effect terms, on one layout."""

    def __init__(self, layout: Layout, obs: Observations, x: np.ndarray, free: np.ndarray,
                 terms: tuple[Term, ...]):
        self.layout, self.obs, self.x0, self.free, self.terms = layout, obs, x, free, terms
        self.jb, self.cb, self.pb = _combine(terms, len(obs), layout.model.n_joints)
        self.m = self.jb.shape[2]

    def _obs(self, theta):
        q = self.obs.q + np.einsum("njm,m->nj", self.jb, theta)
        return Observations(q, self.obs.xyz, self.obs.target, self.obs.target_names)

    def unpack(self, z):
        x = self.x0.copy()
        x[self.free] = z[: self.free.sum()]
        return x, z[self.free.sum():]

    def residuals(self, z):
        x, theta = self.unpack(z)
        obs = self._obs(theta)
        p = predict(self.layout, x, obs) + np.einsum("nim,m->ni", self.cb, theta)
        if self.pb:
            _, jx = jacobian(self.layout, x, obs)
            p = p + np.einsum("nim,m->ni", _param_columns(jx, self.pb), theta)
        return p - self.obs.xyz

    def jac(self, z):
        x, theta = self.unpack(z)
        _, jx, jq = jacobian(self.layout, x, self._obs(theta), with_joints=True)
        jt = np.einsum("nij,njm->nim", jq, self.jb) + self.cb
        if self.pb:
            jt = jt + _param_columns(jx, self.pb)
        return np.concatenate([jx[:, :, self.free], jt], axis=2)


def _fit_extended(layout, obs, x, free, terms, noise_mm, prior_mm):
    """Fit geometry and terms; returns (x, theta (full, 0 where not estimable), J, residuals)."""
    model = _Extended(layout, obs, x, free, terms)
    z0 = np.concatenate([x[free], np.zeros(model.m)])
    j0 = model.jac(z0)
    # which term parameters can this data separate from the geometry? (scaled: mm per unit)
    col_norm = np.sqrt(np.mean(j0.reshape(-1, j0.shape[2]) ** 2, axis=0) * 3)
    col_norm[col_norm == 0] = 1.0
    nuisance = np.r_[np.ones(int(free.sum()), bool), np.zeros(model.m, bool)]
    keep = identifiability.analyse(j0.reshape(-1, j0.shape[2]) / col_norm, nuisance, ~nuisance,
                                   noise_mm=None, prior_mm=prior_mm).keep
    keep[: int(free.sum())] = True
    fixed_terms = ~keep[int(free.sum()):]

    def fun(zk):
        z = z0.copy()
        z[keep] = zk
        return model.residuals(z).ravel()

    def jac(zk):
        z = z0.copy()
        z[keep] = zk
        return model.jac(z).reshape(-1, len(z0))[:, keep]

    sol = least_squares(fun, z0[keep], jac=jac, method="lm", x_scale=1.0 / col_norm[keep],
                        xtol=1e-10, ftol=1e-10)
    z = z0.copy()
    z[keep] = sol.x
    xf, theta = model.unpack(z)
    theta = np.where(fixed_terms, 0.0, theta)
    j = model.jac(z)[:, :, keep]
    return xf, theta, j, model.residuals(z), model


def _linear_columns(term: Term, jq: np.ndarray, model, geo, obs, jx_full=None) -> np.ndarray:
    """d p / d theta of a term at the geometric fit (N, 3, m)."""
    if term.model is not None:  # one new rigid parameter: its Jacobian column in the new layout
        layout = Layout(term.model, obs.target_names)
        x = _embed(geo.x, geo.layout.n_kin, term.model.n_params - model.n_params)
        _, j = jacobian(layout, x, obs)
        return j[:, :, model.n_params: term.model.n_params]
    cols = np.zeros((len(obs), 3, term.size))
    if term.joint_basis is not None:
        cols += np.einsum("nij,njm->nim", jq, term.joint_basis)
    if term.cart_basis is not None:
        cols += term.cart_basis
    if term.param_basis:
        cols += _param_columns(jx_full, _stack(term.param_basis))
    return cols


def _embed(x: np.ndarray, n_kin: int, extra: int, fill=0.0) -> np.ndarray:
    """x of a layout with `extra` more kinematic parameters appended (set to fill)."""
    return np.concatenate([x[:n_kin], np.full(extra, fill, dtype=x.dtype), x[n_kin:]])


def analyze(model, obs: Observations, ctx: Context, options: AnalyzeOptions = AnalyzeOptions(),
            progress=None) -> Finding:
    """Find, name and size the physical effect the rigid model misses (or ``none``).

    Candidates are ranked on the model linearised at the geometric fit (every
    effect here is a small perturbation of it); the named one, and the pair when
    a second effect shows, are then fitted in full.
    """
    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    folds = crossval.fold_ids(obs.q, options.folds, options.seed, NEIGHBOUR_RAD)
    geo = _geometric_baseline(model, obs, folds, options)
    noise = geo.noise_mm
    _, jx_full, jq = jacobian(geo.layout, geo.x, obs, with_joints=True)
    jx = jx_full[:, :, geo.free]
    r0 = geo.residuals
    geo_norm = np.sqrt(np.mean(jx.reshape(-1, jx.shape[2]) ** 2, axis=0) * 3)
    geo_norm[geo_norm == 0] = 1.0
    geo_basis = identifiability.nuisance_basis(jx.reshape(-1, jx.shape[2]) / geo_norm,
                                               np.ones(jx.shape[2], bool))
    say(f"geometric model: {len(obs)} measurements, residual {np.linalg.norm(r0, axis=1).mean():.3f} mm mean")

    column_cache: dict[int, np.ndarray] = {}

    def columns(term: Term) -> np.ndarray:
        if id(term) not in column_cache:
            column_cache[id(term)] = _linear_columns(term, jq, model, geo, obs, jx_full)
        return column_cache[id(term)]

    def linear_score(terms: tuple[Term, ...]):
        cols = [columns(t) for t in terms]
        jt = np.concatenate(cols, axis=2) if cols else np.zeros((len(obs), 3, 0))
        j = np.concatenate([jx, jt], axis=2)
        flat = j.reshape(-1, j.shape[2])
        norm = np.sqrt(np.mean(flat**2, axis=0) * 3)
        norm[norm == 0] = 1.0
        nuisance = np.r_[np.ones(jx.shape[2], bool), np.zeros(jt.shape[2], bool)]
        basis = (geo_basis[0], np.r_[geo_basis[1], np.zeros(jt.shape[2], bool)])
        keep = identifiability.analyse(flat / norm, nuisance, ~nuisance, noise_mm=None,
                                       prior_mm=options.prior_mm, basis=basis, with_condition=False).keep
        keep[: jx.shape[2]] = True
        errors = crossval.one_step_heldout(j[:, :, keep], r0, folds)[0]
        return errors

    def nested(inner: Term, outer: Term) -> bool:
        """Does geometry + outer span every column of inner? (Then outer explains nothing
        that inner cannot, wherever the two tie.)"""
        a = np.concatenate([jx, columns(outer)], axis=2)
        a = a.reshape(-1, a.shape[2])
        b = columns(inner).reshape(len(a), -1)
        coef = np.linalg.lstsq(a, b, rcond=None)[0]
        return bool(np.linalg.norm(a @ coef - b) <= NESTED_RTOL * np.linalg.norm(b))

    baseline_errors = linear_score(())
    baseline = Scored("geometry only", "none", {}, baseline_errors, np.zeros(0), {}, geo.x, (), r0)
    say(f"held-out mean, geometry only: {baseline.heldout_mean_mm:.3f} mm")

    terms = [t for cid in options.causes for t in CAUSES[cid].terms(model, geo.layout, geo.x, obs, ctx)]
    candidates = [Scored(t.label(), t.cause, t.where, linear_score((t,)), np.zeros(t.size), {}, geo.x, (t,))
                  for t in terms]
    candidates.sort(key=lambda s: s.heldout_mean_mm)
    _prefer_single(candidates, lambda c: c.heldout_mean_mm, lambda c: c.terms[0])
    say(f"scored {len(candidates)} candidates")
    e0 = baseline.heldout_mean_mm
    notes = []
    margin = 0.0
    named = None
    if candidates:
        best = candidates[0]
        gain = 1.0 - best.heldout_mean_mm / e0
        others = [c for c in candidates if c.cause != best.cause]
        margin = (others[0].heldout_mean_mm / best.heldout_mean_mm - 1.0) if others else 1.0
        if gain < MIN_GAIN:
            notes.append(f"best candidate {best.label} gains {100 * gain:.1f}% on held-out data, "
                         f"below the {100 * MIN_GAIN:.0f}% needed to name it")
        elif margin < MIN_MARGIN:
            # two causes explain about as much: the same structure (ambiguous), two effects, or
            # one explanation contained in the other (then the smaller one is the answer)?
            pair = linear_score((best.terms + others[0].terms)).mean()
            small, large = sorted((best, others[0]), key=lambda c: sum(t.size for t in c.terms))
            if (1.0 - small.heldout_mean_mm / e0 >= MIN_GAIN and small.terms[0].size < large.terms[0].size
                    and nested(small.terms[0], large.terms[0])):
                named = small
                candidates.insert(0, candidates.pop(candidates.index(small)))
                notes.append(f"{large.label} fits about as well only through terms that are the same as "
                             f"{small.label}; the simpler explanation is named")
            elif pair < (1.0 - MIN_GAIN) * min(best.heldout_mean_mm, others[0].heldout_mean_mm):
                named = best
                notes.append(f"{best.label} and {others[0].label} are both present: together they "
                             f"reach {pair:.4f} mm held-out")
            else:
                notes.append(f"{best.label} and {others[0].label} explain the data about equally well "
                             f"(held-out errors {100 * margin:.1f}% apart, {100 * MIN_MARGIN:.0f}% needed)")
        else:
            named = best
    second = both = None
    if named is not None:
        # with the named effect in the model, is there a second one?
        pairs = [(linear_score(named.terms + (t,)), t) for t in terms if t.cause != named.cause]
        pairs.sort(key=lambda p: p[0].mean())
        _prefer_single(pairs, lambda p: p[0].mean(), lambda p: p[1])
        if pairs and pairs[0][0].mean() < (1.0 - MIN_GAIN) * named.heldout_mean_mm:
            second = next(c for c in candidates if c.terms == (pairs[0][1],))
            both = _full_fit(model, geo, obs, folds, named.terms + second.terms, noise, options,
                             f"{named.label} + {second.label}")
        named = _full_fit(model, geo, obs, folds, named.terms, noise, options, named.label)
    say(f"analysis done in {time.perf_counter() - t0:.1f} s")
    extended = named or baseline
    return Finding(
        cause=named.cause if named else "none", where=named.where if named else {},
        magnitude=named.magnitude if named else {}, baseline=baseline, extended=extended,
        candidates=tuple(candidates), margin=float(margin), second=second, both=both,
        seconds=time.perf_counter() - t0, notes=tuple(notes))


def _geometric_baseline(model, obs, folds, options):
    """The geometric fit to compare against: the parameters above the noise, or every
    structurally identifiable one, whichever predicts held-out data better. (When an
    unmodelled effect dominates the residual, the noise criterion is too strict.)"""
    above_noise = identify(model, obs, IdentifyOptions(regularize="none", prior_mm=options.prior_mm))
    structural = identify(model, obs, IdentifyOptions(regularize="cv", prior_mm=options.prior_mm))
    if np.array_equal(above_noise.free, structural.free):
        return above_noise

    def heldout(result):
        _, j = jacobian(result.layout, result.x, obs)
        return crossval.one_step_heldout(j[:, :, result.free], result.residuals, folds)[0].mean()

    return min((above_noise, structural), key=heldout)


def _prefer_single(ranked: list, error, term) -> None:
    """Parsimony, in place: a term spanning several joints must beat the best single-place
    term of its cause by MULTI_GAIN, else the single place goes first (it says *where*)."""
    if not ranked:
        return
    best = ranked[0]
    singles = [i for i, r in enumerate(ranked) if term(r).cause == term(best).cause and not term(r).multi]
    if singles and singles[0] != 0 and error(best) > (1.0 - MULTI_GAIN) * error(ranked[singles[0]]):
        ranked.insert(0, ranked.pop(singles[0]))


def _full_fit(model, geo, obs, folds, terms: tuple[Term, ...], noise, options, label) -> Scored:
    """Nonlinear fit of geometry plus terms; held-out errors and physical sizes."""
    layout, x, free = geo.layout, geo.x, geo.free
    structural = [t for t in terms if t.model is not None]
    if structural:  # a different rigid model: carry the geometric fit over into its layout
        ext = structural[-1].model
        extra = ext.n_params - model.n_params
        layout = Layout(ext, obs.target_names)
        x = _embed(geo.x, geo.layout.n_kin, extra)
        free = _embed(geo.free, geo.layout.n_kin, extra, fill=True)
    linear = tuple(t for t in terms if t.model is None)
    xf, theta, j, r, fitted = _fit_extended(layout, obs, x, free, linear, noise, options.prior_mm)
    errors = crossval.one_step_heldout(j, r, folds)[0]
    size, col = {}, 0
    for t in terms:
        if t.model is not None:
            size[t.cause] = CAUSES[t.cause].magnitude(t, xf[model.n_params: t.model.n_params], None)
            continue
        th = theta[col: col + t.size]
        delta = np.einsum("njm,m->nj", fitted.jb[:, :, col: col + t.size], th)
        size[t.cause] = CAUSES[t.cause].magnitude(t, th, delta)
        col += t.size
    magnitude = size[terms[0].cause] if len(terms) == 1 else size
    # what the terms do at the targets: the fitted model with and without them
    without = xf.copy()
    for t in structural:
        without[model.n_params: t.model.n_params] = 0.0
    plain = predict(layout, without, obs)
    effect = (r + obs.xyz) - plain
    if len(terms) == 1:
        # the size that needs no model to read: how far the effect moves the targets, less what a
        # geometric calibration absorbs anyway (the part the geometric columns can reproduce)
        geo_cols = j[:, :, : int(free.sum())].reshape(-1, int(free.sum()))
        rest = effect.ravel() - geo_cols @ np.linalg.lstsq(geo_cols, effect.ravel(), rcond=None)[0]
        effect = rest.reshape(-1, 3)
        magnitude = {**magnitude, "effect_beyond_geometry_rms_mm": float(np.sqrt(np.mean(
            np.sum(effect**2, axis=1))))}
    return Scored(label, terms[0].cause, terms[0].where, errors, theta, magnitude, xf, terms, r, effect,
                  np.einsum("njm,m->nj", fitted.jb, theta))
