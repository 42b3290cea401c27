"""What is the rigid model getting wrong? Model-discrepancy analysis.

1. Fit the rigid geometric model (``identify``): the baseline.
2. For every candidate term of every named cause (``effects``), fit geometry and
   term jointly, linearised at the geometric fit (``LinearisedScorer``); the
   term's parameters are estimated only where the data can separate them from
   the geometry (same identifiability rule as ``identify``).
3. Score baseline and candidates on held-out data: grouped k-fold
   cross-validation, neighbouring configurations kept in one fold
   (``score_candidates``).
4. Name the best candidate only when it beats the baseline by MIN_GAIN and the
   best candidate of any other cause by MIN_MARGIN; else ``none``
   (``name_cause``, which also settles near-ties).
5. With the named term in the model, rank the rest again: a second effect
   (``find_second_effect``), and a fit of both. The named term, and the pair,
   are then fitted in full.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from . import crossval, identifiability
from .effects import CAUSES, Context, Term
from .identify import Identification, IdentifyOptions, identify
from .extended_model import ExtendedFit, column_scale, embed, fit_extended, param_columns, stack_param_bases
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


@dataclass(frozen=True)
class Naming:
    """What the naming rule decided."""

    named: Scored | None  # None: the answer is ``none``
    candidates: tuple[Scored, ...]  # best first; a simpler explanation that wins a tie goes first
    margin: float  # how much higher (fraction) the best other cause's held-out error is
    notes: tuple[str, ...] = ()


def analyze(model, obs: Observations, ctx: Context, options: AnalyzeOptions = AnalyzeOptions(),
            progress=None) -> Finding:
    """Find, name and size the physical effect the rigid model misses (or ``none``).

    Candidates are ranked on the model linearised at the geometric fit (every
    effect here is a small perturbation of it); the named one, and the pair when
    a second effect shows, are then fitted in full.
    """
    started = time.perf_counter()
    say = progress or (lambda msg: None)
    folds = crossval.fold_ids(obs.q, options.folds, options.seed, NEIGHBOUR_RAD)
    geometric_fit = _geometric_baseline(model, obs, folds, options)
    scorer = LinearisedScorer(model, geometric_fit, obs, folds, options.prior_mm)
    say(f"geometric model: {len(obs)} measurements, residual "
        f"{np.linalg.norm(scorer.baseline_residuals_mm, axis=1).mean():.3f} mm mean")

    baseline = Scored(label="geometry only", cause="none", where={}, heldout_errors=scorer.heldout_errors_mm(()),
                      theta=np.zeros(0), magnitude={}, x=geometric_fit.x, residuals=scorer.baseline_residuals_mm)
    say(f"held-out mean, geometry only: {baseline.heldout_mean_mm:.3f} mm")

    terms = [term for cause in options.causes
             for term in CAUSES[cause].terms(model, geometric_fit.layout, geometric_fit.x, obs, ctx)]
    candidates = score_candidates(terms, scorer)
    say(f"scored {len(candidates)} candidates")
    naming = name_cause(candidates, baseline, scorer)

    extended, second, both = baseline, None, None
    if naming.named is not None:
        named = naming.named
        second = find_second_effect(named, terms, naming.candidates, scorer)
        if second is not None:
            both = _fit_in_full(model, geometric_fit, obs, folds, named.terms + second.terms, options.prior_mm,
                                f"{named.label} + {second.label}")
        extended = _fit_in_full(model, geometric_fit, obs, folds, named.terms, options.prior_mm, named.label)
    say(f"analysis done in {time.perf_counter() - started:.1f} s")
    return Finding(
        cause=extended.cause, where=extended.where, magnitude=extended.magnitude, baseline=baseline,
        extended=extended, candidates=naming.candidates, margin=float(naming.margin), second=second, both=both,
        seconds=time.perf_counter() - started, notes=naming.notes)


# -- scoring: held-out errors on the model linearised at the geometric fit ----------------------------------


class LinearisedScorer:
    """Held-out errors of geometry plus effect terms, one Gauss-Newton step from the geometric fit.

    A term's parameters enter only where this data can separate them from the
    geometry; each term's Jacobian columns are computed once and reused.
    """

    def __init__(self, model, geometric_fit: Identification, obs: Observations, folds: np.ndarray,
                 prior_mm: float):
        self.model, self.geometric_fit, self.obs, self.folds, self.prior_mm = model, geometric_fit, obs, folds, prior_mm
        self.baseline_residuals_mm = geometric_fit.residuals_mm
        _, self.jacobian_x, self.jacobian_q = jacobian(geometric_fit.layout, geometric_fit.x, obs, with_joints=True)
        self.geometry_columns = self.jacobian_x[:, :, geometric_fit.free]
        flat = self.geometry_columns.reshape(-1, self.n_geometry)
        self.geometry_basis = identifiability.nuisance_basis(flat / column_scale(flat),
                                                             np.ones(self.n_geometry, bool))
        self._term_columns: dict[int, np.ndarray] = {}

    @property
    def n_geometry(self) -> int:
        return self.geometry_columns.shape[2]

    def heldout_errors_mm(self, terms: tuple[Term, ...]) -> np.ndarray:
        """(N,) held-out error of each measurement with geometry and these terms."""
        columns = [self.term_columns(t) for t in terms]
        term_columns = np.concatenate(columns, axis=2) if columns else np.zeros((len(self.obs), 3, 0))
        n_theta = term_columns.shape[2]
        j = np.concatenate([self.geometry_columns, term_columns], axis=2)
        flat = j.reshape(-1, j.shape[2])
        geometry = np.r_[np.ones(self.n_geometry, bool), np.zeros(n_theta, bool)]
        basis = (self.geometry_basis[0], np.r_[self.geometry_basis[1], np.zeros(n_theta, bool)])
        estimated = identifiability.analyse(flat / column_scale(flat), geometry, ~geometry, noise_mm=None,
                                            prior_mm=self.prior_mm, basis=basis, with_condition=False).keep
        estimated[: self.n_geometry] = True
        return crossval.one_step_heldout(j[:, :, estimated], self.baseline_residuals_mm, self.folds)[0]

    def is_nested(self, inner: Term, outer: Term) -> bool:
        """Does geometry + outer span every column of inner? (Then outer explains nothing
        that inner cannot, wherever the two tie.)"""
        a = np.concatenate([self.geometry_columns, self.term_columns(outer)], axis=2)
        a = a.reshape(-1, a.shape[2])
        b = self.term_columns(inner).reshape(len(a), -1)
        coef = np.linalg.lstsq(a, b, rcond=None)[0]
        return bool(np.linalg.norm(a @ coef - b) <= NESTED_RTOL * np.linalg.norm(b))

    def term_columns(self, term: Term) -> np.ndarray:
        """d p / d theta of a term at the geometric fit (N, 3, m)."""
        if id(term) not in self._term_columns:
            self._term_columns[id(term)] = self._linear_columns(term)
        return self._term_columns[id(term)]

    def _linear_columns(self, term: Term) -> np.ndarray:
        fit, obs = self.geometric_fit, self.obs
        if term.model is not None:  # one new rigid parameter: its Jacobian column in the new layout
            layout = Layout(term.model, obs.target_names)
            x = embed(fit.x, fit.layout.n_kin, term.model.n_params - self.model.n_params)
            _, j = jacobian(layout, x, obs)
            return j[:, :, self.model.n_params: term.model.n_params]
        columns = np.zeros((len(obs), 3, term.size))
        if term.joint_basis is not None:
            columns += np.einsum("nij,njm->nim", self.jacobian_q, term.joint_basis)
        if term.cart_basis is not None:
            columns += term.cart_basis
        if term.param_basis:
            columns += param_columns(self.jacobian_x, stack_param_bases(term.param_basis))
        return columns


def score_candidates(terms: Sequence[Term], scorer: LinearisedScorer) -> list[Scored]:
    """Each term scored alone with the geometry; best (lowest held-out mean) first."""
    x = scorer.geometric_fit.x
    ranked = [Scored(label=t.label(), cause=t.cause, where=t.where, heldout_errors=scorer.heldout_errors_mm((t,)),
                     theta=np.zeros(t.size), magnitude={}, x=x, terms=(t,))
              for t in terms]
    ranked.sort(key=lambda s: s.heldout_mean_mm)
    _prefer_single_place(ranked, lambda c: c.heldout_mean_mm, lambda c: c.terms[0])
    return ranked


# -- naming: which cause, if any, the data supports ---------------------------------------------------------


def name_cause(candidates: Sequence[Scored], baseline: Scored, scorer: LinearisedScorer) -> Naming:
    """The naming rule over candidates ranked best first.

    The best candidate is named when it beats geometry alone by MIN_GAIN and the
    best candidate of every other cause by MIN_MARGIN. Below MIN_GAIN the answer
    is ``none``; within MIN_MARGIN the tie is settled by ``_settle_tie``.
    """
    if not candidates:
        return Naming(named=None, candidates=(), margin=0.0)
    best = candidates[0]
    gain = 1.0 - best.heldout_mean_mm / baseline.heldout_mean_mm
    others = [c for c in candidates if c.cause != best.cause]
    margin = (others[0].heldout_mean_mm / best.heldout_mean_mm - 1.0) if others else 1.0
    if gain < MIN_GAIN:
        note = (f"best candidate {best.label} gains {100 * gain:.1f}% on held-out data, "
                f"below the {100 * MIN_GAIN:.0f}% needed to name it")
        return Naming(named=None, candidates=tuple(candidates), margin=margin, notes=(note,))
    if margin >= MIN_MARGIN:
        return Naming(named=best, candidates=tuple(candidates), margin=margin)
    return _settle_tie(best, others[0], candidates, baseline, margin, scorer)


def _settle_tie(best: Scored, runner_up: Scored, candidates: Sequence[Scored], baseline: Scored, margin: float,
                scorer: LinearisedScorer) -> Naming:
    """Two causes explain about as much. One explanation contained in the other: the
    simpler one is named. Two effects (together they beat either by MIN_GAIN): the best
    is named. Else the same structure, ambiguous: ``none``."""
    ranked = list(candidates)
    simpler, larger = sorted((best, runner_up), key=lambda c: sum(t.size for t in c.terms))
    if (1.0 - simpler.heldout_mean_mm / baseline.heldout_mean_mm >= MIN_GAIN
            and simpler.terms[0].size < larger.terms[0].size and scorer.is_nested(simpler.terms[0], larger.terms[0])):
        ranked.insert(0, ranked.pop(ranked.index(simpler)))
        note = (f"{larger.label} fits about as well only through terms that are the same as "
                f"{simpler.label}; the simpler explanation is named")
        return Naming(named=simpler, candidates=tuple(ranked), margin=margin, notes=(note,))
    pair_mean_mm = scorer.heldout_errors_mm(best.terms + runner_up.terms).mean()
    if pair_mean_mm < (1.0 - MIN_GAIN) * min(best.heldout_mean_mm, runner_up.heldout_mean_mm):
        note = (f"{best.label} and {runner_up.label} are both present: together they "
                f"reach {pair_mean_mm:.4f} mm held-out")
        return Naming(named=best, candidates=tuple(ranked), margin=margin, notes=(note,))
    note = (f"{best.label} and {runner_up.label} explain the data about equally well "
            f"(held-out errors {100 * margin:.1f}% apart, {100 * MIN_MARGIN:.0f}% needed)")
    return Naming(named=None, candidates=tuple(ranked), margin=margin, notes=(note,))


def find_second_effect(named: Scored, terms: Sequence[Term], candidates: Sequence[Scored],
                       scorer: LinearisedScorer) -> Scored | None:
    """With the named effect in the model, the candidate of another cause that lowers the
    held-out mean by MIN_GAIN more, or None."""
    with_named = [(scorer.heldout_errors_mm(named.terms + (t,)).mean(), t) for t in terms if t.cause != named.cause]
    with_named.sort(key=lambda pair: pair[0])
    _prefer_single_place(with_named, lambda pair: pair[0], lambda pair: pair[1])
    if not with_named or with_named[0][0] >= (1.0 - MIN_GAIN) * named.heldout_mean_mm:
        return None
    return next(c for c in candidates if c.terms == (with_named[0][1],))


def _prefer_single_place(ranked: list, error, term) -> None:
    """Parsimony, in place: a term spanning several joints must beat the best single-place
    term of its cause by MULTI_GAIN, else the single place goes first (it says *where*)."""
    if not ranked:
        return
    best = ranked[0]
    singles = [i for i, r in enumerate(ranked) if term(r).cause == term(best).cause and not term(r).multi]
    if singles and singles[0] != 0 and error(best) > (1.0 - MULTI_GAIN) * error(ranked[singles[0]]):
        ranked.insert(0, ranked.pop(singles[0]))


# -- fits: the geometric baseline, and geometry plus terms fitted in full -----------------------------------


def _geometric_baseline(model, obs, folds, options) -> Identification:
    """The geometric fit to compare against: the parameters above the noise, or every
    structurally identifiable one, whichever predicts held-out data better. (When an
    unmodelled effect dominates the residual, the noise criterion is too strict.)"""
    above_noise = identify(model, obs, IdentifyOptions(regularize="none", prior_mm=options.prior_mm))
    structural = identify(model, obs, IdentifyOptions(regularize="cv", prior_mm=options.prior_mm))
    if np.array_equal(above_noise.free, structural.free):
        return above_noise

    def heldout_mean_mm(fit: Identification) -> float:
        _, j = jacobian(fit.layout, fit.x, obs)
        return crossval.one_step_heldout(j[:, :, fit.free], fit.residuals_mm, folds)[0].mean()

    return min((above_noise, structural), key=heldout_mean_mm)


def _fit_in_full(model, geometric_fit: Identification, obs, folds, terms: tuple[Term, ...], prior_mm: float,
                 label: str) -> Scored:
    """Nonlinear fit of geometry plus terms; held-out errors and physical sizes."""
    layout, x, free = geometric_fit.layout, geometric_fit.x, geometric_fit.free
    structural = [t for t in terms if t.model is not None]
    if structural:  # a different rigid model: carry the geometric fit over into its layout
        extended_model = structural[-1].model
        extra = extended_model.n_params - model.n_params
        layout = Layout(extended_model, obs.target_names)
        x = embed(geometric_fit.x, geometric_fit.layout.n_kin, extra)
        free = embed(geometric_fit.free, geometric_fit.layout.n_kin, extra, fill=True)
    fit = fit_extended(layout, obs, x, free, tuple(t for t in terms if t.model is None), prior_mm)
    heldout_errors_mm = crossval.one_step_heldout(fit.jacobian, fit.residuals_mm, folds)[0]
    sizes = _physical_sizes(model, terms, fit)
    magnitude = sizes[terms[0].cause] if len(terms) == 1 else sizes
    # what the terms do at the targets: the fitted model with and without them
    without = fit.x.copy()
    for t in structural:
        without[model.n_params: t.model.n_params] = 0.0
    effect_mm = (fit.residuals_mm + obs.xyz_mm) - predict(layout, without, obs)
    if len(terms) == 1:
        # the size that needs no model to read: how far the effect moves the targets, less what a
        # geometric calibration absorbs anyway (the part the geometric columns can reproduce)
        n_free = int(free.sum())
        geometry_columns = fit.jacobian[:, :, :n_free].reshape(-1, n_free)
        absorbed = geometry_columns @ np.linalg.lstsq(geometry_columns, effect_mm.ravel(), rcond=None)[0]
        effect_mm = (effect_mm.ravel() - absorbed).reshape(-1, 3)
        magnitude = {**magnitude, "effect_beyond_geometry_rms_mm": float(np.sqrt(np.mean(
            np.sum(effect_mm**2, axis=1))))}
    return Scored(label=label, cause=terms[0].cause, where=terms[0].where, heldout_errors=heldout_errors_mm,
                  theta=fit.theta, magnitude=magnitude, x=fit.x, terms=terms, residuals=fit.residuals_mm,
                  effect_mm=effect_mm, joint_delta=fit.model.joint_delta(fit.theta))


def _physical_sizes(model, terms: tuple[Term, ...], fit: ExtendedFit) -> dict:
    """Each term's size in physical units (its cause's ``magnitude``), by cause."""
    sizes, col = {}, 0
    for t in terms:
        if t.model is not None:
            sizes[t.cause] = CAUSES[t.cause].magnitude(t, fit.x[model.n_params: t.model.n_params], None)
            continue
        theta = fit.theta[col: col + t.size]
        joint_delta = np.einsum("njm,m->nj", fit.model.bases.joint[:, :, col: col + t.size], theta)
        sizes[t.cause] = CAUSES[t.cause].magnitude(t, theta, joint_delta)
        col += t.size
    return sizes
