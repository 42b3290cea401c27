"""The ur_rtde control script, run natively by the fake UR controller.

ur_rtde uploads ``rtde_control.script`` to port 30003 and then talks to it through
RTDE registers; the fake does not interpret URScript, it implements that register
protocol (ur_rtde 1.6.5, ``scripts/rtde_control.script``):

* ``input_int_register_0`` is the command id, ``input_double_register_0..`` the
  arguments, ``input_int_register_1`` the async flag (or a second integer argument);
* ``output_int_register_0`` is 1 when the script is ready for a command and 2 when it
  is done with one; the client writes command 0 to make it ready again;
* ``output_int_register_1`` and ``output_double_register_0..5`` carry results;
* ``output_int_register_2`` is the async progress word: bit 15 running, bits 16-22 a
  write counter, bits 24-30 the operation id, incremented when an operation starts;
* realtime commands (servo/speed/queries such as tool_contact) are answered with
  "ready" at once instead of the ready/done handshake.

URScript's blocking calls (``movej``, ``stopl``...) and threads become generators: each
``yield`` is one ``sync()``, one 2 ms controller cycle. Register indices are offset by
``reg_offset_int`` / ``reg_offset_float`` of the uploaded script (0, or 24 when the
client asked for the upper register range).
"""
from __future__ import annotations

from typing import Callable, Iterator

import numpy as np

from cellcal.sims.physics.arm_motion import (MovingArm, JointMove, LinearMove, MotionFault, SpeedLinear, frame_to_pose,
                          pose_to_frame)

# ur_rtde RTDE::RobotCommand::Type ids the fake executes
MOVEJ, MOVEJ_IK, MOVEL, MOVEL_FK = 1, 2, 3, 4
SPEED_STOP, SERVO_STOP = 15, 16
TOOL_CONTACT, GET_STEPTIME, GET_JOINT_POSITIONS_HISTORY = 25, 26, 27
SET_TCP, GET_IK_ARGS, PROTECTIVE_STOP, STOPL, STOPJ = 29, 30, 31, 33, 34
GET_JOINT_TORQUES, GET_TCP_OFFSET, GET_FK_DEFAULT, GET_FK_ARGS = 38, 40, 43, 44
GET_IK_DEFAULT, IS_STEADY, MOVE_UNTIL_CONTACT, GET_FLANGE_POSE = 46, 47, 51, 58
START_CONTACT_DETECTION, STOP_CONTACT_DETECTION, READ_CONTACT_DETECTION = 62, 63, 64
CONTACT_DETECTED, STOP_SCRIPT = 254, 255
REALTIME = {6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}
READY, DONE = 1, 2

# movel(q) after a contact uses URScript's defaults
MOVEL_DEFAULT_SPEED_M_S, MOVEL_DEFAULT_ACCEL_M_S2 = 0.25, 1.2
CONTACT_STOP_DECEL_M_S2 = 3.0


