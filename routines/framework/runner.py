"""Running one routine on a cell: plan, check, measure, write the dataset, solve, gate.

The same steps for every routine, in one place, so the daemon and ``cellcal run`` cannot
drift apart. Nothing moves before the whole plan has passed the guard; a device fault
stops the arm, writes no dataset and raises (a routine that can resume keeps what it
measured, marked incomplete); the dataset is on disk before solving.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.robot_files import load_robot
from cellcal.drivers.interfaces import DeviceError
from cellcal.config.reader import ConfigError
from cellcal.routines.framework.base import (Devices, Move, NotForThisCell, Progress, Result, Routine, RoutineError,
                                   frame_text)
from cellcal.routines.framework.context import RunContext
from cellcal.routines.framework.guard import ArmState, GuardedRobot, MotionGuard
from cellcal.routines.framework.records import Dataset, read_dataset, repeated_rows_note
from cellcal.routines.framework.registry import missing_devices, read_options, routine_class


@dataclass
class Prepared:
    routine: Routine
    plan: list[Move]
    guard: MotionGuard

    @property
    def context(self) -> RunContext:
        return self.routine.context


def routine_options(name: str, cell: Cell):
    """The routine's options, its section read once; NotForThisCell when the cell cannot run it
    at all (a device kind it needs is missing, or its section cannot be read for this cell)."""
    why_not = missing_devices(name, cell)
    if why_not is not None:
        raise NotForThisCell(why_not)
    try:
        return read_options(name, cell)
    except ConfigError as exc:
        raise NotForThisCell(str(exc)) from None


def offline_context(name: str, cell: Cell, tool_frame_before=None) -> RunContext:
    """A run's context from the cell file alone (``cellcal run``, a re-solve): the section read,
    the robot model loaded, the controller's frame as given (None: read when the run moves)."""
    before = None if tool_frame_before is None else np.asarray(tool_frame_before, dtype=float)
    return RunContext(name, cell, routine_options(name, cell), load_robot(cell.robot), tool_frame_before=before)


def planning_tool(cell: Cell) -> np.ndarray:
    """The TCP the routines plan with and set before they move: the tool as drawn."""
    return cell.tool.tcp_pose if cell.tool is not None else np.zeros(6)


def prepare(name: str, cell: Cell, resume: str | Path | None = None) -> Prepared:
    """:func:`prepare_run` from the cell file alone (:func:`offline_context`)."""
    return prepare_run(offline_context(name, cell), resume)


def prepare_run(context: RunContext, resume: str | Path | None = None) -> Prepared:
    """The routine, its plan, and the plan checked from the cell's home (raises PlanRefused).

    `resume`: an incomplete dataset of this routine; a routine that can continue one
    (``resume(dataset)``) plans only what it still lacks."""
    name, cell = context.routine, context.cell
    cls = routine_class(name)
    routine = cls(cell, context.options)
    routine.context = context
    if resume is not None:
        if not hasattr(routine, "resume"):
            raise RoutineError(f"routine {name} cannot resume a dataset; run it anew")
        routine.resume(read_dataset(resume, name, getattr(cls, "text_columns", ()),
                                    getattr(cls, "nan_columns", ())))
    plan = routine.plan()
    guard = MotionGuard(cell, context.robot_model)
    guard.check_plan(plan, ArmState(np.asarray(cell.home_q_rad, dtype=float), planning_tool(cell)))
    return Prepared(routine, plan, guard)


def dataset_path(out_dir: str | Path, name: str) -> Path:
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
    return Path(out_dir) / f"{name}-{stamp}.csv"


