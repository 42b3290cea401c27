"""``tcp-npoint``: the tool centre point from seating the tip in a fixed pivot from N orientations.

The plan, from the cell file alone (the tool as drawn, the pivot where [pivot] says):
the TCP set to the drawn tool; for each of N orientations, the tool tilted from the
vertical toward directions evenly round it, every other seat by `spread_deg` and by half
of it, and turned about its own axis by +-`turn_deg` in turn (free at a pivot, and it
halves the error across the axis). Two tilts make a tip that stopped on the flat beside
the socket show: at one tilt, stopping short on a flat looks exactly like a shorter tool.
Each seat:

* a linear move to `approach_mm` back along the tool axis from where the drawn tip would
  rest in the pivot;
* a contact search along the tool axis; a compliant arm (force mode) lets the socket's
  cone guide the tip's rounding to its seat, and the joints of that rest are recorded;
* a linear move back to the approach point.

The pivot fixes the centre of the tip's rounding, not the tip: the fit
(:func:`cellcal.solvers.tool_frames.pivot.fit_pivot`, linear least squares of ``R_i t + p_i = c``
with seats that did not sit right rejected one at a time and named) finds that centre
in the flange frame, and the TCP is that centre plus the tool radius along the tool
axis. The routine determines the tip only: the tool frame it writes keeps the whole
orientation of the controller's frame from before the run (:mod:`.framework.tool_frame`), and the
axis the radius is added along is that frame's z, so the TCP is the tip of the frame
written (measure the axis first, with ``tcf`` or ``tcp-laser``). Only where no controller
frame is known is it the drawn axis, or `tool_axis`. Before anything moves the
planned orientations are judged by the TCP error they would leave at the arm's stated
repeatability; a design that cannot reach `target_mm` is refused, saying how much
spread it needs.

Section ``tcp_npoint`` of the cell file (all optional)::

    orientations: 8          # seats, 4..24
    spread_deg: 30           # tilt of the tool from the vertical (every other seat half of it)
    turn_deg: 60             # turn about the tool axis, + and - in turn
    approach_mm: 5           # where each search starts, back along the axis (it may go twice that)
    search_speed_mm_s: 10
    repeatability_mm: 0.03   # the arm's stated repeatability (RMS distance of a repeated pose)
    target_mm: 0.05          # refuse a design whose expected TCP error (1 sigma) is larger
    outlier_k: 4             # a seat off by more than k robust sigmas is rejected
    tool_axis: [0, 0, 1]     # the tool axis in the flange frame (from tcf) where no controller frame is known
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.reader import Section
from cellcal.config.robot_files import load_robot
from cellcal.solvers.tool_frames import pivot as pv
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.inverse import inverse, tcp_frames
from cellcal.solvers.geometry.robot_model import KinematicModel
from cellcal.routines.framework import gates, tool_frame
from cellcal.routines.framework.base import (PlanPromise, Devices, Gate, Move, Parameter, PlanRefused, Result,
                                             RoutineError)
from cellcal.routines.framework.drawing import seats_about_pivot
from cellcal.routines.framework.steps import StepRoutine

LIFT_MM = 40.0  # above the first and after the last approach point, clear of the fixture
JOINT_SPEED_RAD_S = 1.0
MAX_SPREAD_DEG = 45.0  # beyond, the shank meets a 90 deg socket's rim
MAX_STD_MM = 1.0  # a TCP coordinate this uncertain from the design is not determined


@dataclass(frozen=True)
class TcpNpointOptions:
    orientations: int
    spread_deg: float
    turn_deg: float
    approach_mm: float
    search_speed_mm_s: float
    repeatability_mm: float
    target_mm: float
    outlier_k: float
    tool_axis: np.ndarray | None


def axis_sigma_mm(repeatability_mm: float) -> float:
    """Per-axis standard deviation of a pose whose repeatability (RMS 3D distance) is given."""
    return float(repeatability_mm) / np.sqrt(3.0)


def down_orientation(cell: Cell, model: KinematicModel) -> np.ndarray:
    """A tool frame rotation with z (the tool axis) straight down and x as near the home
    TCP's x as that allows: the orientation the routines turn from."""
    home = tcp_frames(model, cell.home_q_rad, cell.tool.tcp_pose)[0][0]
    z = np.array([0.0, 0.0, -1.0])
    x = home[:, 0] - (home[:, 0] @ z) * z
    if np.linalg.norm(x) < 1e-6:
        x = home[:, 1] - (home[:, 1] @ z) * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def flange_frames(model: KinematicModel, q_rad) -> tuple[np.ndarray, np.ndarray]:
    """Flange rotations (N, 3, 3) and positions (N, 3) in mm from recorded joints, on the
    controller's model (what the controller believes: the calibration's premise)."""
    rotation, position = tcp_frames(model, np.atleast_2d(np.asarray(q_rad, dtype=float)))
    return rotation, position * 1e3


