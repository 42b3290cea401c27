"""``kinematic-fixture``: the arm's geometry from seating the tool in a fixture's sockets (or touching its balls), no tracker.

A plate with two or more sockets at known distances (the fixture of ``cellcal identify
--fixture``, config/fixture_files.py) lies in the cell at the placements the cell file lists
(several plates fixed in the cell, or one plate's placements the arm reaches without moving
it: each placement is a setup of its own). For each placement, each socket, the tool seats
in the socket from N orientations, as ``tcp-npoint`` seats it in the pivot: a linear move to
`approach_mm` back along the tool axis from where the drawn tip would rest, a compliant
contact search along the axis that lets the socket's cone guide the tip to its seat (the
joints of that rest are recorded), and back. The orientations are chosen for identifiability,
as the tracker routine chooses its poses: the candidates are tilts of 0, 1/3, 2/3 and all of
`max_tilt_deg` at azimuths every 30 deg, turned 0 and +-`turn_deg` about the tool axis, on
the usual wrist and (``wrist_flip``) the flipped one, each kept where the nominal arm reaches
it within the joint limits, clear of singularities and with a way in from above on the same
branch; of those the D-optimal seat design (solvers/fixtures/fixture_design.py: each socket's
position eliminated) takes `orientations` per socket for all sockets together. A socket's
seats go wrist branch by wrist branch, from the most upright on to the nearest in joint
space; a change of wrist goes via home, a turn a straight move cannot make via the seat's
way in from above. ``design()`` judges the plan before anything moves: the condition of
what the seats determine and the 1-sigma error they should leave over random poses
(fixture_identify.predict_seats). The whole plan is checked against the cell's limits before anything moves.

The dataset is the measurement CSV's point form (docs/measurements.md, "Point form": the
joints, ``setup``, ``point``, ``target``), so ``cellcal identify --data DATASET --fixture
FIXTURE.yaml`` gives the same result offline. The solve is
:func:`cellcal.solvers.fixtures.fixture_identify.identify_points`: the kinematic parameters the data
determine, each placement's sockets, the target offset (the tip's rounding centre); what
fixture data cannot tie to the world (the base frame, the parameters it absorbs) is held
at nominal and reported as a convention. The routine writes no tool frame.

The placements are plates fixed in the cell (``move_by: fixed``, the default) or one plate
the operator moves between them (``move_by: operator``): before each placement's seats, with
the arm at home (where the run starts, and where each placement's moves end), the routine
asks the operator (``Devices.operator``: the daemon's panel, its waiting lamp, placement
register and confirm button; ``cellcal run``'s terminal) to move the plate there and waits
for the confirm, at most ``confirm_timeout_s`` (then OperatorTimeout: the run ends, nothing
written); an abort during the wait ends the run as aborted. The waits are no motion time.
Both simulated cells (in process, and the fake controller of ``sim-net``) seat the tool in
the plate's sockets and move the plate to where a placement really lies when the confirm is
pressed for it.

A stylus plate (the fixture's ``stylus_radius_mm``, the distance the tip's rounding centre keeps
from a ball's centre when touching it: the ball's radius plus the tip's) has balls, centred at the
layout's points (the placement's ``at_m`` height is the balls' centres'), instead of sockets. The
tip touches each ball once at each of `orientations` spots (at least 6: three only place the
centre) spread round its upper half (azimuths evenly round, elevations in turn the low, middle and
high of ``elevation_deg``, so that the contacts place the ball's centre in all three directions;
the same spot touched again and again would leave its centre to the ball's curvature, see
solvers/fixtures/fixture_design.py), one contact: the tip's rounding LIFT_MM over the ball in the
contact's orientation, a straight move down to `approach_mm` off the spot along its normal (clear of
the ball on the way), a contact search toward the ball's centre that stops at the touch (no
settling: the joints there are recorded), back out along the normal and up over the ball. At each
spot the design chooses the tool's tilt (up to `max_tilt_deg`, every 60 deg round), turn and wrist
among those that point the tool into the ball (within 70 deg of the contact's direction: the tip,
not the shank, touches) and reach it on one wrist branch, by the same D-optimal design with each
ball's centre eliminated exactly (one residual per contact, along the normal). A spot no candidate
reaches refuses the plan before anything moves, naming it. The simulated cells hold the balls
where the truth placed them (off their drawing as the sockets are, their radius as drawn) and stop
a search where the real tip's rounding meets one.

Section ``kinematic_fixture`` of the cell file::

    fixture: plate.yaml                   # or inline: {points: [...], distances_mm: [...], seating_sd_mm: ...,
                                          #   stylus_radius_mm: ... for balls}
    layout_mm: {s0: [0, 0], s1: [50, 0]}  # each point on the plate as drawn (plate frame, z up), mm
    placements:                           # the setups: the plate's origin (base frame, m) and its yaw
      - {name: p1, at_m: [-0.7, 0.3, 0.3], yaw_deg: 0}
    orientations: 8                       # seats per socket (contacts per ball: 6..24) and placement, 4..24
    max_tilt_deg: 40                      # largest tilt of the tool from the vertical the design may choose
    turn_deg: 60                          # turn about the tool axis the design may choose, + and -
    wrist_flip: true                      # seats on the flipped wrist too (the arm goes home to flip)
    approach_mm: 5                        # where each search starts, back along the axis (a ball: its normal)
    search_speed_mm_s: 10
    repeatability_mm: 0.03                # the arm's stated repeatability
    move_by: fixed                        # or operator: one plate, moved by hand between the placements
    confirm_timeout_s: 300                # with move_by: operator, how long each wait for the confirm lasts
    elevation_deg: [30, 80]               # a stylus plate only: the lowest and highest spot on each ball, deg up
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.fixture_files import CellFixture, cell_fixture
from cellcal.config.reader import Section
from cellcal.config.robot_files import load_robot
from cellcal.solvers.geometry import se3
from cellcal.solvers.fixtures.fixture_identify import MIN_ROWS_PER_POINT, FixtureDataError, identify_points
from cellcal.solvers.fixtures.fixture_predict import judge_workspace, predict_seats
from cellcal.solvers.fixtures.point_problem import FixtureOptions, PointData
from cellcal.solvers.fixtures.fixture_design import select_seats
from cellcal.solvers.geometry.inverse import dexterity, inverse, inverse_many, tcp_frames
from cellcal.routines.framework import gates
from cellcal.routines.framework.base import PlanPromise, Move, Parameter, PlanRefused, Result, RoutineError, StepRoutine, drawn_tool
from cellcal.routines.framework.records import Dataset
from cellcal.routines.tcp_npoint import down_orientation

LIFT_MM = 40.0  # above each socket's first approach and after its last, clear of the plate
JOINT_SPEED_RAD_S = 1.0
MAX_TILT_DEG = 45.0  # beyond, the shank meets a 90 deg socket's rim
CANDIDATE_AZIMUTH_STEP_DEG = 30.0  # the seat design chooses among tilts at azimuths this far apart
WRISTS = ("normal", "flipped")  # the wrist branches, in the order a placement's seats take them
MIN_DEXTERITY = 0.08  # seats nearer a singularity are not offered (half of a UR's home pose, 0.16)
DESIGN_EVAL_POSES = 200  # random joint configurations the plan's expected error is judged at
MOVE_BY = ("fixed", "operator")  # the placements: plates fixed in the cell, or one plate the operator moves
CONFIRM_TIMEOUT_S = 300.0  # how long the run waits for the operator to move the plate and confirm
MAX_CONFIRM_TIMEOUT_S = 3600.0
TARGET = "tip"  # the target column: the centre of the tool tip's rounding, what a socket holds
CONTACT_AZIMUTH_STEP_DEG = 60.0  # and the tool's tilts at each, at azimuths this far apart (fewer than a socket's)
MAX_CONTACT_ANGLE_DEG = 70.0  # the tool axis at most this far from the contact's direction: the tip touches first
CLEARANCE_MM = 1.0  # the way in from above passes the ball (with the tip's rounding) at least this far off
MIN_CONTACTS_PER_BALL = 6  # three contacts only place a ball's centre; the rest see the arm
ELEVATION_DEG = (30.0, 80.0)  # the spots' elevations on the ball, from its equator


@dataclass(frozen=True)
class KinematicFixtureOptions:
    placed: CellFixture
    orientations: int
    max_tilt_deg: float
    turn_deg: float
    approach_mm: float
    search_speed_mm_s: float
    repeatability_mm: float
    wrist_flip: bool = True  # seats on both wrist branches (a joint move home between them)
    move_by: str = "fixed"  # "operator": one plate, moved between placements and confirmed on the panel
    confirm_timeout_s: float = CONFIRM_TIMEOUT_S
    elevation_deg: tuple[float, float] = ELEVATION_DEG  # a stylus plate: the spots' elevations on each ball


class KinematicFixture(StepRoutine):
    name = "kinematic-fixture"
    section = "kinematic_fixture"
    selector = 8
    needs = ("robot",)
    text_columns = ("setup", "point", "target")

    @classmethod
    def read_options(cls, section: Section, cell: Cell) -> KinematicFixtureOptions:
        if cell.tool is None:
            section.fail(None, "kinematic-fixture needs the tool as drawn in [tool]")
        travel_mm = cell.limits["contact_travel_m"] * 1e3
        placed = cell_fixture(section, str(cell.path) if cell.path else None)
        options = KinematicFixtureOptions(
            placed,
            section.integer("orientations", 8, low=max(4, MIN_ROWS_PER_POINT), high=24),
            section.number("max_tilt_deg", 40.0, above=0.0, high=MAX_TILT_DEG),
            section.number("turn_deg", 60.0, low=0.0, high=90.0),
            section.number("approach_mm", 5.0, low=2.0, high=travel_mm / 2),
            section.number("search_speed_mm_s", 10.0, above=0.0, high=min(cell.limits["tcp_speed_m_s"] * 1e3, 20.0)),
            section.number("repeatability_mm", 0.03, above=0.0, high=1.0),
            section.flag("wrist_flip", True),
            **_moved_by(section), **_contact_options(section, cell, placed.fixture))
        section.done()
        return options

    # -- plan ------------------------------------------------------------------------

    @property
    def contacts(self) -> bool:
        """A stylus plate (the fixture's stylus_radius_mm): balls the tip touches, not sockets it seats in."""
        return self.options.placed.fixture.stylus_radius_mm is not None

    @property
    def _what(self) -> str:
        return "ball" if self.contacts else "socket"

    @property
    def _seats(self) -> str:
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

    def _candidate_poses(self, setup, point):
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
    def seat_plan(self) -> dict:
        """(placement name, point) -> the chosen seats [(rotation, seat info, joints at rest)], wrist
        branch by branch: `orientations` of each socket's reachable candidates (either wrist branch
        when `wrist_flip`), chosen together for every socket by the D-optimal seat design
        (solvers/fixtures/fixture_design.py) on the nominal model. A stylus plate: one contact at each spot of a
        ball (``spots``), the tool's orientation and wrist there chosen by the same design."""
        cell, o = self.cell, self.options
        model = load_robot(cell.robot)
        tool = cell.tool
        limits = model.joint_limits
        q_all, group, info, normals = [], [], [], []
        for setup in o.placed.placements:
            for point in o.placed.fixture.points:
                where = f"{self._what} {point} of placement {setup.name}"
                candidates, rest, way_in, normal, above = self._candidate_poses(setup, point)
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
            raise PlanRefused(f"{cell.path} [kinematic_fixture]: {self._what} {short[0][1]} of placement {short[0][0]}: "
                              f"only {sum(g == short[0] for g in group)} of the candidate {self._seats} are reachable "
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
        self._design_log_det = design.log_det
        return plan

    def design(self) -> PlanPromise:
        """The planned seats judged before anything moves: the condition of what they determine and
        the 1-sigma error they should leave on the arm's target over random joint configurations,
        at the stated repeatability and the fixture's distances (solvers.fixtures.fixture_identify.predict_seats)."""
        o = self.options
        model = load_robot(self.cell.robot)
        plan = self.seat_plan
        keys = list(plan)
        q = np.array([s[2] for k in keys for s in plan[k]])
        point = np.array([i for i, k in enumerate(keys) for _ in plan[k]])
        distances = tuple((keys.index((s, d.a)), keys.index((s, d.b)), d.mm, d.sd_mm)
                          for s in dict.fromkeys(k[0] for k in keys) for d in o.placed.fixture.distances
                          if (s, d.a) in keys and (s, d.b) in keys)
        data = PointData(q, np.zeros(len(q), int), (TARGET,), point, tuple(keys), np.full((len(q), 3), np.nan),
                         distances)
        limits = model.joint_limits if model.joint_limits is not None else np.tile([-np.pi, np.pi], (model.n_joints, 1))
        rng = np.random.default_rng(0)  # the same poses for every judgement of a plan
        q_eval = rng.uniform(np.maximum(limits[:, 0], -np.pi), np.minimum(limits[:, 1], np.pi),
                             (DESIGN_EVAL_POSES, model.n_joints))
        fit_options = FixtureOptions(seating_sd_mm=max(o.placed.fixture.seating_sd_mm, o.repeatability_mm),
                                     stylus_radius_mm=o.placed.fixture.stylus_radius_mm)
        predicted = predict_seats(model, data, fit_options, q_eval, o.repeatability_mm)
        branches = sorted({s[1]["wrist"] for k in keys for s in plan[k]})
        return PlanPromise(predicted.condition, predicted.mean_error_mm, "mm",
                      {"seats": len(q), "placements": len(o.placed.placements), "points": len(o.placed.fixture.points),
                       "rank": predicted.rank, "wrist_branches": branches,
                       "log_det": self._design_log_det, "evaluated_at_poses": DESIGN_EVAL_POSES})

    def check_design(self) -> PlanPromise:
        return self.design()

    def steps(self) -> list[tuple[Move, dict | None]]:
        cell, o = self.cell, self.options
        model = load_robot(cell.robot)
        accel, joint_accel = cell.limits["tcp_accel_m_s2"], cell.limits["joint_accel_rad_s2"]
        speed = cell.limits["tcp_speed_m_s"]
        joint_speed = min(JOINT_SPEED_RAD_S, cell.limits["joint_speed_rad_s"])
        plan = self.seat_plan
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
        seats = self.seat_plan[(setup.name, point)]
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

    # -- measure ---------------------------------------------------------------------

    def measure(self, devices, robot, plan: list[Move], progress) -> Dataset:
        steps = self.steps_of(plan)
        o = self.options
        n = len(o.placed.placements) * len(o.placed.fixture.points) * o.orientations
        design = self.check_design()
        progress(f"kinematic-fixture: {n} {self._seats}, {o.orientations} per {self._what} "
                 f"({len(o.placed.fixture.points)} {self._what}s) "
                 f"at {len(o.placed.placements)} placements, chosen for identifiability (tilts up to "
                 f"{o.max_tilt_deg:g} deg, wrist {' and '.join(design.details['wrist_branches'])}): condition "
                 f"{design.condition:.3g}, expected error {design.expected_error:.3f} mm (1 sigma) over the workspace "
                 f"at {o.repeatability_mm:g} mm repeatability")

        def missed(move):
            along = "toward the ball's centre" if self.contacts else "along the tool axis"
            return (f"the contact search {along} went {move.travel_m * 1e3:g} mm without touching the "
                    f"{self._what}: are the placement's at_m and the plate's layout_mm in [kinematic_fixture] right, "
                    "and the plate there?")

        def record(seat, q):
            spot = ({"elevation_deg": seat["elevation_deg"], "spot_azimuth_deg": seat["spot_azimuth_deg"]}
                    if self.contacts else {})
            return {"setup": seat["setup"], "point": seat["point"], "target": TARGET,
                    **{f"q{j + 1}_rad": v for j, v in enumerate(q)},
                    "seat": seat["seat"], "tilt_deg": seat["tilt_deg"], "azimuth_deg": seat["azimuth_deg"],
                    "turn_deg": seat["turn_deg"], "wrist_flipped": float(seat["wrist"] == "flipped"), **spot}

        with drawn_tool(robot, self.cell.tool.tcp_pose):
            rows, cycle_s = self._placement_by_placement(devices, robot, plan, steps, missed, record, progress)
        progress(f"kinematic-fixture: {len(rows)} {self._seats} recorded")
        meta = {"tool_radius_m": self.cell.tool.radius_m, "orientations": o.orientations,
                "max_tilt_deg": o.max_tilt_deg, "turn_deg": o.turn_deg, "repeatability_mm": o.repeatability_mm,
                "placements": len(o.placed.placements), "fixture": o.placed.fixture.path, "cycle_time_s": cycle_s,
                "wrist_flip": o.wrist_flip, "design_condition": design.condition,
                "design_expected_error_mm": design.expected_error}
        columns = {k: np.array([row[k] for row in rows], dtype=str if k in self.text_columns else float)
                   for k in rows[0]}
        return Dataset(self.name, columns, meta)

    def asks_operator(self) -> bool:
        return self.options.move_by == "operator"

    def _placement_by_placement(self, devices, robot, plan, steps, missed, record, progress):
        """The seats of each placement in turn (rows, motion time s). With ``move_by: operator``
        the arm is at home (where the run starts, and where each placement's moves end) while the
        operator moves the plate to the next placement and confirms; the wait is no motion time."""
        placements = self.options.placed.placements
        if not self.asks_operator():
            return self.contact_rows(robot, plan, steps, missed, record)
        chunks, first = [], 0
        for i, (move, _) in enumerate(steps):
            if len(chunks) < len(placements) and move.label == f"home after placement {placements[len(chunks)].name}":
                chunks.append((first, i + 1))
                first = i + 1
        if len(chunks) != len(placements) or first != len(steps):
            raise RoutineError("the plan does not end each placement at home: the plate cannot be moved safely")
        rows, cycle_s = [], 0.0
        for k, (setup, (a, b)) in enumerate(zip(placements, chunks)):
            x, y, z = setup.at_m
            message = (f"move the plate to placement {setup.name} ({k + 1} of {len(placements)}): its origin at "
                       f"x {x:.3f} y {y:.3f} z {z:.3f} m, turned {setup.yaw_deg:g} deg about the vertical, as "
                       "[kinematic_fixture] draws it; then press confirm")
            progress(f"kinematic-fixture: waiting for the operator: {message}")
            devices.operator.confirm(message, step=k + 1, timeout_s=self.options.confirm_timeout_s)
            progress(f"kinematic-fixture: placement {setup.name} confirmed")
            found, seconds = self.contact_rows(robot, plan[a:b], steps[a:b], missed, record)
            rows += found
            cycle_s += seconds
        return rows, cycle_s

    # -- solve -----------------------------------------------------------------------

    @classmethod
    def solve(cls, dataset, cell: Cell, options: KinematicFixtureOptions) -> Result:
        model = load_robot(cell.robot)
        names = [f"q{j + 1}_rad" for j in range(model.n_joints)]
        missing = [c for c in (*names, "setup", "point") if c not in dataset.columns]
        if missing:
            raise RoutineError(f"{dataset.path}: the dataset lacks the column(s) {', '.join(missing)}")
        fixture = options.placed.fixture
        setups, points = np.asarray(dataset["setup"], dtype=str), np.asarray(dataset["point"], dtype=str)
        unknown = sorted(set(points) - set(fixture.points))
        if unknown:
            raise RoutineError(f"{dataset.path}: point(s) {', '.join(unknown)} are not the fixture's "
                               f"({', '.join(fixture.points)})")
        keys = list(dict.fromkeys(zip(setups.tolist(), points.tolist())))
        index = {k: i for i, k in enumerate(keys)}
        distances = tuple((index[(s, d.a)], index[(s, d.b)], d.mm, d.sd_mm)
                          for s in dict.fromkeys(setups.tolist()) for d in fixture.distances
                          if (s, d.a) in index and (s, d.b) in index)
        data = PointData(dataset.stack(*names), np.zeros(len(dataset), int), (TARGET,),
                         np.array([index[k] for k in zip(setups.tolist(), points.tolist())]), tuple(keys),
                         np.full((len(dataset), 3), np.nan), distances)
        fit_options = FixtureOptions(seating_sd_mm=fixture.seating_sd_mm, stylus_radius_mm=fixture.stylus_radius_mm)
        try:
            found = identify_points(model, data, fit_options)
        except (FixtureDataError, ValueError) as exc:
            raise RoutineError(f"{dataset.path}: {exc}") from None
        return _result(cls.name, dataset, model, found, data, options)


def _moved_by(section: Section) -> dict:
    """``move_by`` (how the plate gets to each placement) and ``confirm_timeout_s`` (how long a run
    waits for the operator's confirm, with ``move_by: operator``)."""
    move_by = section.choice("move_by", MOVE_BY, "fixed")
    if move_by != "operator" and "confirm_timeout_s" in section:
        section.fail("confirm_timeout_s", "only with move_by: operator (fixed placements wait for nobody)")
    return {"move_by": move_by,
            "confirm_timeout_s": section.number("confirm_timeout_s", CONFIRM_TIMEOUT_S, above=0.0,
                                                high=MAX_CONFIRM_TIMEOUT_S)}


def _contact_options(section: Section, cell: Cell, fixture) -> dict:
    """``elevation_deg`` (a stylus plate only: [lowest, highest] elevation of the spots the tip touches,
    deg above each ball's equator), and the stylus radius checked against the tool's tip."""
    if fixture.stylus_radius_mm is None:
        if "elevation_deg" in section:
            section.fail("elevation_deg", "only with a stylus fixture (stylus_radius_mm): sockets have no spots")
        return {}
    if section.integer("orientations", 8) < MIN_CONTACTS_PER_BALL:
        section.fail("orientations", f"a stylus plate needs at least {MIN_CONTACTS_PER_BALL} contacts per ball (three only "
                                     "place its centre)")
    tip_mm = cell.tool.radius_m * 1e3
    if fixture.stylus_radius_mm <= tip_mm:
        section.fail("fixture", f"stylus_radius_mm {fixture.stylus_radius_mm:g} is where the tip's rounding centre "
                                f"touches (the ball's radius plus the tip's, {tip_mm:g} mm): it must exceed the tip's")
    raw = section.raw("elevation_deg") if "elevation_deg" in section else list(ELEVATION_DEG)
    ok = (isinstance(raw, list) and len(raw) == 2
          and all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in raw))
    if not ok or not 0.0 < raw[0] < raw[1] <= 90.0:
        section.fail("elevation_deg", f"expected [lowest, highest] elevation of the spots on the ball's upper half, "
                                      f"deg, 0 < lowest < highest <= 90, got {raw!r}")
    return {"elevation_deg": (float(raw[0]), float(raw[1]))}


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


def _result(name, dataset, model, found, data: PointData, options: KinematicFixtureOptions) -> Result:
    u = found.unknowns
    expected = float(np.sqrt(options.repeatability_mm**2 + options.placed.fixture.seating_sd_mm**2))
    rms = float(np.sqrt(np.mean(found.errors_mm**2)))
    worth = judge_workspace(model, found)
    gate_list = [gates.residual(rms, expected), gates.conditioning(found.condition)]
    params = []
    for i, (n, a) in enumerate(zip(model.param_names, model.param_is_angle)):
        sd = float(found.std[i]) if found.free[i] else None
        params.append(Parameter(n, float(np.rad2deg(found.z[i]) if a else found.z[i]),
                                (float(np.rad2deg(sd)) if a else sd) if sd is not None else None,
                                "deg" if a else "mm"))
    offset = found.offsets[0]
    std_offset = found.std[u.target(0)]
    params += [Parameter(f"target.{TARGET}.{c}", float(offset[j]), float(std_offset[j]), "mm")
               for j, c in enumerate("xyz")]
    contacts = options.placed.fixture.stylus_radius_mm is not None
    notes = [f"{len(data)} {'contacts' if contacts else 'seats'} at {len(data.points)} "
             f"{'balls' if contacts else 'sockets'} in {len({s for s, _ in data.points})} placements; "
             f"{found.noise_rank} of {int(model.n_params)} geometric parameters identified above the noise "
             f"({found.structural_rank} structurally)"]
    notes += [f"convention (held, never identified): {c}" for c in found.conventions]
    held = [n for n in found.held_at_nominal if n not in found.absorbed]
    if held:
        notes.append(f"held at nominal (below the noise of these seats; not a failure): {', '.join(held)}")
    notes.append(worth.describe())
    notes.append("no tool frame is written: the target offset found is the centre of the tip's rounding, "
                 "fitted with the arm; calibrate the tool with tcp-laser, tcp-npoint or tcf")
    extra = {"setups": len({s for s, _ in data.points}), "points": len(data.points), "seats": len(data),
             "calibration_mean_mm": float(found.errors_mm.mean()),
             "calibration_before_mean_mm": float(found.errors_nominal_mm.mean()),
             "distance_misfit_mm": found.distance_misfit_mm.tolist(),
             "structural_rank": found.structural_rank, "noise_rank": found.noise_rank,
             "held_at_nominal": list(found.held_at_nominal), "conventions": list(found.conventions),
             "kinematics": found.k.tolist(), "target_offset_mm": offset.tolist(), "identify_s": found.seconds,
             "workspace": {"expected_error_mm": worth.expected_error_mm, "correction_mm": worth.correction_mm,
                           "poses": worth.poses}}
    if "design_expected_error_mm" in dataset.meta:  # what the plan promised before anything moved
        extra["design"] = {"condition": float(dataset.meta["design_condition"]),
                           "expected_error_mm": float(dataset.meta["design_expected_error_mm"])}
    return Result(name, params, found.errors_mm, expected, found.condition, gate_list, notes=notes, extra=extra,
                  cycle_time_s=dataset.meta.get("cycle_time_s"))


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
