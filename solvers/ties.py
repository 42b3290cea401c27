"""Explanations the data cannot tell apart, said as such.

Two causes tie when their best candidates' held-out errors lie within the naming
margin of each other (``analyze.MIN_MARGIN``): a one-joint-at-a-time sweep, for
instance, makes the gravity torque on the swept joint a first harmonic of its angle,
so compliance of that joint and a first-order cyclic error of it fit alike. The
tie is reported with its reason: the same column span (one explanation's model
lies in the other's, to ``analyze.NESTED_RTOL``), or held-out errors within the
margin. When one of them is named all the same, the grounds are stated: the
simpler of two nested explanations, or physical plausibility -- the size each
would need against what robots of this class show (``TYPICAL_MAX``). Only a
different experiment can decide a tie that neither settles (``discriminate``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

# Largest size of each effect commonly reported for serial industrial arms: (how the keys of the
# cause's magnitude end, largest typical value, what it means); the largest of those keys is judged.
# Gravity deflection of a joint: stiffness 1e4..1e6 N m/rad against gravity torques up to a few
# kN m, a few hundredths of a degree typical, 0.5 deg an extreme; gear and encoder cyclic errors:
# an arc minute or two (0.02-0.05 deg), 0.1 deg an extreme; backlash after assembly: below 0.1 deg;
# thermal growth: steel 12, aluminium 23 ppm/K; a tilt between parallel axes after machining:
# below 0.5 deg; trigger latency of sensor and IO: below 100 ms.
TYPICAL_MAX = {
    "joint_compliance": ("deflection_rms_deg", 0.5, "joint deflection under gravity"),
    "cyclic_joint_error": ("amplitude_deg", 0.1, "gear or encoder cyclic error"),
    "backlash": ("backlash_deg", 0.1, "lost motion of an assembled joint"),
    "thermal_drift": ("expansion_ppm_per_K", 30.0, "thermal expansion of steel or aluminium"),
    "parallel_axis_tilt": ("tilt_deg", 0.5, "tilt between machined parallel axes"),
    "trigger_latency": ("latency_ms", 100.0, "sensor and IO latency"),
}


@dataclass(frozen=True)
class Tied:
    """One of several explanations the data cannot tell apart."""

    scored: object  # analyze.Scored: the candidate as ranked
    why: str  # "same column span as ..." or "held-out error within the margin of ..."
    size: dict = dataclasses.field(default_factory=dict)  # the physical size it would need ({} not fitted)
    plausible: bool | None = None  # that size within TYPICAL_MAX; None when not judged

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
        return out


@dataclass(frozen=True)
class TieReport:
    naming: object  # analyze.Naming, perhaps settled on physical plausibility
    entries: tuple[Tied, ...] = ()
    grounds: str = ""


def tied_explanations(naming, baseline, scorer, min_gain: float, min_margin: float, size_of) -> TieReport:
    """The explanations of different causes within the margin of the best one, if that one explains
    anything (gains min_gain); none when two effects are both present (``naming.tie == "both"``).

    size_of(scored) -> its cause's magnitude, fitted in full; called only for a tie the naming
    rule left open, to judge plausibility."""
    candidates = naming.candidates
    if not candidates or naming.tie == "both":
        return TieReport(naming)
    lowest_mm = min(c.heldout_mean_mm for c in candidates)
    if 1.0 - lowest_mm / baseline.heldout_mean_mm < min_gain:
        return TieReport(naming)
    picked, causes = [], set()
    for c in candidates:  # the first of each cause, as ranked; a single place before several
        if c.cause in causes or c.terms[0].multi or c.heldout_mean_mm >= lowest_mm * (1.0 + min_margin):
            continue
        picked.append(c)
        causes.add(c.cause)
    if len(picked) < 2:
        return TieReport(naming)
    entries = [Tied(c, _why(c, picked[1] if c is picked[0] else picked[0], scorer, min_margin)) for c in picked]
    if naming.named is not None:  # the simpler of two nested explanations
        grounds = (f"{naming.named.label} is named as the simpler explanation: the other needs more "
                   f"parameters to say the same on these data")
        return TieReport(naming, tuple(entries), grounds)
    entries = [_judged(e, size_of(e.scored)) for e in entries]
    plausible = [e for e in entries if e.plausible]
    if len(plausible) != 1 or any(e.plausible is None for e in entries):
        return TieReport(naming, tuple(entries))
    chosen = plausible[0]
    grounds = "named on physical plausibility alone: " + "; ".join(_size_text(e) for e in entries)
    ranked = (chosen.scored,) + tuple(c for c in candidates if c is not chosen.scored)
    naming = dataclasses.replace(naming, named=chosen.scored, candidates=ranked, notes=naming.notes + (grounds,))
    return TieReport(naming, tuple(entries), grounds)


def _why(c, other, scorer, min_margin: float) -> str:
    a, b = c.terms[0], other.terms[0]
    if scorer.is_nested(a, b) or scorer.is_nested(b, a):
        return f"same column span as {other.label}: on these data one model contains the other"
    apart = 100.0 * abs(c.heldout_mean_mm / other.heldout_mean_mm - 1.0)
    return (f"held-out error {apart:.1f}% from that of {other.label}, within the "
            f"{100 * min_margin:.0f}% margin needed to tell causes apart")


def _largest(cause: str, size: dict) -> tuple[str, float] | None:
    """The size of the cause's kind that TYPICAL_MAX judges, largest first (None: none given)."""
    suffix = TYPICAL_MAX.get(cause, ("\0",))[0]
    sizes = [(k, abs(float(v))) for k, v in size.items() if k.endswith(suffix) and isinstance(v, (int, float))]
    return max(sizes, key=lambda kv: kv[1]) if sizes else None


def _judged(entry: Tied, size: dict) -> Tied:
    largest = _largest(entry.cause, size)
    plausible = None if largest is None else bool(largest[1] <= TYPICAL_MAX[entry.cause][1])
    return dataclasses.replace(entry, size=size, plausible=plausible)


def _size_text(e: Tied) -> str:
    key, value = _largest(e.cause, e.size)
    _, limit, what = TYPICAL_MAX[e.cause]
    verdict = "within" if e.plausible else "beyond"
    return f"{e.label} needs {key} {value:.3g}, {verdict} the {limit:g} typical of {what}"
