"""A fake UR e-Series controller that the unmodified ur_rtde client accepts over loopback.

It serves RTDE (30004), the dashboard server (29999) and the script port (30003) on one
address, runs a 500 Hz control cycle with a joint-space model of a UR arm built from our
own robot model file, and executes the ur_rtde control script's register protocol
natively (:mod:`.script`). A fake-only JSON port (30199, :mod:`.control`) lets tests read the
true arm state and inject faults: a protective or emergency stop, optionally once the
arm has been moving for a given time, dropped connections, a stalled controller, or an
RTDE input it does not keep. RTDE inputs hold their last value after the writer leaves, as
a controller's do; ``program_start`` plays a robot program's first lines, which apply the
tool frame stored in the input registers (:mod:`cellcal.drivers.ur.registers`).

Given a cell file (``--cell-file``), it obeys that cell's hidden truth with the in-process
cell's physics (:mod:`cellcal.sims.physics.truth`): it reports with the arm's drawing, while the real tool on
the arm as built, off by each motion's repeatability, blocks the real beams and touches
the real stylus; a contact search that meets the pivot's or a kinematic-fixture plate's
socket settles in it, one that meets a stylus plate's ball stops there (a plate moved by
hand lies at one placement at a time: ``place_plate``). The beams' sensors switch late (latency, jitter); the digital inputs
sample them once per cycle; the control port's ``edges`` gives each switch's exact time
(for a networked cell's IO module). Without a cell file the truth is the drawing.
A tool change (``mount_tool`` on the control port) puts another tool of the cell's table on
the flange as it really is; where the cell file wires the tool changer's id to the digital
inputs (``mounted: {robot_inputs: [...]}``), they carry it.

The ur_rtde constructors hold Python's GIL while they wait for the controller, so the
fake must live in another process; the ports are fixed, so parallel fakes need distinct
loopback addresses (any 127.x.y.z works on Linux). Start one with
``python -m cellcal.sims.fake_ur.process --host 127.0.7.1`` or :class:`.process.FakeUrProcess`.
"""
from __future__ import annotations

import re
import socket
import sys
import threading
import time
from collections import deque

import numpy as np

from cellcal.config.cell_files import read_cell
from cellcal.config.robot_files import load_robot
from cellcal.sims.fake_ur import rtde
from cellcal.sims.physics.clock import SimClock
from cellcal.sims.physics.arm_motion import ArmKinematics, JointMove, MovingArm, MotionFault, StopMotion
from cellcal.sims.physics.scene import SwitchingSensors, scene_from_spec
from cellcal.sims.inproc.world import PIVOT_SLIDE_SPEED_RAD_S, fixture_sockets, pivot_socket
from cellcal.sims.physics.truth import (CellTruth, beam_blocked, beam_edges, meeting_rest_q, meeting_touch, pivot_rest_q, real_tool_body,
                    real_tool_tip, repeat_offset_m, tool_changer_inputs, tool_id_bits, touching, truth_of_cell)
from cellcal.sims.fake_ur.control import ControlPort
from cellcal.sims.fake_ur.script import ControlScript
from cellcal.sims.fake_ur.sessions import ControlSession, DashboardSession, RtdeSession, ScriptSession

DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT = 29999, 30003, 30004
CONTROL_PORT = 30199  # fake only: inspection and fault injection
HOME_Q = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
PROGRAM_STOP_DECEL_RAD_S2 = 4.0

ROBOT_MODE_RUNNING = 7
SAFETY_MODES = {"normal": 1, "protective_stop": 3, "emergency_stop": 7}
SAFETY_STATUS_BITS = {"normal": 1 << 0, "protective_stop": 1 << 2, "emergency_stop": (1 << 6) | (1 << 7)}
RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2


def _zero(kind: str):
    if kind.startswith("VECTOR"):
        return (0,) * (3 if kind == "VECTOR3D" else 6)
    return False if kind == "BOOL" else 0


