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
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from cellcal.solvers.estimation import crossval, lsq
from cellcal.solvers.analysis import physical_sizes, plausibility, selection, ties
from cellcal.solvers.analysis.effects import CAUSES, Context, JointBasis, Term
from cellcal.solvers.identification.identify import Identification, IdentifyOptions, identify, identify_variants
from cellcal.solvers.analysis.extended_model import ExtendedFit, ExtendedModel, embed, fit_extended, norm_scale
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian_chunks, predict
from cellcal.solvers.analysis.linearised_scorer import LinearisedScorer
from cellcal.solvers.analysis.robust_scoring import LINEAR, RobustScoring, trimmed_mean

MIN_GAIN = 0.10  # held-out mean error must drop by 10% against geometry alone
MIN_MARGIN = 0.08  # ... and the best other cause must stay 8% above the named one
MULTI_GAIN = 0.10  # a several-joint term must beat its cause's best single joint by this much
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
    details: dict | None = None  # what the fitted terms need for later use beyond their sizes (by cause
    #                              when several), see ``Cause.details``

    trim: float = 0.0  # fraction of the largest held-out errors the score leaves out (robust loss)
    judged: object = None  # plausibility.Judgement of its linearised size (None: not judged)
    prior_weights: tuple = ()  # fitted in full: each fold's weight of the prior "no effect" (``_heldout``)

    @property
    def heldout_mean_mm(self) -> float:
        """The held-out score: the mean error (without the largest `trim` fraction under a robust loss)."""
        return float(trimmed_mean(self.heldout_errors, self.trim))


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


@dataclass(frozen=True)
class Naming:
    """What the naming rule decided."""

    named: Scored | None  # None: the answer is ``none``
    candidates: tuple[Scored, ...]  # best (lowest held-out mean) first, whatever was named
    margin: float  # how much higher (fraction) the best other cause's held-out error is
    notes: tuple[str, ...] = ()
    tie: str = ""  # how a near-tie was settled: "nested", "both" (two effects), "ambiguous", "unseparated" or
    #                "unsteady" (a nested lead the models chosen on all rows do not bear out: ``ties._unsteady``)
    contenders: tuple[Scored, ...] = ()  # each cause's preferred candidate, best first (``contenders``);
    #                                      () for made-up namings: then the first single place of each cause
    grounds: str = ""  # why the named one is not the lowest-scored candidate ("" when it is, or none is named)
    set_aside: tuple[Scored, ...] = ()  # contenders whose size is implausible for the robot's class, best first
    plausibility: str = ""  # the grounds those were set aside on, when one of them led ("" else)


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
        second = find_second_effect(named, terms, places, scores, options.nested)
        if second is not None:
            both = _fit_in_full(model, geometric_fit, obs, folds, named.terms + second.terms, options.prior_mm,
                                f"{named.label} + {second.label}", scorer.robust)
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
        robot_class=robot_class, decided_by=_decided_by(naming, tied),
        decide_by=ties.decide_by(tied.entries) if undecided is not None else "")


def heldout_with_terms(model, obs: Observations, terms: Sequence[Term],
                       options: AnalyzeOptions = AnalyzeOptions()) -> np.ndarray:
    """(N,) held-out errors of geometry plus these terms, scored as ``analyze`` scores its candidates
    (same folds, same geometric fit): what a model of known structure reaches on these data."""
    folds = crossval.fold_ids(obs.q, options.folds, options.seed, NEIGHBOUR_RAD)
    geometric_fit = _geometric_baseline(model, obs, folds, options)[0]
    return LinearisedScorer(model, geometric_fit, obs, folds, options.prior_mm, terms).heldout_errors_mm(tuple(terms))


def score_candidates(terms: Sequence[Term], scorer: LinearisedScorer, errors=None) -> list[Scored]:
    """Each term scored alone with the geometry; best (lowest held-out mean) first, nothing else
    considered (the naming's preferences are ``contenders``').
    errors: the terms' held-out errors when already computed (one row per term)."""
    x = scorer.geometric_fit.x
    if errors is None:
        errors = scorer.heldout_errors_many([(t,) for t in terms])
    ranked = [Scored(label=t.label(), cause=t.cause, where=t.where, heldout_errors=e,
                     theta=np.zeros(t.size), magnitude={}, x=x, terms=(t,), trim=scorer.robust.trim)
              for t, e in zip(terms, errors)]
    ranked.sort(key=lambda s: s.heldout_mean_mm)
    return ranked


