"""A tool's drift history: every tool frame measured for it (the store's ``measured_frames``,
full calibrations and checks alike), as changes of the tip (mm) and of the axis (deg)
against the first full calibration and against the last full calibration before each point,
and the rate at which it drifts; and the drift alarm a check ends in when its measured frame
is further from the last full calibration's than the tool's ``drift_mm`` / ``drift_deg``.

A *full calibration* is a calibration whose frame was written to the controller. A point
compares only what it determined (a check that saw the tip only has no axis change).

The rates are fitted by least squares (a straight line, :func:`numpy.polyfit`) to the
changes against the last full calibration of the points since it (that calibration, at
change 0, included), once against time (per week) and once against the run ids (per 1000
runs: every run of the store counts, whatever its routine); fewer than two such points, or
all at one time, give no rate (None) and say why.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from cellcal.routines.framework import tool_frame
from cellcal.routines.framework.base import Result
from cellcal.solvers.geometry import se3
from cellcal.solvers.tool_frames.tcp_laser import axis_pair
from cellcal.solvers.tool_frames.verdict import Verdict, beyond_drift, drift_verdict

SECONDS_PER_WEEK = 7 * 24 * 3600.0
CALIBRATION_ROUTINES = ("tcp-laser", "tcp-npoint", "tcf", "tcp-stylus")  # a full calibration of the tool
NEVER_CALIBRATED = "never calibrated here: checked against the controller's frame"
RATE_FIT = ("least squares straight line through the changes against the last full calibration of the points "
            "since it (that calibration included, at 0), against time and against run ids")


def kind_of(result: Result) -> str:
    """``check`` for a check's result (it has a verdict), else ``calibration``."""
    return "check" if result.verdict is not None else "calibration"


def measured_frame(result: Result) -> np.ndarray | None:
    """The tool frame a result measured (m, rad), or None when it measured none. A check whose
    verdict is ``ok`` carries the frame it was compared with (nothing to write); its measured
    frame is that frame moved by the measured change: the tip by x, y, z; the axis tilted by
    the check's tilts, counted as it counts them (toward the flange's x and y made
    perpendicular to the compared axis, :func:`cellcal.solvers.tool_frames.tcp_laser.axis_pair`)."""
    if result.tool_frame is None or not result.determines:
        return None
    frame = np.asarray(result.tool_frame, dtype=float)
    if result.verdict != Verdict.OK or result.change is None:
        return frame
    change, determines = result.change, frozenset(result.determines)
    tip = axis = None
    if tool_frame.TIP in determines:
        tip = frame[:3] + np.array([change["x_mm"], change["y_mm"], change["z_mm"]], dtype=float) / 1e3
    if tool_frame.AXIS in determines:
        compared = se3.rotvec_to_matrix(frame[3:])[:, 2]
        across_x, across_y = axis_pair(compared)
        axis = (compared + math.tan(math.radians(change["tilt_x_deg"])) * across_x
                + math.tan(math.radians(change["tilt_y_deg"])) * across_y)
        axis /= np.linalg.norm(axis)
    ref = tool_frame.Reference(frame, "the frame the check compared with", True)
    return tool_frame.compose(determines, ref, tip_m=tip, axis=axis)[0]


def change_between(frame, determines, base) -> dict:
    """{"tip_mm", "axis_deg"}: how far `frame`'s tip and axis are from `base`'s (None for what
    `determines` leaves out, or without a base)."""
    if base is None:
        return {"tip_mm": None, "axis_deg": None}
    frame, base = np.asarray(frame, dtype=float), np.asarray(base, dtype=float)
    tip = float(np.linalg.norm(frame[:3] - base[:3]) * 1e3) if tool_frame.TIP in determines else None
    axis = None
    if tool_frame.AXIS in determines:
        cos = se3.rotvec_to_matrix(frame[3:])[:, 2] @ se3.rotvec_to_matrix(base[3:])[:, 2]
        axis = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return {"tip_mm": tip, "axis_deg": axis}


MIN_RATE_SPAN_WEEKS = 1.0 / 7.0  # a rate per week needs at least a day between its first and last point
# a rate per 1000 runs needs its first and last point 100 runs apart (run ids count every run of the
# cell): from fewer it would extrapolate the checks' noise more than tenfold
MIN_RATE_SPAN_RUNS = 100


def _slope(x, y) -> float | None:
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if len(x) < 2 or np.ptp(x) == 0.0:
        return None
    return float(np.polyfit(x - x[0], y, 1)[0])


