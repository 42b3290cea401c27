"""The service: the daemon's core, independent of how it is started (CLI, tests), composed of
three rooms that share its cell, its devices and its store:

* :mod:`.runs`: one run as a state machine, from the start button to a tool frame written
  to the controller (checking, running, solving, gates, writing back), built on a run context
  read once at its start;
* :mod:`.panel`: the panel protocol (start, abort and confirm buttons, lamps, result code and
  outcome registers; the operator at the panel a routine asks);
* :mod:`.tool_custody`: which tool a run is for, the mounted tool's frame on a tool change,
  the frames owed back to the robots after a run that wrote none, and reconnecting a robot
  whose connection was lost.

The routines set the tool as drawn while they measure. A run that writes no frame gives
the controller back the one it had before; when a fault leaves the robot unable to take
it (a safety stop, a lost connection), the idle loop gives it back once the robot is
ready again, reconnecting a robot whose connection was lost, and no run starts before.
"""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from cellcal.daemon.cells import Cell, CellDrivers
from cellcal.daemon.frame_writer import tools_without_block
from cellcal.daemon.notify import Notifier
from cellcal.daemon.panel import PanelOperator, PanelProtocol, panel_routines
from cellcal.daemon.result_codes import RESULT_MEANINGS, ResultCode
from cellcal.daemon.runs import RunEnd, RunMachine
from cellcal.daemon.store import Store
from cellcal.daemon.tool_custody import ToolCustody
from cellcal.drivers.interfaces import DeviceError

__all__ = ["RESULT_MEANINGS", "PanelOperator", "ResultCode", "RunEnd", "Service", "panel_routines"]

log = logging.getLogger("cellcal.daemon")


