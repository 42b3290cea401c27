"""What is the rigid model getting wrong? Model-discrepancy analysis.

1. Fit the rigid geometric model (``identify``): the baseline.
2. For every candidate term of every named cause (``effects``), fit geometry and
   term jointly, linearised at the geometric fit (``LinearisedScorer``); the
   term's parameters are estimated only where the data can separate them from
   the geometry (same identifiability rule as ``identify``). A cause with places (joints, a
   periodic error's orders) offers one candidate: the places one forward search combines,
   chosen again inside each fold's training rows and scored by those choices (``selection``).
3. Score baseline and candidates on held-out data: grouped k-fold
   cross-validation, neighbouring configurations kept in one fold
   (``score_candidates``).
4. Name the best candidate only when it beats the baseline by MIN_GAIN and the
   best candidate of any other cause by MIN_MARGIN; else ``none``
   (``name_cause``, which also settles near-ties). Each cause competes with its
   preferred candidate (``contenders``: a single place unless several places beat it
   by MULTI_GAIN); the candidate list itself stays ordered by held-out score, and a
   preference that names another than the lowest-scored one is said in the grounds.
   A gain of MIN_GAIN that no cause wins is an effect whose cause is undecided
   (``Finding.undecided``), never a plain ``none``.
5. With the named term in the model, rank the rest again: a second effect
   (``find_second_effect``), and a fit of both. The named term, and the pair,
   are then fitted in full.

Steps 3 to 5's rules (the thresholds, the scored candidates and the naming) are :mod:`.naming`'s;
whether a finding holds on another data set, :mod:`.transfer`'s.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from cellcal.solvers.estimation import crossval, lsq
from cellcal.solvers.analysis import physical_sizes, plausibility, selection, ties
from cellcal.solvers.analysis.effects import CAUSES, Context, Term
from cellcal.solvers.identification.identify import Identification, IdentifyOptions, identify_variants
from cellcal.solvers.analysis.extended_model import ExtendedFit, embed, fit_extended
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian_chunks, predict
from cellcal.solvers.analysis.linearised_scorer import LinearisedScorer
from cellcal.solvers.analysis.naming import (MIN_GAIN, MIN_MARGIN, Scored, deciding_grounds, find_second_effect,
                                             name_cause, score_candidates)
from cellcal.solvers.analysis.robust_scoring import LINEAR, RobustScoring

NEIGHBOUR_RAD = crossval.NEIGHBOUR_RAD  # configurations this close share a fold


@dataclass(frozen=True)
class AnalyzeOptions:
    folds: int = 5
    seed: int = 0
    causes: tuple[str, ...] = tuple(CAUSES)
    prior_mm: float = 1.0
    loss: str = "linear"  # robust loss of every fit, as identify's; the held-out scores trimmed (robust_scoring)
    nested: bool = True  # a cause with places is scored by its selection made inside each fold (False: the
    #                      selection made on all rows, scored on the same folds: optimistic; for comparison)
    strict_sizes: bool = plausibility.STRICT  # a lead of implausible size never names its cause (``name_cause``)


@dataclass(frozen=True)
class Finding:
    cause: str
    where: dict
    magnitude: dict
    baseline: Scored
    extended: Scored
    candidates: tuple[Scored, ...]  # best (lowest held-out mean) first
    margin: float  # how much higher (fraction) the best other cause's held-out error is
    second: Scored | None = None  # second effect, fitted together with the first
    both: Scored | None = None
    seconds: float = 0.0
    notes: tuple[str, ...] = field(default_factory=tuple)
    joint_range_deg: tuple[tuple[float, float], ...] = ()  # angles the data cover, per joint
    indistinguishable: tuple = ()  # ties.Tied: explanations these data cannot tell apart, best first
    grounds: str = ""  # why one of them is named all the same, or why not the lowest-scored ("" when neither)
    scorer: object = field(default=None, repr=False, compare=False)  # LinearisedScorer, for the experiment design
    undecided: Scored | None = None  # cause "none" although this, the best contender, gains MIN_GAIN: an
    #                                  effect whose cause these data cannot decide (see indistinguishable)
    decide_by: str = ""  # with undecided: the experiment that decides, in words
    robot_class: object = None  # plausibility.RobotClass whose typical sizes judged the candidates
    decided_by: tuple[str, ...] = ()  # the grounds that decided the finding, as words of ``GROUNDS``

    @property
    def gain_pct(self) -> float:
        return 100.0 * (1.0 - self.extended.heldout_mean_mm / self.baseline.heldout_mean_mm)

    @property
    def shares_pct(self) -> tuple[float, float] | None:
        """With a second effect: each effect's share (percent) of the held-out gain both together reach
        over geometry alone, the named one's alone and what the second adds to it; None without."""
        if self.both is None:
            return None
        gain = self.baseline.heldout_mean_mm - self.both.heldout_mean_mm
        first = (self.baseline.heldout_mean_mm - self.extended.heldout_mean_mm) / gain if gain > 0 else 1.0
        return 100.0 * first, 100.0 * (1.0 - first)


