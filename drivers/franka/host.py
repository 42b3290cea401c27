"""The child process that owns libfranka (pylibfranka) for :mod:`.robot`.

libfranka wants a 1 kHz loop that answers every state with a command, and its Python binding holds
the GIL while it waits for the robot: in the service's interpreter it would stall every thread, and
the service's threads would make it miss its cycles. So the loop lives here, in a process of its own,
with one thread that owns the ``pylibfranka.Robot`` (libfranka is not thread-safe):

* at rest it reads the robot's state (``read_once``) and streams it to the parent;
* a motion runs libfranka's motion generators, each cycle's command computed here from the state the
  cycle brought: joint moves on a synchronised trapezoid in joint space (joint position control),
  linear moves on a straight line with the orientation turned about one axis, solved for the joints
  beforehand with Franka's published kinematics (joint position control), contact searches as guarded moves (the commanded pose advances at the search's speed,
  so the arm's stiffness presses on what it meets) until the external force estimate
  (``O_F_ext_hat_K``) exceeds the cell's threshold, then, if asked, a compliant seating: the commanded
  position gives way to the contact's force across the search and presses with a set force along
  it (admittance control), so a socket's faces slide the tip into its seat;
* every motion ends with the arm settled (its joint speeds below :data:`SETTLED_RAD_S` for
  :data:`SETTLED_FOR_S`), and a stop request decelerates it at the cell's limits.

Protocol on the inherited socket (``multiprocessing.connection`` framing, both ends ours):

* parent -> child: the config dict once; then ``("call", id, name, args)``, ``("stop",)``, ``("exit",)``;
* child -> parent: ``("ready", info)`` or ``("error", kind, text)``; ``("samples", [...])`` in batches;
  ``("result", id, value)`` or ``("raised", id, kind, text)`` per call, where kind is ``reflex``,
  ``network``, ``command`` or ``refused``.
"""
from __future__ import annotations

import argparse
import math
import os
import queue
import socket
import threading
import time
from multiprocessing.connection import Connection

import numpy as np
from scipy.spatial.transform import Rotation

PYLIBFRANKA_MISSING = "the Franka driver needs pylibfranka: pip install 'cellcal[franka]'"
SETTLED_RAD_S = 2e-3  # every joint slower than this ...
SETTLED_FOR_S = 0.05  # ... for this long: the arm is at rest
SETTLE_TIMEOUT_S = 3.0
SEND_EVERY_S = 0.01  # samples go to the parent in batches this often
ROTATION_RADIUS_M = 0.1  # a pure turn counts as the path of a point this far from the axis (timing)
SEAT_DAMPING_N_S_M = 1000.0  # the seating's admittance: 5 N across the search moves the command 5 mm/s
FORCE_BIAS_S = 0.02  # the force estimate's offset, averaged over this long at a search's start


def trapezoid(length: float, speed: float, accel: float):
    """(duration, s(t)) of a trapezoidal (or triangular) profile over `length` (s in 0..1)."""
    if length <= 0:
        return 0.0, lambda t: 1.0
    t_acc = speed / accel
    if accel * t_acc * t_acc >= length:  # never reaches the speed
        t_acc = math.sqrt(length / accel)
        speed = accel * t_acc
    t_flat = (length - accel * t_acc * t_acc) / speed
    total = 2 * t_acc + t_flat

    def s(t: float) -> float:
        if t <= 0:
            return 0.0
        if t >= total:
            return 1.0
        if t < t_acc:
            d = 0.5 * accel * t * t
        elif t < t_acc + t_flat:
            d = 0.5 * accel * t_acc * t_acc + speed * (t - t_acc)
        else:
            r = total - t
            d = length - 0.5 * accel * r * r
        return d / length

    return total, s


def rotvec(rotation: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(rotation).as_rotvec()


def rotation_of(v) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(v, dtype=float)).as_matrix()


def matrix(flat16) -> np.ndarray:
    return np.array(flat16, dtype=float).reshape(4, 4, order="F")


