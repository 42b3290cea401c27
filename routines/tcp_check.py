"""``tcp-check``: is the tool where the controller thinks it is? A few crossings of the
crossed-beam light barrier at the tool's stored frame, then a verdict against the tool's
tolerance bands (``[tool.bands]`` of the cell file, :class:`cellcal.config.cells.Bands`).

The check moves as :mod:`.tcp_laser` does, with the controller on its *own* tool frame (the
frame it holds for the tool: the last one written back; the tool as drawn when it holds none,
so a change is never reported against the bare flange; the service sets the last frame it
wrote on a controller that lost it, before the run) and with fewer motions: the tool upright
only, an approach along its axis onto the beams' crossing and back, and at each of
``heights_mm`` a sweep through both beams and back, at each of ``spins_deg`` (turns about
the vertical). The fit (:mod:`cellcal.solvers.tool_frames.tcp_check`) finds the tip, and the
axis where the sweeps cut the tool at two heights, relative to that frame, with standard
deviations that include the uncertainty of the beams' positions.

What it determines, and what it cannot:

* the **tip** (``determines`` has ``tip``) when every component's uncertainty is small
  against the inner band: 3 sigma along its worst direction <= ``inner_mm``. Upright sweeps
  cannot tell a tip that moved from beams that moved, so the beams' positions must be known:
  ``beams`` below (where the last full ``tcp-laser`` calibration found them, its result's
  ``beams[].point_mm``; uncertainty ``beam_std_mm``, default 0.01 mm) or else ``[beams]`` as
  installed (default uncertainty 0.5 mm, a fixture's placement: then the tip is *not*
  determined, and the result says so). A beam's error goes straight into the tip: 0.1 mm
  wrong is a 0.1 mm shift reported. Two ``spins_deg`` (0 and 180) fit the beams' horizontal
  position, so the tip's x and y no longer depend on it (its length along the axis still
  does, on the beams' height);
* the **axis** (``axis``) with two ``heights_mm`` or more, when 3 sigma of its tilt <=
  ``inner_deg``. The beams' positions do not enter it. With one height the axis is held at
  the stored frame's, and a tilt of the tool by d shows at the tip as (height x d).

A plan that determines neither (at the stated ``repeatability_mm``) is refused before
anything moves, saying why; so is a check with nothing to judge against yet
(:class:`CalibrateFirst`, panel code 15): no beam calibration for the cell (no ``beams``
here, none from a tcp-laser in the store, and no ``beam_std_mm`` saying ``[beams]`` were
measured in place).

Verdicts (``verdict`` in the JSON; the bands apply only to what was determined), decided from
the numbers alone by :func:`cellcal.solvers.tool_frames.verdict.check_verdict`:

* ``ok``: every determined change within the inner band; nothing is written;
* ``corrected``: a determined change beyond the inner band, none beyond the outer band,
  every gate passed: the measured frame is written back (what was determined; the rest kept
  from the stored frame, :mod:`.framework.tool_frame`);
* ``alarm``: a change beyond the outer band (also of what was not determined well enough,
  when even its 3-sigma lower bound is beyond it), a failed gate (the data do not say what
  changed), or a sweep that did not see the beams where it should (:class:`CheckAlarm`:
  the tool is more than ``search_mm`` off); nothing is written, the note says what it saw.

Section ``tcp_check`` of the cell file (all optional)::

    speed_mm_s: 40          # sweeps and approaches
    heights_mm: [12, 90]    # where the beams cut the tool, behind its tip (two: the axis too)
    spins_deg: [0]          # turns of the upright tool about the vertical (two: beams' x, y fitted)
    search_mm: 3            # how far the tool may be off its stored frame (beyond: alarm)
    repeatability_mm: 0.02  # the arm's (one axis, 1 sigma)
    trigger_jitter_ms: 0.3  # the barrier's timestamp noise (1 sigma)
    max_latency_ms: 20      # a latency beyond this fails the result
    beams:                  # where the last tcp-laser found the beams (else [beams] as installed)
      - {channel: 0, point_mm: [-691.4, -174.1, 450.0]}
      - {channel: 1, point_mm: [-691.4, -174.1, 450.0]}
    beam_std_mm: 0.01       # their uncertainty (1 sigma; default 0.01 with beams, else 0.5)
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.reader import Section
from cellcal.solvers.tool_frames import tcp_check as check
from cellcal.solvers.tool_frames.verdict import Measured, Verdict, check_verdict, determined
from cellcal.routines.framework import gates, tool_frame
from cellcal.routines.framework.base import (CalibrateFirst, CheckAlarm, Devices, Gate, Move, Parameter,
                                             PlanPromise, PlanRefused, Result, Routine, RoutineError)
from cellcal.routines.framework.context import BeamPoint
from cellcal.routines.framework.records import Dataset
from cellcal.routines.light_barrier import NAN_COLUMNS, TEXT_COLUMNS, BarrierSweeps, SweepPlan, barrier_data

INSTALLED_BEAM_STD_MM = 0.5  # the beams as installed ([beams]): a fixture's placement
MEASURED_BEAM_STD_MM = 0.01  # the beams as a tcp-laser calibration found them
MAX_BEAM_OFF_MM = 20.0  # a beam point this far off its beam of [beams] is not one a calibration found


@dataclass(frozen=True)
class TcpCheckOptions:
    speed_mm_s: float
    heights_mm: tuple[float, ...]
    spins_deg: tuple[float, ...]
    search_mm: float
    repeatability_mm: float
    trigger_jitter_ms: float
    max_latency_ms: float
    beams: tuple[BeamPoint, ...]  # where the beams are known to be (m), by channel; () = [beams] as installed
    stated_beam_std_mm: float | None  # beam_std_mm as the section states it; None: by where the beams are from

    @property
    def beam_std_mm(self) -> float:
        """The beams' uncertainty (1 sigma): as stated, else by what the beams are."""
        if self.stated_beam_std_mm is not None:
            return self.stated_beam_std_mm
        return MEASURED_BEAM_STD_MM if self.beams else INSTALLED_BEAM_STD_MM


