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

In a cell of two robots each move is its robot's (``Move.robot``), checked on that
robot's model and carried into the cell frame by its base as installed. The two tools
(each the drawn tool: a segment from its tip back along its axis, of its radius) must
stay ``limits.tool_clearance_m`` apart all along every move, the other robot where it
stands. Only a move that meets the other tool at a planned contact point
(``Move.meeting``) may bring them closer, and only with their tips: the part of each
tool within :data:`TIP_ZONE_FACTOR` clearances of its tip is left out there, and both
tips must be that near the contact point.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.config.cells import Cell, ToolSpec
from cellcal.config.robot_files import load_robot
from cellcal.drivers.interfaces import ContactResult, Robot
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.inverse import inverse, tcp_frames, tcp_poses
from cellcal.solvers.geometry.robot_model import KinematicModel
from cellcal.routines.framework.base import Move, PlanRefused, RoutineAborted

JOINT_PATH_SAMPLES = 24  # points along a joint move at which the TCP is checked against the box
STRAIGHT_PATH_SAMPLES = 12  # ... and along a linear move or a search, for the clearance between tools
# a run whose arm is further than this from home in any joint (1 mm at 1 m) goes home before its
# plan's first Cartesian move; a movej to home leaves the joints on it to far less
AT_HOME_RAD = 1e-3
TIP_ZONE_FACTOR = 2.0  # at a meeting, this many clearances of each tool behind its tip may come close


@dataclass
class ArmState:
    q_rad: np.ndarray
    tool_pose: np.ndarray  # the controller's TCP setting

    def tcp_pose(self, model: KinematicModel) -> np.ndarray:
        return tcp_poses(model, self.q_rad, self.tool_pose)[0]


@dataclass(frozen=True)
class Arm:
    """One robot as the guard sees it: its model, its base in the cell frame, its drawn tool."""

    model: KinematicModel
    base: np.ndarray  # 4x4, base -> cell frame, as installed
    tool: ToolSpec | None
    home: ArmState


