"""Routines whose plan is a list of steps, each a move and what that move records (tcf,
tcp-npoint, handshake, kinematic-fixture), and their one way of measuring.

:meth:`StepRoutine.measure` is the template every step routine measures by: the plan found
to be the routine's steps, its design checked and announced, the robots on the tool as drawn
while the steps run, then the dataset. A routine fills in what it announces
(:meth:`~StepRoutine.announce`), how its steps run and record (:meth:`~StepRoutine.run_steps`,
most through :meth:`~StepRoutine.contact_rows`) and what its dataset keeps of the plan
(:meth:`~StepRoutine.dataset_meta`).
"""
from __future__ import annotations

import abc
import contextlib
from typing import Callable

import numpy as np

from cellcal.routines.framework.base import (Devices, Move, PlanPromise, Progress, Routine, RoutineError,
                                             drawn_tool)
from cellcal.routines.framework.records import Dataset


class StepRoutine(Routine):
    """A routine whose plan is a list of steps, each a move and what that move records
    (``None`` for a move that only gets the tool there), behind a design that is checked
    (and may refuse the plan) before anything moves. Subclasses implement ``steps``,
    ``design``, ``check_design`` and the hooks of :meth:`measure`."""

    text_columns: tuple[str, ...] = ()  # the dataset's columns of text; the others hold numbers

    @abc.abstractmethod
    def steps(self) -> list[tuple[Move, object]]:
        """Every move with what it records, from the cell file alone."""

    @abc.abstractmethod
    def design(self) -> PlanPromise:
        """What the planned steps can give at the stated repeatability."""

    @abc.abstractmethod
    def check_design(self) -> PlanPromise:
        """The design the plan gives (:meth:`design`); raises PlanRefused if it cannot meet
        the routine's targets."""

    def plan(self) -> list[Move]:
        self.check_design()
        return [move for move, _ in self.steps()]

    def measure(self, devices: Devices, robot, plan: list[Move], progress: Progress) -> Dataset:
        """`plan` found to be this routine's steps, its design checked (PlanRefused) and
        announced; every robot of :meth:`drawn_tools` on its tool as drawn while
        :meth:`run_steps` moves and records (the tool frames from before given back
        afterwards); the dataset of the rows, its meta :meth:`dataset_meta` and the motion
        time (``cycle_time_s``)."""
        steps = self.steps_of(plan)
        design = self.check_design()
        progress(self.announce(design))
        tools = self.drawn_tools()
        arms = {name: robot if name == "a" else robot.peer(name) for name in tools}
        with contextlib.ExitStack() as drawn:
            before = {name: drawn.enter_context(drawn_tool(arms[name], pose)) for name, pose in tools.items()}
            rows, cycle_s = self.run_steps(devices, robot, plan, steps, progress)
        meta = {**self.dataset_meta(design, before), "cycle_time_s": cycle_s}
        return Dataset.of_rows(self.name, rows, meta, self.text_columns)

    @abc.abstractmethod
    def announce(self, design: PlanPromise) -> str:
        """What the run is about to do and what its checked design promises, said before it moves."""

    @abc.abstractmethod
    def run_steps(self, devices: Devices, robot, plan: list[Move], steps: list[tuple[Move, object]],
                  progress: Progress) -> tuple[list[dict], float]:
        """Move through `plan` (its `steps`) with the guarded `robot` and record: the rows
        (column -> value) and the motion time (s, robot clock)."""

    @abc.abstractmethod
    def dataset_meta(self, design: PlanPromise, before: dict[str, np.ndarray]) -> dict:
        """What the dataset keeps of the plan and the cell besides the motion time; `before`:
        each robot's tool frame from before it was set on the tool as drawn."""

    def drawn_tools(self) -> dict[str, np.ndarray]:
        """The robots set on the tool as drawn while the steps run, each with that tool
        frame: robot a with the cell's tool."""
        return {"a": self.cell.tool.tcp_pose}

    def contact_rows(self, robot, plan: list[Move], steps, missed: Callable[[Move], str],
                     record: Callable[[object, np.ndarray], dict]) -> tuple[list[dict], float]:
        """Run the plan. At each step that records, its contact search must have touched (else
        RoutineError: ``missed(move)`` says what it did not find, and nothing moves after) and
        ``record(what the step records, joints there)`` gives its row. Returns the rows and
        the motion time (s, robot clock)."""
        t0 = robot.samples()[-1].t_s
        rows = []
        for move, (_, what) in zip(plan, steps):
            found = robot.run(move)
            if what is None:
                continue
            if not found.contact:
                raise RoutineError(f"{move.label}: {missed(move)} (nothing moved after)")
            rows.append(record(what, np.asarray(robot.actual_q(), dtype=float)))
        return rows, float(robot.samples()[-1].t_s - t0)

    def steps_of(self, plan: list[Move]) -> list[tuple[Move, object]]:
        """This routine's steps, once `plan` is found to be its plan for this cell file."""
        steps = self.steps()
        if [m.label for m in plan] != [m.label for m, _ in steps]:
            raise RoutineError("the plan given is not this routine's plan for this cell file")
        return steps
