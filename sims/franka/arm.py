"""A Franka arm on MuJoCo physics, built as a cell's hidden truth has it, behind franky-sim's libfranka server.

franky-sim (a simulator of the Franka FR3 that speaks libfranka's network protocol) runs the arm:
MuJoCo integrates its dynamics at 1 kHz, its joint impedance controller tracks what the client
commands, and it reports the state a Franka controller reports, computed with the maker's nominal
kinematics (its URDF). What we add is the cell around it:

* **The arm as built.** The MuJoCo bodies of links 1-7 and the flange are placed from the cell's
  hidden truth (:func:`cellcal.sims.physics.truth.truth_of_cell`: the robot file's geometry off its
  drawing by ``sim_truth.arm_length_error_mm`` / ``arm_angle_error_deg``, drawn from the seed),
  so the physics moves a slightly different arm from the one the controller computes with, as a
  real arm is. Built once and checked at start against our own kinematics of the same parameters.
* **The real tool** on the flange (the truth's), which blocks the real beams and touches the real
  fixtures. The beams' sensors switch late (latency, jitter), timed on the controller's clock (its
  state's ``time``), for the IO module's trigger ring.
* **Contact, through MuJoCo.** The pivot's and a kinematic-fixture plate's sockets are nests of
  flat faces through the apex at the countersink's half angle (a rounded tip rests with its centre
  on the axis, as in the cone; :data:`NEST_FACES`), the stylus and a stylus plate's balls are balls,
  which the whole tool (its core segment, of the tool's radius) can touch; the tool meeting one is
  pushed back by a stiff, damped contact (:data:`CONTACT_STIFFNESS_N_M`), applied to the
  flange as an external force, so the arm, under its own controller, is stopped and guided by it.
  The controller reports the force as its external wrench estimate (``O_F_ext_hat_K``, with
  the estimate's noise) -- what a Franka client detects contact by.
* **Faults.** A reflex (what a Franka does on a collision it did not expect: the motion is aborted,
  the robot reports ``kReflex`` and the reason until an error recovery), on a contact force above
  :data:`COLLISION_FORCE_N` (the tool driven into a fixture) or injected; and a dropped connection.

The controller's clock is the step count (1 ms a step), kept across client connections (franky-sim
would count each connection's states from 0), so the trigger ring's stamps and the robot's samples
share one clock.
"""
from __future__ import annotations

import math
import threading
import xml.etree.ElementTree as ET

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.sims.inproc.world import FixtureBall, PivotSocket, fixture_sockets, pivot_socket
from cellcal.sims.physics.arm_motion import ArmKinematics, joint_body_frames
from cellcal.sims.physics.scene import ContactSphere, SwitchingSensors
from cellcal.sims.physics.truth import CellTruth, beam_blocked, beam_edges, real_tool_tip

