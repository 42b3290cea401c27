"""The service: one explicit state machine from the operator's start button to a written-back
tool frame, and everything that may go wrong on the way.

    idle -> checking -> running -> solving -> gates -> writing back -> done
                  \\          \\         \\        \\            \\
                   refused    fault/aborted      fault        fault (old frame kept)

* checking: the robot is ready, the routine is one this cell can run, its plan passes the
  cell's limits, the sensors it needs answer. A failure here is *refused*: nothing moved.
* running: the routine moves and records (in a worker thread: the main loop keeps serving
  the panel and the signals); the dataset is on disk before solving.
* gates: a result that fails any gate is never written (state fault, code GATE_FAILED);
  nor is a check's (tcp-check) in alarm (CHECK_ALARM), or one whose measured frame has
  drifted beyond the tool's drift alarm since the last full calibration (DRIFT_ALARM,
  :mod:`.drift`). Every measured tool frame goes into the tool's drift history.
* writing back: the tool frame goes to the controller, is read back and compared; the
  frame before is kept in the store, so ``cellcal tool rollback`` can restore it.

Every transition is one log line with the run id (journald-friendly), a row in the
store, and the panel's lamps and result code. The abort button and SIGTERM/SIGINT stop
the motion at once; the run is recorded as aborted and nothing is written back.

The routines set the tool as drawn while they measure. A run that writes no frame gives
the controller back the one it had before; when a fault leaves the robot unable to take
it (a safety stop, a lost connection), the idle loop gives it back once the robot is
ready again, reconnecting a robot whose connection was lost, and no run starts before.
"""
from __future__ import annotations

import enum
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellcal.drivers.interfaces import DeviceError, DeviceTimeout, Operator, OperatorTimeout, RobotState
from cellcal.routines.framework import registry, runner, tool_frame
from cellcal.config.reader import ConfigError
from cellcal.routines.framework.base import CheckAlarm, PlanRefused, Result, RoutineAborted, RoutineError
from cellcal.routines.framework.frames_owed import FramesOwed
from cellcal.routines.framework.gates import frame_change
from cellcal.daemon import cells, drift, outcome
from cellcal.daemon.notify import Notifier
from cellcal.daemon.store import Store
from cellcal.daemon.write_back import TOLERANCE, no_block_note, tool_slot, tools_without_block, write_back

log = logging.getLogger("cellcal.daemon")

RECONNECT_AFTER_S = 2.0  # a robot unusable this long is reconnected (a busy moment is not a lost link)
RECONNECT_EVERY_S = 5.0  # and tried again this often while it stays lost


class ResultCode(enum.IntEnum):
    """The panel's result register: why the last run ended as it did (docs/panel.md)."""

    OK = 0
    NOT_READY = 10
    NO_SUCH_ROUTINE = 11
    LIMITS = 12
    BUSY = 13
    TOOL_NOT_MOUNTED = 14
    SENSOR_FAULT = 20
    ROBOT_FAULT = 21
    DEVICE_TIMEOUT = 22
    COMPUTATION_FAILED = 30
    GATE_FAILED = 31
    WRITE_BACK_FAILED = 32
    CHECK_ALARM = 33
    DRIFT_ALARM = 34
    ABORTED = 40
    INTERRUPTED = 41
    CONFIRM_TIMEOUT = 42
    SERVICE_FAULT = 50


RESULT_MEANINGS = {
    ResultCode.OK: "the run passed every gate and its tool frame was written back and read back",
    ResultCode.NOT_READY: "start refused: the robot is not ready (protective or emergency stop, not connected)",
    ResultCode.NO_SUCH_ROUTINE: "start refused: the routine selector names no routine this cell can run",
    ResultCode.LIMITS: "start refused: the routine's plan would leave the cell's limits; nothing moved",
    ResultCode.BUSY: "start refused: a routine is already running (the press is ignored)",
    ResultCode.TOOL_NOT_MOUNTED: "start refused: no tool is mounted (or one the cell lacks), or the tool selector "
                                 "names another tool than the mounted one or one the cell does not have; nothing "
                                 "moved",
    ResultCode.SENSOR_FAULT: "the trigger or the tracker failed or went silent; motion stopped",
    ResultCode.ROBOT_FAULT: "the robot faulted (connection lost, protective or emergency stop); motion stopped",
    ResultCode.DEVICE_TIMEOUT: "the robot controller did not answer in time (stalled); motion stopped",
    ResultCode.COMPUTATION_FAILED: "the measurements could not be solved (the routine says why)",
    ResultCode.GATE_FAILED: "the result failed a quality gate and was not written back",
    ResultCode.WRITE_BACK_FAILED: "the controller did not keep the written tool frame; the old one was restored",
    ResultCode.CHECK_ALARM: "the tool check found the tool beyond its outer band, or could not tell: nothing "
                            "written; calibrate it deliberately (or replace a bent tool)",
    ResultCode.DRIFT_ALARM: "the tool check found the tool drifted beyond its drift alarm since the last full "
                            "calibration (the reason gives the numbers): nothing written; calibrate it",
    ResultCode.ABORTED: "aborted by the operator or by a stop of the service; nothing written back",
    ResultCode.INTERRUPTED: "the service died during the run; found at the next start, nothing written back",
    ResultCode.CONFIRM_TIMEOUT: "the routine waited for the operator's confirm (the plate moved to its next "
                                "placement) longer than its confirm_timeout_s; motion had stopped, nothing "
                                "written",
    ResultCode.SERVICE_FAULT: "the service could not keep its own records (state folder, datasets, store); "
                              "nothing written back",
}


