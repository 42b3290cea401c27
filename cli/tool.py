"""``cellcal tool history|rollback|trend``: the tool frames written to the controller, putting one
back, and a tool's drift history."""
from __future__ import annotations

import json
import time
from pathlib import Path

from cellcal.cli.common import RECORD_ID, STATE_HELP, UsageError, open_store, whole
from cellcal.cli.common import print_progress
from cellcal.config.cells import TOOL_IDS
from cellcal.config.reader import ConfigError
from cellcal.daemon.cells import NoToolMounted, load_cell, mounted_tool, open_drivers
from cellcal.daemon.claims import devices, held
from cellcal.daemon.drift import trend
from cellcal.daemon.frame_writer import NothingToRestore, rollback
from cellcal.drivers.interfaces import DeviceError, RobotState
from cellcal.routines.framework.base import frame_text, tool_frame_json


def cmd_tool_history(args) -> int:
    """Every tool frame written or restored (of --tool), oldest first, each with its tool: the id
    and, where the run's cell file can be read, the tool's name there."""
    store = open_store(args)
    try:
        frames = store.tool_frames(args.tool)
        name = _tool_namer(store)
        for f in frames:
            f["tool_name"] = name(f["run_id"], f["tool_id"])
        if args.json:
            print(json.dumps({"tool_frames": frames}))
            return 0
        if not frames and args.tool is None:
            print("no tool frame written yet")
        elif not frames:
            others = sorted({f["tool_id"] for f in store.tool_frames()} - {None})
            print(f"no tool frame of tool {args.tool} written yet"
                  + (f" (tools with frames written: {', '.join(map(str, others))})" if others else ""))
        for f in frames:
            when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(f["at"]))
            print(f"{f['id']:4d}  {when}  {f['action']:<8} {_tool_label(f['tool_id'], f['tool_name'])}  "
                  f"run {f['run_id']}  {frame_text(f['frame_after'])}"
                  + ("" if f["stored_after"] is None else
                     f"  (program start: generation {f['stored_after']['generation']})"))
        return 0
    finally:
        store.close()


def _tool_label(tool_id: int | None, name: str | None) -> str:
    """"tool 2 (torch)", "tool 2" where its name is not known, "no tool" for a cell without one."""
    if tool_id is None:
        return "no tool"
    return f"tool {tool_id}" + ("" if name is None else f" ({name})")


def _tool_namer(store):
    """name(run_id, tool_id): the tool's name in the cell file the run was recorded on, or None
    (no run, a cell file no longer there or no longer read, no such tool in it). Each file is
    read once."""
    cells: dict[str, object] = {}

    def name(run_id: int | None, tool_id: int | None) -> str | None:
        run = None if run_id is None or tool_id is None else store.run(run_id)
        if run is None:
            return None
        if run.cell not in cells:
            try:
                cells[run.cell] = load_cell(run.cell)
            except (ConfigError, OSError):
                cells[run.cell] = None
        tool = (getattr(cells[run.cell], "tools", None) or {}).get(tool_id)
        return None if tool is None else tool.name

    return name


def cmd_tool_trend(args) -> int:
    """A tool's drift history (read-only): one JSON object with --json, else a few lines; with
    --report DIR also its trend page (DIR/trend.html)."""
    store = open_store(args)
    try:
        rows = store.measured_frames(args.tool)
        if not rows:
            known = store.measured_tools()
            raise UsageError(f"no measured frame of tool {args.tool} in {store.path.parent}"
                             + (f" (tools measured there: {', '.join(map(str, known))})" if known else
                                " (no run there has measured a tool yet)"))
        history = trend(rows, args.tool)
    finally:
        store.close()
    if args.report is not None:
        from cellcal.reports.trend import write_trend_page  # matplotlib loads only when a page is asked for
        try:
            page = write_trend_page(args.report, history)
        except OSError as exc:
            raise UsageError(f"{args.report}: cannot write the trend page there ({exc.strerror or exc})") from None
        print_progress(f"trend page: {page}")
    if args.json:
        print(json.dumps(history))
        return 0
    _print_trend(history)
    return 0


