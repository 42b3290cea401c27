"""``cellcal run tracker``: the kinematic calibration campaign the arm runs by itself.

The arm moves through poses chosen for identification and the cell's laser tracker
measures a target on its tool at each. The measurements go to disk as the measurement
CSV that ``cellcal identify`` reads (docs/measurements.md; the dataset header rides
along as ``#`` lines, rows marked ``split`` = ``cal``/``val``), then the arm's geometry,
the instrument -> base frame and the target offset are identified on the ``cal`` rows
and checked on the ``val`` rows (as in Cao et al., "A Novel Kinematic Calibration Method for
Industrial Robots Based on the Improved Grey Wolf Optimization Algorithm", and Liu et al.,
"L2-Regularization-Based Kinematic Parameter Identification for Industrial Robots in Limited
Measurement Space", both Actuators 2025: a tracker over the volume the arm works in, an L2
prior toward nominal weighted by cross-validation).

Plan, from the cell file alone: random configurations on the nominal model, kept where
the whole arm is inside the workspace box, the target is in the instrument's view cone
and range, faces the instrument within the reflector's acceptance angle, and the line
of sight passes clear of the arm; the calibration poses chosen from them D-optimally,
the validation poses at random from the rest; all visited in one short tour of joint
moves at the cell's joint speed limits (via home where a straight joint path would
leave the box). The Robot interface has no wait: a joint move returns with the arm at
rest and the target is measured then; the configured settle time is recorded and
counted in the campaign time.

A fault mid-campaign (tracker lost, target not found, a protective stop) ends the run
with one message; what was measured is kept on disk marked ``complete: false``, and
``cellcal run tracker --resume DATASET`` measures only the poses still missing.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from cellcal.config.robot_files import load_robot
from cellcal.drivers.interfaces import DeviceError
from cellcal.solvers.geometry import se3
from cellcal.solvers.identification.identify import IdentificationError, IdentifyOptions, identify
from cellcal.solvers.identification.measurement_model import Observations
from cellcal.solvers.identification.pose_design import Sight, path_clear, select_poses, sighted_candidates, tour
from cellcal.routines.framework import gates
from cellcal.routines.framework.base import (Gate, Move, Parameter, PlanRefused, Result, Routine, RoutineError, drawn_tool,
                                   frame_text)
from cellcal.routines.framework.drawing import errors_per_pose
from cellcal.routines.framework.records import Dataset

MIN_CAL_ROWS = 10  # as cellcal identify: fewer rows cannot carry a kinematic identification
PLAUSIBLE_MM = 5.0  # an arm's lengths are within this of its drawing ...
PLAUSIBLE_DEG = 0.5  # ... and its axes within this; beyond, the data or the model file is wrong
TARGET_PLAUSIBLE_MM = 10.0  # the target is within this of where the section says it is mounted


@dataclass(frozen=True)
class TrackerOptions:
    target: str
    target_m: np.ndarray  # flange frame
    normal: np.ndarray  # the way the target faces, flange frame, unit
    sight: Sight  # where the instrument is and what it sees (base frame, mm, rad)
    poses: int
    validation_poses: int
    candidates: int
    seed: int
    settle_s: float
    measure_s: float
    retries: int
    repeatability_mm: float
    noise_mm: float  # per axis, when the instrument reports no figure of its own
    base_in_instrument: np.ndarray | None  # the frame the cell file has, [x, y, z, rx, ry, rz] m, rad


@dataclass(frozen=True)
class Stop:
    pose: int  # index over all planned poses (calibration first, then validation)
    split: str
    q_rad: np.ndarray


class TrackerCampaign(Routine):
    name = "tracker"
    section = "tracker"
    selector = 5
    needs = ("robot", "tracker")
    text_columns = ("split", "target")

    def __init__(self, cell, options: TrackerOptions):
        super().__init__(cell, options)
        self.model = load_robot(cell.robot)
        self.resumed: Dataset | None = None
        self.plan_id = ""
        self._stops: dict[str, Stop] = {}
        self._rows: list[dict] = []
        self._motion_s = 0.0

    # -- options ---------------------------------------------------------------------

    @classmethod
    def read_options(cls, s, cell) -> TrackerOptions:
        tool = cell.tool
        target_m = s.vector("target_m", 3, tool.tcp_m.tolist() if tool is not None else None, required=tool is None)
        normal = s.vector("target_normal", 3, tool.axis.tolist() if tool is not None else [0.0, 0.0, 1.0],
                          nonzero=True)
        instrument = s.vector("instrument_m", 3, required=True)
        if np.linalg.norm(instrument) < 0.5:
            s.fail("instrument_m", "the instrument must stand at least 0.5 m from the robot base's origin")
        axis = s.vector("instrument_axis", 3, (-instrument).tolist(), nonzero=True)
        view = s.number("view_half_angle_deg", 60.0, above=0.0, high=90.0)
        acceptance = s.number("target_acceptance_deg", 30.0, above=0.0, high=90.0)
        clearance = s.number("clearance_m", 0.08, low=0.0, high=0.5)
        max_range = s.number("max_range_m", 15.0, above=0.5, high=100.0)
        poses = s.integer("poses", 60, low=MIN_CAL_ROWS, high=2000)
        validation = s.integer("validation_poses", 30, low=0, high=2000)
        candidates = s.integer("candidates", 600, low=1, high=20000)
        if candidates < poses + validation:
            s.fail("candidates", f"{candidates} is fewer than poses + validation_poses = {poses + validation}")
        base = s.vector("base_in_instrument_m_rad", 6) if "base_in_instrument_m_rad" in s else None
        options = TrackerOptions(
            target=s.text("target", "smr1"), target_m=target_m, normal=normal / np.linalg.norm(normal),
            sight=Sight(instrument * 1e3, axis / np.linalg.norm(axis), np.deg2rad(view), np.deg2rad(acceptance),
                        clearance * 1e3, max_range * 1e3),
            poses=poses, validation_poses=validation, candidates=candidates,
            seed=s.integer("seed", 1, low=0, high=2**32 - 1),
            settle_s=s.number("settle_s", 1.0, low=0.0, high=60.0),
            measure_s=s.number("measure_s", 0.5, low=0.0, high=60.0),
            retries=s.integer("retries", 2, low=0, high=10),
            repeatability_mm=s.number("repeatability_mm", 0.05, low=0.0, high=5.0),
            noise_mm=s.number("noise_mm", 0.02, above=0.0, high=5.0), base_in_instrument=base)
        s.done()
        return options

    # -- plan ------------------------------------------------------------------------

    def _poses(self) -> list[Stop]:
        """Every pose of the campaign: D-optimal calibration poses, then random validation poses."""
        o, cell = self.options, self.cell
        rng = np.random.default_rng(o.seed)
        box = (np.asarray(cell.workspace_min_m) * 1e3, np.asarray(cell.workspace_max_m) * 1e3)
        home = np.asarray(cell.home_q_rad, dtype=float)
        q = sighted_candidates(self.model, o.candidates, rng, target_mm=o.target_m * 1e3, normal=o.normal,
                               sight=o.sight, box_mm=box, tool_mm=self._tool()[:3] * 1e3, home_q=home)
        if len(q) < o.poses + o.validation_poses:
            raise PlanRefused(
                f"{cell.path}: [tracker] only {len(q)} configurations put the target in the instrument's view "
                f"inside the workspace box; {o.poses + o.validation_poses} poses are asked for: move the "
                "instrument (instrument_m), widen view_half_angle_deg or target_acceptance_deg, or ask for fewer")
        chosen = select_poses(self.model, q, o.poses, target_offsets=[o.target_m * 1e3]).chosen
        rest = np.setdiff1d(np.arange(len(q)), chosen)
        val = rng.choice(rest, o.validation_poses, replace=False) if o.validation_poses else rest[:0]
        return [Stop(i, "cal", q[k]) for i, k in enumerate(chosen)] + \
            [Stop(o.poses + i, "val", q[k]) for i, k in enumerate(val)]

    def _tool(self) -> np.ndarray:
        return self.cell.tool.tcp_pose if self.cell.tool is not None else np.zeros(6)

    def plan(self) -> list[Move]:
        stops = self._poses()
        self.plan_id = hashlib.sha256(np.round(np.array([s.q_rad for s in stops]), 9).tobytes()
                                      + self.options.target.encode()).hexdigest()[:16]
        if self.resumed is not None:
            stops = self._remaining(stops)
        home = np.asarray(self.cell.home_q_rad, dtype=float)
        limits = self.cell.limits
        speed, accel = limits["joint_speed_rad_s"], limits["joint_accel_rad_s2"]
        order = tour(np.array([s.q_rad for s in stops]), home, speed, accel)
        box = (np.asarray(self.cell.workspace_min_m) * 1e3, np.asarray(self.cell.workspace_max_m) * 1e3)
        tool_mm = self._tool()[:3] * 1e3
        moves, q_at = [], home
        for k in order:
            stop = stops[k]
            label = f"{stop.split} pose {stop.pose + 1 - (self.options.poses if stop.split == 'val' else 0)}"
            if not path_clear(self.model, q_at, stop.q_rad, box, tool_mm):
                moves.append(Move.joint(f"via home to {label}", home, speed, accel))
            moves.append(Move.joint(label, stop.q_rad, speed, accel))
            self._stops[label] = stop
            q_at = stop.q_rad
        if moves:  # every pose was kept only with a clear straight path from home, and so back
            moves.append(Move.joint("back home", home, speed, accel))
        return moves

    # -- resume ----------------------------------------------------------------------

    def resume(self, dataset: Dataset) -> None:
        """Continue an incomplete campaign: its rows are kept and its poses not measured again."""
        _check_columns(dataset, self.model.n_joints, "pose")
        self.resumed = dataset

    def _remaining(self, stops: list[Stop]) -> list[Stop]:
        done = self.resumed
        if done.meta.get("plan_id") != self.plan_id:
            raise RoutineError(f"{done.path}: cannot resume: it was planned from another cell file or other "
                               f"[tracker] options (plan {done.meta.get('plan_id')!r}, now {self.plan_id!r})")
        measured = {int(p) for p in done["pose"]}
        left = [s for s in stops if s.pose not in measured]
        if not left:
            raise RoutineError(f"{done.path}: nothing left to measure, every pose is in it; "
                               "solve it with --from")
        return left

    # -- measure ---------------------------------------------------------------------

    def _joint_columns(self) -> list[str]:
        return [f"q{j}_rad" for j in range(1, self.model.n_joints + 1)]

    def measure(self, devices, robot, plan, progress) -> Dataset:
        # the tool as drawn while it measures; the controller's frame from before given back
        # afterwards, as every routine does (this one writes no tool frame)
        with drawn_tool(robot, self._tool()):
            return self._measure(devices, robot, plan, progress)

    def _measure(self, devices, robot, plan, progress) -> Dataset:
        o = self.options
        t_last = _clock(robot, None)
        n_stops = sum(1 for m in plan if m.label in self._stops)
        for move in plan:
            stop = self._stops.get(move.label)
            try:
                robot.run(move)
                t_now = _clock(robot, t_last)
                self._motion_s += max(t_now - t_last, 0.0)
                t_last = t_now
                if stop is None:
                    continue
                q = np.asarray(robot.actual_q(), dtype=float)
                reading = self._read(devices.tracker, move.label)
            except DeviceError as exc:
                raise DeviceError(exc.device, f"{exc.what} (at '{move.label}', after {len(self._rows)} of "
                                              f"{n_stops} measurements)") from exc
            sigma = reading.quality * 1e3 if np.isfinite(reading.quality) and reading.quality > 0 else o.noise_mm
            self._rows.append({"pose": stop.pose, "split": stop.split, "target": o.target, "q": q,
                               "xyz_mm": np.asarray(reading.position_m, dtype=float) * 1e3,
                               "t_s": float(reading.t_s), "sigma_mm": sigma})
            if len(self._rows) % 10 == 0 or len(self._rows) == n_stops:
                progress(f"tracker: {len(self._rows)} of {n_stops} poses measured")
        return self._dataset(complete=True)

    def _read(self, tracker, label: str):
        for _ in range(self.options.retries + 1):
            reading = tracker.measure(self.options.target)
            if reading.status == "ok":
                return reading
        raise RoutineError(f"the tracker reports '{reading.status}' at '{label}' {self.options.retries + 1} "
                           "times in a row: is the target steady and the air calm?")

    def partial(self) -> Dataset | None:
        """What was measured before a fault (None when nothing new was)."""
        return self._dataset(complete=False) if self._rows else None

    def _dataset(self, complete: bool) -> Dataset:
        o = self.options
        old = self.resumed
        n_old = len(old) if old is not None else 0
        rows = self._rows
        q = np.array([r["q"] for r in rows]).reshape(len(rows), self.model.n_joints)
        xyz = np.array([r["xyz_mm"] for r in rows]).reshape(len(rows), 3)
        new = {"pose": np.array([r["pose"] for r in rows], dtype=float),
               "split": np.array([r["split"] for r in rows], dtype=str),
               "target": np.array([r["target"] for r in rows], dtype=str),
               **{c: q[:, j] for j, c in enumerate(self._joint_columns())},
               "x_mm": xyz[:, 0], "y_mm": xyz[:, 1], "z_mm": xyz[:, 2],
               "t_s": np.array([r["t_s"] for r in rows], dtype=float),
               "sigma_mm": np.array([r["sigma_mm"] for r in rows], dtype=float)}
        if old is not None:
            new = {c: np.concatenate([old[c] if c in old.columns else np.full(n_old, np.nan), v])
                   for c, v in new.items()}
        motion_s = self._motion_s + (float(old.meta.get("motion_s", 0.0)) if old is not None else 0.0)
        n = n_old + len(rows)
        meta = {"plan_id": self.plan_id, "target": o.target, "poses": o.poses,
                "validation_poses": o.validation_poses, "measured": n, "settle_s": o.settle_s,
                "measure_s": o.measure_s, "motion_s": motion_s,
                "cycle_time_s": motion_s + n * (o.settle_s + o.measure_s)}
        if old is not None:
            meta["resumed_from"] = old.path
        return Dataset(self.name, new, meta, complete=complete)

    # -- solve -----------------------------------------------------------------------

    @classmethod
    def solve(cls, dataset: Dataset, cell, options: TrackerOptions) -> Result:
        model = load_robot(cell.robot)
        cal, val = _observations(dataset, model.n_joints)
        if len(cal) < MIN_CAL_ROWS:
            raise RoutineError(f"{dataset.path or 'the dataset'}: {len(cal)} calibration rows; the "
                               f"identification needs at least {MIN_CAL_ROWS}")
        try:
            found = identify(model, cal, IdentifyOptions())
        except IdentificationError as exc:
            raise RoutineError(str(exc)) from None
        layout = found.layout
        sigma = np.asarray(dataset["sigma_mm"], dtype=float) if "sigma_mm" in dataset.columns else np.array([])
        sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, options.noise_mm) if sigma.size else \
            np.array([options.noise_mm])
        expected = float(np.sqrt(3 * np.mean(sigma**2) + options.repeatability_mm**2))
        rms = float(np.sqrt(np.mean(np.sum(found.residuals_mm**2, axis=1))))
        err_val = found.errors(val) if len(val) else np.array([])
        gate_list = [gates.residual(rms, expected), _validation_gate(err_val, expected),
                     gates.conditioning(found.condition), gates.identifiability(list(found.uncertain)),
                     _plausible(found, options)]
        notes = [f"{len(cal)} calibration and {len(val)} validation measurements"]
        if not dataset.complete:
            notes.append("the dataset is incomplete (the campaign stopped early): solved from the poses it has; "
                         "--resume it to measure the rest")
        held = {n: "not identifiable from these poses" for n in found.unidentifiable}
        held.update({h.name: h.reason for h in found.held_implausible})
        held.update({n: "held on request" for n in found.fixed})
        by_reason: dict[str, list[str]] = {}
        for n, why in held.items():
            by_reason.setdefault(why, []).append(n)
        notes += [f"held at nominal ({why}; not a failure): {', '.join(names)}" for why, names in by_reason.items()]
        if not found.success:
            notes.append(f"the fit did not converge: {found.message}")
        params = [Parameter(name, float(np.rad2deg(v) if a else v),
                            float(np.rad2deg(sd) if a else sd) if free else None, "deg" if a else "mm")
                  for name, v, sd, a, free in zip(layout.names, found.x, found.std, layout.is_angle, found.free)]
        frame = _frame(found, options)
        notes.append(_frame_note(frame))
        err_cal_before = found.errors(cal, nominal=True)
        extra = {"calibration_mean_mm": float(found.errors(cal).mean()),
                 "calibration_before_mean_mm": float(err_cal_before.mean()),
                 "held_at_nominal": list(found.held_at_nominal), "uncertain": list(found.uncertain),
                 "lambda": found.lam, "identify_s": found.seconds, "complete": dataset.complete,
                 "campaign_time_s": float(dataset.meta.get("cycle_time_s", np.nan))}
        if len(val):
            extra.update({"validation_mean_mm": float(err_val.mean()), "validation_max_mm": float(err_val.max()),
                          "validation_before_mean_mm": float(found.errors(val, nominal=True).mean()),
                          "validation_before_max_mm": float(found.errors(val, nominal=True).max())})
        split = np.asarray(dataset["split"], dtype=str)
        at_cal, at_val = np.flatnonzero(split == "cal"), np.flatnonzero(split == "val")
        drawing = errors_per_pose({"calibration, nominal model": (at_cal, err_cal_before),
                                   "calibration, identified": (at_cal, found.errors(cal)),
                                   "validation, nominal model": (at_val, found.errors(val, nominal=True) if len(val)
                                                                 else err_val),
                                   "validation, identified": (at_val, err_val)}, expected)
        return Result(cls.name, params, found.residuals_mm, expected, found.condition, gate_list, frame=frame,
                      notes=notes, extra=extra, cycle_time_s=dataset.meta.get("cycle_time_s"), drawing=drawing)


def _check_columns(dataset: Dataset, n_joints: int, *more: str) -> None:
    needed = ["split", "target", *[f"q{j}_rad" for j in range(1, n_joints + 1)], "x_mm", "y_mm", "z_mm", *more]
    missing = [c for c in needed if c not in dataset.columns]
    if missing:
        raise RoutineError(f"{dataset.path}: not a tracker campaign's dataset: column(s) {', '.join(missing)} "
                           "missing")


def _observations(dataset: Dataset, n_joints: int) -> tuple[Observations, Observations]:
    """Calibration and validation rows; targets numbered by first appearance in the
    calibration rows, as ``cellcal identify`` numbers them."""
    _check_columns(dataset, n_joints)
    q = dataset.stack(*[f"q{j}_rad" for j in range(1, n_joints + 1)])
    xyz = dataset.stack("x_mm", "y_mm", "z_mm")
    split = np.asarray(dataset["split"], dtype=str)
    target = np.asarray(dataset["target"], dtype=str)
    cal, val = split == "cal", split == "val"
    names = tuple(dict.fromkeys(target[cal]))
    if set(target[val]) - set(names):
        raise RoutineError(f"{dataset.path}: validation rows measure a target no calibration row does")
    index = np.array([names.index(t) if t in names else -1 for t in target])
    return (Observations(q[cal], xyz[cal], index[cal], names or ("tcp",)),
            Observations(q[val], xyz[val], index[val], names or ("tcp",)))


def _validation_gate(errors_mm: np.ndarray, expected_mm: float) -> Gate:
    if not len(errors_mm):
        return Gate("validation", True, 0.0, 0.0, "no validation poses were measured")
    rms = float(np.sqrt(np.mean(errors_mm**2)))
    limit = gates.RESIDUAL_FACTOR * expected_mm
    ok = rms <= limit
    why = (f"validation RMS {rms:.4f} mm on {len(errors_mm)} poses the fit did not see is within "
           f"{gates.RESIDUAL_FACTOR:g}x the expected noise" if ok else
           f"validation RMS {rms:.4f} mm on poses the fit did not see is above {gates.RESIDUAL_FACTOR:g}x the "
           f"expected noise {expected_mm:.4f} mm: the model does not carry over (too few or too alike poses, "
           "or an effect the geometry cannot describe)")
    return Gate("validation", ok, rms, limit, why)


def _plausible(found, options: TrackerOptions) -> Gate:
    """The arm's geometry within a manufacturing tolerance of its drawing, the target where it is mounted."""
    layout, model = found.layout, found.layout.model
    dev = np.abs(found.x[: layout.n_kin] - model.nominal)
    mm = float(dev[~model.param_is_angle].max(initial=0.0))
    deg = float(np.rad2deg(dev[model.param_is_angle].max(initial=0.0)))
    target_mm = float(np.linalg.norm(found.x[layout.target(0)] - options.target_m * 1e3))
    ok = mm <= PLAUSIBLE_MM and deg <= PLAUSIBLE_DEG and target_mm <= TARGET_PLAUSIBLE_MM
    why = (f"lengths within {mm:.3f} mm and axes within {deg:.4f} deg of the drawing (limits {PLAUSIBLE_MM:g} mm, "
           f"{PLAUSIBLE_DEG:g} deg); target {target_mm:.2f} mm from target_m (limit {TARGET_PLAUSIBLE_MM:g} mm)"
           + ("" if ok else ": is it the right robot model, the target where [tracker] says, the data sound?"))
    return Gate("plausibility", ok, mm, PLAUSIBLE_MM, why)