def panel_routines() -> dict[int, str]:
    """The routine selector register's values (docs/panel.md) -> routine names: each routine
    class declares its own ``selector`` (:func:`cellcal.routines.framework.registry.panel_selectors`)."""
    return registry.panel_selectors()


@dataclass
class RunOutcome:
    run_id: int
    state: str
    code: ResultCode
    reason: str
    result: Result | None = None


class Service:
    """The daemon's core, independent of how it is started (CLI, tests)."""

    def __init__(self, cell, drivers, store: Store, *, out_dir: str | Path, notifier: Notifier | None = None,
                 routines: dict[int, str] | None = None, report=None, reconnect=None, trend=None):
        self.cell, self.drivers, self.store = cell, drivers, store
        self.out_dir = Path(out_dir)
        self.notifier = notifier or Notifier({})
        self.routines = dict(panel_routines() if routines is None else routines)
        self.report = report  # callable(run_id, result, store) -> path, or None
        self.trend = trend  # callable(tool_id, trend dict) -> path of the tool's trend page, or None
        self._history_note: str | None = None  # said at the end of the run under way (a check's history)
        self.reconnect = reconnect  # callable() -> a fresh set of the cell's drivers, or None
        self._reconnect_at: float | None = None  # when the robot is to be reconnected (it is unusable)
        self._reconnecting: threading.Thread | None = None  # the reconnection under way, off the main loop
        self._frame_owed: tuple[int, np.ndarray] | None = None  # (run id, the frame from before it)
        self._others_owed = FramesOwed()  # the same for the cell's other robots (robot b of a handshake)
        self._unconfirmed = False  # the panel just came back: a pending start is not taken
        self._waiting = 0  # the step a routine waits for the operator to confirm (PanelOperator); 0: none waits
        self._confirmed = threading.Event()  # the confirm button, pressed while a routine waits
        self.state = "idle"
        self.abort = threading.Event()
        self._worker: threading.Thread | None = None
        self._active = False  # a run is under way: from start() until its end state is decided
        self._run_id: int | None = None  # the run under way, once the store has it
        self._lock = threading.Lock()  # the panel: one caller at a time
        self.panel_ok = True
        self.last: RunOutcome | None = None
        # the tool the run under way (or the last) is for, and its view of the cell
        self._run_tool = 0 if getattr(cell, "tool", None) is None else int(getattr(cell.tool, "id", 1))
        self._run_cell = cell
        # the tool whose frame the controller's running tool frame holds (None: not known, the
        # mounted tool is read at each start: the first run sets its tool's frame)
        source = getattr(cell, "mounted_source", None)
        self._tcp_tool: int | None = self._run_tool if source is None or source.kind == "file" else None
        # what status() reports, each kept current by the thread that knows it (plain attribute
        # writes: a reader never takes a lock the run or the panel loop holds)
        self._seen = {"routine": None, "progress": None, "since": time.time(), "reason": None, "result_code": None,
                      "robot": None}

    # -- the panel ------------------------------------------------------------------------

    def _panel(self, what: str, *args, **kwargs):
        """A panel call that survives a dropped connection (logged once per drop)."""
        with self._lock:  # also keeps a reconnection from swapping the drivers under the call
            panel = self.drivers.panel
            if panel is None:
                return None
            try:
                value = getattr(panel, what)(*args, **kwargs)
            except DeviceError as exc:
                if self.panel_ok:
                    self.panel_ok = False
                    log.warning("panel lost: %s", exc)
                    self._event("panel_lost", str(exc))
                return None
        if not self.panel_ok:
            self.panel_ok, self._unconfirmed = True, True
            log.info("panel back")
            self._event("panel_back", None)
        return value

    def _event(self, kind: str, message: str | None) -> None:
        """An event in the store; a store that cannot take it is logged, never fatal here."""
        try:
            self.store.event(kind, message)
        except Exception as exc:
            log.error("the results store did not take the event %s (%s): %s", kind, message, exc)

    def _progress(self, run_id: int, message: str) -> None:
        self._seen["progress"] = message
        log.info("run %d: %s", run_id, message)

    def _transition(self, run_id: int | None, state: str, message: str | None = None) -> None:
        self._seen["since"] = time.time()
        if state == "checking":
            self._seen["progress"] = None
        self.state = state
        tag = f"run {run_id}: " if run_id is not None else ""
        log.info("%s%s%s", tag, state, f": {message}" if message else "")
        # begin_run records "checking" and finish_run the final state, each in its own transaction
        if run_id is not None and state not in ("checking", "done", "fault", "refused", "aborted"):
            self.store.record_state(run_id, state, message)
        self.notifier.status(f"{state}{f' (run {run_id})' if run_id is not None else ''}")
        if state == "checking":  # a new run: the last one's lamps are history
            self._panel("set_lamps", busy=True, done=False, fault=False)
        elif state not in ("idle", "done", "fault", "refused", "aborted"):
            self._panel("set_lamps", busy=True)

    # -- one run --------------------------------------------------------------------------

    def busy(self) -> bool:
        return self._active

    def poll_panel(self) -> None:
        """One look at the panel: abort while running; a start request otherwise. The abort
        button is read first: a start pressed together with it (or while it is held) is
        refused, and an abort always stops a run it finds."""
        if self.busy():
            if self._panel("abort_requested"):
                self.request_abort("abort button")
            self._take_confirm()
            if self._panel("start_requested"):
                log.info("start pressed while run %s is going on: refused (result code %d BUSY)",
                         self._run_id, ResultCode.BUSY)
                self._event("start_refused_busy", f"run {self._run_id}")
                self._panel("set_result", int(ResultCode.BUSY), increment_counter=False)
            return
        self.recover()
        aborted = self._panel("abort_requested")  # an abort with nothing running is cleared, not remembered
        self._take_confirm()
        pressed = self._panel("start_requested")
        if pressed is None:
            return
        unconfirmed, self._unconfirmed = self._unconfirmed, False
        if pressed and aborted:
            self._abort_wins("pressed together with abort (abort wins)")
        elif pressed and unconfirmed:
            self._discarded("pending when the panel came back")
        elif pressed:
            selector = self._panel("routine_selector")
            if selector is None:  # the request cannot be confirmed: never start from it
                log.warning("start request seen but the routine selector could not be read: not started")
                return
            tool = self._panel("tool_selector")
            if tool is None:
                log.warning("start request seen but the tool selector could not be read: not started")
                return
            if self._panel("abort_requested"):  # abort pressed meanwhile (or with it, read apart): it wins
                self._abort_wins("followed by abort before it was taken (abort wins)")
                return
            self.start(self.routines.get(int(selector), f"selector {selector}"), tool=int(tool))

    def discard_requests(self, why: str) -> None:
        """Clear the panel's requests without acting on them (those pending when the service
        starts: a press nobody can vouch for never starts a run)."""
        if self._panel("start_requested"):
            self._discarded(why)
        self._panel("abort_requested")
        if self._has_confirm():
            self._panel("confirm_requested")
            self._panel("set_waiting", 0)

    def _has_confirm(self) -> bool:
        """The panel has the confirm button and the waiting lamp (every OperatorPanel has them, a
        stand-in of a test may not)."""
        return hasattr(getattr(self.drivers, "panel", None), "confirm_requested")

    def _take_confirm(self) -> None:
        """The confirm button: it answers a routine waiting for the operator (the abort button,
        read before it, wins); pressed while none waits it is cleared and ignored."""
        if not self._has_confirm() or not self._panel("confirm_requested"):
            return
        if self._waiting:
            log.info("run %s: the operator confirmed step %d", self._run_id, self._waiting)
            self._confirmed.set()
        else:
            log.info("confirm pressed while no routine waits for it: cleared, ignored")
            self._event("confirm_ignored", None if self._run_id is None or not self._active else f"run {self._run_id}")

    def _abort_wins(self, why: str) -> None:
        """A start the abort button overrules: nothing starts, and the press is answered
        (result code 40, counted, so a PLC waiting on the counter sees it)."""
        self._discarded(why)
        self._panel("set_lamps", done=False, fault=False)
        self._panel("set_result", int(ResultCode.ABORTED))

    def _discarded(self, why: str) -> None:
        log.warning("a start request %s: cleared, not started (press start again)", why)
        self._event("start_discarded", why)

    def announce_interrupted(self, run_ids: list[int]) -> None:
        """Runs a previous process died in (found at start-up): the panel says so, result
        code INTERRUPTED and the fault lamp, until the next run."""
        if run_ids:
            self._panel("set_lamps", busy=False, done=False, fault=True)
            self._panel("set_result", int(ResultCode.INTERRUPTED), increment_counter=False)

    def start(self, routine: str, tool: int = 0) -> None:
        """Start a run in the worker thread (returns at once); `tool`: the tool the operator
        selected (0: whichever is mounted)."""
        if self.busy():
            raise RuntimeError("a run is already going on")
        if self._worker is not None:  # the last run's final panel writes
            self._worker.join()
        self.abort.clear()
        self._active = True
        self._run_id = None
        self._worker = threading.Thread(target=self._run_safely, args=(routine, tool), name="cellcal-run",
                                        daemon=True)
        self._worker.start()

    def wait(self, timeout_s: float | None = None) -> RunOutcome | None:
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
            # the service's own bookkeeping failed (store, state folder) or a bug: the run still
            # ends, in fault, with the lamps and the result register right and nothing written back
            log.exception("run %s: the service failed", self._run_id)
            self.last = self._end_broken(routine, exc)
        finally:
            self._active = False

    def _end_broken(self, routine: str, exc: Exception) -> RunOutcome:
        run_id = -1 if self._run_id is None else self._run_id
        reason = f"the service failed during the run: {type(exc).__name__}: {exc}"
        if self._frame_owed is not None and self._frame_owed[0] == run_id:
            self._recover_quietly()
        if run_id >= 0:
            try:
                self.store.finish_run(run_id, "fault", int(ResultCode.SERVICE_FAULT), reason)
            except Exception as again:
                log.error("run %d: the results store cannot record its end either: %s", run_id, again)
        self.state = "fault"
        self._seen["reason"], self._seen["result_code"] = reason, int(ResultCode.SERVICE_FAULT)
        log.error("run %d (%s): fault: code %d %s: %s", run_id, routine, ResultCode.SERVICE_FAULT,
                  ResultCode.SERVICE_FAULT.name, reason)
        self._active = False
        self._panel("set_lamps", busy=False, done=False, fault=True)
        self._panel("set_outcome", outcome.registers(None, self._tool_id(), None))
        self._panel("set_result", int(ResultCode.SERVICE_FAULT))
        self.state = "idle"
        return RunOutcome(run_id, "fault", ResultCode.SERVICE_FAULT, reason)

    def _recover_quietly(self) -> None:
        try:
            self.recover()
        except Exception as exc:
            log.error("giving the tool frame back failed: %s", exc)

    def run(self, routine: str, tool: int = 0) -> RunOutcome:
        """The whole state machine for one run, in the calling thread; `tool`: the tool the
        operator selected (0: whichever is mounted)."""
        self._seen["routine"] = routine
        wrong_tool = self._mount(tool)  # decides the tool this run is for: _tool_id() from here on
        # the run's row belongs to the tool this run is for (0: none, NULL in the store), so it is
        # decided (_mount) before this line; a tool known only later goes in with store.record_run_tool
        run_id = self._run_id = self.store.begin_run(routine, self.cell.path, tool_id=self._tool_id() or None)
        self._history_note = None
        self._transition(run_id, "checking", routine)
        if wrong_tool is not None:
            return self._end(run_id, "refused", ResultCode.TOOL_NOT_MOUNTED, wrong_tool)
        cell = self._cell_for(run_id, routine)
        prepared, frame_before, refusal = self._check(routine, cell)
        if refusal is None and self._tcp_tool != self._run_tool:
            frame_before, refusal = self._tool_frame_for_mounted(run_id, frame_before)
        if refusal is None and self.abort.is_set():
            refusal = (ResultCode.ABORTED, "abort pressed before anything moved")
        if refusal is not None:
            code, why = refusal
            return self._end(run_id, "aborted" if code is ResultCode.ABORTED else "refused", code, why)
        self._frame_owed = (run_id, frame_before)
        self._others_owed.owe(run_id, self._other_robots())
        self.store.owe_frame(run_id, frame_before)
        self._transition(run_id, "running", f"{len(prepared.plan)} moves")
        try:
            dataset = runner.measure(prepared, self.drivers, self.out_dir,
                                     lambda message: self._progress(run_id, message), abort=self.abort,
                                     operator=PanelOperator(self, run_id))
        except RoutineAborted as exc:
            return self._end(run_id, "aborted", ResultCode.ABORTED, str(exc))
        except OperatorTimeout as exc:
            return self._end(run_id, "fault", ResultCode.CONFIRM_TIMEOUT, f"{exc.what}; nothing written")
        except CheckAlarm as exc:
            return self._end(run_id, "fault", ResultCode.CHECK_ALARM, f"tool check alarm: {exc}")
        except DeviceError as exc:
            if self.abort.is_set():
                return self._end(run_id, "aborted", ResultCode.ABORTED, f"stopped by abort ({exc.what})")
            return self._end(run_id, "fault", _device_code(self.drivers, exc), str(exc))
        except RoutineError as exc:
            return self._end(run_id, "fault", ResultCode.COMPUTATION_FAILED, str(exc))
        except OSError as exc:
            return self._end(run_id, "fault", ResultCode.SERVICE_FAULT, f"the dataset could not be written: {exc}")
        self._transition(run_id, "solving", dataset.path)
        try:
            result = runner.solve(routine, cell, dataset)
        except CheckAlarm as exc:
            return self._end(run_id, "fault", ResultCode.CHECK_ALARM, f"tool check alarm: {exc}")
        except (RoutineError, ValueError, np.linalg.LinAlgError) as exc:
            return self._end(run_id, "fault", ResultCode.COMPUTATION_FAILED, str(exc))
        judgement = self._judge_drift(run_id, routine, result)
        result, drifted = judgement.applied_to(result), judgement.why  # a new Result: the routine's stays as it was
        self.store.record_result(run_id, result)
        self._record_measured(run_id, routine, result)
        if self.report is not None:
            try:
                self.store.record_report(run_id, str(self.report(run_id, result, self.store)))
            except OSError as exc:
                log.warning("run %d: report not written: %s", run_id, exc)
        self._transition(run_id, "gates")
        if result.verdict == "alarm":  # before the gates: an alarm is never corrected, whatever passed
            saw = result.extra.get("saw") or "; ".join(result.reasons()) or "beyond the tool's outer band"
            return self._end(run_id, "fault", ResultCode.CHECK_ALARM, f"tool check alarm: {saw}", result)
        if drifted is not None:
            return self._end(run_id, "fault", ResultCode.DRIFT_ALARM, f"tool drift alarm: {drifted}; nothing "
                                                                      "written: calibrate the tool", result)
        if not result.passed_gates:
            return self._end(run_id, "fault", ResultCode.GATE_FAILED, "; ".join(result.reasons()), result)
        if self.abort.is_set():
            return self._end(run_id, "aborted", ResultCode.ABORTED, "abort pressed before write-back", result)
        if result.verdict == "ok":
            return self._end(run_id, "done", ResultCode.OK, "tool check ok: the tool is within its inner band; "
                                                            "nothing written", result)
        if result.tool_frame is None:
            return self._end(run_id, "done", ResultCode.OK,
                             f"every gate passed; {routine} determines no tool frame, so nothing was written to "
                             "the controller (the result is in the store and the report)", result)
        self._transition(run_id, "writing back")
        failure = self.write_back(run_id, result.tool_frame)
        if failure is not None:
            return self._end(run_id, "fault", ResultCode.WRITE_BACK_FAILED, failure, result)
        self._frame_owed = None  # the new frame is the controller's now
        self.store.frame_settled(run_id)
        self.store.measured_frame_written(run_id)
        self._write_trend()
        mm, deg = frame_change(result.tool_frame, dataset.meta.get("tool_frame_before", np.zeros(6)))
        return self._end(run_id, "done", ResultCode.OK, f"tool frame written back ({mm:.3f} mm, {deg:.3f} deg "
                                                         "from the previous one)", result, wrote=True)

    def _judge_drift(self, run_id: int, routine: str, result: Result) -> drift.DriftJudgement:
        """A check's drift judgement (:func:`.drift.judge`) against the tool's history in the store.
        A check of a tool no full calibration in this store has written says so
        (``self._history_note``)."""
        if result.verdict is None or getattr(self._run_cell, "tool", None) is None:
            return drift.DriftJudgement(result.verdict)
        rows = self.store.measured_frames(self._tool_id())
        # a calibration written before the store kept measured frames (schema 6) counts too
        calibrated = bool(drift.full_calibrations(rows)) or any(
            self._last_passed(name) for name in drift.CALIBRATION_ROUTINES)
        judgement = drift.judge(result, rows, self._run_cell.tool.bands, calibrated)
        if judgement.never_calibrated:
            self._history_note = drift.NEVER_CALIBRATED
        if judgement.why is not None:
            log.warning("run %d: %s: drift alarm: %s", run_id, routine, judgement.why)
        return judgement

    def _record_measured(self, run_id: int, routine: str, result: Result) -> None:
        """The tool frame the run measured, in the tool's drift history (whatever the verdict;
        marked written after a write-back), and the tool's trend page brought up to date."""
        frame = drift.measured_frame(result)
        if frame is None or self._tool_id() == 0:
            return
        self.store.record_measured_frame(run_id, self._tool_id(), drift.kind_of(result), routine, frame,
                                         result.determines)
        self._write_trend()

    def _write_trend(self) -> None:
        if self.trend is None or self._tool_id() == 0:
            return
        tool_id = self._tool_id()
        try:
            self.trend(tool_id, drift.trend(self.store.measured_frames(tool_id), tool_id))
        except OSError as exc:
            log.warning("the trend page of tool %d was not written: %s", tool_id, exc)

    def _cell_for(self, run_id: int, routine: str):
        """The cell as this run sees it: a routine may take what earlier runs in this store
        found (:meth:`Routine.with_history`: tcp-check, the beams of the last tcp-laser)."""
        if routine not in registry.available():
            return self._run_cell
        try:
            cell, note = registry.routine_class(routine).with_history(self._run_cell, self._last_passed)
        except Exception as exc:  # the past is a help, never a reason not to run
            log.warning("run %d: earlier results not used: %s", run_id, exc)
            return self._run_cell
        if note:
            log.info("run %d: %s", run_id, note)
        return cell

    def _check(self, routine: str, cell=None):
        """(the prepared routine, the controller's tool frame, None) when it may run, else
        (None, None, (code, why))."""
        cell = self._run_cell if cell is None else cell
        if routine not in registry.available():
            return None, None, (ResultCode.NO_SUCH_ROUTINE,
                                f"no routine {routine!r} (routines: {', '.join(registry.available())})")
        why_not = registry.unavailable(routine, cell)
        if why_not is not None:
            return None, None, (ResultCode.NO_SUCH_ROUTINE, f"this cell cannot run {routine}: {why_not}")
        if self._reconnecting is not None:
            return None, None, (ResultCode.NOT_READY, "the service is reconnecting to the robot")
        if self._frame_owed is not None:
            self.recover()
        self._others_owed.give_back(self._other_robots(), self._event)
        waiting = self._others_owed.waiting(registry.routine_class(routine).robots)
        if waiting is not None:
            return None, None, (ResultCode.NOT_READY, waiting)
        if self._frame_owed is not None:
            return None, None, (ResultCode.NOT_READY, f"the tool frame from before run {self._frame_owed[0]} "
                                                      "is not yet back on the controller")
        robot = self.drivers.robot
        try:
            state = robot.state()
            before = np.asarray(robot.tool_frame(), dtype=float) if state is RobotState.READY else None
        except DeviceError as exc:
            return None, None, (ResultCode.NOT_READY, f"the robot does not answer: {exc}")
        if state is not RobotState.READY:
            return None, None, (ResultCode.NOT_READY, f"the robot is not ready: {state.value}")
        try:
            prepared = runner.prepare(routine, cell)
        except PlanRefused as exc:
            return None, None, (ResultCode.LIMITS, f"plan refused, nothing moved: {exc}")
        except (RoutineError, ConfigError) as exc:
            return None, None, (ResultCode.NO_SUCH_ROUTINE, str(exc))
        for kind in type(prepared.routine).needs:
            if getattr(self.drivers, kind, None) is None:
                return None, None, (ResultCode.SENSOR_FAULT, f"the cell has no {kind} for {routine}")
        if prepared.routine.asks_operator() and getattr(self.drivers, "panel", None) is None:
            return None, None, (ResultCode.SENSOR_FAULT, f"{routine} waits for the operator's confirm between "
                                                         "placements, and the cell has no panel to press it on")
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            probe = self.out_dir / f".cellcal-write-probe-{run_id_tag()}"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            return None, None, (ResultCode.SERVICE_FAULT,
                                f"the datasets folder {self.out_dir} cannot be written ({exc.strerror or exc}); "
                                "nothing moved: check the state folder's owner and permissions")
        return prepared, before, None

    # -- between runs ---------------------------------------------------------------------

    def recover(self) -> None:
        """Between runs: reconnect a robot whose connection was lost (once it has been unusable
        for RECONNECT_AFTER_S, then every RECONNECT_EVERY_S, in a thread of its own so the
        panel is served meanwhile), and give the controller back the tool frame a run that
        wrote none left changed."""
        if self._reconnecting is not None:
            if self._reconnecting.is_alive():
                return
            self._reconnecting = None
        state, now = self._robot_state(), time.monotonic()
        lost = state is RobotState.DISCONNECTED or any(
            _state_of(robot) is RobotState.DISCONNECTED for robot in self._other_robots().values())
        if not lost or self.reconnect is None:
            self._reconnect_at = None
        elif self._reconnect_at is None:
            self._reconnect_at = now + RECONNECT_AFTER_S
        elif now >= self._reconnect_at:
            self._reconnect_at = now + RECONNECT_EVERY_S
            self._reconnecting = threading.Thread(target=self._reconnect, name="cellcal-reconnect", daemon=True)
            self._reconnecting.start()
            return
        if self._others_owed:
            self._others_owed.give_back(self._other_robots(), self._event)
        if self._frame_owed is None or state is not RobotState.READY:
            return
        run_id, frame = self._frame_owed
        robot = self.drivers.robot
        try:
            if np.abs(np.asarray(robot.tool_frame(), dtype=float) - frame).max() > TOLERANCE:
                robot.set_tcp(frame)
                log.info("run %d: the tool frame from before it is back on the controller", run_id)
                self._event("tool_frame_given_back", f"run {run_id}")
        except DeviceError as exc:
            log.warning("run %d: the tool frame from before it could not be given back yet: %s", run_id, exc)
            return
        self._frame_owed = None
        self.store.frame_settled(run_id)

    def _reconnect(self) -> None:
        """Off the main loop: the lost robots' connections closed (the controller lets one
        client hold its RTDE inputs), a fresh set of the cell's devices opened, and swapped in
        under the panel's lock, so no panel call runs on a device being replaced; the main
        loop starts no run meanwhile (NOT_READY)."""
        old = self.drivers
        robots = list(dict.fromkeys([*(getattr(old, "robots", None) or {}).values(), old.robot]))
        for robot in robots:
            try:
                robot.close()
            except Exception as exc:
                log.info("closing the lost connection: %s", exc)
        try:
            fresh = self.reconnect()
        except Exception as exc:  # anything a half-reachable cell raises: the service keeps running
            log.warning("the robot's connection is still lost: %s", exc)
            return
        with self._lock:
            self.drivers = fresh
        for device in (old.trigger, old.tracker, old.panel):
            if device is not None:
                try:
                    device.close()
                except Exception as exc:
                    log.info("closing the replaced connection: %s", exc)
        log.info("reconnected the cell's devices")
        self._event("reconnected", None)
        self._reconnect_at = None

    def resume_owed_frame(self) -> int | None:
        """At start-up: a tool frame a run owes the controller (a fault or a stop of the
        service left the tool as drawn on it) is given back by the idle loop once the robot
        is ready; a frame from before a newer write is stale and never comes back. Returns
        the run it is owed for."""
        owed = self.store.owed_frame()
        if owed is None:
            return None
        run_id, frame = owed
        self._frame_owed = (run_id, np.asarray(frame, dtype=float))
        log.info("run %d left the controller on another tool frame than before it: it is given back once the "
                 "robot is ready", run_id)
        return run_id

    def _other_robots(self) -> dict:
        """The cell's robots besides robot a (``drivers.robot``), by name."""
        robots = getattr(self.drivers, "robots", None) or {}
        return {name: robot for name, robot in robots.items() if name != "a" and robot is not self.drivers.robot}

    def _robot_state(self) -> RobotState:
        try:
            state = self.drivers.robot.state()
        except DeviceError:
            state = RobotState.DISCONNECTED
        self._seen["robot"] = state.value
        return state

    def status(self) -> dict:
        """What the service is doing, for the status page and its API: a fresh dict built from
        what the run and the panel loop last recorded, without calling a device or taking a
        lock (safe from any thread, and never slows a run)."""
        seen = dict(self._seen)
        tools = getattr(self.cell, "tools", None) or {}
        tool = tools.get(self._run_tool)
        reconnecting = self._reconnecting is not None
        return {"state": self.state, "run_id": self._run_id if self._active else None,
                "last_run_id": self._run_id, "routine": seen["routine"],
                "progress": seen["progress"] if self._active else None, "since": seen["since"],
                "reason": seen["reason"], "result_code": seen["result_code"],
                "result": None if seen["result_code"] is None else ResultCode(seen["result_code"]).name,
                "mounted_tool": None if tool is None else {"id": tool.id, "name": tool.name},
                "devices": {"robot": "reconnecting" if reconnecting else (seen["robot"] or "unknown"),
                            "panel": "none" if getattr(self.drivers, "panel", None) is None else
                            ("ok" if self.panel_ok else "lost"),
                            # used during runs only: "open" since the service started, a failure shows
                            # as the run's fault (result code and reason)
                            **{kind: "open" for kind in ("trigger", "tracker")
                               if getattr(self.drivers, kind, None) is not None}},
                "frame_owed_by_run": None if self._frame_owed is None else self._frame_owed[0],
                "cell": {"name": getattr(self.cell, "name", None)}}

    def announce_tool_blocks(self) -> None:
        """Said once at the start: each tool of the cell's table whose frame this robot keeps in
        no register block (the registers ran out): its write-backs reach the running program only."""
        try:
            notes = tools_without_block(self.cell, self.drivers.robot)
        except DeviceError as exc:
            log.warning("the robot's blocks of stored tool frames could not be told: %s", exc)
            return
        for note in notes:
            log.warning("%s", note)

    def write_back(self, run_id: int, frame) -> str | None:
        """The frame to the controller (running and stored for the program's start, in the block
        of the tool the run was for), read back and compared; the old frames restored on a
        mismatch (:mod:`.write_back`). A tool without a block gets the running frame, and the
        run's reason says so."""
        slot = tool_slot(self.cell, self._tool_id())
        before, written, failure = write_back(self.drivers.robot, frame, generation=run_id, slot=slot)
        if failure is not None:
            return failure
        note = no_block_note(self.drivers.robot, self._tool_id(), slot)
        if note is not None:
            log.warning("run %d: %s", run_id, note)
            self._history_note = note if self._history_note is None else f"{self._history_note}; {note}"
        self.store.record_tool_frame(run_id, "write", before.running, written.running,
                                     before.stored_json(), written.stored_json())
        return None

    def _end(self, run_id: int, state: str, code: ResultCode, reason: str, result: Result | None = None,
             wrote: bool = False) -> RunOutcome:
        if self._frame_owed is not None and self._frame_owed[0] == run_id:
            self.recover()
        if self._history_note is not None and self._run_id == run_id:
            reason = f"{reason} ({self._history_note})"
        self.store.finish_run(run_id, state, int(code), reason)
        self._seen["reason"], self._seen["result_code"] = reason, int(code)
        self._active = False  # the panel shows the end next: a press after it starts the next run
        self._transition(run_id, state, f"{reason} (code {int(code)} {code.name})")
        # the done lamp says a frame went to the controller; a run that wrote none lights neither
        self._panel("set_lamps", busy=False, done=wrote, fault=state in ("fault", "refused"))
        self._panel("set_outcome", outcome.registers(None if result is None else result.verdict, self._tool_id(),
                                                     self._change(result, wrote)))
        self._panel("set_result", int(code))
        self.state = "idle"
        return RunOutcome(run_id, state, code, reason, result)


    def _mount(self, tool: int) -> str | None:
        """Decide the tool this run is for: the mounted one, read from the cell file's source
        (its ``mounted``: fixed, the panel's register or the tool changer's inputs on the robot);
        ``_tool_id()`` and ``_run_cell`` are then that tool's. Returns why a start for tool
        `tool` (the selector; 0: whichever is mounted) may not run, or None."""
        tools = getattr(self.cell, "tools", None) or {}
        source = getattr(self.cell, "mounted_source", None)
        try:
            mounted = self._run_tool if source is None else cells.mounted_tool(self.cell, self.drivers)
        except cells.NoToolMounted as exc:
            self._run_tool = tool if tool in tools else 0
            return f"{exc}; nothing moved"
        except DeviceError as exc:
            self._run_tool = tool if tool in tools else 0
            return f"which tool is mounted cannot be read from {source.describe()}: {exc}; nothing moved"
        if mounted != self._run_tool and mounted in tools:
            log.info("tool %d (%s) is mounted (%s)", mounted, tools[mounted].name, source.describe())
        drawn = getattr(self.cell, "tool", None)
        if mounted == 0 or mounted not in tools or (drawn is not None and getattr(drawn, "id", 1) == mounted):
            self._run_cell = self.cell
        elif self._run_cell.tool is None or self._run_cell.tool.id != mounted:
            self._run_cell = self.cell.with_tool(mounted)
        self._run_tool = mounted
        if tool == 0:
            return None
        if tool not in tools:
            have = ", ".join(f"{t.id} {t.name}" for t in tools.values()) or "none"
            return f"the tool selector names tool {tool}; this cell has no such tool (its tools: {have}); nothing moved"
        if tool != mounted:
            return (f"the tool selector names tool {tool} ({tools[tool].name}) but tool {mounted} "
                    f"({tools[mounted].name}) is mounted ({source.describe()}); nothing moved")
        return None

    def _tool_id(self) -> int:
        """The tool the run under way (or the last) is for: its id in the cell's tool table (a
        file's one ``tool`` is tool 1; 0: the cell describes none)."""
        return self._run_tool

    def _last_passed(self, routine: str):
        """The last passed result of `routine` for the tool this run is for."""
        try:
            return self.store.last_passed_result(routine, tool_id=self._run_tool)
        except TypeError:  # a store without tools per run
            return self.store.last_passed_result(routine)

    def held_frame(self, tool_id: int) -> tuple[np.ndarray, str]:
        """The frame the controller holds for tool `tool_id` (m, rad) and where it comes from:
        the last frame written or restored for it in this store, else the tool as drawn."""
        rows = [r for r in self.store.tool_frames() if int(r.get("tool_id") or 1) == tool_id]
        if rows:
            row = rows[-1]
            done = "written" if row["action"] == "write" else "restored"
            return np.asarray(row["frame_after"], dtype=float), f"the last frame {done} for it (run {row['run_id']})"
        return np.asarray(self.cell.tools[tool_id].tcp_pose, dtype=float), "its drawing (never calibrated here)"

    def _tool_frame_for_mounted(self, run_id: int, frame_before):
        """A tool change: the controller's running tool frame is made the mounted tool's own
        (:meth:`held_frame`) before anything moves, so the run measures against it. Returns
        (the frame before the run, None) or (None, refusal)."""
        tool_id = self._run_tool
        frame, origin = self.held_frame(tool_id)
        robot = self.drivers.robot
        try:
            robot.set_tcp(frame)
            back = np.asarray(robot.tool_frame(), dtype=float)
        except DeviceError as exc:
            return None, (ResultCode.NOT_READY, f"tool {tool_id}'s frame could not be set on the controller: {exc}")
        if np.abs(back - frame).max() > TOLERANCE:  # doubles travel exactly
            return None, (ResultCode.ROBOT_FAULT, f"the controller reports {back.tolist()} after tool {tool_id}'s "
                                                  f"frame {frame.tolist()} was set")
        self._tcp_tool = tool_id
        message = (f"tool {tool_id} ({self._run_cell.tool.name}) mounted: the controller's tool frame set to "
                   f"{origin}")
        log.info("run %d: %s", run_id, message)
        self._event("tool_frame_for_tool", f"run {run_id}: {message}")
        return frame, None

    @staticmethod
    def _change(result: Result | None, wrote: bool) -> dict | None:
        """What the outcome registers carry: a check's measured change, else the change of the
        frame written (against the controller's before the run), else nothing."""
        if result is None:
            return None
        if result.change is not None:
            return result.change
        before = result.extra.get("tool_frame_before")
        if not wrote or result.tool_frame is None or before is None:
            return None
        return tool_frame.change(result.tool_frame, before, result.determines)