def _print_trend(history: dict) -> None:
    def mm(v):
        return "-" if v is None else f"{v:.4f}"

    first, last, rate, latest = (history["first_calibration"], history["last_calibration"], history["rate"],
                                 history["latest"])
    print(f"tool {history['tool_id']}: {len(history['points'])} measured frames")
    if first is None:
        print("never calibrated here: every check was against the controller's frame")
    else:
        print(f"first full calibration: run {first['run_id']}; last: run {last['run_id']}")
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(latest["at"]))
    print(f"latest: run {latest['run_id']} ({latest['kind']}, {when}): since the first calibration tip "
          f"{mm(latest['since_first_calibration']['tip_mm'])} mm, axis "
          f"{mm(latest['since_first_calibration']['axis_deg'])} deg; since the last: tip "
          f"{mm(latest['since_last_calibration']['tip_mm'])} mm, axis "
          f"{mm(latest['since_last_calibration']['axis_deg'])} deg")
    print(f"rate since the last full calibration ({rate['points']} points, least squares): tip "
          f"{mm(rate['tip_mm_per_week'])} mm/week, {mm(rate['tip_mm_per_1000_runs'])} mm/1000 runs; axis "
          f"{mm(rate['axis_deg_per_week'])} deg/week, {mm(rate['axis_deg_per_1000_runs'])} deg/1000 runs"
          + (f" ({rate['why_none']})" if rate["why_none"] else ""))
    for p in history["points"]:
        since = p["since_last_calibration"]
        print(f"  run {p['run_id']:5d}  {time.strftime('%Y-%m-%d %H:%M', time.localtime(p['at']))}  "
              f"{p['kind']:<11} {p['routine']:<10} {'written' if p['written'] else '       '}  "
              f"tip {mm(since['tip_mm'])} mm  axis {mm(since['axis_deg'])} deg")


def cmd_tool_rollback(args) -> int:
    """Restore the tool frames the controller had before a run's write-back (default: the latest one
    not yet undone): the running program's and the one the robot program applies at its start."""
    store = open_store(args)
    try:
        entry = _write_to_undo(store, args.run, args.tool)  # entry["tool_id"]: whose frame goes back
        cell = load_cell(args.cell)
        _check_same_robot(store.run(entry["run_id"]), cell, args.cell)
        # the robot's claim first: while the service holds the robot, say so plainly; nothing is written
        with held(cell, kinds=("robot",)), open_drivers(cell) as drivers:
            if drivers.robot.state() is not RobotState.READY:
                raise UsageError(f"the robot is not ready ({drivers.robot.state().value}); nothing changed")
            # the tool's block always; the running program's frame only when it is that tool's
            mounted = _is_mounted(cell, drivers, entry["tool_id"])
            try:
                restored, failure = rollback(drivers.robot, entry, mounted)
            except NothingToRestore as exc:
                raise UsageError(str(exc)) from None
        if failure is not None:
            raise DeviceError("robot", f"rollback: {failure}")
        store.record_tool_frame(entry["run_id"], "rollback", restored.frame_before, restored.frame_after,
                                restored.stored_before, restored.stored_after)
        if not mounted:
            print_progress(f"{_tool_label(entry['tool_id'], None)} is not mounted: only its block of stored frames "
                           "was written, the running program's frame (the mounted tool's) is left alone")
        tool = _tool_label(entry["tool_id"], None)
        _print_restored(args, entry["run_id"], restored.frame_after, restored.generation, None if mounted else tool)
        left = [w for w in store.writes_not_undone(entry["tool_id"]) if w["tool_id"] == entry["tool_id"]]
        print_progress(f"the next rollback without RUN undoes run {left[-1]['run_id']}'s write-back ({tool})" if left
                       else f"every recorded write-back of {tool} is now undone: a rollback of it without RUN has "
                            "nothing left to undo")
        return 0
    finally:
        store.close()


def _is_mounted(cell, drivers, tool_id: int | None) -> bool:
    """Whether tool `tool_id` is on the flange now, from the cell file's source of the mounted
    tool (a cell that describes no tool: its one running frame is the tool's)."""
    if not getattr(cell, "tools", None) or tool_id is None:
        return True
    try:
        return mounted_tool(cell, drivers) == tool_id
    except NoToolMounted:
        return False


