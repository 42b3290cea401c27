"""``tcf``: the tool axis (the tool frame's z) from moves along it, touching a fixed ball.

A pivot fixes a point of the tool, never its direction: the axis needs something that
feels the tool's body. Here that is the cell's stylus ball, touched by the shank. The
plan, from the cell file alone (the tool as drawn, the stylus where [stylus] says): the
TCP set to the drawn tool, the tool held straight down at a few turns about its axis;
at each turn, at two heights along the tool (`near_mm` and `far_mm` behind the tip, the
tool translated along its own axis between them), the ball is touched by contact
searches across the axis from four sides (+x, +y, -x, -y of the base, stepping round
the ball by its corners).

Each pair of opposite touches is centred on where the axis crosses that search line
(the shank's and the ball's radii cancel), so the crossing moves with the height by
the axis' tilt: :func:`cellcal.solvers.tool_frames.pivot.fit_axis` solves that linear least
squares for the axis in the flange frame over all turns (turning the tool separates
its tilt from anything fixed in the base frame). The routine determines the axis only:
the tool frame it writes keeps the TCP position of the controller's frame from before
the run, and that frame's orientation turned by the smallest rotation that takes its z
onto the axis found, so its turn about the axis (a round tool has no x of its own) is kept
too (:mod:`.framework.tool_frame`). Only where no controller frame is known are they the drawing's,
the TCP `tcp_mm` where given. The tilts are reported as tcp-laser's: how far the axis
leans from the drawn axis toward the flange's x and y.

Section ``tcf`` of the cell file (all optional)::

    turns: 3                 # orientations of the tool about its axis, evenly spread
    near_mm: 15              # heights behind the tip where the shank touches the ball
    far_mm: 85
    clearance_mm: 4          # gap at each search's start (a search may go twice that)
    search_speed_mm_s: 5
    repeatability_mm: 0.03   # the arm's stated repeatability (RMS distance of a repeated pose)
    target_deg: 0.05         # refuse a design whose expected axis error (1 sigma) is larger
    tcp_mm: [0, 0, 150]      # the TCP in the flange frame (from tcp-npoint) where no controller frame is known
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.reader import Section
from cellcal.config.robot_files import load_robot
from cellcal.solvers.tool_frames import pivot as pv
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.inverse import inverse
from cellcal.solvers.tool_frames.tcp_laser import axis_pair
from cellcal.routines.framework import gates, tool_frame
from cellcal.routines.framework.base import (PlanPromise, Devices, Gate, Move, Parameter, PlanRefused, Result,
                                             RoutineError)
from cellcal.routines.framework.drawing import axis_crossings
from cellcal.routines.framework.steps import StepRoutine
from cellcal.routines.tcp_npoint import JOINT_SPEED_RAD_S, LIFT_MM, axis_sigma_mm, down_orientation, flange_frames

SIDES = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # base frame
CONTACT_TOLERANCE_MM = 0.25  # shank plus ball radius from the touches may be this far from the drawing
MAX_TILT_STD_DEG = 0.5  # an axis this uncertain is not determined


@dataclass(frozen=True)
class TcfOptions:
    turns: int
    near_mm: float
    far_mm: float
    clearance_mm: float
    search_speed_mm_s: float
    repeatability_mm: float
    target_deg: float
    tcp_mm: np.ndarray | None


class Tcf(StepRoutine):
    name = "tcf"
    section = "tcf"
    selector = 6
    needs = ("robot",)

    @classmethod
    def read_options(cls, section: Section, cell: Cell) -> TcfOptions:
        if cell.tool is None:
            section.fail(None, "tcf needs the tool as drawn in [tool]")
        if cell.stylus is None:
            section.fail(None, "tcf needs the stylus ball in [stylus] to touch the tool's shank")
        r_mm, length_mm = cell.tool.radius_m * 1e3, cell.tool.length_m * 1e3
        low, high = r_mm + 5.0, length_mm - 5.0
        if high <= low + 5.0:
            section.fail(None, f"the tool of [tool] is too short ({length_mm:g} mm) for touches at two heights")
        near = section.number("near_mm", min(15.0, high), low=low, high=high)
        far = section.number("far_mm", min(85.0, high), low=low, high=high)
        if far < near + 5.0:
            section.fail("far_mm", f"{far:g} must be 5 mm or more behind near_mm ({near:g})")
        travel_mm = cell.limits["contact_travel_m"] * 1e3
        options = TcfOptions(
            section.integer("turns", 3, low=2, high=8), near, far,
            section.number("clearance_mm", 4.0, low=1.0, high=travel_mm / 2),
            section.number("search_speed_mm_s", 5.0, above=0.0, high=min(cell.limits["tcp_speed_m_s"] * 1e3, 20.0)),
            section.number("repeatability_mm", 0.03, above=0.0, high=1.0),
            section.number("target_deg", 0.05, above=0.0, high=5.0),
            section.vector("tcp_mm", 3) if "tcp_mm" in section else None)
        section.done()
        return options

    # -- plan ------------------------------------------------------------------------

    def turns(self) -> list[np.ndarray]:
        """Tool frame rotations: straight down, turned evenly about the (vertical) tool axis."""
        down = down_orientation(self.cell, load_robot(self.cell.robot))
        return [se3.rot("z", 2 * np.pi * j / self.options.turns) @ down for j in range(self.options.turns)]

    def touches(self, far_mm: float | None = None) -> list[dict]:
        """Every planned touch: turn, height, side, and the search line's direction."""
        o = self.options
        far = o.far_mm if far_mm is None else far_mm
        return [{"turn": j + 1, "height_mm": h, "side": k, "dir_x": -s[0], "dir_y": -s[1], "dir_z": -s[2]}
                for j in range(o.turns) for h in (o.near_mm, far) for k, s in enumerate(SIDES)]

    def design(self, far_mm: float | None = None) -> PlanPromise:
        """The planned touches (the far height `far_mm`, default the option's) judged at the
        stated repeatability: the tool axis' expected error, deg."""
        touches = self.touches(far_mm)
        tool = self.cell.tool.tcp_pose
        rotations = {j + 1: r @ se3.rotvec_to_matrix(tool[3:]).T for j, r in enumerate(self.turns())}
        pairs = [t for t in touches if t["side"] < 2]
        line = [2 * (t["turn"] - 1) + t["side"] for t in pairs]
        found = pv.axis_design(line, [rotations[t["turn"]] for t in pairs], [SIDES[t["side"]] for t in pairs],
                               [t["height_mm"] for t in pairs], self.cell.tool.axis,
                               axis_sigma_mm(self.options.repeatability_mm) / np.sqrt(2.0))
        return PlanPromise(found.condition, float(np.rad2deg(found.expected_error)), "deg",
                      {"tilt_std_deg": np.rad2deg(found.std).tolist()})

    def check_design(self) -> PlanPromise:
        """PlanRefused when the heights are too close for the target at the stated repeatability."""
        o = self.options
        design = self.design()
        if design.expected_error <= o.target_deg:
            return design
        top = self.cell.tool.length_m * 1e3 - 5.0
        need = pv.smallest_setting(lambda f: self.design(f).expected_error, o.target_deg, o.far_mm, top)
        what = (f"at least {need - o.near_mm:.1f} mm apart is needed" if need is not None else
                f"not even {top - o.near_mm:.1f} mm apart (the tool's length) reaches it: plan more turns or a "
                "looser target_deg")
        raise PlanRefused(f"{self.cell.path} [tcf]: the heights {o.near_mm:g} and {o.far_mm:g} mm are "
                          f"{o.far_mm - o.near_mm:g} mm apart; {what} for {o.target_deg:g} deg at "
                          f"{o.repeatability_mm:g} mm repeatability (this design: "
                          f"{design.expected_error:.3f} deg expected); move far_mm or near_mm")

    def steps(self) -> list[tuple[Move, dict | None]]:
        cell, o = self.cell, self.options
        model = load_robot(cell.robot)
        tool = cell.tool
        ball = np.asarray(cell.stylus["centre_m"], dtype=float)
        reach = tool.radius_m + float(cell.stylus["radius_m"]) + o.clearance_mm / 1e3
        speed, accel = cell.limits["tcp_speed_m_s"], cell.limits["tcp_accel_m_s2"]
        joint_speed, joint_accel = min(JOINT_SPEED_RAD_S, cell.limits["joint_speed_rad_s"]), \
            cell.limits["joint_accel_rad_s2"]
        up = np.array([0.0, 0.0, 1.0])
        steps: list[tuple[Move, dict | None]] = []

        def go(label, rotation, tip):
            steps.append((Move.linear(label, np.concatenate([tip, se3.matrix_to_rotvec(rotation)]), speed, accel),
                          None))

        for j, rotation in enumerate(self.turns()):
            above = ball + reach * SIDES[0] + LIFT_MM / 1e3 * up
            if j == 0:
                q = inverse(model, np.concatenate([above, se3.matrix_to_rotvec(rotation)]), cell.home_q_rad,
                            tool.tcp_pose)
                if q is None:
                    raise PlanRefused("move 'above the stylus': cannot be reached from home")
                steps.append((Move.joint("above the stylus", q, joint_speed, joint_accel), None))
            else:
                go(f"turn {j + 1}", rotation, above)
            order = (0, 1, 2, 3)
            for i, h in enumerate((o.near_mm, o.far_mm)):
                level = ball - h / 1e3 * up
                go(f"down to {h:g} mm (turn {j + 1})", rotation, level + reach * SIDES[order[0]])
                for n, k in enumerate(order):
                    start = level + reach * SIDES[k]
                    if n > 0:
                        go(f"round the ball at {h:g} mm (turn {j + 1})", rotation,
                           level + reach * (SIDES[order[n - 1]] + SIDES[k]))
                        go(f"beside the ball, side {k + 1} at {h:g} mm (turn {j + 1})", rotation, start)
                    touch = {"turn": j + 1, "height_mm": h, "side": k,
                             **dict(zip(("dir_x", "dir_y", "dir_z"), -SIDES[k]))}
                    steps.append((Move.contact(f"touch side {k + 1} at {h:g} mm (turn {j + 1})", -SIDES[k],
                                               o.search_speed_mm_s / 1e3, 2 * o.clearance_mm / 1e3), touch))
                    go(f"back from side {k + 1} at {h:g} mm (turn {j + 1})", rotation, start)
                order = order[::-1]
            go(f"up (turn {j + 1})", rotation, above)  # two heights, two reversals: back at side 1
        steps.append((Move.joint("home", cell.home_q_rad, joint_speed, joint_accel), None))
        return steps

    # -- measure ---------------------------------------------------------------------

    def announce(self, design: PlanPromise) -> str:
        o = self.options
        return (f"tcf: {o.turns} turns of the tool, the shank touched at {o.near_mm:g} and {o.far_mm:g} mm behind "
                f"the tip from four sides: condition {design.condition:.3g}, expected axis error "
                f"{design.expected_error:.4f} deg (1 sigma) at {o.repeatability_mm:g} mm repeatability")

    def run_steps(self, devices: Devices, robot, plan: list[Move], steps, progress) -> tuple[list[dict], float]:
        def missed(move):
            return (f"the contact search went {move.travel_m * 1e3:g} mm without touching the stylus: is [stylus] "
                    f"centre_m {np.round(self.cell.stylus['centre_m'], 4).tolist()} m right, and the tool as [tool] "
                    "draws it?")

        recorded = itertools.count(1)

        def record(touch, q):
            if next(recorded) % len(SIDES) == 0:  # the last of a height's touches
                progress(f"tcf: turn {touch['turn']}, touches at {touch['height_mm']:g} mm done")
            return {**touch, **{f"q{j + 1}_rad": v for j, v in enumerate(q)}}

        return self.contact_rows(robot, plan, steps, missed, record)

    def dataset_meta(self, design: PlanPromise, before: dict) -> dict:
        o = self.options
        return {"tool_radius_m": self.cell.tool.radius_m, "stylus_radius_m": float(self.cell.stylus["radius_m"]),
                "planned_tool": self.cell.tool.tcp_pose.tolist(), "clearance_mm": o.clearance_mm,
                "search_speed_mm_s": o.search_speed_mm_s, "repeatability_mm": o.repeatability_mm}

    # -- solve -----------------------------------------------------------------------

    @classmethod
    def solve(cls, dataset, cell: Cell, options: TcfOptions) -> Result:
        meta = dataset.meta
        missing = [k for k in ("tool_radius_m", "stylus_radius_m", "planned_tool") if k not in meta]
        if missing:
            raise RoutineError(f"{dataset.path}: the dataset's meta lacks {', '.join(missing)}")
        model = load_robot(cell.robot)
        names = [f"q{j + 1}_rad" for j in range(model.n_joints)]
        need = ["turn", "height_mm", "side", "dir_x", "dir_y", "dir_z", *names]
        absent = [n for n in need if n not in dataset.columns]
        if absent:
            raise RoutineError(f"{dataset.path}: columns missing: {', '.join(absent)}")
        rotations, positions = flange_frames(model, dataset.stack(*names))
        pairs = crossings(dataset, rotations, positions)
        if len({p["line"] for p in pairs}) < 2 or len(pairs) < len({p["line"] for p in pairs}) + 3:
            raise RoutineError(f"{dataset.path}: {len(pairs)} opposite pairs of touches cannot give the axis with a "
                               "check (two turns at two heights at least)")
        drawn = se3.rotvec_to_matrix(np.asarray(meta["planned_tool"], dtype=float)[3:])[:, 2]
        line = [p["line"] for p in pairs]
        args = (line, [p["rotation"] for p in pairs], [p["direction"] for p in pairs], [p["height_mm"] for p in pairs])
        sigma = axis_sigma_mm(options.repeatability_mm) / np.sqrt(2.0)
        design = pv.axis_design(*args, drawn, sigma)
        if design.expected_error > np.deg2rad(options.target_deg):
            raise RoutineError(f"{dataset.path}: these touches leave an expected axis error of "
                               f"{np.rad2deg(design.expected_error):.3f} deg at {options.repeatability_mm:g} mm "
                               f"repeatability, above target_deg {options.target_deg:g}: not solved")
        try:
            fit = pv.fit_axis(*args, [p["midpoint_mm"] for p in pairs], drawn)
        except ValueError as exc:
            raise RoutineError(f"{dataset.path}: {exc}") from None
        result = _result(cls.name, dataset, cell, options, fit, design, pairs, drawn, sigma)
        crossing = np.array([p["midpoint_mm"] for p in pairs]) - fit.offsets[line]
        result.drawing = axis_crossings(line, args[3], crossing, crossing - fit.residuals_mm,
                                        [f"turn {k // 2 + 1}, {'xy'[k % 2]} line" for k in range(len(fit.offsets))])
        return result


