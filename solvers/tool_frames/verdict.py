"""A check's verdict on a tool, decided from numbers only: the measured change of its frame
against the frame it was compared with, the change's uncertainty, and the tool's bands.

Each part of the change (the tip in mm, the axis' tilt in deg) is judged on its own:

* it is *determined* when ``K_SIGMA`` standard deviations along its worst direction fit in
  the inner band; only a determined part is held against the inner band;
* it is *beyond the outer band* when its size is (a determined part), or when even its
  ``K_SIGMA`` lower bound is (a part not determined well enough: only a sure excess counts).

The verdict, first match wins: ``alarm`` when a part is beyond the outer band, a gate failed
(the data do not say what changed) or nothing was determined; ``ok`` when every determined
part is within the inner band; else ``corrected``. A check that is ``ok`` or ``corrected``
turns ``drift`` when its measured frame is further from the last full calibration's than the
tool's drift alarm (:func:`drift_verdict`). What the words say about it is the routine's.

``bands`` is any object with ``inner_mm``, ``outer_mm``, ``inner_deg``, ``outer_deg`` and
``drift_mm``, ``drift_deg`` (None: that drift alarm off), as the cell file's tool bands are.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

K_SIGMA = 3.0  # a change is determined for a band when K_SIGMA standard deviations fit in the inner band


class Verdict(enum.StrEnum):
    """A check's verdict; its value is the word of the result's JSON and of the store."""

    OK = "ok"  # every determined change within the inner band: nothing to write
    CORRECTED = "corrected"  # a determined change beyond the inner band, none beyond the outer: written back
    ALARM = "alarm"  # beyond the outer band, a failed gate or nothing determined: nothing written
    DRIFT = "drift"  # ok or corrected, but beyond the drift alarm since the last full calibration: nothing written


@dataclass(frozen=True)
class Measured:
    """One part of a check's change: its size (the tip's distance in mm, or the axis' tilt in
    deg) and its standard deviation along the worst-determined direction (same unit)."""

    size: float
    std: float


@dataclass(frozen=True)
class Part:
    """How one part of the change stands against its bands."""

    measured: bool  # the check fitted it at all (an axis needs two heights)
    determined: bool  # K_SIGMA std within the inner band
    beyond_inner: bool  # determined, and its size beyond the inner band
    beyond_outer: bool  # its size (not determined: its K_SIGMA lower bound) beyond the outer band


@dataclass(frozen=True)
class CheckVerdict:
    """A check's verdict and the judgement of each part it rests on."""

    verdict: Verdict
    tip: Part
    axis: Part
    gates_passed: bool


def determined(std: float, inner: float, k_sigma: float = K_SIGMA) -> bool:
    """Whether a change known to `std` (1 sigma) can be held against an inner band `inner`."""
    return k_sigma * std <= inner


def judge_part(measured: Measured | None, inner: float, outer: float, k_sigma: float = K_SIGMA) -> Part:
    """One part of the change against its inner and outer band; None: the check did not fit it."""
    if measured is None:
        return Part(False, False, False, False)
    known = determined(measured.std, inner, k_sigma)
    lower = measured.size - (0.0 if known else k_sigma * measured.std)
    return Part(True, known, known and measured.size > inner, lower > outer)


def check_verdict(tip: Measured | None, axis: Measured | None, bands, gates_passed: bool,
                  k_sigma: float = K_SIGMA) -> CheckVerdict:
    """The verdict of a check whose tip changed by `tip` (mm) and whose axis tilted by `axis`
    (deg; None: held, not fitted), every gate passed or not (see the module's doc)."""
    tip_part = judge_part(tip, bands.inner_mm, bands.outer_mm, k_sigma)
    axis_part = judge_part(axis, bands.inner_deg, bands.outer_deg, k_sigma)
    parts = (tip_part, axis_part)
    if any(p.beyond_outer for p in parts) or not gates_passed or not any(p.determined for p in parts):
        verdict = Verdict.ALARM
    elif any(p.beyond_inner for p in parts):
        verdict = Verdict.CORRECTED
    else:
        verdict = Verdict.OK
    return CheckVerdict(verdict, tip_part, axis_part, gates_passed)


def beyond_drift(tip_mm: float | None, axis_deg: float | None, bands) -> tuple[bool, bool]:
    """(tip, axis): whether the change since the last full calibration is beyond the tool's drift
    alarm (a part not determined, None, or an alarm that is off is never beyond)."""
    tip = bands.drift_mm is not None and tip_mm is not None and tip_mm > bands.drift_mm
    axis = bands.drift_deg is not None and axis_deg is not None and axis_deg > bands.drift_deg
    return tip, axis


def drift_verdict(verdict: Verdict | None, tip_mm: float | None, axis_deg: float | None, bands) -> Verdict | None:
    """A check's verdict once its change since the last full calibration (`tip_mm`, `axis_deg`;
    None: not determined, or no calibration to compare with) is known: ``drift`` for an ``ok``
    or ``corrected`` check beyond the drift alarm; any other verdict stays (an alarm stays one)."""
    if verdict not in (Verdict.OK, Verdict.CORRECTED):
        return verdict
    return Verdict.DRIFT if any(beyond_drift(tip_mm, axis_deg, bands)) else verdict
