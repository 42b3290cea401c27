"""In-process simulated cell devices behind the driver interfaces, registered as "sim".

A cell file says ``robot: {driver: sim}`` (and the same for trigger, tracker, panel);
the driver registry builds one :class:`~.world.SimWorld` per cell
(:func:`~.world.world_of_cell`, the ``sim`` backends' shared object) and hands it
to each, so the trigger fires when the simulated arm crosses the beam and the tracker
measures where the arm is. Built on their own (no ``world``), each device
gets a private world of a UR10e at home, which is enough for unit tests of one device.

Nothing here sleeps: waiting (a motion, ``events(timeout_s)``) advances simulated time.
"""
from __future__ import annotations

import numpy as np

from cellcal.config.robot_files import load_robot
from cellcal.drivers.interfaces import (ContactResult, DeviceError, OperatorPanel, Robot, RobotSample,
                                  RobotState, StoredToolFrame, Tracker, TrackerMeasurement, TriggerEvent, TriggerInput)
from cellcal.sims.physics.arm_motion import JointMove, LinearMove, MotionFault, SpeedLinear
from cellcal.sims.physics.kinematic_arm import TrackerNoise
from cellcal.sims.physics.scene import model_from_spec
from cellcal.sims.inproc.world import SimWorld

MOTION_TIMEOUT_MARGIN_S = 2.0
STORED_SLOTS = 4  # tool frames kept for the program's start: a UR's register blocks from register 24


def default_world() -> SimWorld:
    return SimWorld(load_robot("ur10e"))


def _positive(device: str, what: str, value: float, limit: float) -> float:
    value = float(value)
    if not np.isfinite(value) or value <= 0:
        raise DeviceError(device, f"{what} {value!r} must be a positive number")
    if value > limit:
        raise DeviceError(device, f"{what} {value:g} is above the cell's limit {limit:g}")
    return value


