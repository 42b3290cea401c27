"""Quality gates every result passes before it may be written back.

Each gate says in words what it compared and why it failed. A result is written back
only when all pass (:attr:`~.base.Result.passed_gates`); the daemon never overrides that.
"""
from __future__ import annotations

import numpy as np

from cellcal.config.cells import PLAUSIBLE_DEG, PLAUSIBLE_MM, ToolSpec
from cellcal.solvers.geometry import se3
from cellcal.routines.framework.base import Gate
from cellcal.routines.framework.tool_frame import AXIS_ONLY, TIP_AND_AXIS, TIP_ONLY, controller_frame

RESIDUAL_FACTOR = 3.0  # residual RMS may be this many times the expected noise
MAX_CONDITION = 1e6  # of the scaled normal equations: beyond, some direction is barely measured
TOOL_PLAUSIBLE_MM = PLAUSIBLE_MM  # a real tool is within this of its drawing ...
TOOL_PLAUSIBLE_DEG = PLAUSIBLE_DEG  # ... and its axis within this of the drawn axis (config.cells)
PREVIOUS_MAX_MM = 2.0  # a recalibration moves the TCP by less than this unless the tool was changed ...
PREVIOUS_MAX_DEG = 1.0  # ... or bent


def residual(rms_mm: float, expected_mm: float, factor: float = RESIDUAL_FACTOR) -> Gate:
    limit = factor * expected_mm
    ok = bool(np.isfinite(rms_mm) and rms_mm <= limit)
    why = (f"residual RMS {rms_mm:.4f} mm is within {factor:g}x the expected noise {expected_mm:.4f} mm" if ok else
           f"residual RMS {rms_mm:.4f} mm is above {factor:g}x the expected noise {expected_mm:.4f} mm: "
           "the data do not fit the model (a fixture moved, a bad trigger, a loose tool?)")
    return Gate("residual", ok, rms_mm, limit, why)


def conditioning(condition: float, limit: float = MAX_CONDITION) -> Gate:
    ok = bool(np.isfinite(condition) and condition <= limit)
    why = (f"condition number {condition:.3g} is within {limit:.0e}" if ok else
           f"condition number {condition:.3g} is above {limit:.0e}: the poses barely determine some "
           "parameter; spread the orientations more")
    return Gate("conditioning", ok, condition, limit, why)


def identifiability(undetermined: list[str]) -> Gate:
    ok = not undetermined
    why = ("every reported parameter is determined by the data" if ok else
           f"not determined by these data: {', '.join(undetermined)}")
    return Gate("identifiability", ok, float(len(undetermined)), 0.0, why)


def frame_change(frame_a, frame_b) -> tuple[float, float]:
    """(position change mm, z-axis change deg) between two tool frames [x, y, z, rx, ry, rz] (m, rad)."""
    a, b = np.asarray(frame_a, dtype=float), np.asarray(frame_b, dtype=float)
    za = se3.rotvec_to_matrix(a[3:])[:, 2]
    zb = se3.rotvec_to_matrix(b[3:])[:, 2]
    angle = float(np.degrees(np.arccos(np.clip(za @ zb, -1.0, 1.0))))
    return float(np.linalg.norm(a[:3] - b[:3]) * 1e3), angle


def _compared(mm: float, deg: float, determines, max_mm: float, max_deg: float) -> tuple[bool, float, float, str]:
    """(passed, value, limit, words) of a frame comparison over what a result determined: the
    position for the tip, the axis' direction for the axis, both for both."""
    determines = frozenset(determines)
    if determines == TIP_ONLY:
        return (mm <= max_mm, mm, max_mm,
                f"the tip {mm:.3f} mm (limit {max_mm:g} mm; the axis is not compared: this routine does not "
                "determine it)")
    if determines == AXIS_ONLY:
        return (deg <= max_deg, deg, max_deg,
                f"the axis {deg:.3f} deg (limit {max_deg:g} deg; the TCP position is not compared: this routine "
                "does not determine it)")
    return (mm <= max_mm and deg <= max_deg, mm, max_mm,
            f"the tip {mm:.3f} mm and the axis {deg:.3f} deg (limits {max_mm:g} mm, {max_deg:g} deg)")


def plausible_tool(tool_frame, drawn: ToolSpec | None, max_mm: float = TOOL_PLAUSIBLE_MM,
                   max_deg: float = TOOL_PLAUSIBLE_DEG, determines=TIP_AND_AXIS) -> Gate:
    """The result against the tool as drawn, over what it `determines` (``tip``, ``axis``)."""
    if drawn is None:
        return Gate("plausibility", True, 0.0, max_mm, "no drawn tool in the cell file to compare with")
    ok, value, limit, words = _compared(*frame_change(tool_frame, drawn.tcp_pose), determines, max_mm, max_deg)
    why = (f"{words} from the tool as drawn"
           + ("" if ok else ": is the right tool mounted, and the cell file's [tool] right?"))
    return Gate("plausibility", ok, value, limit, why)


def agrees_with_previous(tool_frame, previous, max_mm: float = PREVIOUS_MAX_MM,
                         max_deg: float = PREVIOUS_MAX_DEG, determines=TIP_AND_AXIS) -> Gate:
    """Against the frame the controller had before the run (the previous result), over what
    the result `determines` (``tip``, ``axis``): what it did not determine it keeps from that
    frame, so comparing that would only compare the frame with itself."""
    if controller_frame(previous) is None:
        return Gate("previous", True, 0.0, max_mm, "no previous tool frame on the controller to compare with")
    ok, value, limit, words = _compared(*frame_change(tool_frame, previous), determines, max_mm, max_deg)
    why = (f"{words} from the controller's tool frame before the run"
           + ("" if ok else ": more than a recalibration should change; confirm the tool was changed"))
    return Gate("previous", ok, value, limit, why)
