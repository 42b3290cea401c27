"""``handshake``: robot b's base in robot a's frame, from their needle tips meeting.

A cell of two robots (``robots: {a, b}`` in the cell file) with a needle on each. The
routine chooses the meeting points itself, spread over a box of the shared workspace
(section ``handshake``: its centre and half extents): the box's corners as two
interleaved tetrahedra first, so any four in order are out of one plane, then its face
centres, its centre, and the corners of the half-size box. At each point:

* robot a holds its needle tip there, the needle tilted `tilt_deg` from the line between
  the bases towards a direction that goes round from point to point, and turned about its
  own axis by +-`turn_deg` in turn (the tips are unknowns of the fit: each robot must
  show its needle in several orientations);
* robot b comes to `standoff_mm` back along its own needle (tilted likewise towards
  another direction, turned the other way), then to `approach_mm`, and searches along the
  needle onto a's tip; a compliant search is guided onto it by the centring cup of a's
  needle, and both robots' joints are recorded;
* robot b goes back to its standoff before robot a moves on.

Every move is checked by the guard before anything moves, robot b's in the cell frame by
its base as installed, and the two needles stay ``limits.tool_clearance_m`` apart except
at their tips at the planned meeting. Robot b is aimed with its base as installed; each
meeting shows how far off that aim is, and the following ones are aimed that much better
(the moves re-checked by the guard as they are sent).

The fit (:func:`cellcal.solvers.tool_frames.handshake.fit_handshake`) is one least-squares problem in
b's base pose and both needle tips, from a closed-form SVD start; its condition, the
points' own conditioning and the errors the design should give at the stated
repeatability are reported. Before anything moves the design is judged: a plan whose
expected frame error is above `target_mm` / `target_deg` is refused, as is (by the
solver) a point set of fewer than four or on one plane.

Section ``handshake`` of the cell file::

    points: 12                  # meetings, 4..23
    centre_m: [x, y, z]         # middle of the box the points are spread over (cell frame)
    half_extent_m: [x, y, z]
    tilt_deg: 20                # each needle from the line between the bases
    turn_deg: 60                # about each needle's axis, + and - in turn
    approach_mm: 10             # where each search starts (it may go twice that)
    standoff_mm: 120            # where robot b waits while robot a moves
    search_speed_mm_s: 5
    repeatability_mm: 0.02      # each arm's stated repeatability (RMS distance of a repeated pose)
    target_mm: 0.1              # refuse a design whose expected base error (1 sigma) is larger
    target_deg: 0.01
    min_out_of_plane_mm: 20     # refuse points that stand less than this (RMS) out of one plane
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.reader import Section
from cellcal.config.robot_files import load_robot
from cellcal.solvers.tool_frames import handshake as hs
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.inverse import inverse, tcp_frames
from cellcal.routines.framework.base import PlanPromise, Devices, Move, PlanRefused, Result, RoutineError
from cellcal.routines.framework.steps import StepRoutine
from cellcal.routines.handshake_result import handshake_result
from cellcal.routines.tcp_npoint import axis_sigma_mm

JOINT_SPEED_RAD_S = 1.0
# the unit cube's points in the order they are used: two interleaved tetrahedra (the
# corners), the face centres, the centre, the half-size box's corners
_CORNERS = [(-1, -1, -1), (1, 1, -1), (1, -1, 1), (-1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1), (1, 1, 1)]
_ORDER = np.array(_CORNERS + [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1), (0, 0, 0)]
                  + [tuple(0.5 * np.array(c)) for c in _CORNERS], dtype=float)


@dataclass(frozen=True)
class HandshakeOptions:
    points: int
    centre_m: np.ndarray
    half_extent_m: np.ndarray
    tilt_deg: float
    turn_deg: float
    approach_mm: float
    standoff_mm: float
    search_speed_mm_s: float
    repeatability_mm: float
    target_mm: float
    target_deg: float
    min_out_of_plane_mm: float


@dataclass(frozen=True)
class Meeting:
    """One planned meeting: the point and each needle's tool frame rotation (cell frame)."""

    number: int
    point_m: np.ndarray
    rotation_a: np.ndarray
    rotation_b: np.ndarray

    @property
    def direction_b(self) -> np.ndarray:
        """The way robot b's needle points (and searches), cell frame."""
        return self.rotation_b[:, 2]


