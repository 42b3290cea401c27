"""The in-process simulated cell: one arm, its light beams and one clock, shared by the sim devices.

The simulated robot, trigger, tracker and panel of :mod:`.devices` all look at one
``SimWorld``, so a trigger sees the arm cross its beam and a tracker measures where the
arm really is. Time is simulated: a motion is integrated in controller cycles as fast as
the CPU allows, so a routine's sweep takes milliseconds of wall time in tests.

The arm is the fake UR controller's (:class:`~cellcal.sims.physics.arm_motion.MovingArm`: our own forward
kinematics of the robot model, trapezoidal joint and linear moves, 2 ms cycle), so the
in-process cell and the cell behind the real client libraries move the TCP along the
same path with the same timing.

What the arm really does is the cell's :class:`~cellcal.sims.physics.truth.CellTruth`: the joints move the
arm as built (not as drawn), the real tool body blocks the real beams and touches the
real stylus, and each motion ends off by the arm's repeatability. The controller side
(reported TCP pose, the TCP a routine sets) computes with the drawing, as a real
controller does. Beam edges are timed between cycles, where the tool's straight step
crosses the beam, not at the cycle that first shows the new level: a real light
barrier switches when the tool gets there. The edge's timestamp adds the sensor's
latency and a jitter drawn uniformly from [-jitter, +jitter].

The pivot is a conical socket (:class:`PivotSocket`). A contact search that meets it
ends as a compliant one (force mode) does: the cone guides the tip's rounding to its
seat and the arm comes to rest there, off by its repeatability; a tip that lands on the
flat beside the socket stays where it landed. The kinematic-fixture plate's sockets seat
the same way; a stylus plate's balls (:class:`FixtureBall`) stop the search where the
tip's rounding meets one, nothing guiding it further.

A tool change (:meth:`SimWorld.mount_tool`) puts another tool of the cell's table on the
flange as it really is; where the cell file wires the tool changer's id to the robot's digital
inputs (``mounted: {robot_inputs: [...]}``), they carry it.

A two-robot cell has one world per arm, each in its own base frame and on its own
clock (:func:`world_of_cell` builds both and links them; ``of_robot`` picks one). Robot
a's needle ends in a small centring cup facing out along its axis; robot b's needle
tip, searched along its axis onto it, is guided by the cup to a's real tip as by the
pivot's cone, and rests there off by its repeatability (the handshake's meeting). A
tip that lands beside the cup stays where it landed.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from cellcal.config.cells import Cell
from cellcal.config.robot_files import load_robot
from cellcal.drivers.interfaces import DeviceError, RobotSample, RobotState, TriggerEvent
from cellcal.solvers.geometry.robot_model import KinematicModel
from cellcal.sims.physics.arm_motion import ArmKinematics, JointMove, MovingArm, MotionFault
from cellcal.sims.physics.scene import LightBeam
from cellcal.sims.physics.truth import (CellTruth, beam_blocked, beam_edges, meeting_rest_q, meeting_touch, pivot_rest_q, real_tool_body,
                    real_tool_tip, repeat_offset_m, tool_axis_m, tool_changer_inputs, tool_id_bits, touching,
                    truth_of_cell)

HOME_Q = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
SAMPLE_BUFFER_S = 120.0
PIVOT_CONE_DEG = 90.0  # included angle of the pivot socket (a countersink)
PIVOT_RIM_RADIUS_M = 0.004  # its opening: a rounding whose centre is over it slides to the seat
PIVOT_FACE_RADIUS_M = 0.020  # the fixture's flat top around the socket
PIVOT_SLIDE_SPEED_RAD_S = 0.05  # how fast the compliant arm follows the socket to rest


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


class SimWorld:
    """The arm's true state, the beams around it and the simulated clock."""

    def __init__(self, model: KinematicModel, *, q0=HOME_Q, truth: CellTruth | None = None,
                 workspace: Workspace = Workspace(), limits: SpeedLimits = SpeedLimits(),
                 cycle_s: float = 0.002, seed: int | None = 0):
        if len(q0) != model.n_joints:
            raise ValueError(f"q0 has {len(q0)} joints, {model.name} has {model.n_joints}")
        self.model = model
        self.truth = truth if truth is not None else CellTruth(np.asarray(model.nominal, float), None)
        self.kinematics = ArmKinematics(model)  # the controller's: the drawing
        self.physics = ArmKinematics(model, self.truth.arm_params)  # the arm as built
        self.arm = MovingArm(self.kinematics, q0, cycle_s)
        self.cycle_s = cycle_s
        self.beams: list[LightBeam] = list(self.truth.beams)
        self.contacts = [c for c in (self.truth.stylus, *self.truth.contacts) if c is not None]
        self.pivot = pivot_socket(self.truth)
        self.plate_step = 1  # the placement a plate the operator moves is at (CellTruth.plate_moved)
        self.sockets = fixture_sockets(self.truth)  # the kinematic-fixture plate's, each seats as the pivot does
        self._touched: PivotSocket | None = None  # the socket the last contact search met
        self._pivot_fouling: list[np.ndarray] = []
        self.partner = None  # () -> (tip, axis): the other robot's real tip and tool axis, this base frame
        self.arms = {"a": self}  # every arm of the cell by name (of_robot)
        self.workspace = workspace
        self.limits = limits
        self.tool_inputs: tuple = ()  # the digital inputs carrying the tool changer's id, least significant first
        self.rng = np.random.default_rng(seed)
        self.t_s = 0.0
        self.state = RobotState.READY
        self.stop_reason = ""
        self._stop_after_motion_s: float | None = None
        self._repeat_offset_m = np.zeros(3)
        self._motion = None
        self._body = self.tool_body()
        self._blocked = {id(b): beam_blocked(b, self._body, self.tool_radius_m) for b in self.beams}
        self._edges: list[TriggerEvent] = []  # device-stamped, not yet delivered
        self.samples: deque[RobotSample] = deque(maxlen=int(SAMPLE_BUFFER_S / cycle_s))
        self.samples.append(self._sample())

    # -- the state a device reads ----------------------------------------------------

    @property
    def tcp_pose(self) -> np.ndarray:
        """The TCP pose the controller reports (its drawing of the arm, its TCP setting)."""
        return self.arm.tcp_pose.copy()

    @property
    def q(self) -> np.ndarray:
        return self.arm.q.copy()

    @property
    def tool_radius_m(self) -> float:
        return 0.0 if self.truth.tool is None else self.truth.tool.radius_m

    def tool_body(self, q=None) -> tuple[np.ndarray, np.ndarray]:
        """The real tool's core segment (base frame, m) at joints q (default: now); a point at
        the controller's TCP when the truth has no tool."""
        q = self.arm.q if q is None else q
        return real_tool_body(self.truth, self.physics, self.kinematics, q, self.arm.tcp_offset, self._repeat_offset_m)

    def tool_tip_m(self) -> np.ndarray:
        """Where the real tool tip is now (what a tracker target at the tip measures)."""
        return real_tool_tip(self.truth, self.physics, self.arm.q, self._body)

    def touching(self) -> bool:
        return any(touching(c, self._body, self.tool_radius_m) for c in self.contacts)

    def pivot_touch(self) -> str | None:
        """'seat' or 'face' when the real tip's rounding touches the pivot fixture (see
        :meth:`PivotSocket.touch`), 'ball' when it touches a stylus plate's ball (no settling),
        None when clear or the cell has no pivot."""
        for socket in ([self.pivot] if self.pivot is not None else []) + self.sockets:
            touch = socket.touch(self._body[0], self.tool_radius_m)
            if touch is not None:
                self._touched = socket
                return touch
        return None

    def of_robot(self, name: str) -> "SimWorld":
        """The world of the cell's robot `name` (``a`` is this one)."""
        return self.arms[name]

    def partner_touch(self) -> str | None:
        """'seat' or 'face' when the real tip has reached the other robot's tip (the plane
        through it across its axis): 'seat' within its cup's rim, 'face' beside it on the
        cup's face; None when not there or with no other robot."""
        if self.partner is None or self.truth.tool is None:
            return None
        return meeting_touch(self.tool_tip_m(), *self.partner())

    def settle_on_partner(self, device: str = "sim robot") -> None:
        """The end of a compliant search that met the other robot's cup: the real tip
        slides to the other's real tip and rests there, off by this arm's repeatability."""
        offset = repeat_offset_m(self.truth, self.rng)
        try:
            q_rest = meeting_rest_q(self.truth, self.physics, self.arm.q, self.partner()[0], offset)
        except MotionFault as exc:
            raise DeviceError(device, f"cannot settle on the other robot's tip: {exc}") from None
        self._slide_to(q_rest, offset, device)

    def settle_in_pivot(self, device: str = "sim robot") -> None:
        """The end of a compliant contact search that met the socket: the arm, orientation
        held, follows the cone until the tip's rounding rests in it. The rest is a new pose,
        off by the arm's repeatability like every other; the controller reports its joints."""
        offset = repeat_offset_m(self.truth, self.rng)
        socket = self._touched if self._touched is not None else self.pivot
        seat = socket.seat_m + (self._pivot_fouling.pop(0) if self._pivot_fouling else 0.0)
        try:
            q_rest = pivot_rest_q(self.truth, self.physics, self.arm.q, seat, offset)
        except MotionFault as exc:
            raise DeviceError(device, f"cannot settle in the pivot: {exc}") from None
        self._slide_to(q_rest, offset, device)

    def _slide_to(self, q_rest, offset, device: str) -> None:
        """The compliant arm follows a guide to rest at `q_rest` (that rest's draw `offset`)."""
        slide = JointMove(self.arm.q, q_rest, PIVOT_SLIDE_SPEED_RAD_S, self.limits.joint_accel_rad_s2)
        self.arm.start(slide)
        self._motion, self._repeat_offset_m = slide, offset  # this rest's draw, not a fresh one
        self.run_motion(slide.profile.duration + 1.0, device)

    def place_plate(self, step: int) -> None:
        """The operator moves the kinematic-fixture plate to placement `step` (1, 2, ...: the cell
        file's order) as it really lies there; nothing changes for plates fixed in the cell."""
        self.plate_step = int(step)
        self.sockets = fixture_sockets(self.truth, self.plate_step)
        self._touched = None

    def foul_pivot(self, offset_m) -> None:
        """Swarf in the socket: the next seat comes to rest `offset_m` (base frame) off."""
        self._pivot_fouling.append(np.asarray(offset_m, dtype=float))

    @property
    def mounted_tool(self) -> int:
        """The id of the tool on the flange (0: none, or a cell without a tool table)."""
        return self.truth.tool_id

    def mount_tool(self, tool_id: int, device: str = "sim robot") -> None:
        """A tool change: tool `tool_id` of the cell's table as it really is goes on the flange
        (0: none, the bare flange); its body now blocks the beams and touches the fixtures, and
        the tool changer's id shows on the digital inputs (:attr:`tool_inputs`). The controller's
        tool frame is left as it was. Raises DeviceError while the arm moves, ValueError for an
        id the table does not have."""
        if self.arm.motion is not None:
            raise DeviceError(device, "the arm is moving: a tool is changed with the arm at rest")
        self.truth = self.truth.with_tool(tool_id)
        self._tool_put_there()

    def bend_tool(self, shift_m, device: str = "sim robot") -> None:
        """The mounted tool's real tip moved by `shift_m` (flange frame, m): bent, or knocked on the
        flange. The controller's tool frame is left as it was. Raises DeviceError while the arm moves,
        ValueError with no tool mounted."""
        if self.arm.motion is not None:
            raise DeviceError(device, "the arm is moving: a tool is bent with the arm at rest")
        self.truth = self.truth.with_tool_bent(shift_m)
        self._tool_put_there()

    def _tool_put_there(self) -> None:
        """Another real tool on the flange: the fixtures it meets and the beams it blocks, put there
        (not moved: no edges)."""
        self.pivot = pivot_socket(self.truth)
        self.sockets = fixture_sockets(self.truth, self.plate_step)
        self._body = self.tool_body()
        self._blocked = {id(b): beam_blocked(b, self._body, self.tool_radius_m) for b in self.beams}
        self._edges = []  # put there, not moved: no edges

    def digital_inputs(self) -> int:
        bits = tool_id_bits(self.mounted_tool, self.tool_inputs)
        for beam in self.beams:
            level = self._blocked[id(beam)] == beam.level_when_blocked
            bits |= int(level) << beam.channel
        return bits

    def _sample(self) -> RobotSample:
        return RobotSample(self.t_s, self.arm.q.copy(), self.arm.tcp_pose.copy(), self.digital_inputs())

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
        if self.arm.motion is not None and self.arm.motion is not self._motion:
            self._motion = self.arm.motion  # a new motion ends a little off: repeatability
            self._repeat_offset_m = repeat_offset_m(self.truth, self.rng)
        body_old = self._body
        try:
            self.arm.step()
        except MotionFault as exc:
            self.t_s += self.cycle_s
            self.samples.append(self._sample())
            raise DeviceError("sim robot", str(exc)) from None
        t_old, self.t_s = self.t_s, self.t_s + self.cycle_s
        self._body = self.tool_body()
        self._edges += beam_edges(self.truth, self.beams, self._blocked, body_old, self._body, t_old,
                                  self.cycle_s, self.rng)
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


