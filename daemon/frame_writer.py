"""A tool frame to the robot controller, read back and compared, or the old one put back.

The frame goes to two places of the controller (:class:`~cellcal.drivers.interfaces.Robot`):

* the running program's tool frame (``set_tcp``), which the controller reports back (``tool_frame``);
* the frame the robot program applies at its next start (``store_tool_frame``), on robots that
  keep one (the robot's driver says where: docs/robots.md "What each robot keeps"). Its generation is
  the run whose result it is. A cell with a tool table keeps one per tool, each in its own
  block (slot) of the robot's: :func:`tool_slot`. A tool whose block the robot does not
  have (the registers ran out) gets the running program's frame only (:func:`no_block_note`).

Both are read before anything is written, and each is read back after its write and compared
(exactly: the values travel as doubles). On a mismatch or a device error, both are written as
they were before and read back again; the message says whether that worked. The same
function serves ``cellcal tool rollback``, which writes an older pair (:func:`rollback`): the
running frame only when the tool is the mounted one, its block always.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cellcal.config.cells import tool_blocks
from cellcal.drivers.interfaces import DeviceError, Robot, StoredToolFrame

TOLERANCE = 1e-9  # m and rad: the controller must report what was sent


@dataclass(frozen=True)
class ControllerFrames:
    """The running program's tool frame (None: left as it is, it is another tool's) and the
    stored one in block `slot` (None: the robot keeps none for this tool)."""

    running: np.ndarray | None
    stored: StoredToolFrame | None
    slot: int | None = 0

    def stored_json(self) -> dict | None:
        return None if self.stored is None else stored_json(self.stored, self.slot)


def stored_json(stored: StoredToolFrame, slot: int | None = 0) -> dict:
    """As the store keeps it: {"tool_frame", "generation", "slot"} (the block it is in)."""
    return {"tool_frame": [float(v) for v in stored.tool_frame], "generation": int(stored.generation),
            "slot": int(slot or 0)}


def stored_from_json(value: dict | None) -> StoredToolFrame | None:
    return None if value is None else StoredToolFrame(np.asarray(value["tool_frame"], float), int(value["generation"]))


def slot_from_json(value: dict | None) -> int | None:
    """The block a stored frame was in (a row from before tool tables: block 0); None: none stored."""
    return None if value is None else int(value.get("slot", 0))


def tool_slot(cell, tool_id: int) -> int | None:
    """The block of the robot's stored tool frames that is tool `tool_id`'s: its ``frame_block``
    in the cell's tool table, else its place there (file order; a file's one ``tool``: 0). A
    cell that describes no tool has the one frame, block 0; None: the table has no such tool."""
    tools = cell.tools
    if not tools:
        return 0
    return tool_blocks(tools).get(int(tool_id))


def keeps_block(robot: Robot, slot: int | None) -> bool:
    """Whether the robot keeps a frame for its program's start in block `slot`."""
    return slot is not None and 0 <= int(slot) < int(robot.tool_frame_slots())


def no_block_note(robot: Robot, tool_id: int, slot: int | None) -> str | None:
    """Why tool `tool_id`'s frame reaches only the running program: the robot keeps stored
    frames, and none in the tool's block (the registers ran out). None when it has its block,
    and for a robot that keeps no stored frame at all (then no tool has one)."""
    slots = int(robot.tool_frame_slots())
    if slots == 0 or keeps_block(robot, slot):
        return None
    which = "" if slot is None else f"it would take block {slot}; "
    return (f"tool {tool_id} has no register block on this robot ({which}{robot.tool_frame_slots_text()}): its "
            "frame lasts until the program stops, and the robot program keeps its installation's TCP for it at "
            "its next start")


def tools_without_block(cell, robot: Robot) -> list[str]:
    """:func:`no_block_note` for every tool of the cell's table that has none (the daemon says
    them once at its start)."""
    tools = cell.tools
    return [note for tool_id in tools if (note := no_block_note(robot, tool_id, tool_slot(cell, tool_id)))]


def read_frames(robot: Robot, slot: int | None = 0, running=None) -> ControllerFrames:
    """The running frame, and the stored one of block `slot` where the robot keeps that block.
    `running`: the running frame when it is known already (a run read it at its start), not read again."""
    kept = keeps_block(robot, slot)
    running = robot.tool_frame() if running is None else running
    return ControllerFrames(np.asarray(running, dtype=float), robot.stored_tool_frame(slot) if kept else None,
                            slot if kept else None)