def contenders(candidates: Sequence[Scored]) -> list[Scored]:
    """Each cause's candidate in the contest between causes, best (lowest held-out mean) first: its
    best-scored one, or its best single place when that scores within MULTI_GAIN of it (parsimony:
    a single place says *where*)."""
    by_cause: dict[str, list[Scored]] = {}
    for c in sorted(candidates, key=lambda s: s.heldout_mean_mm):
        by_cause.setdefault(c.cause, []).append(c)
    out = []
    for ranked in by_cause.values():
        _prefer_single_place(ranked, lambda c: c.heldout_mean_mm, lambda c: c.terms[0])
        out.append(ranked[0])
    return sorted(out, key=lambda s: s.heldout_mean_mm)


# -- naming: which cause, if any, the data supports ---------------------------------------------------------


def name_cause(candidates: Sequence[Scored], baseline: Scored, scorer: LinearisedScorer,
               strict_sizes: bool | None = None) -> Naming:
    """The naming rule over the candidates (any order; the Naming lists them best first).

    Each cause competes with its ``contenders`` entry. The best contender is named when
    it beats geometry alone by MIN_GAIN and the contender of every other cause by
    MIN_MARGIN. Below MIN_GAIN the answer is ``none``; within MIN_MARGIN the tie is
    settled by ``_settle_tie``. strict_sizes (None: ``plausibility.STRICT``): a lead of a size beyond
    what arms of the robot's class show names nothing even when no plausible explanation comes close.
    """
    strict_sizes = plausibility.STRICT if strict_sizes is None else strict_sizes
    if not candidates:
        return Naming(named=None, candidates=(), margin=0.0)
    ranked = tuple(sorted(candidates, key=lambda s: s.heldout_mean_mm))
    every = tuple(contenders(ranked))
    # a size beyond what arms of the robot's class show is a reason against (``plausibility``): such a lead
    # does not name its cause when an explanation of plausible size comes within MIN_MARGIN of it (and gains
    # MIN_GAIN) -- the plausible contenders compete; when none does, the data prefer the lead clearly: it
    # competes all the same with its size said (``strict_sizes``: nothing is named then)
    aside = tuple(c for c in every if c.judged is not None and not c.judged.plausible)
    rivals = tuple(c for c in every if all(c is not a for a in aside))
    leading = [a for a in aside if (not rivals or a.heldout_mean_mm < rivals[0].heldout_mean_mm)
               and 1.0 - a.heldout_mean_mm / baseline.heldout_mean_mm >= MIN_GAIN]
    why_aside = "; ".join(f"{a.label} leads at {a.heldout_mean_mm:.4f} mm held-out but is set aside: it "
                          f"{a.judged.text()}" for a in leading)
    close = [r for r in rivals if leading and 1.0 - r.heldout_mean_mm / baseline.heldout_mean_mm >= MIN_GAIN
             and r.heldout_mean_mm < (1.0 + MIN_MARGIN) * leading[0].heldout_mean_mm]
    if leading and not close:
        lead = leading[0]
        if strict_sizes:
            why_aside = (f"{lead.label} leads at {lead.heldout_mean_mm:.4f} mm held-out but is set aside: it "
                         f"{lead.judged.text()}, and no explanation of a plausible size comes within "
                         f"{100 * MIN_MARGIN:.0f}% of it")
            return Naming(named=None, candidates=ranked, margin=0.0, notes=(why_aside,), contenders=rivals,
                          set_aside=aside, plausibility=why_aside)
        why_aside = (f"{lead.label} {lead.judged.text()}, but no explanation of a plausible size comes within "
                     f"{100 * MIN_MARGIN:.0f}% of it: it competes all the same")
        rivals, aside = every, ()
    if not rivals:
        note = "every explanation needs a size beyond what arms of this class show: none is named"
        return Naming(named=None, candidates=ranked, margin=0.0, notes=(note,), set_aside=aside,
                      plausibility=why_aside)
    best = rivals[0]
    gain = 1.0 - best.heldout_mean_mm / baseline.heldout_mean_mm
    margin = (rivals[1].heldout_mean_mm / best.heldout_mean_mm - 1.0) if len(rivals) > 1 else 1.0
    lowest = ranked[0]
    grounds = ""
    if lowest is not best and lowest.cause == best.cause:
        grounds = (f"{best.label} rather than {lowest.label} ({lowest.heldout_mean_mm:.4f} mm held-out): several "
                   f"places must beat the best single place of their cause by {100 * MULTI_GAIN:.0f}% "
                   f"({100 * (1.0 - lowest.heldout_mean_mm / best.heldout_mean_mm):.1f}% here), and a single place "
                   f"says where")
    if gain < MIN_GAIN:
        note = (f"best candidate {best.label} gains {100 * gain:.1f}% on held-out data, "
                f"below the {100 * MIN_GAIN:.0f}% needed to name it")
        return Naming(named=None, candidates=ranked, margin=margin, notes=(note,), contenders=rivals,
                      set_aside=aside, plausibility=why_aside)
    if margin >= MIN_MARGIN:
        return Naming(named=best, candidates=ranked, margin=margin, contenders=rivals, grounds=grounds,
                      set_aside=aside, plausibility=why_aside)
    return dataclasses.replace(_settle_tie(best, rivals[1], ranked, baseline, margin, scorer), contenders=rivals,
                               grounds=grounds, set_aside=aside, plausibility=why_aside)