@dataclass(frozen=True)
class PivotSocket:
    """The pivot as built: a conical socket opening upwards in a flat-topped fixture, cut so
    that a vertical tool of `tool_radius_m` rests with its tip at `point_m` (the pivot's
    real place). A rounded tip rests with its centre on the socket's axis at the depth the
    cone and its radius give, whatever the tool's tilt (up to where the shank meets the
    rim, 90 deg minus half the cone angle)."""

    point_m: np.ndarray
    tool_radius_m: float
    half_angle_rad: float = np.deg2rad(PIVOT_CONE_DEG / 2.0)
    rim_radius_m: float = PIVOT_RIM_RADIUS_M
    face_radius_m: float = PIVOT_FACE_RADIUS_M

    @property
    def seat_m(self) -> np.ndarray:
        """Where the centre of the tip's rounding rests."""
        return np.asarray(self.point_m, dtype=float) + [0.0, 0.0, self.tool_radius_m]

    @property
    def apex_m(self) -> np.ndarray:
        return self.seat_m - [0.0, 0.0, self.tool_radius_m / np.sin(self.half_angle_rad)]

    def touch(self, centre_m, radius_m: float) -> str | None:
        """Whether a rounding of `radius_m` centred at `centre_m` touches the fixture: 'seat'
        when its centre is over the opening (the contact pushes it towards the axis, so a
        compliant search slides it to the seat: the capture range is the rim's radius),
        'face' when it lands on the flat top beside the socket (it stays there, off-centre),
        None when clear. Judged in the fixture's section through the centre: the cone's
        wall from the apex to the rim, then the top face to the fixture's edge."""
        d = np.asarray(centre_m, dtype=float) - self.apex_m
        rho, h = float(np.hypot(d[0], d[1])), float(d[2])
        depth = self.rim_radius_m / np.tan(self.half_angle_rad)
        # the section lies within rho <= face radius and 0 <= h <= depth: a centre farther than
        # the radius from that box touches nothing (exactly the answer below, checked every cycle)
        if rho > self.face_radius_m + radius_m or h > depth + radius_m or h < -radius_m:
            return None
        section = (((0.0, 0.0), (self.rim_radius_m, depth)), ((self.rim_radius_m, depth), (self.face_radius_m, depth)))
        if min(_distance_2d((rho, h), a, b) for a, b in section) > radius_m:
            return None
        return "seat" if rho < self.rim_radius_m else "face"