class SimRobot(Robot):
    """The simulated arm: every command checked against the cell's limits before it moves."""

    def __init__(self, world: SimWorld | None = None, *, contacts=()):
        self.world = world or default_world()
        self.name = f"sim robot ({self.world.model.name})"
        # surfaces that end move_until_contact: ContactPlane/ContactSphere, or their cell-file form
        self.contacts = [model_from_spec(dict(c)) if isinstance(c, dict) else c for c in contacts]
        self._closed = False
        # slot -> the frame kept for the program's start, as a UR's input register blocks from register
        # 24 (STORED_SLOTS of them); each as a controller after its restart: none stored
        self._stored = {slot: StoredToolFrame(np.zeros(6), 0) for slot in range(STORED_SLOTS)}

    # -- checks ----------------------------------------------------------------------

    def _ready(self) -> None:
        if self._closed:
            raise DeviceError(self.name, "closed")
        if self.world.state is not RobotState.READY:
            raise DeviceError(self.name, f"not ready: {self.world.state.value} ({self.world.stop_reason})")

    def _check_joints(self, q: np.ndarray) -> None:
        limits = self.world.model.joint_limits
        if q.shape != (self.world.model.n_joints,) or not np.all(np.isfinite(q)):
            raise DeviceError(self.name, f"joint target must be {self.world.model.n_joints} finite numbers")
        if limits is not None:
            outside = [i for i, (v, (lo, hi)) in enumerate(zip(q, limits)) if not lo <= v <= hi]
            if outside:
                raise DeviceError(self.name, f"joint target outside the joint limits at joint(s) {outside}")

    def _check_position(self, position_m: np.ndarray, what: str) -> None:
        ws = self.world.workspace
        if not ws.contains(position_m):
            raise DeviceError(self.name, f"{what} {np.round(position_m, 4).tolist()} m is outside the "
                                         f"workspace box {ws.min_m.tolist()}..{ws.max_m.tolist()} m")

    # -- motion ----------------------------------------------------------------------

    def move_j(self, q_rad, speed_rad_s: float, accel_rad_s2: float) -> None:
        self._ready()
        limits = self.world.limits
        speed = _positive(self.name, "joint speed", speed_rad_s, limits.joint_speed_rad_s)
        accel = _positive(self.name, "joint acceleration", accel_rad_s2, limits.joint_accel_rad_s2)
        q = np.asarray(q_rad, dtype=float)
        self._check_joints(q)
        self._check_position(self.world.kinematics.tcp_pose(q, self.world.arm.tcp_offset)[:3], "joint target's TCP")
        motion = self.world.arm.start(JointMove(self.world.arm.q, q, speed, accel))
        self.world.run_motion(motion.profile.duration + MOTION_TIMEOUT_MARGIN_S, self.name)

    def move_l(self, tcp_pose, speed_m_s: float, accel_m_s2: float) -> None:
        self._ready()
        limits = self.world.limits
        speed = _positive(self.name, "TCP speed", speed_m_s, limits.tcp_speed_m_s)
        accel = _positive(self.name, "TCP acceleration", accel_m_s2, limits.tcp_accel_m_s2)
        pose = np.asarray(tcp_pose, dtype=float)
        if pose.shape != (6,) or not np.all(np.isfinite(pose)):
            raise DeviceError(self.name, "TCP target must be 6 finite numbers [x, y, z, rx, ry, rz]")
        # the whole straight path lies in the box when both ends do (the box is convex)
        self._check_position(pose[:3], "TCP target")
        arm = self.world.arm
        try:
            motion = LinearMove(self.world.kinematics, arm.q, arm.tcp_offset, pose, speed, accel)
        except MotionFault as exc:
            raise DeviceError(self.name, str(exc)) from None
        self._check_joints(motion.q_end)
        arm.start(motion)
        self.world.run_motion(motion.profile.duration + MOTION_TIMEOUT_MARGIN_S, self.name)

    def move_until_contact(self, direction_m_s, timeout_s: float) -> ContactResult:
        self._ready()
        twist = np.zeros(6)
        twist[:3] = np.asarray(direction_m_s, dtype=float)
        _positive(self.name, "contact speed", np.linalg.norm(twist[:3]), self.world.limits.tcp_speed_m_s)
        world, arm = self.world, self.world.arm
        arm.start(SpeedLinear(world.kinematics, arm.q, arm.tcp_offset, twist, world.limits.tcp_accel_m_s2))
        contact, pivot = False, None
        for _ in range(int(np.ceil(timeout_s / world.cycle_s))):
            world.step()
            if world.state is not RobotState.READY:
                raise DeviceError(self.name, f"{world.state.value}: {world.stop_reason}")
            position = arm.tcp_pose[:3]
            if not world.workspace.contains(position):
                arm.halt()
                raise DeviceError(self.name, f"contact search left the workspace box at "
                                             f"{np.round(position, 4).tolist()} m")
            pivot, meeting = world.pivot_touch(), world.partner_touch()
            if pivot or meeting or world.touching() or any(c.distance_m(position) <= 0.0 for c in self.contacts):
                contact = True
                break
        arm.halt()
        if contact and pivot == "seat":  # compliant: the socket's cone guides the tip to its seat
            world.settle_in_pivot(self.name)
        elif contact and meeting == "seat":  # the other robot's cup guides the tip onto its tip
            world.settle_on_partner(self.name)
        return ContactResult(contact, world.tcp_pose, world.q)

    def stop(self) -> None:
        self.world.arm.halt()  # motions run to completion inside a call, so there is nothing to decelerate

    def digital_inputs(self) -> int:
        """The world's digital inputs now: the beams' levels, the tool changer's id."""
        if self._closed:
            raise DeviceError(self.name, "closed")
        return self.world.digital_inputs()

    # -- state -----------------------------------------------------------------------

    def actual_q(self) -> np.ndarray:
        return self.world.q

    def actual_tcp_pose(self) -> np.ndarray:
        return self.world.tcp_pose

    def samples(self, since_t_s: float | None = None) -> list[RobotSample]:
        if since_t_s is None:
            return list(self.world.samples)
        return [s for s in self.world.samples if s.t_s > since_t_s]

    def set_tcp(self, tcp_pose) -> None:
        pose = np.asarray(tcp_pose, dtype=float)
        if pose.shape != (6,) or not np.all(np.isfinite(pose)):
            raise DeviceError(self.name, "tool frame must be 6 finite numbers [x, y, z, rx, ry, rz]")
        self.world.arm.set_tcp(pose)

    def tool_frame(self) -> np.ndarray:
        return self.world.arm.tcp_offset.copy()

    def tool_frame_slots(self) -> int:
        return len(self._stored)

    def tool_frame_slots_text(self) -> str:
        return f"blocks for {len(self._stored)} tools, as a UR's from input register 24"

    def _slot(self, slot: int) -> int:
        if self._closed:
            raise DeviceError(self.name, "closed")
        if int(slot) not in self._stored:
            raise DeviceError(self.name, f"no tool frame block {slot}: it keeps {self.tool_frame_slots_text()} "
                                         f"(blocks 0..{len(self._stored) - 1})")
        return int(slot)

    def stored_tool_frame(self, slot: int = 0) -> StoredToolFrame:
        """The frame the robot program would apply at its start from block `slot` (a controller's
        input registers)."""
        return self._stored[self._slot(slot)]

    def store_tool_frame(self, stored: StoredToolFrame, slot: int = 0) -> None:
        slot = self._slot(slot)
        frame = np.asarray(stored.tool_frame, dtype=float)
        if frame.shape != (6,) or not np.all(np.isfinite(frame)) or not 0 <= int(stored.generation) < 2**31:
            raise DeviceError(self.name, "a stored tool frame must be 6 finite numbers and a generation in "
                                         "0..2**31-1")
        self._stored[slot] = StoredToolFrame(frame.copy(), int(stored.generation))

    def state(self) -> RobotState:
        return RobotState.DISCONNECTED if self._closed else self.world.state

    def close(self) -> None:
        self._closed = True


