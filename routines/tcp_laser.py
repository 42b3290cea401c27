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
controller's frame before the run (:mod:`.framework.tool_frame`). Tilting the tool is what separates the height of
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
from cellcal.solvers.tool_frames import tcp_laser as laser
from cellcal.routines.framework import gates, tool_frame
from cellcal.routines.framework.base import Devices, Gate, Move, Parameter, Result, Routine, RoutineError
from cellcal.routines.framework.drawing import beam_crossings
from cellcal.routines.framework.records import Dataset
from cellcal.routines.light_barrier import NAN_COLUMNS, TEXT_COLUMNS, BarrierSweeps, SweepPlan, barrier_data

MAX_STD = {"mm": 0.1, "rad": np.deg2rad(0.1), "ms": 1.0}  # a parameter this uncertain is not determined


@dataclass(frozen=True)
class TcpLaserOptions(SweepPlan):
    """The sweeps (upright and tilted), and what the fit needs besides."""

    repeatability_mm: float
    trigger_jitter_ms: float


class TcpLaser(Routine):
    name = "tcp-laser"
    section = "tcp_laser"
    selector = 1
    needs = ("robot", "trigger")
    text_columns = TEXT_COLUMNS
    nan_columns = NAN_COLUMNS

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
        tilted = section.number("tilted_height_mm", min(heights), low=low, high=high)
        tilt_deg = section.number("tilt_deg", 45.0, low=0.0, high=45.0)
        tilts = section.integer("tilts", 4, low=1, high=8)
        search = section.number("search_mm", 3.0, above=0.0, high=20.0)
        repeat = section.number("repeatability_mm", 0.02, above=0.0, high=1.0)
        jitter = section.number("trigger_jitter_ms", 0.3, low=0.0, high=10.0)
        latency = section.number("max_latency_ms", 20.0, above=0.0, high=200.0)
        options = TcpLaserOptions(speed, tuple(float(h) for h in heights), tilted, tilt_deg, tilts,
                                  tuple(float(s) for s in spins), search, latency, repeat, jitter)
        section.done()
        if options.tilt_deg < 5.0:  # tilts are what tell the beams' height from the tool's length
            section.fail("tilt_deg", f"{options.tilt_deg:g} is too small to separate the beams' height "
                                     "from the tool's length (5 deg or more)")
        return options

    def __init__(self, cell: Cell, options: TcpLaserOptions):
        super().__init__(cell, options)
        self.sweeps = BarrierSweeps(self.name, cell, lambda: self.robot_model, options)

    def plan(self) -> list[Move]:
        return self.sweeps.moves()

    def measure(self, devices: Devices, robot, plan: list[Move], progress) -> Dataset:
        """The sweeps with the controller on the tool as drawn (the plan's)."""
        return self.sweeps.measure(devices, robot, plan, progress, self.cell.tool.tcp_pose, self.tool_frame_before)

    # -- solve -----------------------------------------------------------------------

    @classmethod
    def solve(cls, dataset, cell: Cell, options: TcpLaserOptions) -> Result:
        geometry, edges, beams = barrier_data(dataset)
        meta = dataset.meta
        try:
            fit = laser.fit(edges, geometry, options.repeatability_mm, options.trigger_jitter_ms / 1e3)
        except ValueError as exc:
            raise RoutineError(f"{dataset.path}: {exc}") from None
        result = _result(cls.name, fit, geometry, beams, cell, options, meta)
        result.drawing = beam_crossings(
            laser.crossing_offsets(edges, geometry, fit), edges.beam, dataset["edge"],
            np.array([laser.perpendicular_pair(d) for d in geometry.beam_directions]),
            [int(b["channel"]) for b in beams], fit.reach_mm, geometry.beam_points_mm - fit.beam_points_mm)
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