def _distance_2d(point, a, b) -> float:
    p, a, b = np.asarray(point), np.asarray(a), np.asarray(b)
    t = float(np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0))
    return float(np.linalg.norm(a + t * (b - a) - p))


def pivot_socket(truth: CellTruth) -> PivotSocket | None:
    """The truth's pivot as a socket for its tool (None without a pivot or a tool)."""
    if truth.pivot_m is None or truth.tool is None:
        return None
    return PivotSocket(np.asarray(truth.pivot_m, dtype=float), truth.tool.radius_m)


def world_of_cell(cell: Cell) -> SimWorld:
    """The world the in-process sim devices of `cell` share (the registry's shared object
    of the ``sim`` backends): its robot at home, its truth, workspace and limits. In a
    two-robot cell, robot b's world too (``of_robot("b")``), in b's base frame, with the
    cell's box carried into it, and each arm's tool visible to the other."""
    model = load_robot(cell.robot)
    limits = SpeedLimits(**{k: v for k, v in cell.limits.items() if k in SpeedLimits.__dataclass_fields__})
    box = Workspace(cell.workspace_min_m, cell.workspace_max_m)
    world = SimWorld(model, q0=cell.home_q_rad, truth=truth_of_cell(cell, model), workspace=box, limits=limits)
    world.tool_inputs = tool_changer_inputs(cell)
    if world.truth.second is not None:
        b = cell.robots["b"]
        other = SimWorld(load_robot(b.robot), q0=b.home_q_rad, truth=world.truth.for_second(),
                         workspace=_box_in(box, b.base_matrix), limits=limits, seed=1)
        link_tips(world, other, world.truth.second.base)
        world.arms = other.arms = {"a": world, "b": other}
    return world


