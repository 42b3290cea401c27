"""What every routine is: plan -> check the whole plan -> move and record -> dataset on
disk -> solve (a pure function in ``solvers``) -> gates -> result.

A routine is one module with one :class:`Routine` subclass and one row of the routine
table (:mod:`.table`: its name, its panel selector number and the section of the cell file
it owns, which the class declares alike); it reads and bounds its own options in
:meth:`Routine.read_options`, at cell load (Klipper style). :mod:`.registry` reads the table,
and everything else asks the registry. It gets its devices
through the driver interfaces only (the cell file picks the backends) and moves the arm
only through :class:`~.guard.GuardedRobot`, so every command passes the cell's limits.
Results of every routine have the same shape (:class:`Result`), and so have the designs
they judge before moving (:class:`PlanPromise`), so the daemon and the store can treat them alike.
"""
from __future__ import annotations

import abc
import contextlib
import json
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.reader import Section
from cellcal.config.robot_files import load_robot
from cellcal.drivers.interfaces import DeviceError, Operator, Robot, Tracker, TriggerInput
from cellcal.solvers.geometry import se3
from cellcal.solvers.tool_frames.verdict import Verdict
from cellcal.routines.framework.drawing import Drawing


class RoutineError(RuntimeError):
    """The routine could not run or solve; the message says what to fix (exit 1)."""


class NotForThisCell(RoutineError):
    """The cell cannot run this routine at all (a device, a second robot or a section it
    needs is missing): refused before anything moves, exit 2, panel result code 11."""


@dataclass(frozen=True)
class RunEnding:
    """How the run that produced a result ended: its result code's name, the reason it ended
    with and whether a tool frame was written to the controller."""

    code_name: str
    reason: str
    wrote: bool



class CalibrateFirst(RoutineError):
    """A check with nothing to judge against yet (no beam calibration for the cell): refused
    before anything moves, saying what to run first (exit 2, panel result code 15)."""


class CheckAlarm(RoutineError):
    """A check saw the tool too far from its stored frame to measure it (a sweep missed a
    beam, or blocked it where it should not): verdict alarm, nothing written (panel code 33)."""


class RoutineAborted(RuntimeError):
    """The run was aborted (operator, service stopping): no further command is sent."""


class PlanRefused(ValueError):
    """A planned move would leave the cell's limits; names the move and the limit (exit 2)."""


@dataclass(frozen=True)
class Move:
    """One motion command of a plan, in the robot's units (m, rad, rotation vectors).

    kind ``joint``: to ``q_rad``; ``linear``: the TCP to ``pose`` on a straight line;
    ``contact``: along ``direction`` at ``speed`` until contact, at most ``travel_m``.
    ``robot`` names the robot that moves (``a`` unless the cell has two); ``meeting``, for
    a move that brings the two robots' tool tips together, is the planned contact point
    (cell frame, m): only there may the tools come closer than the cell's clearance.
    """

    kind: str
    label: str
    speed: float  # rad/s for joint moves, m/s otherwise
    accel: float  # rad/s^2 for joint moves, m/s^2 otherwise
    q_rad: np.ndarray | None = None
    pose: np.ndarray | None = None
    direction: np.ndarray | None = None  # unit, base frame
    travel_m: float = 0.0
    robot: str = "a"
    meeting: np.ndarray | None = None

    @classmethod
    def joint(cls, label, q_rad, speed, accel, *, robot="a") -> "Move":
        return cls("joint", label, float(speed), float(accel), q_rad=np.asarray(q_rad, dtype=float), robot=robot)

    @classmethod
    def linear(cls, label, pose, speed, accel, *, robot="a", meeting=None) -> "Move":
        return cls("linear", label, float(speed), float(accel), pose=np.asarray(pose, dtype=float), robot=robot,
                   meeting=meeting)

    @classmethod
    def contact(cls, label, direction, speed, travel_m, accel=1.0, *, robot="a", meeting=None) -> "Move":
        d = np.asarray(direction, dtype=float)
        return cls("contact", label, float(speed), float(accel), direction=d / np.linalg.norm(d),
                   travel_m=float(travel_m), robot=robot, meeting=meeting)