class ControlScript:
    """One running instance of the control script: registers in, motions out."""

    def __init__(self, arm: MovingArm, inputs: dict, outputs: dict, *, int_offset: int = 0,
                 float_offset: int = 0, protective_stop: Callable[[str], None] = lambda why: None,
                 log: Callable[[str], None] = lambda text: None, settle: Callable = lambda search: None):
        self.arm, self.inputs, self.outputs = arm, inputs, outputs
        self.int_offset, self.float_offset = int_offset, float_offset
        self.protective_stop, self.log = protective_stop, log
        self.settle = settle  # after a contact search: the motion the cell's compliance adds (a seat), or None
        self.running = True
        self.fault: str | None = None
        self.executing = False
        self.main: Iterator | None = None
        self.main_cmd = 0
        self.threads: dict[str, Iterator] = {}
        self.internal_cmd = 0
        self.async_wr_count = 0
        self.async_op_id = 0
        self.contact_step_back = 0
        self._unsupported: set[int] = set()
        self._async_progress(-1)
        self._out_int(0, READY)

    # registers, with the script's offsets
    def _in_int(self, i: int) -> int:
        return int(self.inputs.get(f"input_int_register_{i + self.int_offset}", 0))

    def _in_float(self, i: int) -> float:
        return float(self.inputs.get(f"input_double_register_{i + self.float_offset}", 0.0))

    def _in_six(self, i: int) -> np.ndarray:
        return np.array([self._in_float(i + k) for k in range(6)])

    def _out_int(self, i: int, value: int) -> None:
        self.outputs[f"output_int_register_{i + self.int_offset}"] = int(value)

    def _out_six(self, i: int, values) -> None:
        for k, v in enumerate(values):
            self.outputs[f"output_double_register_{i + k + self.float_offset}"] = float(v)

    def _async_progress(self, value: int) -> None:
        """write_async_progress_register: 0 starts an operation, negative finishes it."""
        self.async_wr_count = (self.async_wr_count + 1) % 128
        if value == 0:
            self.async_op_id = (self.async_op_id + 1) % 128
        word = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            word += min(value, 32767) + 32768
        self._out_int(2, word)

    # the main loop
    def tick(self) -> None:
        """One pass of the script's main loop, ending at its ``sync()``."""
        if not self.running:
            return
        for name, thread in list(self.threads.items()):
            self._step(thread, lambda n=name: self.threads.pop(n, None))
        if not self.running:
            return
        if self.main is not None:
            self._advance_main()
            return
        cmd = self._in_int(0)
        if cmd == 0:
            cmd, self.internal_cmd = self.internal_cmd, 0
        if cmd in REALTIME:
            self._realtime(cmd)
            self._out_int(0, READY)
        elif cmd == 0:
            self.executing = False
            self._out_int(0, READY)
        elif not self.executing:
            self.executing = True
            self.main, self.main_cmd = self._process(cmd), cmd
            self._advance_main()

    def terminate(self, fault: str | None = None) -> None:
        """The program ends (stop command, protective stop, runtime error)."""
        self.running = False
        self.fault = fault
        self.main = None
        self.threads.clear()
        self.log(f"control script stopped: {fault or 'program ended'}")

    def _step(self, generator: Iterator, on_finish: Callable[[], None]) -> None:
        try:
            next(generator)
        except StopIteration:
            on_finish()
        except MotionFault as exc:
            self.terminate(str(exc))

    def _advance_main(self) -> None:
        def finished():
            self.main = None
            if not self.running:
                return
            if self.main_cmd == STOP_SCRIPT:
                self.terminate()
            else:
                self._out_int(0, DONE)
        self._step(self.main, finished)

    def _run(self, motion) -> Iterator:
        """A blocking URScript move: returns when the motion ends or is replaced."""
        self.arm.start(motion)
        while self.arm.motion is motion:
            yield

    def _stop_async_move(self) -> None:
        if self.threads.pop("move", None) is not None:
            self._async_progress(-1)  # a killed thread cannot signal its own end

    def _start_thread(self, name: str, generator: Iterator) -> None:
        self.threads[name] = generator
        self._step(generator, lambda: self.threads.pop(name, None))  # runs up to its first sync()

    def _async_motion(self, motion) -> Iterator:
        self._async_progress(0)
        yield from self._run(motion)
        self._async_progress(-1)

    def _move(self, motion, asynchronous: bool) -> Iterator:
        self._stop_async_move()
        if asynchronous:
            self._start_thread("move", self._async_motion(motion))
        else:
            yield from self._run(motion)

    # commands
    def _process(self, cmd: int) -> Iterator:
        arm, kin = self.arm, self.arm.kin
        if cmd in (MOVEJ, MOVEJ_IK, MOVEL, MOVEL_FK):
            target = self._in_six(0)
            speed, accel, asynchronous = self._in_float(6), self._in_float(7), self._in_int(1) == 1
            if cmd == MOVEJ_IK:
                target = kin.ik(*pose_to_frame(target), arm.q, arm.tcp_offset)
            if cmd == MOVEL_FK:
                target = kin.tcp_pose(target, arm.tcp_offset)
            if cmd in (MOVEJ, MOVEJ_IK):
                motion = JointMove(arm.q, target, speed, accel)
            else:
                motion = LinearMove(kin, arm.q, arm.tcp_offset, target, speed, accel)
            yield from self._move(motion, asynchronous)
        elif cmd in (STOPL, STOPJ, SPEED_STOP, SERVO_STOP):
            yield from self._stop(cmd)
        elif cmd == SET_TCP:
            arm.set_tcp(self._in_six(0))
        elif cmd == GET_TCP_OFFSET:
            self._out_six(0, arm.tcp_offset)
        elif cmd == GET_FK_DEFAULT:
            self._out_six(0, arm.tcp_pose)
        elif cmd == GET_FK_ARGS:
            self._out_six(0, kin.tcp_pose(self._in_six(0), self._in_six(6)))
        elif cmd in (GET_IK_DEFAULT, GET_IK_ARGS):
            seed = self._in_six(6) if cmd == GET_IK_ARGS else arm.q
            self._out_six(0, kin.ik(*pose_to_frame(self._in_six(0)), seed, arm.tcp_offset))
        elif cmd == IS_STEADY:
            self._out_int(1, 0 if arm.moving else 1)
        elif cmd == PROTECTIVE_STOP:
            self.protective_stop("protective stop requested by the control script")
        elif cmd == MOVE_UNTIL_CONTACT:
            yield from self._move_until_contact(self._in_six(0), self._in_float(12))
        elif cmd == START_CONTACT_DETECTION:
            self.threads.pop("contact", None)
            self._start_thread("contact", self._contact_thread())
        elif cmd in (STOP_CONTACT_DETECTION, READ_CONTACT_DETECTION):
            if cmd == STOP_CONTACT_DETECTION:
                self.threads.pop("contact", None)
            self._out_int(1, self.contact_step_back)
        elif cmd == CONTACT_DETECTED:
            self._stop_async_move()
            yield from self._back_to_contact(self.contact_step_back)
        elif cmd != STOP_SCRIPT and cmd not in self._unsupported:
            self._unsupported.add(cmd)
            self.log(f"command {cmd} is not simulated; acknowledged without effect")

    def _stop(self, cmd: int) -> Iterator:
        decel, asynchronous = self._in_float(0), self._in_int(1) == 1
        stop_move = self.threads.pop("stop", None) is None
        if not stop_move:
            self._async_progress(-1)
        if stop_move:
            self._stop_async_move()
        linear = cmd in (STOPL, SPEED_STOP, SERVO_STOP)
        decel = decel if decel > 0 else (10.0 if linear else 2.0)
        motion = self.arm.stop_linear(decel) if linear else self.arm.stop_joint(decel)
        if asynchronous:
            self._start_thread("stop", self._async_motion(motion))
        else:
            yield from self._run(motion)

    def _move_until_contact(self, twist: np.ndarray, accel: float) -> Iterator:
        arm = self.arm
        motion = arm.start(SpeedLinear(arm.kin, arm.q, arm.tcp_offset, twist, accel))
        while (step_back := arm.tool_contact()) <= 0:
            if arm.motion is not motion:
                return
            yield
        yield from self._back_to_contact(step_back)
        slide = self.settle(motion)
        if slide is not None:
            yield from self._run(slide)

    def _back_to_contact(self, step_back: int) -> Iterator:
        """Stop, then return to the joints of the last cycle before the contact began."""
        arm = self.arm
        q_contact = arm.past_q(step_back)
        yield from self._run(arm.stop_linear(CONTACT_STOP_DECEL_M_S2))
        target = arm.kin.tcp_pose(q_contact, arm.tcp_offset)
        yield from self._run(LinearMove(arm.kin, arm.q, arm.tcp_offset, target,
                                        MOVEL_DEFAULT_SPEED_M_S, MOVEL_DEFAULT_ACCEL_M_S2))

    def _contact_thread(self) -> Iterator:
        self.contact_step_back = 0
        while self.arm.tool_contact() > 0:  # first wait until out of contact
            yield
        while (step_back := self.arm.tool_contact()) == 0:
            yield
        self.contact_step_back = step_back
        self.internal_cmd = CONTACT_DETECTED

    def _realtime(self, cmd: int) -> None:
        arm = self.arm
        if cmd == TOOL_CONTACT:
            self._out_int(1, arm.tool_contact())
        elif cmd == GET_STEPTIME:
            self.outputs[f"output_double_register_{self.float_offset}"] = arm.dt
        elif cmd == GET_JOINT_POSITIONS_HISTORY:
            self._out_six(0, arm.past_q(self._in_int(1)))
        elif cmd == GET_JOINT_TORQUES:
            self._out_six(0, np.zeros(6))
        elif cmd == GET_FLANGE_POSE:
            self._out_six(0, frame_to_pose(*arm.kin.flange(arm.q)))
        elif cmd not in self._unsupported:
            self._unsupported.add(cmd)
            self.log(f"realtime command {cmd} is not simulated; ignored")