def measure(prepared: Prepared, drivers, out_dir: str | Path, progress: Progress, abort=None,
            operator=None) -> Dataset:
    """Move through the plan and write the dataset; on a device fault or an abort (the
    `abort` event set), stop and raise. `operator`: who the routine asks when it waits for
    someone at the cell (:meth:`Routine.asks_operator`)."""
    routine = prepared.routine
    robots = {**(getattr(drivers, "robots", None) or {}), "a": drivers.robot}  # drivers.robot is robot a
    if operator is None and routine.asks_operator():
        raise RoutineError(f"{routine.name} waits for the operator between its steps, and nobody was given to ask")
    if routine.context.tool_frame_before is None:  # a run from the cell file alone: read as it starts
        routine.context = replace(routine.context,
                                  tool_frame_before=np.asarray(drivers.robot.tool_frame(), dtype=float))
    previous = routine.context.tool_frame_before
    robot = GuardedRobot.of_cell(robots, prepared.guard, abort, {"a": previous})["a"]
    devices = Devices(robot=drivers.robot, trigger=drivers.trigger, tracker=drivers.tracker, operator=operator)
    try:
        dataset = routine.measure(devices, robot, prepared.plan, progress)
    except BaseException as exc:
        for arm in robots.values():
            try:
                arm.stop()
            except DeviceError:
                pass
        _give_back(drivers.robot, previous, progress)
        kept = _keep_partial(routine, previous, out_dir, progress)
        if kept and isinstance(exc, DeviceError):
            raise DeviceError(exc.device, f"{exc.what}; {kept}") from exc
        if kept and isinstance(exc, RoutineError):
            raise RoutineError(f"{exc}; {kept}") from exc
        raise
    _write(dataset, routine, previous, out_dir)
    progress(f"wrote {dataset.path}")
    return dataset


def _give_back(robot, previous: np.ndarray, progress: Progress) -> None:
    """After a fault or an interrupt: the controller's tool frame from before the run, if the
    routine could not give it back itself (the arm was still moving); says so when the
    controller does not take it yet (a safety stop): the service gives it back once the
    robot is ready, ``cellcal run`` cannot."""
    try:
        if np.abs(np.asarray(robot.tool_frame(), dtype=float) - previous).max() <= 1e-9:
            return
        robot.set_tcp(previous)
        progress("the tool frame from before the run is back on the controller")
    except (DeviceError, OSError) as exc:
        progress(f"the controller still has the tool as drawn; its tool frame before the run was "
                 f"{frame_text(previous)} (could not give it back: {exc})")


def _write(dataset: Dataset, routine: Routine, previous: np.ndarray, out_dir) -> None:
    cell = routine.cell
    dataset.meta.setdefault("tool_frame_before", previous.tolist())
    dataset.cell = f"{cell.name} ({cell.path})"
    dataset.robot = cell.robot
    dataset.write(dataset_path(out_dir, routine.name))


def _keep_partial(routine: Routine, previous, out_dir, progress) -> str:
    """A routine that can resume (``partial()``) keeps what it measured before a fault,
    marked incomplete; says where, or "" when there is nothing to keep."""
    partial = routine.partial() if hasattr(routine, "partial") else None
    if partial is None or not len(partial):
        return ""
    partial.complete = False
    try:
        _write(partial, routine, previous, out_dir)
    except OSError as exc:
        progress(f"could not keep the {len(partial)} measurements taken: {exc}")
        return ""
    kept = (f"{len(partial)} measurements kept in {partial.path} (incomplete; "
            f"'cellcal run {routine.name} --resume {partial.path}' measures the rest)")
    progress(kept)
    return kept


def solve(name: str, cell: Cell, dataset: Dataset) -> Result:
    """:func:`solve_run` from the cell file alone, the controller's frame before as the dataset recorded it."""
    return solve_run(offline_context(name, cell, dataset.meta.get("tool_frame_before")), dataset)


def solve_run(context: RunContext, dataset: Dataset) -> Result:
    cls = routine_class(context.routine)
    result = cls.solve(dataset, context.cell, context.options)
    result.dataset = dataset.path
    result.tool_frame_before = context.tool_frame_before
    if result.cycle_time_s is None and "cycle_time_s" in dataset.meta:
        result.cycle_time_s = float(dataset.meta["cycle_time_s"])
    return result


def solve_file(name: str, cell: Cell, path: str | Path) -> Result:
    """Re-solve a recorded dataset offline with the same code (``--from``); rows that repeat an
    earlier one are noted on the result (its standard deviations are too small)."""
    cls = routine_class(name)
    dataset = read_dataset(path, name, getattr(cls, "text_columns", ()), getattr(cls, "nan_columns", ()))
    result = solve(name, cell, dataset)
    if (note := repeated_rows_note(dataset)) is not None:
        result.notes.append(note)
    return result
