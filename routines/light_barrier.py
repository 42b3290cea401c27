"""Sweeps through a crossed-beam light barrier, as ``tcp-laser`` and ``tcp-check`` both move
and record them, and the dataset -> geometry step both solve from.

:class:`BarrierSweeps` plans the motions from the cell file and a :class:`SweepPlan` (the
tool's orientations: upright at each turn about the vertical, and tilted ones for a
calibration; at each an approach along the tool's axis onto the beams' crossing and back,
then horizontal sweeps through both beams and back at heights along the tool), moves through
them recording every edge with the flange pose and velocity interpolated in the robot's state
stream at the edge's device timestamp, and checks each motion saw the edges it must.
:func:`barrier_data` turns such a dataset into the solver's geometry and edges (mm).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from cellcal.config.cells import Cell
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.inverse import tcp_poses
from cellcal.solvers.tool_frames import tcp_laser as laser
from cellcal.routines.framework.base import Devices, Move, RoutineError, drawn_tool
from cellcal.routines.framework.records import Dataset

EDGE_WAIT_S = 0.2  # after the last motion, for edges still on their way
APPROACH_SLACK_MM = 1.0  # beyond the search margin and the speed ramp, so edges fall at constant speed
TEXT_COLUMNS = ("kind", "edge")
NAN_COLUMNS = ("height_mm",)  # travel and approach moves are at no height along the tool


@dataclass(frozen=True)
class SweepPlan:
    """What the sweeps are: their speed, the heights along the tool (behind its tip) where the
    beams cut it upright and tilted, the tilted orientations (``tilts`` of ``tilt_deg``; none for
    a check), the turns about the vertical, how far off the drawing the tool and the beams may be,
    and the longest trigger latency (how long a motion's edges may take to arrive)."""

    speed_mm_s: float
    heights_mm: tuple[float, ...]
    tilted_height_mm: float
    tilt_deg: float
    tilts: int
    spins_deg: tuple[float, ...]
    search_mm: float
    max_latency_ms: float


@dataclass(frozen=True)
class Step:
    """What one planned motion is for: the edges each beam must show during it, in order."""

    kind: str  # "travel", "approach" or "sweep"
    orientation: int = -1
    height_mm: float = float("nan")
    direction: int = 0
    expect: tuple[str, ...] = ()


class BarrierSweeps:
    """The sweeps of routine `name` on `cell`, planned once, when first asked, with robot a's
    kinematic model (`robot_model()`: the run's). `missed(error)`: what a motion that did not
    see the edges it must raises (the error itself for a calibration; a check's alarm)."""

    def __init__(self, name: str, cell: Cell, robot_model: Callable[[], object], sweep: SweepPlan,
                 missed: Callable[[RoutineError], Exception] = lambda error: error):
        self.name, self.cell, self.robot_model, self.sweep, self.missed = name, cell, robot_model, sweep, missed
        self._steps: list[tuple[Move, Step]] | None = None

    @property
    def steps(self) -> list[tuple[Move, Step]]:
        """Every motion and what it is for, from the cell file alone (planned once)."""
        if self._steps is None:
            self._steps = self._planned()
        return self._steps

    def moves(self) -> list[Move]:
        return [move for move, _ in self.steps]

    def _planned(self) -> list[tuple[Move, Step]]:
        cell, o = self.cell, self.sweep
        tool = cell.tool
        r_tool = tool.radius_m
        points = np.array([b.point_m for b in cell.beams])
        dirs = np.array([b.direction for b in cell.beams])
        reach = np.array([r_tool + b.radius_m for b in cell.beams])
        cross = laser.crossing_point(points, dirs)
        home = tcp_poses(self.robot_model(), cell.home_q_rad, tool.tcp_pose)[0]
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
            across_beams, worst = laser.sweep_direction(u, dirs)
            half = float(np.max((reach + margin) / worst)) + ramp + slack
            # the tip along the axis where it first blocks a beam through the crossing
            across = np.linalg.norm(np.cross(u, dirs), axis=1)
            first = r_tool - reach / across
            above = cross + (float(np.min(first)) - margin - ramp - slack) * u
            below = cross + (float(np.max(first)) + margin + ramp + slack) * u
            go("to orientation 0" if k == 0 else f"turn to orientation {k}", rot, above)
            go(f"approach {k} down", rot, below, Step("approach", k, direction=1, expect=("blocked",)), speed)
            go(f"approach {k} up", rot, above, Step("approach", k, direction=-1, expect=("cleared",)), speed)
            go(f"aside {k}", rot, above - half * across_beams)
            for i, h in enumerate((o.tilted_height_mm,) if tilted else o.heights_mm):
                level = cross + h / 1e3 * u
                go(f"down to {h:g} mm ({k})" if i == 0 else f"to {h:g} mm ({k})", rot, level - half * across_beams)
                for sign in (1, -1):
                    go(f"sweep {k} at {h:g} mm {'out' if sign > 0 else 'back'}", rot, level + sign * half * across_beams,
                       Step("sweep", k, h, sign, ("blocked", "cleared")), speed)
            go(f"up ({k})", rot, above - half * across_beams)
        steps.append((Move.joint("home", cell.home_q_rad, cell.limits["joint_speed_rad_s"],
                                 cell.limits["joint_accel_rad_s2"]), Step("travel")))
        return steps

    def orientations(self) -> list[tuple[float, bool, np.ndarray]]:
        """(turn about the vertical in deg, tilted?, rotation) of each orientation, base frame, about the
        tip, from the home orientation: each upright turn followed by its share of the tilted
        ones (the same turn, the axis tilted along one beam, then the other, then the opposite
        ways)."""
        o = self.sweep
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

    def measure(self, devices: Devices, robot, plan: list[Move], progress, tool, before=None) -> Dataset:
        """Move through `plan` (this plan's moves) with the controller set to `tool`, and record
        every edge; `before`: the controller's frame before (given back afterwards), when known."""
        planned = self.steps
        steps = [step for _, step in planned]
        if [m.label for m in plan] != [m.label for m, _ in planned]:
            raise RoutineError("the plan given is not this routine's plan for this cell file")
        if devices.trigger is None:
            raise RoutineError(f"{self.cell.path}: {self.name} needs a trigger in [drivers]")
        with drawn_tool(robot, tool, before):
            devices.trigger.events(0.0)  # edges from before the routine are not its own
            samples = list(robot.samples())[-1:]
            t0 = samples[0].t_s
            starts, events, rows, checked = [], [], [], 0
            wait = self.sweep.max_latency_ms / 1e3
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
                raise self.missed(RoutineError(f"{plan[i].label} (motion {i + 1}) saw no edge on beam channel "
                                               f"{ch}: is the barrier where [beams] says?"))
            if kinds != step.expect:
                raise self.missed(RoutineError(
                    f"{plan[i].label} (motion {i + 1}) saw edges {', '.join(kinds)} on beam channel {ch}, expected "
                    f"{', '.join(step.expect)}: something else in the beam, or the barrier not where [beams] says?"))
        return [(i, e) for e in seen]

    def _dataset(self, rows, samples, t0, tool) -> Dataset:
        """The edges with the flange at each (from the TCP samples of the controller set to `tool`)."""
        steps = [step for _, step in self.steps]
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
            values = [i, step.orientation, step.kind, step.height_mm, step.direction, self.sweep.speed_mm_s / 1e3,
                      e.channel, e.edge.value, e.t_s, *flange, *se3.matrix_to_rotvec(rot), *velocity,
                      *(q[k] + f * (q[k + 1] - q[k]))]
            for key, v in zip(cols, values):
                cols[key].append(v)
        columns = {k: np.array(v, dtype=str if k in TEXT_COLUMNS else float) for k, v in cols.items()}
        o, tool_spec = self.sweep, self.cell.tool
        meta = {"speed_mm_s": o.speed_mm_s, "heights_mm": list(o.heights_mm), "tilt_deg": o.tilt_deg,
                "tilts": o.tilts, "spins_deg": list(o.spins_deg), "cycle_time_s": float(t[-1] - t0),
                "planned_tool": tool.tolist(), "tool_radius_m": tool_spec.radius_m,
                "tool_length_m": tool_spec.length_m,
                "beams": [{"channel": b.channel, "point_m": b.point_m.tolist(), "direction": b.direction.tolist(),
                           "radius_m": b.radius_m} for b in self.cell.beams],
                "device_time": bool(all(e.device_time for _, e in rows)), "n_moves": len(steps)}
        return Dataset(self.name, columns, meta)


def barrier_data(dataset, points_m: dict | None = None) -> tuple[laser.LaserGeometry, laser.LaserEdges, list[dict]]:
    """The solver's geometry and edges (mm) of a sweeps dataset, and its beams (the dataset's
    meta: [beams] as the run had them), each beam's point replaced by `points_m` (channel ->
    point, m) where given. RoutineError when the dataset cannot be solved."""
    meta = dataset.meta
    missing = [k for k in ("planned_tool", "tool_radius_m", "tool_length_m", "beams") if k not in meta]
    if missing:
        raise RoutineError(f"{dataset.path}: the dataset's meta lacks {', '.join(missing)}")
    if len(dataset) == 0:
        raise RoutineError(f"{dataset.path}: the dataset has no edges")
    planned = np.asarray(meta["planned_tool"], dtype=float)
    beams = [dict(b) for b in meta["beams"]]
    for b in beams:
        if points_m and int(b["channel"]) in points_m:
            b["point_m"] = np.asarray(points_m[int(b["channel"])], dtype=float).tolist()
    channel_index = {int(b["channel"]): i for i, b in enumerate(beams)}
    unknown = sorted({int(c) for c in dataset["channel"]} - set(channel_index))
    if unknown:
        raise RoutineError(f"{dataset.path}: edges on channels {unknown} of no beam in the dataset's meta")
    r_tool = float(meta["tool_radius_m"]) * 1e3
    geometry = laser.LaserGeometry(
        r_tool, float(meta["tool_length_m"]) * 1e3, planned[:3] * 1e3, se3.rotvec_to_matrix(planned[3:])[:, 2],
        np.array([b["point_m"] for b in beams], dtype=float) * 1e3,
        np.array([np.asarray(b["direction"], float) / np.linalg.norm(b["direction"]) for b in beams]),
        np.array([r_tool + float(b["radius_m"]) * 1e3 for b in beams]))
    edges = laser.LaserEdges(
        se3.rotvec_to_matrix(dataset.stack("flange_rx", "flange_ry", "flange_rz")),
        dataset.stack("flange_x_m", "flange_y_m", "flange_z_m") * 1e3,
        dataset.stack("vx_m_s", "vy_m_s", "vz_m_s") * 1e3,
        np.array([channel_index[int(c)] for c in dataset["channel"]]), dataset["move"].astype(int))
    return geometry, edges, beams