@dataclass(frozen=True)
class Devices:
    """What a routine may use, behind the driver interfaces (None where the cell has none)."""

    robot: Robot
    trigger: TriggerInput | None = None
    tracker: Tracker | None = None
    operator: Operator | None = None  # who moves a fixture between setups (Routine.asks_operator)


@dataclass(frozen=True)
class Gate:
    """One quality check of a result: passed, the value, the limit, and why, in words."""

    name: str
    passed: bool
    value: float
    limit: float
    why: str

    def as_json(self) -> dict:
        return {"name": self.name, "passed": self.passed, "value": _finite(self.value),
                "limit": _finite(self.limit), "why": self.why}


@dataclass(frozen=True)
class Parameter:
    name: str
    value: float
    std: float | None
    unit: str

    def as_json(self) -> dict:
        return {"name": self.name, "value": self.value, "std": self.std, "unit": self.unit}


@dataclass
class Result:
    """The same shape for every routine.

    ``tool_frame`` is the flange -> TCP frame [x, y, z, rx, ry, rz] (m, rad) that would be
    written back, for routines that find one; ``frame`` a base frame for those that find
    that. ``passed_gates`` is True only when every gate passed: the result may be written back
    (``passed_gates`` in the JSON; whether it was is the daemon's record). ``drawing`` is what the run's
    report draws of the measurements against the fitted geometry (:mod:`.drawing`).
    """

    routine: str
    parameters: list[Parameter]
    residuals_mm: np.ndarray  # (N,) or (N, k): what the fit leaves per measurement
    expected_noise_mm: float
    condition: float
    gates: list[Gate]
    tool_frame: np.ndarray | None = None
    frame: dict | None = None
    notes: list[str] = field(default_factory=list)
    extra: dict = field(default_factory=dict)  # routine-specific numbers, units in the keys
    # what of `tool_frame` the routine measured, of "tip" and "axis" (routines/framework/tool_frame.py); the rest
    # of the frame is the controller's from before the run. Empty for routines that find no tool frame.
    determines: frozenset[str] = frozenset()
    dataset: str | None = None
    cycle_time_s: float | None = None
    # the controller's tool frame before the run (m, rad), from the run's context; None: not known
    tool_frame_before: np.ndarray | None = None
    sim_truth: dict | None = None
    drawing: Drawing | None = None
    # a check (tcp-check): ok (nothing to write), corrected (write tool_frame), alarm or drift
    # (never write; the service ends the run with CHECK_ALARM or, for drift, which the service
    # decides from the store, DRIFT_ALARM); None for a calibration. Its word is given as one too.
    verdict: Verdict | None = None
    # the measured change of the tool against the frame it was compared with, as the panel
    # carries it: {"x_mm", "y_mm", "z_mm", "tilt_x_deg", "tilt_y_deg"} (flange frame; None: not determined)
    change: dict | None = None

    def __post_init__(self):
        if self.verdict is not None:
            self.verdict = Verdict(self.verdict)

    @property
    def passed_gates(self) -> bool:
        return bool(self.gates) and all(g.passed for g in self.gates)

    @property
    def residual_rms_mm(self) -> float:
        r = np.asarray(self.residuals_mm, dtype=float)
        r = r.reshape(len(r), -1) if r.size else r.reshape(0, 1)
        return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) if len(r) else float("nan")

    def reasons(self) -> list[str]:
        """Why the result must not be written back (empty when it may)."""
        if not self.gates:
            return ["no gate was evaluated"]
        return [f"{g.name}: {g.why}" for g in self.gates if not g.passed]

    def as_json(self) -> dict:
        out = {"routine": self.routine, "dataset": self.dataset, "passed_gates": self.passed_gates,
               "reasons": self.reasons(), "parameters": [p.as_json() for p in self.parameters],
               "residual_rms_mm": _finite(self.residual_rms_mm), "expected_noise_mm": self.expected_noise_mm,
               "n_measurements": int(len(self.residuals_mm)), "condition": _finite(self.condition),
               "gates": [g.as_json() for g in self.gates], "notes": list(self.notes)}
        if self.tool_frame is not None:
            out["tool_frame"] = tool_frame_json(self.tool_frame)
            out["determines"] = sorted(self.determines)
        if self.frame is not None:
            out["frame"] = self.frame
        if self.cycle_time_s is not None:
            out["cycle_time_s"] = self.cycle_time_s
        if self.verdict is not None:
            out["verdict"] = self.verdict.value
        if self.change is not None:
            out["change"] = self.change
        out.update(self.extra)
        if self.tool_frame_before is not None:
            out["tool_frame_before"] = [float(v) for v in np.ravel(self.tool_frame_before)]
        if self.sim_truth is not None:
            out["sim_truth"] = self.sim_truth
        return out

    def json_text(self) -> str:
        return json.dumps(self.as_json(), default=jsonable)