def flange_rotations(tool_rotations, tool_pose) -> np.ndarray:
    """Flange rotations that hold the TCP frame at `tool_rotations` for a tool frame `tool_pose`."""
    return np.einsum("nij,kj->nik", np.asarray(tool_rotations), se3.rotvec_to_matrix(np.asarray(tool_pose)[3:]))


def unit_option(section: Section, key: str) -> np.ndarray | None:
    """An optional direction (normalised), None when the section does not give it."""
    if key not in section:
        return None
    axis = section.vector(key, 3, nonzero=True)
    return axis / np.linalg.norm(axis)


class TcpNpoint(StepRoutine):
    name = "tcp-npoint"
    section = "tcp_npoint"
    selector = 3
    needs = ("robot",)

    @classmethod
    def read_options(cls, section: Section, cell: Cell) -> TcpNpointOptions:
        if cell.tool is None:
            section.fail(None, "tcp-npoint needs the tool as drawn in [tool]")
        if cell.pivot_m is None:
            section.fail(None, "tcp-npoint needs the pivot in [pivot] (point_m)")
        travel_mm = cell.limits["contact_travel_m"] * 1e3
        options = TcpNpointOptions(
            section.integer("orientations", 8, low=4, high=24),
            section.number("spread_deg", 30.0, above=0.0, high=MAX_SPREAD_DEG),
            section.number("turn_deg", 60.0, low=0.0, high=90.0),
            section.number("approach_mm", 5.0, low=2.0, high=travel_mm / 2),
            section.number("search_speed_mm_s", 10.0, above=0.0, high=min(cell.limits["tcp_speed_m_s"] * 1e3, 20.0)),
            section.number("repeatability_mm", 0.03, above=0.0, high=1.0),
            section.number("target_mm", 0.05, above=0.0, high=10.0),
            section.number("outlier_k", 4.0, low=2.0, high=20.0),
            unit_option(section, "tool_axis"))
        section.done()
        return options

    # -- plan ------------------------------------------------------------------------

    def seats(self, spread_deg: float | None = None) -> list[tuple[np.ndarray, dict]]:
        """(tool frame rotation, what it is) of each seat, from the drawn tool and home."""
        o = self.options
        spread = o.spread_deg if spread_deg is None else spread_deg
        down = down_orientation(self.cell, load_robot(self.cell.robot))
        out = []
        for k in range(o.orientations):
            azimuth = 360.0 * k / o.orientations
            phi = np.deg2rad(azimuth)
            tilt_deg = spread if k % 2 == 0 else spread / 2.0
            tilt = se3.rotvec_to_matrix(np.deg2rad(tilt_deg) * np.array([np.cos(phi), np.sin(phi), 0.0]))
            turn = o.turn_deg * (1 if k % 2 == 0 else -1)
            rotation = tilt @ down @ se3.rot("z", np.deg2rad(turn))
            out.append((rotation, {"seat": k + 1, "tilt_deg": tilt_deg, "azimuth_deg": azimuth, "turn_deg": turn}))
        return out

    def design(self, spread_deg: float | None = None) -> PlanPromise:
        """The planned seats (tilted `spread_deg`, default the option's) judged at the stated
        repeatability: the TCP's expected error, mm."""
        rotations = flange_rotations([r for r, _ in self.seats(spread_deg)], self.cell.tool.tcp_pose)
        found = pv.pivot_design(rotations, axis_sigma_mm(self.options.repeatability_mm))
        return PlanPromise(found.condition, found.expected_error, "mm", {"tcp_std_mm": found.std.tolist()})

    def check_design(self) -> PlanPromise:
        """The planned orientations judged before anything moves; PlanRefused when they
        cannot reach the target at the stated repeatability, saying what spread would."""
        o = self.options
        design = self.design()
        if design.expected_error <= o.target_mm:
            return design
        need = pv.smallest_setting(lambda s: self.design(s).expected_error, o.target_mm, o.spread_deg, MAX_SPREAD_DEG)
        what = (f"at least {need:.1f} deg is needed" if need is not None else
                f"not even {MAX_SPREAD_DEG:g} deg reaches it: plan more orientations or a looser target_mm")
        raise PlanRefused(f"{self.cell.path} [tcp_npoint]: the {o.orientations} orientations spread "
                          f"+-{o.spread_deg:.1f} deg about the pivot; {what} for {o.target_mm:g} mm at "
                          f"{o.repeatability_mm:g} mm repeatability (this design: {design.expected_error:.3f} mm "
                          f"expected, condition {design.condition:.3g}); raise spread_deg")

    def steps(self) -> list[tuple[Move, dict | None]]:
        """Every motion and, for the seats' searches, which seat it is."""
        cell, o = self.cell, self.options
        model = load_robot(cell.robot)
        tool = cell.tool
        r = tool.radius_m
        centre = np.asarray(cell.pivot_m, dtype=float) + [0.0, 0.0, r]  # the drawn tip's rounding at rest
        accel, joint_accel = cell.limits["tcp_accel_m_s2"], cell.limits["joint_accel_rad_s2"]
        speed = cell.limits["tcp_speed_m_s"]
        joint_speed = min(JOINT_SPEED_RAD_S, cell.limits["joint_speed_rad_s"])
        approach = o.approach_mm / 1e3
        steps: list[tuple[Move, dict | None]] = []
        for i, (rotation, seat) in enumerate(self.seats()):
            axis = rotation[:, 2]
            rest = centre + r * axis  # the drawn tip when seated
            at = np.concatenate([rest - approach * axis, se3.matrix_to_rotvec(rotation)])
            if i == 0:
                above = at.copy()
                above[:3] -= LIFT_MM / 1e3 * axis
                q = inverse(model, above, cell.home_q_rad, tool.tcp_pose)
                if q is None:
                    raise PlanRefused(f"move 'above the pivot': the pose {np.round(above[:3], 4).tolist()} m "
                                      "cannot be reached from home")
                steps.append((Move.joint("above the pivot", q, joint_speed, joint_accel), None))
            steps.append((Move.linear(f"approach seat {i + 1}", at, speed, accel), None))
            steps.append((Move.contact(f"seat {i + 1}", axis, o.search_speed_mm_s / 1e3, 2 * approach), seat))
            steps.append((Move.linear(f"retract seat {i + 1}", at, speed, accel), None))
        lift = steps[-1][0].pose.copy()
        lift[:3] -= LIFT_MM / 1e3 * self.seats()[-1][0][:, 2]
        steps.append((Move.linear("lift", lift, speed, accel), None))
        steps.append((Move.joint("home", cell.home_q_rad, joint_speed, joint_accel), None))
        return steps

    # -- measure ---------------------------------------------------------------------

    def announce(self, design: PlanPromise) -> str:
        o = self.options
        return (f"tcp-npoint: {o.orientations} orientations tilted {o.spread_deg:g} and {o.spread_deg / 2:g} deg "
                f"about the pivot, turned +-{o.turn_deg:g} deg about the tool axis: condition {design.condition:.3g}, "
                f"expected TCP error {design.expected_error:.4f} mm (1 sigma) at {o.repeatability_mm:g} mm "
                "repeatability")

    def run_steps(self, devices: Devices, robot, plan: list[Move], steps, progress) -> tuple[list[dict], float]:
        o = self.options

        def missed(move):
            return (f"the contact search along the tool axis went {move.travel_m * 1e3:g} mm without touching the "
                    f"pivot: is [pivot] point_m {np.round(self.cell.pivot_m, 4).tolist()} m right, and the fixture "
                    "there?")

        def record(seat, q):
            progress(f"tcp-npoint: seat {seat['seat']} of {o.orientations} recorded")
            return {**seat, **{f"q{j + 1}_rad": v for j, v in enumerate(q)},
                    **dict(zip(("x_m", "y_m", "z_m", "rx", "ry", "rz"), robot.actual_tcp_pose()))}

        return self.contact_rows(robot, plan, steps, missed, record)

    def dataset_meta(self, design: PlanPromise, before: dict) -> dict:
        o = self.options
        return {"tool_radius_m": self.cell.tool.radius_m, "planned_tool": self.cell.tool.tcp_pose.tolist(),
                "pivot_point_m": np.asarray(self.cell.pivot_m).tolist(), "spread_deg": o.spread_deg,
                "turn_deg": o.turn_deg, "approach_mm": o.approach_mm, "search_speed_mm_s": o.search_speed_mm_s,
                "repeatability_mm": o.repeatability_mm}

    # -- solve -----------------------------------------------------------------------

    @classmethod
    def solve(cls, dataset, cell: Cell, options: TcpNpointOptions) -> Result:
        meta = dataset.meta
        missing = [k for k in ("tool_radius_m", "planned_tool") if k not in meta]
        if missing:
            raise RoutineError(f"{dataset.path}: the dataset's meta lacks {', '.join(missing)}")
        model = load_robot(cell.robot)
        names = [f"q{j + 1}_rad" for j in range(model.n_joints)]
        if any(n not in dataset.columns for n in names) or len(dataset) < 4:
            raise RoutineError(f"{dataset.path}: needs the joints ({', '.join(names)}) of 4 or more seats")
        rotations, positions = flange_frames(model, dataset.stack(*names))
        sigma = axis_sigma_mm(options.repeatability_mm)
        design = pv.pivot_design(rotations, sigma)
        if design.expected_error > options.target_mm:
            raise RoutineError(f"{dataset.path}: these {len(dataset)} seats' orientations leave an expected TCP "
                               f"error of {design.expected_error:.3f} mm at {options.repeatability_mm:g} mm "
                               f"repeatability, above target_mm {options.target_mm:g} (condition "
                               f"{design.condition:.3g}): not solved")
        fit = pv.fit_pivot(rotations, positions, noise_floor=sigma, k=options.outlier_k)
        result = _result(cls.name, dataset, cell, options, fit, design)
        result.drawing = seats_about_pivot(positions - fit.pivot_point, fit.residuals_mm, fit.kept,
                                           float(np.linalg.norm(fit.tool_point)), result.expected_noise_mm)
        return result