STEP_S = 0.001  # franky-sim's step: the libfranka control rate
CONTACT_STIFFNESS_N_M = 2.0e5  # 200 N/mm a contact: a steel nest on a stiff post (the arm is the soft part: ~10 N/mm)
CONTACT_DAMPING_N_S_M = 1.0e3  # about 0.6 of critical for the few kg the flange carries
FORCE_NOISE_N = 0.15  # the external force estimate's noise (1 sigma per axis)
# A nest's faces: a pyramid of 12 around the countersink's axis, so a push tilted up to 44 deg from it
# (atan of cos 15 deg, at 45 deg faces) stays seated as in the cone (45 deg); a trihedral nest would hold
# only 27 deg. Each face has a quarter of a contact's stiffness and damping: seated, the nest is as stiff
# as three faces would be.
NEST_FACES = 12
REFLEX_ERROR = "cartesian_reflex"  # the error bit a collision reflex sets (libfranka's Errors)
# A collision: a contact force above this stops the arm with a reflex, as a Franka's collision detection
# does (franky-sim simulates none); a contact search and its seating press with a few newtons.
COLLISION_FORCE_N = 30.0
# libfranka's Errors, in the order the state carries them (41 flags)
ERROR_NAMES = (
    "joint_position_limits_violation", "cartesian_position_limits_violation", "self_collision_avoidance_violation",
    "joint_velocity_violation", "cartesian_velocity_violation", "force_control_safety_violation", "joint_reflex",
    "cartesian_reflex", "max_goal_pose_deviation_violation", "max_path_pose_deviation_violation",
    "cartesian_velocity_profile_safety_violation", "joint_position_motion_generator_start_pose_invalid",
    "joint_motion_generator_position_limits_violation", "joint_motion_generator_velocity_limits_violation",
    "joint_motion_generator_velocity_discontinuity", "joint_motion_generator_acceleration_discontinuity",
    "cartesian_position_motion_generator_start_pose_invalid", "cartesian_motion_generator_elbow_limit_violation",
    "cartesian_motion_generator_velocity_limits_violation", "cartesian_motion_generator_velocity_discontinuity",
    "cartesian_motion_generator_acceleration_discontinuity", "cartesian_motion_generator_elbow_sign_inconsistent",
    "cartesian_motion_generator_start_elbow_invalid", "cartesian_motion_generator_joint_position_limits_violation",
    "cartesian_motion_generator_joint_velocity_limits_violation",
    "cartesian_motion_generator_joint_velocity_discontinuity",
    "cartesian_motion_generator_joint_acceleration_discontinuity", "cartesian_position_motion_generator_invalid_frame",
    "force_controller_desired_force_tolerance_violation", "controller_torque_discontinuity",
    "start_elbow_sign_inconsistent", "communication_constraints_violation", "power_limit_violation",
    "joint_p2p_insufficient_torque_for_planning", "tau_j_range_violation", "instability_detected",
    "joint_move_in_wrong_direction", "cartesian_spline_motion_generator_violation",
    "joint_via_motion_generator_planning_joint_limit_violation", "base_acceleration_initialization_timeout",
    "base_acceleration_invalid_reading")


def _quat(rotation: np.ndarray) -> list[float]:
    """MuJoCo's (w, x, y, z) of a rotation matrix."""
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rotation, dtype=float).ravel())
    return q.tolist()


def _matrix(quat_text: str) -> np.ndarray:
    """The rotation matrix of MuJoCo's (w, x, y, z) quaternion text."""
    import mujoco

    q = np.array([float(v) for v in quat_text.split()], dtype=float)
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, q / np.linalg.norm(q))
    return m.reshape(3, 3)


def _frame_of(body: ET.Element) -> np.ndarray:
    frame = np.eye(4)
    frame[:3, :3] = _matrix(body.get("quat", "1 0 0 0"))
    frame[:3, 3] = [float(v) for v in body.get("pos", "0 0 0").split()]
    return frame


def _set_frame(body: ET.Element, frame: np.ndarray) -> None:
    body.set("pos", " ".join(repr(float(v)) for v in frame[:3, 3]))
    body.set("quat", " ".join(repr(v) for v in _quat(frame[:3, :3])))


def place_bodies(worldbody: ET.Element, prefix: str, nominal, true) -> np.ndarray:
    """Move links 1-7 and the hand of robot `prefix` from the arm `nominal` to the arm `true` (each
    a :func:`joint_body_frames` pair). franky-sim's bodies sit where its URDF puts them, each link's
    frame shifted along its joint's axis from ours (the modified-DH offset d before the joint, not
    after it: the meshes and masses are drawn so); the shifts are found from the nominal arm, checked
    to be shifts along the axis (which commute with the joint's turn), and kept, so each body moves
    only by the arm's errors. Returns the hand's mount on the flange (4x4)."""
    bodies = {b.get("name"): b for b in worldbody.iter("body")}
    links = [bodies[f"{prefix}fr3_link{i}"] for i in range(1, len(nominal[0]) + 1)]
    shift = np.eye(4)  # S_{k-1}: the previous body's frame in ours
    shifts = []
    for body, ours in zip(links, nominal[0]):
        s = np.linalg.inv(ours) @ shift @ _frame_of(body)  # S_k = N_k^-1 S_{k-1} X_k
        if np.abs(s[:3, :3] - np.eye(3)).max() > 1e-9 or np.abs(s[:2, 3]).max() > 1e-9:
            raise ValueError(f"{body.get('name')}: franky-sim's body is not ours shifted along the joint axis")
        shifts.append(s)
        shift = s
    hand = bodies[f"{prefix}hand"]
    mount = np.linalg.inv(nominal[1]) @ shift @ _frame_of(hand)  # flange -> hand, as franky-sim mounts it
    if np.abs(mount[:3, 3]).max() > 1e-9:
        raise ValueError("franky-sim's hand is not on the flange")
    previous = np.eye(4)
    for body, frame, s in zip(links, true[0], shifts):
        _set_frame(body, np.linalg.inv(previous) @ frame @ s)
        previous = s
    _set_frame(hand, np.linalg.inv(previous) @ true[1] @ mount)
    return mount