# The grounds a finding can be decided on (``Finding.decided_by``): the held-out gain over geometry alone
# (MIN_GAIN), the margin over every other cause (MIN_MARGIN), a single place preferred to several
# (MULTI_GAIN), the simpler of two nested explanations, two effects present together, a tie the data
# leave open, and the physical plausibility of the sizes needed (``plausibility``).
GROUNDS = ("gain", "margin", "single place", "nested", "two effects", "tie", "plausibility")


def _decided_by(naming: Naming, tied) -> tuple[str, ...]:
    """The words of GROUNDS that decided: what named the finding, or what left it ``none``."""
    out = ["gain"]  # what is named gains MIN_GAIN; below it nothing is
    if naming.named is not None and naming.tie == "":
        out.append("margin")
    if naming.named is not None and naming.grounds:
        out.append("single place")
    out += {"nested": ["nested"], "both": ["two effects"], "ambiguous": ["tie"], "unseparated": ["tie"],
            "unsteady": ["tie"]}.get(
        naming.tie, [])
    if tied.entries and naming.named is None:
        out.append("tie")
    if naming.plausibility or tied.grounds.startswith("named on physical plausibility"):
        out.append("plausibility")
    return tuple(dict.fromkeys(out))


def _settle_tie(best: Scored, runner_up: Scored, candidates: Sequence[Scored], baseline: Scored, margin: float,
                scorer: LinearisedScorer) -> Naming:
    """Two causes explain about as much. One explanation contained in the other: the
    simpler one is named. Two effects (together they beat either by MIN_GAIN): the best
    is named. Else the same structure, ambiguous: ``none``. The candidates keep their order."""
    ranked = tuple(candidates)
    simpler, larger = sorted((best, runner_up), key=lambda c: sum(t.size for t in c.terms))
    if (1.0 - simpler.heldout_mean_mm / baseline.heldout_mean_mm >= MIN_GAIN
            and simpler.terms[0].size < larger.terms[0].size and scorer.is_nested(simpler.terms[0], larger.terms[0])):
        note = (f"{larger.label} fits about as well only through terms that are the same as "
                f"{simpler.label}; the simpler explanation is named")
        return Naming(named=simpler, candidates=ranked, margin=margin, notes=(note,), tie="nested")
    pair_mean_mm = float(trimmed_mean(scorer.heldout_errors_mm(best.terms + runner_up.terms), best.trim))
    if pair_mean_mm < (1.0 - MIN_GAIN) * min(best.heldout_mean_mm, runner_up.heldout_mean_mm):
        note = (f"{best.label} and {runner_up.label} are both present: together they "
                f"reach {pair_mean_mm:.4f} mm held-out")
        return Naming(named=best, candidates=ranked, margin=margin, notes=(note,), tie="both")
    note = (f"{best.label} and {runner_up.label} explain the data about equally well "
            f"(held-out errors {100 * margin:.1f}% apart, {100 * MIN_MARGIN:.0f}% needed)")
    return Naming(named=None, candidates=ranked, margin=margin, notes=(note,), tie="ambiguous")