def flat(m: np.ndarray) -> list[float]:
    return np.asarray(m, dtype=float).flatten(order="F").tolist()


# Franka's published kinematics (modified DH, Craig: Rx(alpha) Tx(a) Rz(q) Tz(d)), the same for the FR3
# and the Panda: (alpha, a, d) of joints 1-7 in rad and m, then the flange 0.107 m along joint 7's axis.
# The robot's controller computes its poses (O_T_EE) with exactly these; the driver solves linear
# moves with them.
FRANKA_MDH = ((0.0, 0.0, 0.333), (-math.pi / 2, 0.0, 0.0), (math.pi / 2, 0.0, 0.316), (math.pi / 2, 0.0825, 0.0),
              (-math.pi / 2, -0.0825, 0.384), (math.pi / 2, 0.0, 0.0), (math.pi / 2, 0.088, 0.0))
FLANGE_M = 0.107
IK_TOLERANCE_M = 1e-10  # position (m) and orientation (rad) of a solved pose
IK_STEPS = 20


def _frames(q) -> list[np.ndarray]:
    """Each joint's frame (4x4, base frame) after its turn, and the flange's last."""
    m, out = np.eye(4), []
    for (alpha, a, d), angle in zip(FRANKA_MDH, q):
        ca, sa, cq, sq = math.cos(alpha), math.sin(alpha), math.cos(angle), math.sin(angle)
        step = np.array([[cq, -sq, 0.0, a], [sq * ca, cq * ca, -sa, -d * sa], [sq * sa, cq * sa, ca, d * ca],
                         [0.0, 0.0, 0.0, 1.0]])
        m = m @ step
        out.append(m)
    flange = out[-1].copy()
    flange[:3, 3] += flange[:3, 2] * FLANGE_M
    out.append(flange)
    return out


def forward(q) -> np.ndarray:
    """The flange (4x4) at joints q, with Franka's published kinematics."""
    return _frames(q)[-1]


def inverse(target: np.ndarray, seed, f_t_ee: np.ndarray):
    """Joints near `seed` that put the end effector (flange . f_t_ee) at `target`: damped Newton steps of
    the least joint motion (the spare degree of freedom is left where the seed has it); None if none
    converges."""
    q = np.array(seed, dtype=float)
    for _ in range(IK_STEPS):
        frames = _frames(q)
        pose = frames[-1] @ f_t_ee
        error = np.concatenate([target[:3, 3] - pose[:3, 3], rotvec(target[:3, :3] @ pose[:3, :3].T)])
        if np.abs(error).max() < IK_TOLERANCE_M:
            return q
        jacobian = np.zeros((6, 7))
        for j, frame in enumerate(frames[:7]):
            axis = frame[:3, 2]
            jacobian[:3, j] = np.cross(axis, pose[:3, 3] - frame[:3, 3])
            jacobian[3:, j] = axis
        q = q + jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + 1e-12 * np.eye(6), error)
    return None


class Stopped(Exception):
    """The parent asked the motion to stop; it was decelerated to rest."""


