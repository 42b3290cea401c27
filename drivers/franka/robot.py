"""Franka arm (FR3, Panda): libfranka through Franka's own Python binding, pylibfranka.

libfranka's 1 kHz loop runs in a child process (:mod:`.host` says why and how the motions are made);
this adapter is the cell's side of it: every call has a deadline, the state stream arrives in
batches and is kept (controller time stamps: the state's ``time``, so trigger edges stamped on the
cell's clock line up), and every libfranka error becomes a :class:`DeviceError`:

* a reflex (libfranka's ``ControlException``: a collision, a limit, a discontinuity) stops the arm
  and leaves it in reflex mode, which :meth:`state` reports as a protective stop, until
  :meth:`recover` (libfranka's automatic error recovery) -- which the service calls only on the
  operator's next start;
* a lost connection (``NetworkException``, or a stream that stops) makes the adapter unusable
  (:meth:`state`: disconnected) until it is opened again;
* a stop pressed on the arm's external enabling or stop device (``kUserStopped``) reads as an
  emergency stop.

The tool frame is libfranka's end effector: :meth:`set_tcp` sets flange -> TCP (``F_T_EE``) with
``set_EE`` and reads it back from the state. It is volatile: the robot forgets it when it restarts
(Desk's end-effector configuration applies then), and this robot keeps no tool frame for a program's start
(:meth:`tool_frame_slots` is 0). A Franka user makes a frame persistent in Desk (the end effector's
settings), which no client can write; ``cellcal`` sets it at each run instead.

Contact searches end on the external force estimate (``O_F_ext_hat_K``) passing ``contact_force_n``;
with ``seat_s`` > 0 the arm then gives way to the contact across the search for that long, pressing
with ``seat_force_n`` along it (admittance), so a socket's faces slide the tip into its seat (0: stop
where touched, for balls and planes).

Register in the driver registry::

    register("robot", "franka", "cellcal.drivers.franka.robot:FrankaRobot")
"""
from __future__ import annotations

import collections
import importlib.util
import itertools
import logging
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection
import socket

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.config.reader import Section
from cellcal.drivers.franka.host import PYLIBFRANKA_MISSING, ROTATION_RADIUS_M
from cellcal.drivers.arguments import check_robot_options, limited as _limit, travel_s as _travel_s, vector as _vector
from cellcal.drivers.interfaces import ContactResult, DeviceError, DeviceTimeout, Robot, RobotSample, RobotState
from cellcal.drivers.registry import DriverConfigError

log = logging.getLogger(__name__)

# libfranka's robot modes (franka::RobotMode)
MODE_OTHER, MODE_IDLE, MODE_MOVE, MODE_GUIDING, MODE_REFLEX, MODE_USER_STOPPED, MODE_RECOVERY = range(7)
JOINT_SPEED_MAX, JOINT_ACCEL_MAX = 2.62, 10.0  # the FR3's slowest joint limits (rad/s, rad/s^2)
TOOL_SPEED_MAX, TOOL_ACCEL_MAX = 2.0, 10.0  # its Cartesian limits (m/s, m/s^2; translation)
KEPT_SAMPLES = 60000  # a minute of the 1 kHz stream
FRAME_TOLERANCE = 1e-6  # a tool frame read back: libfranka carries it as 32-bit floats


def pose_of(flat16) -> np.ndarray:
    """[x, y, z, rx, ry, rz] of libfranka's column-major 4x4."""
    m = np.asarray(flat16, dtype=float).reshape(4, 4, order="F")
    return np.concatenate([m[:3, 3], Rotation.from_matrix(m[:3, :3]).as_rotvec()])


def flat_of(pose) -> list[float]:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(np.asarray(pose[3:6], dtype=float)).as_matrix()
    m[:3, 3] = pose[:3]
    return m.flatten(order="F").tolist()