def checked_beams(points_m: dict, cell: Cell) -> tuple[BeamPoint, ...]:
    """The beams where they are known to be (channel -> point, m), each of ``[beams]`` once and
    near its line; ValueError saying what is wrong."""
    channels = {b.channel for b in cell.beams}
    for ch, point in points_m.items():
        beam = next((b for b in cell.beams if b.channel == ch), None)
        if beam is None:
            raise ValueError(f"channel {ch}: each beam of [beams] (channels {sorted(channels)}) once")
        off = (np.asarray(point, dtype=float) - beam.point_m) * 1e3
        off -= (off @ beam.direction) * beam.direction
        if np.linalg.norm(off) > MAX_BEAM_OFF_MM:
            raise ValueError(f"channel {ch}: point_mm is {np.linalg.norm(off):.1f} mm off the beam of [beams] "
                             f"(at most {MAX_BEAM_OFF_MM:g} mm): is it a tcp-laser result's point_mm, in mm?")
    if set(points_m) != channels:
        raise ValueError(f"give every beam of [beams] (channels {sorted(channels)}), not only {sorted(points_m)}")
    return tuple(BeamPoint(ch, np.asarray(points_m[ch], dtype=float)) for ch in sorted(points_m))


class TcpCheck(Routine):
    name = "tcp-check"
    section = "tcp_check"
    selector = 7
    needs = ("robot", "trigger")
    text_columns = TEXT_COLUMNS
    nan_columns = NAN_COLUMNS

    @classmethod
    def read_options(cls, section: Section, cell: Cell) -> TcpCheckOptions:
        if cell.tool is None:
            section.fail(None, "tcp-check needs the tool as drawn in [tool]")
        if len(cell.beams) != 2:
            section.fail(None, f"tcp-check needs two crossed beams in [beams], the file has {len(cell.beams)}")
        if abs(float(cell.beams[0].direction @ cell.beams[1].direction)) > np.cos(np.deg2rad(30)):
            section.fail(None, "the two beams of [beams] must cross at 30 deg or more")
        top = min(cell.limits["tcp_speed_m_s"] * 1e3, 250.0)
        speed = section.number("speed_mm_s", 40.0, above=0.0, high=top)
        low, high = cell.tool.radius_m * 1e3 + 5.0, cell.tool.length_m * 1e3 - 5.0
        heights = section.sequence("heights_mm", [12.0, 90.0], nonempty=True)
        if not (len(heights) <= 4 and all(isinstance(h, (int, float)) and not isinstance(h, bool)
                                          and low <= h <= high for h in heights)):
            section.fail("heights_mm", f"{heights!r}: one to four distances behind the tip, in {low:g}..{high:g} mm "
                                       "(on the tool's body)")
        if len(heights) > 1 and max(heights) - min(heights) < 10.0:
            section.fail("heights_mm", f"{heights!r}: two heights must be 10 mm or more apart to tell the axis")
        spins = section.sequence("spins_deg", [0.0], nonempty=True)
        if not (len(spins) <= 2 and all(isinstance(s, (int, float)) and not isinstance(s, bool) and -180 <= s <= 180
                                        for s in spins)):
            section.fail("spins_deg", f"{spins!r}: one or two turns in -180..180 deg")
        if len(spins) == 2 and abs(abs(spins[0] - spins[1]) - 180.0) > 45.0:
            section.fail("spins_deg", f"{spins!r}: two turns must be 135..225 deg apart to tell the beams' position "
                                      "from the tip's")
        search = section.number("search_mm", 3.0, above=0.0, high=20.0)
        repeat = section.number("repeatability_mm", 0.02, above=0.0, high=1.0)
        jitter = section.number("trigger_jitter_ms", 0.3, low=0.0, high=10.0)
        latency = section.number("max_latency_ms", 20.0, above=0.0, high=200.0)
        beams = ()
        if "beams" in section:
            found = {}
            for item in section.items_of("beams", nonempty=True):
                ch = item.integer("channel", required=True, low=0, high=17)
                point_m = item.vector("point_mm", 3, required=True) / 1e3
                item.done()
                if ch in found:
                    section.fail("beams", f"channel {ch}: each beam of [beams] (channels "
                                          f"{sorted(b.channel for b in cell.beams)}) once")
                found[ch] = point_m
            try:
                beams = checked_beams(found, cell)
            except ValueError as exc:
                section.fail("beams", str(exc))
        beam_std = section.number("beam_std_mm", 0.0, low=0.0, high=50.0) if "beam_std_mm" in section else None
        section.done()
        return TcpCheckOptions(speed, tuple(float(h) for h in heights), tuple(float(s) for s in spins), search,
                               repeat, jitter, latency, beams, beam_std)

    @classmethod
    def with_history(cls, cell: Cell, options: TcpCheckOptions, last_result) -> tuple[TcpCheckOptions, str | None]:
        """In the service: the beams where the newest tcp-laser calibration that passed found
        them (its result's ``beams[].point_mm``), whichever tool it calibrated (the beams are the
        cell's), unless the cell file's ``tcp_check`` section gives them (then those)."""
        if options.beams:
            return options, None
        last = last_result("tcp-laser", any_tool=True)
        if last is None:
            return options, None
        run_id, found = last
        points_m = {int(b["channel"]): np.array([float(v) for v in b["point_mm"]]) / 1e3
                    for b in found.get("beams", []) if "channel" in b and "point_mm" in b}
        if not points_m:
            return options, None
        try:
            beams = checked_beams(points_m, cell)
        except ValueError as exc:
            return options, f"the beams tcp-laser run {run_id} found were not used ({exc}): [beams] as installed"
        return replace(options, beams=beams), f"the beams where tcp-laser run {run_id} found them"

    def __init__(self, cell: Cell, options: TcpCheckOptions):
        super().__init__(cell, options)
        o = options  # the sweeps upright only: no tilted orientations
        upright = SweepPlan(o.speed_mm_s, o.heights_mm, min(o.heights_mm), 0.0, 0, o.spins_deg, o.search_mm,
                            o.max_latency_ms)
        self.sweeps = BarrierSweeps(self.name, cell, lambda: self.robot_model, upright, missed=self._alarm)

    # -- what the plan can tell -----------------------------------------------------

    def design(self) -> PlanPromise:
        """Expected 1-sigma errors of the tip (mm) and the axis (deg) at the stated
        repeatability, and what that lets the check judge against the tool's bands."""
        o, bands = self.options, self.cell.tool.bands
        n = len(o.spins_deg)
        # each sweep pair locates the tool across each beam to about one motion's repeatability;
        # a held beam position adds its uncertainty to the tip as it is
        tip_std = float(np.hypot(o.beam_std_mm, o.repeatability_mm / np.sqrt(n)))
        axis_std = float("inf")
        if len(o.heights_mm) > 1:
            span = max(o.heights_mm) - min(o.heights_mm)
            axis_std = float(np.degrees(np.sqrt(2.0 / n) * o.repeatability_mm / span))
        determines = set()
        if determined(tip_std, bands.inner_mm):
            determines.add(tool_frame.TIP)
        if determined(axis_std, bands.inner_deg):
            determines.add(tool_frame.AXIS)
        return PlanPromise(float("nan"), tip_std, "mm", {"axis_std_deg": axis_std, "determines": sorted(determines)})

    def check_design(self) -> PlanPromise:
        o = self.options
        if not o.beams and o.stated_beam_std_mm is None:
            raise CalibrateFirst(
                f"no beam calibration for this cell yet: run tcp-laser first (the beams it finds serve every tool's "
                f"check), or give tcp_check.beams in {self.cell.path} (beam_std_mm, if [beams] were measured in "
                f"place); with [beams] as installed (known to {INSTALLED_BEAM_STD_MM:g} mm) a check cannot tell a tip "
                "that moved from beams that did")
        d = self.design()
        if d.details["determines"]:
            return d
        bands = self.cell.tool.bands
        source = "tcp_check.beams" if o.beams else "[beams] as installed"
        axis = ("one height in heights_mm does not tell the axis" if len(o.heights_mm) < 2 else
                f"the axis to {d.details['axis_std_deg']:.3f} deg (1 sigma), more than a third of inner_deg "
                f"{bands.inner_deg:g}")
        raise PlanRefused(
            f"{self.cell.path}: [tcp_check] determines nothing a band can judge: the tip to {d.expected_error:.3f} mm "
            f"(1 sigma; the beams' positions from {source} are known to {o.beam_std_mm:g} mm), more than a third of "
            f"inner_mm {bands.inner_mm:g}; {axis}. Give tcp_check.beams from the last tcp-laser result, or two "
            "heights_mm further apart")

    def plan(self) -> list[Move]:
        self.check_design()
        return self.sweeps.moves()

    # -- measure ---------------------------------------------------------------------

    def measure(self, devices: Devices, robot, plan: list[Move], progress) -> Dataset:
        """The sweeps with the controller on its own tool frame before the run (what is checked),
        or on the tool as drawn when it holds none."""
        before = self.tool_frame_before
        if before is None:  # a routine built without a run's context
            before = robot.tool_frame()
        held = tool_frame.controller_frame(before)
        tool = self.cell.tool.tcp_pose if held is None else held
        return self.sweeps.measure(devices, robot, plan, progress, tool, before)

    def _alarm(self, error: RoutineError) -> CheckAlarm:
        return CheckAlarm(
            f"tcp-check alarm: {error}. The tool is more than search_mm {self.options.search_mm:g} mm off its "
            "stored frame, or something else is in the beams: a bent tool, a collision? Nothing written; a full "
            "calibration (tcp-laser) is the operator's choice")

    # -- solve -----------------------------------------------------------------------

    @classmethod
    def solve(cls, dataset, cell: Cell, options: TcpCheckOptions) -> Result:
        geometry, edges, beams = barrier_data(dataset, {b.channel: b.point_m for b in options.beams})
        meta = dataset.meta
        if options.beams:
            beam_source = "tcp_check.beams (where the last tcp-laser calibration found them)"
        else:
            beam_source = "[beams] as installed"
        heights = {float(h) for h in dataset["height_mm"] if np.isfinite(h)}
        spins = meta.get("spins_deg", list(options.spins_deg))
        try:
            fit = check.fit(edges, geometry, options.repeatability_mm, options.trigger_jitter_ms / 1e3,
                            tilt=len(heights) > 1, beam_across=len(spins) > 1, beam_std_mm=options.beam_std_mm)
        except ValueError as exc:
            raise RoutineError(f"{dataset.path}: {exc}") from None
        return _result(cls.name, fit, geometry, cell, options, meta, beam_source, beams)