def trend(rows: list[dict], tool_id: int) -> dict:
    """The drift history of a tool from its measured frames (``Store.measured_frames``, oldest
    first): one JSON-able object (docs/cli.md ``tool trend``)."""
    full = full_calibrations(rows)
    first = full[0] if full else None
    points, last = [], None
    for r in rows:
        determines = frozenset(r["determines"])
        since_first = change_between(r["frame"], determines, None if first is None else first["frame"])
        since_last = change_between(r["frame"], determines, None if last is None else last["frame"])
        if any(r is f for f in full):
            last = r
            since_last = change_between(r["frame"], determines, r["frame"])
        points.append({"run_id": r["run_id"], "at": r["at"], "kind": r["kind"], "routine": r["routine"],
                       "written": r["written"], "determines": sorted(determines),
                       "tip_mm": [v * 1e3 for v in r["frame"][:3]],
                       "since_first_calibration": since_first, "since_last_calibration": since_last,
                       "last_calibration_run": None if last is None else last["run_id"]})
    rate = {"fitted": RATE_FIT, "points": 0, "tip_mm_per_week": None, "tip_mm_per_1000_runs": None,
            "axis_deg_per_week": None, "axis_deg_per_1000_runs": None,
            "why_none": "no full calibration of this tool recorded" if last is None else None}
    if last is not None:
        since = [p for p in points if p["last_calibration_run"] == last["run_id"]]
        rate["points"] = len(since)
        for key, name in (("tip_mm", "tip_mm"), ("axis_deg", "axis_deg")):
            used = [p for p in since if p["since_last_calibration"][key] is not None]
            weeks = [(p["at"] - last["at"]) / SECONDS_PER_WEEK for p in used]
            runs = [p["run_id"] for p in used]
            values = [p["since_last_calibration"][key] for p in used]
            # a weekly rate from minutes of history extrapolates the checks' noise: none under a day
            per_week = _slope(weeks, values) if len(weeks) > 1 and np.ptp(weeks) >= MIN_RATE_SPAN_WEEKS else None
            per_run = _slope(runs, values) if len(runs) > 1 and np.ptp(runs) >= MIN_RATE_SPAN_RUNS else None
            rate[f"{name}_per_week"] = per_week
            rate[f"{name}_per_1000_runs"] = None if per_run is None else per_run * 1000.0
        missing = []
        if all(rate[k] is None for k in ("tip_mm_per_week", "axis_deg_per_week")):
            missing.append("no rate per week: fewer than two points a day or more apart")
        if all(rate[k] is None for k in ("tip_mm_per_1000_runs", "axis_deg_per_1000_runs")):
            missing.append(f"no rate per 1000 runs: fewer than two points {MIN_RATE_SPAN_RUNS} runs or more apart")
        if missing:
            rate["why_none"] = "; ".join(missing) + f" since the last full calibration (run {last['run_id']})"
    latest = points[-1] if points else None
    return {"tool_id": int(tool_id), "never_calibrated": first is None,
            "first_calibration": None if first is None else {"run_id": first["run_id"], "at": first["at"]},
            "last_calibration": None if last is None else {"run_id": last["run_id"], "at": last["at"]},
            "latest": latest, "rate": rate, "points": points}


def full_calibrations(rows: list[dict]) -> list[dict]:
    """The full calibrations (written back) of `rows`, a tool's measured frames, oldest first."""
    return [r for r in rows if r["kind"] == "calibration" and r["written"]]


def since_last_calibration(frame, determines, rows: list[dict]) -> tuple[dict, dict] | None:
    """(the last full calibration's row, :func:`change_between` of `frame` and its frame), or
    None when `rows` hold no full calibration."""
    full = full_calibrations(rows)
    if not full:
        return None
    return full[-1], change_between(frame, frozenset(determines), full[-1]["frame"])


def _drift_words(change: dict, last: dict, bands) -> str | None:
    """Why a change since the last full calibration (`last`) is beyond the drift alarm, or None."""
    tip, axis = beyond_drift(change["tip_mm"], change["axis_deg"], bands)
    beyond = []
    if tip:
        beyond.append(f"tip {change['tip_mm']:.3f} mm from the last full calibration's (run {last['run_id']}), "
                      f"beyond the drift alarm {bands.drift_mm:g} mm")
    if axis:
        beyond.append(f"axis {change['axis_deg']:.3f} deg from the last full calibration's (run {last['run_id']}), "
                      f"beyond the drift alarm {bands.drift_deg:g} deg")
    return "; ".join(beyond) or None