class Service:
    """The daemon's core: `cell` and its opened `drivers`, the results `store`; `report`:
    callable(run_id, result, store, ending) -> path of the run's report (``ending``: how
    the run ended, its headline), or None; `trend`:
    callable(tool_id, trend dict) -> path of the tool's trend page, or None; `reconnect`:
    callable() -> a fresh set of the cell's drivers, or None."""

    def __init__(self, cell: Cell, drivers: CellDrivers, store: Store, *, out_dir: str | Path,
                 notifier: Notifier | None = None, routines: dict[int, str] | None = None, report=None,
                 reconnect=None, trend=None):
        self.cell, self.drivers, self.store = cell, drivers, store
        self.out_dir = Path(out_dir)
        self.notifier = notifier or Notifier({})
        self.routines = dict(panel_routines() if routines is None else routines)
        self.report, self.trend = report, trend
        self.state = "idle"
        self.abort = threading.Event()
        self._worker: threading.Thread | None = None
        self.active = False  # a run is under way: from start() until its end state is decided
        self.run_id: int | None = None  # the run under way (or the last), once the store has it
        self.last: RunEnd | None = None
        # what status() reports, each kept current by the thread that knows it (plain attribute
        # writes: a reader never takes a lock the run or the panel loop holds)
        self.seen = {"routine": None, "progress": None, "since": time.time(), "robot": None, "last_run": None,
                     "waiting": None, "mounted_read_at_run": None}
        self.panel = PanelProtocol(self)
        self.custody = ToolCustody(self, reconnect)
        self.runs = RunMachine(self)
        self._last_run_from_store()

    def _last_run_from_store(self) -> None:
        """After a restart: the last run the store holds (one the previous process died in is
        INTERRUPTED by now) is what the panel shows, so the status says it too."""
        try:
            rows = self.store.runs(1)
        except Exception as exc:  # a store that cannot be read is said by the first run's end
            log.warning("the last run could not be read from the store: %s", exc)
            return
        if rows and rows[0].result_code is not None:
            row = rows[0]
            self.last_run_ended(row.id, row.routine, row.state, row.result_code, row.reason, row.verdict,
                                row.finished_at or row.started_at)

    def last_run_ended(self, run_id: int, routine: str, state: str, code: int, reason: str | None,
                       verdict, at: float | None = None) -> None:
        """What status() says of the last finished run (kept apart from the one under way)."""
        try:
            name = ResultCode(code).name
        except ValueError:
            name = str(code)
        self.seen["last_run"] = {"id": run_id, "routine": routine, "state": state, "result_code": int(code),
                                 "result": name, "reason": reason,
                                 "verdict": None if verdict is None else str(verdict),
                                 "at": time.time() if at is None else at,
                                 # the panel's fault lamp after it (docs/panel.md): a refusal or a fault
                                 "fault_lamp": state in ("fault", "refused", "interrupted")}

    # -- what the rooms share ---------------------------------------------------------------

    def event(self, kind: str, message: str | None) -> None:
        """An event in the store; a store that cannot take it is logged, never fatal here."""
        try:
            self.store.event(kind, message)
        except Exception as exc:
            log.error("the results store did not take the event %s (%s): %s", kind, message, exc)

    def progress(self, run_id: int, message: str) -> None:
        self.seen["progress"] = message
        log.info("run %d: %s", run_id, message)

    def transition(self, run_id: int | None, state: str, message: str | None = None) -> None:
        self.seen["since"] = time.time()
        if state == "checking":
            self.seen["progress"] = None
        self.state = state
        tag = f"run {run_id}: " if run_id is not None else ""
        log.info("%s%s%s", tag, state, f": {message}" if message else "")
        # begin_run records "checking" and finish_run the final state, each in its own transaction
        if run_id is not None and state not in ("checking", "done", "fault", "refused", "aborted"):
            self.store.record_state(run_id, state, message)
        self.notifier.status(f"{state}{f' (run {run_id})' if run_id is not None else ''}")
        self.panel.show_state(state)

    # -- the panel ------------------------------------------------------------------------

    def poll_panel(self) -> None:
        self.panel.poll()

    def discard_requests(self, why: str) -> None:
        self.panel.discard_requests(why)

    def announce_interrupted(self, run_ids: list[int]) -> None:
        self.panel.announce_interrupted(run_ids)

    # -- one run --------------------------------------------------------------------------

    def busy(self) -> bool:
        return self.active

    def start(self, routine: str, tool: int = 0) -> None:
        """Start a run in the worker thread (returns at once); `tool`: the tool the operator
        selected (0: whichever is mounted)."""
        if self.busy():
            raise RuntimeError("a run is already going on")
        if self._worker is not None:  # the last run's final panel writes
            self._worker.join()
        self.abort.clear()
        self.active = True
        self.run_id = None
        self._worker = threading.Thread(target=self._run_safely, args=(routine, tool), name="cellcal-run",
                                        daemon=True)
        self._worker.start()

    def wait(self, timeout_s: float | None = None) -> RunEnd | None:
        if self._worker is not None:
            self._worker.join(timeout_s)
        return self.last

    def request_abort(self, why: str) -> None:
        """Stop the motion now; the worker ends the run as aborted."""
        if not self.busy():
            return
        log.warning("abort: %s", why)
        self.abort.set()
        try:
            self.drivers.robot.stop()
        except DeviceError as exc:
            log.warning("stop after abort failed: %s", exc)

    def _run_safely(self, routine: str, tool: int = 0) -> None:
        try:
            self.last = self.run(routine, tool)
        except Exception as exc:
            log.exception("run %s: the service failed", self.run_id)
            self.last = self.runs.end_broken(routine, exc)
        finally:
            self.active = False

    def run(self, routine: str, tool: int = 0) -> RunEnd:
        """One run in the calling thread (:meth:`.runs.RunMachine.run`)."""
        return self.runs.run(routine, tool)

    # -- the tool frames ------------------------------------------------------------------

    def recover(self) -> None:
        self.custody.recover()

    def resume_owed_frame(self) -> int | None:
        return self.custody.resume_owed_frame()

    def held_frame(self, tool_id: int):
        return self.custody.held_frame(tool_id)

    @property
    def _reconnecting(self) -> threading.Thread | None:
        return self.custody.reconnecting

    def announce_tool_blocks(self) -> None:
        """Said once at the start: each tool of the cell's table whose frame this robot keeps in
        no register block (the registers ran out): its writes reach the running program only."""
        try:
            notes = tools_without_block(self.cell, self.drivers.robot)
        except DeviceError as exc:
            log.warning("the robot's blocks of stored tool frames could not be told: %s", exc)
            return
        for note in notes:
            log.warning("%s", note)

    # -- status -----------------------------------------------------------------------------

    def status(self) -> dict:
        """What the service is doing, for the status page and its API: a fresh dict built from
        what the run and the panel loop last recorded, without calling a device or taking a
        lock (safe from any thread, and never slows a run)."""
        seen, drivers, custody = dict(self.seen), self.drivers, self.custody
        tool = self.cell.tools.get(custody.run_tool)
        last = seen["last_run"]
        devices = {"robot": "reconnecting" if custody.reconnecting is not None else (seen["robot"] or "unknown"),
                   "panel": "none" if drivers.panel is None else ("ok" if self.panel.ok else "lost"),
                   # used during runs only: "open" since the service started, a failure shows
                   # as the run's fault (result code and reason)
                   **{kind: "open" for kind, device in (("trigger", drivers.trigger),
                                                        ("tracker", drivers.tracker)) if device is not None}}
        source = self.cell.mounted_source
        mounted = None if tool is None else {
            "id": tool.id, "name": tool.name, "source": source.describe(),
            # read from the panel or the tool changer at each start: as of that start's run (None: not
            # read since the service started); the cell file's `mounted` holds always
            "read_at_run": None if source.kind == "file" else seen["mounted_read_at_run"]}
        waiting = seen["waiting"]
        if waiting is not None:
            waiting = {**waiting, "time_left_s": max(0.0, waiting["until"] - time.time())}
        return {"state": self.state, "run_id": self.run_id if self.active else None,
                "last_run_id": None if last is None else last["id"], "routine": seen["routine"],
                "progress": seen["progress"] if self.active else None, "since": seen["since"],
                # the last finished run's, as earlier versions of the API said them
                **{key: None if last is None else last[key] for key in ("reason", "result_code", "result")},
                "last_run": last, "waiting": waiting,
                "health": health(self.state, self.active, last, devices, waiting, custody.owed.run_of()),
                "mounted_tool": mounted, "devices": devices,
                "frame_owed_by_run": custody.owed.run_of(),
                "cell": {"name": self.cell.name}}