class MotionGuard:
    def __init__(self, cell: Cell, model: KinematicModel):
        self.cell, self.model = cell, model
        self.low, self.high = np.asarray(cell.workspace_min_m), np.asarray(cell.workspace_max_m)
        self.limits = cell.limits
        self.joint_limits = model.joint_limits
        self.clearance_m = float(cell.limits.get("tool_clearance_m", 0.02))
        self.arms: dict[str, Arm] = {}
        for name, spec in (cell.robots or {}).items():
            arm_model = model if name == "a" else load_robot(spec.robot)
            tool_pose = spec.tool.tcp_pose if spec.tool is not None else np.zeros(6)
            self.arms[name] = Arm(arm_model, spec.base_matrix, spec.tool,
                                  ArmState(np.asarray(spec.home_q_rad, dtype=float), tool_pose))

    def _model(self, move: Move) -> KinematicModel:
        if move.robot == "a":
            return self.model
        if move.robot not in self.arms:
            self._refuse(move, f"the cell has no robot {move.robot!r} (robots: {', '.join(self.arms)})")
        return self.arms[move.robot].model

    def _to_cell(self, move: Move, position) -> np.ndarray:
        p = np.asarray(position, dtype=float)
        if move.robot == "a" or move.robot not in self.arms:
            return p
        base = self.arms[move.robot].base
        return p @ base[:3, :3].T + base[:3, 3]

    # -- single checks -----------------------------------------------------------------

    def _refuse(self, move: Move, what: str):
        raise PlanRefused(f"move '{move.label}': {what}")

    def _box(self, move: Move, position, what: str) -> None:
        p = self._to_cell(move, position)
        if np.any(p < self.low - 1e-9) or np.any(p > self.high + 1e-9):
            self._refuse(move, f"{what} {np.round(p, 4).tolist()} m leaves the workspace box "
                               f"{self.low.tolist()}..{self.high.tolist()} m")

    def _joints(self, move: Move, q) -> None:
        q = np.asarray(q, dtype=float)
        model = self._model(move)
        if q.shape != (model.n_joints,) or not np.all(np.isfinite(q)):
            self._refuse(move, f"joint target must be {model.n_joints} finite numbers")
        limits = self.joint_limits if move.robot == "a" else model.joint_limits
        if limits is None:
            return
        for i, (v, (lo, hi)) in enumerate(zip(q, limits)):
            if not lo <= v <= hi:
                self._refuse(move, f"joint {i + 1} at {np.rad2deg(v):.2f} deg is outside its limits "
                                   f"{np.rad2deg(lo):.1f}..{np.rad2deg(hi):.1f} deg")

    def _ceiling(self, move: Move, value: float, key: str, unit: str) -> None:
        limit = self.limits[key]
        if not np.isfinite(value) or value <= 0:
            self._refuse(move, f"{key.rsplit('_', 2)[0].replace('_', ' ')} {value!r} must be a positive number")
        if value > limit + 1e-12:
            self._refuse(move, f"{value:g} {unit} is above the cell's limit {key} = {limit:g}")

    def check(self, move: Move, state: ArmState, others: dict | None = None) -> ArmState:
        """Check one move from `state` (its robot's), the other robots standing at `others`
        (name -> ArmState; their homes when not given); return the state after it (raises
        PlanRefused)."""
        model = self._model(move)
        if move.kind == "joint":
            self._ceiling(move, move.speed, "joint_speed_rad_s", "rad/s")
            self._ceiling(move, move.accel, "joint_accel_rad_s2", "rad/s^2")
            self._joints(move, move.q_rad)
            s = np.linspace(0.0, 1.0, JOINT_PATH_SAMPLES)[:, None]
            path = state.q_rad + s * (move.q_rad - state.q_rad)
            for p in tcp_poses(model, path, state.tool_pose)[:, :3]:
                self._box(move, p, "the TCP on the way at")
            self._clearance(move, state, path, None, others)
            return ArmState(move.q_rad.copy(), state.tool_pose)
        if move.kind == "linear":
            self._ceiling(move, move.speed, "tcp_speed_m_s", "m/s")
            self._ceiling(move, move.accel, "tcp_accel_m_s2", "m/s^2")
            if move.pose is None or move.pose.shape != (6,) or not np.all(np.isfinite(move.pose)):
                self._refuse(move, "TCP target must be 6 finite numbers [x, y, z, rx, ry, rz]")
            self._box(move, move.pose[:3], "the TCP target")
            q_end = inverse(model, move.pose, state.q_rad, state.tool_pose)
            if q_end is None:
                self._refuse(move, "the TCP target cannot be reached from the arm's configuration")
            self._joints(move, q_end)
            self._clearance(move, state, None, move.pose, others)
            return ArmState(q_end, state.tool_pose)
        if move.kind == "contact":
            self._ceiling(move, move.speed, "tcp_speed_m_s", "m/s")
            self._ceiling(move, move.accel, "tcp_accel_m_s2", "m/s^2")
            travel = self.limits["contact_travel_m"]
            if not 0 < move.travel_m <= travel + 1e-12:
                self._refuse(move, f"contact travel {move.travel_m:g} m is above the cell's limit "
                                   f"contact_travel_m = {travel:g} (or not positive)")
            start = state.tcp_pose(model)
            self._box(move, start[:3] + move.direction * move.travel_m, "the end of the contact search at")
            end = start.copy()
            end[:3] += move.direction * move.travel_m
            q_end = inverse(model, end, state.q_rad, state.tool_pose)
            if q_end is None:
                self._refuse(move, "the contact search's full travel cannot be reached")
            self._joints(move, q_end)
            self._clearance(move, state, None, end, others)
            return state  # where it stops is not known in advance; the next move starts from the plan's view
        self._refuse(move, f"unknown move kind {move.kind!r}")

    def check_plan(self, plan: list[Move], start: ArmState | dict) -> ArmState:
        """Every move of a plan in order, from `start` (robot a's state, or every robot's by
        name; a robot not given starts at its home), before any of them runs; returns robot
        a's state at the end."""
        states = {name: arm.home for name, arm in self.arms.items()}
        states.update(start if isinstance(start, dict) else {"a": start})
        for move in plan:
            others = {name: st for name, st in states.items() if name != move.robot}
            states[move.robot] = self.check(move, states.get(move.robot, states["a"]), others)
        return states["a"]

    # -- two robots: the clearance between their tools -----------------------------------

    def tool_segment(self, name: str, q_rad) -> tuple[np.ndarray, np.ndarray, float] | None:
        """Robot `name`'s drawn tool at joints q, cell frame: (tip, back, radius), or None
        when the cell does not draw it."""
        arm = self.arms.get(name)
        if arm is None or arm.tool is None:
            return None
        rotation, position = tcp_frames(arm.model, q_rad)
        return self._segment(arm, rotation[0], position[0])

    @staticmethod
    def _segment(arm: Arm, rotation, position):
        r, p = arm.base[:3, :3] @ rotation, arm.base[:3, :3] @ position + arm.base[:3, 3]
        tip = p + r @ arm.tool.tcp_m
        return tip, tip - r @ arm.tool.axis * arm.tool.length_m, arm.tool.radius_m

    def _flanges(self, move: Move, state: ArmState, path_q, target):
        """Flange frames (rotations, positions; robot's base) along a move: at the joint
        samples of a joint move, else along the TCP's straight line to `target`."""
        model = self._model(move)
        if path_q is not None:
            return tcp_frames(model, path_q)
        start = state.tcp_pose(model)
        s = np.linspace(0.0, 1.0, STRAIGHT_PATH_SAMPLES)
        turn = se3.matrix_to_rotvec(se3.rotvec_to_matrix(target[3:]) @ se3.rotvec_to_matrix(start[3:]).T)
        tcp_r = np.einsum("nij,jk->nik", se3.rotvec_to_matrix(s[:, None] * turn), se3.rotvec_to_matrix(start[3:]))
        tcp_p = start[:3] + s[:, None] * (target[:3] - start[:3])
        tool_r = se3.rotvec_to_matrix(state.tool_pose[3:])
        rotation = np.einsum("nij,kj->nik", tcp_r, tool_r)
        return rotation, tcp_p - np.einsum("nij,j->ni", rotation, state.tool_pose[:3])

    def _clearance(self, move: Move, state: ArmState, path_q, target, others) -> None:
        if others is None:
            others = {n: arm.home for n, arm in self.arms.items() if n != move.robot}
        arm = self.arms.get(move.robot)
        if arm is None or arm.tool is None or not others:
            return
        rotations, positions = self._flanges(move, state, path_q, target)
        for name, other in others.items():
            fixed = self.tool_segment(name, other.q_rad)
            if fixed is None:
                continue
            for rotation, position in zip(rotations, positions):
                self._apart(move, self._segment(arm, rotation, position), fixed, name)

    def _apart(self, move: Move, mine, theirs, name: str) -> None:
        """Refuse when the tools `mine` and `theirs` (tip, back, radius) come closer than the
        clearance, except at the tips at the move's planned meeting point."""
        clear = self.clearance_m
        zone = TIP_ZONE_FACTOR * clear
        pairs = [(mine, theirs)]
        if move.meeting is not None:
            tips_far = max(np.linalg.norm(mine[0] - move.meeting), np.linalg.norm(theirs[0] - move.meeting))
            if tips_far > zone and np.linalg.norm(mine[0] - theirs[0]) - mine[2] - theirs[2] < clear:
                self._refuse(move, f"the tool tips come within {clear * 1e3:g} mm of each other "
                                   f"{tips_far * 1e3:.1f} mm from the planned contact point "
                                   f"{np.round(move.meeting, 4).tolist()} m")
            pairs = [(_behind(mine, zone), theirs), (mine, _behind(theirs, zone))]
        for a, b in pairs:
            gap, pa, pb = segments_closest(a[0], a[1], b[0], b[1])
            gap -= a[2] + b[2]
            if gap < clear:
                where = "" if move.meeting is None else ", away from the tips at the planned contact point"
                self._refuse(move, f"the tools come {gap * 1e3:.1f} mm apart (tool_clearance_m "
                                   f"{clear * 1e3:g} mm) at {np.round(0.5 * (pa + pb), 4).tolist()} m in the cell "
                                   f"frame, {np.linalg.norm(pa - mine[0]) * 1e3:.0f} mm behind robot {move.robot}'s "
                                   f"tip and {np.linalg.norm(pb - theirs[0]) * 1e3:.0f} mm behind robot {name}'s{where}")


