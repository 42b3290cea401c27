"""``kinematic-fixture``: the arm's geometry from seating the tool in a fixture's sockets (or touching its balls), no tracker.

A plate with two or more sockets at known distances (the fixture of ``cellcal identify
--fixture``, config/fixture_files.py) lies in the cell at the placements the cell file lists
(several plates fixed in the cell, or one plate's placements the arm reaches without moving
it: each placement is a setup of its own). For each placement, each socket, the tool seats
in the socket from N orientations, as ``tcp-npoint`` seats it in the pivot: a linear move to
`approach_mm` back along the tool axis from where the drawn tip would rest, a compliant
contact search along the axis that lets the socket's cone guide the tip to its seat (the
joints of that rest are recorded), and back. The orientations are chosen for identifiability
by a D-optimal seat design, on both wrist branches (``wrist_flip``), and the moves keep clear
of the plate: routines/fixture_seats.py. ``design()`` judges the plan before anything moves:
the condition of what the seats determine and the 1-sigma error they should leave over random
poses (fixture_predict.predict_seats). The whole plan is checked against the cell's limits
before anything moves.

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
spot the same design chooses the tool's tilt, turn and wrist (each ball's centre eliminated
exactly: one residual per contact, along the normal); a spot no candidate reaches refuses the
plan before anything moves, naming it. The simulated cells hold the balls
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
    wrist_flip: true                      # seats on the flipped wrist too (the arm goes home to flip; six-joint arms)
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
from cellcal.solvers.fixtures.fixture_identify import MIN_ROWS_PER_POINT, FixtureDataError, identify_points
from cellcal.solvers.fixtures.fixture_predict import judge_workspace, predict_seats
from cellcal.solvers.fixtures.point_problem import FixtureOptions, PointData
from cellcal.routines.fixture_seats import SeatPlanner
from cellcal.routines.framework import gates
from cellcal.routines.framework.base import Devices, Move, Parameter, PlanPromise, Result, RoutineError
from cellcal.routines.framework.steps import StepRoutine

MAX_TILT_DEG = 45.0  # beyond, the shank meets a 90 deg socket's rim
DESIGN_EVAL_POSES = 200  # random joint configurations the plan's expected error is judged at
MOVE_BY = ("fixed", "operator")  # the placements: plates fixed in the cell, or one plate the operator moves
CONFIRM_TIMEOUT_S = 300.0  # how long the run waits for the operator to move the plate and confirm
MAX_CONFIRM_TIMEOUT_S = 3600.0
TARGET = "tip"  # the target column: the centre of the tool tip's rounding, what a socket holds
MIN_CONTACTS_PER_BALL = 6  # three contacts only place a ball's centre; the rest see the arm
ELEVATION_DEG = (30.0, 80.0)  # the spots' elevations on the ball, from its equator


def _wrist_flip(section, cell) -> bool:
    """Seats on both wrist branches: a six-joint arm's (its wrist turned over: joints 4 and 6 by a half
    turn, joint 5 mirrored), the default there; an arm with another number of joints has no such pair
    of branches, and the option is refused for it (default off)."""
    six = load_robot(cell.robot).n_joints == 6
    flip = section.flag("wrist_flip", six)
    if flip and not six:
        section.fail("wrist_flip", f"the wrist branches are a six-joint arm's; {cell.robot} has "
                                   f"{load_robot(cell.robot).n_joints} joints: leave wrist_flip out")
    return flip


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
            _wrist_flip(section, cell),
            **_moved_by(section), **_contact_options(section, cell, placed.fixture))
        section.done()
        return options

    # -- plan ------------------------------------------------------------------------

    @functools.cached_property
    def planner(self) -> SeatPlanner:
        """The seats of this cell file's section and the moves to them (routines/fixture_seats.py)."""
        return SeatPlanner(self.cell, self.options)

    def steps(self) -> list[tuple[Move, dict | None]]:
        return self.planner.steps()

    def design(self) -> PlanPromise:
        """The planned seats judged before anything moves: the condition of what they determine and
        the 1-sigma error they should leave on the arm's target over random joint configurations,
        at the stated repeatability and the fixture's distances (solvers.fixtures.fixture_predict.predict_seats)."""
        o = self.options
        model = load_robot(self.cell.robot)
        chosen = self.planner.seat_plan
        plan = chosen.seats
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
                       "log_det": chosen.log_det, "evaluated_at_poses": DESIGN_EVAL_POSES})

    def check_design(self) -> PlanPromise:
        return self.design()

    # -- measure ---------------------------------------------------------------------

    def announce(self, design: PlanPromise) -> str:
        o, what = self.options, self.planner.what
        n = len(o.placed.placements) * len(o.placed.fixture.points) * o.orientations
        return (f"kinematic-fixture: {n} {self.planner.seats_word}, {o.orientations} per {what} "
                f"({len(o.placed.fixture.points)} {what}s) "
                f"at {len(o.placed.placements)} placements, chosen for identifiability (tilts up to "
                f"{o.max_tilt_deg:g} deg, wrist {' and '.join(design.details['wrist_branches'])}): condition "
                f"{design.condition:.3g}, expected error {design.expected_error:.3f} mm (1 sigma) over the workspace "
                f"at {o.repeatability_mm:g} mm repeatability")

    def run_steps(self, devices: Devices, robot, plan: list[Move], steps, progress) -> tuple[list[dict], float]:
        contacts = self.planner.contacts

        def missed(move):
            along = "toward the ball's centre" if contacts else "along the tool axis"
            return (f"the contact search {along} went {move.travel_m * 1e3:g} mm without touching the "
                    f"{self.planner.what}: are the placement's at_m and the plate's layout_mm in [kinematic_fixture] "
                    "right, and the plate there?")

        def record(seat, q):
            spot = ({"elevation_deg": seat["elevation_deg"], "spot_azimuth_deg": seat["spot_azimuth_deg"]}
                    if contacts else {})
            return {"setup": seat["setup"], "point": seat["point"], "target": TARGET,
                    **{f"q{j + 1}_rad": v for j, v in enumerate(q)},
                    "seat": seat["seat"], "tilt_deg": seat["tilt_deg"], "azimuth_deg": seat["azimuth_deg"],
                    "turn_deg": seat["turn_deg"], "wrist_flipped": float(seat["wrist"] == "flipped"), **spot}

        rows, cycle_s = self._placement_by_placement(devices, robot, plan, steps, missed, record, progress)
        progress(f"kinematic-fixture: {len(rows)} {self.planner.seats_word} recorded")
        return rows, cycle_s

    def dataset_meta(self, design: PlanPromise, before: dict) -> dict:
        o = self.options
        return {"tool_radius_m": self.cell.tool.radius_m, "orientations": o.orientations,
                "max_tilt_deg": o.max_tilt_deg, "turn_deg": o.turn_deg, "repeatability_mm": o.repeatability_mm,
                "placements": len(o.placed.placements), "fixture": o.placed.fixture.path,
                "wrist_flip": o.wrist_flip, "design_condition": design.condition,
                "design_expected_error_mm": design.expected_error}

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

