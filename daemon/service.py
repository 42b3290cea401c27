"""The service: one explicit state machine from the operator's start button to a written-back
tool frame, and everything that may go wrong on the way.

    idle -> checking -> running -> solving -> gates -> writing back -> done
                  \\          \\         \\        \\            \\
                   refused    fault/aborted      fault        fault (old frame kept)

* checking: the robot is ready, the routine is one this cell can run, its plan passes the
  cell's limits, the sensors it needs answer. A failure here is *refused*: nothing moved.
* running: the routine moves and records (in a worker thread: the main loop keeps serving
  the panel and the signals); the dataset is on disk before solving.
* gates: a result that fails any gate is never written (state fault, code GATE_FAILED).
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
import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellcal.drivers.interfaces import DeviceError, DeviceTimeout, RobotState
from cellcal.routines import registry, runner
from cellcal.routines.base import PlanRefused, Result, RoutineAborted, RoutineError
from cellcal.routines.gates import frame_change
from cellcal.daemon.notify import Notifier
from cellcal.daemon.store import Store
from cellcal.daemon.write_back import TOLERANCE, write_back

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
    SENSOR_FAULT = 20
    ROBOT_FAULT = 21
    DEVICE_TIMEOUT = 22
    COMPUTATION_FAILED = 30
    GATE_FAILED = 31
    WRITE_BACK_FAILED = 32
    ABORTED = 40
    INTERRUPTED = 41


RESULT_MEANINGS = {
    ResultCode.OK: "the run passed every gate and its tool frame was written back and read back",
    ResultCode.NOT_READY: "start refused: the robot is not ready (protective or emergency stop, not connected)",
    ResultCode.NO_SUCH_ROUTINE: "start refused: the routine selector names no routine this cell can run",
    ResultCode.LIMITS: "start refused: the routine's plan would leave the cell's limits; nothing moved",
    ResultCode.BUSY: "start refused: a routine is already running (the press is ignored)",
    ResultCode.SENSOR_FAULT: "the trigger or the tracker failed or went silent; motion stopped",
    ResultCode.ROBOT_FAULT: "the robot faulted (connection lost, protective or emergency stop); motion stopped",
    ResultCode.DEVICE_TIMEOUT: "the robot controller did not answer in time (stalled); motion stopped",
    ResultCode.COMPUTATION_FAILED: "the measurements could not be solved (the routine says why)",
    ResultCode.GATE_FAILED: "the result failed a quality gate and was not written back",
    ResultCode.WRITE_BACK_FAILED: "the controller did not keep the written tool frame; the old one was restored",
    ResultCode.ABORTED: "aborted by the operator or by a stop of the service; nothing written back",
    ResultCode.INTERRUPTED: "the service died during the run; found at the next start, nothing written back",
}


def panel_routines() -> dict[int, str]:
    """The routine selector register's values (docs/panel.md) -> routine names: each routine
    class declares its own ``selector`` (:func:`cellcal.routines.registry.panel_selectors`)."""
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
                 routines: dict[int, str] | None = None, report=None, reconnect=None):
        self.cell, self.drivers, self.store = cell, drivers, store
        self.out_dir = Path(out_dir)
        self.notifier = notifier or Notifier({})
        self.routines = dict(panel_routines() if routines is None else routines)
        self.report = report  # callable(run_id, result, store) -> path, or None
        self.reconnect = reconnect  # callable() -> a fresh set of the cell's drivers, or None
        self._reconnect_at: float | None = None  # when the robot is to be reconnected (it is unusable)
        self._frame_owed: tuple[int, np.ndarray] | None = None  # (run id, the frame from before it)
        self._unconfirmed = False  # the panel just came back: a pending start is not taken
        self.state = "idle"
        self.abort = threading.Event()
        self._worker: threading.Thread | None = None
        self._active = False  # a run is under way: from start() until its end state is decided
        self._lock = threading.Lock()  # the panel: one caller at a time
        self.panel_ok = True
        self.last: RunOutcome | None = None

    # -- the panel ------------------------------------------------------------------------

    def _panel(self, what: str, *args, **kwargs):
        """A panel call that survives a dropped connection (logged once per drop)."""
        panel = self.drivers.panel
        if panel is None:
            return None
        try:
            with self._lock:
                value = getattr(panel, what)(*args, **kwargs)
        except DeviceError as exc:
            if self.panel_ok:
                self.panel_ok = False
                log.warning("panel lost: %s", exc)
                self.store.event("panel_lost", str(exc))
            return None
        if not self.panel_ok:
            self.panel_ok, self._unconfirmed = True, True
            log.info("panel back")
            self.store.event("panel_back", None)
        return value

    def _transition(self, run_id: int | None, state: str, message: str | None = None) -> None:
        self.state = state
        tag = f"run {run_id}: " if run_id is not None else ""
        log.info("%s%s%s", tag, state, f": {message}" if message else "")
        # begin_run records "checking" and finish_run the final state, each in its own transaction
        if run_id is not None and state not in ("checking", "done", "fault", "refused", "aborted"):
            self.store.record_state(run_id, state, message)
        self.notifier.status(f"{state}{f' (run {run_id})' if run_id is not None else ''}")
        busy = state not in ("idle", "done", "fault", "refused", "aborted")
        self._panel("set_lamps", busy=busy)

    # -- one run --------------------------------------------------------------------------

    def busy(self) -> bool:
        return self._active

    def poll_panel(self) -> None:
        """One look at the panel: abort while running; a start request otherwise."""
        if self.busy():
            if self._panel("abort_requested"):
                self.request_abort("abort button")
            if self._panel("start_requested"):
                log.info("start pressed while a run is going on: ignored")
            return
        self.recover()
        self._panel("abort_requested")  # an abort with nothing running is cleared, not remembered
        pressed = self._panel("start_requested")
        if pressed is None:
            return
        unconfirmed, self._unconfirmed = self._unconfirmed, False
        if pressed and unconfirmed:
            self._discarded("pending when the panel came back")
        elif pressed:
            selector = self._panel("routine_selector")
            if selector is None:  # the request cannot be confirmed: never start from it
                log.warning("start request seen but the routine selector could not be read: not started")
                return
            self.start(self.routines.get(int(selector), f"selector {selector}"))

    def discard_requests(self, why: str) -> None:
        """Clear the panel's requests without acting on them (those pending when the service
        starts: a press nobody can vouch for never starts a run)."""
        if self._panel("start_requested"):
            self._discarded(why)
        self._panel("abort_requested")

    def _discarded(self, why: str) -> None:
        log.warning("a start request %s: cleared, not started (press start again)", why)
        self.store.event("start_discarded", why)

    def start(self, routine: str) -> None:
        """Start a run in the worker thread (returns at once)."""
        if self.busy():
            raise RuntimeError("a run is already going on")
        if self._worker is not None:  # the last run's final panel writes
            self._worker.join()
        self.abort.clear()
        self._active = True
        self._worker = threading.Thread(target=self._run_safely, args=(routine,), name="cellcal-run", daemon=True)
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

    def _run_safely(self, routine: str) -> None:
        try:
            self.last = self.run(routine)
        except Exception as exc:  # a bug must not leave the lamps busy or the run open
            log.exception("run failed unexpectedly")
            self.last = RunOutcome(-1, "fault", ResultCode.COMPUTATION_FAILED, f"internal error: {exc}")
        finally:
            self._active = False

    def run(self, routine: str) -> RunOutcome:
        """The whole state machine for one run, in the calling thread."""
        run_id = self.store.begin_run(routine, self.cell.path)
        self._transition(run_id, "checking", routine)
        prepared, frame_before, refusal = self._check(routine)
        if refusal is not None:
            code, why = refusal
            return self._end(run_id, "refused", code, why)
        self._frame_owed = (run_id, frame_before)
        self.store.record_frame_before(run_id, frame_before)
        self._transition(run_id, "running", f"{len(prepared.plan)} moves")
        try:
            dataset = runner.measure(prepared, self.drivers, self.out_dir,
                                     lambda message: log.info("run %d: %s", run_id, message), abort=self.abort)
        except RoutineAborted as exc:
            return self._end(run_id, "aborted", ResultCode.ABORTED, str(exc))
        except DeviceError as exc:
            if self.abort.is_set():
                return self._end(run_id, "aborted", ResultCode.ABORTED, f"stopped by abort ({exc.what})")
            return self._end(run_id, "fault", _device_code(self.drivers, exc), str(exc))
        except RoutineError as exc:
            return self._end(run_id, "fault", ResultCode.COMPUTATION_FAILED, str(exc))
        self._transition(run_id, "solving", dataset.path)
        try:
            result = runner.solve(routine, self.cell, dataset)
        except (RoutineError, ValueError, np.linalg.LinAlgError) as exc:
            return self._end(run_id, "fault", ResultCode.COMPUTATION_FAILED, str(exc))
        self.store.record_result(run_id, result)
        if self.report is not None:
            try:
                self.store.record_report(run_id, str(self.report(run_id, result, self.store)))
            except OSError as exc:
                log.warning("run %d: report not written: %s", run_id, exc)
        self._transition(run_id, "gates")
        if not result.write_back:
            return self._end(run_id, "fault", ResultCode.GATE_FAILED, "; ".join(result.reasons()), result)
        if self.abort.is_set():
            return self._end(run_id, "aborted", ResultCode.ABORTED, "aborted before write-back", result)
        if result.tool_frame is None:
            return self._end(run_id, "done", ResultCode.OK, "no tool frame to write (a frame routine)", result)
        self._transition(run_id, "writing back")
        failure = self.write_back(run_id, result.tool_frame)
        if failure is not None:
            return self._end(run_id, "fault", ResultCode.WRITE_BACK_FAILED, failure, result)
        self._frame_owed = None  # the new frame is the controller's now
        mm, deg = frame_change(result.tool_frame, dataset.meta.get("tool_frame_before", np.zeros(6)))
        return self._end(run_id, "done", ResultCode.OK, f"tool frame written back ({mm:.3f} mm, {deg:.3f} deg "
                                                         "from the previous one)", result)

    def _check(self, routine: str):
        """(the prepared routine, the controller's tool frame, None) when it may run, else
        (None, None, (code, why))."""
        if self._frame_owed is not None:
            self.recover()
        if self._frame_owed is not None:
            return None, None, (ResultCode.NOT_READY, f"the tool frame from before run {self._frame_owed[0]} "
                                                      "is not yet back on the controller")
        robot = self.drivers.robot
        try:
            state = robot.state()
            before = np.asarray(robot.tcp(), dtype=float) if state is RobotState.READY else None
        except DeviceError as exc:
            return None, None, (ResultCode.NOT_READY, f"the robot does not answer: {exc}")
        if state is not RobotState.READY:
            return None, None, (ResultCode.NOT_READY, f"the robot is not ready: {state.value}")
        if routine not in registry.available():
            return None, None, (ResultCode.NO_SUCH_ROUTINE,
                                f"no routine {routine!r} (routines: {', '.join(registry.available())})")
        try:
            prepared = runner.prepare(routine, self.cell)
        except PlanRefused as exc:
            return None, None, (ResultCode.LIMITS, f"plan refused, nothing moved: {exc}")
        except RoutineError as exc:
            return None, None, (ResultCode.NO_SUCH_ROUTINE, str(exc))
        for kind in type(prepared.routine).needs:
            if getattr(self.drivers, kind, None) is None:
                return None, None, (ResultCode.SENSOR_FAULT, f"the cell has no {kind} for {routine}")
        return prepared, before, None

    # -- between runs ---------------------------------------------------------------------

    def recover(self) -> None:
        """Between runs: reconnect a robot whose connection was lost (once it has been unusable
        for RECONNECT_AFTER_S, then every RECONNECT_EVERY_S), and give the controller back the
        tool frame a run that wrote none left changed."""
        state, now = self._robot_state(), time.monotonic()
        if state is not RobotState.DISCONNECTED or self.reconnect is None:
            self._reconnect_at = None
        elif self._reconnect_at is None:
            self._reconnect_at = now + RECONNECT_AFTER_S
        elif now >= self._reconnect_at:
            self._reconnect_at = now + RECONNECT_EVERY_S
            try:  # the old connections first: the controller lets one client hold its RTDE inputs
                self.drivers.close()
            except Exception as exc:
                log.info("closing the lost connections: %s", exc)
            try:
                self.drivers = self.reconnect()
            except Exception as exc:  # anything a half-reachable cell raises: the service keeps running
                log.warning("the robot's connection is still lost: %s", exc)
                return
            log.info("reconnected the cell's devices")
            self.store.event("reconnected", None)
            self._reconnect_at = None
            state = self._robot_state()
        if self._frame_owed is None or state is not RobotState.READY:
            return
        run_id, frame = self._frame_owed
        robot = self.drivers.robot
        try:
            if np.abs(np.asarray(robot.tcp(), dtype=float) - frame).max() > TOLERANCE:
                robot.set_tcp(frame)
                log.info("run %d: the tool frame from before it is back on the controller", run_id)
                self.store.event("tool_frame_given_back", f"run {run_id}")
        except DeviceError as exc:
            log.warning("run %d: the tool frame from before it could not be given back yet: %s", run_id, exc)
            return
        self._frame_owed = None

    def give_back_frame_of(self, run_id: int) -> None:
        """A run the service died in (found interrupted at start-up) may have left the drawing's
        tool frame on the controller: the idle loop gives back the one it had, as after a fault."""
        row = self.store.run(run_id)
        if row is not None and row.tool_frame_before is not None:
            self._frame_owed = (run_id, np.array(json.loads(row.tool_frame_before), dtype=float))

    def _robot_state(self) -> RobotState:
        try:
            return self.drivers.robot.state()
        except DeviceError:
            return RobotState.DISCONNECTED

    def write_back(self, run_id: int, frame) -> str | None:
        """The frame to the controller (running and stored for the program's start), read back
        and compared; the old frames restored on a mismatch (:mod:`.write_back`)."""
        before, written, failure = write_back(self.drivers.robot, frame, generation=run_id)
        if failure is not None:
            return failure
        self.store.record_tool_frame(run_id, "write", before.running, written.running,
                                     before.stored_json(), written.stored_json())
        return None

    def _end(self, run_id: int, state: str, code: ResultCode, reason: str, result: Result | None = None) -> RunOutcome:
        if self._frame_owed is not None and self._frame_owed[0] == run_id:
            self.recover()
        self.store.finish_run(run_id, state, int(code), reason)
        self._active = False  # the panel shows the end next: a press after it starts the next run
        self._transition(run_id, state, f"{code.name.lower()}: {reason}")
        self._panel("set_lamps", busy=False, done=state == "done", fault=state in ("fault", "refused"))
        self._panel("set_result", int(code))
        self.state = "idle"
        return RunOutcome(run_id, state, code, reason, result)


def _device_code(drivers, exc: DeviceError) -> ResultCode:
    robot_name = getattr(drivers.robot, "name", None)
    if exc.device == robot_name or "robot" in exc.device:
        return ResultCode.DEVICE_TIMEOUT if isinstance(exc, DeviceTimeout) else ResultCode.ROBOT_FAULT
    return ResultCode.SENSOR_FAULT  # the trigger or the tracker failed or went silent
