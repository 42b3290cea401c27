"""One run, as one explicit state machine from the operator's start button to a tool frame
written to the controller, and everything that may go wrong on the way.

    idle -> checking -> running -> solving -> gates -> writing back -> done
                  \\          \\         \\        \\            \\
                   refused    fault/aborted      fault        fault (old frame kept)

* checking: the robot is ready, the routine is one this cell can run, its plan passes the
  cell's limits, the sensors it needs answer. A failure here is *refused*: nothing moved. The
  run's context is built here, once (:class:`~cellcal.routines.framework.context.RunContext`:
  the routine's options, the robot model, the controller's tool frame before the run, what
  earlier runs found); every later step takes what it needs from it.
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
the motion at once; the run is recorded as aborted and nothing is written.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from cellcal.config.reader import ConfigError
from cellcal.config.robot_files import load_robot
from cellcal.daemon import drift
from cellcal.daemon.frame_writer import no_block_note, tool_slot, write_tool_frame
from cellcal.daemon.panel import PanelOperator
from cellcal.daemon.result_codes import ResultCode, device_code
from cellcal.drivers.interfaces import DeviceError, OperatorTimeout, RobotState
from cellcal.routines.framework import registry, runner, tool_frame
from cellcal.routines.framework.base import (CalibrateFirst, CheckAlarm, NotForThisCell, PlanRefused, Result,
                                             RoutineAborted, RoutineError, RunEnding)
from cellcal.routines.framework.context import RunContext
from cellcal.routines.framework.gates import frame_change
from cellcal.solvers.tool_frames.verdict import Verdict

log = logging.getLogger("cellcal.daemon")


@dataclass
class RunEnd:
    """How a run ended: its state (done, refused, aborted, fault), the panel's result code, why."""

    run_id: int
    state: str
    code: ResultCode
    reason: str
    result: Result | None = None