def _write_to_undo(store, run: int | None, tool: int | None = None) -> dict:
    """The write-back a rollback undoes (its ``tool_id`` the tool whose frame goes back): RUN's,
    else the latest one of `tool` not yet undone; with neither, the latest one not yet undone
    when every such write is of one tool. Each tool's history is walked on its own. Anything
    else is a UsageError saying what to give; nothing is changed."""
    where = store.path.parent
    if run is not None:
        writes = [f for f in store.tool_frames()
                  if f["action"] == "write" and f["frame_before"] is not None and f["run_id"] == run]
        if not writes:
            raise UsageError(f"no write-back of run {run} in {where} (cellcal tool history lists them)")
        entry = writes[-1]
        if tool is not None and entry["tool_id"] != tool:
            raise UsageError(f"run {run} wrote the frame of {_tool_label(entry['tool_id'], None)}, not of tool {tool} "
                             f"(--tool); nothing changed: leave out --tool, or give a run of tool {tool} "
                             f"(cellcal tool history --tool {tool} lists them)")
        return entry
    writes = store.writes_not_undone(tool)
    if not writes:
        done = [f for f in store.tool_frames(tool) if f["action"] == "write"]
        whose = "" if tool is None else f" of tool {tool}"
        others = sorted({w["tool_id"] for w in store.writes_not_undone()} - {None}) if tool is not None else []
        raise UsageError(f"no write-back{whose} to undo in {where}: "
                         + ("every one recorded has been rolled back already" if done else "none recorded")
                         + (f" (tools with write-backs to undo: {', '.join(map(str, others))})" if others else ""))
    tools = sorted({w["tool_id"] for w in writes}, key=lambda t: (t is None, t or 0))
    if len(tools) > 1:
        name = _tool_namer(store)
        latest = {w["tool_id"]: w for w in writes}  # oldest first: each tool's latest wins
        listed = "; ".join(f"{_tool_label(t, name(latest[t]['run_id'], t))}: latest run {latest[t]['run_id']}"
                           for t in tools)
        raise UsageError(f"write-backs of {len(tools)} tools are not undone in {where} ({listed}); give --tool ID "
                         "to say whose to undo (cellcal tool history --tool ID lists its writes); nothing changed")
    return writes[-1]


def _robots(cell) -> str:
    labels = [d.label for d in devices(cell, ("robot",))]
    return ", ".join(labels) if labels else "a simulated robot, in process"


def _check_same_robot(run, cell, given: str) -> None:
    """A rollback gives a frame back to the robot the run wrote it to: the run's cell file, or a
    file of the same cell name and the same robots (a copy, /etc/cellcal/cell.yaml); else UsageError
    naming both."""
    if run is None:
        return
    recorded, path = Path(run.cell), Path(cell.path)
    try:
        if recorded == path or (recorded.exists() and path.exists() and recorded.samefile(path)):
            return
    except OSError:
        pass
    try:
        other = load_cell(recorded)
    except (ConfigError, OSError) as exc:
        raise UsageError(f"run {run.id} was recorded on the cell {recorded}, which cannot be read to compare "
                         f"with --cell {given} ({exc}); give --cell the cell file of the robot run {run.id} "
                         "wrote to") from None
    mine = [d.key for d in devices(cell, ("robot",))]
    if other.name == cell.name and [d.key for d in devices(other, ("robot",))] == mine:
        return
    raise UsageError(f"run {run.id} wrote to the robot of cell {other.name} ({recorded}: {_robots(other)}), not "
                     f"to --cell {given} (cell {cell.name}: {_robots(cell)}); a rollback puts a frame back only "
                     f"on the robot it came from: give --cell {recorded}")