def _joint_armature(scene: ET.Element, prefix: str) -> np.ndarray:
    """Each arm joint's armature (its motor's reflected inertia, kg m^2) in franky-sim's model.

    franky-sim's joint controller is a PD per joint whose damping torque is added explicitly, from the
    last step's speed: at 1 ms steps a damping gain above 2 x inertia / step is unstable, and its
    default wrist gains (200 N m s/rad on 0.074 kg m^2) make joints 5-7 chatter in a limit cycle at
    rest. The cell's arm uses the wrist's inertia / step (half the bound, the links' own inertia not
    counted) and gives every joint the same ratio of damping to stiffness: each then lags its command
    by the same time (37 ms), so a tool path keeps its shape as it lags, where franky-sim's defaults
    (100 ms at the shoulder) swing a tool that turns fast off its line by centimetres."""
    default = next((float(j.get("armature")) for d in scene.iter("default") for j in d.findall("joint")
                    if j.get("armature") is not None), 0.0)
    joints = {j.get("name"): j for j in scene.iter("joint")}
    return np.array([float(joints[f"{prefix}fr3_joint{i}"].get("armature", default)) for i in range(1, 8)])


def _nearest_on_segment(segment, point: np.ndarray) -> np.ndarray:
    front, back = segment
    axis = back - front
    length2 = float(axis @ axis)
    k = 0.0 if length2 == 0.0 else min(max(float((point - front) @ axis) / length2, 0.0), 1.0)
    return front + k * axis


