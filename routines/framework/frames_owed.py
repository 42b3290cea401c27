"""Tool frames owed back to the robots of a cell besides robot a.

A routine sets each robot it moves on the tool as drawn and gives it back its frame from
before when it ends (:func:`.base.drawn_tool`), also after a fault, as far as the robot
still takes a frame. A robot that faulted (a protective or emergency stop, a lost
connection) does not take it then. For robot a the service keeps that frame owed in its
store and gives it back once the robot is ready again; :class:`FramesOwed` does the same
for the cell's other robots (robot b of a handshake), so a failed or aborted handshake
cannot leave robot b on the needle as drawn.
"""
from __future__ import annotations

import logging

import numpy as np

from cellcal.drivers.interfaces import DeviceError, RobotState

log = logging.getLogger("cellcal.daemon")

TOLERANCE = 1e-9  # m and rad: a robot that reports this close to the frame owed has it


class FramesOwed:
    """Robot name -> (run id, the robot's tool frame from before that run), until the robot
    reports that frame again. The frame owed is the oldest one not given back: a later run's
    "before" on a robot still owed its frame is the drawing a fault left, never taken."""

    def __init__(self):
        self.owed: dict[str, tuple[int, np.ndarray]] = {}
        self._told: set[str] = set()  # robots whose wait for readiness has been logged (once each)

    def __bool__(self) -> bool:
        return bool(self.owed)

    def owe(self, run_id: int, robots: dict) -> None:
        """Before run `run_id` moves: each robot's tool frame (robots: name -> driver). A robot
        that does not answer is left out: nothing has changed its frame yet, and a routine
        that needs it fails before it does."""
        for name, robot in robots.items():
            if name in self.owed:
                continue
            try:
                self.owed[name] = (run_id, np.asarray(robot.tool_frame(), dtype=float))
            except DeviceError as exc:
                log.info("run %d: robot %s's tool frame could not be read before the run: %s", run_id, name, exc)

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
                    log.info("run %d: robot %s's tool frame from before it is back on its controller", run_id, name)
                    if event is not None:
                        event("tool_frame_given_back", f"run {run_id}, robot {name}")
            except DeviceError as exc:
                if name not in self._told:  # once: this is asked on every look at the panel
                    self._told.add(name)
                    log.warning("run %d: robot %s's tool frame from before it, %s (m, rad), is given back once the "
                                "robot is ready (%s)", run_id, name, np.round(frame, 7).tolist(), exc.what)
                continue
            del self.owed[name]
            self._told.discard(name)

    def waiting(self, names) -> str | None:
        """Why a routine that moves the robots `names` must not start yet, or None."""
        owed = [(name, run_id) for name, (run_id, _) in sorted(self.owed.items()) if name in names]
        if not owed:
            return None
        return "; ".join(f"robot {name}'s tool frame from before run {run_id} is not yet back on its controller"
                         for name, run_id in owed)