class PanelOperator(Operator):
    """The operator at the panel, as a routine asks them (:class:`~cellcal.drivers.interfaces.Operator`):
    the waiting lamp lit and the step (the placement) in its register, the message in the log and the
    status page's progress, until the confirm button (read by the service's panel loop), the abort
    button (the run ends aborted: abort wins) or the timeout (CONFIRM_TIMEOUT)."""

    name = "operator at the panel"
    LOOK_S = 0.05  # how often the wait looks at the abort event between confirm presses

    def __init__(self, service: "Service", run_id: int):
        self.service, self.run_id = service, run_id

    def confirm(self, message: str, *, step: int, timeout_s: float) -> None:
        service = self.service
        service._confirmed.clear()
        service._waiting = int(step)  # before the lamp: a press the lamp asked for is never taken as early
        service._panel("set_waiting", int(step))
        service._event("waiting_for_operator", f"run {self.run_id}: {message}")
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                if service.abort.is_set():
                    raise RoutineAborted(f"aborted while waiting for the operator ({message})")
                if service._confirmed.wait(self.LOOK_S):
                    if service.abort.is_set():  # pressed together with abort: abort wins
                        raise RoutineAborted(f"aborted while waiting for the operator ({message})")
                    return
                if time.monotonic() >= deadline:
                    raise OperatorTimeout(self.name, f"no confirm within {timeout_s:g} s (confirm_timeout_s) "
                                                     f"after asking: {message}")
        finally:
            service._waiting = 0
            service._confirmed.clear()
            service._panel("set_waiting", 0)


def run_id_tag() -> str:
    return f"{threading.get_ident()}-{time.monotonic_ns()}"


def _state_of(robot) -> RobotState:
    try:
        return robot.state()
    except DeviceError:
        return RobotState.DISCONNECTED


def _device_code(drivers, exc: DeviceError) -> ResultCode:
    robot_name = getattr(drivers.robot, "name", None)
    if exc.device == robot_name or "robot" in exc.device:
        return ResultCode.DEVICE_TIMEOUT if isinstance(exc, DeviceTimeout) else ResultCode.ROBOT_FAULT
    return ResultCode.SENSOR_FAULT  # the trigger or the tracker failed or went silent