def find_second_effect(named: Scored, terms: Sequence[Term], places: dict, scores: selection.Scores,
                       nested: bool = True) -> Scored | None:
    """With the named effect in the model, the candidate of another cause that lowers the
    held-out mean by MIN_GAIN more, or None; scored alone. A cause with places is searched
    again with the named effect in the model (the same forward search, nested as the first)."""
    scorer = scores.scorer
    others = [t for t in terms if t.cause != named.cause and t.extra.get("all", True)]
    searched = [s for s in (selection.select(CAUSES[cause], *p, scores, base=named.terms)
                            for cause, p in places.items() if cause != named.cause) if s]
    if not others and not searched:
        return None
    steps = ([scorer.steps(named.terms + (t,)) for t in others]
             + [selection.nested_steps(scores, s, named.terms) if nested else scorer.steps(named.terms + (s.term,))
                for s in searched])
    candidates = others + [s.term for s in searched]
    errors = scorer.heldout_errors_of_steps(np.concatenate(steps + [scorer.steps((t,)) for t in candidates]))
    with_named = [(float(trimmed_mean(e, named.trim)), t, alone)
                  for e, t, alone in zip(errors, candidates, errors[len(candidates):])]
    with_named.sort(key=lambda entry: entry[0])
    _prefer_single_place(with_named, lambda entry: entry[0], lambda entry: entry[1])
    if not with_named or with_named[0][0] >= (1.0 - MIN_GAIN) * named.heldout_mean_mm:
        return None
    _, term, alone = with_named[0]
    return score_candidates([term], scorer, [alone])[0]


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


# -- transfer: does the effect fitted on one data set hold on another? ---------------------------------------


class TransferError(ValueError):
    """The second data set cannot test the finding (its message says what is missing)."""


@dataclass(frozen=True)
class Transfer:
    """The finding of data set A tried on data set B (another time, pose set or target).

    Kinematics (and the effect's parameters) as fitted on A; only what B must set itself,
    the instrument -> base frame and the target offsets, fitted on B."""

    baseline_errors_mm: np.ndarray  # (M,) B's errors with A's geometric fit
    extended_errors_mm: np.ndarray | None  # (M,) with A's geometry + effect fit; None: nothing named on A
    carried: str  # label of the effect carried over ("" when none)
    coverage_per_joint: tuple[float, ...]  # fraction of B's rows whose angle lies within A's range, per joint
    coverage_all: float  # fraction of B's rows with every joint within A's ranges
    note: str = ""

    @property
    def baseline_mean_mm(self) -> float:
        return float(self.baseline_errors_mm.mean())

    @property
    def extended_mean_mm(self) -> float | None:
        return None if self.extended_errors_mm is None else float(self.extended_errors_mm.mean())

    @property
    def gain_pct(self) -> float | None:
        if self.extended_errors_mm is None:
            return None
        return 100.0 * (1.0 - self.extended_mean_mm / self.baseline_mean_mm)