class Contacts:
    """The stiff, damped contact between the real tip's rounding and the cell's nests and balls."""

    def __init__(self, seats: list, radius_m: float):
        self.seats, self.radius_m = seats, radius_m
        angles = 2.0 * np.pi * np.arange(NEST_FACES) / NEST_FACES
        self._outward = np.stack([np.cos(angles), np.sin(angles), np.zeros(NEST_FACES)], axis=1)

    def force(self, body, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The force (N, base frame) the fixtures exert on the real tool, whose core segment is `body`
        (the tip's rounding centre first) moving at `velocity`, and where it acts (the contacts' mean
        point, weighted by their force): the nests meet the tip's rounding, the balls the whole tool."""
        total, moment_point, weight = np.zeros(3), np.zeros(3), 0.0
        for seat in self.seats:
            point = body[0] if isinstance(seat, PivotSocket) else _nearest_on_segment(body, seat.centre_m)
            for depth, normal, share in self._penetrations(seat, point):
                push = share * (CONTACT_STIFFNESS_N_M * depth - CONTACT_DAMPING_N_S_M * float(velocity @ normal))
                if push > 0:  # a contact pushes, never pulls
                    total += push * normal
                    moment_point, weight = moment_point + push * point, weight + push
        return total, (moment_point / weight if weight > 0 else body[0])

    def _penetrations(self, seat, centre):
        """(depth, normal, share of a contact's stiffness) of each surface the rounding presses."""
        r = self.radius_m
        face = 3.0 / NEST_FACES
        if isinstance(seat, (FixtureBall, ContactSphere)):  # a ball: a stylus, a stylus plate's
            d = centre - seat.centre_m
            n = float(np.linalg.norm(d))
            depth = seat.radius_m + r - n
            return [(depth, d / n, 1.0)] if depth > 0 and n > 0 else []
        if isinstance(seat, PivotSocket):  # the countersink's faces up to the rim, then the flat top
            d = centre - seat.apex_m
            rho = math.hypot(d[0], d[1])
            a = seat.half_angle_rad
            rim_height = seat.rim_radius_m / math.tan(a)  # the top's height above the apex
            if d[2] - r > rim_height or rho > seat.face_radius_m + r:
                return []
            out = []
            for e in self._outward:
                normal = np.array([0.0, 0.0, math.sin(a)]) - e * math.cos(a)
                gap = float(d @ normal)
                if d[2] - gap * normal[2] <= rim_height:  # nearest to the face itself
                    if gap < r:
                        out.append((r - gap, normal, face))
                else:  # nearest to the face's top edge, where it meets the flat top
                    corner = seat.rim_radius_m * e + [0.0, 0.0, rim_height]
                    along = np.array([-e[1], e[0], 0.0])
                    v = d - corner - float((d - corner) @ along) * along
                    gap = float(np.linalg.norm(v))
                    if 0.0 < gap < r:
                        out.append((r - gap, v / gap, face))
            if rho >= seat.rim_radius_m and d[2] - rim_height < r:  # beside the opening: the flat top
                out.append((r - (d[2] - rim_height), np.array([0.0, 0.0, 1.0]), 1.0))
            return out
        return []


class CellArm:
    """One simulated Franka arm in its cell: franky-sim's MuJoCo FR3 and libfranka server, the cell's
    beams, fixtures and real tool around it. :meth:`run` steps it (in the calling thread) until
    :meth:`close`; the control port's requests read and change it under :attr:`lock`."""

    def __init__(self, truth: CellTruth, model, *, host: str, q0, seed: int = 0, time_scale: float = 1.0,
                 end_effector=None):
        import mujoco
        from franky_sim.franka_robot_protocol import RobotCommand
        from franky_sim.mujoco_simulator import MujocoSimulator

        self.truth, self.model, self.host = truth, model, host
        self.time_scale = float(time_scale)
        self.lock = threading.RLock()
        self.rng = np.random.default_rng(seed)
        self.physics = ArmKinematics(model, truth.arm_params)  # the arm as built
        self.sim = MujocoSimulator(enable_visualization=False)
        self.sim.init()
        self.robot = self.sim.add_robot(initial_q=tuple(float(v) for v in q0))
        self._mount = place_bodies(self.sim.worldbody, "robot0_", joint_body_frames(model, model.nominal),
                                   joint_body_frames(model, truth.arm_params))
        # every joint lags its command by one time constant, the shortest the wrist's damping allows
        lag_s = float(np.min(_joint_armature(self.sim.scene, "robot0_") / STEP_S / self.robot.kp))
        self.robot.kv = self.robot.kp * lag_s
        self.robot.__class__ = _cell_robot_class(type(self.robot))
        self.robot.cell = self
        self.server = _cell_server_class()(self.robot, [host])
        self.server.cell = self
        self.server._FrankaServer__command_class_map[RobotCommand.kAutomaticErrorRecovery] = _recovery_command()
        self.server.init()
        self.sim.start()
        self._check_bodies()
        if end_effector is not None:  # the end effector configured in Desk (flange -> TCP, 4x4)
            hand = self.robot.robot_parameters  # where franky-sim puts the nominal end effector (its hand's TCP)
            f_t_ne = np.eye(4)
            f_t_ne[:3, :3] = Rotation.from_euler("xyz", hand.ee_tcp_rpy).as_matrix()
            f_t_ne[:3, 3] = hand.ee_tcp_xyz
            self.robot.set_NE_T_EE(tuple((np.linalg.inv(f_t_ne) @ end_effector).flatten(order="F").tolist()))
        self.steps = 0
        self.force_n = np.zeros(3)
        self.reflex = None  # no reflex active (sets the error flags too)
        self.faults: list[dict] = []
        self.motion_s = 0.0  # how long the current motion has run
        self.plate_step = 1
        self.seats = self._seats()
        self._contacts = Contacts(self.seats, self.tool_radius_m)
        self._hand = mujoco.mj_name2id(self.sim.model, mujoco.mjtObj.mjOBJ_BODY, "robot0_hand")
        self._body = self.tool_body()
        self._tip_old = self._body[0]
        self._blocked = {id(b): beam_blocked(b, self._body, self.tool_radius_m) for b in truth.beams}
        self.sensors = SwitchingSensors({b.channel: self._blocked[id(b)] for b in truth.beams})
        self.cond = threading.Condition(self.lock)
        self._edges_told = self.sensors.count
        self._closing = threading.Event()
        self.messages: list[str] = []

    # what the physics says
    @property
    def tool_radius_m(self) -> float:
        return 0.0 if self.truth.tool is None else self.truth.tool.radius_m

    @property
    def t_s(self) -> float:
        return self.steps * STEP_S

    def q(self) -> np.ndarray:
        return np.array(self.robot.inner_state.q, dtype=float)

    def tool_body(self) -> tuple[np.ndarray, np.ndarray]:
        """The real tool's core segment (base frame, m): the real tool on the arm as built."""
        rotation, position = self.physics.flange(self.q())
        if self.truth.tool is None:
            return position, position
        return self.truth.tool.segment(rotation, position)

    def end_effector_pose(self) -> np.ndarray:
        """The controller's tool frame now (F_T_EE, flange -> TCP) as [x, y, z, rx, ry, rz]."""
        f_t_ee = np.array(self.robot.state.F_T_EE, dtype=float).reshape(4, 4, order="F")
        return np.concatenate([f_t_ee[:3, 3], Rotation.from_matrix(f_t_ee[:3, :3]).as_rotvec()])

    def tool_tip(self) -> np.ndarray:
        return real_tool_tip(self.truth, self.physics, self.q(), self._body)

    def _seats(self) -> list:
        seats = [pivot_socket(self.truth), self.truth.stylus] + fixture_sockets(self.truth, self.plate_step)
        return [s for s in seats if s is not None]

    def _check_bodies(self) -> None:
        """MuJoCo's flange (the hand body, its mount undone) where our kinematics of the truth puts
        it, at a few joint configurations: both describe one arm."""
        import mujoco

        m, data = self.sim.model, mujoco.MjData(self.sim.model)
        hand = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "robot0_hand")
        rng = np.random.default_rng(0)
        for _ in range(4):
            q = rng.uniform(-1.0, 1.0, 7)
            for addr, v in zip(self.robot._qpos_addrs, q):
                data.qpos[addr] = v
            mujoco.mj_kinematics(m, data)
            rotation = data.xmat[hand].reshape(3, 3) @ self._mount[:3, :3].T
            r, p = self.physics.flange(q)
            if np.abs(rotation - r).max() > 1e-9 or np.abs(data.xpos[hand] - p).max() > 1e-9:
                raise AssertionError("the MuJoCo arm and the truth's kinematics disagree")

    # one step
    def step(self) -> None:
        with self.lock:
            self._fire_faults()
            self.server.process_commands()
            body = self._body
            velocity = (body[0] - self._tip_old) / STEP_S
            self.force_n, at = self._contacts.force(body, velocity)
            data, hand = self.sim.data, self._hand
            data.xfrc_applied[hand, :3] = self.force_n  # at the body's centre of mass: the force, and its moment
            data.xfrc_applied[hand, 3:] = np.cross(at - data.xipos[hand], self.force_n)
            if self.reflex is None and float(np.linalg.norm(self.force_n)) > COLLISION_FORCE_N:
                self.trigger_reflex(REFLEX_ERROR, f"a collision: {np.linalg.norm(self.force_n):.0f} N on the tool "
                                                  f"at {np.round(body[0], 4).tolist()} m")
            self.sim.step()
            self._tip_old = body[0]
            t_old = self.t_s
            self.steps += 1
            self._body = self.tool_body()
            self.sensors.schedule(beam_edges(self.truth, self.truth.beams, self._blocked, body, self._body,
                                             t_old, STEP_S, self.rng))
            self.sensors.advance(self.t_s)
            self.server._FrankaServer__message_id = self.steps  # the controller's clock, across connections
            self.server.send_state()
            self.motion_s = self.motion_s + STEP_S if self.server.current_motion_id else 0.0
            if self.sensors.count != self._edges_told:  # wake a reader of the edges only for new ones
                self._edges_told = self.sensors.count
                self.cond.notify_all()

    def run(self) -> None:
        """Step until :meth:`close`, one step per `STEP_S / time_scale` of the wall when the machine keeps up."""
        import time

        start, n = time.monotonic(), 0
        while not self._closing.is_set():
            self.step()
            n += 1
            lag = start + n * STEP_S / self.time_scale - time.monotonic()
            if lag > 0:
                time.sleep(lag)
            elif lag < -0.05:  # behind by more than 50 steps: do not race to catch up
                start, n = time.monotonic(), 0

    def close(self) -> None:
        self._closing.set()

    def cleanup(self) -> None:
        try:
            self.server.cleanup()
        finally:
            self.sim.cleanup()

    # faults and the operator's hands
    def _fire_faults(self) -> None:
        for fault in list(self.faults):
            after = fault.get("after_motion_s")
            if after is not None and self.motion_s < float(after):
                continue
            self.faults.remove(fault)
            if fault["kind"] == "reflex":
                self.trigger_reflex(fault.get("why", "cartesian_reflex"))
            elif fault["kind"] == "drop":
                self.server.reset_state()

    def trigger_reflex(self, why: str = REFLEX_ERROR, cause: str = "injected") -> None:
        """A collision reflex: the motion is aborted, the robot holds and reports the reason until recovered."""
        from franky_sim.franka_robot_protocol import BaseCommand, MoveStatus, RobotCommand

        reason = why if why in ERROR_NAMES else REFLEX_ERROR
        self.reflex = reason
        motion = self.server.current_motion_id
        self.server.stop_motion(send_preemption_signal=False)
        if motion:
            try:
                BaseCommand.send_response(self.server._tcp_socket, RobotCommand.kMove, motion,
                                          MoveStatus.kReflexAborted)
            except OSError:
                pass
        self.log(f"reflex: {reason} ({cause})")

    def recover(self) -> None:
        self.reflex = None
        self.log("automatic error recovery")

    def place_plate(self, step: int) -> dict:
        with self.lock:
            if isinstance(step, bool) or not isinstance(step, int) or step < 1:
                return {"ok": False, "error": f"step must be a placement number (1, 2, ...), not {step!r}"}
            if self.server.current_motion_id:
                return {"ok": False, "error": "the arm is moving: the plate is moved with the arm at rest"}
            self.plate_step = step
            self.seats = self._seats()
            self._contacts = Contacts(self.seats, self.tool_radius_m)
            self.log(f"the operator moved the plate to placement {step}")
            return {"ok": True, "step": step, "sockets": len(self.seats)}

    def log(self, text: str) -> None:
        self.messages.append(f"{self.t_s:.3f} {text}")
        del self.messages[:-200]

    @property
    def reflex(self) -> str | None:
        """The reason of an active reflex (libfranka's error name), until an error recovery."""
        return self._reflex

    @reflex.setter
    def reflex(self, reason: str | None) -> None:
        self._reflex = reason
        self.errors = tuple(reason == name for name in ERROR_NAMES)  # the state's flags, sent every step