def _result(name, fit: check.CheckFit, geometry, cell: Cell, options: TcpCheckOptions, meta, beam_source,
            beams) -> Result:
    bands = cell.tool.bands
    ref = tool_frame.reference(meta.get("tool_frame_before"), np.asarray(meta["planned_tool"], dtype=float))
    # the change in the stored frame's own flange-frame terms: tip minus stored tip, and the axis' lean
    shift_mm = fit.tip_mm - ref.pose[:3] * 1e3
    tip_sigma = check.largest_std(fit.tip_cov_mm2)
    tip_std = np.sqrt(np.clip(np.diag(fit.tip_cov_mm2), 0.0, None))
    tip_mm = float(np.linalg.norm(shift_mm))
    tilt_deg = tilt_std = None
    tilt_norm, tilt_sigma = 0.0, float("inf")
    if fit.tilt_rad is not None:
        tilt_deg = np.degrees(fit.tilt_rad)
        tilt_std = np.degrees(np.sqrt(np.clip(np.diag(fit.tilt_cov_rad2), 0.0, None)))
        tilt_sigma = float(np.degrees(check.largest_std(fit.tilt_cov_rad2)))
        tilt_norm = float(np.linalg.norm(tilt_deg))
    tip_ok = determined(tip_sigma, bands.inner_mm)
    axis_ok = tilt_deg is not None and determined(tilt_sigma, bands.inner_deg)
    determines = frozenset(({tool_frame.TIP} if tip_ok else set()) | ({tool_frame.AXIS} if axis_ok else set()))

    params = [Parameter(f"tcp_{c}_mm", float(fit.tip_mm[j]), float(tip_std[j]), "mm") for j, c in enumerate("xyz")]
    params += [Parameter(f"shift_{c}_mm", float(shift_mm[j]), float(tip_std[j]), "mm") for j, c in enumerate("xyz")]
    if tilt_deg is not None:
        params += [Parameter(f"axis_tilt_{c}_deg", float(tilt_deg[j]), float(tilt_std[j]), "deg")
                   for j, c in enumerate("xy")]
    params.append(Parameter("latency_ms", fit.latency_s * 1e3, fit.latency_std_s * 1e3, "ms"))

    if determines:
        frame, frame_notes = tool_frame.compose(
            determines, ref, tip_m=fit.tip_mm / 1e3 if tip_ok else None, axis=fit.axis if axis_ok else None)
    else:
        frame, frame_notes = ref.pose.copy(), ["the check determined nothing: the tool frame is the stored one"]
    latency_ms, latency_std_ms = fit.latency_s * 1e3, fit.latency_std_s * 1e3
    latency_ok = bool(-3 * latency_std_ms <= latency_ms <= options.max_latency_ms)
    expected = float(np.sqrt(np.mean(fit.sigma_mm**2)))
    gate_list = [
        gates.residual(float(np.sqrt(np.mean(fit.residuals_mm**2))), expected),
        gates.conditioning(fit.condition), gates.identifiability(list(fit.undetermined)),
        gates.plausible_tool(frame, cell.tool, determines=determines or tool_frame.TIP_AND_AXIS),
        Gate("latency", latency_ok, latency_ms, options.max_latency_ms,
             f"trigger latency {latency_ms:.3f} +- {latency_std_ms:.3f} ms"
             + (f" is within 0..{options.max_latency_ms:g} ms" if latency_ok else
                f" is outside 0..{options.max_latency_ms:g} ms: are the barrier's and the robot's clocks the same?"))]

    # the verdict: what was determined against the bands; what was not, only when surely beyond the outer band
    failed = [g for g in gate_list if not g.passed]
    judged = check_verdict(Measured(tip_mm, tip_sigma), None if tilt_deg is None else Measured(tilt_norm, tilt_sigma),
                           bands, gates_passed=not failed)
    notes = [_verdict_note(judged, determines, bands, shift_mm, tilt_deg, tip_sigma, tilt_sigma, failed),
             *frame_notes]
    if judged.verdict is Verdict.OK:
        frame = ref.pose.copy()
    undetermined_words = []
    if not tip_ok:
        undetermined_words.append(f"the tip (known to {tip_sigma:.3f} mm, 1 sigma: more than a third of inner_mm "
                                  f"{bands.inner_mm:g}; the beams' positions from {beam_source} are known to "
                                  f"{options.beam_std_mm:g} mm)")
    if not axis_ok:
        undetermined_words.append("the axis (" + ("one height: held at the stored frame's; a tilt d shows at the tip "
                                                  "as height x d" if tilt_deg is None else
                                                  f"known to {tilt_sigma:.3f} deg, more than a third of inner_deg "
                                                  f"{bands.inner_deg:g}") + ")")
    if undetermined_words:
        notes.append("not determined, so no band applies to it: " + "; ".join(undetermined_words))
    notes.append(f"the beams' positions are from {beam_source}, known to {options.beam_std_mm:g} mm (1 sigma): an "
                 "error in them goes straight into the tip (its length along the axis on the beams' height"
                 + (", x and y on their horizontal position" if len(meta.get("spins_deg", [0])) < 2 else "") + ")")
    if not ref.from_controller:
        notes.append("the controller holds no tool frame: the tool was checked against the tool as drawn")
    if not fit.success:
        notes.append(f"the fit did not converge: {fit.message}")
    change = {"x_mm": float(shift_mm[0]) if tip_ok else None, "y_mm": float(shift_mm[1]) if tip_ok else None,
              "z_mm": float(shift_mm[2]) if tip_ok else None,
              "tilt_x_deg": float(tilt_deg[0]) if axis_ok else None,
              "tilt_y_deg": float(tilt_deg[1]) if axis_ok else None}
    extra = {"latency_ms": latency_ms, "latency_std_ms": latency_std_ms, "tip_shift_mm": tip_mm,
             "tip_std_mm": tip_sigma, "axis_tilt_deg": tilt_norm if tilt_deg is not None else None,
             "axis_std_deg": tilt_sigma if tilt_deg is not None else None,
             "bands": {"inner_mm": bands.inner_mm, "inner_deg": bands.inner_deg, "outer_mm": bands.outer_mm,
                       "outer_deg": bands.outer_deg},
             "compared_with": ref.source, "beams_from": beam_source, "n_edges": int(len(fit.residuals_mm)),
             "speed_mm_s": float(meta.get("speed_mm_s", options.speed_mm_s))}
    if judged.verdict is Verdict.ALARM:  # what was seen, as the run's reason says it (the log, the store, the page)
        extra["saw"] = notes[0].removeprefix("alarm: ")
    return Result(name, params, fit.residuals_mm, expected, fit.condition, gate_list, tool_frame=frame, notes=notes,
                  extra=extra, determines=determines, verdict=judged.verdict, change=change)