class RunMachine:
    """The runs of `service` (:class:`~cellcal.daemon.service.Service`), one at a time."""

    def __init__(self, service):
        self.service = service
        self.notes: list[str] = []  # said at the end of the run under way (a check's history, a tool's block)

    def run(self, routine: str, tool: int = 0) -> RunEnd:
        """The whole state machine for one run, in the calling thread; `tool`: the tool the
        operator selected (0: whichever is mounted)."""
        service, custody = self.service, self.service.custody
        service.seen["routine"] = routine
        wrong_tool = custody.mount(tool)  # decides the tool this run is for
        # the run's row belongs to the tool this run is for (0: none, NULL in the store), so it is
        # decided (mount) before this line; a tool known only later goes in with store.record_run_tool
        run_id = service.run_id = service.store.begin_run(routine, service.cell.path, tool_id=custody.run_tool or None)
        service.seen["mounted_read_at_run"] = run_id  # the mounted tool as this start read it
        self.notes = []
        service.transition(run_id, "checking", routine)
        if wrong_tool is not None:
            return self._end(run_id, "refused", ResultCode.TOOL_NOT_MOUNTED, wrong_tool)
        context, prepared, refusal = self._check(run_id, routine)
        if refusal is None and service.abort.is_set():
            refusal = (ResultCode.ABORTED, "abort pressed before anything moved")
        if refusal is not None:
            code, why = refusal
            return self._end(run_id, "aborted" if code is ResultCode.ABORTED else "refused", code, why)
        custody.owe(run_id, context.tool_frame_before)
        service.transition(run_id, "running", f"{len(prepared.plan)} moves")
        try:
            dataset = runner.measure(prepared, service.drivers, service.out_dir,
                                     lambda message: service.progress(run_id, message), abort=service.abort,
                                     operator=PanelOperator(service, run_id))
        except RoutineAborted as exc:
            return self._end(run_id, "aborted", ResultCode.ABORTED, str(exc))
        except OperatorTimeout as exc:
            return self._end(run_id, "fault", ResultCode.CONFIRM_TIMEOUT, f"{exc.what}; nothing written")
        except PlanRefused as exc:  # a move checked from where the arm really is: the limits, not the service
            return self._end(run_id, "fault", ResultCode.LIMITS, f"a move was refused before it was sent: {exc}; "
                                                                 "the arm stopped, nothing written")
        except CheckAlarm as exc:
            return self._end(run_id, "fault", ResultCode.CHECK_ALARM, f"tool check alarm: {exc}",
                             verdict=Verdict.ALARM)
        except DeviceError as exc:
            if service.abort.is_set():
                return self._end(run_id, "aborted", ResultCode.ABORTED, f"stopped by abort ({exc.what})")
            return self._end(run_id, "fault", device_code(service.drivers.robot.name, exc), str(exc))
        except RoutineError as exc:
            return self._end(run_id, "fault", ResultCode.COMPUTATION_FAILED, str(exc))
        except OSError as exc:
            return self._end(run_id, "fault", ResultCode.SERVICE_FAULT, f"the dataset could not be written: {exc}")
        service.transition(run_id, "solving", dataset.path)
        try:
            result = runner.solve_run(context, dataset)
        except CheckAlarm as exc:
            return self._end(run_id, "fault", ResultCode.CHECK_ALARM, f"tool check alarm: {exc}",
                             verdict=Verdict.ALARM)
        except (RoutineError, ValueError, np.linalg.LinAlgError) as exc:
            return self._end(run_id, "fault", ResultCode.COMPUTATION_FAILED, str(exc))
        return self._gates(context, result)

    def _gates(self, context: RunContext, result: Result) -> RunEnd:
        """The result recorded, judged (the check's verdict, the drift alarm, the gates, the
        abort button) and, when every judgement lets it, its tool frame written."""
        service, run_id, routine = self.service, context.run_id, context.routine
        measured = drift.measured_frame(result)  # what the run measured, before any verdict turns it
        judgement = self._judge_drift(context, result, measured)
        result, drifted = judgement.applied_to(result), judgement.why  # a new Result: the routine's stays as it was
        service.store.record_result(run_id, result)
        self._record_measured(context, result, measured)
        service.transition(run_id, "gates")
        if result.verdict == "alarm":  # before the gates: an alarm is never corrected, whatever passed
            saw = result.extra.get("saw") or "; ".join(result.reasons()) or "the check's verdict is alarm"
            return self._end(run_id, "fault", ResultCode.CHECK_ALARM, f"tool check alarm: {saw}", result)
        if drifted is not None:
            return self._end(run_id, "fault", ResultCode.DRIFT_ALARM, f"tool drift alarm: {drifted}; nothing "
                                                                      "written: calibrate the tool", result)
        if not result.passed_gates:
            return self._end(run_id, "fault", ResultCode.GATE_FAILED, "; ".join(result.reasons()), result)
        if service.abort.is_set():
            return self._end(run_id, "aborted", ResultCode.ABORTED, "abort pressed before write-back", result)
        if result.verdict == "ok":
            return self._end(run_id, "done", ResultCode.OK, "tool check ok: the tool is within its inner band; "
                                                            "nothing written", result)
        if result.tool_frame is None:
            return self._end(run_id, "done", ResultCode.OK,
                             f"every gate passed; {routine} determines no tool frame, so nothing was written to "
                             "the controller (the result is in the store and the report)", result)
        service.transition(run_id, "writing back")
        failure = self.write_tool_frame(context, result.tool_frame)
        if failure is not None:
            return self._end(run_id, "fault", ResultCode.WRITE_BACK_FAILED, failure, result)
        service.custody.written()  # the new frame is the controller's now
        service.store.measured_frame_written(run_id)
        self._write_trend(context.tool_id)
        if tool_frame.controller_frame(context.tool_frame_before) is None:  # the bare flange: no frame to compare
            return self._end(run_id, "done", ResultCode.OK, "tool frame written back (the controller held none "
                                                             "before: all zero, the bare flange)", result, wrote=True)
        mm, deg = frame_change(result.tool_frame, context.tool_frame_before)
        return self._end(run_id, "done", ResultCode.OK, f"tool frame written back ({mm:.3f} mm, {deg:.3f} deg "
                                                         "from the previous one)", result, wrote=True)

    # -- checking ---------------------------------------------------------------------------

    def _check(self, run_id: int, routine: str):
        """(the run's context, the prepared routine, None) when it may run, else (None, None,
        (code, why)). A tool change puts the mounted tool's frame on the controller last."""
        service, custody = self.service, self.service.custody
        cell = custody.run_cell
        if routine not in registry.available():
            return None, None, (ResultCode.NO_SUCH_ROUTINE,
                                f"no routine {routine!r} (routines: {', '.join(registry.available())})")
        try:
            options = runner.routine_options(routine, cell)  # the routine's section, read once for the run
        except NotForThisCell as exc:
            return None, None, (ResultCode.NO_SUCH_ROUTINE, f"this cell cannot run {routine}: {exc}")
        if custody.reconnecting is not None:
            return None, None, (ResultCode.NOT_READY, "the service is reconnecting to the robot")
        self._clear_protective_stop(service.drivers.robot)  # the operator's start clears what the robot lets it
        if custody.owed:
            custody.recover()
        waiting = custody.waiting(registry.routine_class(routine).robots)
        if waiting is not None:
            return None, None, (ResultCode.NOT_READY, waiting)
        robot, changed = service.drivers.robot, custody.tool_changed()
        try:
            state = robot.state()
            # the frame before the run: on a tool change, the mounted tool's (set last, read back)
            before = np.asarray(robot.tool_frame(), dtype=float) if state is RobotState.READY and not changed \
                else None
        except DeviceError as exc:
            return None, None, (ResultCode.NOT_READY, f"the robot does not answer: {exc}")
        if state is not RobotState.READY:
            return None, None, (ResultCode.NOT_READY, f"the robot is not ready: {state.value}")
        held = (*custody.held_frame(custody.run_tool), None) if changed else None
        if held is None and before is not None and cell.tool is not None:
            held = custody.not_the_written_frame(before)
        options, note = self._with_history(run_id, routine, cell, options)
        try:
            context = RunContext(routine, cell, options, load_robot(cell.robot), run_id=run_id,
                                 tool_id=custody.run_tool, tool_frame_before=before if held is None else held[0],
                                 history_note=note)
            prepared = runner.prepare_run(context)
        except PlanRefused as exc:
            return None, None, (ResultCode.LIMITS, f"plan refused, nothing moved: {exc}")
        except CalibrateFirst as exc:
            return None, None, (ResultCode.CALIBRATE_FIRST, f"{exc}; nothing moved")
        except (RoutineError, ConfigError) as exc:
            return None, None, (ResultCode.NO_SUCH_ROUTINE, str(exc))
        for kind in type(prepared.routine).needs:
            if service.drivers.device(kind) is None:
                return None, None, (ResultCode.SENSOR_FAULT, f"the cell has no {kind} for {routine}")
        if prepared.routine.asks_operator() and service.drivers.panel is None:
            return None, None, (ResultCode.SENSOR_FAULT, f"{routine} waits for the operator's confirm between "
                                                         "placements, and the cell has no panel to press it on")
        try:
            service.out_dir.mkdir(parents=True, exist_ok=True)
            probe = service.out_dir / f".cellcal-write-probe-{run_id_tag()}"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            return None, None, (ResultCode.SERVICE_FAULT,
                                f"the datasets folder {service.out_dir} cannot be written ({exc.strerror or exc}); "
                                "nothing moved: check the state folder's owner and permissions")
        if held is not None:
            refusal = custody.tool_frame_for_mounted(run_id, *held)
            if refusal is not None:
                return None, None, refusal
        return context, prepared, None

    @staticmethod
    def _clear_protective_stop(robot) -> None:
        """A protective stop the robot lets the PC clear (a reflex, on some arms), cleared at the
        operator's start, before anything else is asked of the robot; a robot whose stops are cleared at
        the robot itself stays stopped, and the start is refused below as not ready."""
        try:
            if robot.state() is RobotState.PROTECTIVE_STOP and robot.recover():
                log.info("start: the robot's protective stop cleared (the operator's start)")
        except DeviceError as exc:
            log.warning("start: the robot's protective stop could not be cleared: %s", exc)

    def _with_history(self, run_id: int, routine: str, cell, options):
        """The routine's options with what earlier runs in this store found (:meth:`Routine.with_history`:
        tcp-check, the beams of the last tcp-laser), and the note saying so."""
        try:
            options, note = registry.routine_class(routine).with_history(cell, options, self._last_passed)
        except Exception as exc:  # the past is a help, never a reason not to run
            log.warning("run %d: earlier results not used: %s", run_id, exc)
            return options, None
        if note:
            log.info("run %d: %s", run_id, note)
        return options, note

    def _last_passed(self, routine: str, any_tool: bool = False):
        """The last passed result of `routine` for the tool this run is for (`any_tool`: for
        whichever tool, e.g. the beams a tcp-laser found are the cell's)."""
        return self.service.store.last_passed_result(routine, tool_id=None if any_tool else
                                                     self.service.custody.run_tool)

    # -- the result -------------------------------------------------------------------------

    def _judge_drift(self, context: RunContext, result: Result, measured) -> drift.DriftJudgement:
        """A check's drift judgement (:func:`.drift.judge`) of its `measured` frame against the
        tool's history in the store. A check of a tool no full calibration in this store has
        written says so (in the run's end)."""
        if result.verdict is None or context.cell.tool is None:
            return drift.DriftJudgement(result.verdict)
        rows = self.service.store.measured_frames(context.tool_id)
        # a calibration written before the store kept measured frames (schema 6) counts too
        calibrated = bool(drift.full_calibrations(rows)) or any(
            self._last_passed(name) for name in drift.CALIBRATION_ROUTINES)
        judgement = drift.judge(result, measured, rows, context.cell.tool.bands, calibrated)
        if judgement.never_calibrated:
            self.notes.append(drift.NEVER_CALIBRATED)
        if judgement.why is not None:
            log.warning("run %d: %s: drift alarm: %s", context.run_id, context.routine, judgement.why)
            together = self._drifting_together(context, measured, result.determines)
            if together is not None:
                log.warning("run %d: %s", context.run_id, together)
                judgement = replace(judgement, why=f"{judgement.why}; {together}")
        return judgement

    def _drifting_together(self, context: RunContext, measured, determines) -> str | None:
        """:func:`.drift.drifting_together` over every tool of the cell, this check's frame counted
        as its tool's newest (it is recorded after the judgement)."""
        store, cell = self.service.store, self.service.cell
        rows = {t: store.measured_frames(t) for t in cell.tools}
        rows.setdefault(context.tool_id, [])
        rows[context.tool_id] = [*rows[context.tool_id], {"run_id": context.run_id, "kind": "check",
                                                          "frame": list(np.asarray(measured, dtype=float)),
                                                          "determines": sorted(determines), "written": False}]
        return drift.drifting_together(context.tool_id, rows, {t: tool.bands for t, tool in cell.tools.items()})

    def _record_measured(self, context: RunContext, result: Result, measured) -> None:
        """The tool frame the run measured, in the tool's drift history (whatever the verdict;
        marked written after a write), and the tool's trend page brought up to date."""
        if measured is None or context.tool_id == 0:
            return
        self.service.store.record_measured_frame(context.run_id, context.tool_id, drift.kind_of(result),
                                                 context.routine, measured, result.determines)
        self._write_trend(context.tool_id)

    def _write_trend(self, tool_id: int) -> None:
        service = self.service
        if service.trend is None or tool_id == 0:
            return
        try:
            service.trend(tool_id, drift.trend(service.store.measured_frames(tool_id), tool_id))
        except OSError as exc:
            log.warning("the trend page of tool %d was not written: %s", tool_id, exc)

    def write_tool_frame(self, context: RunContext, frame) -> str | None:
        """The frame to the controller (running and stored for the program's start, in the block
        of the tool the run was for), read back and compared; the old frames restored on a
        mismatch (:mod:`.frame_writer`). A tool without a block gets the running frame, and the
        run's reason says so. None when it was written, else why not."""
        service, run_id = self.service, context.run_id
        robot, slot = service.drivers.robot, tool_slot(service.cell, context.tool_id)
        before, written, failure = write_tool_frame(robot, frame, generation=run_id, slot=slot,
                                                    running_before=context.tool_frame_before)
        if failure is not None:
            return failure
        note = no_block_note(robot, context.tool_id, slot)
        if note is not None:
            log.warning("run %d: %s", run_id, note)
            self.notes.append(note)
        service.store.record_tool_frame(run_id, "write", before.running, written.running,
                                        before.stored_json(), written.stored_json())
        return None

    # -- the end ----------------------------------------------------------------------------

    def _end(self, run_id: int, state: str, code: ResultCode, reason: str, result: Result | None = None,
             wrote: bool = False, verdict: Verdict | None = None) -> RunEnd:
        """The run's end, recorded and shown; `verdict`: a check's that ended without a result
        (a check always ends with one: the PLC, the store and the page read it)."""
        service, custody = self.service, self.service.custody
        if custody.owed_by(run_id):
            custody.recover()
        if self.notes:
            reason = f"{reason} ({'; '.join(self.notes)})"
        if result is not None:
            verdict = result.verdict
            self._report(run_id, result, RunEnding(code.name, reason, wrote))
        elif verdict is not None:
            service.store.record_verdict(run_id, verdict)
        service.store.finish_run(run_id, state, int(code), reason)
        service.last_run_ended(run_id, service.seen["routine"], state, code, reason, verdict)
        service.active = False  # the panel shows the end next: a press after it starts the next run
        service.transition(run_id, state, f"{reason} (code {int(code)} {code.name})")
        # the done lamp says a frame went to the controller; a run that wrote none lights neither
        service.panel.show_end(code, done=wrote, fault=state in ("fault", "refused"),
                               verdict=verdict, tool_id=custody.run_tool,
                               change=_change(result, wrote))
        service.state = "idle"
        return RunEnd(run_id, state, code, reason, result)

    def _report(self, run_id: int, result: Result, ending: RunEnding) -> None:
        """The run's report, written once its end is known: its headline says what happened."""
        service = self.service
        if service.report is None:
            return
        try:
            service.store.record_report(run_id, str(service.report(run_id, result, service.store, ending)))
        except OSError as exc:
            log.warning("run %d: report not written: %s", run_id, exc)

    def end_broken(self, routine: str, exc: Exception) -> RunEnd:
        """The service's own bookkeeping failed (store, state folder) or a bug: the run still
        ends, in fault, with the lamps and the result register right and nothing written."""
        service, custody = self.service, self.service.custody
        run_id = -1 if service.run_id is None else service.run_id
        reason = f"the service failed during the run: {type(exc).__name__}: {exc}"
        if custody.owed_by(run_id):
            custody.recover_quietly()
        if run_id >= 0:
            try:
                service.store.finish_run(run_id, "fault", int(ResultCode.SERVICE_FAULT), reason)
            except Exception as again:
                log.error("run %d: the results store cannot record its end either: %s", run_id, again)
        service.state = "fault"
        service.last_run_ended(run_id, routine, "fault", ResultCode.SERVICE_FAULT, reason, None)
        log.error("run %d (%s): fault: code %d %s: %s", run_id, routine, ResultCode.SERVICE_FAULT,
                  ResultCode.SERVICE_FAULT.name, reason)
        service.active = False
        service.panel.show_end(ResultCode.SERVICE_FAULT, done=False, fault=True, verdict=None,
                               tool_id=custody.run_tool, change=None)
        service.state = "idle"
        return RunEnd(run_id, "fault", ResultCode.SERVICE_FAULT, reason)


def _change(result: Result | None, wrote: bool) -> dict | None:
    """What the outcome registers carry: a check's measured change, else the change of the
    frame written (against the controller's before the run), else nothing."""
    if result is None:
        return None
    if result.change is not None:
        return result.change
    if not wrote or result.tool_frame is None or result.tool_frame_before is None:
        return None
    return tool_frame.change(result.tool_frame, result.tool_frame_before, result.determines)


def run_id_tag() -> str:
    return f"{threading.get_ident()}-{time.monotonic_ns()}"