def _frame_with_z(z: np.ndarray, turn_rad: float) -> np.ndarray:
    """A rotation whose z is `z`, x as near the cell's z as that allows, turned about z."""
    z = z / np.linalg.norm(z)
    ref = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z]) @ se3.rot("z", turn_rad)


def _tilted(axis: np.ndarray, tilt_rad: float, azimuth_rad: float) -> np.ndarray:
    """`axis` tilted by `tilt_rad` towards the direction at `azimuth_rad` round it."""
    frame = _frame_with_z(axis, azimuth_rad)
    return np.cos(tilt_rad) * axis + np.sin(tilt_rad) * frame[:, 0]


class Handshake(StepRoutine):
    name = "handshake"
    section = "handshake"
    selector = 4
    needs = ("robot",)
    robots = ("a", "b")

    @classmethod
    def read_options(cls, section: Section, cell: Cell) -> HandshakeOptions:
        if "b" not in cell.robots:
            section.fail(None, "the handshake needs a cell of two robots ([robots] a and b)")
        for name in ("a", "b"):
            if cell.robots[name].tool is None:
                section.fail(None, f"the handshake needs robot {name}'s needle as drawn in [robots.{name}.tool]")
        base_b = cell.robots["b"].base_pose[:3]
        travel_mm = cell.limits["contact_travel_m"] * 1e3
        options = HandshakeOptions(
            section.integer("points", 12, low=hs.MIN_POINTS, high=len(_ORDER)),
            section.vector("centre_m", 3, base_b / 2 + [0.0, 0.0, 0.5]),
            section.vector("half_extent_m", 3, [0.2, 0.25, 0.15]),
            section.number("tilt_deg", 20.0, low=0.0, high=40.0),
            section.number("turn_deg", 60.0, low=0.0, high=90.0),
            section.number("approach_mm", 10.0, low=2.0, high=travel_mm / 2),
            section.number("standoff_mm", 120.0, low=20.0, high=500.0),
            section.number("search_speed_mm_s", 5.0, above=0.0, high=min(cell.limits["tcp_speed_m_s"] * 1e3, 20.0)),
            section.number("repeatability_mm", 0.02, above=0.0, high=1.0),
            section.number("target_mm", 0.1, above=0.0, high=100.0),
            section.number("target_deg", 0.01, above=0.0, high=10.0),
            section.number("min_out_of_plane_mm", 20.0, above=0.0, high=1000.0))
        if np.any(options.half_extent_m < 0):
            section.fail("half_extent_m", "must not be negative")
        section.done()
        return options

    # -- plan ------------------------------------------------------------------------

    def meetings(self) -> list[Meeting]:
        """Where the tips meet and how each needle is held there (cell frame)."""
        o = self.options
        toward_b = self._toward_b()
        tilt = np.deg2rad(o.tilt_deg)
        out = []
        for k in range(o.points):
            point = o.centre_m + _ORDER[k] * o.half_extent_m
            azimuth = np.deg2rad(137.5 * k)  # goes round without repeating
            turn = np.deg2rad(o.turn_deg) * (1 if k % 2 == 0 else -1)
            axis_a = _tilted(toward_b, tilt, azimuth)
            axis_b = _tilted(-toward_b, tilt, azimuth + np.pi / 2)
            out.append(Meeting(k + 1, point, _frame_with_z(axis_a, turn), _frame_with_z(axis_b, -turn)))
        return out

    def _poses(self, meeting: Meeting, offset_b_m=np.zeros(3)) -> dict:
        """TCP poses of a meeting: robot a's (its base = the cell frame) and robot b's at the
        standoff and the approach, in b's base frame as installed (aimed `offset_b_m` off)."""
        o = self.options
        base = self.cell.robots["b"].base_matrix
        to_b_rot, to_b = base[:3, :3].T, -base[:3, :3].T @ base[:3, 3]
        rotvec_b = se3.matrix_to_rotvec(to_b_rot @ meeting.rotation_b)

        def b_pose(back_mm):
            tip = meeting.point_m - back_mm / 1e3 * meeting.direction_b
            return np.concatenate([to_b_rot @ tip + to_b + offset_b_m, rotvec_b])

        return {"a": np.concatenate([meeting.point_m, se3.matrix_to_rotvec(meeting.rotation_a)]),
                "standoff": b_pose(o.standoff_mm), "approach": b_pose(o.approach_mm)}

    def _toward_b(self) -> np.ndarray:
        """Horizontal unit direction from robot a's base to robot b's (cell frame)."""
        toward = np.array(self.cell.robots["b"].base_pose[:3], dtype=float)
        toward[2] = 0.0
        return toward / np.linalg.norm(toward)

    def _waiting_pose(self) -> np.ndarray:
        """Where robot b waits while robot a moves (its base frame as installed): its tip
        on the line through the box's centre, beyond the box's side and the standoff,
        its needle pointing at robot a."""
        o = self.options
        toward = self._toward_b()
        reach = float(np.abs(o.half_extent_m) @ np.abs(toward)) + o.standoff_mm / 1e3
        base = self.cell.robots["b"].base_matrix
        tip = base[:3, :3].T @ (o.centre_m + reach * toward - base[:3, 3])
        return np.concatenate([tip, se3.matrix_to_rotvec(base[:3, :3].T @ _frame_with_z(-toward, 0.0))])

    def steps(self) -> list[tuple[Move, Meeting | None]]:
        """Every motion and, for the searches, which meeting it is."""
        cell = self.cell
        limits = cell.limits
        speed, accel, joint_accel = limits["tcp_speed_m_s"], limits["tcp_accel_m_s2"], limits["joint_accel_rad_s2"]
        joint_speed = min(JOINT_SPEED_RAD_S, limits["joint_speed_rad_s"])
        q = {name: np.asarray(cell.robots[name].home_q_rad, dtype=float) for name in ("a", "b")}
        steps: list[tuple[Move, Meeting | None]] = []
        waiting = self._waiting_pose()
        for m in self.meetings():
            poses = self._poses(m)
            reached = {}
            for name, pose, what in (("a", poses["a"], "holds meeting point"), ("b", poses["standoff"], "stands off"),
                                     ("b", waiting, "waits after")):
                found = inverse(load_robot(cell.robots[name].robot), pose, q[name], cell.robots[name].tool.tcp_pose)
                if found is None:
                    raise PlanRefused(f"move 'robot {name} {what} {m.number}': the pose "
                                      f"{np.round(pose[:3], 4).tolist()} m (robot {name}'s base) cannot be "
                                      f"reached; is [handshake] centre_m/half_extent_m within both robots' reach?")
                q[name] = reached[what] = found
            steps.append((Move.joint(f"robot a holds meeting point {m.number}", reached["holds meeting point"],
                                     joint_speed, joint_accel), None))
            steps.append((Move.joint(f"robot b stands off {m.number}", reached["stands off"], joint_speed,
                                     joint_accel, robot="b"), None))
            steps += self._meeting_moves(m, poses, speed, accel)
            steps.append((Move.joint(f"robot b waits after {m.number}", reached["waits after"], joint_speed,
                                     joint_accel, robot="b"), None))
        steps.append((Move.joint("robot b home", cell.robots["b"].home_q_rad, joint_speed, joint_accel, robot="b"),
                       None))
        steps.append((Move.joint("robot a home", cell.home_q_rad, joint_speed, joint_accel), None))
        return steps

    def _meeting_moves(self, m: Meeting, poses: dict, speed, accel) -> list[tuple[Move, Meeting | None]]:
        """Robot b's approach, search and retreat for one meeting (poses from :meth:`_poses`)."""
        o = self.options
        base = self.cell.robots["b"].base_matrix
        direction_b = base[:3, :3].T @ m.direction_b
        return [(Move.linear(f"robot b approaches {m.number}", poses["approach"], speed, accel, robot="b",
                             meeting=m.point_m), None),
                (Move.contact(f"meeting {m.number}", direction_b, o.search_speed_mm_s / 1e3,
                              2 * o.approach_mm / 1e3, robot="b", meeting=m.point_m), m),
                (Move.linear(f"robot b backs off {m.number}", poses["standoff"], speed, accel, robot="b",
                             meeting=m.point_m), None)]

    def design(self) -> PlanPromise:
        """The planned meetings judged at the stated repeatability, on the drawn tips and the
        base as installed (what the plan aims at): robot b's base position's expected error,
        mm, and its rotation's (``details["rotation_deg"]``)."""
        cell = self.cell
        base = cell.robots["b"].base_matrix
        frames = {"a": ([], []), "b": ([], [])}
        for m in self.meetings():
            held = (("a", m.rotation_a, m.point_m),
                    ("b", base[:3, :3].T @ m.rotation_b, base[:3, :3].T @ (m.point_m - base[:3, 3])))
            for name, rotation, tip in held:
                tool = cell.robots[name].tool
                flange = rotation @ se3.rotvec_to_matrix(tool.tcp_pose[3:]).T
                frames[name][0].append(flange)
                frames[name][1].append((tip - flange @ tool.tcp_m) * 1e3)
        sigma = np.sqrt(2.0) * axis_sigma_mm(self.options.repeatability_mm)  # both arms' repeatability
        found = hs.design(*(np.array(v) for v in (*frames["a"], *frames["b"])), cell.robots["a"].tool.tcp_m * 1e3,
                          cell.robots["b"].tool.tcp_m * 1e3, sigma)
        return PlanPromise(found.condition, found.position_mm, "mm", {"rotation_deg": found.rotation_deg})

    def check_design(self) -> PlanPromise:
        """The plan judged before anything moves: PlanRefused for points on one plane or too
        few (the solver's reason), or an expected frame error above the targets."""
        o = self.options
        try:
            points = hs.check_points([m.point_m * 1e3 for m in self.meetings()], o.min_out_of_plane_mm)
        except hs.HandshakeRefused as exc:
            raise PlanRefused(f"{self.cell.path} [handshake]: {exc}") from None
        design = self.design()
        rotation_deg = design.details["rotation_deg"]
        if design.expected_error > o.target_mm or rotation_deg > o.target_deg:
            raise PlanRefused(
                f"{self.cell.path} [handshake]: these {o.points} meetings would leave robot b's base "
                f"{design.expected_error:.4f} mm and {rotation_deg:.5f} deg off (1 sigma) at "
                f"{o.repeatability_mm:g} mm repeatability, above target_mm {o.target_mm:g} / target_deg "
                f"{o.target_deg:g} (condition {design.condition:.3g}, points' conditioning {points.condition:.3g}); "
                "plan more points, a larger half_extent_m or more tilt_deg")
        return design

    # -- measure ---------------------------------------------------------------------

    def announce(self, design: PlanPromise) -> str:
        o = self.options
        points = hs.point_set([m.point_m * 1e3 for m in self.meetings()])
        return (f"handshake: {o.points} meetings over {np.round(2 * o.half_extent_m * 1e3).tolist()} mm round "
                f"{np.round(o.centre_m, 3).tolist()} m, points' conditioning {points.condition:.3g}; expected "
                f"base error {design.expected_error:.4f} mm, {design.details['rotation_deg']:.5f} deg (1 sigma) at "
                f"{o.repeatability_mm:g} mm repeatability, condition {design.condition:.3g}")

    def drawn_tools(self) -> dict[str, np.ndarray]:
        return {name: self.cell.robots[name].tool.tcp_pose for name in self.robots}

    def dataset_meta(self, design: PlanPromise, before: dict) -> dict:
        return {"planned_tip_a_m": self.cell.robots["a"].tool.tcp_m.tolist(),
                "planned_tip_b_m": self.cell.robots["b"].tool.tcp_m.tolist(),
                "base_b_as_installed": self.cell.robots["b"].base_pose.tolist(),
                "repeatability_mm": self.options.repeatability_mm, "tool_frame_before_b": before["b"].tolist()}

    def run_steps(self, devices: Devices, robot, plan: list[Move], steps, progress) -> tuple[list[dict], float]:
        """Run the steps; robot b's moves of each meeting re-aimed by what the meetings so far
        showed (its base as installed is off by that much)."""
        robot_b = robot.peer("b")
        o = self.options
        motion_s = 0.0  # each move on its own robot's clock: the two robots move in turn
        speed, accel = self.cell.limits["tcp_speed_m_s"], self.cell.limits["tcp_accel_m_s2"]
        misses: list[np.ndarray] = []
        rows = []
        pending: list = []  # the current meeting's re-aimed moves of robot b
        for move, meeting in steps:
            if move.robot == "b" and move.label.startswith("robot b stands off"):
                number = int(move.label.rsplit(" ", 1)[1])
                m = self.meetings()[number - 1]
                aim = np.mean(misses, axis=0) if misses else np.zeros(3)
                poses = self._poses(m, aim)
                pending = self._meeting_moves(m, poses, speed, accel)
                if misses:
                    move = Move.linear(f"robot b stands off {number}", poses["standoff"], speed, accel, robot="b")
            if pending and move.label == pending[0][0].label:
                move = pending.pop(0)[0]
            arm = robot if move.robot == "a" else robot_b
            t_s = arm.samples()[-1].t_s
            found = arm.run(move)
            motion_s += arm.samples()[-1].t_s - t_s
            if meeting is None:
                continue
            if not found.contact:
                raise RoutineError(
                    f"{move.label}: robot b's needle went {move.travel_m * 1e3:g} mm along its axis without meeting "
                    f"robot a's tip at {np.round(meeting.point_m, 4).tolist()} m: is [robots.b] base_m / "
                    "base_rotvec_deg where robot b stands? (nothing moved after)")
            q_a, q_b = np.asarray(robot.actual_q(), dtype=float), np.asarray(robot_b.actual_q(), dtype=float)
            reached = np.asarray(robot_b.actual_tcp_pose(), dtype=float)[:3]
            planned = self._poses(meeting)["approach"][:3] + move.direction * o.approach_mm / 1e3
            misses.append(reached - planned)
            rows.append({"point": meeting.number, **{f"qa{j + 1}_rad": v for j, v in enumerate(q_a)},
                         **{f"qb{j + 1}_rad": v for j, v in enumerate(q_b)}})
            progress(f"handshake: meeting {meeting.number} of {o.points} recorded "
                     f"(robot b {np.linalg.norm(misses[-1]) * 1e3:.2f} mm from where its base as installed puts it)")
        return rows, float(motion_s)

    # -- solve -----------------------------------------------------------------------

    @classmethod
    def solve(cls, dataset, cell: Cell, options: HandshakeOptions) -> Result:
        meta = dataset.meta
        models = {name: load_robot(cell.robots[name].robot) for name in ("a", "b")}
        frames = {}
        for name, letter in (("a", "qa"), ("b", "qb")):
            columns = [f"{letter}{j + 1}_rad" for j in range(models[name].n_joints)]
            if any(c not in dataset.columns for c in columns):
                raise RoutineError(f"{dataset.path}: needs both robots' joints ({', '.join(columns)}, ...)")
            rotation, position = tcp_frames(models[name], dataset.stack(*columns))
            frames[name] = (rotation, position * 1e3)
        tips = [np.asarray(meta.get(f"planned_tip_{n}_m", cell.robots[n].tool.tcp_m), dtype=float) * 1e3
                for n in ("a", "b")]
        sigma = np.sqrt(2.0) * axis_sigma_mm(options.repeatability_mm)  # both arms' repeatability, per axis
        try:
            fit = hs.fit_handshake(*frames["a"], *frames["b"], *tips, min_out_of_plane_mm=options.min_out_of_plane_mm,
                                   sigma_prior_mm=sigma)
        except hs.HandshakeRefused as exc:
            raise RoutineError(f"{dataset.path}: {exc}: not solved") from None
        design = hs.design(*frames["a"], *frames["b"], *tips, sigma)
        rotation_a, position_a = frames["a"]
        points = np.einsum("nij,j->ni", rotation_a, fit.tip_a_mm) + position_a
        return handshake_result(cls.name, dataset, cell, options, fit, design, points)
