"""What a run found, as the panel's outcome registers carry it (docs/panel.md "Outcome registers").

A PLC or the robot program reads these without parsing anything: the verdict of a check,
the tool, and the measured change of the tool frame against the frame it was compared with
(x, y, z of the tip in 0.001 mm, the axis' lean toward x and y in 0.001 deg, flange frame),
each a signed 16-bit value (two's complement). A change beyond +-32.767 saturates at
+-32767; a component the run did not determine, or a run that measured no tool, reads
-32768 (0x8000). They are written before the result code and the run counter, so a PLC
that waits for the counter to move reads the outcome of that run.
"""
from __future__ import annotations

import math

from cellcal.solvers.tool_frames.verdict import Verdict

VERDICTS = {None: 0, Verdict.OK: 1, Verdict.CORRECTED: 2, Verdict.ALARM: 3, Verdict.DRIFT: 4}  # register values
CHANGE_KEYS = {"change_x": "x_mm", "change_y": "y_mm", "change_z": "z_mm",
               "tilt_x": "tilt_x_deg", "tilt_y": "tilt_y_deg"}
SCALE = 1000  # register counts per mm, and per degree
NOT_DETERMINED = -32768
LIMIT = 32767


def _signed16(value: float | None) -> int:
    """A change in mm or deg -> the register's raw 0..65535 (two's complement of 0.001 units)."""
    if value is None or not math.isfinite(value):
        counts = NOT_DETERMINED
    else:
        counts = max(-LIMIT, min(LIMIT, int(round(value * SCALE))))
    return counts & 0xFFFF


def registers(verdict: Verdict | str | None, tool_id: int, change: dict | None) -> dict[str, int]:
    """The outcome registers' raw values: verdict (0 a calibration or no result, 1 ok, 2
    corrected, 3 alarm, 4 drift alarm), the tool's id, and the change (``change``: keys of CHANGE_KEYS'
    values, None where not determined; None altogether when nothing was measured)."""
    change = change or {}
    out = {"verdict": VERDICTS[None if verdict is None else Verdict(verdict)], "tool_id": int(tool_id) & 0xFFFF}
    out.update({name: _signed16(change.get(key)) for name, key in CHANGE_KEYS.items()})
    return out


def decoded(raw: dict[str, int]) -> dict:
    """The registers as a PLC program would read them: the verdict's name, the tool id, the
    change in mm and deg (None: not determined)."""
    names = {v: k for k, v in VERDICTS.items()}
    out = {"verdict": names.get(raw["verdict"], f"unknown {raw['verdict']}"), "tool_id": raw["tool_id"]}
    for name, key in CHANGE_KEYS.items():
        counts = raw[name] - 0x10000 if raw[name] >= 0x8000 else raw[name]
        out[key] = None if counts == NOT_DETERMINED else counts / SCALE
    return out