def _frame(found, options: TrackerOptions) -> dict:
    """The robot base in the instrument frame, in the units people read and as a cell-file line."""
    b = found.x[found.layout.base]
    sd = found.std[found.layout.base]
    pose = np.concatenate([b[:3] / 1e3, b[3:]])
    out = {"from": "instrument", "to": "robot base",
           "x_mm": float(b[0]), "y_mm": float(b[1]), "z_mm": float(b[2]),
           "rx_deg": float(np.rad2deg(b[3])), "ry_deg": float(np.rad2deg(b[4])), "rz_deg": float(np.rad2deg(b[5])),
           "std_mm": sd[:3].tolist(), "std_deg": np.rad2deg(sd[3:]).tolist(), "pose_m_rad": pose.tolist(),
           "cell_file": "tracker:\n  base_in_instrument_m_rad: ["
                        + ", ".join(f"{v:.7f}" for v in pose) + "]"}
    if options.base_in_instrument is not None:
        before = options.base_in_instrument
        turn = se3.rotvec_to_matrix(pose[3:]) @ se3.rotvec_to_matrix(before[3:]).T
        out["change_from_cell_file_mm"] = float(np.linalg.norm(pose[:3] - before[:3]) * 1e3)
        out["change_from_cell_file_deg"] = float(np.rad2deg(np.linalg.norm(se3.matrix_to_rotvec(turn))))
    return out


def _frame_note(frame: dict) -> str:
    return (f"robot base in the instrument frame: {frame_text(frame, angle_digits=5, lean=False)}; for the cell file: "
            + frame["cell_file"].replace("\n  ", " "))


def _clock(robot, since_t_s) -> float:
    """The robot's clock: the time of its latest state sample."""
    samples = robot.samples(since_t_s)
    return float(samples[-1].t_s) if samples else (since_t_s or 0.0)
