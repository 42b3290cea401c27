"""Explanations the data cannot tell apart, said as such.

Two causes tie when their best candidates' held-out errors lie within the naming
margin of each other (``naming.MIN_MARGIN``): a one-joint-at-a-time sweep, for
instance, makes the gravity torque on the swept joint a first harmonic of its angle,
so compliance of that joint and a first-order cyclic error of it fit alike. The
tie is reported with its reason: the same column span (one explanation's model
lies in the other's, to ``linearised_scorer.NESTED_RTOL``), or held-out errors within the
margin. A lead beyond the margin is a tie too when the data themselves do not
separate the two: each fitted to the data, the other refitted to its predictions
misses them by fewer than sqrt(DECIDE_LAMBDA) noise standard deviations over all
rows (for the closer direction). A held-out lead then comes from how the folds fall
on a few loosely determined parameters, not from anything the data show. So too a lead
won by a search's steadiness (``_unsteady``): scored with each fold's own choice of places,
one cause leads by the margin, scored as the models chosen on all rows it does not. When one of them is named all the same, the grounds are stated: the
simpler of two nested explanations, or physical plausibility -- the size each
would need against what robots of its class show (``plausibility.TYPICAL_MAX``). Only a
different experiment can decide a tie that neither settles (``discriminate``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from cellcal.solvers.analysis import plausibility
from cellcal.solvers.analysis.robust_scoring import trimmed_mean

# Two explanations whose predictions, each fitted, lie fewer than 2 * 2.33 noise standard deviations
# apart over all the data (summed squares) cannot be told apart by a decision that errs below 1% either
# way; the experiment design asks the same of the poses it proposes (``discriminate``).
DECIDE_LAMBDA = (2.0 * 2.326) ** 2
MEAN_PER_SIGMA = np.sqrt(8.0 / np.pi)  # mean length of 3-D noise per standard deviation of one coordinate

# The typical maxima of the default robot class, as (magnitude key suffix, value, what it means): the table
# itself, per cause and robot class with its reasoning, is ``plausibility.TYPICAL_MAX``.
TYPICAL_MAX = {cause: (next(iter(q.suffixes)), plausibility.TYPICAL_MAX[cause][plausibility.DEFAULT_CLASS], q.what)
               for cause, q in plausibility.QUANTITY.items()}


@dataclass(frozen=True)
class Tied:
    """One of several explanations the data cannot tell apart."""

    scored: object  # naming.Scored: the candidate as ranked
    why: str  # "same column span as ..." or "held-out error within the margin of ..."
    size: dict = dataclasses.field(default_factory=dict)  # the physical size it would need ({} not fitted)
    plausible: bool | None = None  # that size within the class's typical maximum; None when not judged
    judged: object = None  # plausibility.Judgement of that size

    @property
    def cause(self) -> str:
        return self.scored.cause

    @property
    def label(self) -> str:
        return self.scored.label

    def json(self) -> dict:
        out = {"cause": self.cause, "where": self.scored.where, "label": self.label,
               "heldout_mean_mm": self.scored.heldout_mean_mm, "why": self.why}
        if self.size:
            out["size_needed"] = self.size
            out["plausible"] = self.plausible
        if self.judged is not None:
            out["plausibility"] = self.judged.json()
        return out


@dataclass(frozen=True)
class TieReport:
    naming: object  # naming.Naming, perhaps settled on physical plausibility
    entries: tuple[Tied, ...] = ()
    grounds: str = ""


def tied_explanations(naming, baseline, scorer, min_gain: float, min_margin: float, size_of,
                      robot_class: str = plausibility.DEFAULT_CLASS, searched=frozenset()) -> TieReport:
    """The explanations of different causes within the margin of the best one, if that one explains
    anything (gains min_gain); none when two effects are both present (``naming.tie == "both"``).

    size_of(scored) -> its cause's magnitude, fitted in full; called only for a tie the naming
    rule left open, to judge plausibility against the typical maxima of robot_class. searched: the ids
    of the terms a forward search chose (scored with each fold's own choice: ``_unsteady``)."""
    candidates = naming.candidates
    if not candidates or naming.tie == "both":
        return TieReport(naming)
    rivals = naming.contenders or _first_single_places(candidates)
    if not rivals:
        return TieReport(naming)
    lowest_mm = rivals[0].heldout_mean_mm  # the best contender: the one the naming rule weighs
    if 1.0 - lowest_mm / baseline.heldout_mean_mm < min_gain:
        return TieReport(naming)
    picked = [c for c in rivals if c.heldout_mean_mm < lowest_mm * (1.0 + min_margin)]
    apart = fixed = None
    if len(picked) == 1 and naming.named is picked[0]:  # named by the margin: do the data themselves separate them?
        runner_up, apart = _unseparated(picked[0], rivals, baseline, scorer, min_gain)
        if runner_up is not None:
            note = (f"{picked[0].label} leads {runner_up.label} by {100 * naming.margin:.1f}% held-out, but fitted "
                    f"to these data their predictions lie only {apart:.1f} noise standard deviations apart, "
                    f"{np.sqrt(DECIDE_LAMBDA):.2f} needed to tell them apart")
            naming = dataclasses.replace(naming, named=None, tie="unseparated", notes=naming.notes + (note,))
        else:
            runner_up, fixed = _unsteady(picked[0], rivals, baseline, scorer, min_gain, min_margin, searched)
            if runner_up is None:
                return TieReport(naming)
            note = (f"{picked[0].label} leads {runner_up.label} by {100 * naming.margin:.1f}% held-out with each "
                    f"fold choosing its own places, but as the models chosen on all rows their held-out errors "
                    f"lie {100 * abs(fixed):.1f}% apart, {100 * min_margin:.0f}% needed: the lead comes from how "
                    f"steadily each cause's places are chosen on fewer rows, not from what either explains")
            naming = dataclasses.replace(naming, named=None, tie="unsteady", notes=naming.notes + (note,))
        picked.append(runner_up)
    if len(picked) < 2:
        return TieReport(naming)
    entries = [Tied(c, _why(c, picked[1] if c is picked[0] else picked[0], scorer, min_margin, apart, fixed))
               for c in picked]
    if naming.named is not None:  # the simpler of two nested explanations
        grounds = (f"{naming.named.label} is named as the simpler explanation: the other needs more "
                   f"parameters to say the same on these data")
        return TieReport(naming, tuple(entries), grounds)
    entries = [_judged(e, size_of(e.scored), robot_class) for e in entries]
    plausible = [e for e in entries if e.plausible]
    if len(plausible) != 1 or any(e.plausible is None for e in entries):
        return TieReport(naming, tuple(entries))
    chosen = plausible[0]
    grounds = "named on physical plausibility alone: " + "; ".join(_size_text(e) for e in entries)
    naming = dataclasses.replace(naming, named=chosen.scored, notes=naming.notes + (grounds,))
    return TieReport(naming, tuple(entries), grounds)


def _first_single_places(candidates) -> tuple:
    """The first single-place candidate of each cause, in the order given (for namings without contenders)."""
    out, causes = [], set()
    for c in candidates:
        if c.cause not in causes and not c.terms[0].multi:
            out.append(c)
            causes.add(c.cause)
    return tuple(out)


# What drives each cause's effect, and how an experiment varies it, for the experiment that tells two causes
# apart: vary what drives one while what drives the other stays, and the other way round.
DRIVERS = {
    "joint_compliance": ("the gravity torque on {where}", "another posture of the joints beyond it, or a payload"),
    "cyclic_joint_error": ("the angle of {where} itself", "the same angles in other postures"),
    "backlash": ("the side {where} approaches each pose from", "each pose approached from both sides"),
    "thermal_drift": ("the arm's temperature", "the same poses cold and warm"),
    "parallel_axis_tilt": ("the angles of {where}", "those angles over their range"),
    "trigger_latency": ("the speed through the trigger", "sweeps at several speeds, both directions"),
}


def decide_by(entries) -> str:
    """The experiment that decides a tie, in words: what drives each of the two best explanations, to be
    varied apart."""
    if len(entries) < 2:
        return ""
    follows, how = [], []
    for e in entries[:2]:
        where = e.scored.where
        joints = where.get("joints") or ([where["joint"]] if "joint" in where else [])
        place = ("joint " + ", ".join(str(j) for j in joints)) if joints else "the joints"
        driver, vary = DRIVERS.get(e.cause, (f"what drives {e.cause}", "it"))
        follows.append(f"{e.cause} follows {driver.format(where=place)}")
        how.append(vary)
    return (f"{follows[0]}, {follows[1]}: measure poses where the two change independently ({how[0]}; "
            f"{how[1]}); `cellcal analyze --discriminate N -o POSES.csv` proposes such poses and how many suffice")


def _unsteady(best, rivals, baseline, scorer, min_gain: float, min_margin: float, searched):
    """(a contender of another cause, the fractional margin between the two) when either was chosen by a
    forward search (its held-out errors those of each fold's own choice of places, ``selection``) and,
    scored as the models chosen on all rows, the two lie within min_margin of each other (the contender
    gaining min_gain); else (None, None). Inside a fold's fewer rows the search of one cause may pick
    another place now and then (compliance of a joint the fold barely sees) while a rival's pick stays
    put: that costs the first its nested score, and says how steady its choice is, not that the other
    explains the data better."""
    if not searched:
        return None, None
    others = [c for c in rivals if c.cause != best.cause]
    if not others or not any(id(c.terms[0]) in searched for c in (best, *others)):
        return None, None
    errors = scorer.heldout_errors_many([c.terms for c in (best, *others)])
    fixed = np.array([float(trimmed_mean(e, c.trim)) for e, c in zip(errors, (best, *others))])
    margins = np.where(1.0 - fixed[1:] / baseline.heldout_mean_mm >= min_gain, fixed[1:] / fixed[0] - 1.0, np.inf)
    i = int(np.argmin(margins))
    return (others[i], float(margins[i])) if margins[i] < min_margin else (None, None)


def _unseparated(best, candidates, baseline, scorer, min_gain: float):
    """(the first single-place candidate of another cause, how many noise standard deviations apart the
    two put the data) when it also explains the data (gains min_gain) and they lie fewer than
    sqrt(DECIDE_LAMBDA) apart, the closer direction counted (either may be the truth), but for a best
    explanation that contains the other only the other refitted to it; else (None, None).
    The noise is what the best explanation leaves on held-out data."""
    other = next((c for c in candidates if c.cause != best.cause and not c.terms[0].multi), None)
    if other is None or 1.0 - other.heldout_mean_mm / baseline.heldout_mean_mm < min_gain:
        return None, None
    sigma_mm = best.heldout_mean_mm / MEAN_PER_SIGMA
    a, b = best.terms[0], other.terms[0]
    apart = [scorer.separation_mm2(a, b)]
    if not scorer.is_nested(b, a):  # the best contains the other: it reproduces the other's predictions on
        apart.append(scorer.separation_mm2(b, a))  # any data, that direction tells nothing
    lam = min(apart) / sigma_mm**2
    return (other, float(np.sqrt(lam))) if lam < DECIDE_LAMBDA else (None, None)


def _why(c, other, scorer, min_margin: float, apart: float | None = None, fixed: float | None = None) -> str:
    """Why c ties with other: the same column span; `apart` noise standard deviations between their fitted
    predictions (``_unseparated``); `fixed`, the margin of the models chosen on all rows (``_unsteady``);
    else held-out errors within the margin."""
    a, b = c.terms[0], other.terms[0]
    if scorer.is_nested(a, b) or scorer.is_nested(b, a):
        return f"same column span as {other.label}: on these data one model contains the other"
    if fixed is not None:
        return (f"as the models chosen on all rows, held-out errors {100 * abs(fixed):.1f}% from those of "
                f"{other.label}, within the {100 * min_margin:.0f}% margin needed to tell causes apart (the "
                f"lead with each fold's own choice of places comes from how steadily they are chosen)")
    if apart is not None:
        return (f"fitted to these data, its predictions and those of {other.label} lie {apart:.1f} noise "
                f"standard deviations apart, fewer than the {np.sqrt(DECIDE_LAMBDA):.2f} needed to tell them apart")
    apart = 100.0 * abs(c.heldout_mean_mm / other.heldout_mean_mm - 1.0)
    return (f"held-out error {apart:.1f}% from that of {other.label}, within the "
            f"{100 * min_margin:.0f}% margin needed to tell causes apart")


def _judged(entry: Tied, size: dict, robot_class: str) -> Tied:
    judged = plausibility.judge(entry.cause, size, robot_class)
    return dataclasses.replace(entry, size=size, plausible=None if judged is None else judged.plausible, judged=judged)


def _size_text(e: Tied) -> str:
    return f"{e.label} {e.judged.text()}"
