"""``cellcal sim-cell``: every fake of a networked cell file, as one long-running process.

What is started and how it is wired is :mod:`cellcal.sims.net.cell`'s; this is the
command. One line on stdout says everything is listening; SIGTERM or SIGINT shuts down
cleanly. Exit 2 for a bad cell file, 1 when a fake cannot start (a port in use).
"""
from __future__ import annotations

import signal
import sys
import threading

from cellcal.sims.net.cell import SimCell, SimCellError
from cellcal.daemon.cells import CellFileError, load_cell


def cmd_sim_cell(args) -> int:
    try:
        cell = load_cell(args.cell)
        sim = SimCell(cell)
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
                print("cellcal sim-cell: the fake UR controller ended", file=sys.stderr)
                return 1
        return 0
    finally:
        sim.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def add_parser(sub) -> None:
    p = sub.add_parser("sim-cell", help="serve the fakes of a networked simulated cell until stopped",
                       description="Start the fake UR controller, the Modbus IO module (panel and trigger "
                                   "ring) and the tracker server a cell file's drivers connect to, wired to "
                                   "one simulated arm and beam. Runs until SIGTERM or SIGINT.")
    p.add_argument("--cell", default="sim-net", metavar="CELL.yaml",
                   help="cell file, or the name of a shipped cell (default: sim-net)")
    p.set_defaults(func=cmd_sim_cell)