def transfer(model, finding: Finding, obs_a: Observations, obs_b: Observations, ctx_b: Context,
             loss: str = "linear") -> Transfer:
    """Score A's finding on B: A's geometric fit, and A's fit of geometry plus the named effect,
    each with B's frame and target offsets refitted on B (everything else as on A); B's rows
    inside A's joint ranges (``coverage``). When B cannot show the effect (it leaves a place of
    the effect without the motion its basis needs) only the geometry is scored, and the note says why."""
    lo, hi = obs_a.q.min(0), obs_a.q.max(0)
    inside = (obs_b.q >= lo) & (obs_b.q <= hi)
    start = identify(model, obs_b)  # B's own fit: where its frame and targets start from
    layout = Layout(model, obs_b.target_names)
    x_geo = np.concatenate([finding.baseline.x[: model.n_params], start.x[layout.n_kin:]])
    baseline = _frame_refit(layout, obs_b, x_geo, (), np.zeros(0), loss)
    extended, carried, note = None, "", ""
    if finding.cause == "none":
        note = ("no effect named on the first data set: nothing to carry over; the geometric fit alone is "
                "scored on the second")
    else:
        named = finding.extended
        ext_layout, x_ext = layout, x_geo.copy()
        structural = [t for t in named.terms if t.model is not None]
        if structural:  # a different rigid model: its extra parameters as fitted on A
            ext_layout = Layout(structural[-1].model, obs_b.target_names)
            x_ext = np.concatenate([named.x[: ext_layout.n_kin], start.x[layout.n_kin:]])
        else:
            x_ext[: model.n_params] = named.x[: model.n_params]
        carried = named.label
        try:
            terms = tuple(_term_on_rows(t, model, layout, x_ext, obs_b, ctx_b) for t in named.terms
                          if t.model is None)
        except TransferError as exc:  # B cannot show the effect: the geometry alone is scored, and why said
            carried, note = "", str(exc)
        else:
            extended = _frame_refit(ext_layout, obs_b, x_ext, terms, named.theta, loss)
    return Transfer(baseline, extended, carried, tuple(float(f) for f in inside.mean(0)),
                    float(inside.all(1).mean()), note)


def _term_on_rows(term: Term, model, layout: Layout, x: np.ndarray, obs: Observations, ctx: Context) -> Term:
    """The same term (same parameters, same meaning of theta) with its basis at other rows."""
    if term.extra.get("parts"):  # several single parts side by side (cyclic orders of several joints)
        parts = [_term_on_rows(p, model, layout, x, obs, ctx) for p in term.extra["parts"]]
        basis = JointBasis.side_by_side([(p.joint_basis, p.size) for p in parts], len(obs), model.n_joints)
        return dataclasses.replace(term, joint_basis=basis, extra={})
    basis = term.joint_basis
    if hasattr(basis, "values_of") and term.cart_basis is None and not term.param_basis:
        joint = int(np.nonzero(basis.mix)[1][0])  # a function of one joint's angle: evaluate it at B's angles
        return dataclasses.replace(term, joint_basis=JointBasis.of_angle(obs.q[:, joint], basis.values_of, joint,
                                                                         model.n_joints, term.size))
    same = [t for t in CAUSES[term.cause].terms(model, layout, x, obs, ctx)
            if t.where == term.where and t.names == term.names]
    if not same:
        raise TransferError(f"{term.label()} cannot be evaluated on the second data set: it does not move the "
                            "place of the effect enough (or lacks the columns it needs, e.g. payload, time or "
                            "temperature); only the geometry is scored: measure it with that joint moving as in "
                            "the first")
    return same[0]


def _frame_refit(layout: Layout, obs: Observations, x: np.ndarray, terms: tuple[Term, ...], theta: np.ndarray,
                 loss: str) -> np.ndarray:
    """(M,) errors after fitting only the base frame and target offsets (kinematics and theta held)."""
    free = np.zeros(layout.size, bool)
    free[layout.n_kin:] = True
    model = ExtendedModel(layout, obs, x, free, terms)
    n = model.n_free
    theta = np.asarray(theta, dtype=float)[: model.n_theta]
    first = lsq.RFactor(n)
    for _, j in model.jacobian_chunks(np.concatenate([x[free], theta])):
        first.add(j[:, :, :n].reshape(-1, n))
    scale = norm_scale(np.linalg.norm(first.r, axis=0), len(obs))
    f_scale = RobustScoring.of(loss, model.residuals_mm(np.concatenate([x[free], theta]))).f_scale_mm

    def evaluate(z_free, jac):
        z = np.concatenate([z_free, theta])
        ne = lsq.NormalEquations(n, loss, f_scale)
        if jac:
            for _, j, residuals in model.jacobian_chunks(z, with_residuals=True):
                ne.add(j[:, :, :n].reshape(-1, n), residuals.ravel())
        else:
            ne.add(None, model.residuals_mm(z).ravel())
        return ne

    sol = lsq.levenberg_marquardt(evaluate, x[free], 1.0 / scale, ftol=1e-10, xtol=1e-10, gtol=1e-8)
    return np.linalg.norm(model.residuals_mm(np.concatenate([sol.x, theta])), axis=1)
