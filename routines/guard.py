"""The one place every motion passes: the cell's workspace box, joint limits, speed and
acceleration ceilings, and a bounded travel for contact searches.

:meth:`MotionGuard.check_plan` walks a whole plan from the arm's start before anything
moves (``--dry-run`` stops there); :class:`GuardedRobot` checks every command again as it
is sent, so a command a routine builds at run time (from what it measured) is held to
the same limits. A refusal names the move and the limit; nothing is clipped.

Paths are checked on the controller's own model (the robot file): a joint move by its
TCP at joint-space samples along the way, a linear move by its ends (the box is convex)
and the joints of its end (solved by inverse kinematics from where it starts), a
contact search by the full length it may travel.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config.cells import Cell
from ..drivers.interfaces import ContactResult, Robot
from ..solvers.inverse import inverse, tcp_poses
from ..solvers.robot_model import KinematicModel
from .base import Move, PlanRefused, RoutineAborted

JOINT_PATH_SAMPLES = 24  # points along a joint move at which the TCP is checked against the box


@dataclass
class ArmState:
    q_rad: np.ndarray
    tool_pose: np.ndarray  # the controller's TCP setting

    def tcp(self, model: KinematicModel) -> np.ndarray:
        return tcp_poses(model, self.q_rad, self.tool_pose)[0]


class MotionGuard:
    def __init__(self, cell: Cell, model: KinematicModel):
        self.cell, self.model = cell, model
        self.low, self.high = np.asarray(cell.workspace_min_m), np.asarray(cell.workspace_max_m)
        self.limits = cell.limits
        self.joint_limits = model.joint_limits

    # -- single checks -----------------------------------------------------------------

    def _refuse(self, move: Move, what: str):
        raise PlanRefused(f"move '{move.label}': {what}")

    def _box(self, move: Move, position, what: str) -> None:
        p = np.asarray(position, dtype=float)
        if np.any(p < self.low - 1e-9) or np.any(p > self.high + 1e-9):
            self._refuse(move, f"{what} {np.round(p, 4).tolist()} m leaves the workspace box "
                               f"{self.low.tolist()}..{self.high.tolist()} m")

    def _joints(self, move: Move, q) -> None:
        q = np.asarray(q, dtype=float)
        if q.shape != (self.model.n_joints,) or not np.all(np.isfinite(q)):
            self._refuse(move, f"joint target must be {self.model.n_joints} finite numbers")
        if self.joint_limits is None:
            return
        for i, (v, (lo, hi)) in enumerate(zip(q, self.joint_limits)):
            if not lo <= v <= hi:
                self._refuse(move, f"joint {i + 1} at {np.rad2deg(v):.2f} deg is outside its limits "
                                   f"{np.rad2deg(lo):.1f}..{np.rad2deg(hi):.1f} deg")

    def _ceiling(self, move: Move, value: float, key: str, unit: str) -> None:
        limit = self.limits[key]
        if not np.isfinite(value) or value <= 0:
            self._refuse(move, f"{key.rsplit('_', 2)[0].replace('_', ' ')} {value!r} must be a positive number")
        if value > limit + 1e-12:
            self._refuse(move, f"{value:g} {unit} is above the cell's limit {key} = {limit:g}")

    def check(self, move: Move, state: ArmState) -> ArmState:
        """Check one move from `state`; return the state after it (raises PlanRefused)."""
        if move.kind == "joint":
            self._ceiling(move, move.speed, "joint_speed_rad_s", "rad/s")
            self._ceiling(move, move.accel, "joint_accel_rad_s2", "rad/s^2")
            self._joints(move, move.q_rad)
            s = np.linspace(0.0, 1.0, JOINT_PATH_SAMPLES)[:, None]
            path = state.q_rad + s * (move.q_rad - state.q_rad)
            for p in tcp_poses(self.model, path, state.tool_pose)[:, :3]:
                self._box(move, p, "the TCP on the way at")
            return ArmState(move.q_rad.copy(), state.tool_pose)
        if move.kind == "linear":
            self._ceiling(move, move.speed, "tcp_speed_m_s", "m/s")
            self._ceiling(move, move.accel, "tcp_accel_m_s2", "m/s^2")
            if move.pose is None or move.pose.shape != (6,) or not np.all(np.isfinite(move.pose)):
                self._refuse(move, "TCP target must be 6 finite numbers [x, y, z, rx, ry, rz]")
            self._box(move, move.pose[:3], "the TCP target")
            q_end = inverse(self.model, move.pose, state.q_rad, state.tool_pose)
            if q_end is None:
                self._refuse(move, "the TCP target cannot be reached from the arm's configuration")
            self._joints(move, q_end)
            return ArmState(q_end, state.tool_pose)
        if move.kind == "contact":
            self._ceiling(move, move.speed, "tcp_speed_m_s", "m/s")
            self._ceiling(move, move.accel, "tcp_accel_m_s2", "m/s^2")
            travel = self.limits["contact_travel_m"]
            if not 0 < move.travel_m <= travel + 1e-12:
                self._refuse(move, f"contact travel {move.travel_m:g} m is above the cell's limit "
                                   f"contact_travel_m = {travel:g} (or not positive)")
            start = state.tcp(self.model)
            self._box(move, start[:3] + move.direction * move.travel_m, "the end of the contact search at")
            end = start.copy()
            end[:3] += move.direction * move.travel_m
            q_end = inverse(self.model, end, state.q_rad, state.tool_pose)
            if q_end is None:
                self._refuse(move, "the contact search's full travel cannot be reached")
            self._joints(move, q_end)
            return state  # where it stops is not known in advance; the next move starts from the plan's view
        self._refuse(move, f"unknown move kind {move.kind!r}")

    def check_plan(self, plan: list[Move], start: ArmState) -> ArmState:
        """Every move of a plan in order, from `start`, before any of them runs."""
        state = start
        for move in plan:
            state = self.check(move, state)
        return state


class GuardedRobot:
    """The robot as a routine sees it: every motion command checked by the guard first.

    Also records every command that reached the robot (``sent``), so tests can show no
    command outside the limits ever got through.
    """

    def __init__(self, robot: Robot, guard: MotionGuard, abort=None):
        self.robot, self.guard = robot, guard
        self.abort = abort  # a threading.Event: once set, every further command is refused
        self.sent: list[Move] = []

    def _state(self) -> ArmState:
        return ArmState(np.asarray(self.robot.actual_q(), dtype=float), np.asarray(self.robot.tcp(), dtype=float))

    def run(self, move: Move) -> ContactResult | None:
        """Check `move` from where the arm is now, then send it."""
        if self.abort is not None and self.abort.is_set():
            raise RoutineAborted(f"aborted before move '{move.label}'")
        self.guard.check(move, self._state())
        self.sent.append(move)
        if move.kind == "joint":
            self.robot.move_j(move.q_rad, move.speed, move.accel)
        elif move.kind == "linear":
            self.robot.move_l(move.pose, move.speed, move.accel)
        else:
            return self.robot.move_until_contact(move.direction * move.speed, move.travel_m / move.speed)
        return None

    def set_tcp(self, tool_pose) -> None:
        self.robot.set_tcp(tool_pose)

    def tcp(self) -> np.ndarray:
        return self.robot.tcp()

    def actual_q(self) -> np.ndarray:
        return self.robot.actual_q()

    def actual_tcp_pose(self) -> np.ndarray:
        return self.robot.actual_tcp_pose()

    def samples(self, since_t_s=None):
        return self.robot.samples(since_t_s)

    def stop(self) -> None:
        self.robot.stop()