def analyze(model, obs: Observations, ctx: Context, options: AnalyzeOptions = AnalyzeOptions(),
            progress=None, geometry=None) -> Finding:
    """Find, name and size the physical effect the rigid model misses (or ``none``).

    Candidates are ranked on the model linearised at the geometric fit (every
    effect here is a small perturbation of it); the named one, and the pair when
    a second effect shows, are then fitted in full.
    """
    started = time.perf_counter()
    say = progress or (lambda msg: None)
    folds = crossval.fold_ids(obs.q, options.folds, options.seed, NEIGHBOUR_RAD)
    # geometry: the geometric baseline when it is not identify's (point-form data: point_analysis.geometry,
    # whose point positions every fold estimates with the geometry)
    geometric_fit, nested_baseline = (geometry, None) if geometry is not None else \
        _geometric_baseline(model, obs, folds, options)
    parts = {cause: CAUSES[cause].terms(model, geometric_fit.layout, geometric_fit.x, obs,
                                        dataclasses.replace(ctx, folds=folds))
             for cause in options.causes}
    scorer = LinearisedScorer(model, geometric_fit, obs, folds, options.prior_mm,
                              [t for cause in options.causes for t in parts[cause]],
                              RobustScoring.of(options.loss, geometric_fit.residuals_mm))
    # a cause with places offers the forward search's choice (``selection``), scored by the choices made
    # inside each fold (nested); the others' terms compete as they are
    places = {cause: CAUSES[cause].search_places(parts[cause]) for cause in options.causes}
    places = {cause: p for cause, p in places.items() if p is not None}
    scores = selection.Scores(scorer)
    searched = [s for s in (selection.select(CAUSES[cause], *p, scores) for cause, p in places.items()) if s]
    terms = [t for cause in options.causes if cause not in places
             for t in CAUSES[cause].compose(parts[cause], scorer)]
    say(f"geometric model: {len(obs)} measurements, residual "
        f"{np.linalg.norm(scorer.baseline_residuals_mm, axis=1).mean():.3f} mm mean")

    # geometry alone and every candidate in one pass over the rows
    errors = scorer.heldout_errors_of_steps(np.concatenate(
        [scorer.steps(())] + [scorer.steps((t,)) for t in terms]
        + [selection.nested_steps(scores, s) if options.nested else scorer.steps((s.term,)) for s in searched]))
    terms = terms + [s.term for s in searched]
    # the baseline as its choice of variant made inside each fold scores it (the candidates keep the
    # all-rows choice as their geometry: the same linearisation point for every one)
    base_errors = nested_baseline if nested_baseline is not None and options.nested else errors[0]
    baseline = Scored(label="geometry only", cause="none", where={}, heldout_errors=base_errors,
                      theta=np.zeros(0), magnitude={}, x=geometric_fit.x, residuals=scorer.baseline_residuals_mm,
                      trim=scorer.robust.trim)
    say(f"held-out mean, geometry only: {baseline.heldout_mean_mm:.3f} mm")
    candidates = score_candidates(terms, scorer, errors[1:])
    say(f"scored {len(candidates)} candidates")
    robot_class = plausibility.robot_class(model)  # every candidate's size against what arms of its class show
    candidates = plausibility.judge_candidates(candidates, scorer, robot_class.name)
    naming = name_cause(candidates, baseline, scorer, options.strict_sizes)
    tied = ties.tied_explanations(naming, baseline, scorer, MIN_GAIN, MIN_MARGIN,
                                  lambda s: _fit_in_full(model, geometric_fit, obs, folds, s.terms, options.prior_mm,
                                                         s.label, scorer.robust).magnitude, robot_class.name,
                                  frozenset(id(s.term) for s in searched) if options.nested else frozenset())
    naming = tied.naming
    undecided = None
    leading = sorted(naming.contenders + naming.set_aside, key=lambda s: s.heldout_mean_mm)
    if naming.named is None and leading and 1.0 - leading[0].heldout_mean_mm / baseline.heldout_mean_mm >= MIN_GAIN:
        undecided = leading[0]
    grounds = "; ".join(g for g in (naming.plausibility, tied.grounds,
                                    naming.grounds if naming.named is not None else "") if g)

    extended, second, both = baseline, None, None
    if naming.named is not None:
        named = naming.named
        chosen = next((s for s in searched if named.terms[0] is s.term), None)  # named by a search: its choices
        second, together = find_second_effect(named, terms, places, scores, options.nested,
                                              None if chosen is None else chosen.per_fold)
        if second is not None:
            both = _fit_in_full(model, geometric_fit, obs, folds, named.terms + second.terms, options.prior_mm,
                                f"{named.label} + {second.label}", scorer.robust)
            if options.nested and (chosen is not None or second.cause in places):
                # chosen inside the folds: scored as it was found, each fold's own choices on that fold
                both = dataclasses.replace(both, heldout_errors=together, prior_weights=())
        extended = _fit_in_full(model, geometric_fit, obs, folds, named.terms, options.prior_mm, named.label,
                                scorer.robust)
        if options.nested and any(named.terms[0] is s.term for s in searched):
            # what was chosen by a search is scored as it was named: each fold's own choice on that fold
            extended = dataclasses.replace(extended, heldout_errors=named.heldout_errors, prior_weights=())
        elif geometry is not None:  # the full fit holds the points: score as the candidates were, points refit
            extended = dataclasses.replace(extended, heldout_errors=scorer.heldout_errors_mm(named.terms),
                                           prior_weights=())
        if geometry is not None and both is not None:
            both = dataclasses.replace(both, heldout_errors=scorer.heldout_errors_mm(named.terms + second.terms))
    say(f"analysis done in {time.perf_counter() - started:.1f} s")
    return Finding(
        cause=extended.cause, where=extended.where, magnitude=extended.magnitude, baseline=baseline,
        extended=extended, candidates=naming.candidates, margin=float(naming.margin), second=second, both=both,
        seconds=time.perf_counter() - started, notes=naming.notes,
        joint_range_deg=tuple((float(lo), float(hi)) for lo, hi in np.rad2deg([obs.q.min(0), obs.q.max(0)]).T),
        indistinguishable=tied.entries, grounds=grounds, scorer=scorer, undecided=undecided,
        robot_class=robot_class, decided_by=deciding_grounds(naming, tied),
        decide_by=ties.decide_by(tied.entries) if undecided is not None else "")


