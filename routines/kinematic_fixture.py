"""``kinematic-fixture``: the arm's geometry from seating the tool in a fixture's sockets, no tracker.

A plate with two or more sockets at known distances (the fixture of ``cellcal identify
--fixture``, config/fixture_files.py) lies in the cell at the placements the cell file lists
(several plates fixed in the cell, or one plate's placements the arm reaches without moving
it: each placement is a setup of its own). For each placement, each socket, the tool seats
in the socket from N orientations, as ``tcp-npoint`` seats it in the pivot: a linear move to
`approach_mm` back along the tool axis from where the drawn tip would rest, a compliant
contact search along the axis that lets the socket's cone guide the tip to its seat (the
joints of that rest are recorded), and back. The orientations are a spread of tilts about
the socket (every other seat tilted `max_tilt_deg`, the others half of it, at azimuths
evenly round the vertical, turned +-`turn_deg` about the tool axis in turn), not the
D-optimal selection of the tracker routine: large tilts carry most of what the plate can
see of the arm. The whole plan is checked against the cell's limits before anything moves.

The dataset is the measurement CSV's point form (docs/measurements.md, "Point form": the
joints, ``setup``, ``point``, ``target``), so ``cellcal identify --data DATASET --fixture
FIXTURE.yaml`` gives the same result offline. The solve is
:func:`cellcal.solvers.fixture_identify.identify_points`: the kinematic parameters the data
determine, each placement's sockets, the target offset (the tip's rounding centre); what
fixture data cannot tie to the world (the base frame, the parameters it absorbs) is held
at nominal and reported as a convention. The routine writes no tool frame.

Not yet there: a plate the operator moves between setups (a confirm press on the panel),
stylus contacts instead of sockets, the networked simulated cell.

Section ``kinematic_fixture`` of the cell file::

    fixture: plate.yaml                   # or inline: {points: [...], distances_mm: [...], seating_sd_mm: ...}
    layout_mm: {s0: [0, 0], s1: [50, 0]}  # each point on the plate as drawn (plate frame, z up), mm
    placements:                           # the setups: the plate's origin (base frame, m) and its yaw
      - {name: p1, at_m: [-0.7, 0.3, 0.3], yaw_deg: 0}
    orientations: 8                       # seats per socket and placement, 4..24
    max_tilt_deg: 40                      # tilt of the tool from the vertical (every other seat half of it)
    turn_deg: 60                          # turn about the tool axis, + and - in turn
    approach_mm: 5                        # where each search starts, back along the axis
    search_speed_mm_s: 10
    repeatability_mm: 0.03                # the arm's stated repeatability
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.fixture_files import CellFixture, cell_fixture
from cellcal.config.reader import Section
from cellcal.config.robot_files import load_robot
from cellcal.solvers import se3
from cellcal.solvers.fixture_identify import (MIN_ROWS_PER_POINT, FixtureDataError, FixtureOptions, PointData,
                                              identify_points)
from cellcal.solvers.inverse import inverse
from cellcal.routines import gates
from cellcal.routines.base import Design, Move, Parameter, PlanRefused, Result, RoutineError, StepRoutine, drawn_tool
from cellcal.routines.records import Dataset
from cellcal.routines.tcp_npoint import down_orientation

LIFT_MM = 40.0  # above each socket's first approach and after its last, clear of the plate
JOINT_SPEED_RAD_S = 1.0
MAX_TILT_DEG = 45.0  # beyond, the shank meets a 90 deg socket's rim
TARGET = "tip"  # the target column: the centre of the tool tip's rounding, what a socket holds


@dataclass(frozen=True)
class KinematicFixtureOptions:
    placed: CellFixture
    orientations: int
    max_tilt_deg: float
    turn_deg: float
    approach_mm: float
    search_speed_mm_s: float
    repeatability_mm: float


class KinematicFixture(StepRoutine):
    name = "kinematic-fixture"
    section = "kinematic_fixture"
    selector = None
    needs = ("robot",)
    text_columns = ("setup", "point", "target")

    @classmethod
    def read_options(cls, section: Section, cell: Cell) -> KinematicFixtureOptions:
        if cell.tool is None:
            section.fail(None, "kinematic-fixture needs the tool as drawn in [tool]")
        travel_mm = cell.limits["contact_travel_m"] * 1e3
        options = KinematicFixtureOptions(
            cell_fixture(section, str(cell.path) if cell.path else None),
            section.integer("orientations", 8, low=max(4, MIN_ROWS_PER_POINT), high=24),
            section.number("max_tilt_deg", 40.0, above=0.0, high=MAX_TILT_DEG),
            section.number("turn_deg", 60.0, low=0.0, high=90.0),
            section.number("approach_mm", 5.0, low=2.0, high=travel_mm / 2),
            section.number("search_speed_mm_s", 10.0, above=0.0, high=min(cell.limits["tcp_speed_m_s"] * 1e3, 20.0)),
            section.number("repeatability_mm", 0.03, above=0.0, high=1.0))
        section.done()
        return options

    # -- plan ------------------------------------------------------------------------

    def orientations(self) -> list[tuple[np.ndarray, dict]]:
        """(tool frame rotation, what it is) of each seat in one socket."""
        o = self.options
        down = down_orientation(self.cell, load_robot(self.cell.robot))
        out = []
        for k in range(o.orientations):
            azimuth = 360.0 * k / o.orientations
            phi = np.deg2rad(azimuth)
            tilt_deg = o.max_tilt_deg if k % 2 == 0 else o.max_tilt_deg / 2.0
            tilt = se3.rotvec_to_matrix(np.deg2rad(tilt_deg) * np.array([np.cos(phi), np.sin(phi), 0.0]))
            turn = o.turn_deg * (1 if k % 2 == 0 else -1)
            out.append((tilt @ down @ se3.rot("z", np.deg2rad(turn)),
                        {"seat": k + 1, "tilt_deg": tilt_deg, "azimuth_deg": azimuth, "turn_deg": turn}))
        return out

    def design(self) -> Design:
        placed = self.options.placed
        n = len(placed.placements) * len(placed.fixture.points) * self.options.orientations
        return Design(float("nan"), float("nan"), "mm",
                      {"seats": n, "placements": len(placed.placements), "points": len(placed.fixture.points)})

    def check_design(self) -> Design:
        return self.design()

    def steps(self) -> list[tuple[Move, dict | None]]:
        cell, o = self.cell, self.options
        model = load_robot(cell.robot)
        tool = cell.tool
        r = tool.radius_m
        accel, joint_accel = cell.limits["tcp_accel_m_s2"], cell.limits["joint_accel_rad_s2"]
        speed = cell.limits["tcp_speed_m_s"]
        joint_speed = min(JOINT_SPEED_RAD_S, cell.limits["joint_speed_rad_s"])
        approach = o.approach_mm / 1e3
        seats = self.orientations()
        steps: list[tuple[Move, dict | None]] = []
        for setup in o.placed.placements:
            for point in o.placed.fixture.points:
                where = f"socket {point} of placement {setup.name}"
                centre = setup.point_m(o.placed.layout_mm[point]) + [0.0, 0.0, r]  # the drawn tip's rounding at rest
                for i, (rotation, seat) in enumerate(seats):
                    axis = rotation[:, 2]
                    at = np.concatenate([centre + r * axis - approach * axis, se3.matrix_to_rotvec(rotation)])
                    if i == 0:
                        above = at.copy()
                        above[:3] -= LIFT_MM / 1e3 * axis
                        q = inverse(model, above, cell.home_q_rad, tool.tcp_pose)
                        if q is None:
                            raise PlanRefused(f"{cell.path} [kinematic_fixture]: move 'above {where}': the pose "
                                              f"{np.round(above[:3], 4).tolist()} m cannot be reached from home; "
                                              "check the placement's at_m")
                        steps.append((Move.joint(f"above {where}", q, joint_speed, joint_accel), None))
                    label = f"{where} seat {i + 1}"
                    steps.append((Move.linear(f"approach {label}", at, speed, accel), None))
                    steps.append((Move.contact(label, axis, o.search_speed_mm_s / 1e3, 2 * approach),
                                  {**seat, "setup": setup.name, "point": point}))
                    steps.append((Move.linear(f"retract {label}", at, speed, accel), None))
                lift = steps[-1][0].pose.copy()
                lift[:3] -= LIFT_MM / 1e3 * seats[-1][0][:, 2]
                steps.append((Move.linear(f"lift from {where}", lift, speed, accel), None))
            # home between placements: a straight joint path from one to the next may leave the box
            steps.append((Move.joint(f"home after placement {setup.name}", cell.home_q_rad, joint_speed,
                                     joint_accel), None))
        return steps

    # -- measure ---------------------------------------------------------------------

    def measure(self, devices, robot, plan: list[Move], progress) -> Dataset:
        steps = self.steps_of(plan)
        o = self.options
        n = len(o.placed.placements) * len(o.placed.fixture.points) * o.orientations
        progress(f"kinematic-fixture: {n} seats, {o.orientations} per socket ({len(o.placed.fixture.points)} sockets) "
                 f"at {len(o.placed.placements)} placements, tilted {o.max_tilt_deg:g} and {o.max_tilt_deg / 2:g} deg")

        def missed(move):
            return (f"the contact search along the tool axis went {move.travel_m * 1e3:g} mm without touching the "
                    "socket: are the placement's at_m and the plate's layout_mm in [kinematic_fixture] right, and "
                    "the plate there?")

        def record(seat, q):
            return {"setup": seat["setup"], "point": seat["point"], "target": TARGET,
                    **{f"q{j + 1}_rad": v for j, v in enumerate(q)},
                    "seat": seat["seat"], "tilt_deg": seat["tilt_deg"], "azimuth_deg": seat["azimuth_deg"]}

        with drawn_tool(robot, self.cell.tool.tcp_pose):
            rows, cycle_s = self.contact_rows(robot, plan, steps, missed, record)
        progress(f"kinematic-fixture: {len(rows)} seats recorded")
        meta = {"tool_radius_m": self.cell.tool.radius_m, "orientations": o.orientations,
                "max_tilt_deg": o.max_tilt_deg, "turn_deg": o.turn_deg, "repeatability_mm": o.repeatability_mm,
                "placements": len(o.placed.placements), "fixture": o.placed.fixture.path, "cycle_time_s": cycle_s}
        columns = {k: np.array([row[k] for row in rows], dtype=str if k in self.text_columns else float)
                   for k in rows[0]}
        return Dataset(self.name, columns, meta)

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
        fit_options = FixtureOptions(seating_sd_mm=fixture.seating_sd_mm)
        try:
            found = identify_points(model, data, fit_options)
        except (FixtureDataError, ValueError) as exc:
            raise RoutineError(f"{dataset.path}: {exc}") from None
        return _result(cls.name, dataset, model, found, data, options)


def _result(name, dataset, model, found, data: PointData, options: KinematicFixtureOptions) -> Result:
    u = found.unknowns
    expected = float(np.sqrt(options.repeatability_mm**2 + options.placed.fixture.seating_sd_mm**2))
    rms = float(np.sqrt(np.mean(found.errors_mm**2)))
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
    notes = [f"{len(data)} seats at {len(data.points)} sockets in {len({s for s, _ in data.points})} placements; "
             f"{found.noise_rank} of {int(model.n_params)} geometric parameters identified above the noise "
             f"({found.structural_rank} structurally)"]
    notes += [f"convention (held, never identified): {c}" for c in found.conventions]
    held = [n for n in found.held_at_nominal if n not in found.absorbed]
    if held:
        notes.append(f"held at nominal (below the noise of these seats; not a failure): {', '.join(held)}")
    notes.append("no tool frame is written: the target offset found is the centre of the tip's rounding, "
                 "fitted with the arm; calibrate the tool with tcp-laser, tcp-npoint or tcf")
    extra = {"setups": len({s for s, _ in data.points}), "points": len(data.points), "seats": len(data),
             "calibration_mean_mm": float(found.errors_mm.mean()),
             "calibration_before_mean_mm": float(found.errors_nominal_mm.mean()),
             "distance_misfit_mm": found.distance_misfit_mm.tolist(),
             "structural_rank": found.structural_rank, "noise_rank": found.noise_rank,
             "held_at_nominal": list(found.held_at_nominal), "conventions": list(found.conventions),
             "kinematics": found.k.tolist(), "target_offset_mm": offset.tolist(), "identify_s": found.seconds}
    return Result(name, params, found.errors_mm, expected, found.condition, gate_list, notes=notes, extra=extra,
                  cycle_time_s=dataset.meta.get("cycle_time_s"))