def link_tips(a: SimWorld, b: SimWorld, base_b: np.ndarray) -> None:
    """Let b's tool find a's tip: b's partner is a's real tip and axis in b's base frame
    (`base_b`: b's base -> a's base, the truth)."""
    rotation, position = base_b[:3, :3], base_b[:3, 3]
    b.partner = lambda: (rotation.T @ (a.tool_tip_m() - position), rotation.T @ tool_axis_m(a.tool_body()))


def _box_in(box: Workspace, base: np.ndarray) -> Workspace:
    """The smallest box in a robot's base frame that holds the cell's box (its controller
    keeps a box of its own; the guard holds the cell's exactly)."""
    corners = np.array(np.meshgrid(*zip(box.min_m, box.max_m))).reshape(3, -1).T
    local = (corners - base[:3, 3]) @ base[:3, :3]
    return Workspace(local.min(axis=0), local.max(axis=0))


@dataclass(frozen=True)
class FixtureBall:
    """A stylus plate's ball as built: a contact search stops where the tip's rounding touches it
    (sphere on sphere); nothing guides the tip, so the arm rests where it stopped."""

    centre_m: np.ndarray
    radius_m: float

    def touch(self, centre_m, radius_m: float) -> str | None:
        """'ball' when a rounding of `radius_m` centred at `centre_m` touches the ball, None when clear."""
        gap = np.linalg.norm(np.asarray(centre_m, dtype=float) - self.centre_m) - self.radius_m - radius_m
        return "ball" if gap <= 0.0 else None


def fixture_sockets(truth: CellTruth, step: int = 1) -> list:
    """The kinematic-fixture plate's sockets as really placed, as sockets for the mounted tool (a
    plate the operator moves: those of placement `step`, :meth:`CellTruth.plate_sockets`); a stylus
    plate's balls (:class:`FixtureBall`), which a search touches without settling."""
    if truth.plate_ball_radius_m is not None:
        return [FixtureBall(np.asarray(point, dtype=float), truth.plate_ball_radius_m)
                for _, _, point in truth.plate_sockets(step)]
    if truth.tool is None:
        return []
    return [PivotSocket(np.asarray(point, dtype=float), truth.tool.radius_m)
            for _, _, point in truth.plate_sockets(step)]