def heldout_with_terms(model, obs: Observations, terms: Sequence[Term],
                       options: AnalyzeOptions = AnalyzeOptions()) -> np.ndarray:
    """(N,) held-out errors of geometry plus these terms, scored as ``analyze`` scores its candidates
    (same folds, same geometric fit): what a model of known structure reaches on these data."""
    folds = crossval.fold_ids(obs.q, options.folds, options.seed, NEIGHBOUR_RAD)
    geometric_fit = _geometric_baseline(model, obs, folds, options)[0]
    return LinearisedScorer(model, geometric_fit, obs, folds, options.prior_mm, terms).heldout_errors_mm(tuple(terms))


# -- fits: the geometric baseline, and geometry plus terms fitted in full -----------------------------------


def _geometric_baseline(model, obs, folds, options) -> tuple[Identification, np.ndarray | None]:
    """The geometric fit to compare against: the parameters above the noise, or every
    structurally identifiable one, whichever predicts held-out data better. (When an
    unmodelled effect dominates the residual, the noise criterion is too strict.)

    Returns (the fit chosen on all rows' folds, the candidates' linearisation point; the baseline's
    held-out errors (N,) with the choice made again inside each fold's training rows, or None
    when the two variants are one). Chosen on the same folds it is scored on, the baseline would
    look better than a user would find it, which errs against naming an effect."""
    variants = (IdentifyOptions(regularize="none", prior_mm=options.prior_mm, loss=options.loss),
                IdentifyOptions(regularize="cv", prior_mm=options.prior_mm, loss=options.loss))
    above_noise, structural = identify_variants(model, obs, variants)  # one nominal and first fit for both
    if np.array_equal(above_noise.free, structural.free):
        return above_noise, None

    robust = RobustScoring.of(options.loss, above_noise.residuals_mm)

    def scored(fit: Identification):
        def columns():
            return ((rows, j[:, :, fit.free]) for rows, _, j in jacobian_chunks(fit.layout, fit.x, obs))
        factors = None
        for rows, j in columns():
            factors = factors or crossval.FoldFactors(folds, j.shape[2])
            factors.add(rows, *robust.weighted(rows, j, fit.residuals_mm[rows]))
        errors = crossval.heldout_errors(columns(), fit.residuals_mm, factors, factors.steps(np.arange(factors.p)))[0]
        return errors, np.array([factors.inner_sse(k) for k in range(len(factors.ids))])

    (e_noise, inner_noise), (e_struct, inner_struct) = scored(above_noise), scored(structural)
    fit = above_noise if robust.mean_mm(e_noise) <= robust.mean_mm(e_struct) else structural
    fold_index = np.unique(np.asarray(folds), return_inverse=True)[1].ravel()
    nested = np.where((inner_noise <= inner_struct)[fold_index], e_noise, e_struct)
    return fit, nested


