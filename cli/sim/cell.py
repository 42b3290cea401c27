"""``cellcal sim-cell``: every fake of a networked cell file, as one long-running process.

What is started and how it is wired is :mod:`cellcal.sims.net.cell`'s; this is the
command. One line on stdout says everything is listening; SIGTERM or SIGINT shuts down
cleanly. ``--tool ID`` starts it with that tool of the cell's table mounted;
``--mount-tool ID``, from another shell, changes the tool of the sim-cell running for that
cell file (a tool change at the tool changer) and exits. ``--time-scale K`` runs the cell's
simulated clock K times faster than the wall (default 1: real time). Exit 2 for a bad cell file or a
tool the cell lacks, 1 when a fake cannot start (a port in use) or the running sim-cell
does not answer or refuses the change (the arm moving).
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading

from cellcal.cli.common import number
from cellcal.sims.net.cell import SimCell, SimCellError, mount_tool_on_running
from cellcal.sims.physics.clock import MAX_TIME_SCALE
from cellcal.daemon.cells import CellFileError, load_cell


def cmd_sim_cell(args) -> int:
    try:
        cell = load_cell(args.cell)
        if args.mount_tool is not None:
            return _mount_tool(cell, args.mount_tool)
        if args.tool is not None:
            cell = cell.with_tool(args.tool)  # CellFileError for a tool the table lacks
        sim = SimCell(cell, time_scale=args.time_scale)
    except CellFileError as exc:
        print(f"cellcal sim-cell: error: {exc}", file=sys.stderr)
        return 2
    stopping = threading.Event()
    # set from a thread of its own: the handler runs in the main thread, which may hold the Event's
    # lock at that moment (inside stopping.wait), and setting it there would deadlock
    previous = {sig: signal.signal(sig, lambda *_: threading.Thread(target=stopping.set).start())
                for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        try:
            sim.start()
        except SimCellError as exc:
            print(f"cellcal sim-cell: {exc}", file=sys.stderr)
            return 1
        print(sim.addresses.listening_line(), flush=True)
        while not stopping.wait(0.2):
            if sim.fake_ur is None or not sim.fake_ur.alive:
                print(f"cellcal sim-cell: the {getattr(sim.fake_ur, 'what', 'fake controller')} ended", file=sys.stderr)
                return 1
        return 0
    finally:
        sim.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _mount_tool(cell, tool_id: int) -> int:
    """The tool change on the running sim-cell; one line on stdout says what is mounted."""
    try:
        reply = mount_tool_on_running(cell, tool_id)
    except SimCellError as exc:
        print(f"cellcal sim-cell: {exc}", file=sys.stderr)
        return 1
    said = [f"tool {tool_id} ({cell.tools[tool_id].name}) mounted" if tool_id else "no tool mounted"]
    if cell.mounted_source.kind == "robot_inputs":
        said.append(f"robot digital inputs 0x{reply['digital_inputs']:x}")
    if reply.get("panel_register") is not None:
        said.append(f"panel register {reply['panel_register']}: {tool_id}")
    print(f"cellcal sim-cell: {'; '.join(said)}", flush=True)
    return 0


def _tool_id(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a tool id (an integer)") from None
    if not 0 <= value <= 255:
        raise argparse.ArgumentTypeError(f"{value} is not a tool id: 1..255 (0: no tool)")
    return value


def add_parser(sub) -> None:
    p = sub.add_parser("sim-cell", help="serve the fakes of a networked simulated cell until stopped",
                       description="Start the robot controller's fake (a fake UR controller for driver ur_rtde; "
                                   "a simulated Franka arm, franky-sim on MuJoCo, for driver franka: the franka "
                                   "extra), the Modbus IO module (panel and trigger ring) and the tracker server a "
                                   "cell file's drivers connect to, wired to one simulated arm and beam. Runs until "
                                   "SIGTERM or SIGINT.")
    p.add_argument("--cell", default="sim-net", metavar="CELL.yaml",
                   help="cell file, or the name of a shipped cell (default: sim-net)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--tool", type=_tool_id, metavar="ID",
                       help="start with this tool of the cell's tool table mounted (default: the file's mounted one)")
    which.add_argument("--mount-tool", type=_tool_id, metavar="ID",
                       help="do not start: change the tool of the sim-cell running for this cell file to ID "
                            "(0: none), as at the tool changer, and exit")
    p.add_argument("--time-scale", type=number(0.0, MAX_TIME_SCALE, above=True), default=1.0, metavar="K",
                   help=f"run the simulated clock K times faster than the wall: the arm moves K times as fast, "
                        f"every timestamp stays simulated time (0 < K <= {MAX_TIME_SCALE:g}; default 1, real time)")
    p.set_defaults(func=cmd_sim_cell)
