"""Running one routine on a cell: plan, check, measure, write the dataset, solve, gate.

The same steps for every routine, in one place, so the daemon and ``cellcal run`` cannot
drift apart. Nothing moves before the whole plan has passed the guard; a device fault
stops the arm, writes no dataset and raises (a routine that can resume keeps what it
measured, marked incomplete); the dataset is on disk before solving.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.robot_files import load_robot
from cellcal.drivers.interfaces import DeviceError
from cellcal.routines.base import Devices, Move, Progress, Result, Routine, RoutineError
from cellcal.routines.guard import ArmState, GuardedRobot, MotionGuard
from cellcal.routines.records import Dataset, read_dataset
from cellcal.routines.registry import read_options, routine_class


@dataclass
class Prepared:
    routine: Routine
    plan: list[Move]
    guard: MotionGuard


def planning_tool(cell: Cell) -> np.ndarray:
    """The TCP the routines plan with and set before they move: the tool as drawn."""
    return cell.tool.tcp_pose if cell.tool is not None else np.zeros(6)


def prepare(name: str, cell: Cell, resume: str | Path | None = None) -> Prepared:
    """The routine, its plan, and the plan checked from the cell's home (raises PlanRefused).

    `resume`: an incomplete dataset of this routine; a routine that can continue one
    (``resume(dataset)``) plans only what it still lacks."""
    cls = routine_class(name)
    routine = cls(cell, read_options(name, cell))
    missing = [k for k in cls.needs if k not in cell.drivers]
    if missing:
        raise RoutineError(f"{cell.path}: routine {name} needs a {' and a '.join(missing)} in [drivers]")
    if resume is not None:
        if not hasattr(routine, "resume"):
            raise RoutineError(f"routine {name} cannot resume a dataset; run it anew")
        routine.resume(read_dataset(resume, name, getattr(cls, "text_columns", ())))
    plan = routine.plan()
    guard = MotionGuard(cell, load_robot(cell.robot))
    guard.check_plan(plan, ArmState(np.asarray(cell.home_q_rad, dtype=float), planning_tool(cell)))
    return Prepared(routine, plan, guard)


def dataset_path(out_dir: str | Path, name: str) -> Path:
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
    return Path(out_dir) / f"{name}-{stamp}.csv"


def measure(prepared: Prepared, drivers, out_dir: str | Path, progress: Progress, abort=None) -> Dataset:
    """Move through the plan and write the dataset; on a device fault or an abort (the
    `abort` event set), stop and raise."""
    routine = prepared.routine
    robots = {**(getattr(drivers, "robots", None) or {}), "a": drivers.robot}  # drivers.robot is robot a
    robot = GuardedRobot.of_cell(robots, prepared.guard, abort)["a"]
    devices = Devices(robot=drivers.robot, trigger=drivers.trigger, tracker=drivers.tracker)
    previous = np.asarray(drivers.robot.tcp(), dtype=float)
    try:
        dataset = routine.measure(devices, robot, prepared.plan, progress)
    except BaseException as exc:
        for arm in robots.values():
            try:
                arm.stop()
            except DeviceError:
                pass
        kept = _keep_partial(routine, previous, out_dir, progress)
        if kept and isinstance(exc, DeviceError):
            raise DeviceError(exc.device, f"{exc.what}; {kept}") from exc
        if kept and isinstance(exc, RoutineError):
            raise RoutineError(f"{exc}; {kept}") from exc
        raise
    _write(dataset, routine, previous, out_dir)
    progress(f"wrote {dataset.path}")
    return dataset


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
    cls = routine_class(name)
    result = cls.solve(dataset, cell, read_options(name, cell))
    result.dataset = dataset.path
    if "tool_frame_before" in dataset.meta:
        result.extra.setdefault("tool_frame_before", list(dataset.meta["tool_frame_before"]))
    if result.cycle_time_s is None and "cycle_time_s" in dataset.meta:
        result.cycle_time_s = float(dataset.meta["cycle_time_s"])
    return result


def solve_file(name: str, cell: Cell, path: str | Path) -> Result:
    """Re-solve a recorded dataset offline with the same code (``--from``)."""
    cls = routine_class(name)
    return solve(name, cell, read_dataset(path, name, getattr(cls, "text_columns", ())))
