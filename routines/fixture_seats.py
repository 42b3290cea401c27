"""Where ``kinematic-fixture`` seats the tool in a plate's sockets (or touches its balls), and
the moves there and back clear of the plate, planned on the nominal arm before anything moves.

The candidates (:meth:`SeatPlanner.candidate_orientations`; a ball's at each of its spots,
:meth:`SeatPlanner.spots`) are kept where the arm reaches them within the joint limits, clear of
singularities and with a way in from above on the same wrist branch; the D-optimal seat design
(solvers/fixtures/fixture_design.py) chooses among them for all sockets together, as the tracker
routine chooses its poses (:attr:`SeatPlanner.seat_plan`). :meth:`SeatPlanner.steps` goes wrist
branch by wrist branch, a change of wrist via home; a way in or a joint move that would pass
nearer a ball than CLEARANCE_MM refuses the plan.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.robot_files import load_robot
from cellcal.solvers.fixtures.fixture_design import select_seats
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.inverse import dexterity, inverse, inverse_many, tcp_frames
from cellcal.routines.framework.base import Move, PlanRefused
from cellcal.routines.tcp_npoint import down_orientation

LIFT_MM = 40.0  # above each socket's first approach and after its last, clear of the plate
JOINT_SPEED_RAD_S = 1.0
CANDIDATE_AZIMUTH_STEP_DEG = 30.0  # the seat design chooses among tilts at azimuths this far apart
WRISTS = ("normal", "flipped")  # the wrist branches, in the order a placement's seats take them
MIN_DEXTERITY = 0.08  # seats nearer a singularity are not offered (half of a UR's home pose, 0.16)
CONTACT_AZIMUTH_STEP_DEG = 60.0  # and the tool's tilts at each, at azimuths this far apart (fewer than a socket's)
MAX_CONTACT_ANGLE_DEG = 70.0  # the tool axis at most this far from the contact's direction: the tip touches first
CLEARANCE_MM = 1.0  # the way in from above passes the ball (with the tip's rounding) at least this far off


@dataclass(frozen=True)
class SeatPlan:
    """The seats the design chose, wrist branch by branch, and its log-determinant."""

    seats: dict  # (placement name, point) -> [(rotation, seat info, joints at rest)]
    log_det: float


class SeatPlanner:
    """The seats (a stylus plate: the contacts) of one cell file's ``kinematic_fixture`` section
    and the moves that make them, from the nominal arm; nothing moves here."""

    def __init__(self, cell: Cell, options):  # the routine's KinematicFixtureOptions
        self.cell = cell
        self.options = options

    @property
    def contacts(self) -> bool:
        """A stylus plate (the fixture's stylus_radius_mm): balls the tip touches, not sockets it seats in."""
        return self.options.placed.fixture.stylus_radius_mm is not None

    @property
    def what(self) -> str:
        return "ball" if self.contacts else "socket"

    @property
    def seats_word(self) -> str:
        return "contacts" if self.contacts else "seats"

    def candidate_orientations(self, azimuth_step_deg: float = CANDIDATE_AZIMUTH_STEP_DEG) -> list[tuple[np.ndarray, dict]]:
        """(tool frame rotation, what it is) of every seat the design may choose in one socket: tilts of
        0, 1/3, 2/3 and all of `max_tilt_deg` at azimuths every 30 deg, each turned -, 0 and +`turn_deg`
        about the tool axis."""
        o = self.options
        down = down_orientation(self.cell, load_robot(self.cell.robot))
        out = []
        tilts = [(0.0, 0.0)] + [(o.max_tilt_deg * f, az) for f in (1 / 3, 2 / 3, 1.0)
                                 for az in np.arange(0.0, 360.0, azimuth_step_deg)]
        for tilt_deg, azimuth in tilts:
            phi = np.deg2rad(azimuth)
            tilt = se3.rotvec_to_matrix(np.deg2rad(tilt_deg) * np.array([np.cos(phi), np.sin(phi), 0.0]))
            for turn in (-o.turn_deg, 0.0, o.turn_deg) if o.turn_deg > 0 else (0.0,):
                out.append((tilt @ down @ se3.rot("z", np.deg2rad(turn)),
                            {"tilt_deg": float(tilt_deg), "azimuth_deg": float(azimuth), "turn_deg": float(turn)}))
        return out

    def spots(self) -> list[tuple[float, float]]:
        """(elevation, azimuth on the plate) deg of the spots of a ball's upper half the tip touches, one
        contact each (`orientations` of them): azimuths evenly around, elevations in turn low, middle and
        high of `elevation_deg`, so the contacts' normals span the ball and place its centre in all three
        directions (contacts at one spot would place it only along that spot's normal). The design
        chooses the tool's orientation and wrist at each. Raises PlanRefused for a spot whose way in from
        above (the tip's rounding LIFT_MM over the ball, then down to `approach_mm` off the spot) would
        not keep clear of the ball."""
        o = self.options
        contact_mm = o.placed.fixture.stylus_radius_mm
        out = []
        for k in range(o.orientations):
            elevation = float(np.linspace(*o.elevation_deg, 3)[k % 3])
            e = np.deg2rad(elevation)
            above = np.array([0.0, 0.0, contact_mm + LIFT_MM])
            start = (contact_mm + o.approach_mm) * np.array([np.cos(e), 0.0, np.sin(e)])
            if _segment_clearance(above, start) < contact_mm + CLEARANCE_MM:
                raise PlanRefused(f"{self.cell.path} [kinematic_fixture]: elevation_deg: a spot {elevation:g} deg up the "
                                  f"ball cannot be reached from above without touching it on the way; raise the lowest "
                                  "elevation")
            out.append((elevation, float(360.0 * k / o.orientations)))
        return out

    def candidate_poses(self, setup, point):
        """The candidates at one point: (rotation, seat info) of each, the TCP pose at rest (a socket) or
        at contact (a ball), the pose its way in must reach on the same wrist branch, the ball's outward
        normal at each contact (None for a socket), and the pose above the point the arm first reaches."""
        o, r = self.options, self.cell.tool.radius_m
        if not self.contacts:
            candidates = self.candidate_orientations()
            centre = setup.point_m(o.placed.layout_mm[point]) + [0.0, 0.0, r]
            rest = np.array([np.concatenate([centre + r * rot[:, 2], se3.matrix_to_rotvec(rot)])
                             for rot, _ in candidates])
            axes = np.array([rot[:, 2] for rot, _ in candidates])
            way_in = rest.copy()
            way_in[:, :3] -= (LIFT_MM + o.approach_mm) / 1e3 * axes
            upright = int(np.argmin([c["tilt_deg"] for _, c in candidates]))
            above = rest[upright].copy()
            above[:3] -= LIFT_MM / 1e3 * axes[upright]
            return candidates, rest, way_in, None, above
        centre = setup.point_m(o.placed.layout_mm[point])  # the ball's centre as drawn
        contact_m = o.placed.fixture.stylus_radius_mm / 1e3
        tools = self.candidate_orientations(CONTACT_AZIMUTH_STEP_DEG)
        candidates, normal = [], []
        for spot, (elevation, azimuth) in enumerate(self.spots()):
            e, a = np.deg2rad(elevation), np.deg2rad(azimuth + setup.yaw_deg)
            n = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            for rot, seat in tools:
                # the tip, not the shank, touches first: the tool points into the ball
                if -n @ rot[:, 2] >= np.cos(np.deg2rad(MAX_CONTACT_ANGLE_DEG)):
                    candidates.append((rot, {**seat, "elevation_deg": elevation, "spot_azimuth_deg": azimuth,
                                             "spot": spot, "normal": n}))
                    normal.append(n)
        normal = np.array(normal)
        rot_vecs = np.array([se3.matrix_to_rotvec(rot) for rot, _ in candidates])
        axes = np.array([rot[:, 2] for rot, _ in candidates])
        rest = np.concatenate([centre + contact_m * normal + r * axes, rot_vecs], axis=1)
        way_in = np.concatenate([centre + (contact_m + LIFT_MM / 1e3) * np.array([0.0, 0.0, 1.0]) + r * axes, rot_vecs],
                                axis=1)
        down = next(rot for rot, c in tools if c["tilt_deg"] == 0.0 and c["turn_deg"] == 0.0)  # the upright tool
        above = np.concatenate([centre + [0.0, 0.0, contact_m + LIFT_MM / 1e3] + r * down[:, 2],
                                se3.matrix_to_rotvec(down)])
        return candidates, rest, way_in, normal, above

    @functools.cached_property
    def seat_plan(self) -> SeatPlan:
        """`orientations` of each socket's reachable candidates (either wrist branch when
        `wrist_flip`; a ball: one at each spot), chosen together for every socket by the
        D-optimal seat design on the nominal model."""
        cell, o = self.cell, self.options
        model = load_robot(cell.robot)
        tool = cell.tool
        limits = model.joint_limits
        q_all, group, info, normals = [], [], [], []
        for setup in o.placed.placements:
            for point in o.placed.fixture.points:
                where = f"{self.what} {point} of placement {setup.name}"
                candidates, rest, way_in, normal, above = self.candidate_poses(setup, point)
                q_up = _reach(model, above, cell.home_q_rad, tool.tcp_pose)
                if q_up is None:
                    raise PlanRefused(f"{cell.path} [kinematic_fixture]: move 'above {where}': the pose "
                                      f"{np.round(above[:3], 4).tolist()} m cannot be reached from home; "
                                      "check the placement's at_m")
                seeds = [("normal", q_up)]
                if o.wrist_flip:
                    flipped = q_up + [0.0, 0.0, 0.0, np.pi, 0.0, np.pi]
                    flipped[4] = -q_up[4]
                    flipped = inverse(model, above, flipped, tool.tcp_pose)
                    if flipped is not None and np.sign(np.sin(flipped[4])) != np.sign(np.sin(q_up[4])):
                        seeds.append(("flipped", flipped))
                for branch, seed in seeds:
                    q = inverse_many(model, rest, seed, tool.tcp_pose)
                    ok = np.isfinite(q).all(axis=1)
                    if model.n_joints == 6:  # each seat on its seed's wrist branch (a six-joint arm's joint 5)
                        ok[ok] &= np.sign(np.sin(q[ok, 4])) == np.sign(np.sin(seed[4]))
                    if limits is not None:
                        ok[ok] &= np.all((q[ok] >= limits[:, 0]) & (q[ok] <= limits[:, 1]), axis=1)
                    # clear of singularities, and the way in from above on the same branch
                    ok[ok] &= dexterity(model, q[ok], tool.tcp_pose) >= MIN_DEXTERITY
                    q_above = inverse_many(model, way_in[ok], q[ok], tool.tcp_pose)
                    near = np.isfinite(q_above).all(axis=1) & (np.abs(q_above - q[ok]).max(axis=1) < 0.5)
                    if limits is not None:  # the way in within the limits too
                        near[near] &= np.all((q_above[near] >= limits[:, 0]) & (q_above[near] <= limits[:, 1]), axis=1)
                    ok[ok] &= near
                    for i in np.flatnonzero(ok):
                        q_all.append(q[i])
                        group.append((setup.name, point))
                        info.append((candidates[i], branch))
                        normals.append(normal[i] if normal is not None else None)
        q_all = np.array(q_all)
        keys = [(s.name, p) for s in o.placed.placements for p in o.placed.fixture.points]
        short = [k for k in keys if sum(g == k for g in group) < o.orientations]
        if short:
            raise PlanRefused(f"{cell.path} [kinematic_fixture]: {self.what} {short[0][1]} of placement {short[0][0]}: "
                              f"only {sum(g == short[0] for g in group)} of the candidate {self.seats_word} are reachable "
                              f"within the joint limits, {o.orientations} are asked for; check the placement's at_m or "
                              "lower orientations")
        labels = np.array([f"{s}/{p}" for s, p in group])
        slots = None
        if self.contacts:
            slots = np.array([seat["spot"] for (_, seat), _ in info])
            for k in keys:
                lost = sorted(set(range(o.orientations)) - {slots[c] for c in range(len(group)) if group[c] == k})
                if lost:
                    elevation, azimuth = self.spots()[lost[0]]
                    raise PlanRefused(f"{cell.path} [kinematic_fixture]: ball {k[1]} of placement {k[0]}: its spot "
                                      f"{elevation:g} deg up, {azimuth:g} deg around cannot be touched: no tool "
                                      "orientation reaches it within the joint limits; check the placement's at_m, "
                                      "elevation_deg or max_tilt_deg")
        design = select_seats(model, q_all, labels, o.orientations, target_offset=tool.tcp_pose[:3] * 1e3,
                              normals=np.array(normals, dtype=float) if self.contacts else None, slots=slots)
        plan: dict = {k: [] for k in keys}
        for c in design.chosen:
            (rot, seat), branch = info[c]
            plan[group[c]].append((rot, {**seat, "wrist": branch}, q_all[c]))
        for k, seats in plan.items():
            seats[:] = _short_round(seats)
            for n, (_, seat, _) in enumerate(seats):
                seat["seat"] = n + 1
        return SeatPlan(plan, design.log_det)

    def steps(self) -> list[tuple[Move, dict | None]]:
        """Every move, placement by placement (each from home back home), with what each search records."""
        cell, o = self.cell, self.options
        model = load_robot(cell.robot)
        accel, joint_accel = cell.limits["tcp_accel_m_s2"], cell.limits["joint_accel_rad_s2"]
        speed = cell.limits["tcp_speed_m_s"]
        joint_speed = min(JOINT_SPEED_RAD_S, cell.limits["joint_speed_rad_s"])
        plan = self.seat_plan.seats
        steps: list[tuple[Move, dict | None]] = []
        for setup in o.placed.placements:
            q_from = np.asarray(cell.home_q_rad, dtype=float)  # each placement starts at home
            if self.contacts:
                for point in o.placed.fixture.points:
                    q_from = self._contact_steps(steps, setup, point, model, (speed, accel, joint_speed, joint_accel),
                                                 q_from)
            else:
                # every socket on the usual wrist, then (via home, once per placement) on the flipped one
                # in the reverse order: the fewest long moves
                points = list(o.placed.fixture.points)
                on_wrist = None  # the wrist the arm has been seating on at this placement
                for b, wrist in enumerate(WRISTS):
                    for point in points if b == 0 else points[::-1]:
                        seats = [seat for seat in plan[(setup.name, point)] if seat[1]["wrist"] == wrist]
                        if seats:
                            self._socket_steps(steps, setup, point, seats, model, on_wrist not in (None, wrist),
                                               (speed, accel, joint_speed, joint_accel))
                            on_wrist = wrist
            # home between placements: a straight joint path from one to the next may leave the box
            steps.append((Move.joint(f"home after placement {setup.name}", cell.home_q_rad, joint_speed,
                                     joint_accel), None))
        return steps

    def _socket_steps(self, steps, setup, point, seats, model, via_home: bool, speeds) -> None:
        """The moves of one socket's seats on one wrist branch: above the first seat by a joint move (via
        home first when the wrist changes: a flip next to the plate may hit it), each seat's approach,
        compliant search and retract, a turn between seats by a straight move where the arm stays on its
        branch (else lift and come in from above again), and a lift at the end."""
        cell, o = self.cell, self.options
        tool, r = cell.tool, cell.tool.radius_m
        speed, accel, joint_speed, joint_accel = speeds
        approach = o.approach_mm / 1e3
        where = f"socket {point} of placement {setup.name}"
        centre = setup.point_m(o.placed.layout_mm[point]) + [0.0, 0.0, r]  # the drawn tip's rounding at rest
        state = None  # the joints the plan has the arm at (as the guard follows it)
        for i, (rotation, seat, q_rest) in enumerate(seats):
            axis = rotation[:, 2]
            at = np.concatenate([centre + r * axis - approach * axis, se3.matrix_to_rotvec(rotation)])
            q_at = None if state is None else inverse(model, at, state, tool.tcp_pose)
            if q_at is None or np.sign(np.sin(q_at[4])) != np.sign(np.sin(q_rest[4])):
                # from above: the first seat, or a turn a straight move cannot make
                if i > 0:
                    self._lift(steps, where, seats[i - 1][0], speed, accel)
                elif via_home:
                    steps.append((Move.joint(f"home before the {seat['wrist']} wrist at placement {setup.name}",
                                             cell.home_q_rad, joint_speed, joint_accel), None))
                above = at.copy()
                above[:3] -= LIFT_MM / 1e3 * axis
                q = inverse(model, above, q_rest, tool.tcp_pose)
                if q is None:
                    raise PlanRefused(f"{cell.path} [kinematic_fixture]: move 'above {where}': the pose "
                                      f"{np.round(above[:3], 4).tolist()} m cannot be reached from home; "
                                      "check the placement's at_m")
                steps.append((Move.joint(f"above {where} seat {seat['seat']}", q, joint_speed, joint_accel), None))
                q_at = inverse(model, at, q, tool.tcp_pose)
            state = q_at
            label = f"{where} seat {seat['seat']}"
            steps.append((Move.linear(f"approach {label}", at, speed, accel), None))
            steps.append((Move.contact(label, axis, o.search_speed_mm_s / 1e3, 2 * approach),
                          {**seat, "setup": setup.name, "point": point}))
            steps.append((Move.linear(f"retract {label}", at, speed, accel), None))
        self._lift(steps, where, seats[-1][0], speed, accel)

    def _contact_steps(self, steps, setup, point, model, speeds, q_from) -> np.ndarray:
        """The moves of one ball's contacts, wrist branch by branch: for each, the tip's rounding to
        LIFT_MM over the ball in the contact's orientation (a turn there by a straight move when it stays
        on its wrist, else a joint move; a change of wrist via home), down a straight line to
        `approach_mm` off the spot along its normal (clear of the ball: ``spots``), the contact search
        toward the ball's centre, back along the normal and up over the ball again. A joint move whose
        tip (on the nominal arm) would pass nearer a ball of the placement than CLEARANCE_MM refuses the
        plan. q_from: the joints the arm is at before; returns those it ends at."""
        cell, o = self.cell, self.options
        tool, r = cell.tool, cell.tool.radius_m
        speed, accel, joint_speed, joint_accel = speeds
        where = f"ball {point} of placement {setup.name}"
        centre = setup.point_m(o.placed.layout_mm[point])
        contact_m, approach = o.placed.fixture.stylus_radius_mm / 1e3, o.approach_mm / 1e3
        seats = self.seat_plan.seats[(setup.name, point)]
        balls = np.array([setup.point_m(o.placed.layout_mm[p]) for p in o.placed.fixture.points])

        def joint_move(label, q_to):
            clear = _joint_path_clearance(model, q_from, q_to, tool.tcp_pose, r, balls) - contact_m
            if clear < CLEARANCE_MM / 1e3:
                raise PlanRefused(f"{cell.path} [kinematic_fixture]: move '{label}': a joint move that would pass "
                                  f"{clear * 1e3:.1f} mm from a ball of placement {setup.name}; check the placement's "
                                  "at_m and layout_mm, or set wrist_flip: false")
            steps.append((Move.joint(label, q_to, joint_speed, joint_accel), None))

        state = None
        for i, (rotation, seat, q_rest) in enumerate(seats):
            axis, n = rotation[:, 2], seat["normal"]
            rotvec = se3.matrix_to_rotvec(rotation)
            above = np.concatenate([centre + [0.0, 0.0, contact_m + LIFT_MM / 1e3] + r * axis, rotvec])
            start = np.concatenate([centre + (contact_m + approach) * n + r * axis, rotvec])
            first_of_branch = i == 0 or seats[i - 1][1]["wrist"] != seat["wrist"]
            label = f"{where} contact {i + 1}"
            q_above = None if state is None or first_of_branch else inverse(model, above, state, tool.tcp_pose)
            limits = model.joint_limits
            if (q_above is not None and np.sign(np.sin(q_above[4])) == np.sign(np.sin(q_rest[4]))
                    and (limits is None or np.all((q_above >= limits[:, 0]) & (q_above <= limits[:, 1])))):
                steps.append((Move.linear(f"over {label}", above, speed, accel), None))
            else:
                if first_of_branch and i > 0:  # a wrist flip next to the plate may hit it: via home
                    joint_move(f"home before the {seat['wrist']} wrist at {where}", np.asarray(cell.home_q_rad, float))
                    q_from = np.asarray(cell.home_q_rad, dtype=float)
                q_above = inverse(model, above, q_rest, tool.tcp_pose)
                if q_above is None:
                    raise PlanRefused(f"{cell.path} [kinematic_fixture]: move 'over {label}': the pose "
                                      f"{np.round(above[:3], 4).tolist()} m cannot be reached; check the placement's at_m")
                joint_move(f"over {label}", q_above)
            state = q_from = q_above
            steps.append((Move.linear(f"approach {label}", start, speed, accel), None))
            steps.append((Move.contact(label, -n, o.search_speed_mm_s / 1e3, 2 * approach),
                          {**seat, "setup": setup.name, "point": point}))
            steps.append((Move.linear(f"retract {label}", start, speed, accel), None))
            steps.append((Move.linear(f"lift from {label}", above, speed, accel), None))
        return q_from

    @staticmethod
    def _lift(steps, where, rotation, speed, accel) -> None:
        lift = steps[-1][0].pose.copy()
        lift[:3] -= LIFT_MM / 1e3 * rotation[:, 2]
        steps.append((Move.linear(f"lift from {where}", lift, speed, accel), None))


def _reach(model, pose, home_q, tool_pose):
    """Joints for a pose from home, or from home turned at the base toward the pose (a far pose
    the damped solver does not reach from straight home); None when neither converges."""
    q = inverse(model, pose, home_q, tool_pose)
    if q is None:
        home_tcp = tcp_frames(model, home_q, tool_pose)[1][0]
        turned = np.array(home_q, dtype=float)
        turned[0] += np.arctan2(pose[1], pose[0]) - np.arctan2(home_tcp[1], home_tcp[0])
        q = inverse(model, pose, turned, tool_pose, max_iter=200)
    return q


def _short_round(seats: list) -> list:
    """The seats of one socket, wrist branch by branch (the normal wrist first), each branch from its
    most upright seat on to the nearest in joint space: small turns between neighbouring seats."""
    out = []
    for branch in WRISTS:
        left = [s for s in seats if s[1]["wrist"] == branch]
        if not left:
            continue
        here = min(range(len(left)), key=lambda i: left[i][1]["tilt_deg"])
        while left:
            seat = left.pop(here)
            out.append(seat)
            if left:
                here = min(range(len(left)), key=lambda i: float(np.abs(left[i][2] - seat[2]).max()))
    return out


def _joint_path_clearance(model, q0, q1, tool_pose, tip_radius_m, centres, samples: int = 24) -> float:
    """Smallest distance (m) of the nominal tip's rounding centre from any of `centres` along the joint move
    q0 -> q1 (straight in joint space, as a joint move goes)."""
    qs = np.asarray(q0, dtype=float) + np.linspace(0.0, 1.0, samples)[:, None] * (np.asarray(q1) - np.asarray(q0))
    rot, tcp = tcp_frames(model, qs, tool_pose)
    tips = tcp - tip_radius_m * rot[:, :, 2]
    return float(np.linalg.norm(tips[:, None, :] - np.asarray(centres)[None], axis=2).min())


def _segment_clearance(a, b) -> float:
    """Smallest distance of the origin (a ball's centre) from the segment a-b."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    t = float(np.clip(-a @ (b - a) / max((b - a) @ (b - a), 1e-30), 0.0, 1.0))
    return float(np.linalg.norm(a + t * (b - a)))