def _print_restored(args, run_id: int, frame, generation: int | None, block_only: str | None = None) -> None:
    """What a rollback put back: one line, or with --json one object ``{"restored": {...}}``:
    ``run_id`` (the run whose write-back was undone), ``tool_frame`` (the frame restored, as a
    run's JSON gives it), ``running`` (whether the running program's frame is now this one:
    false for a tool not mounted, `block_only` its label, whose frame went to its block only) and
    ``program_start_generation`` (the robot program's start frame now that generation; null when
    the controller keeps none)."""
    if args.json:
        print(json.dumps({"restored": {"run_id": run_id, "tool_frame": tool_frame_json(frame),
                                       "running": block_only is None, "program_start_generation": generation}}))
        return
    if block_only is not None:
        print(f"restored {block_only}'s frame from before run {run_id} into its block of stored frames only, for "
              f"its next mounting (the running frame is the mounted tool's): {frame_text(frame)}"
              + ("" if generation is None else f"; generation {generation}"))
        return
    print(f"restored the tool frame from before run {run_id}: {frame_text(frame)}"
          + ("" if generation is None else f"; the robot program's start frame back to generation {generation}"))


def add_parser(sub) -> None:
    tool = sub.add_parser("tool", help="tool frames written to the controller").add_subparsers(dest="what",
                                                                                              required=True)
    p = tool.add_parser("history", help="every tool frame written or restored, each with its tool",
                        description="Every tool frame written to the controller or restored by a rollback, "
                                    "oldest first; each row names its tool (the id in the cell's tool table and, "
                                    "where the run's cell file can be read, its name).")
    p.add_argument("--tool", type=whole(*TOOL_IDS), metavar="ID", help="only the frames of this tool")
    p.add_argument("--state-dir", metavar="DIR", help=STATE_HELP)
    p.add_argument("--json", action="store_true", help='print one JSON object on stdout: {"tool_frames": [...]}, '
                                                       'each with its tool_id and tool_name (null: not known)')
    p.set_defaults(func=cmd_tool_history)
    p = tool.add_parser("rollback", help="restore the tool frame from before a run's write-back (default: the latest)",
                        description="Write back to the robot the tool frames (the running program's and the one "
                                    "the robot program applies at its start) it had before a run's write-back, "
                                    "read them back and compare. Each tool of the cell has its own history. "
                                    "Without RUN: undo the latest write-back of --tool not yet undone, so "
                                    "repeated rollbacks walk back through that tool's history one write-back at a "
                                    "time; --tool may be left out while only one tool has write-backs not undone. "
                                    "With RUN: restore the frames from before RUN's write-back; that undoes RUN's "
                                    "and every later write-back of its tool (with --tool, RUN must be of that "
                                    "tool). The run must have written to the "
                                    "robot of --cell. While the cellcal service holds the robot this is refused "
                                    "(stop the service first); nothing is changed.")
    p.add_argument("run", type=RECORD_ID, nargs="?", metavar="RUN",
                   help="the run whose write-back to undo (a number from cellcal runs list; default: the latest "
                        "not yet undone)")
    p.add_argument("--tool", type=whole(*TOOL_IDS), metavar="ID",
                   help="the tool whose write-back to undo (default: the one tool with write-backs not yet undone; "
                        "needed when several tools have them)")
    p.add_argument("--cell", required=True, metavar="CELL.yaml", help="the cell whose robot gets the frame back")
    p.add_argument("--state-dir", metavar="DIR", help=STATE_HELP)
    p.add_argument("--json", action="store_true", help='print one JSON object on stdout: {"restored": {...}}')
    p.set_defaults(func=cmd_tool_rollback)
    p = tool.add_parser("trend", help="a tool's drift history: its change since the first and the last full "
                                      "calibration, and the rate",
                        description="Every tool frame measured for the tool (full calibrations and checks), as "
                                    "the change of the tip (mm) and of the axis (deg) against the first and "
                                    "against the last full calibration, with the drift rate since the last one "
                                    "(least squares straight line: mm and deg per week and per 1000 runs). "
                                    "Read-only: never makes a store.")
    p.add_argument("--tool", type=whole(*TOOL_IDS), default=1, metavar="ID",
                   help="the tool's id (default 1: the cell's one tool)")
    p.add_argument("--state-dir", metavar="DIR", help=STATE_HELP)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout: the whole trend")
    p.add_argument("--report", metavar="DIR", help="also write the tool's trend page (DIR/trend.html and its plot)")
    p.set_defaults(func=cmd_tool_trend)