def _heldout(columns, residuals_mm: np.ndarray, folds: np.ndarray, robust: RobustScoring = LINEAR,
             effect_at: np.ndarray | None = None, weights: list | None = None) -> np.ndarray:
    """(N,) held-out errors of a linearised model with every column estimated. columns()
    yields (rows, Jacobian rows (n, 3, p)) over all rows in blocks; it is called twice.
    effect_at: the effect parameters' values at the linearisation point, after the geometry's
    columns: their prior "no effect" is weighed by a nested ridge (``crossval.ridge_steps``),
    each fold's weight appended to `weights`."""
    factors = None
    for rows, j in columns():
        factors = factors or crossval.FoldFactors(folds, j.shape[2])
        factors.add(rows, *robust.weighted(rows, j, residuals_mm[rows]))
    if effect_at is None or not len(effect_at):
        steps = factors.steps(np.arange(factors.p))
    else:
        n_geometry = factors.p - len(effect_at)
        penalised = np.arange(factors.p) >= n_geometry
        steps, chosen = crossval.ridge_steps(factors, np.arange(factors.p), penalised,
                                             np.r_[np.zeros(n_geometry), effect_at])
        if weights is not None:
            weights.extend(float(w) for w in chosen)
    return crossval.heldout_errors(columns(), residuals_mm, factors, steps)[0]


