"""``tcp-laser``: the tool centre point and axis from sweeps through a crossed-beam light barrier.

The plan, from the cell file alone: the TCP set to the tool as drawn, then for each of a
few orientations of the tool (upright at two turns about the vertical, and tilted along
one beam, then the other, every change of orientation a turn about the tip):

* an approach along the tool's axis onto the beams' crossing, down until the tip blocks
  both beams and back up until both clear (the tool's length);
* horizontal sweeps through both beams, each followed by the same sweep back: upright at
  two heights along the tool (distances behind the tip where the beams cut its body: the
  axis), tilted at one (near the tip).

Every edge is recorded with the flange pose and velocity interpolated in the robot's
state stream at the edge's device timestamp. The fit (:mod:`cellcal.solvers.tool_frames.tcp_laser`)
finds the tip and the axis in the flange frame, where the beams really are, their
widths, and the trigger latency: each sweep's return crosses the same place the other way,
so the latency is measured, not assumed. The tool frame written has the tip and the axis
found; its turn about the axis (not measured: a round tool has none) is kept from the
controller's frame before the run (:mod:`.tool_frame`). Tilting the tool is what separates the height of
the beams from the length of the tool; turning it, the tool's offset from where the beams
are. The arm's repeatability, drawn afresh for every motion, is what limits the result,
so the plan spends its time on many short motions.

Section ``tcp_laser`` of the cell file (all optional)::

    speed_mm_s: 40          # sweeps and approaches
    heights_mm: [12, 90]    # upright sweeps: where the beams cut the tool, behind its tip
    tilted_height_mm: 12    # tilted sweeps (default: the lowest of heights_mm)
    tilt_deg: 45            # tilt of the tilted orientations
    tilts: 4                # how many, along one beam, the other, then the opposite ways
    spins_deg: [180, 0]     # turns of the upright tool about the vertical (end on 0: the
                            # arm returns home without unwinding its wrist)
    search_mm: 3            # how far the tool and beams may be off their drawing
    repeatability_mm: 0.02  # the arm's (one axis, 1 sigma): the expected noise
    trigger_jitter_ms: 0.3  # the barrier's timestamp noise (1 sigma)
    max_latency_ms: 20      # a latency beyond this fails the result
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.reader import Section
from cellcal.config.robot_files import load_robot
from cellcal.solvers.geometry import se3
from cellcal.solvers.tool_frames import tcp_laser as laser
from cellcal.solvers.geometry.inverse import tcp_poses
from cellcal.routines.framework import gates, tool_frame
from cellcal.routines.framework.base import Devices, Gate, Move, Parameter, Result, Routine, RoutineError, drawn_tool
from cellcal.routines.framework.drawing import beam_crossings
from cellcal.routines.framework.records import Dataset

EDGE_WAIT_S = 0.2  # after the last motion, for edges still on their way
APPROACH_SLACK_MM = 1.0  # beyond the search margin and the speed ramp, so edges fall at constant speed
MAX_STD = {"mm": 0.1, "rad": np.deg2rad(0.1), "ms": 1.0}  # a parameter this uncertain is not determined


@dataclass(frozen=True)
class TcpLaserOptions:
    speed_mm_s: float
    heights_mm: tuple[float, ...]
    tilted_height_mm: float
    tilt_deg: float
    tilts: int
    spins_deg: tuple[float, ...]
    search_mm: float
    repeatability_mm: float
    trigger_jitter_ms: float
    max_latency_ms: float


@dataclass(frozen=True)
class Step:
    """What one planned motion is for: the edges each beam must show during it, in order."""

    kind: str  # "travel", "approach" or "sweep"
    orientation: int = -1
    height_mm: float = float("nan")
    direction: int = 0
    expect: tuple[str, ...] = ()


class TcpLaser(Routine):
    name = "tcp-laser"
    section = "tcp_laser"
    selector = 1
    needs = ("robot", "trigger")
    text_columns = ("kind", "edge")
    nan_columns = ("height_mm",)  # travel and approach moves are at no height along the tool

    @classmethod
    def read_options(cls, section: Section, cell: Cell) -> TcpLaserOptions:
        if cell.tool is None:
            section.fail(None, "tcp-laser needs the tool as drawn in [tool]")
        if len(cell.beams) != 2:
            section.fail(None, f"tcp-laser needs two crossed beams in [beams], the file has {len(cell.beams)}")
        if abs(float(cell.beams[0].direction @ cell.beams[1].direction)) > np.cos(np.deg2rad(30)):
            section.fail(None, "the two beams of [beams] must cross at 30 deg or more")
        top = min(cell.limits["tcp_speed_m_s"] * 1e3, 250.0)
        speed = section.number("speed_mm_s", 40.0, above=0.0, high=top)
        tool_mm = cell.tool.length_m * 1e3
        heights = section.sequence("heights_mm", [12.0, 90.0])
        low, high = cell.tool.radius_m * 1e3 + 5.0, tool_mm - 5.0
        if len(heights) < 2 or not all(isinstance(h, (int, float)) and not isinstance(h, bool) and low <= h <= high
                                       for h in heights) or max(heights) - min(heights) < 10.0:
            section.fail("heights_mm", f"{heights!r}: two or more distances behind the tip, in "
                                       f"{low:g}..{high:g} mm (on the tool's body), spread by 10 mm or more")
        spins = section.sequence("spins_deg", [180.0, 0.0], nonempty=True)
        if not all(isinstance(s, (int, float)) and not isinstance(s, bool) and -180 <= s <= 180 for s in spins):
            section.fail("spins_deg", f"{spins!r}: turns in -180..180 deg")
        options = TcpLaserOptions(
            speed, tuple(float(h) for h in heights), section.number("tilted_height_mm", min(heights), low=low, high=high),
            section.number("tilt_deg", 45.0, low=0.0, high=45.0), section.integer("tilts", 4, low=1, high=8),
            tuple(float(s) for s in spins), section.number("search_mm", 3.0, above=0.0, high=20.0),
            section.number("repeatability_mm", 0.02, above=0.0, high=1.0),
            section.number("trigger_jitter_ms", 0.3, low=0.0, high=10.0),
            section.number("max_latency_ms", 20.0, above=0.0, high=200.0))
        section.done()
        if options.tilt_deg < 5.0:  # tilts are what tell the beams' height from the tool's length
            section.fail("tilt_deg", f"{options.tilt_deg:g} is too small to separate the beams' height "
                                     "from the tool's length (5 deg or more)")
        return options

    # -- plan ------------------------------------------------------------------------

    def steps(self) -> list[tuple[Move, Step]]:
        """Every motion and what it is for, from the cell file alone."""
        cell, o = self.cell, self.options
        tool = cell.tool
        r_tool = tool.radius_m
        points = np.array([b.point_m for b in cell.beams])
        dirs = np.array([b.direction for b in cell.beams])
        reach = np.array([r_tool + b.radius_m for b in cell.beams])
        cross = laser.crossing_point(points, dirs)
        home = tcp_poses(load_robot(cell.robot), cell.home_q_rad, tool.tcp_pose)[0]
        r_home = se3.rotvec_to_matrix(home[3:])
        travel_v, accel = cell.limits["tcp_speed_m_s"], cell.limits["tcp_accel_m_s2"]
        speed = o.speed_mm_s / 1e3
        ramp = speed**2 / (2 * accel)
        margin = o.search_mm / 1e3
        slack = APPROACH_SLACK_MM / 1e3
        steps: list[tuple[Move, Step]] = []

        def go(label, rotation, position, step=Step("travel"), v=travel_v):
            pose = np.concatenate([position, se3.matrix_to_rotvec(rotation)])
            steps.append((Move.linear(label, pose, v, accel), step))

        spun = 0.0
        for k, (spin_deg, tilted, turn) in enumerate(self.orientations()):
            rot = turn @ r_home
            # turns of more than 90 deg go through upright waypoints, so the wrist turns the way meant
            ways = int(np.ceil(abs(spin_deg - spun) / 90.0 - 1e-9))
            for w in range(1, ways):
                way = se3.rot("z", np.deg2rad(spun + (spin_deg - spun) * w / ways)) @ r_home
                go(f"turning ({k})", way, cross + (r_tool - float(np.max(reach)) - margin - ramp - slack) * way[:, 2])
            spun = spin_deg
            u = rot[:, 2]  # the drawn tool axis in the base frame, toward the tip
            sweep, worst = laser.sweep_direction(u, dirs)
            half = float(np.max((reach + margin) / worst)) + ramp + slack
            # the tip along the axis where it first blocks a beam through the crossing
            across = np.linalg.norm(np.cross(u, dirs), axis=1)
            first = r_tool - reach / across
            above = cross + (float(np.min(first)) - margin - ramp - slack) * u
            below = cross + (float(np.max(first)) + margin + ramp + slack) * u
            go("to orientation 0" if k == 0 else f"turn to orientation {k}", rot, above)
            go(f"approach {k} down", rot, below, Step("approach", k, direction=1, expect=("blocked",)), speed)
            go(f"approach {k} up", rot, above, Step("approach", k, direction=-1, expect=("cleared",)), speed)
            go(f"aside {k}", rot, above - half * sweep)
            for i, h in enumerate((o.tilted_height_mm,) if tilted else o.heights_mm):
                level = cross + h / 1e3 * u
                go(f"down to {h:g} mm ({k})" if i == 0 else f"to {h:g} mm ({k})", rot, level - half * sweep)
                for sign in (1, -1):
                    go(f"sweep {k} at {h:g} mm {'out' if sign > 0 else 'back'}", rot, level + sign * half * sweep,
                       Step("sweep", k, h, sign, ("blocked", "cleared")), speed)
            go(f"up ({k})", rot, above - half * sweep)
        steps.append((Move.joint("home", cell.home_q_rad, cell.limits["joint_speed_rad_s"],
                                 cell.limits["joint_accel_rad_s2"]), Step("travel")))
        return steps

    def orientations(self) -> list[tuple[float, bool, np.ndarray]]:
        """(turn about the vertical in deg, tilted?, rotation) of each orientation, base frame, about the
        tip, from the home orientation: each upright turn followed by its share of the tilted
        ones (the same turn, the axis tilted along one beam, then the other, then the opposite
        ways)."""
        o = self.options
        d0 = self.cell.beams[0].direction
        start = np.arctan2(d0[1], d0[0])
        out = []
        for i, spin_deg in enumerate(o.spins_deg):
            spin = se3.rot("z", np.deg2rad(spin_deg))
            out.append((spin_deg, False, spin))
            for j in range(i, o.tilts, len(o.spins_deg)):
                psi = start + np.pi / 2 * j + np.pi / 4 * (j // 4)
                tilt = np.deg2rad(o.tilt_deg) * np.array([-np.sin(psi), np.cos(psi), 0.0])
                out.append((spin_deg, True, se3.rotvec_to_matrix(tilt) @ spin))
        return out

    def plan(self) -> list[Move]:
        return [move for move, _ in self.steps()]

    # -- measure ---------------------------------------------------------------------

    def measure(self, devices: Devices, robot, plan: list[Move], progress) -> Dataset:
        planned = self.steps()
        steps = [step for _, step in planned]
        if [m.label for m in plan] != [m.label for m, _ in planned]:
            raise RoutineError("the plan given is not this routine's plan for this cell file")
        if devices.trigger is None:
            raise RoutineError(f"{self.cell.path}: {self.name} needs a trigger in [drivers]")
        tool = self.measuring_tool(robot)
        with drawn_tool(robot, tool):
            devices.trigger.events(0.0)  # edges from before the routine are not its own
            samples = list(robot.samples())[-1:]
            t0 = samples[0].t_s
            starts, events, rows, checked = [], [], [], 0
            wait = self.options.max_latency_ms / 1e3
            for i, (move, step) in enumerate(zip(plan, steps)):
                starts.append(samples[-1].t_s)
                robot.run(move)
                samples += robot.samples(samples[-1].t_s)
                events += devices.trigger.events(0.0)
                # a motion's edges are all in once the clock is past its end by the longest latency
                while checked < i and starts[checked + 1] + wait <= samples[-1].t_s:
                    rows += self._edges_of(checked, events, starts, steps, plan)
                    checked += 1
                if step.kind == "sweep" and step.direction < 0:
                    progress(f"tcp-laser: orientation {step.orientation}, sweeps at {step.height_mm:g} mm done")
            events += devices.trigger.events(max(EDGE_WAIT_S, wait))
            samples += robot.samples(samples[-1].t_s)
            for i in range(checked, len(steps)):
                rows += self._edges_of(i, events, starts, steps, plan)
        return self._dataset(rows, samples, t0, tool)

    def measuring_tool(self, robot) -> np.ndarray:
        """The tool frame the controller is set to while measuring: the tool as drawn (the
        plan's). A check (``tcp-check``) measures at the controller's own frame instead."""
        return self.cell.tool.tcp_pose

    def _edges_of(self, i, events, starts, steps, plan) -> list[tuple]:
        """(motion index, event) of the edges motion `i` saw, checked against what each beam
        must show during it; RoutineError naming the motion and the channel otherwise."""
        step = steps[i]
        if step.kind == "travel":
            return []
        end = starts[i + 1] if i + 1 < len(starts) else np.inf
        channels = [b.channel for b in self.cell.beams]
        seen = sorted((e for e in events if starts[i] < e.t_s <= end and e.channel in channels), key=lambda e: e.t_s)
        for ch in channels:
            kinds = tuple(e.edge.value for e in seen if e.channel == ch)
            if not kinds:
                raise RoutineError(f"{plan[i].label} (motion {i + 1}) saw no edge on beam channel {ch}: "
                                   "is the barrier where [beams] says?")
            if kinds != step.expect:
                raise RoutineError(f"{plan[i].label} (motion {i + 1}) saw edges {', '.join(kinds)} on beam "
                                   f"channel {ch}, expected {', '.join(step.expect)}: something else in the "
                                   "beam, or the barrier not where [beams] says?")
        return [(i, e) for e in seen]

    def _dataset(self, rows, samples, t0, tool) -> Dataset:
        """The edges with the flange at each (from the TCP samples of the controller set to `tool`)."""
        steps = [step for _, step in self.steps()]
        t = np.array([s.t_s for s in samples])
        tcp = np.array([s.tcp_pose for s in samples])
        q = np.array([s.q_rad for s in samples])
        tool = np.asarray(tool, dtype=float)
        r_tool = se3.rotvec_to_matrix(tool[3:])
        cols: dict[str, list] = {k: [] for k in ("move", "orientation", "kind", "height_mm", "direction",
                                                 "speed_m_s", "channel", "edge", "t_s", "flange_x_m", "flange_y_m",
                                                 "flange_z_m", "flange_rx", "flange_ry", "flange_rz",
                                                 "vx_m_s", "vy_m_s", "vz_m_s")}
        for j in range(q.shape[1]):
            cols[f"q{j + 1}_rad"] = []
        for i, e in rows:
            k = int(np.clip(np.searchsorted(t, e.t_s) - 1, 0, len(t) - 2))
            f = (e.t_s - t[k]) / (t[k + 1] - t[k])
            position = tcp[k, :3] + f * (tcp[k + 1, :3] - tcp[k, :3])
            rot = se3.rotvec_to_matrix(tcp[k if f < 0.5 else k + 1, 3:]) @ r_tool.T
            flange = position - rot @ tool[:3]
            velocity = (tcp[k + 1, :3] - tcp[k, :3]) / (t[k + 1] - t[k])
            step = steps[i]
            values = [i, step.orientation, step.kind, step.height_mm, step.direction, self.options.speed_mm_s / 1e3,
                      e.channel, e.edge.value, e.t_s, *flange, *se3.matrix_to_rotvec(rot), *velocity,
                      *(q[k] + f * (q[k + 1] - q[k]))]
            for key, v in zip(cols, values):
                cols[key].append(v)
        columns = {k: np.array(v, dtype=str if k in self.text_columns else float) for k, v in cols.items()}
        o, tool_spec = self.options, self.cell.tool
        meta = {"speed_mm_s": o.speed_mm_s, "heights_mm": list(o.heights_mm), "tilt_deg": o.tilt_deg,
                "tilts": o.tilts, "spins_deg": list(o.spins_deg), "cycle_time_s": float(t[-1] - t0),
                "planned_tool": tool.tolist(), "tool_radius_m": tool_spec.radius_m,
                "tool_length_m": tool_spec.length_m,
                "beams": [{"channel": b.channel, "point_m": b.point_m.tolist(), "direction": b.direction.tolist(),
                           "radius_m": b.radius_m} for b in self.cell.beams],
                "device_time": bool(all(e.device_time for _, e in rows)), "n_moves": len(steps)}
        return Dataset(self.name, columns, meta)

    # -- solve -----------------------------------------------------------------------

    @classmethod
    def solve(cls, dataset, cell: Cell, options: TcpLaserOptions) -> Result:
        meta = dataset.meta
        need = ("planned_tool", "tool_radius_m", "tool_length_m", "beams")
        missing = [k for k in need if k not in meta]
        if missing:
            raise RoutineError(f"{dataset.path}: the dataset's meta lacks {', '.join(missing)}")
        if len(dataset) == 0:
            raise RoutineError(f"{dataset.path}: the dataset has no edges")
        planned = np.asarray(meta["planned_tool"], dtype=float)
        beams = meta["beams"]
        channel_index = {int(b["channel"]): i for i, b in enumerate(beams)}
        unknown = sorted({int(c) for c in dataset["channel"]} - set(channel_index))
        if unknown:
            raise RoutineError(f"{dataset.path}: edges on channels {unknown} of no beam in the dataset's meta")
        r_tool = float(meta["tool_radius_m"]) * 1e3
        geometry = laser.LaserGeometry(
            r_tool, float(meta["tool_length_m"]) * 1e3, planned[:3] * 1e3,
            se3.rotvec_to_matrix(planned[3:])[:, 2],
            np.array([b["point_m"] for b in beams], dtype=float) * 1e3,
            np.array([np.asarray(b["direction"], float) / np.linalg.norm(b["direction"]) for b in beams]),
            np.array([r_tool + float(b["radius_m"]) * 1e3 for b in beams]))
        edges = laser.LaserEdges(
            se3.rotvec_to_matrix(dataset.stack("flange_rx", "flange_ry", "flange_rz")),
            dataset.stack("flange_x_m", "flange_y_m", "flange_z_m") * 1e3,
            dataset.stack("vx_m_s", "vy_m_s", "vz_m_s") * 1e3,
            np.array([channel_index[int(c)] for c in dataset["channel"]]), dataset["move"].astype(int))
        try:
            fit = laser.fit(edges, geometry, options.repeatability_mm, options.trigger_jitter_ms / 1e3)
        except ValueError as exc:
            raise RoutineError(f"{dataset.path}: {exc}") from None
        result = _result(cls.name, fit, geometry, beams, cell, options, meta)
        result.drawing = beam_crossings(
            laser.crossing_offsets(edges, geometry, fit), edges.beam, dataset["edge"],
            np.array([laser.perpendicular_pair(d) for d in geometry.beam_directions]), list(channel_index),
            fit.reach_mm, geometry.beam_points_mm - fit.beam_points_mm)
        return result


def _result(name, fit: laser.LaserFit, geometry, beams, cell: Cell, options: TcpLaserOptions, meta) -> Result:
    ref = tool_frame.reference(meta.get("tool_frame_before"), np.asarray(meta["planned_tool"], dtype=float))
    frame, frame_notes = tool_frame.compose(tool_frame.TIP_AND_AXIS, ref, tip_m=fit.tip_mm / 1e3, axis=fit.axis)
    e1, e2 = laser.axis_pair(geometry.axis)
    tilt = [float(np.degrees(np.arctan2(fit.axis @ e, fit.axis @ geometry.axis))) for e in (e1, e2)]
    std = dict(zip(fit.names, fit.std))
    params = [Parameter(f"tcp_{c}_mm", float(fit.tip_mm[j]), float(fit.tip_std_mm[j]), "mm")
              for j, c in enumerate("xyz")]
    params += [Parameter(f"axis_tilt_{c}_deg", tilt[j], float(np.degrees(std[f"axis_tilt_{c}_rad"])), "deg")
               for j, c in enumerate("xy")]
    params.append(Parameter("latency_ms", fit.latency_s * 1e3, fit.latency_std_s * 1e3, "ms"))
    beam_report = []
    for i, b in enumerate(beams):
        ch = int(b["channel"])
        off = fit.x[5 + 2 * i:7 + 2 * i]
        params += [Parameter(f"beam{ch}_across_mm", float(off[0]), float(std[f"beam{i}_across_mm"]), "mm"),
                   Parameter(f"beam{ch}_up_mm", float(off[1]), float(std[f"beam{i}_up_mm"]), "mm"),
                   Parameter(f"beam{ch}_half_width_mm", float(fit.reach_mm[i] - geometry.tool_radius_mm),
                             float(std[f"beam{i}_reach_mm"]), "mm")]
        beam_report.append({"channel": ch, "point_mm": fit.beam_points_mm[i].tolist(),
                            "off_file_mm": float(np.linalg.norm(off)),
                            "half_width_mm": float(fit.reach_mm[i] - geometry.tool_radius_mm)})
    undetermined = list(fit.undetermined) + [
        n for n, u, s in zip(fit.names, fit.units, fit.std) if n not in fit.undetermined and not s <= MAX_STD[u]]
    latency_ms, latency_std_ms = fit.latency_s * 1e3, fit.latency_std_s * 1e3
    latency_ok = bool(-3 * latency_std_ms <= latency_ms <= options.max_latency_ms)
    gate_list = [
        gates.residual(float(np.sqrt(np.mean(fit.residuals_mm**2))), float(np.sqrt(np.mean(fit.sigma_mm**2)))),
        gates.conditioning(fit.condition), gates.identifiability(undetermined),
        gates.plausible_tool(frame, cell.tool, determines=tool_frame.TIP_AND_AXIS),
        gates.agrees_with_previous(frame, meta.get("tool_frame_before"), determines=tool_frame.TIP_AND_AXIS),
        Gate("latency", latency_ok, latency_ms, options.max_latency_ms,
             f"trigger latency {latency_ms:.3f} +- {latency_std_ms:.3f} ms"
             + (f" is within 0..{options.max_latency_ms:g} ms" if latency_ok else
                f" is outside 0..{options.max_latency_ms:g} ms: are the barrier's and the robot's clocks the same?"))]
    notes = [*frame_notes,
             f"axis_tilt_x_deg / axis_tilt_y_deg: how far the found axis leans from the drawn axis toward "
             f"{np.round(e1, 3).tolist()} / {np.round(e2, 3).tolist()} (flange frame; for a tool drawn along the "
             "flange's z, toward x / toward y); the tool frame's rx, ry are a rotation vector's (a lean toward x is a "
             "turn about y)",
             f"the tool radius is taken from [tool] ({geometry.tool_radius_mm:g} mm): the barrier measures only "
             "the tool radius plus the beam's half width",
             "the beams' directions are taken from [beams]; their positions are fitted"]
    if not fit.success:
        notes.append(f"the fit did not converge: {fit.message}")
    extra = {"latency_ms": latency_ms, "latency_std_ms": latency_std_ms,
             "tcp_std_mm": float(np.linalg.norm(fit.tip_std_mm)), "axis_std_deg": fit.axis_std_deg,
             "speed_mm_s": float(meta.get("speed_mm_s", options.speed_mm_s)), "n_edges": int(len(fit.residuals_mm)),
             "beams": beam_report, "rotation_about_axis": f"kept from {ref.source}"}
    return Result(name, params, fit.residuals_mm, float(np.sqrt(np.mean(fit.sigma_mm**2))), fit.condition, gate_list,
                  tool_frame=frame, notes=notes, extra=extra, determines=tool_frame.TIP_AND_AXIS)