def jsonable(value):
    """``json.dumps(..., default=jsonable)``: numpy arrays and scalars as plain JSON."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    raise TypeError(f"not JSON-able: {type(value).__name__}")


def tool_frame_json(pose) -> dict:
    """A tool frame as people and controllers read it: mm, and a rotation vector in degrees."""
    pose = np.asarray(pose, dtype=float)
    return {"x_mm": pose[0] * 1e3, "y_mm": pose[1] * 1e3, "z_mm": pose[2] * 1e3,
            "rx_deg": math.degrees(pose[3]), "ry_deg": math.degrees(pose[4]), "rz_deg": math.degrees(pose[5]),
            "pose_m_rad": pose.tolist()}


FRAME_KEYS = ("x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg")  # tool_frame_json's numbers, in order


def frame_text(frame, angle_digits: int = 4, lean: bool = True) -> str:
    """A frame on one line as people read it: ``x 1.2345 y .. z .. mm, rotation vector rx 0.1234
    ry .. rz .. deg`` and, for a tool frame (`lean`), how its z axis leans from the flange's z:
    ``(z axis leans 0.0486 deg toward x, -0.4838 deg toward y)``, the numbers a routine's
    ``axis_tilt_x_deg`` / ``axis_tilt_y_deg`` give for a tool drawn along the flange's z (a lean
    toward x is a turn about y: the rotation vector's ry, not its rx).
    `frame` is a pose [x, y, z, rx, ry, rz] (m, rad) or a dict with :func:`tool_frame_json`'s keys
    (a base frame a routine found has them too; give ``lean=False`` for one)."""
    f = frame if isinstance(frame, dict) else tool_frame_json(frame)
    a = angle_digits
    text = (f"x {f['x_mm']:.4f} y {f['y_mm']:.4f} z {f['z_mm']:.4f} mm, "
            f"rotation vector rx {f['rx_deg']:.{a}f} ry {f['ry_deg']:.{a}f} rz {f['rz_deg']:.{a}f} deg")
    if lean:
        toward_x, toward_y = np.degrees(se3.z_axis_lean(np.radians([f["rx_deg"], f["ry_deg"], f["rz_deg"]])))
        text += f" (z axis leans {toward_x:.{a}f} deg toward x, {toward_y:.{a}f} deg toward y)"
    return text


def gate_line(gate) -> str:
    """A quality gate on one line: ``[pass] name: why`` or ``[FAIL] name: why``. `gate` is a
    :class:`Gate` or its JSON (:meth:`Gate.as_json`, as a result's JSON and the store give it)."""
    g = gate.as_json() if isinstance(gate, Gate) else gate
    return f"[{'pass' if g['passed'] else 'FAIL'}] {g['name']}: {g['why']}"


def _finite(value):
    value = float(value)
    return value if math.isfinite(value) else None


Progress = Callable[[str], None]


@contextlib.contextmanager
def drawn_tool(robot, tool_pose, before=None):
    """The controller on the tool as drawn while a routine measures (its moves and contacts
    are planned for that tool); the tool frame from before (yielded) given back afterwards,
    also after a fault, as far as the robot still takes it (the service gives it back once
    the robot is ready again). `before`: that frame when the run knows it (its context), else
    it is read here."""
    before = np.asarray(robot.tool_frame() if before is None else before, dtype=float)
    robot.set_tcp(tool_pose)
    try:
        yield before
    except BaseException:
        # a fault or an interrupt (Ctrl-C) may land while a move is still under way, and a
        # controller that is moving does not take a new tool frame: stop it first
        with contextlib.suppress(DeviceError):
            robot.stop()
        with contextlib.suppress(DeviceError):
            robot.set_tcp(before)
        raise
    else:
        with contextlib.suppress(DeviceError):
            robot.set_tcp(before)


@dataclass(frozen=True)
class PlanPromise:
    """What a routine's plan can give, judged before anything moves at the arm's stated
    repeatability (:meth:`Routine.design`): the same shape for every routine.

    ``expected_error`` is the 1-sigma error the plan should leave on what the routine
    measures, in ``unit``; ``condition`` the design's condition number; ``details`` the
    routine's own further numbers, units in the keys.
    """

    condition: float
    expected_error: float
    unit: str
    details: dict = field(default_factory=dict)


class Routine(abc.ABC):
    """One measuring routine. Subclasses declare ``name`` (``tcp-laser``: ``cellcal run``'s
    and the store's), ``section`` (``tcp_laser``: theirs in the cell file) and ``selector``
    (the operator panel's routine selector value, or None where the panel cannot select
    it), and implement the four steps. :mod:`.registry` refuses two routines that claim one
    name, section or selector."""

    name: str = ""
    section: str = ""
    selector: int | None = None
    needs: tuple[str, ...] = ("robot",)  # device kinds the cell must have
    robots: tuple[str, ...] = ("a",)  # the cell's robots it moves (and sets on the tool as drawn)

    def __init__(self, cell: Cell, options):
        self.cell = cell
        self.options = options
        self.context = None  # the run's (:class:`~.context.RunContext`, given by the runner), None for one built alone
        self._model = None

    @property
    def robot_model(self):
        """Robot a's kinematic model: the run's, loaded once at its start (else loaded here, once)."""
        if self.context is not None:
            return self.context.robot_model
        if self._model is None:
            self._model = load_robot(self.cell.robot)
        return self._model

    @property
    def tool_frame_before(self) -> np.ndarray | None:
        """The controller's tool frame before the run, as the run read it at its start; None
        where the routine was built without a run's context that knows it."""
        return None if self.context is None else self.context.tool_frame_before

    @classmethod
    @abc.abstractmethod
    def read_options(cls, section: Section, cell: Cell):
        """Read and bound every option of the routine's section (``section.done()`` at the
        end); raise through ``section.fail`` naming the key. Runs at cell load."""

    @abc.abstractmethod
    def plan(self) -> list[Move]:
        """Every motion of the routine, from the cell file alone (nothing moves here)."""

    @abc.abstractmethod
    def measure(self, devices: Devices, robot: "Robot", plan: list[Move], progress: Progress):
        """Move through the plan with the guarded `robot` and record; returns the dataset
        (a :class:`~.records.Dataset`). Raises DeviceError on a device fault."""

    @classmethod
    @abc.abstractmethod
    def solve(cls, dataset, cell: Cell, options) -> Result:
        """The result of a recorded dataset: a pure solver call, residuals, gates."""

    def design(self) -> PlanPromise | None:
        """What the plan can give, judged before anything moves; None for a routine that
        judges no design before it moves."""
        return None

    def asks_operator(self) -> bool:
        """True when the run stops and waits for the operator's confirm (``Devices.operator``),
        as this cell file configures the routine: the caller must give it an operator."""
        return False

    @classmethod
    def with_history(cls, cell: Cell, options, last_result) -> tuple[object, str | None]:
        """The routine's options (read from its section) as the service runs it, given what
        earlier runs found (`last_result(routine, any_tool=False)`: (run id, result JSON) of the
        newest run of that routine for the tool this run is for, or for any tool, that passed
        every gate, or None), and a note saying what was taken from them; the options unchanged
        and None for a routine that needs nothing of the past."""
        return options, None

