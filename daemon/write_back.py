"""A tool frame to the robot controller, read back and compared, or the old one put back.

The frame goes to two places of the controller (:class:`~cellcal.drivers.interfaces.Robot`):

* the running program's tool frame (``set_tcp``), which the controller reports back (``tcp``);
* the frame the robot program applies at its next start (``store_tool_frame``), on robots that
  keep one (a UR: RTDE input registers, README "Persistent tool frame"). Its generation is
  the run whose result it is.

Both are read before anything is written, and each is read back after its write and compared
(exactly: the values travel as doubles). On a mismatch or a device error, both are written as
they were before and read back again; the message says whether that worked. The same
function serves ``cellcal tool rollback``, which writes an older pair.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.drivers.interfaces import DeviceError, Robot, StoredToolFrame

TOLERANCE = 1e-9  # m and rad: the controller must report what was sent


@dataclass(frozen=True)
class ControllerFrames:
    """The running program's tool frame and the stored one (None: the robot keeps none)."""

    running: np.ndarray
    stored: StoredToolFrame | None

    def stored_json(self) -> dict | None:
        return None if self.stored is None else stored_json(self.stored)


def stored_json(stored: StoredToolFrame) -> dict:
    return {"tool_frame": [float(v) for v in stored.tool_frame], "generation": int(stored.generation)}


def stored_from_json(value: dict | None) -> StoredToolFrame | None:
    return None if value is None else StoredToolFrame(np.asarray(value["tool_frame"], float), int(value["generation"]))


def read_frames(robot: Robot) -> ControllerFrames:
    return ControllerFrames(np.asarray(robot.tcp(), dtype=float), robot.stored_tool_frame())


def _write_checked(robot: Robot, target: ControllerFrames) -> str | None:
    """Write both frames and read each back: None when the controller keeps them, else what it reports."""
    running = np.asarray(target.running, dtype=float)
    robot.set_tcp(running)
    readback = np.asarray(robot.tcp(), dtype=float)
    if np.abs(readback - running).max() > TOLERANCE:
        return f"the controller reports the tool frame {readback.tolist()} after {running.tolist()} was written"
    if target.stored is not None:
        robot.store_tool_frame(target.stored)
        back = robot.stored_tool_frame()
        if not target.stored.same_as(back):
            shown = "nothing" if back is None else \
                f"{np.asarray(back.tool_frame).tolist()} generation {back.generation}"
            return (f"the stored tool frame reads back as {shown} after {running.tolist()} generation "
                    f"{target.stored.generation} was written")
    return None


def replace_frames(robot: Robot, target: ControllerFrames) -> tuple[ControllerFrames | None, str | None]:
    """(the frames before, None) when ``target`` is written and read back; (before, why) when
    it was not, with the frames before restored (the message says if that failed too)."""
    try:
        before = read_frames(robot)
    except DeviceError as exc:
        return None, f"the tool frame could not be read before writing, nothing written: {exc}"
    if before.stored is None and target.stored is not None:
        target = ControllerFrames(target.running, None)  # this robot keeps no frame for the program's start
    try:
        failure = _write_checked(robot, target)
    except DeviceError as exc:
        failure = f"writing the tool frame failed: {exc}"
    if failure is None:
        return before, None
    try:
        problem = _write_checked(robot, before)
    except DeviceError as exc:
        problem = str(exc)
    restored = "old frame restored" if problem is None else f"restoring the old frame failed too: {problem}"
    return before, f"{failure}; {restored}"


def write_back(robot: Robot, tool_frame, generation: int) -> tuple[ControllerFrames | None, ControllerFrames,
                                                                    str | None]:
    """A run's tool frame to both places: (before, written, None) or (before, target, why not)."""
    frame = np.asarray(tool_frame, dtype=float)
    target = ControllerFrames(frame, StoredToolFrame(frame, int(generation)))
    before, failure = replace_frames(robot, target)
    if before is not None and before.stored is None:
        target = ControllerFrames(frame, None)
    return before, target, failure