def _result(name, dataset, cell: Cell, options: TcpNpointOptions, fit: pv.PivotFit, design: pv.PlanQuality) -> Result:
    meta = dataset.meta
    planned = np.asarray(meta["planned_tool"], dtype=float)
    ref = tool_frame.reference(meta.get("tool_frame_before"), planned, axis=options.tool_axis,
                               axis_option="tool_axis of [tcp_npoint]")
    axis = ref.axis  # the axis of the frame written: the TCP on any other would not be its frame's tip
    radius_mm = float(meta["tool_radius_m"]) * 1e3
    tcp_mm = fit.tool_point + radius_mm * axis
    frame, frame_notes = tool_frame.compose(tool_frame.TIP_ONLY, ref, tip_m=tcp_mm / 1e3)
    seats = dataset["seat"].astype(int) if "seat" in dataset.columns else np.arange(1, len(dataset) + 1)
    n_kept = int(fit.kept.sum())
    kept_residuals = fit.residuals_mm[fit.kept]
    expected = options.repeatability_mm * np.sqrt((3 * n_kept - 6) / (3 * n_kept))
    lengths = np.linalg.norm(fit.residuals_mm, axis=1)
    notes, rejected = [], [int(seats[i]) for i in fit.rejected]
    for i in fit.rejected:
        where = (f" (tilted toward {dataset['azimuth_deg'][i]:.0f} deg)" if "azimuth_deg" in dataset.columns else "")
        notes.append(f"seat {seats[i]}{where} rejected: it is {lengths[i]:.3f} mm off the others' pivot, above "
                     f"{options.outlier_k:g} x {fit.scale:.4f} mm: it did not sit right (swarf in the socket, "
                     "an off-centre contact?)")
    max_rejected = max(1, len(seats) // 4)
    seat_ok = len(rejected) <= max_rejected
    rms = float(np.sqrt(np.mean(np.sum(kept_residuals**2, axis=1))))
    seating = Gate("seating", seat_ok, float(len(rejected)), float(max_rejected),
                   (f"{len(rejected)} of {len(seats)} seats rejected (at most {max_rejected})" if seat_ok else
                    f"{len(rejected)} of {len(seats)} seats rejected, more than {max_rejected}: the tip does not "
                    "seat reliably; clean the socket, check [pivot] point_m"))
    if rms > gates.RESIDUAL_FACTOR * expected:
        notes.append(f"the seats scatter {rms:.3f} mm RMS about one pivot: the tip did not seat in the socket "
                     "(off-centre contacts beside it?), or the socket or tool moved during the run")
    offset_mm = float(np.linalg.norm(fit.pivot_point - (np.asarray(cell.pivot_m) * 1e3 + [0, 0, radius_mm]))) \
        if cell.pivot_m is not None else float("nan")
    undetermined = [f"tcp_{c}_mm" for c, s in zip("xyz", design.std) if not s <= MAX_STD_MM]
    gate_list = [gates.residual(rms, expected), gates.conditioning(fit.condition),
                 gates.identifiability(undetermined), seating,
                 gates.plausible_tool(frame, cell.tool, determines=tool_frame.TIP_ONLY),
                 gates.agrees_with_previous(frame, meta.get("tool_frame_before"), determines=tool_frame.TIP_ONLY)]
    params = [Parameter(f"tcp_{c}_mm", float(tcp_mm[j]), float(fit.std[j]), "mm") for j, c in enumerate("xyz")]
    params += [Parameter(f"pivot_{c}_mm", float(fit.pivot_point[j]), float(fit.pivot_std[j]), "mm")
               for j, c in enumerate("xyz")]
    notes += frame_notes
    notes.append(f"the pivot holds the centre of the tip's rounding; the TCP is that centre plus the tool radius "
                 f"{radius_mm:g} mm along the axis of the frame written (the z of {ref.source}): 0.1 deg of axis "
                 f"error moves it {radius_mm * np.deg2rad(0.1):.4f} mm; run tcf or tcp-laser first for a measured axis")
    extra = {"rejected_seats": rejected, "seat_residuals_mm": lengths.tolist(),
             "expected_tcp_error_mm": design.expected_error, "design_condition": design.condition,
             "tcp_std_mm": float(np.linalg.norm(fit.std)), "tip_centre_mm": fit.tool_point.tolist(),
             "pivot_off_cell_file_mm": offset_mm, "outlier_scale_mm": fit.scale,
             "orientation": f"kept from {ref.source}"}
    return Result(name, params, kept_residuals, float(expected), fit.condition, gate_list, tool_frame=frame,
                  notes=notes, extra=extra, determines=tool_frame.TIP_ONLY)