class SimTrigger(TriggerInput):
    """The light barrier on the world's beams, stamped with the world clock (device time)."""

    def __init__(self, world: SimWorld | None = None, *, channels=None):
        self.world = world or default_world()
        self.channels = None if channels is None else {int(c) for c in channels}
        self.name = "sim trigger"
        self._closed = False

    def events(self, timeout_s: float = 0.0) -> list[TriggerEvent]:
        if self._closed:
            raise DeviceError(self.name, "closed")
        edges = self.world.take_edges(timeout_s)
        return [e for e in edges if self.channels is None or e.channel in self.channels]

    def close(self) -> None:
        self._closed = True


class SimTracker(Tracker):
    """A tracker whose instrument frame is the robot base; each target sits at the real tool tip."""

    def __init__(self, world: SimWorld | None = None, *, targets=("smr1",), constant_mm: float = 0.015,
                 per_m_mm: float = 0.006, seed: int | None = 1):
        self.world = world or default_world()
        self.targets = tuple(targets)
        self.noise = TrackerNoise(constant_mm, per_m_mm)
        self.rng = np.random.default_rng(seed)
        self.name = "sim tracker"

    def measure(self, target: str = "smr1", timeout_s: float = 5.0) -> TrackerMeasurement:
        if target not in self.targets:
            raise DeviceError(self.name, f"target not found: {target!r} (targets: {', '.join(self.targets)})")
        true_m = self.world.tool_tip_m()
        sigma_m = float(self.noise.sigma(true_m[None, :] * 1000.0)[0]) / 1000.0
        return TrackerMeasurement(self.world.t_s, true_m + self.rng.normal(0.0, sigma_m, 3), None, "ok", sigma_m)


class SimPanel(OperatorPanel):
    """The operator panel in memory; tests play the operator with press_start()/press_abort()."""

    def __init__(self, world: SimWorld | None = None, *, routine: int = 1):
        self.name = "sim panel"
        self._start = self._abort = False
        self.routine = int(routine)
        self.tool = 0  # the tool selector: 0, whichever is mounted
        self.world = world
        # the mounted-tool register as the PLC or the tool changer writes it; None: the tool on the
        # world's flange (world.mount_tool), as the cell's PLC reports it (0 without a world)
        self.mounted: int | None = None
        self.lamps = {"busy": False, "done": False, "fault": False}
        self.result_code = 0
        self.run_counter = 0
        self.outcome: dict[str, int] = {}  # the outcome registers' raw values (daemon/outcome.py)
        self._confirm = False
        self.waiting = 0  # the waiting lamp's step (the placement register): 0 while no routine waits

    # the operator's side
    def press_start(self) -> None:
        self._start = True

    def press_abort(self) -> None:
        self._abort = True

    def press_confirm(self) -> None:
        """The operator has done what the waiting lamp asks: the plate of a waiting kinematic-fixture
        run is moved to the placement asked for (in the world, before the press), then confirm."""
        if self.waiting and self.world is not None:
            self.world.place_plate(self.waiting)
        self._confirm = True

    def select_routine(self, routine: int) -> None:
        self.routine = int(routine)

    def select_tool(self, tool: int) -> None:
        self.tool = int(tool)

    # the daemon's side
    def start_requested(self) -> bool:
        pressed, self._start = self._start, False
        return pressed

    def abort_requested(self) -> bool:
        pressed, self._abort = self._abort, False
        return pressed

    def confirm_requested(self) -> bool:
        pressed, self._confirm = self._confirm, False
        return pressed

    def set_waiting(self, step: int) -> None:
        self.waiting = int(step)

    def routine_selector(self) -> int:
        return self.routine

    def tool_selector(self) -> int:
        return self.tool

    def mounted_tool(self) -> int:
        if self.mounted is not None:
            return int(self.mounted)
        return self.world.mounted_tool if self.world is not None else 0

    def set_lamps(self, *, busy: bool | None = None, done: bool | None = None,
                  fault: bool | None = None) -> None:
        for name, value in (("busy", busy), ("done", done), ("fault", fault)):
            if value is not None:
                self.lamps[name] = bool(value)

    def set_outcome(self, registers: dict[str, int]) -> None:
        self.outcome = dict(registers)

    def set_result(self, code: int, increment_counter: bool = True) -> None:
        self.result_code = int(code) & 0xFFFF
        if increment_counter:
            self.run_counter = (self.run_counter + 1) % 65536

