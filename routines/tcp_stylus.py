"""tcp-stylus: a cylindrical tool touched on a fixed stylus ball (after Chang et al. 2025).

Every contact is a guarded search, a back-off and a slow second touch whose joints are
recorded: the controller notices a contact at its next 2 ms cycle, so the touch overshoots
by at most ``touch_speed_m_s`` x 2 ms (4 um at 2 mm/s; the solver takes off the mean half).

1. Coarse, as Chang et al.'s section 2.2: end-face touches at four orientations (four-point TCP
   and stylus); side touches at two heights from three sides, the tool held in one
   orientation (the axis direction from axial moves).
2. Side contacts from ``stations`` orientations tilted up to ``tilt_deg``, each station on
   its own sector of the mantle, low and high along the axis; each station re-aimed by what
   the contacts so far say, so that its searches can start close.
3. End-face touches re-aimed onto the axis found: they fix the TCP along the axis, which no
   side contact can see.

Solving is one least-squares fit (:func:`cellcal.solvers.tool_frames.stylus.fit`) of the axis line (4),
the stylus (3), the contact radius (1) and the end's place along the axis (1). The routine
determines the tip and the axis; the turn of the tool frame about its axis is kept from the
controller's frame before the run (:mod:`.framework.tool_frame`), as is the TCP's place along the
axis when no end-face touch fixes it. On a
simulated cell ``sim_truth.position_error_mm`` is therefore the TCP's full 3-D error (its
place along the axis measured by the end-face touches; with ``face_touches: 0`` it would
hold the convention's error too) and ``axis_error_deg`` the angle between the axes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.reader import Section
from cellcal.config.robot_files import load_robot
from cellcal.solvers.geometry import se3
from cellcal.solvers.tool_frames import stylus as fitting
from cellcal.solvers.tool_frames import stylus_design as design
from cellcal.solvers.geometry.inverse import inverse, tcp_frames
from cellcal.routines.framework import gates, tool_frame
from cellcal.routines.framework.base import Gate, Move, Parameter, PlanRefused, Result, Routine, RoutineError, drawn_tool
from cellcal.routines.framework.drawing import contacts_on_cylinder
from cellcal.routines.framework.records import Dataset

SEARCH_MARGIN_MM = 5.0  # a search goes this far beyond where the contact is expected
MAX_OUTLIER_SHARE = 0.2
COLUMNS = ("probe", "group", "height_mm", "roll_deg", *(f"q{i}_rad" for i in range(1, 7)),
           "x_m", "y_m", "z_m", "rx", "ry", "rz", "dir_x", "dir_y", "dir_z", "speed_m_s")


@dataclass(frozen=True)
class TcpStylusOptions:
    side_contacts: int
    face_touches: int
    stations: int
    tilt_deg: float
    sides_deg: float
    heights_mm: tuple[float, float]
    clearance_mm: float
    coarse_clearance_mm: float
    retreat_mm: float
    search_speed_m_s: float
    touch_speed_m_s: float
    backoff_mm: float
    contact_noise_mm: float
    fit_radius: bool
    loss: str
    end_shape: str


@dataclass(frozen=True)
class Probe:
    """One contact as planned, on the drawn tool and the stylus where the cell file says."""

    kind: str  # coarse-face, axial, side, face
    station: int  # one orientation family, reached by one joint move
    group: int  # axial moves of one group share an orientation and a side
    height_mm: float  # of the contact along the axis from the tip (0: the end face)
    roll_deg: float
    clearance_mm: float  # where its search starts
    refit: bool  # estimate the tool from the contacts so far before this probe
    tcp: np.ndarray  # planned TCP pose at contact [m, rotation vector]
    approach: np.ndarray  # unit, base frame: the way the tool moves to touch


class TcpStylus(Routine):
    name = "tcp-stylus"
    section = "tcp_stylus"
    selector = 2
    needs = ("robot",)
    text_columns = ("kind",)

    def __init__(self, cell, options):
        super().__init__(cell, options)
        self.model = load_robot(cell.robot)

    @classmethod
    def read_options(cls, section: Section, cell: Cell) -> TcpStylusOptions:
        if cell.tool is None or cell.stylus is None:
            section.fail(None, "tcp-stylus needs the cell file's [tool] and [stylus]")
        travel_mm = cell.limits["contact_travel_m"] * 1e3 - SEARCH_MARGIN_MM
        length_mm, radius_mm = cell.tool.length_m * 1e3, cell.tool.radius_m * 1e3
        h = section.vector("heights_mm", 2, [max(2 * radius_mm + 2.0, 8.0), 0.9 * length_mm])
        if not radius_mm + 1.0 < h[0] < h[1] < length_mm - radius_mm:
            section.fail("heights_mm", f"{h.tolist()} must rise from above the tool's radius + 1 mm "
                                       f"({radius_mm + 1:g}) to below its length less its radius "
                                       f"({length_mm - radius_mm:g} mm)")
        if travel_mm <= 0:
            section.fail(None, f"the cell's contact_travel_m leaves no room for a {SEARCH_MARGIN_MM:g} mm search")
        opts = TcpStylusOptions(
            side_contacts=section.integer("side_contacts", 182, low=16, high=2000),
            face_touches=section.integer("face_touches", 8, low=0, high=100),
            stations=section.integer("stations", 8, low=4, high=40),
            tilt_deg=section.number("tilt_deg", 45.0, low=0.0, high=60.0),
            sides_deg=section.number("sides_deg", 45.0, low=0.0, high=90.0),
            heights_mm=(float(h[0]), float(h[1])),
            clearance_mm=section.number("clearance_mm", 1.0, above=0.0, high=travel_mm),
            coarse_clearance_mm=section.number("coarse_clearance_mm", 8.0, above=0.0, high=travel_mm),
            retreat_mm=section.number("retreat_mm", 30.0, above=5.0, high=300.0),
            search_speed_m_s=section.number("search_speed_m_s", 0.025, above=0.0, high=cell.limits["tcp_speed_m_s"]),
            touch_speed_m_s=section.number("touch_speed_m_s", 0.002, above=0.0, high=0.02),
            backoff_mm=section.number("backoff_mm", 0.15, above=0.0, high=5.0),
            contact_noise_mm=section.number("contact_noise_mm", 0.02, above=0.0, high=5.0),
            fit_radius=section.flag("fit_radius", True),
            loss=section.choice("loss", fitting.LOSSES, "cauchy"),
            end_shape=section.choice("end_shape", fitting.END_SHAPES, "round"))
        section.done()
        return opts

    # -- planning ------------------------------------------------------------------------

    def probes(self) -> list[Probe]:
        """Every contact of the routine, in the order made."""
        o, cell = self.options, self.cell
        home_x = tcp_frames(self.model, np.asarray(cell.home_q_rad, float), cell.tool.tcp_pose)[0][0][:, 0]
        stylus = np.asarray(cell.stylus["centre_m"], float)
        r_s, r_contact = cell.stylus["radius_m"], cell.tool.radius_m + cell.stylus["radius_m"]
        middle = np.r_[-stylus[:2] / np.linalg.norm(stylus[:2]), 0.0]  # from the stylus toward the robot
        up = np.array([0.0, 0.0, 1.0])

        def side_of(deg):
            return se3.rot("z", np.deg2rad(deg)) @ middle

        def axis_of(tilt_deg, azimuth_deg, side):
            """Straight down, tilted by tilt_deg toward azimuth_deg (0: over the stylus) from `side`."""
            t, a = np.deg2rad(tilt_deg), np.deg2rad(azimuth_deg)
            return -np.cos(t) * up + np.sin(t) * (np.cos(a) * side + np.sin(a) * np.cross(up, side))

        def frame(axis, roll_deg):
            x0 = home_x - (home_x @ axis) * axis
            x0 /= np.linalg.norm(x0)
            g = np.deg2rad(roll_deg)
            x = np.cos(g) * x0 + np.sin(g) * np.cross(axis, x0)
            return np.column_stack([x, np.cross(axis, x), axis])

        def face(kind, station, axis, roll, clearance, refit=False):
            tcp = np.r_[stylus - axis * r_s, se3.matrix_to_rotvec(frame(axis, roll))]
            return Probe(kind, station, station, 0.0, roll, clearance, refit, tcp, axis)

        def side(kind, station, group, axis, towards, h_mm, roll, clearance, refit=False):
            n = towards - (towards @ axis) * axis
            n /= np.linalg.norm(n)
            tcp = np.r_[stylus + n * r_contact + axis * h_mm / 1e3, se3.matrix_to_rotvec(frame(axis, roll))]
            return Probe(kind, station, group, h_mm, roll, clearance, refit, tcp, -n)

        c0, fine, straight = o.coarse_clearance_mm, o.clearance_mm, axis_of(0, 0, middle)
        out = [face("coarse-face", i, axis_of(25.0, 120.0 * i, middle), 0.0, c0) for i in range(3)]
        out.append(face("coarse-face", 3, straight, 0.0, c0))
        for g, beta in enumerate((-60.0, 0.0, 60.0)):
            out += [side("axial", 3, 10 + g, straight, side_of(beta), h, 0.0, c0) for h in o.heights_mm]
        rolls, previous = [], None
        for s, tilt, azimuth, beta, h, angle in design.design(o.side_contacts, o.stations, o.tilt_deg,
                                                              o.sides_deg, o.heights_mm):
            axis, towards = axis_of(tilt, azimuth, side_of(beta)), side_of(beta)
            ball = frame(axis, 0.0).T @ -(towards - (towards @ axis) * axis)  # toward the ball, roll 0
            roll = np.degrees(np.arctan2(ball[1], ball[0])) - angle  # turn that puts the ball at `angle`
            roll = roll + 360.0 * np.round(((rolls[-1] if s == previous else 0.0) - roll) / 360.0)
            rolls.append(roll)
            out.append(side("side", 20 + s, 20 + s, axis, towards, h, roll, max(fine, c0 / 2) if s == 0 else fine,
                            refit=s != previous))
            previous = s
        station = out[-1].station  # the last station holds the tool straight: the end faces down
        last = [r for p, r in zip(out[-len(rolls):], rolls) if p.station == station]
        for i, roll in enumerate(np.linspace(min(last), max(last), o.face_touches)):
            out.append(face("face", station, straight, roll, fine, refit=i == 0))
        return out

    def _steps(self, n: int, probe: Probe, prev, shift_m, approach, q) -> tuple[list, tuple, np.ndarray]:
        """The moves of the n-th probe after the previous one's (station, kind, approach, start,
        far, above), re-aimed by the base-frame translation `shift_m`. From one side or
        orientation to another the tool goes out along its approach, up until its tip is
        ``retreat_mm`` above the stylus, across, and down again."""
        o, lim = self.options, self.cell.limits
        v, a = lim["tcp_speed_m_s"], lim["tcp_accel_m_s2"]
        contact = np.r_[probe.tcp[:3] + shift_m, probe.tcp[3:]]
        start, far, back = contact.copy(), contact.copy(), contact.copy()
        start[:3] -= approach * probe.clearance_mm / 1e3
        far[:3] -= approach * o.retreat_mm / 1e3
        back[:3] -= approach * o.backoff_mm / 1e3
        above = far.copy()
        above[2] = max(far[2], self.cell.stylus["centre_m"][2] + shift_m[2] + o.retreat_mm / 1e3)
        label = f"contact {n} ({probe.kind})"
        steps = []
        if prev is None or prev[0] != probe.station or prev[1] != probe.kind or not np.allclose(prev[2], approach,
                                                                                                  atol=0.02):
            if prev is not None:
                steps += [Move.linear(f"{label}: out from the last one", prev[4], v, a),
                          Move.linear(f"{label}: up from the last one", prev[5], v, a)]
            if prev is None or prev[0] != probe.station:
                q_above = inverse(self.model, above, q, self.cell.tool.tcp_pose)
                if q_above is None:
                    raise PlanRefused(f"{label}: no joint solution for the pose above it "
                                      f"{np.round(above[:3], 4).tolist()} m; reduce tilt_deg or sides_deg")
                near = np.array(q, float)  # the last joint turns the tool: keep its sweep centred on home
                near[-1] = self.cell.home_q_rad[-1] + np.deg2rad(probe.roll_deg)
                q = design.nearest_turn(q_above, near, self.model.joint_limits)
                steps.append(Move.joint(f"{label}: to its orientation", q, lim["joint_speed_rad_s"],
                                        lim["joint_accel_rad_s2"]))
            else:
                steps.append(Move.linear(f"{label}: across", above, v, a))
            steps.append(Move.linear(f"{label}: down", far, v, a))
        steps += [Move.linear(f"{label}: approach", start, v, a),
                  Move.contact(f"{label}: search", approach, o.search_speed_m_s,
                               (probe.clearance_mm + SEARCH_MARGIN_MM) / 1e3, accel=a),
                  Move.linear(f"{label}: back off", back, v, a),
                  Move.contact(f"{label}: touch", approach, o.touch_speed_m_s, (2 * o.backoff_mm + 0.5) / 1e3, accel=a),
                  Move.linear(f"{label}: retract", start, v, a)]
        return steps, (probe.station, probe.kind, approach, start, far, above), q

    def plan(self) -> list[Move]:
        plan, q, prev, clearance = [], np.asarray(self.cell.home_q_rad, float), None, []
        for n, probe in enumerate(self.probes(), start=1):
            steps, prev, q = self._steps(n, probe, prev, np.zeros(3), probe.approach, q)
            plan += steps
            clearance += [probe.clearance_mm] * len(steps)
        plan += self._leave(prev)
        self._check_clear(plan, clearance + [clearance[-1]] * 3)
        return plan

    def _leave(self, prev) -> list[Move]:
        """Out from the last contact, up, and back home."""
        lim, home = self.cell.limits, np.asarray(self.cell.home_q_rad, float)
        return [Move.linear("out from the last contact", prev[4], lim["tcp_speed_m_s"], lim["tcp_accel_m_s2"]),
                Move.linear("up from the last contact", prev[5], lim["tcp_speed_m_s"], lim["tcp_accel_m_s2"]),
                Move.joint("back home", home, lim["joint_speed_rad_s"], lim["joint_accel_rad_s2"])]

    def _check_clear(self, plan: list[Move], clearance_mm: list[float]) -> None:
        """Refuse a plan in which the drawn tool would pass the stylus (where the file says)
        closer than half its clearance, on any move but the touches themselves."""
        tool, stylus = self.cell.tool, self.cell.stylus
        gaps = design.path_gaps(self.model, [(m.kind, m.q_rad if m.kind == "joint" else m.pose) for m in plan],
                                self.cell.home_q_rad, tool.tcp_pose, tool.tcp_m, tool.axis, tool.radius_m,
                                tool.length_m, np.asarray(stylus["centre_m"]), stylus["radius_m"])
        for move, gap, need in zip(plan, gaps, clearance_mm):
            if gap < need / 2e3 and not move.label.endswith((": back off", ": retract")):
                raise PlanRefused(f"move '{move.label}' would pass the stylus {gap * 1e3:.1f} mm away; "
                                  "change tilt_deg, sides_deg or retreat_mm")

    # -- measuring -----------------------------------------------------------------------

    def _reaim(self, probe: Probe, estimate) -> tuple[np.ndarray, np.ndarray]:
        """Translation (m) and approach direction that put the real tool where `probe` meant."""
        if estimate is None:
            return np.zeros(3), probe.approach
        tool = self.cell.tool
        flange_rot = se3.rotvec_to_matrix(probe.tcp[3:]) @ se3.rotvec_to_matrix(tool.tcp_pose[3:]).T
        tip, at_tip = tool.tcp_m * 1e3, probe.kind == "face"
        shift = design.reaim(estimate, flange_rot, tip - probe.height_mm * tool.axis, tip,
                             np.asarray(self.cell.stylus["centre_m"]) * 1e3, at_tip)
        if not at_tip:
            return shift / 1e3, probe.approach
        axis = flange_rot @ estimate.line.direction  # along the real axis, onto the ball's top
        return (shift - (axis - probe.approach) * self.cell.stylus["radius_m"] * 1e3) / 1e3, axis

    def _touch(self, robot, n: int, steps: list, approach):
        """Search, back off, touch again slowly; the ContactResult of the slow touch."""
        where = f"{self.cell.path}: [stylus] centre_m {np.round(self.cell.stylus['centre_m'], 4).tolist()}"
        approach_move, search, back, touch = steps[-5:-1]
        found = robot.run(search)
        if not found.contact:
            raise RoutineError(f"contact {n} found nothing within {search.travel_m * 1e3:.1f} mm: is the stylus "
                               f"where [stylus] says? ({where})")
        if np.linalg.norm(np.asarray(found.tcp_pose)[:3] - approach_move.pose[:3]) < 1e-5:
            raise RoutineError(f"contact {n} touched where its search began: something is in the way, or the "
                               f"stylus is not where [stylus] says ({where})")
        pose = np.asarray(found.tcp_pose, float).copy()
        pose[:3] -= approach * self.options.backoff_mm / 1e3
        robot.run(Move.linear(back.label, pose, back.speed, back.accel))
        touched = robot.run(touch)
        if not touched.contact:
            raise RoutineError(f"contact {n}: the slow touch found nothing within {touch.travel_m * 1e3:.2f} mm of "
                               "where the search touched: did the stylus move?")
        return touched

    def measure(self, devices, robot, plan, progress):
        cell = self.cell
        with drawn_tool(robot, cell.tool.tcp_pose):
            rows, kinds, t0 = self._contacts(robot, progress)
        times = np.array([s.t_s for s in robot.samples(t0)])
        data = np.array(rows, dtype=float)
        columns = {name: data[:, i] for i, name in enumerate(COLUMNS)}
        columns["kind"] = np.array(kinds, dtype=str)
        meta = {"cycle_s": float(np.median(np.diff(times))) if len(times) > 2 else 0.0,
                "cycle_time_s": float(times[-1] - t0) if len(times) else 0.0,
                "tool_drawn": cell.tool.tcp_pose.tolist(), "tool_axis_drawn": cell.tool.axis.tolist(),
                "tool_radius_m": cell.tool.radius_m, "stylus_radius_m": cell.stylus["radius_m"],
                "stylus_file_m": np.asarray(cell.stylus["centre_m"]).tolist()}
        return Dataset(self.name, columns, meta)

    def _contacts(self, robot, progress) -> tuple[list, list, float]:
        """Every contact, re-aimed on what the earlier ones showed: (rows, kinds, start time s)."""
        cell, o = self.cell, self.options
        samples = robot.samples()
        t0 = samples[-1].t_s if samples else 0.0
        probes = self.probes()
        rows, kinds, estimate, prev = [], [], None, None
        q = np.asarray(robot.actual_q(), float)
        for n, probe in enumerate(probes, start=1):
            if probe.refit:
                estimate = self._estimate(rows, kinds, probe.kind == "side" and estimate is None)
                offset = estimate.stylus_mm - np.asarray(cell.stylus["centre_m"]) * 1e3
                progress(f"contact {n}: re-aimed on {len(rows)} contacts; the stylus is "
                         f"{np.linalg.norm(offset):.3f} mm from where [stylus] says")
            shift, approach = self._reaim(probe, estimate)
            try:
                steps, prev, q = self._steps(n, probe, prev, shift, approach, q)
            except PlanRefused as exc:  # re-aimed on the stylus found, mid-run: the arm has moved already
                raise RoutineError(f"re-aimed on the stylus: {exc}") from None
            for move in steps[:-5]:
                robot.run(move)
            robot.run(steps[-5])
            touched = self._touch(robot, n, steps, approach)
            robot.run(steps[-1])
            kinds.append(probe.kind)
            rows.append([n, probe.group, probe.height_mm, probe.roll_deg, *touched.q_rad, *touched.tcp_pose,
                         *approach, o.touch_speed_m_s])
        for move in self._leave(prev):
            robot.run(move)
        return rows, kinds, t0

    def _estimate(self, rows, kinds, coarse_only: bool) -> fitting.Estimate:
        """What the contacts so far say (the coarse result, or the fit of every side contact)."""
        cell, o = self.cell, self.options
        drawn = _drawn(cell.tool.tcp_m, cell.tool.axis, cell.stylus["centre_m"])
        try:
            first, found = design.start_and_fit(
                _recorded(self.model, dict(zip(COLUMNS, np.array(rows).T)), np.array(kinds), 0.0), drawn,
                cell.stylus["radius_m"] * 1e3, cell.tool.radius_m * 1e3, fit_radius=o.fit_radius,
                end_shape=o.end_shape, loss=o.loss, noise_mm=o.contact_noise_mm, coarse_only=coarse_only)
        except (ValueError, np.linalg.LinAlgError) as exc:
            raise RoutineError(f"the contacts so far do not determine the tool: {exc}") from None
        first = first or drawn
        if coarse_only:
            return first
        return fitting.Estimate(found.line, found.tip_mm if found.tip_mm is not None else found.line.foot(first.tip_mm),
                                found.stylus_mm)

    # -- solving -------------------------------------------------------------------------

    @classmethod
    def solve(cls, dataset, cell: Cell, options: TcpStylusOptions) -> Result:
        meta, where = dataset.meta, dataset.path or "dataset"
        missing = [k for k in (*COLUMNS, "kind") if k not in dataset.columns] + [
            k for k in ("cycle_s", "tool_drawn", "tool_axis_drawn", "tool_radius_m", "stylus_radius_m", "stylus_file_m")
            if k not in meta]
        if missing or not len(dataset):
            raise RoutineError(f"{where}: not a complete tcp-stylus dataset (missing: {', '.join(missing) or 'rows'})")
        data = _recorded(load_robot(cell.robot), dataset.columns, dataset["kind"], float(meta["cycle_s"]))
        drawn = _drawn(np.asarray(meta["tool_drawn"][:3]), meta["tool_axis_drawn"], meta["stylus_file_m"])
        drawn_tip, use = drawn.tip_mm, data.kind != "coarse-face"
        try:
            start, fit = design.start_and_fit(data, drawn, meta["stylus_radius_m"] * 1e3, meta["tool_radius_m"] * 1e3,
                                              fit_radius=options.fit_radius, end_shape=options.end_shape,
                                              loss=options.loss, noise_mm=options.contact_noise_mm)
        except (ValueError, np.linalg.LinAlgError) as exc:
            raise RoutineError(f"{where}: the contacts do not determine the tool: {exc}") from None
        seen = design.determined(fit)
        n_face = int(np.sum(data.kind == "face"))
        ref = tool_frame.reference(meta.get("tool_frame_before"), np.asarray(meta["tool_drawn"], dtype=float))
        tip = fit.tip_mm if fit.tip_mm is not None else fit.line.foot(ref.pose[:3] * 1e3)
        frame, frame_notes = tool_frame.compose(tool_frame.TIP_AND_AXIS, ref, tip_m=tip / 1e3,
                                                axis=fit.line.direction)
        shown = fitting.summary(fit, drawn_tip, seen.null_space)
        kept, left_out = fit.residuals_mm[fit.kept], int(np.sum(~fit.kept))
        share = left_out / len(fit.kept)
        notes = ["the tool frame's z is the tool axis; no contact on a round tool can measure its turn about the axis",
                 *frame_notes,
                 f"the TCP's place along the axis is fixed by {n_face} end-face touches" if n_face else
                 "no end-face touch: the TCP's place along the axis is not measured; it is the point of the found "
                 f"axis nearest the TCP of {ref.source} (a convention)",
                 "tool.rx, tool.ry: the found axis as the rotation vector of the smallest turn from the flange's z (a "
                 "description of the axis; the tool frame's own rx, ry also carry its kept turn about the axis)",
                 *fit.notes]
        gate_list = [gates.residual(float(np.sqrt(np.mean(kept**2))), options.contact_noise_mm),
                     gates.conditioning(seen.condition), gates.identifiability(seen.undetermined),
                     Gate("outliers", share <= MAX_OUTLIER_SHARE, share, MAX_OUTLIER_SHARE,
                          f"{left_out} of {len(fit.kept)} contacts left out as outliers" +
                          ("" if share <= MAX_OUTLIER_SHARE else ": too many to trust the rest; is the stylus loose?")),
                     gates.plausible_tool(frame, cell.tool, determines=tool_frame.TIP_AND_AXIS),
                     gates.agrees_with_previous(frame, meta.get("tool_frame_before"),
                                                determines=tool_frame.TIP_AND_AXIS)]
        frame_known = all(ok for name, *_, ok in shown if name.startswith(("tcp", "axis", "tool")))
        extra = {"stylus_mm": fit.stylus_mm.tolist(), "contact_radius_mm": fit.radius_mm,
                 "contacts": {"made": len(dataset), "fitted": int(use.sum()), "end_face": n_face,
                              "coarse_end_face": int(np.sum(~use)), "left_out": left_out},
                 "tcp_along_axis": "end-face touches" if n_face else f"convention: nearest the TCP of {ref.source}",
                 "rotation_about_axis": f"kept from {ref.source}",
                 "rank": seen.rank, "fitted": list(fit.names)}
        if start is not None:  # how far Chang et al.'s coarse stage was from the fine result
            extra["coarse_off_fine_mm"] = float(np.linalg.norm(start.tip_mm - tip))
            cos = min(1.0, float(start.line.direction @ fit.line.direction))
            extra["coarse_off_fine_deg"] = float(np.degrees(np.arccos(cos)))
        used = data.contacts(use)
        drawing = contacts_on_cylinder(used.stylus_in_flange(fit.stylus_mm), np.where(data.kind[use] == "face", "face",
                                       "side"), fit.kept, fit.line.point_mm, fit.line.direction, tip, fit.radius_mm)
        return Result(cls.name, [Parameter(n, v, sd, unit) for n, v, sd, unit, ok in shown if ok], kept,
                      options.contact_noise_mm, seen.condition, gate_list, tool_frame=frame if frame_known else None,
                      notes=notes, extra=extra, drawing=drawing,
                      determines=tool_frame.TIP_AND_AXIS if frame_known else tool_frame.NOTHING)


def _drawn(tip_m, axis, stylus_m) -> fitting.Estimate:
    """The tool as drawn and the stylus where the cell file says (mm)."""
    tip = np.asarray(tip_m, float) * 1e3
    return fitting.Estimate(fitting.Line(tip, np.asarray(axis, float)), tip, np.asarray(stylus_m, float) * 1e3)


def _recorded(model, columns, kinds, cycle_s: float) -> design.Recorded:
    """The dataset's rows as the fit wants them."""
    return design.Recorded.of(model, np.column_stack([columns[f"q{i}_rad"] for i in range(1, 7)]), kinds,
                              columns["group"], np.column_stack([columns[k] for k in ("dir_x", "dir_y", "dir_z")]),
                              columns["speed_m_s"], cycle_s)
