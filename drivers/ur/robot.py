"""Universal Robots arm: ur_rtde's control and IO interfaces, and the RTDE state stream.

The state stream is read losslessly by :mod:`.state`. ur_rtde's
RTDEControlInterface (and RTDEIOInterface) run in a child process
(:mod:`.process`), and this adapter owns every deadline. ur_rtde's own waits
are blind: a synchronous move waits up to 300 s for its "done" register and never
notices a dead connection meanwhile. So:

* moves are sent asynchronously and then watched on the state stream: the control
  script's async progress word (``output_int_register_2``) tells when the move ended;
  connection, control script and safety system are checked every few milliseconds;
* every other call has a deadline. A call that misses it leaves the adapter unusable,
  and the caller is not left hanging;
* ``moveUntilContact`` blocks inside the controller, so its timeout is enforced by
  stopping the program through the dashboard server and re-uploading the control script.

A protective or emergency stop, a lost or stalled connection, or a timeout raise
:class:`DeviceError` naming "UR robot at HOST" and what happened, after a best-effort
stop. The tool frame changes only through :meth:`set_tcp` (the running program's) and
:meth:`store_tool_frame` (the one the robot program applies at its start; one block of input
registers per tool of a tool changer, :meth:`tool_frame_slots`).

Register in the driver registry::

    register("robot", "ur_rtde", "cellcal.drivers.ur.robot:UrRtdeRobot")
"""
from __future__ import annotations

import importlib.util
import logging
import math
import socket
import threading
import time

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.config.reader import Section
from cellcal.drivers.arguments import check_robot_options, limited as _limit, travel_s as _travel_s, vector as _vector
from cellcal.drivers.interfaces import ContactResult, DeviceError, DeviceTimeout, Robot, RobotSample, RobotState, StoredToolFrame
from cellcal.drivers.registry import DriverConfigError
from cellcal.drivers.ur.host import UR_RTDE_MISSING, UR_RTDE_MODULES
from cellcal.drivers.ur.process import DASHBOARD_PORT, UrRtdeProcess
from cellcal.drivers.ur.registers import FIRST_REGISTER, FIRST_REGISTER_RANGE, ToolFrameRegisters
from cellcal.drivers.ur.state import ROBOT_VARIABLES, UrStateStream

log = logging.getLogger(__name__)

# ur_rtde's argument limits (rtde_control_interface.h)
JOINT_SPEED_MAX, JOINT_ACCEL_MAX = 3.14, 40.0
TOOL_SPEED_MAX, TOOL_ACCEL_MAX = 3.0, 150.0
ROTATION_RADIUS_M = 0.5  # for deadlines only: a turn of 1 rad counts as 0.5 m of TCP path
POLL_S = 0.004
SETTLED_TOLERANCE = 5e-5  # m and rad: stream pose vs the controller's get_forward_kin at rest


def _rotation_angle(rotvec_a, rotvec_b) -> float:
    relative = Rotation.from_rotvec(rotvec_b) * Rotation.from_rotvec(rotvec_a).inv()
    return float(relative.magnitude())