def _behind(tool, zone_m: float):
    """The tool without its first `zone_m` from the tip (all of it kept when it is shorter)."""
    tip, back, radius = tool
    length = np.linalg.norm(back - tip)
    if length <= zone_m:
        return back, back, radius
    return tip + (back - tip) * zone_m / length, back, radius


def segments_closest(a0, a1, b0, b1) -> tuple[float, np.ndarray, np.ndarray]:
    """Distance between segments a0-a1 and b0-b1 and the closest points on each."""
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    aa, ee, f = float(d1 @ d1), float(d2 @ d2), float(d2 @ r)
    if aa < 1e-18 and ee < 1e-18:
        return float(np.linalg.norm(r)), a0, b0
    if aa < 1e-18:
        s, t = 0.0, float(np.clip(f / ee, 0.0, 1.0))
    else:
        c = float(d1 @ r)
        if ee < 1e-18:
            s, t = float(np.clip(-c / aa, 0.0, 1.0)), 0.0
        else:
            b = float(d1 @ d2)
            denom = aa * ee - b * b
            s = float(np.clip((b * f - c * ee) / denom, 0.0, 1.0)) if denom > 1e-18 else 0.0
            t = (b * s + f) / ee
            if t < 0.0:
                s, t = float(np.clip(-c / aa, 0.0, 1.0)), 0.0
            elif t > 1.0:
                s, t = float(np.clip((b - c) / aa, 0.0, 1.0)), 1.0
    pa, pb = a0 + s * d1, b0 + t * d2
    return float(np.linalg.norm(pa - pb)), pa, pb