class Host:
    def __init__(self, conn: Connection, config: dict):
        self.conn, self.config = conn, config
        self.send_lock = threading.Lock()
        self.calls: queue.Queue = queue.Queue()
        self.stop_requested = threading.Event()
        self.batch: list = []
        self.last_sent = time.monotonic()
        self.robot = None
        self.franka = None

    # talking to the parent
    def send(self, message) -> None:
        with self.send_lock:
            try:
                self.conn.send(message)
            except OSError:
                os._exit(0)

    def sample(self, state, force: bool = False) -> None:
        """Queue one state for the parent; send the batch when it is due."""
        self.batch.append((state.time.to_sec(), list(state.q), list(state.O_T_EE), int(state.robot_mode.value)))
        now = time.monotonic()
        if force or now - self.last_sent >= SEND_EVERY_S:
            self.send(("samples", self.batch))
            self.batch, self.last_sent = [], now

    def listen(self) -> None:
        while True:
            try:
                message = self.conn.recv()
            except (EOFError, OSError):
                os._exit(0)
            if message[0] == "exit":
                os._exit(0)
            if message[0] == "stop":
                self.stop_requested.set()
            elif message[0] == "call":
                self.calls.put(message[1:])

    # the robot thread
    def connect(self) -> None:
        import pylibfranka

        self.franka = pylibfranka
        self.robot = pylibfranka.Robot(self.config["host"], pylibfranka.RealtimeConfig.kIgnore)
        c = self.config
        self.robot.set_collision_behavior([c["reflex_torque_nm"]] * 7, [c["reflex_torque_nm"]] * 7,
                                          [c["reflex_force_n"]] * 6, [c["reflex_force_n"]] * 6)

    def info(self) -> dict:
        state = self.robot.read_once()
        self.sample(state, force=True)
        return {"F_T_NE": list(state.F_T_NE), "F_T_EE": list(state.F_T_EE), "q": list(state.q)}

    def run(self) -> None:
        while True:
            try:
                call = self.calls.get(timeout=self.config["idle_read_s"])
            except queue.Empty:
                self._idle_read()
                continue
            call_id, name, args = call
            self.stop_requested.clear()
            try:
                value = getattr(self, "do_" + name)(*args)
                message = ("result", call_id, value)
            except Stopped:
                message = ("result", call_id, "stopped")
            except Exception as exc:  # each reported to the parent, which raises DeviceError
                message = ("raised", call_id, self.kind_of(exc), f"{type(exc).__name__}: {exc}")
            self.send(message)

    def kind_of(self, exc: Exception) -> str:
        f = self.franka
        if isinstance(exc, f.ControlException):
            return "reflex"
        if isinstance(exc, f.NetworkException):
            return "network"
        if isinstance(exc, (f.CommandException, f.InvalidOperationException)):
            return "command"
        if isinstance(exc, ValueError):
            return "refused"
        return "command"

    def _idle_read(self) -> None:
        try:
            self.sample(self.robot.read_once())
        except self.franka.NetworkException as exc:
            self.send(("lost", f"{type(exc).__name__}: {exc}"))
            time.sleep(0.2)

    # commands
    def do_read(self):
        return self.info()

    def do_set_ee(self, f_t_ee):
        """The tool frame (flange -> TCP), set as libfranka sets it: NE_T_EE = F_T_NE^-1 F_T_EE."""
        state = self.robot.read_once()
        ne_t_ee = np.linalg.inv(matrix(state.F_T_NE)) @ matrix(f_t_ee)
        self.robot.set_EE(flat(ne_t_ee))
        for _ in range(50):  # the controller applies it with its next states
            state = self.robot.read_once()
            self.sample(state)
            if np.abs(matrix(state.F_T_EE) - matrix(f_t_ee)).max() < 1e-6:
                break
        self.sample(state, force=True)
        return list(state.F_T_EE)

    def do_recover(self):
        """libfranka's automatic error recovery; the time of the first state after it that shows the
        robot out of reflex (or of the last read, 1 s on)."""
        self.robot.automatic_error_recovery()
        for _ in range(1000):
            state = self.robot.read_once()
            self.sample(state)
            if state.robot_mode != self.franka.RobotMode.Reflex:
                break
        self.sample(state, force=True)
        return state.time.to_sec()

    def do_move_j(self, q_target, speed, accel):
        q_target = np.asarray(q_target, dtype=float)
        q0 = np.array(self.robot.read_once().q_d, dtype=float)
        delta = q_target - q0
        total, s = trapezoid(float(np.abs(delta).max()), speed, accel)
        return self._run_joints(lambda t: q0 + s(t) * delta, total)

    def _run_joints(self, at, total):
        """Joint position control along `at(t)` (joints at the motion's time t) until `total`, then settle;
        a stop decelerates the joints at the driver's ``stop_decel_rad_s2``."""
        f = self.franka
        control = self.robot.start_joint_position_control(f.ControllerMode.JointImpedance)
        control.readOnce()
        t, last = 0.0, at(0.0)
        velocity = np.zeros_like(last)
        while True:
            if self.stop_requested.is_set():
                self._stop_joints(control, last, velocity, self.config["stop_decel_rad_s2"])
                raise Stopped()
            q = at(min(t, total))
            done = t >= total
            command = f.JointPositions(q.tolist())
            command.motion_finished = done
            velocity, last = (q - last) / 0.001, q
            control.writeOnce(command)
            if done:
                break
            state, duration = control.readOnce()
            self.sample(state)
            t += duration.to_sec()
        return self.settle()

    def _stop_joints(self, control, q, v, accel) -> None:
        f = self.franka
        speed = float(np.abs(v).max())
        direction = v / speed if speed > 0 else np.zeros_like(v)
        while True:
            state, duration = control.readOnce()
            self.sample(state)
            dt = duration.to_sec()
            speed = max(speed - accel * dt, 0.0)
            q = q + direction * speed * dt
            command = f.JointPositions(q.tolist())
            command.motion_finished = speed == 0.0
            control.writeOnce(command)
            if speed == 0.0:
                break
        self.settle()

    def do_move_l(self, pose, speed, accel):
        """The TCP on a straight line, its orientation turned about one axis: the line solved for the
        joints before the arm moves (one pose a millisecond of the profile, each from the last, so the
        arm's spare degree of freedom stays where it was), then run in joint position control. A
        Cartesian motion generator would solve each cycle from wherever the arm lags to, and a big turn
        then swings the tool off the line."""
        state = self.robot.read_once()
        f_t_ee = matrix(state.F_T_EE)
        q0 = np.array(state.q_d, dtype=float)
        start = forward(q0) @ f_t_ee
        p0, r0 = start[:3, 3].copy(), start[:3, :3].copy()
        p1, r1 = np.asarray(pose[:3], dtype=float), rotation_of(pose[3:6])
        turn = rotvec(r0.T @ r1)
        length = max(float(np.linalg.norm(p1 - p0)), float(np.linalg.norm(turn)) * ROTATION_RADIUS_M)
        total, s = trapezoid(length, speed, accel)
        path, q = [], q0
        for t in np.arange(0.0, total + 0.001, 0.001):
            k = s(float(t))
            target = np.eye(4)
            target[:3, :3] = r0 @ rotation_of(turn * k)
            target[:3, 3] = p0 + k * (p1 - p0)
            q = inverse(target, q, f_t_ee)
            if q is None:
                raise ValueError(f"move_l: no joint solution on the line at {np.round(target[:3, 3], 4).tolist()} m "
                                 "(out of reach or through a singularity)")
            path.append(q)
        return self._run_joints(lambda t: path[min(int(round(t / 0.001)), len(path) - 1)], (len(path) - 1) * 0.001)

    def do_contact(self, twist, timeout_s):
        """A guarded move: the commanded pose moves along `twist` (ramped at the contact acceleration)
        until the external force estimate passes the threshold, so the arm's own stiffness presses
        the tool on whatever it meets (a face it slides along does not hide the contact); then it
        decelerates, and seats. True for a contact, False when `timeout_s` ran out first."""
        f, c = self.franka, self.config
        twist = np.asarray(twist, dtype=float)
        accel = c["contact_accel_m_s2"]
        control = self.robot.start_cartesian_pose_control(f.ControllerMode.JointImpedance)
        state, duration = control.readOnce()
        command = matrix(state.O_T_EE_c)
        t, bias, n_bias, speed_k = 0.0, np.zeros(3), 0, 0.0
        contact = False
        top = float(np.linalg.norm(twist[:3])) or float(np.linalg.norm(twist[3:]) * ROTATION_RADIUS_M) or 1.0
        while True:
            dt = duration.to_sec()
            force = np.array(state.O_F_ext_hat_K[:3], dtype=float)
            if t <= FORCE_BIAS_S:  # the estimate's offset, before the tool can have moved far
                bias, n_bias = bias + force, n_bias + 1
            elif np.linalg.norm(force - bias / max(n_bias, 1)) > c["contact_force_n"]:
                contact = True
            stopping = contact or t >= timeout_s or self.stop_requested.is_set()
            step = accel * dt / top
            speed_k = max(speed_k - step, 0.0) if stopping else min(speed_k + step, 1.0)
            command[:3, 3] += twist[:3] * speed_k * dt
            command[:3, :3] = rotation_of(twist[3:] * speed_k * dt) @ command[:3, :3]
            message = f.CartesianPose(flat(command))
            message.motion_finished = stopping and speed_k == 0.0
            control.writeOnce(message)
            if message.motion_finished:
                break
            state, duration = control.readOnce()
            self.sample(state)
            t += duration.to_sec()
        if self.stop_requested.is_set() and not contact:
            self.settle()
            raise Stopped()
        if contact and c["seat_s"] > 0:
            self._seat(twist[:3] / top, c["seat_s"], c["seat_force_n"], bias / max(n_bias, 1))
        self.settle()
        return contact

    def _seat(self, direction, duration_s, push_n, bias) -> None:
        """Admittance seating for `duration_s`: the commanded position moves with the external force
        across the search (a damper of SEAT_DAMPING_N_S_M), and along it until the contact pushes back
        with `push_n`; the orientation is held. A socket's faces so slide the tip to where they push
        it equally from every side, whatever the arm's own tracking errors."""
        f = self.franka
        control = self.robot.start_cartesian_pose_control(f.ControllerMode.JointImpedance)
        state, duration = control.readOnce()
        target = matrix(state.O_T_EE_c)
        t = 0.0
        while True:
            force = np.array(state.O_F_ext_hat_K[:3], dtype=float) - bias
            along = float(force @ direction)
            across = force - along * direction
            dt = duration.to_sec()
            target[:3, 3] += dt * (across + direction * (push_n + along)) / SEAT_DAMPING_N_S_M
            done = t >= duration_s or self.stop_requested.is_set()
            command = f.CartesianPose(flat(target))
            command.motion_finished = done
            control.writeOnce(command)
            if done:
                break
            state, duration = control.readOnce()
            self.sample(state)
            t += duration.to_sec()

    def settle(self):
        """Read until the arm is at rest (or SETTLE_TIMEOUT_S of the controller's time); its last state's time."""
        still, t, start = 0.0, None, None
        while True:
            state = self.robot.read_once()
            self.sample(state)
            now = state.time.to_sec()
            start = now if start is None else start
            dt = 0.0 if t is None else now - t
            t = now
            still = still + dt if np.abs(np.asarray(state.dq)).max() < SETTLED_RAD_S else 0.0
            if still >= SETTLED_FOR_S or now - start > SETTLE_TIMEOUT_S:
                self.sample(state, force=True)
                return now


def main() -> None:
    parser = argparse.ArgumentParser(description="libfranka in a child process (internal)")
    parser.add_argument("--fd", type=int, required=True)
    args = parser.parse_args()
    conn = Connection(socket.socket(fileno=args.fd).detach())
    try:
        config = conn.recv()
        host = Host(conn, config)
        try:
            host.connect()
            info = host.info()
        except ModuleNotFoundError as exc:
            conn.send(("error", "missing", f"{PYLIBFRANKA_MISSING} ({exc})"))
            os._exit(1)
        except Exception as exc:  # pylibfranka's NetworkException and friends
            conn.send(("error", "network", f"{type(exc).__name__}: {exc}"))
            os._exit(1)
        conn.send(("ready", info))
        threading.Thread(target=host.listen, daemon=True, name="parent").start()
        host.run()
    except (EOFError, OSError):
        pass
    os._exit(0)


if __name__ == "__main__":
    main()