class UrRtdeRobot(Robot):
    @staticmethod
    def check_installed() -> None:
        """Refuse to start without ur_rtde (the package's `ur` extra), saying what to install,
        before anything is opened (also run by `cellcal service install` on the cell file)."""
        if any(importlib.util.find_spec(m) is None for m in UR_RTDE_MODULES):
            raise DriverConfigError(UR_RTDE_MISSING, key="driver")

    @staticmethod
    def check_options(**options) -> None:
        """Refuse an option out of range, naming it (also run by the registry at cell load)."""
        o = Section.of_options(DriverConfigError, **options)
        check_robot_options(o)
        o.number("reach_tolerance_rad", above=0.0, high=0.1)
        o.number("reach_tolerance_m", above=0.0, high=0.1)
        o.number("contact_accel_m_s2", above=0.0, high=TOOL_ACCEL_MAX)
        o.number("stop_decel_rad_s2", above=0.0, high=JOINT_ACCEL_MAX)
        o.integer("tool_frame_register", low=FIRST_REGISTER_RANGE[0], high=FIRST_REGISTER_RANGE[1])

    def __init__(self, host: str, *, frequency_hz: float = -1.0, connect_timeout_s: float = 5.0,
                 command_timeout_s: float = 3.0, stale_after_s: float = 0.5,
                 motion_timeout_factor: float = 2.0, motion_timeout_margin_s: float = 2.0,
                 reach_tolerance_rad: float = 1e-3, reach_tolerance_m: float = 1e-3,
                 contact_accel_m_s2: float = 0.5, stop_decel_rad_s2: float = 4.0,
                 tool_frame_register: int = FIRST_REGISTER):
        self.host = host
        self.name = f"UR robot at {host}"
        self.check_options(
            host=host, connect_timeout_s=connect_timeout_s, command_timeout_s=command_timeout_s,
            stale_after_s=stale_after_s, motion_timeout_factor=motion_timeout_factor,
            motion_timeout_margin_s=motion_timeout_margin_s, reach_tolerance_rad=reach_tolerance_rad,
            reach_tolerance_m=reach_tolerance_m, contact_accel_m_s2=contact_accel_m_s2,
            stop_decel_rad_s2=stop_decel_rad_s2, tool_frame_register=tool_frame_register)
        self.check_installed()
        self.command_timeout_s, self.connect_timeout_s = command_timeout_s, connect_timeout_s
        self.motion_timeout_factor, self.motion_timeout_margin_s = motion_timeout_factor, motion_timeout_margin_s
        self.reach_tolerance_rad, self.reach_tolerance_m = reach_tolerance_rad, reach_tolerance_m
        self.contact_accel_m_s2, self.stop_decel_rad_s2 = contact_accel_m_s2, stop_decel_rad_s2
        self._registers = ToolFrameRegisters(host, device=self.name, first_register=tool_frame_register,
                                             timeout_s=command_timeout_s)
        self._lock = threading.RLock()  # ur_rtde's control interface takes one command at a time
        self._broken: str | None = None
        self._blocking_motion: int | None = None  # the pending moveUntilContact call
        self._moving = False
        self._stream = UrStateStream(host, device=self.name, variables=ROBOT_VARIABLES, frequency_hz=frequency_hz,
                                     connect_timeout_s=connect_timeout_s, stale_after_s=stale_after_s)
        try:
            self._ur = UrRtdeProcess(host, device=self.name, frequency_hz=frequency_hz,
                                     connect_timeout_s=connect_timeout_s)
        except BaseException:
            self._stream.close()
            raise
        self._closed = False

    @property
    def state_stream(self) -> UrStateStream:
        """The robot's RTDE state stream, for a trigger on the robot's own inputs to share."""
        return self._stream

    def _failure(self) -> str | None:
        return self._stream.failure() or self._ur.failure()

    def _call(self, method: str, *args, timeout_s: float | None = None):
        """A control-interface call with a deadline; a call left running makes the adapter unusable."""
        if self._broken:
            raise DeviceError(self.name, f"not usable after {self._broken}; reconnect")
        with self._lock:
            try:
                return self._ur.call(f"control.{method}", *args,
                                     timeout_s=self.command_timeout_s if timeout_s is None else timeout_s)
            except DeviceTimeout as exc:
                self._broken = f"{method} got no reply"
                raise DeviceTimeout(self.name, exc.what) from None

    def _check_link(self, during: str) -> None:
        """Raise if the stream ended (DeviceError) or the controller went silent (DeviceTimeout)."""
        what = self._failure()
        if what is not None:
            raise (DeviceTimeout if self._stream.stalled() else DeviceError)(self.name, f"{what} during {during}")

    def _check_safety(self, during: str) -> None:
        """Raise if the stream ended or the safety system stopped the arm."""
        self._check_link(during)
        status = self._stream.status
        if status.emergency_stopped or status.protective_stopped:
            kind = "emergency stop" if status.emergency_stopped else "protective stop"
            q = np.round(self._stream.latest().q_rad, 4).tolist()
            raise DeviceError(self.name, f"{kind} during {during} (safety status bits "
                                         f"0x{status.safety_status_bits:x}); the arm stopped at q={q} rad")

    def _prepare(self, what: str) -> None:
        """Before a command: healthy stream, no safety stop, control script running, and the
        stream showing it running (it may lag the control interface's own connection), so a
        later stopped state on the stream means the script stopped after the command."""
        if self._broken:
            raise DeviceError(self.name, f"not usable after {self._broken}; reconnect")
        self._check_safety(f"preparing {what}")
        if self._stream.status.program_running:
            return
        if not self._call("isProgramRunning"):
            log.info("%s: control script not running; uploading it again", self.name)
            self._call("reuploadScript")
        # both connections must see it: ur_rtde refuses commands while its own view says stopped
        self._await(lambda: self._stream.status.program_running and self._call("isProgramRunning"),
                    self.command_timeout_s, f"control script start before {what}")

    def _settled_sample(self, what: str) -> RobotSample:
        """The stream sample of the arm as it is now, after a motion ended or the tool changed.

        The controller computes the TCP pose (get_forward_kin) and the stream is read
        until it shows that pose: the sample is then the controller's present state, not
        an older one still queued on a busy machine. The tolerance allows for encoder
        noise at rest.
        """
        pose = np.array(self._call("getForwardKinematics"))

        def shows_pose() -> bool:
            now = self._stream.latest().tcp_pose
            return (np.linalg.norm(now[:3] - pose[:3]) < SETTLED_TOLERANCE
                    and _rotation_angle(now[3:], pose[3:]) < SETTLED_TOLERANCE)

        self._await(shows_pose, self.command_timeout_s, f"the state stream to catch up after {what}",
                    safety=False)
        return self._stream.latest()

    def _await(self, done, timeout_s: float, what: str, during: str | None = None, safety: bool = True,
               controller_clock: bool = False) -> None:
        """Poll ``done`` until the deadline; the stream (and, with ``safety``, the safety state) is watched.
        With ``controller_clock`` the time is up only once it is up on both clocks, the controller's
        (the stream's timestamps: a motion's time) and the wall's: a host slowed by load, whose
        controller model runs behind the wall, does not cut a motion short, nor does a stream that
        was still catching up when the wait began (its clock then starts early). A controller that
        stops advancing is caught by the stream's stale limit. On a real arm the two clocks are one."""
        wall_deadline = time.monotonic() + timeout_s
        t_deadline = self._stream.latest().t_s + timeout_s

        def up() -> bool:
            wall_up = time.monotonic() > wall_deadline
            return wall_up and (not controller_clock or self._stream.latest().t_s > t_deadline)

        while not done():
            if safety:
                self._check_safety(during or what)
            else:
                self._check_link(what)
            if up():
                clock = " of the controller's time and the wall's" if controller_clock else ""
                raise DeviceTimeout(self.name, f"{what} did not happen within {timeout_s:.3g} s{clock}")
            time.sleep(POLL_S)

    def _deadline_s(self, travel_s: float) -> float:
        return travel_s * self.motion_timeout_factor + self.motion_timeout_margin_s

    def _async_move(self, what: str, method: str, args, travel_s: float, reached) -> None:
        """Send an asynchronous move and watch it to its end; stop the arm on any failure."""
        self._prepare(what)
        op_before = self._stream.status.async_operation_id
        self._moving = True
        try:
            if not self._call(method, *args, True):
                self._check_safety(what)
                raise DeviceError(self.name, f"{what} was refused by the controller")

            def finished() -> bool:
                status = self._stream.status
                return not status.program_running or (
                    status.async_operation_id != op_before and not status.async_operation_running)

            self._await(finished, self._deadline_s(travel_s), f"the end of {what}", during=what,
                        controller_clock=True)
            if not self._stream.status.program_running:
                self._explain_program_stop(what)
            try:
                self._await(lambda: reached(self._stream.latest()), 0.25, f"{what} reaching its target")
            except DeviceTimeout:
                raise DeviceError(self.name, f"{what} ended before its target (stopped by another caller "
                                             f"or by the controller)") from None
        except DeviceError:
            self.stop()
            raise
        finally:
            self._moving = False

    def _explain_program_stop(self, during: str) -> None:
        """The script stopped: name the safety stop behind it if one shows up promptly."""
        deadline = time.monotonic() + 0.1
        while time.monotonic() < deadline:
            self._check_safety(during)
            time.sleep(POLL_S)
        raise DeviceError(self.name, f"the control script stopped during {during}")

    # Robot
    def move_j(self, q_rad, speed_rad_s: float, accel_rad_s2: float) -> None:
        q = _vector(q_rad, 6, "q_rad")
        speed = _limit(speed_rad_s, JOINT_SPEED_MAX, "speed_rad_s")
        accel = _limit(accel_rad_s2, JOINT_ACCEL_MAX, "accel_rad_s2")
        travel = _travel_s(float(np.abs(q - self.actual_q()).max()), speed, accel)
        self._async_move("move_j", "moveJ", (q.tolist(), speed, accel), travel,
                         lambda s: np.abs(s.q_rad - q).max() <= self.reach_tolerance_rad)

    def move_l(self, tcp_pose, speed_m_s: float, accel_m_s2: float) -> None:
        pose = _vector(tcp_pose, 6, "tcp_pose")
        speed = _limit(speed_m_s, TOOL_SPEED_MAX, "speed_m_s")
        accel = _limit(accel_m_s2, TOOL_ACCEL_MAX, "accel_m_s2")
        now = self.actual_tcp_pose()
        path = np.linalg.norm(pose[:3] - now[:3]) + ROTATION_RADIUS_M * _rotation_angle(now[3:], pose[3:])
        travel = _travel_s(float(path), speed, accel)

        def reached(sample: RobotSample) -> bool:
            return (np.linalg.norm(sample.tcp_pose[:3] - pose[:3]) <= self.reach_tolerance_m
                    and _rotation_angle(sample.tcp_pose[3:], pose[3:]) <= self.reach_tolerance_rad)

        self._async_move("move_l", "moveL", (pose.tolist(), speed, accel), travel, reached)

    def move_until_contact(self, direction_m_s, timeout_s: float) -> ContactResult:
        """TCP velocity [vx, vy, vz] or twist [vx, vy, vz, wx, wy, wz] in the base frame.

        Returns contact=False, with the arm stopped, when timeout_s passes first.
        """
        twist = _vector(direction_m_s, 6, "direction_m_s", lengths=(3, 6))
        twist = np.concatenate([twist, np.zeros(6 - len(twist))])
        timeout_s = _limit(timeout_s, math.inf, "timeout_s")
        with self._lock:
            self._prepare("move_until_contact")
            call = self._ur.start_call("control.moveUntilContact", twist.tolist(), [0.0] * 6,
                                       self.contact_accel_m_s2)
            self._blocking_motion, self._moving = call, True
            try:
                return self._contact_result(call, timeout_s)
            finally:
                self._blocking_motion, self._moving = None, False

    def _contact_result(self, call: int, timeout_s: float) -> ContactResult:
        # the search's time is the controller's, as its motion is: a host slowed by load (or a
        # simulated clock faster than the wall) never lets it travel farther than planned; a
        # stream that stops advancing is caught by the safety check below (stale_after_s)
        deadline_t_s = self._stream.latest().t_s + timeout_s
        while True:
            try:
                contact = self._ur.result(call, POLL_S * 5, keep_waiting=True)
                break
            except DeviceTimeout:
                pass
            except DeviceError as exc:  # ur_rtde raised, or the link to it ended
                if self._failure() is not None:
                    self._broken = self._broken or "move_until_contact was cut off"
                raise DeviceError(self.name, f"{exc.what} during move_until_contact") from None
            try:
                self._check_safety("move_until_contact")
            except DeviceError:
                self._stop_program(call, "move_until_contact failed")
                raise
            if self._stream.latest().t_s > deadline_t_s:
                self._stop_program(call, "move_until_contact timed out")
                sample = self._settled_sample("move_until_contact")
                return ContactResult(False, sample.tcp_pose, sample.q_rad)
        if not contact:
            self._check_safety("move_until_contact")
            raise DeviceError(self.name, "move_until_contact was refused or ended without a contact")
        sample = self._settled_sample("move_until_contact")
        return ContactResult(True, sample.tcp_pose, sample.q_rad)

    def _stop_program(self, call: int, why: str) -> None:
        """Stop a command blocking inside the controller, then bring the control script back."""
        try:
            self._dashboard("stop")
            self._ur.result(call, self.command_timeout_s)  # ur_rtde returns once the program ends
        except DeviceTimeout:
            self._broken = f"{why}: ur_rtde did not return after the program was stopped"
            raise DeviceError(self.name, self._broken) from None
        except DeviceError as exc:
            log.warning("%s: %s; stopping it failed: %s", self.name, why, exc.what)
            return
        status = self._stream.status
        if not (status.protective_stopped or status.emergency_stopped):
            self._prepare("the next command")

    def _dashboard(self, command: str) -> str:
        """One dashboard-server command on its own connection, with a deadline."""
        try:
            with socket.create_connection((self.host, DASHBOARD_PORT), timeout=self.command_timeout_s) as sock:
                sock.settimeout(self.command_timeout_s)
                reader = sock.makefile("r", encoding="utf-8", newline="\n")
                reader.readline()  # banner
                sock.sendall((command + "\n").encode())
                return reader.readline().strip()
        except OSError as exc:
            raise DeviceError(self.name, f"dashboard server: {command!r} failed: {exc}") from None

    def stop(self) -> None:
        """Best effort and never raises: it runs on error paths where the cause matters more."""
        try:
            if self._blocking_motion is not None:
                self._dashboard("stop")
            elif not self._broken and self._failure() is None and self._stream.status.program_running:
                self._call("stopJ", self.stop_decel_rad_s2, False)
        except DeviceError as exc:
            log.warning("%s: stop failed: %s", self.name, exc.what)

    def unlock_protective_stop(self) -> None:
        """Release a protective stop (once its cause is understood) and restart the control script."""
        reply = self._dashboard("unlock protective stop")
        self._await(lambda: not self._stream.status.protective_stopped, self.command_timeout_s,
                    f"protective stop release (dashboard said {reply!r})", safety=False)
        self._prepare("the next command")

    def set_digital_output(self, channel: int, level: bool) -> None:
        """A standard (0-7) or configurable (8-15) digital output, through RTDEIOInterface."""
        channel = int(channel)
        if not 0 <= channel <= 15:
            raise ValueError(f"channel must be 0..15, got {channel}")
        method = "setStandardDigitalOut" if channel < 8 else "setConfigurableDigitalOut"
        if not self._ur.call(f"io.{method}", channel % 8, bool(level), timeout_s=self.command_timeout_s):
            raise DeviceError(self.name, f"digital output {channel} was not set")
        self._await(lambda: bool(self._stream.status.digital_outputs >> channel & 1) == bool(level),
                    self.command_timeout_s, f"digital output {channel} reading {int(level)}", safety=False)

    def digital_inputs(self) -> int:
        """``actual_digital_input_bits`` of the state stream, from a sample that arrived after
        this call with none older still queued here: the inputs as the controller last sent them
        (a tool changer's id read at a start), not as a busy reader last saw them. An input that
        changed within the last few controller cycles may not show yet."""
        if self._broken:
            raise DeviceError(self.name, f"not usable after {self._broken}; reconnect")
        self._check_link("digital_inputs")
        return int(self._stream.current(self.command_timeout_s).digital_inputs)

    def actual_q(self) -> np.ndarray:
        return self._stream.latest().q_rad.copy()

    def actual_tcp_pose(self) -> np.ndarray:
        return self._stream.latest().tcp_pose.copy()

    def samples(self, since_t_s: float | None = None) -> list[RobotSample]:
        return self._stream.samples(since_t_s)

    def set_tcp(self, tcp_pose) -> None:
        pose = _vector(tcp_pose, 6, "tcp_pose")
        self._prepare("set_tcp")
        if not self._call("setTcp", pose.tolist()):
            self._check_safety("set_tcp")
            raise DeviceError(self.name, "set_tcp was refused by the controller")
        readback = self.tool_frame()
        if np.abs(readback - pose).max() > 1e-9:
            raise DeviceError(self.name, f"set_tcp: the controller reports {readback.tolist()}, "
                                         f"not the {pose.tolist()} sent")
        self._settled_sample("set_tcp")  # from here on actual_tcp_pose() reports the new tool

    def tool_frame(self) -> np.ndarray:
        self._prepare("tcp")
        return np.array(self._call("getTCPOffset"))

    def tool_frame_slots(self) -> int:
        """One block of RTDE input registers per slot, from ``tool_frame_register`` up to 47 (24: 4)."""
        return self._registers.slots

    def tool_frame_slots_text(self) -> str:
        return self._registers.text()

    def stored_tool_frame(self, slot: int = 0) -> StoredToolFrame:
        """The frame the robot program applies at start: block `slot` of RTDE input registers
        (:mod:`.registers`)."""
        self._usable("stored_tool_frame")
        return self._registers.read(slot)

    def store_tool_frame(self, stored: StoredToolFrame, slot: int = 0) -> None:
        self._usable("store_tool_frame")
        self._registers.write(stored, slot)

    def _usable(self, what: str) -> None:
        if self._broken:
            raise DeviceError(self.name, f"not usable after {self._broken}; reconnect")
        if self._failure() is not None:
            raise DeviceError(self.name, f"{self._failure()} before {what}")

    def state(self) -> RobotState:
        """DISCONNECTED once unusable, the safety stops as the controller reports them,
        PROGRAM_RUNNING while this adapter moves the arm, READY otherwise."""
        if self._broken or self._failure() is not None:
            return RobotState.DISCONNECTED
        status = self._stream.status
        if status.emergency_stopped:
            return RobotState.EMERGENCY_STOP
        if status.protective_stopped:
            return RobotState.PROTECTIVE_STOP
        return RobotState.PROGRAM_RUNNING if self._moving else RobotState.READY

    def close(self) -> None:
        """Stop the control script (if the link still works) and end the ur_rtde process."""
        if getattr(self, "_closed", True):
            return
        self._closed = True
        if not self._broken and self._failure() is None:
            try:
                self._call("stopScript")
            except DeviceError as exc:
                log.warning("%s: stopping the control script failed: %s", self.name, exc.what)
        self._broken = self._broken or "close()"
        self._ur.close()
        self._stream.close()