def crossings(dataset, rotations, positions) -> list[dict]:
    """Opposite touches paired: for each turn, height and line (x or y), where the axis
    crosses the line (the pair's midpoint along it, flange position, mm), and the pair's
    half-chord with the line's offset from the crossing of the other line (for the radii)."""
    side = dataset["side"].astype(int)
    key = {}
    for i, (turn, height, k) in enumerate(zip(dataset["turn"].astype(int), dataset["height_mm"], side)):
        key.setdefault((turn, float(height), k % 2), {})[k // 2] = i
    turns = sorted({k[0] for k in key})
    pairs = []
    for (turn, height, axis), found in sorted(key.items()):
        if len(found) != 2:
            continue
        a, b = found[0], found[1]  # touched from the + side, from the - side
        direction = -np.array([dataset["dir_x"][a], dataset["dir_y"][a], dataset["dir_z"][a]])
        mid = 0.5 * (positions[a] + positions[b])
        pairs.append({"turn": turn, "height_mm": height, "axis": axis, "line": 2 * turns.index(turn) + axis,
                      "rotation": rotations[a], "direction": direction, "midpoint_mm": float(direction @ mid),
                      "half_chord_mm": float(direction @ (positions[a] - positions[b])) / 2.0, "position_mm": mid})
    by = {(p["turn"], p["height_mm"], p["axis"]): p for p in pairs}
    for p in pairs:
        other = by.get((p["turn"], p["height_mm"], 1 - p["axis"]))
        if other is not None:
            aside = other["midpoint_mm"] - other["direction"] @ p["position_mm"]
            p["reach_mm"] = float(np.hypot(p["half_chord_mm"], aside))
    return pairs


def _result(name, dataset, cell: Cell, options: TcfOptions, fit: pv.AxisFit, design: pv.PlanQuality, pairs, drawn,
            sigma: float) -> Result:
    meta = dataset.meta
    planned = np.asarray(meta["planned_tool"], dtype=float)
    ref = tool_frame.reference(meta.get("tool_frame_before"), planned,
                               tip_m=None if options.tcp_mm is None else options.tcp_mm / 1e3,
                               tip_option="tcp_mm of [tcf]")
    frame, frame_notes = tool_frame.compose(tool_frame.AXIS_ONLY, ref, axis=fit.axis)
    n, dof = len(fit.residuals_mm), len(fit.residuals_mm) - len(fit.offsets) - 2
    expected = sigma * np.sqrt(dof / n)
    rms = float(np.sqrt(np.mean(fit.residuals_mm**2)))
    reach = [p["reach_mm"] for p in pairs if "reach_mm" in p]
    drawn_reach = (float(meta["tool_radius_m"]) + float(meta["stylus_radius_m"])) * 1e3
    reach_mm = float(np.mean(reach)) if reach else float("nan")
    reach_ok = bool(np.isfinite(reach_mm) and abs(reach_mm - drawn_reach) <= CONTACT_TOLERANCE_MM)
    contacts = Gate("contacts", reach_ok, reach_mm, drawn_reach,
                    f"the touches put the shank's axis {reach_mm:.3f} mm from the ball's centre; a shank and ball "
                    f"as drawn give {drawn_reach:.3f} mm" + ("" if reach_ok else
                                                             f" (more than {CONTACT_TOLERANCE_MM:g} mm off): "
                                                             "something else was touched, or [tool] radius_m or "
                                                             "[stylus] radius_m is wrong"))
    # the tilts as tcp-laser counts them (toward flange x and y made perpendicular to the drawn axis), from the
    # fit's, which are counted on solvers.tool_frames.pivot.across(drawn): the same plane, turned
    e = np.stack(axis_pair(drawn))
    turn = e @ pv.across(drawn).T
    tilt_deg = [float(np.degrees(np.arctan2(fit.axis @ u, fit.axis @ drawn))) for u in e]
    tilt_std_deg = np.rad2deg(np.sqrt(np.diag(turn @ fit.covariance[-2:, -2:] @ turn.T)))
    undetermined = [f"axis_tilt_{c}_deg" for c, s in zip("xy", tilt_std_deg) if not s <= MAX_TILT_STD_DEG]
    gate_list = [gates.residual(rms, expected), gates.conditioning(fit.condition), gates.identifiability(undetermined),
                 contacts, gates.plausible_tool(frame, cell.tool, determines=tool_frame.AXIS_ONLY),
                 gates.agrees_with_previous(frame, meta.get("tool_frame_before"), determines=tool_frame.AXIS_ONLY)]
    params = [Parameter(f"axis_tilt_{c}_deg", tilt_deg[j], float(tilt_std_deg[j]), "deg") for j, c in enumerate("xy")]
    params += [Parameter(f"axis_{c}", float(fit.axis[j]), None, "1") for j, c in enumerate("xyz")]
    axis_std_deg = float(np.hypot(*tilt_std_deg))
    notes = [*frame_notes,
             f"axis_tilt_x_deg / axis_tilt_y_deg: how far the found axis leans from the drawn axis toward "
             f"{np.round(e[0], 3).tolist()} / {np.round(e[1], 3).tolist()} (flange frame; for a tool drawn along the "
             "flange's z, toward x / toward y); the tool frame's rx, ry are a rotation vector's (a lean toward x is a "
             "turn about y)"]
    extra = {"axis": fit.axis.tolist(), "axis_std_deg": axis_std_deg,
             "axis_off_drawing_deg": float(np.degrees(np.arccos(np.clip(fit.axis @ drawn, -1.0, 1.0)))),
             "expected_axis_error_deg": float(np.rad2deg(design.expected_error)),
             "design_condition": design.condition, "contact_reach_mm": reach_mm,
             "n_touches": int(len(dataset)), "n_crossings": n,
             "rotation_about_axis": f"kept from {ref.source}", "position": f"kept from {ref.source}"}
    return Result(name, params, fit.residuals_mm, float(expected), fit.condition, gate_list, tool_frame=frame,
                  notes=notes, extra=extra, determines=tool_frame.AXIS_ONLY)