def _verdict_note(judged, determines, bands, shift_mm, tilt_deg, tip_sigma: float, tilt_sigma: float,
                  failed) -> str:
    """The words of a check's verdict (its first note): what it saw against which band."""
    tip_mm = float(np.linalg.norm(shift_mm))
    dominant = "xyz"[int(np.argmax(np.abs(shift_mm)))]
    tip_words = (f"tip {tip_mm:.3f} mm off (x {shift_mm[0]:+.3f}, y {shift_mm[1]:+.3f}, z {shift_mm[2]:+.3f} mm, "
                 f"mostly along {dominant})")
    tilt_words = "" if tilt_deg is None else (
        f"axis tilted {float(np.linalg.norm(tilt_deg)):.3f} deg (toward x {tilt_deg[0]:+.3f}, toward y "
        f"{tilt_deg[1]:+.3f} deg)")
    if judged.verdict is Verdict.ALARM:
        beyond = ([f"{tip_words}, beyond the outer band {bands.outer_mm:g} mm"] if judged.tip.beyond_outer else []) \
            + ([f"{tilt_words}, beyond the outer band {bands.outer_deg:g} deg"] if judged.axis.beyond_outer else [])
        if beyond:
            return (f"alarm: {'; '.join(beyond)}: a bent tool or a collision? Nothing written; a full "
                    "calibration (tcp-laser) is the operator's choice")
        if failed:
            return ("alarm: the check's data do not say what changed ("
                    + "; ".join(f"{g.name}: {g.why}" for g in failed) + "); nothing written")
        return (f"alarm: the check determined nothing a band can judge (tip to {tip_sigma:.3f} mm, axis to "
                f"{tilt_sigma:.3f} deg, 1 sigma); nothing written")
    if judged.verdict is Verdict.OK:
        return (f"ok: {tool_frame.described(determines)} within the inner band ({bands.inner_mm:g} mm / "
                f"{bands.inner_deg:g} deg); nothing to write")
    tip_ok, axis_ok = judged.tip.determined, judged.axis.determined
    return (f"corrected: {tip_words if tip_ok else ''}"
            f"{'; ' if tip_ok and axis_ok else ''}{tilt_words if axis_ok else ''}: within the outer band "
            f"({bands.outer_mm:g} mm / {bands.outer_deg:g} deg), determined to 3 sigma within the inner "
            "band: the measured frame is written back")