def _cell_robot_class(base):
    """franky-sim's robot, reporting the cell's contact force as its external wrench estimate and a reflex's errors."""

    class CellFrankaRobot(base):
        cell: CellArm

        @property
        def state(self):
            state = super().state
            cell = self.cell
            noise = cell.rng.normal(0.0, FORCE_NOISE_N, 3)
            force = tuple((cell.force_n + noise).tolist()) + (0.0, 0.0, 0.0)
            errors = cell.errors
            # franky-sim 1.0.4 reports the pose of the commanded joints here (its kinematics hands back
            # pinocchio's frame object, which the commanded pose's computation then overwrites); a Franka
            # reports the pose of the measured joints, with the nominal kinematics, as this does
            measured = self.to_franka_pose(self.kinematics(np.asarray(state.q)).copy())
            return state.replace(O_T_EE=measured, O_F_ext_hat_K=force, K_F_ext_hat_K=force, current_errors=errors,
                                 last_motion_errors=errors, errors=errors, reflex_reason=errors)

    return CellFrankaRobot


def _cell_server_class():
    from franky_sim.franka_robot_protocol import RobotMode
    from franky_sim.franka_robot_server import FrankaRobotServer

    class CellRobotServer(FrankaRobotServer):
        cell: CellArm

        @property
        def robot_state(self):
            state = super().robot_state
            return state.replace(robot_mode=RobotMode.kReflex) if self.cell.reflex else state

    return CellRobotServer


def _recovery_command():
    from franky_sim.franka_robot_protocol import AutomaticErrorRecoveryCommand

    class Recovery(AutomaticErrorRecoveryCommand):
        def handle(self, server):
            server.cell.recover()
            super().handle(server)

    return Recovery
