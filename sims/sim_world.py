"""The in-process simulated cell: one arm, its light beams and one clock, shared by the sim devices.

The simulated robot, trigger, tracker and panel of :mod:`.sim_devices` all look at one
``SimWorld``, so a trigger sees the arm cross its beam and a tracker measures where the
arm really is. Time is simulated: a motion is integrated in controller cycles as fast as
the CPU allows, so a routine's sweep takes milliseconds of wall time in tests.

The arm is the fake UR controller's (:class:`~.arm_motion.MovingArm`: our own forward
kinematics of the robot model, trapezoidal joint and linear moves, 2 ms cycle), so the
in-process cell and the cell behind the real client libraries move the TCP along the
same path with the same timing.

Beam edges are timed between cycles, where the TCP's straight step crosses the beam's
radius, not at the cycle that first shows the new level: a real light barrier switches
when the tip gets there. The edge's timestamp adds the sensor's latency and a jitter
drawn uniformly from [-jitter, +jitter].
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..config.cells import Cell
from ..config.robot_files import load_robot
from ..drivers.interfaces import DeviceError, Edge, RobotSample, RobotState, TriggerEvent
from ..solvers.robot_model import KinematicModel
from .arm_motion import ArmKinematics, MovingArm, MotionFault
from .scene import LightBeam, model_from_spec

HOME_Q = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
SAMPLE_BUFFER_S = 120.0


@dataclass(frozen=True)
class Workspace:
    """The box the TCP must stay in, base frame, metres."""

    min_m: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))
    max_m: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))

    def contains(self, position_m) -> bool:
        p = np.asarray(position_m, dtype=float)
        return bool(np.all(p >= self.min_m) and np.all(p <= self.max_m))


@dataclass(frozen=True)
class SpeedLimits:
    """The cell's speed and acceleration ceilings; a command above them is refused, not clipped."""

    tcp_speed_m_s: float = 0.25
    tcp_accel_m_s2: float = 2.5
    joint_speed_rad_s: float = 1.5
    joint_accel_rad_s2: float = 4.0


@dataclass(frozen=True)
class BeamTiming:
    """How late and how unevenly the beam's sensor reports an edge."""

    latency_s: float = 0.0
    jitter_s: float = 0.0


def beam_crossing(beam: LightBeam, p0: np.ndarray, p1: np.ndarray) -> float | None:
    """Fraction s in [0, 1] of the step p0 -> p1 where the distance to the beam line
    equals its radius (the switching point), or None when the step does not cross it."""
    d = beam.direction / np.linalg.norm(beam.direction)
    a0 = (p0 - beam.point_m) - ((p0 - beam.point_m) @ d) * d
    step = (p1 - p0) - ((p1 - p0) @ d) * d
    qa, qb, qc = step @ step, 2.0 * (a0 @ step), a0 @ a0 - beam.radius_m**2
    if qa < 1e-30:
        return None
    disc = qb * qb - 4.0 * qa * qc
    if disc < 0.0:
        return None
    roots = [(-qb - np.sqrt(disc)) / (2.0 * qa), (-qb + np.sqrt(disc)) / (2.0 * qa)]
    inside0 = qc < 0.0
    # entering: the smaller root; leaving: the larger
    s = roots[1] if inside0 else roots[0]
    return float(np.clip(s, 0.0, 1.0))