def _fit_in_full(model, geometric_fit: Identification, obs, folds, terms: tuple[Term, ...], prior_mm: float,
                 label: str, robust: RobustScoring = LINEAR) -> Scored:
    """Nonlinear fit of geometry plus terms; held-out errors and physical sizes."""
    layout, x, free = geometric_fit.layout, geometric_fit.x, geometric_fit.free
    structural = [t for t in terms if t.model is not None]
    if structural:  # a different rigid model: carry the geometric fit over into its layout
        extended_model = structural[-1].model
        extra = extended_model.n_params - model.n_params
        layout = Layout(extended_model, obs.target_names)
        x = embed(geometric_fit.x, geometric_fit.layout.n_kin, extra)
        free = embed(geometric_fit.free, geometric_fit.layout.n_kin, extra, fill=True)
    fit = fit_extended(layout, obs, x, free, tuple(t for t in terms if t.model is None), prior_mm, robust.loss,
                       robust.f_scale_mm)
    sizes = _physical_sizes(model, terms, fit)
    magnitude = sizes[terms[0].cause] if len(terms) == 1 else sizes
    details = _details(terms, fit, obs)
    details = details.get(terms[0].cause) if len(terms) == 1 else (details or None)
    # what the terms do at the targets: the fitted model with and without them
    without = fit.x.copy()
    for t in structural:
        without[model.n_params: t.model.n_params] = 0.0
    effect_mm = (fit.residuals_mm + obs.xyz_mm) - predict(layout, without, obs)
    effect_at = fit.z[fit.estimated][fit.model.n_free:]  # the effect's estimated parameters, fitted
    weights: list[float] = []
    if len(terms) != 1:
        heldout_errors_mm = _heldout(fit.jacobian_chunks, fit.residuals_mm, folds, robust, effect_at, weights)
    else:
        # the size that needs no model to read: how far the effect moves the targets, less what a
        # geometric calibration absorbs anyway (the part the geometric columns can reproduce)
        n_free = int(free.sum())
        absorbed = lsq.RFactor(n_free + 1)
        for rows, j in fit.jacobian_chunks():
            absorbed.add(np.concatenate([j[:, :, :n_free].reshape(-1, n_free), effect_mm[rows].reshape(-1, 1)], 1))
        r = absorbed.r
        coef = np.linalg.lstsq(r[:n_free, :n_free], r[:n_free, n_free], rcond=None)[0]
        beyond = np.empty_like(effect_mm)

        def columns():  # the held-out pass also takes what the geometry absorbs off the effect
            for rows, j in fit.jacobian_chunks():
                beyond[rows] = effect_mm[rows] - j[:, :, :n_free] @ coef
                yield rows, j

        heldout_errors_mm = _heldout(columns, fit.residuals_mm, folds, robust, effect_at, weights)
        effect_mm = beyond
        magnitude = {**magnitude, "effect_beyond_geometry_rms_mm": float(np.sqrt(np.mean(
            np.sum(effect_mm**2, axis=1))))}
    return Scored(label=label, cause=terms[0].cause, where=terms[0].where, heldout_errors=heldout_errors_mm,
                  trim=robust.trim, theta=fit.theta, magnitude=magnitude, x=fit.x, terms=terms,
                  residuals=fit.residuals_mm, effect_mm=effect_mm, joint_delta=fit.model.joint_delta(fit.theta),
                  details=details, prior_weights=tuple(weights))


def _details(terms: tuple[Term, ...], fit: ExtendedFit, obs) -> dict:
    """``Cause.details`` of each fitted term that has any, by cause."""
    out, col = {}, 0
    for t in (t for t in terms if t.model is None):
        found = CAUSES[t.cause].details(t, fit.theta[col: col + t.size], obs.q)
        if found is not None:
            out[t.cause] = found
        col += t.size
    return out


def _physical_sizes(model, terms: tuple[Term, ...], fit: ExtendedFit) -> dict:
    """Each term's size in physical units (its cause's ``magnitude``), by cause."""
    sizes, col, cov_root = {}, 0, None
    for t in terms:
        if t.model is not None:
            sizes[t.cause] = CAUSES[t.cause].magnitude(t, fit.x[model.n_params: t.model.n_params], None)
            continue
        theta = fit.theta[col: col + t.size]
        own = np.zeros_like(fit.theta)
        own[col: col + t.size] = theta
        joint_delta = fit.model.bases.joint.delta(own)
        sizes[t.cause] = CAUSES[t.cause].magnitude(t, theta, joint_delta)
        places = CAUSES[t.cause].places(t)
        if places is not None:  # each place's size where the data determine it, else its group's
            cov_root = physical_sizes.theta_covariance_root(fit) if cov_root is None else cov_root
            entries, flat = physical_sizes.place_sizes(places[0], theta, cov_root[col: col + t.size], places[1])
            sizes[t.cause] = {**sizes[t.cause], **flat, "places": entries}
        col += t.size
    return sizes
