"""Which cause, if any, the data support: the naming rule of :mod:`.analyze` (its steps 3 to 5).

Every candidate is scored alone with the geometry on held-out data (``score_candidates``); each
cause competes with its preferred candidate (``contenders``: a single place unless several places
beat it by MULTI_GAIN); the best is named when it beats geometry alone by MIN_GAIN and every other
cause by MIN_MARGIN (``name_cause``; near-ties settled by ``_settle_tie``); with it in the model, a
second effect must gain MIN_GAIN more (``find_second_effect``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from cellcal.solvers.analysis import plausibility, selection
from cellcal.solvers.analysis.effects import CAUSES, Term
from cellcal.solvers.analysis.linearised_scorer import LinearisedScorer
from cellcal.solvers.analysis.robust_scoring import trimmed_mean

MIN_GAIN = 0.10  # held-out mean error must drop by 10% against geometry alone
MIN_MARGIN = 0.08  # ... and the best other cause must stay 8% above the named one
MULTI_GAIN = 0.10  # a several-joint term must beat its cause's best single joint by this much


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
    prior_weights: tuple = ()  # fitted in full: each fold's weight of the prior "no effect" (``analyze._heldout``)

    @property
    def heldout_mean_mm(self) -> float:
        """The held-out score: the mean error (without the largest `trim` fraction under a robust loss)."""
        return float(trimmed_mean(self.heldout_errors, self.trim))


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


def deciding_grounds(naming: Naming, tied) -> tuple[str, ...]:
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
                       nested: bool = True, named_per_fold: tuple | None = None
                       ) -> tuple[Scored | None, np.ndarray | None]:
    """With the named effect in the model, the candidate of another cause that lowers the
    held-out mean by MIN_GAIN more: (it scored alone, the held-out errors of both together), or (None, None).
    A cause with places is searched again with the named effect in the model (the same forward search,
    nested as the first). named_per_fold: the named effect's own choice in each fold (its
    ``selection.Selection.per_fold``) when it was chosen by a search: each fold's search and score then
    hold that fold's choice, as the named effect's own score did (nested); the all-rows choice there
    would score the pair on rows that chose it."""
    scorer = scores.scorer
    bases = named_per_fold if nested and named_per_fold is not None else (named.terms,) * scores.n_folds
    # a cause with places competes by its search with the named effect in the model, not by its first choice
    others = [t for t in terms if t.cause != named.cause and t.cause not in places and t.extra.get("all", True)]
    searched = [s for s in (selection.select(CAUSES[cause], *p, scores, base=named.terms,
                                             fold_bases=bases if nested else None)
                            for cause, p in places.items() if cause != named.cause) if s]
    if not others and not searched:
        return None, None
    if nested:
        steps = ([selection.nested_steps(scores, None, tuple(b + (t,) for b in bases)) for t in others]
                 + [selection.nested_steps(scores, s, bases) for s in searched])
    else:
        steps = ([scorer.steps(named.terms + (t,)) for t in others]
                 + [scorer.steps(named.terms + (s.term,)) for s in searched])
    candidates = others + [s.term for s in searched]
    errors = scorer.heldout_errors_of_steps(np.concatenate(steps + [scorer.steps((t,)) for t in candidates]))
    with_named = [(float(trimmed_mean(e, named.trim)), t, alone, e)
                  for e, t, alone in zip(errors, candidates, errors[len(candidates):])]
    with_named.sort(key=lambda entry: entry[0])
    _prefer_single_place(with_named, lambda entry: entry[0], lambda entry: entry[1])
    if not with_named or with_named[0][0] >= (1.0 - MIN_GAIN) * named.heldout_mean_mm:
        return None, None
    _, term, alone, together = with_named[0]
    return score_candidates([term], scorer, [alone])[0], together


def _prefer_single_place(ranked: list, error, term) -> None:
    """Parsimony, in place: a term spanning several joints must beat the best single-place
    term of its cause by MULTI_GAIN, else the single place goes first (it says *where*)."""
    if not ranked:
        return
    best = ranked[0]
    singles = [i for i, r in enumerate(ranked) if term(r).cause == term(best).cause and not term(r).multi]
    if singles and singles[0] != 0 and error(best) > (1.0 - MULTI_GAIN) * error(ranked[singles[0]]):
        ranked.insert(0, ranked.pop(singles[0]))