def _write_checked(robot: Robot, target: ControllerFrames) -> str | None:
    """Write both frames and read each back: None when the controller keeps them, else what it reports."""
    if target.running is not None:
        running = np.asarray(target.running, dtype=float)
        robot.set_tcp(running)
        readback = np.asarray(robot.tool_frame(), dtype=float)
        if np.abs(readback - running).max() > TOLERANCE:
            return f"the controller reports the tool frame {readback.tolist()} after {running.tolist()} was written"
    if target.stored is not None:
        robot.store_tool_frame(target.stored, target.slot)
        back = robot.stored_tool_frame(target.slot)
        if not target.stored.same_as(back):
            shown = "nothing" if back is None else \
                f"{np.asarray(back.tool_frame).tolist()} generation {back.generation}"
            return (f"the stored tool frame reads back as {shown} after "
                    f"{np.asarray(target.stored.tool_frame).tolist()} generation {target.stored.generation} "
                    f"was written (block {target.slot})")
    return None


def replace_frames(robot: Robot, target: ControllerFrames, running_before=None
                   ) -> tuple[ControllerFrames | None, str | None]:
    """(the frames before, None) when ``target`` is written and read back; (before, why) when
    it was not, with the frames before restored (the message says if that failed too). A
    target without a running frame leaves the running program's alone. `running_before`: the
    running frame before, when known (:func:`read_frames`)."""
    try:
        before = read_frames(robot, target.slot, running_before)
    except DeviceError as exc:
        return None, f"the tool frame could not be read before writing, nothing written: {exc}"
    if before.stored is None and target.stored is not None:
        target = replace(target, stored=None)  # this robot keeps no frame in that block for the program's start
    try:
        failure = _write_checked(robot, target)
    except DeviceError as exc:
        failure = f"writing the tool frame failed: {exc}"
    if failure is None:
        return before, None
    try:
        problem = _write_checked(robot, before if target.running is not None else replace(before, running=None))
    except DeviceError as exc:
        problem = str(exc)
    restored = "old frame restored" if problem is None else f"restoring the old frame failed too: {problem}"
    return before, f"{failure}; {restored}"


def write_tool_frame(robot: Robot, tool_frame, generation: int, slot: int | None = 0, running_before=None
                     ) -> tuple[ControllerFrames | None, ControllerFrames, str | None]:
    """A run's tool frame to both places, the stored one in block `slot` (None, or a block the
    robot does not keep: the running frame only): (before, written, None) or (before, target,
    why not). `running_before`: the controller's running frame before, when the run knows it."""
    frame = np.asarray(tool_frame, dtype=float)
    target = ControllerFrames(frame, StoredToolFrame(frame, int(generation)), slot)
    if not keeps_block(robot, slot):
        target = ControllerFrames(frame, None, None)
    before, failure = replace_frames(robot, target, running_before)
    if before is not None and before.stored is None:
        target = ControllerFrames(frame, None, None)
    return before, target, failure


@dataclass(frozen=True)
class Restored:
    """What a rollback changed: the tool's frame before and after it (the running frame's when
    the tool is mounted, else its block's), and the stored ones as the store keeps them."""

    frame_before: np.ndarray | None
    frame_after: np.ndarray
    stored_before: dict | None
    stored_after: dict | None
    generation: int | None  # the generation restored to the block (None: no block written)


class NothingToRestore(ValueError):
    """The tool is not mounted and the write kept nothing in a block: no frame of it to restore."""


def rollback(robot: Robot, entry: dict, mounted: bool) -> tuple[Restored | None, str | None]:
    """Put back the frames from before the write `entry` (a row of the store's tool frames):
    its block as it was (the slot it was written to; a row from before tool tables: block 0),
    and the running frame only when its tool is `mounted` (else the running program's frame is
    the mounted tool's). (what changed, None), or (None, why it failed: the frames before are
    restored, the message says whether that worked). Raises NothingToRestore, nothing written,
    when the tool is not mounted and has no block to restore."""
    frame = np.asarray(entry["frame_before"], dtype=float)
    stored, slot = stored_from_json(entry["stored_before"]), slot_from_json(entry["stored_before"])
    if not mounted and stored is None:
        raise NothingToRestore(
            f"tool {entry.get('tool_id')} is not mounted and its write-back of run {entry['run_id']} kept no frame "
            "for the program's start (the robot has no register block for it): its frame lived only in the running "
            "program; nothing changed (mount the tool and roll back again)")
    if not mounted and not keeps_block(robot, slot):
        raise NothingToRestore(
            f"tool {entry.get('tool_id')} is not mounted, and this robot has no block {slot} for its frame now "
            f"({robot.tool_frame_slots_text()}); nothing changed (check tool_frame_register)")
    target = ControllerFrames(frame if mounted else None, stored, slot)
    before, failure = replace_frames(robot, target)
    if failure is not None:
        return None, failure
    kept = before.stored is not None and stored is not None
    if mounted:
        changed_from = before.running
    else:
        changed_from = np.asarray(before.stored.tool_frame if before.stored is not None else entry["frame_after"])
    return Restored(changed_from, frame, before.stored_json(), target.stored_json() if kept else None,
                    stored.generation if kept else None), None