class GuardedRobot:
    """The robot as a routine sees it: every motion command checked by the guard first.

    Also records every command that reached the robot (``sent``), so tests can show no
    command outside the limits ever got through. Given the controller's tool frame when the
    run starts (`tool_frame`), it keeps it, and every frame set through it, instead of asking the
    controller before each move (the run is the only one that sets it meanwhile).
    """

    def __init__(self, robot: Robot, guard: MotionGuard, abort=None, name: str = "a", tool_frame=None):
        self.robot, self.guard = robot, guard
        self.abort = abort  # a threading.Event: once set, every further command is refused
        self.name = name  # which robot of the cell
        self.peers: dict[str, GuardedRobot] = {}  # the cell's other robots, guarded alike
        self.sent: list[Move] = []
        self._tool_frame = None if tool_frame is None else np.asarray(tool_frame, dtype=float)
        self._unwound = False  # the run's first move checks for a wrist left beyond its limits

    @classmethod
    def of_cell(cls, robots: dict, guard: MotionGuard, abort=None, tool_frames: dict | None = None
                ) -> dict[str, "GuardedRobot"]:
        """Every robot of a cell (name -> driver) guarded, each checked against where the
        others are when it moves; `tool_frames`: the controller's frame of those whose frame the
        run knows at its start (name -> frame)."""
        frames = tool_frames or {}
        guarded = {name: cls(robot, guard, abort, name, frames.get(name)) for name, robot in robots.items()}
        for name, g in guarded.items():
            g.peers = {n: other for n, other in guarded.items() if n != name}
        return guarded

    def peer(self, name: str) -> "GuardedRobot":
        """Another robot of the cell, guarded alike."""
        if name not in self.peers:
            raise RoutineAborted(f"the cell has no robot {name!r} opened")
        return self.peers[name]

    def _state(self) -> ArmState:
        frame = self.robot.tool_frame() if self._tool_frame is None else self._tool_frame
        return ArmState(np.asarray(self.robot.actual_q(), dtype=float), np.asarray(frame, dtype=float))

    def run(self, move: Move) -> ContactResult | None:
        """Check `move` from where the arm is now (the other robots where they are), then send it."""
        if self.abort is not None and self.abort.is_set():
            raise RoutineAborted(f"stopped before move '{move.label}'")
        if move.robot != self.name:
            raise PlanRefused(f"move '{move.label}': a move of robot {move.robot}, sent to robot {self.name}")
        others = {name: peer._state() for name, peer in self.peers.items()} if self.peers else None
        if not self._unwound:
            self._unwound = True
            for lead in (self.unwinding, self.to_plan_start):  # the second looks after the first has run
                before = lead(move)
                if before is not None:
                    self.run(before)
        self.guard.check(move, self._state(), others)
        self.sent.append(move)
        if move.kind == "joint":
            self.robot.move_j(move.q_rad, move.speed, move.accel)
        elif move.kind == "linear":
            self.robot.move_l(move.pose, move.speed, move.accel)
        else:
            return self.robot.move_until_contact(move.direction * move.speed, move.travel_m / move.speed)
        return None

    def unwinding(self, first: Move) -> Move | None:
        """The joint move that turns back, by whole turns, every joint the arm holds outside its
        limits (a run aborted during a wrist's turn may leave it a little beyond one) when the
        turned value is inside them: the same pose, so the plan's first move starts within the
        limits. None when every joint is inside its limits, or one cannot be turned back in."""
        limits = self.guard.joint_limits if self.name == "a" else self.guard.arms[self.name].model.joint_limits
        if limits is None:
            return None
        q = np.asarray(self.robot.actual_q(), dtype=float)
        low, high = np.asarray(limits, dtype=float).T
        outside = (q < low) | (q > high)
        if not np.any(outside):
            return None
        turned = np.where(outside, q - 2.0 * np.pi * np.round(q / (2.0 * np.pi)), q)
        if np.any(turned < low) or np.any(turned > high):
            return None
        joints = ", ".join(f"{i + 1} ({np.rad2deg(q[i]):.2f} deg)" for i in np.flatnonzero(outside))
        return self._joint_move(f"unwind joint {joints} back inside its limits before '{first.label}'", turned)

    def to_plan_start(self, first: Move) -> Move | None:
        """The joint move to the joints every plan is checked from (the robot's home) when the arm is
        elsewhere and the plan's first move is a Cartesian one: a run aborted between two orientations
        leaves the arm where a straight line to the plan's first pose could wind a wrist past its
        limits. The joint move's own path is checked as any other. None at home (within
        AT_HOME_RAD), or when the plan starts with a joint move (checked from wherever the arm is)."""
        if first.kind == "joint":
            return None
        arm = self.guard.arms.get(self.name)
        if arm is None:
            return None
        q = np.asarray(self.robot.actual_q(), dtype=float)
        if q.shape != arm.home.q_rad.shape or np.abs(q - arm.home.q_rad).max() <= AT_HOME_RAD:
            return None
        return self._joint_move(f"back to home, where the plan starts, before '{first.label}'", arm.home.q_rad.copy())

    def _joint_move(self, label: str, q) -> Move:
        """A joint move of this robot at the cell's joint speed and acceleration limits."""
        cell = self.guard.limits
        return Move.joint(label, q, cell["joint_speed_rad_s"], cell["joint_accel_rad_s2"], robot=self.name)

    def set_tcp(self, tool_pose) -> None:
        tracked, self._tool_frame = self._tool_frame is not None, None  # unknown should the write fail
        self.robot.set_tcp(tool_pose)
        if tracked:
            self._tool_frame = np.asarray(tool_pose, dtype=float)

    def tool_frame(self) -> np.ndarray:
        return self.robot.tool_frame()

    def actual_q(self) -> np.ndarray:
        return self.robot.actual_q()

    def actual_tcp_pose(self) -> np.ndarray:
        return self.robot.actual_tcp_pose()

    def samples(self, since_t_s=None):
        return self.robot.samples(since_t_s)

    def stop(self) -> None:
        self.robot.stop()