class SimWorld:
    """The arm's true state, the beams around it and the simulated clock."""

    def __init__(self, model: KinematicModel, *, q0=HOME_Q, beams=(), workspace: Workspace = Workspace(),
                 limits: SpeedLimits = SpeedLimits(), beam_timing: BeamTiming = BeamTiming(),
                 cycle_s: float = 0.002, seed: int | None = 0):
        if len(q0) != model.n_joints:
            raise ValueError(f"q0 has {len(q0)} joints, {model.name} has {model.n_joints}")
        self.model = model
        self.kinematics = ArmKinematics(model)
        self.arm = MovingArm(self.kinematics, q0, cycle_s)
        self.cycle_s = cycle_s
        self.beams: list[LightBeam] = list(beams)
        self.workspace = workspace
        self.limits = limits
        self.beam_timing = beam_timing
        self.rng = np.random.default_rng(seed)
        self.t_s = 0.0
        self.state = RobotState.READY
        self.stop_reason = ""
        self._stop_after_motion_s: float | None = None
        self._blocked = {id(b): self._is_blocked(b, self.arm.tcp_pose[:3]) for b in self.beams}
        self._edges: list[TriggerEvent] = []  # device-stamped, not yet delivered
        self.samples: deque[RobotSample] = deque(maxlen=int(SAMPLE_BUFFER_S / cycle_s))
        self.samples.append(self._sample())

    # -- the state a device reads ----------------------------------------------------

    @property
    def tcp_pose(self) -> np.ndarray:
        return self.arm.tcp_pose.copy()

    @property
    def q(self) -> np.ndarray:
        return self.arm.q.copy()

    def digital_inputs(self) -> int:
        bits = 0
        for beam in self.beams:
            level = self._blocked[id(beam)] == beam.level_when_blocked
            bits |= int(level) << beam.channel
        return bits

    def _sample(self) -> RobotSample:
        return RobotSample(self.t_s, self.arm.q.copy(), self.arm.tcp_pose.copy(), self.digital_inputs())

    @staticmethod
    def _is_blocked(beam: LightBeam, position: np.ndarray) -> bool:
        return beam.distance_m(position) < beam.radius_m

    # -- faults ----------------------------------------------------------------------

    def protective_stop(self, why: str = "injected protective stop", *, after_motion_s: float | None = None) -> None:
        """Stop the arm dead now, or once the current or next motion has run that long."""
        if after_motion_s is not None:
            self._stop_after_motion_s = float(after_motion_s)
            self.stop_reason = why
            return
        self.arm.halt()
        self.state = RobotState.PROTECTIVE_STOP
        self.stop_reason = why

    def reset_protective_stop(self) -> None:
        """The operator unlocks the stop (as from the teach pendant)."""
        self.state = RobotState.READY
        self.stop_reason = ""
        self._stop_after_motion_s = None

    # -- time ------------------------------------------------------------------------

    def step(self) -> None:
        """Advance one controller cycle: move, time any beam edge, record a sample."""
        p_old = self.arm.tcp_pose[:3].copy()
        try:
            self.arm.step()
        except MotionFault as exc:
            self.t_s += self.cycle_s
            self.samples.append(self._sample())
            raise DeviceError("sim robot", str(exc)) from None
        t_old, self.t_s = self.t_s, self.t_s + self.cycle_s
        p_new = self.arm.tcp_pose[:3]
        for beam in self.beams:
            blocked = self._is_blocked(beam, p_new)
            if blocked != self._blocked[id(beam)]:
                self._blocked[id(beam)] = blocked
                s = beam_crossing(beam, p_old, p_new)
                t_edge = t_old + (self.cycle_s if s is None else s * self.cycle_s)
                timing = self.beam_timing
                t_edge += timing.latency_s + (self.rng.uniform(-timing.jitter_s, timing.jitter_s)
                                              if timing.jitter_s > 0 else 0.0)
                self._edges.append(TriggerEvent(t_edge, beam.channel,
                                                Edge.BLOCKED if blocked else Edge.CLEARED, True))
        self.samples.append(self._sample())
        if self._stop_after_motion_s is not None and self.arm.moving_s >= self._stop_after_motion_s:
            self._stop_after_motion_s = None
            self.protective_stop(self.stop_reason or "injected protective stop")

    def run_motion(self, timeout_s: float, device: str = "sim robot") -> None:
        """Step until the arm's motion ends; raises DeviceError on a stop or a fault."""
        n_max = int(np.ceil(timeout_s / self.cycle_s))
        for _ in range(n_max):
            if self.arm.motion is None:
                return
            self.step()
            if self.state is not RobotState.READY:
                raise DeviceError(device, f"{self.state.value}: {self.stop_reason}")
        self.arm.halt()
        raise DeviceError(device, f"motion did not finish within {timeout_s:g} s of simulated time")

    def idle(self, duration_s: float) -> None:
        """Let simulated time pass with the arm at rest (a device waiting)."""
        for _ in range(int(np.ceil(max(duration_s, 0.0) / self.cycle_s))):
            self.step()

    def take_edges(self, timeout_s: float = 0.0) -> list[TriggerEvent]:
        """Edges whose timestamp the clock has reached, idling up to timeout_s for the first one."""
        waited = 0.0
        while True:
            ready = [e for e in self._edges if e.t_s <= self.t_s]
            if ready or not self._edges or waited >= timeout_s:
                break
            self.step()
            waited += self.cycle_s
        self._edges = [e for e in self._edges if e.t_s > self.t_s]
        return sorted(ready, key=lambda e: e.t_s)


def world_of_cell(cell: Cell) -> SimWorld:
    """The world the in-process sim devices of `cell` share (the registry's shared object
    of the ``sim`` backends): its robot at home, its beam, workspace, limits and timing."""
    return SimWorld(load_robot(cell.robot), q0=cell.home_q_rad, beams=[model_from_spec(cell.beam)],
                    workspace=Workspace(cell.workspace_min_m, cell.workspace_max_m),
                    limits=SpeedLimits(**cell.limits), beam_timing=BeamTiming(**cell.trigger_timing))