class FrankaRobot(Robot):
    @staticmethod
    def check_installed() -> None:
        """Refuse to start without pylibfranka (the package's `franka` extra), saying what to install."""
        if importlib.util.find_spec("pylibfranka") is None:
            raise DriverConfigError(PYLIBFRANKA_MISSING, key="driver")

    @staticmethod
    def check_options(**options) -> None:
        """Refuse an option out of range, naming it (also run by the registry at cell load)."""
        o = Section.of_options(DriverConfigError, **options)
        check_robot_options(o)
        o.number("contact_force_n", above=0.0, high=50.0)
        o.number("contact_accel_m_s2", above=0.0, high=TOOL_ACCEL_MAX)
        o.number("seat_s", low=0.0, high=10.0)
        o.number("seat_force_n", above=0.0, high=50.0)
        o.number("reflex_force_n", above=0.0, high=200.0)
        o.number("reflex_torque_nm", above=0.0, high=200.0)
        o.number("stop_decel_rad_s2", above=0.0, high=JOINT_ACCEL_MAX)

    def __init__(self, host: str, *, connect_timeout_s: float = 15.0, command_timeout_s: float = 3.0,
                 stale_after_s: float = 0.5, motion_timeout_factor: float = 2.0,
                 motion_timeout_margin_s: float = 3.0, contact_force_n: float = 4.0,
                 contact_accel_m_s2: float = 0.5, seat_s: float = 1.0, seat_force_n: float = 5.0,
                 reflex_force_n: float = 60.0, reflex_torque_nm: float = 60.0, stop_decel_rad_s2: float = 4.0):
        self.host = host
        self.name = f"Franka robot at {host}"
        self.check_options(host=host, connect_timeout_s=connect_timeout_s, command_timeout_s=command_timeout_s,
                           stale_after_s=stale_after_s, motion_timeout_factor=motion_timeout_factor,
                           motion_timeout_margin_s=motion_timeout_margin_s, contact_force_n=contact_force_n,
                           contact_accel_m_s2=contact_accel_m_s2, seat_s=seat_s, seat_force_n=seat_force_n,
                           reflex_force_n=reflex_force_n, reflex_torque_nm=reflex_torque_nm,
                           stop_decel_rad_s2=stop_decel_rad_s2)
        self.check_installed()
        self.command_timeout_s, self.stale_after_s = command_timeout_s, stale_after_s
        self.motion_timeout_factor, self.motion_timeout_margin_s = motion_timeout_factor, motion_timeout_margin_s
        self._lock = threading.RLock()  # one command at a time, as libfranka takes them
        self._cond = threading.Condition()
        self._samples: collections.deque = collections.deque(maxlen=KEPT_SAMPLES)
        self._results: dict[int, tuple] = {}
        self._waiting: set[int] = set()
        self._ids = itertools.count(1)
        self._failure: str | None = None
        self._closed = False
        self._moving = False
        self._received_at = time.monotonic()
        parent_sock, child_sock = socket.socketpair()
        self._child = subprocess.Popen([sys.executable, "-m", "cellcal.drivers.franka.host", "--fd",
                                        str(child_sock.fileno())], pass_fds=[child_sock.fileno()],
                                       stdin=subprocess.DEVNULL)
        child_sock.close()
        self._conn = Connection(parent_sock.detach())
        self._send_lock = threading.Lock()
        try:
            self._send({"host": host, "contact_force_n": contact_force_n, "contact_accel_m_s2": contact_accel_m_s2,
                        "seat_s": seat_s, "seat_force_n": seat_force_n, "reflex_force_n": reflex_force_n,
                        "reflex_torque_nm": reflex_torque_nm, "idle_read_s": 0.002,
                        "stop_decel_rad_s2": stop_decel_rad_s2})
            self._await_ready(connect_timeout_s)
        except BaseException:
            self._end_child()
            raise
        self._reader = threading.Thread(target=self._read, daemon=True, name=f"libfranka process {host}")
        self._reader.start()
        self._wait_for_sample(command_timeout_s)

    # the child
    def _send(self, message) -> None:
        with self._send_lock:
            self._conn.send(message)

    def _await_ready(self, timeout_s: float) -> dict:
        deadline = time.monotonic() + timeout_s + 10.0  # + the child's interpreter start-up
        while True:
            if not self._conn.poll(max(deadline - time.monotonic(), 0.0)):
                raise DeviceTimeout(self.name, f"libfranka did not connect within {timeout_s:g} s")
            try:
                reply = self._conn.recv()
            except (EOFError, OSError):
                raise DeviceError(self.name, "the libfranka process ended while connecting") from None
            if reply[0] != "samples":  # the first states come before the word that it is ready
                break
        if reply[0] == "error":
            if reply[1] == "missing":
                raise DriverConfigError(reply[2], key="driver")
            raise DeviceError(self.name, f"cannot connect: {reply[2]} (is the robot's FCI enabled in Desk, "
                                         "and the address the robot's?)")
        return reply[1]

    def _read(self) -> None:
        while True:
            try:
                message = self._conn.recv()
            except (EOFError, OSError):
                with self._cond:
                    if self._failure is None and not self._closed:
                        self._failure = "the libfranka process ended"
                    self._cond.notify_all()
                return
            with self._cond:
                kind = message[0]
                if kind == "samples" and message[1]:
                    times, qs, poses, modes = zip(*message[1])
                    m = np.asarray(poses, dtype=float).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
                    tcp = np.concatenate([m[:, :3, 3], Rotation.from_matrix(m[:, :3, :3]).as_rotvec()], axis=1)
                    for t, q, pose, mode in zip(times, qs, tcp, modes):  # one conversion for the whole batch
                        self._samples.append((RobotSample(t, np.asarray(q, dtype=float), pose), mode))
                    self._received_at = time.monotonic()
                elif kind == "lost":
                    self._failure = f"connection lost: {message[1]}"
                elif kind in ("result", "raised"):
                    if message[1] in self._waiting:
                        self._results[message[1]] = message
                self._cond.notify_all()

    def _wait_for_sample(self, timeout_s: float) -> None:
        with self._cond:
            if not self._cond.wait_for(lambda: self._samples or self._failure, timeout_s) or self._failure:
                raise DeviceError(self.name, f"no state from the robot within {timeout_s:g} s")

    def _call(self, name: str, *args, timeout_s: float):
        if self._closed:
            raise DeviceError(self.name, f"{name}: connection closed")
        if self._failure is not None:
            raise DeviceError(self.name, f"{name}: {self._failure}")
        call_id = next(self._ids)
        with self._cond:
            self._waiting.add(call_id)
        try:
            self._send(("call", call_id, name, args))
        except OSError as exc:
            raise DeviceError(self.name, f"{name}: the libfranka process is unreachable: {exc}") from None
        deadline = time.monotonic() + timeout_s
        with self._cond:
            try:
                while call_id not in self._results:
                    if self._failure is not None:
                        raise DeviceError(self.name, f"{name}: {self._failure}")
                    if time.monotonic() - self._received_at > max(self.stale_after_s, 0.05) and self._samples:
                        self._failure = f"no state from the robot for {self.stale_after_s:g} s"
                        raise DeviceError(self.name, f"{name}: {self._failure}")
                    left = deadline - time.monotonic()
                    if left <= 0:
                        self._failure = f"{name} did not end within {timeout_s:g} s"
                        self._send_quietly(("stop",))
                        raise DeviceTimeout(self.name, self._failure)
                    self._cond.wait(min(left, 0.02))
                reply = self._results.pop(call_id)
            finally:
                self._waiting.discard(call_id)
        if reply[0] == "raised":
            kind, text = reply[2], reply[3]
            if kind == "network":
                self._failure = f"connection lost: {text}"
            raise DeviceError(self.name, f"{name}: {self._fault_text(kind, text)}")
        return reply[2]

    def _fault_text(self, kind: str, text: str) -> str:
        if kind == "reflex":
            return f"reflex, the arm stopped ({text}); it stays stopped until the operator's next start"
        return text

    def _send_quietly(self, message) -> None:
        try:
            self._send(message)
        except OSError:
            pass

    def _latest(self) -> tuple[RobotSample, int]:
        with self._cond:
            if not self._samples:
                raise DeviceError(self.name, "no state received yet")
            return self._samples[-1]

    def _motion_timeout(self, travel_s: float) -> float:
        return travel_s * self.motion_timeout_factor + self.motion_timeout_margin_s

    def _prepare(self, what: str) -> None:
        state = self.state()
        if state in (RobotState.PROTECTIVE_STOP, RobotState.EMERGENCY_STOP, RobotState.DISCONNECTED):
            raise DeviceError(self.name, f"{what}: the robot is not ready ({state.value})")

    # the interface
    def move_j(self, q_rad, speed_rad_s: float, accel_rad_s2: float) -> None:
        q = _vector(q_rad, 7, "q_rad")
        speed = _limit(speed_rad_s, JOINT_SPEED_MAX, "speed_rad_s")
        accel = _limit(accel_rad_s2, JOINT_ACCEL_MAX, "accel_rad_s2")
        with self._lock:
            self._prepare("move_j")
            length = float(np.abs(q - self.actual_q()).max())
            self._motion("move_j", q.tolist(), speed, accel, travel_s=_travel_s(length, speed, accel))

    def move_l(self, tcp_pose, speed_m_s: float, accel_m_s2: float) -> None:
        pose = _vector(tcp_pose, 6, "tcp_pose")
        speed = _limit(speed_m_s, TOOL_SPEED_MAX, "speed_m_s")
        accel = _limit(accel_m_s2, TOOL_ACCEL_MAX, "accel_m_s2")
        with self._lock:
            self._prepare("move_l")
            now = self.actual_tcp_pose()
            turn = (Rotation.from_rotvec(pose[3:]) * Rotation.from_rotvec(now[3:]).inv()).magnitude()
            length = max(float(np.linalg.norm(pose[:3] - now[:3])), turn * ROTATION_RADIUS_M)
            self._motion("move_l", pose.tolist(), speed, accel, travel_s=_travel_s(length, speed, accel))

    def _motion(self, name: str, *args, travel_s: float):
        self._moving = True
        try:
            value = self._call(name, *args, timeout_s=self._motion_timeout(travel_s) + 3.0)
        finally:
            self._moving = False
        if value == "stopped":
            raise DeviceError(self.name, f"{name} was stopped")
        self._catch_up(value)
        return value

    def _catch_up(self, t_s) -> None:
        """Wait until the stream holds the state of controller time `t_s` (the motion's settled state)."""
        if not isinstance(t_s, float):
            return
        with self._cond:
            self._cond.wait_for(lambda: self._samples and self._samples[-1][0].t_s >= t_s - 1e-9,
                                self.command_timeout_s)

    def move_until_contact(self, direction_m_s, timeout_s: float) -> ContactResult:
        twist = _vector(direction_m_s, 6, "direction_m_s", lengths=(3, 6))
        twist = np.concatenate([twist, np.zeros(6 - len(twist))])
        if not 0.0 < float(timeout_s) < 600.0:
            raise ValueError(f"timeout_s must be in (0, 600), got {timeout_s}")
        with self._lock:
            self._prepare("move_until_contact")
            self._moving = True
            try:
                contact = self._call("contact", twist.tolist(), float(timeout_s),
                                     timeout_s=self._motion_timeout(float(timeout_s)) + 5.0)
            finally:
                self._moving = False
            if contact == "stopped":
                raise DeviceError(self.name, "move_until_contact was stopped")
            sample, _ = self._latest()
            return ContactResult(bool(contact), sample.tcp_pose.copy(), sample.q_rad.copy())

    def stop(self) -> None:
        """Best effort and never raises: the running motion decelerates at the cell's limits."""
        self._send_quietly(("stop",))

    def actual_q(self) -> np.ndarray:
        return self._latest()[0].q_rad.copy()

    def actual_tcp_pose(self) -> np.ndarray:
        return self._latest()[0].tcp_pose.copy()

    def samples(self, since_t_s: float | None = None) -> list[RobotSample]:
        with self._cond:
            return [s for s, _ in self._samples if since_t_s is None or s.t_s > since_t_s]

    def set_tcp(self, tool_frame) -> None:
        pose = _vector(tool_frame, 6, "tool_frame")
        with self._lock:
            self._prepare("set_tcp")
            readback = pose_of(self._call("set_ee", flat_of(pose), timeout_s=self.command_timeout_s))
            if np.abs(readback[:3] - pose[:3]).max() > FRAME_TOLERANCE or \
                    (Rotation.from_rotvec(readback[3:]) * Rotation.from_rotvec(pose[3:]).inv()).magnitude() > 1e-5:
                raise DeviceError(self.name, f"set_tcp: the controller reports {readback.tolist()}, "
                                             f"not the {pose.tolist()} sent")
            self._frame = pose.copy()

    def tool_frame(self) -> np.ndarray:
        """The end effector frame (F_T_EE) the controller reports now. What was set with
        :meth:`set_tcp` is returned as set (libfranka carries it in 32-bit floats)."""
        with self._lock:
            reported = pose_of(self._call("read", timeout_s=self.command_timeout_s)["F_T_EE"])
            kept = getattr(self, "_frame", None)
            if kept is not None and np.abs(reported - kept).max() < FRAME_TOLERANCE:
                return kept.copy()
            return reported

    def state(self) -> RobotState:
        if self._closed or self._failure is not None:
            return RobotState.DISCONNECTED
        with self._cond:
            if not self._samples:
                return RobotState.DISCONNECTED
            _, mode = self._samples[-1]
            if time.monotonic() - self._received_at > max(self.stale_after_s, 0.05) and not self._moving:
                return RobotState.DISCONNECTED
        if mode == MODE_REFLEX:
            return RobotState.PROTECTIVE_STOP
        if mode == MODE_USER_STOPPED:
            return RobotState.EMERGENCY_STOP
        return RobotState.PROGRAM_RUNNING if self._moving else RobotState.READY

    def recover(self) -> bool:
        """libfranka's automatic error recovery after a reflex (the operator's start asks for it)."""
        with self._lock:
            if self.state() is not RobotState.PROTECTIVE_STOP:
                return False
            self._catch_up(self._call("recover", timeout_s=self.command_timeout_s + 5.0))
            return self.state() is RobotState.READY

    def close(self) -> None:
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        self._end_child()

    def _end_child(self) -> None:
        self._send_quietly(("exit",))
        try:
            self._child.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            self._child.kill()
            try:
                self._child.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                pass
        self._conn.close()
