"""Tool frames owed back to a cell's robots.

A routine sets each robot it moves on the tool as drawn and gives it back its frame from
before when it ends (:func:`.base.drawn_tool`), also after a fault, as far as the robot
still takes a frame. A robot that faulted (a protective or emergency stop, a lost
connection) does not take it then. :class:`FramesOwed` keeps the frame owed to each robot
(robot a and the cell's others alike: robot b of a handshake) until the robot reports it
again, so a failed or aborted run cannot leave a robot on the tool as drawn; robot a's is also
kept in the service's store (`settled` says when it is back), so a restart gives it back too.
"""
from __future__ import annotations

import logging

import numpy as np

from cellcal.drivers.interfaces import DeviceError, RobotState

log = logging.getLogger("cellcal.daemon")

TOLERANCE = 1e-9  # m and rad: a robot that reports this close to the frame owed has it
ROBOT_A = "a"  # the robot whose tool the cell's routines calibrate (the store keeps its frame owed)


def _whose(name: str) -> str:
    return "the tool frame" if name == ROBOT_A else f"robot {name}'s tool frame"


def _its(name: str) -> str:
    return "the controller" if name == ROBOT_A else "its controller"


class FramesOwed:
    """Robot name -> (run id, the robot's tool frame from before that run), until the robot
    reports that frame again. The frame owed is the oldest one not given back: a later run's
    "before" on a robot still owed its frame is the drawing a fault left, never taken.
    `settled(run_id)`: robot a has the frame owed for run `run_id` back (given back or replaced
    by a write)."""

    def __init__(self, settled=None):
        self.owed: dict[str, tuple[int, np.ndarray]] = {}
        self._told: set[str] = set()  # robots whose wait for readiness has been logged (once each)
        self._settled = settled

    def __bool__(self) -> bool:
        return bool(self.owed)

    def run_of(self, name: str = ROBOT_A) -> int | None:
        """The run robot `name` is owed its frame for, or None."""
        return self.owed[name][0] if name in self.owed else None

    def owe(self, run_id: int, robots: dict, known: dict | None = None) -> None:
        """Before run `run_id` moves: each robot's tool frame (robots: name -> driver), as `known`
        gives it (name -> frame: the run read it at its start) or read now. A robot that does
        not answer is left out: nothing has changed its frame yet, and a routine that needs it
        fails before it does."""
        known = known or {}
        for name, robot in robots.items():
            if name in self.owed:
                continue
            if name in known:
                self.owed[name] = (run_id, np.asarray(known[name], dtype=float))
                continue
            try:
                self.owed[name] = (run_id, np.asarray(robot.tool_frame(), dtype=float))
            except DeviceError as exc:
                log.info("run %d: robot %s's tool frame could not be read before the run: %s", run_id, name, exc)

    def settle(self, name: str = ROBOT_A) -> None:
        """Robot `name` has its frame: owed nothing more."""
        run_id, _ = self.owed.pop(name)
        self._told.discard(name)
        if name == ROBOT_A and self._settled is not None:
            self._settled(run_id)

    def give_back(self, robots: dict, event=None) -> None:
        """Each robot owed a frame that is ready now gets it back (when it has another), and
        is owed nothing more; one that is not ready, or does not take it, stays owed.
        `event(kind, message)` records a frame given back (the store's events)."""
        for name, (run_id, frame) in list(self.owed.items()):
            robot = robots.get(name)
            if robot is None:
                continue
            try:
                ready = robot.state() is RobotState.READY
            except DeviceError:
                ready = False
            try:
                if not ready:
                    raise DeviceError(f"robot {name}", "not ready")
                if np.abs(np.asarray(robot.tool_frame(), dtype=float) - frame).max() > TOLERANCE:
                    robot.set_tcp(frame)
                    log.info("run %d: %s from before it is back on %s", run_id, _whose(name), _its(name))
                    if event is not None:
                        event("tool_frame_given_back", f"run {run_id}" if name == ROBOT_A else
                              f"run {run_id}, robot {name}")
            except DeviceError as exc:
                if name not in self._told:  # once: this is asked on every look at the panel
                    self._told.add(name)
                    log.warning("run %d: %s from before it, %s (m, rad), is given back once the robot is ready (%s)",
                                run_id, _whose(name), np.round(frame, 7).tolist(), exc.what)
                continue
            self.settle(name)

    def waiting(self, names) -> str | None:
        """Why a routine that moves the robots `names` must not start yet, or None."""
        owed = [(name, run_id) for name, (run_id, _) in sorted(self.owed.items()) if name in names]
        if not owed:
            return None
        return "; ".join(f"{_whose(name)} from before run {run_id} is not yet back on {_its(name)}"
                         for name, run_id in owed)