@dataclasses.dataclass(frozen=True)
class DriftJudgement:
    """What a check's place in its tool's history adds to its result: the verdict (``drift``
    when it drifted beyond the drift alarm, else the check's own), why it drifted, and whether
    no full calibration of the tool was found to compare with."""

    verdict: Verdict | None
    why: str | None = None
    never_calibrated: bool = False

    @property
    def notes(self) -> tuple[str, ...]:
        """The notes it puts before the check's own."""
        if self.why is not None:
            return (f"drift alarm: {self.why}; nothing written",)
        return (NEVER_CALIBRATED,) if self.never_calibrated else ()

    def applied_to(self, result: Result) -> Result:
        """`result` as the run records and reports it: a new Result with this verdict, these notes
        first and ``never_calibrated`` in its JSON; `result` itself is left as the routine gave it."""
        if self.verdict == result.verdict and not self.notes and not self.never_calibrated:
            return result
        extra = {**result.extra, "never_calibrated": True} if self.never_calibrated else dict(result.extra)
        return dataclasses.replace(result, verdict=self.verdict, notes=[*self.notes, *result.notes], extra=extra)


def judge(result: Result, frame, rows: list[dict], bands, calibrated: bool) -> DriftJudgement:
    """A check's drift judgement, decided after its own verdict (an alarm stays an alarm): its
    measured `frame` (:func:`measured_frame`, taken before any judgement turns the verdict) against the last full calibration in `rows` (the tool's measured frames) and
    the tool's drift alarm in `bands`. `calibrated`: a full calibration of the tool is known
    (in `rows`, or one written before the store kept measured frames); without one the check
    says so and keeps its verdict. A calibration's result (no verdict) is judged nothing."""
    if result.verdict is None:
        return DriftJudgement(None)
    if not calibrated:
        return DriftJudgement(result.verdict, never_calibrated=True)
    if result.verdict not in (Verdict.OK, Verdict.CORRECTED) or frame is None:
        return DriftJudgement(result.verdict)
    found = since_last_calibration(frame, result.determines, rows)
    if found is None:
        return DriftJudgement(result.verdict)
    last, change = found
    verdict = drift_verdict(result.verdict, change["tip_mm"], change["axis_deg"], bands)
    return DriftJudgement(verdict, _drift_words(change, last, bands) if verdict is Verdict.DRIFT else None)


TOGETHER_DEG = 30.0  # two tips that moved within this angle of each other moved "the same way"


def _tip_move_mm(rows: list[dict]) -> tuple[int, np.ndarray] | None:
    """(the newest check's run, its tip minus the last full calibration's, mm) of a tool's
    measured frames, or None: no calibration, no check since it, or a check without the tip."""
    full = full_calibrations(rows)
    if not full:
        return None
    after = [r for r in rows if r["kind"] == "check" and r["run_id"] > full[-1]["run_id"]
             and tool_frame.TIP in r["determines"]]
    if not after:
        return None
    return after[-1]["run_id"], (np.asarray(after[-1]["frame"][:3]) - np.asarray(full[-1]["frame"][:3])) * 1e3


def drifting_together(tool_id: int, rows_by_tool: dict[int, list[dict]], bands_by_tool: dict) -> str | None:
    """When tool `tool_id`'s newest check drifted beyond its drift alarm and so did the newest
    check of every other tool checked since its calibration, the same way (their tips' moves
    within TOGETHER_DEG and within a factor of two in size): the words saying so. A tool does not
    bend the way another does; beams that moved make every tool's check show the same move."""
    moves = {t: _tip_move_mm(rows) for t, rows in rows_by_tool.items()}
    moves = {t: m for t, m in moves.items() if m is not None}
    if tool_id not in moves or len(moves) < 2:
        return None
    for t, (_, move) in moves.items():
        limit = getattr(bands_by_tool.get(t), "drift_mm", None)
        if limit is None or float(np.linalg.norm(move)) <= limit:
            return None
    own = moves[tool_id][1]
    for t, (_, move) in moves.items():
        cos = float(own @ move) / (np.linalg.norm(own) * np.linalg.norm(move))
        ratio = float(np.linalg.norm(move) / np.linalg.norm(own))
        if cos < math.cos(math.radians(TOGETHER_DEG)) or not 0.5 <= ratio <= 2.0:
            return None
    said = ", ".join(f"tool {t} {float(np.linalg.norm(m)):.3f} mm (run {run})" for t, (run, m) in sorted(moves.items()))
    return (f"every tool checked since its calibration drifted the same way ({said}): beams that moved show as "
            "every tool drifting at once, a bent tool as one. Calibrate with tcp-laser first (it finds the beams "
            "anew), then check the others")