ROBOT_FAULTS = ("disconnected", "protective stop", "emergency stop")  # RobotState's values a run cannot start from


def health(state: str, active: bool, last: dict | None, devices: dict, waiting: dict | None,
           owed_by: int | None) -> dict:
    """The headline of the status page: ``level`` (``ok``, ``running``, ``waiting``, ``attention``
    or ``fault``) and ``says``, the state with what is wrong beside it: a robot that is not ready,
    a panel lost, the fault lamp of the last run, a frame still owed to the controller."""
    problems, level = [], "ok"
    robot = devices.get("robot")
    if robot in ROBOT_FAULTS:
        problems.append(f"robot {robot}")
        level = "fault"
    elif robot not in ("ready", None):  # reconnecting, not read yet, another program running on it
        problems.append(f"robot {robot}")
        level = "attention"
    if devices.get("panel") == "lost":
        problems.append("panel lost")
        level = "fault" if level == "fault" else "attention"
    if owed_by is not None:
        problems.append(f"run {owed_by}'s tool frame not yet given back to the controller")
        level = "fault" if level == "fault" else "attention"
    if active:
        if waiting is not None:
            head, level = f"waiting for the operator: {waiting['message']}", "waiting"
        else:
            head, level = ("running" if state == "running" else f"running: {state}"), "running"
    else:
        head = state
        if last is not None and last["fault_lamp"]:
            problems.append(f"the last run ({last['id']}, {last['routine']}) ended {last['state']}: "
                            f"{last['result_code']} {last['result']}")
            level = "fault"
    return {"level": level, "says": "; ".join([head, *problems])}


