"""``cellcal tool history|rollback``: the tool frames written to the controller, and putting one back."""
from __future__ import annotations

import json
import time

import numpy as np

from cellcal.cli.common import STATE_HELP, UsageError, open_store
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.daemon.write_back import ControllerFrames, replace_frames, stored_from_json
from cellcal.drivers.interfaces import DeviceError, RobotState
from cellcal.routines.base import frame_text


def cmd_tool_history(args) -> int:
    store = open_store(args)
    try:
        frames = store.tool_frames()
        if args.json:
            print(json.dumps(frames))
            return 0
        if not frames:
            print("no tool frame written yet")
        for f in frames:
            when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(f["at"]))
            print(f"{f['id']:4d}  {when}  {f['action']:<8} run {f['run_id']}  {frame_text(f['frame_after'])}"
                  + ("" if f["stored_after"] is None else
                     f"  (program start: generation {f['stored_after']['generation']})"))
        return 0
    finally:
        store.close()


def cmd_tool_rollback(args) -> int:
    """Restore the tool frames the controller had before a run's write-back (default: the latest):
    the running program's and the one the robot program applies at its start."""
    store = open_store(args)
    try:
        writes = [f for f in store.tool_frames() if f["action"] == "write" and f["frame_before"] is not None]
        if args.run is not None:
            writes = [f for f in writes if f["run_id"] == args.run]
        if not writes:
            raise UsageError("no write-back to roll back" + (f" for run {args.run}" if args.run else ""))
        entry = writes[-1]
        frame = np.asarray(entry["frame_before"], dtype=float)
        target = ControllerFrames(frame, stored_from_json(entry["stored_before"]))
        cell = load_cell(args.cell)
        with open_drivers(cell) as drivers:
            if drivers.robot.state() is not RobotState.READY:
                raise UsageError(f"the robot is not ready ({drivers.robot.state().value}); nothing changed")
            current, failure = replace_frames(drivers.robot, target)
        if failure is not None:
            raise DeviceError("robot", f"rollback: {failure}")
        store.record_tool_frame(entry["run_id"], "rollback", current.running, frame, current.stored_json(),
                                target.stored_json() if current.stored is not None else None)
        print(f"restored the tool frame from before run {entry['run_id']}: {frame_text(frame)}"
              + ("" if current.stored is None or target.stored is None else
                 f"; the robot program's start frame back to generation {target.stored.generation}"))
        return 0
    finally:
        store.close()


def add_parser(sub) -> None:
    tool = sub.add_parser("tool", help="tool frames written to the controller").add_subparsers(dest="what",
                                                                                              required=True)
    p = tool.add_parser("history", help="every tool frame written or restored")
    p.add_argument("--state-dir", metavar="DIR", help=STATE_HELP)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_tool_history)
    p = tool.add_parser("rollback", help="restore the tool frame from before a run's write-back (default: the last)")
    p.add_argument("run", type=int, nargs="?", metavar="RUN")
    p.add_argument("--cell", required=True, metavar="CELL.yaml", help="the cell whose robot gets the frame back")
    p.add_argument("--state-dir", metavar="DIR", help=STATE_HELP)
    p.set_defaults(func=cmd_tool_rollback)