class FakeUrController(ControlPort):
    """The controller: arm, cell, registers, safety state and the servers around them."""

    def __init__(self, host: str = "127.0.0.1", *, robot: str | None = None, q0=HOME_Q, cell: dict | None = None,
                 cell_file: str | None = None, version=(5, 15, 0, 11908), serial: str = "20235500001",
                 control_port: int = CONTROL_PORT, frequency_hz: float = 500.0, seed: int = 0,
                 verbose: bool = False, arm: str = "a", tool: int | None = None, time_scale: float = 1.0):
        self.host, self.version, self.serial = host, tuple(version), serial
        # the controller's time is its cycle count; the wall only paces the cycles, time_scale times faster
        self.clock = SimClock(time_scale, source=lambda: self.t_s)
        self.control_port, self.frequency_hz, self.verbose = control_port, frequency_hz, verbose
        self.lock = threading.RLock()
        self.cell = scene_from_spec(cell)
        cell_spec = read_cell(cell_file) if cell_file is not None else None
        if cell_spec is not None and tool is not None:  # another tool of the table mounted (CellFileError if none)
            cell_spec = cell_spec.with_tool(tool)
        robot = robot or (cell_spec.robots[arm].robot if cell_spec is not None else "ur10e")
        model = load_robot(robot)
        self.truth = truth_of_cell(cell_spec, load_robot(cell_spec.robot)) if cell_spec is not None else \
            CellTruth(np.asarray(model.nominal, dtype=float), None)
        # robot b of a two-robot cell: its own truth, and where its base really is, to see robot a's tip
        self._partner_base, self._partner = (self.truth.second.base, None) if arm == "b" else (None, None)
        if arm == "b":
            self.truth = self.truth.for_second()
        # the tool changer's id on the digital inputs (the cell file's `mounted: {robot_inputs: [...]}`)
        self.tool_inputs = tool_changer_inputs(cell_spec) if arm == "a" else ()
        self.physics = ArmKinematics(model, self.truth.arm_params)  # the arm as built
        self.rng = np.random.default_rng(seed)  # repeatability and sensor jitter
        self.contacts = [c for c in (self.truth.stylus, *self.truth.contacts) if c is not None]
        self.pivot, self._pivot_touch = pivot_socket(self.truth), None
        # the kinematic-fixture plate's sockets (seated as the pivot is); the socket a search met
        self.plate_step, self.sockets, self._socket = 1, fixture_sockets(self.truth), None
        self._joint_accel = cell_spec.limits["joint_accel_rad_s2"] if cell_spec is not None else 4.0
        self.arm = MovingArm(ArmKinematics(model), q0, 1.0 / frequency_hz, contact=self._touching)
        self._motion, self._repeat_offset_m = None, np.zeros(3)
        self._body_for: tuple = (None, None, None)
        self._body = self.tool_body()
        self._blocked = {id(b): beam_blocked(b, self._body, self._tool_radius_m) for b in self.truth.beams}
        self.sensors = SwitchingSensors({b.channel: self._blocked[id(b)] for b in self.truth.beams})
        model = re.search(r"ur(\d+)", robot.lower())
        self.model_name = f"UR{model.group(1)}" if model else "UR10"
        self.inputs: dict = {}  # RTDE inputs as last written: held after the writer disconnects
        self.ignored_inputs: set[str] = set()  # fault "ignore_input": writes to these are not kept
        self.outputs: dict = {name: _zero(kind) for name, kind in rtde.OUTPUT_TYPES.items()
                              if name.startswith("output_") and "register" in name}
        self.script: ControlScript | None = None
        self.safety = "normal"
        self.digital_inputs = self.digital_outputs = 0
        self.t_s, self.cycle = 0.0, 0
        self.stalled = self.closing = False
        self.faults: list[dict] = []
        self.messages: deque = deque(maxlen=500)
        self._input_owners: dict[str, object] = {}
        self._static = {name: _zero(kind) for name, kind in rtde.OUTPUT_TYPES.items()}
        self._static.update(robot_mode=ROBOT_MODE_RUNNING, joint_mode=(253,) * 6, speed_scaling=1.0,
                            target_speed_fraction=1.0, joint_temperatures=(31.0,) * 6,
                            actual_main_voltage=48.0, actual_robot_voltage=48.0, actual_robot_current=0.6,
                            actual_joint_voltage=(47.9,) * 6, actual_tool_accelerometer=(0.0, 0.0, 9.81),
                            actual_execution_time=0.35, tool_temperature=33.0, payload=0.0)
        # recent (cycle, snapshot): 5 s of the wall, so a sender starved on a busy machine still sends every cycle
        self._published: deque = deque([(0, self._snapshot())], maxlen=int(2500 * self.clock.time_scale))
        self._cycle_cond = threading.Condition()
        self._sockets: set[socket.socket] = set()
        self._listeners: list[socket.socket] = []
        self._stopped = threading.Event()

    # the real tool (the cell's truth)
    @property
    def _tool_radius_m(self) -> float:
        return 0.0 if self.truth.tool is None else self.truth.tool.radius_m

    def tool_body(self, q=None) -> tuple[np.ndarray, np.ndarray]:
        """The real tool's core segment (base frame, m) at joints q (default: now)."""
        q = self.arm.q if q is None else q
        return real_tool_body(self.truth, self.physics, self.arm.kin, q, self.arm.tcp_offset, self._repeat_offset_m)

    def _touching(self, tcp_position: np.ndarray) -> bool:
        """Contact for moveUntilContact and tool_contact: the real tool on a real surface, or the
        TCP on a surface added to the scene."""
        if self.cell.touching(tcp_position):
            return True
        body = self._body_now()
        kind = None
        for seat in ([self.pivot] if self.pivot is not None else []) + self.sockets:
            kind = seat.touch(body[0], self._tool_radius_m)
            if kind:
                if not self.arm.contact_history[-1]:
                    self._socket = seat
                break
        if not kind and self._partner is not None:  # robot a's needle, from robot b
            kind = meeting_touch(real_tool_tip(self.truth, self.physics, self.arm.q, body), *self._partner)
            kind = kind and f"meeting {kind}"
        if kind:
            if not self.arm.contact_history[-1]:  # the contact begins: what was touched, in which motion
                self._pivot_touch = (kind, self.arm.motion)
            return True
        return any(touching(c, body, self._tool_radius_m) for c in self.contacts)

    def _settle(self, search):
        """After the contact `search` (a motion): one that met the pivot's socket slides,
        orientation held, until the tip rests in its seat (the in-process cell's compliance), a
        new rest with its own repeatability draw; None otherwise."""
        if self._pivot_touch not in (("seat", search), ("meeting seat", search)):
            return None
        kind, self._pivot_touch = self._pivot_touch[0], None
        offset = repeat_offset_m(self.truth, self.rng)
        if kind == "seat":
            seat = self._socket if self._socket is not None else self.pivot
            q_rest = pivot_rest_q(self.truth, self.physics, self.arm.q, seat.seat_m, offset)
        else:  # robot a's centring cup guides the tip onto robot a's tip
            q_rest = meeting_rest_q(self.truth, self.physics, self.arm.q, self._partner[0], offset)
        self._motion = slide = JointMove(self.arm.q, q_rest, PIVOT_SLIDE_SPEED_RAD_S, self._joint_accel)
        self._repeat_offset_m = offset
        return slide

    def _body_now(self) -> tuple[np.ndarray, np.ndarray]:
        """The real tool body now, computed again only when the joints, the repeatability offset
        or the tool frame were replaced (an arm at rest costs nothing)."""
        inputs = (self.arm.q, self._repeat_offset_m, self.arm.tcp_offset)
        if any(a is not b for a, b in zip(inputs, self._body_for)):
            self._body_for, self._body_cache = inputs, self.tool_body()
        return self._body_cache

    @property
    def mounted_tool(self) -> int:
        """The id of the tool on the flange (0: none, or a cell without a tool table)."""
        return self.truth.tool_id

    def mount_tool(self, tool_id) -> dict:
        """A tool change: tool `tool_id` of the cell's table as it really is goes on the flange
        (0: none, the bare flange), its body now blocks the beams and touches the fixtures, and
        the tool changer's id shows on the digital inputs. Refused while the arm moves. The
        controller's own tool frame is left as it was: setting it is the robot program's job."""
        with self.lock:
            if isinstance(tool_id, bool) or not isinstance(tool_id, int):
                return {"ok": False, "error": f"tool must be a tool id (an integer; 0: none), not {tool_id!r}"}
            if self.arm.moving:
                return {"ok": False, "error": "the arm is moving: a tool is changed with the arm at rest"}
            try:
                self.truth = self.truth.with_tool(tool_id)
            except ValueError as exc:
                return {"ok": False, "error": str(exc)}
            self._tool_put_there()
            self.log(f"tool change: tool {tool_id} mounted" if tool_id else "tool change: no tool mounted")
            return {"ok": True, "mounted_tool": tool_id, "digital_inputs": self.digital_inputs}

    def bend_tool(self, shift_m) -> dict:
        """The mounted tool's real tip moved by `shift_m` (flange frame, m): bent, or knocked on the
        flange. The controller's tool frame is left as it was. Refused while the arm moves."""
        with self.lock:
            if self.arm.moving:
                return {"ok": False, "error": "the arm is moving: a tool is bent with the arm at rest"}
            try:
                self.truth = self.truth.with_tool_bent(shift_m)
            except (ValueError, TypeError) as exc:
                return {"ok": False, "error": str(exc)}
            self._tool_put_there()
            self.log(f"tool {self.truth.tool_id} bent: its tip moved {np.round(np.asarray(shift_m) * 1e3, 3).tolist()} "
                     "mm (flange frame)")
            return {"ok": True, "tool_tcp_m": self.truth.tool.tcp_m.tolist()}

    def _tool_put_there(self) -> None:
        """Another real tool on the flange: the fixtures it meets, the beams it blocks (put there,
        not moved: no edges), the tool changer's id on the inputs."""
        self.pivot, self._pivot_touch = pivot_socket(self.truth), None
        self.sockets, self._socket = fixture_sockets(self.truth, self.plate_step), None
        self._body_for = (None, None, None)  # the body cache is the old tool's
        self._body = self._body_now()
        self._blocked = {id(b): beam_blocked(b, self._body, self._tool_radius_m) for b in self.truth.beams}
        self.sensors.reset({b.channel: self._blocked[id(b)] for b in self.truth.beams})  # put there, not moved
        self.digital_inputs = self._input_bits()

    def place_plate(self, step) -> dict:
        """The operator moves the kinematic-fixture plate to placement `step` (1, 2, ...: the cell
        file's order) as it really lies there (a plate moved by hand: ``move_by: operator``; plates
        fixed in the cell stay). Refused while the arm moves."""
        with self.lock:
            if isinstance(step, bool) or not isinstance(step, int) or step < 1:
                return {"ok": False, "error": f"step must be a placement number (1, 2, ...), not {step!r}"}
            if self.arm.moving:
                return {"ok": False, "error": "the arm is moving: the plate is moved with the arm at rest"}
            self.plate_step = step
            self.sockets, self._socket = fixture_sockets(self.truth, step), None
            self.log(f"the operator moved the plate to placement {step}")
            return {"ok": True, "step": step, "sockets": len(self.sockets)}

    def _input_bits(self) -> int:
        bits = self.cell.input_bits(self.arm.tcp_pose, self.t_s) | tool_id_bits(self.mounted_tool, self.tool_inputs)
        for beam in self.truth.beams:
            level = self.sensors.blocked[beam.channel] == beam.level_when_blocked
            bits = bits | (1 << beam.channel) if level else bits & ~(1 << beam.channel)
        return bits

    # the control cycle
    def run_cycle(self) -> None:
        with self.lock:
            self._fire_faults()
            if self.script is not None:
                self.script.tick()
                if not self.script.running and self.arm.motion is not None \
                        and not isinstance(self.arm.motion, StopMotion):
                    self.arm.stop_joint(PROGRAM_STOP_DECEL_RAD_S2)  # a program that ends stops the arm
            motion = self.arm.motion
            if motion is not None and motion is not self._motion and not isinstance(motion, StopMotion):
                self._motion = motion  # a new motion ends a little off: repeatability (a stop continues one)
                self._repeat_offset_m = repeat_offset_m(self.truth, self.rng)
            body_old = self._body
            try:
                self.arm.step()
            except MotionFault as exc:
                if self.script is not None:
                    self.script.terminate(str(exc))
            t_old = self.t_s
            self.cycle += 1
            self.t_s = self.cycle / self.frequency_hz
            self._body = self._body_now()
            if self._body is not body_old:
                self.sensors.schedule(beam_edges(self.truth, self.truth.beams, self._blocked, body_old, self._body,
                                                 t_old, 1.0 / self.frequency_hz, self.rng))
            self.sensors.advance(self.t_s)  # the inputs sample the sensors once per cycle
            self.digital_inputs = self._input_bits()
            published = (self.cycle, self._snapshot())
        with self._cycle_cond:
            self._published.append(published)
            self._cycle_cond.notify_all()

    def cycles_after(self, seen: int, timeout_s: float = 0.1) -> list[tuple[int, dict]]:
        """Every (cycle, snapshot) published after ``seen`` that is still kept, waiting for one;
        a sender that was held up sends them all, as a real controller sends every cycle."""
        with self._cycle_cond:
            self._cycle_cond.wait_for(lambda: self._published[-1][0] > seen or self.closing, timeout_s)
            new = []
            for entry in reversed(self._published):  # the newest few, without walking the whole buffer
                if entry[0] <= seen:
                    break
                new.append(entry)
            return new[::-1]

    def _snapshot(self) -> dict:
        arm, running = self.arm, self.program_running
        snap = dict(self._static)
        q, qd, pose, speed = tuple(arm.q), tuple(arm.qd), tuple(arm.tcp_pose), tuple(arm.tcp_speed)
        snap.update(timestamp=self.t_s, actual_q=q, target_q=q, actual_qd=qd, target_qd=qd,
                    actual_TCP_pose=pose, target_TCP_pose=pose, actual_TCP_speed=speed, target_TCP_speed=speed,
                    actual_digital_input_bits=self.digital_inputs,
                    actual_digital_output_bits=self.digital_outputs,
                    safety_mode=SAFETY_MODES[self.safety], safety_status=SAFETY_MODES[self.safety],
                    safety_status_bits=SAFETY_STATUS_BITS[self.safety],
                    runtime_state=RUNTIME_PLAYING if running else RUNTIME_STOPPED,
                    robot_status_bits=1 | (2 if running else 0))
        snap.update(self.outputs)
        snap.update((k, v) for k, v in self.inputs.items() if k in self._static)
        return snap

    @property
    def program_running(self) -> bool:
        return self.script is not None and self.script.running

    # what sessions call
    def log(self, text: str) -> None:
        self.messages.append(f"{self.t_s:.3f} {text}")
        if self.verbose:
            print(f"fake_ur {self.host}: {text}", file=sys.stderr, flush=True)

    def claim_inputs(self, session, payload: bytes, recipe_id: int) -> rtde.Recipe:
        with self.lock:
            taken = {n for n, owner in self._input_owners.items() if owner is not session}
            recipe = rtde.parse_input_setup(payload, recipe_id, taken)
            if recipe.valid:
                self._input_owners.update((n, session) for n in recipe.names)
            return recipe

    def release_inputs(self, session) -> None:
        with self.lock:
            for name in [n for n, owner in self._input_owners.items() if owner is session]:
                del self._input_owners[name]

    def write_inputs(self, values: dict) -> None:
        with self.lock:
            self.inputs.update((k, v) for k, v in values.items() if k not in self.ignored_inputs)
            for prefix, shift in (("standard", 0), ("configurable", 8)):
                mask = values.get(f"{prefix}_digital_output_mask", 0)
                if mask:
                    level = values.get(f"{prefix}_digital_output", 0)
                    self.digital_outputs = (self.digital_outputs & ~(mask << shift)) | ((level & mask) << shift)

    def load_program(self, text: str) -> None:
        with self.lock:
            if self.safety != "normal":
                self.log(f"program rejected: robot is in {self.safety.replace('_', ' ')}")
                return
            if self.script is not None:
                self.script.terminate()
            if "signal_ready" not in text:  # e.g. sendCustomScriptFunction: apply its register writes
                for reg, offset, value in re.findall(
                        r"write_output_integer_register\((\d+)\s*\+?\s*(\d*)\s*,\s*(-?\d+)\)", text):
                    self.outputs[f"output_int_register_{int(reg) + int(offset or 0)}"] = int(value)
                self.log("custom program run (register writes only)")
                return
            # ur_rtde injects the offset after the comment that ends the line: "= # int register offset\n24"
            offsets = [int(m) if m else 0 for m in (
                _first(r"reg_offset_int\s*=\s*(?:#[^\n]*\n)?\s*(\d+)", text),
                _first(r"reg_offset_float\s*=\s*(?:#[^\n]*\n)?\s*(\d+)", text))]
            self.script = ControlScript(self.arm, self.inputs, self.outputs, int_offset=offsets[0],
                                        float_offset=offsets[1], protective_stop=self.protective_stop,
                                        log=self.log, settle=self._settle)
            self.log(f"control script started (register offsets {offsets[0]}/{offsets[1]})")

    def protective_stop(self, why: str) -> None:
        self._safety_stop("protective_stop", why)

    def _safety_stop(self, safety: str, why: str) -> None:
        with self.lock:
            self.safety = safety
            self.arm.halt()
            if self.script is not None:
                self.script.terminate(why)
            self.log(f"{safety.replace('_', ' ')}: {why}")

    # servers
    def start(self) -> "FakeUrController":
        for port, session in ((RTDE_PORT, RtdeSession), (DASHBOARD_PORT, DashboardSession),
                              (SCRIPT_PORT, ScriptSession), (self.control_port, ControlSession)):
            self._listen(port, session)
        threading.Thread(target=self._cycle_loop, daemon=True, name="control-cycle").start()
        return self

    def _listen(self, port: int, session_class) -> None:
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            server.bind((self.host, port))
        except OSError as exc:
            server.close()
            raise OSError(f"fake UR controller cannot listen on {self.host}:{port}: {exc}") from None
        server.listen(16)
        self._listeners.append(server)
        threading.Thread(target=self._accept, args=(server, session_class), daemon=True,
                         name=f"accept-{port}").start()

    def _accept(self, server: socket.socket, session_class) -> None:
        while not self.closing:
            try:
                sock, _ = server.accept()
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if session_class is not ControlSession:
                self._sockets.add(sock)
            threading.Thread(target=self._serve, args=(session_class(self, sock), sock), daemon=True).start()

    def _serve(self, session, sock: socket.socket) -> None:
        try:
            session.serve()
        finally:
            self._sockets.discard(sock)
            sock.close()

    def _close_clients(self) -> None:
        for sock in list(self._sockets):
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self.log("dropped every client connection")

    def _cycle_loop(self) -> None:
        period = self.clock.wall_s(1.0 / self.frequency_hz)
        next_t = time.perf_counter()
        while not self.closing:
            try:
                self.run_cycle()
            except Exception:  # a fake that silently stops cycling would look like a stalled controller
                self._internal_error()
            next_t += period
            delay = next_t - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.25:  # hopelessly behind: let the clock slip rather than race
                next_t = time.perf_counter()

    def _internal_error(self) -> None:
        import traceback

        text = traceback.format_exc()
        print(f"fake_ur {self.host}: internal error\n{text}", file=sys.stderr, flush=True)
        with self.lock:
            self.arm.halt()
            if self.script is not None:
                self.script.terminate(f"fake controller internal error: {text.strip().splitlines()[-1]}")

    def wait(self) -> None:
        self._stopped.wait()

    def close(self) -> None:
        self.closing = True
        self._stopped.set()
        for sock in self._listeners:
            sock.close()
        self._close_clients()
        with self._cycle_cond:
            self._cycle_cond.notify_all()


def _first(pattern: str, text: str) -> str | None:
    match = re.search(pattern, text)
    return match.group(1) if match else None
