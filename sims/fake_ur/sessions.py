"""The fake UR controller's network faces: one session class per port.

* ``RtdeSession`` (30004): recipes, start/pause, a sender thread streaming data packages
  at the recipe's frequency, input data packages written into the controller's inputs;
* ``DashboardSession`` (29999): the dashboard server's line protocol, answered the way
  PolyScope 5 answers (only what a client reads is imitated, e.g. ``true`` in remote);
* ``ScriptSession`` (30003): collects uploaded program text until a top-level ``end``;
* ``ControlSession`` (fake only): JSON lines for tests to inspect the arm and inject
  faults, which a real controller has no port for.

Sessions hold no robot state; they call the controller under its lock.
"""
from __future__ import annotations

import json
import socket
import struct
import threading

from cellcal.drivers.ur.process import recv_exact
from cellcal.sims.fake_ur import rtde

# ur_rtde keeps only the newest of the packages it finds in one read: a sender that was held up
# spaces the last packages of its backlog (controller time) so such a client reads them one by
# one; the older ones go at once. A real controller never falls behind its own cycle: a sender
# starved on a loaded host that spaced its whole backlog would fall further behind with every
# sleep (each costs a scheduler wake-up) until the state it streams is seconds old.
CATCH_UP_SPACING_S = 0.0003
CATCH_UP_SPACED = 4

DASHBOARD_REPLIES = {  # commands answered without touching the controller's state
    "close safety popup": "closing safety popup", "close popup": "closing popup", "power on": "Powering on",
    "power off": "Powering off", "brake release": "Brake releasing", "get loaded program": "No program loaded",
    "isProgramSaved": "false <unnamed>", "quit": "Disconnected", "play": "Failed to execute: play",
    "pause": "Failed to execute: pause"}


class RtdeSession:
    def __init__(self, controller, sock: socket.socket):
        self.controller, self.sock = controller, sock
        self.outputs: list[rtde.Recipe] = []
        self.inputs: dict[int, rtde.Recipe] = {}
        self.started = False
        self.send_lock = threading.Lock()

    def serve(self) -> None:
        try:
            while True:
                size, kind = rtde.HEADER.unpack(recv_exact(self.sock, rtde.HEADER.size))
                payload = recv_exact(self.sock, size - rtde.HEADER.size)
                if not self.controller.stalled:
                    self._handle(kind, payload)
        except (ConnectionError, OSError):
            pass
        finally:
            self.started = False
            self.controller.release_inputs(self)

    def _send(self, data: bytes) -> None:
        with self.send_lock:
            self.sock.sendall(data)

    def _handle(self, kind: int, payload: bytes) -> None:
        c = self.controller
        if kind == rtde.REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            self._send(rtde.packet(kind, bytes([1 if version in (1, 2) else 0])))
        elif kind == rtde.GET_URCONTROL_VERSION:
            self._send(rtde.packet(kind, struct.pack(">IIII", *c.version)))
        elif kind == rtde.SETUP_OUTPUTS:
            recipe = rtde.parse_output_setup(payload, len(self.outputs) + 1)
            if recipe.valid:
                self.outputs.append(recipe)
            self._send(rtde.packet(kind, recipe.type_reply()))
        elif kind == rtde.SETUP_INPUTS:
            recipe = c.claim_inputs(self, payload, len(self.inputs) + 1)
            if recipe.valid:
                self.inputs[recipe.recipe_id] = recipe
            self._send(rtde.packet(kind, recipe.type_reply()))
        elif kind == rtde.START:
            ok = bool(self.outputs) or bool(self.inputs)
            self._send(rtde.packet(kind, bytes([1 if ok else 0])))
            if ok and not self.started:
                self.started = True
                threading.Thread(target=self._stream, daemon=True, name="rtde-sender").start()
        elif kind == rtde.PAUSE:
            self.started = False
            self._send(rtde.packet(kind, bytes([1])))
        elif kind == rtde.DATA_PACKAGE and payload:
            recipe = self.inputs.get(payload[0])
            if recipe is not None:
                c.write_inputs(recipe.unpack(payload))

    def _stream(self) -> None:
        """Send every output recipe at its frequency, one package per due cycle."""
        c = self.controller
        decimation = [max(1, round(c.frequency_hz / r.frequency_hz)) if r.frequency_hz > 0 else 1
                      for r in self.outputs]
        seen = c.cycles_after(-1)[-1][0]
        try:
            while self.started and not c.closing:
                backlog = c.cycles_after(seen)
                burst = []
                for i, (cycle, snapshot) in enumerate(backlog):
                    seen = cycle
                    if c.stalled:
                        continue
                    data = b"".join(r.pack(snapshot) for r, k in zip(self.outputs, decimation) if cycle % k == 0)
                    if not data:
                        continue
                    if len(backlog) - i > CATCH_UP_SPACED:  # far behind: these go in one send
                        burst.append(data)
                        continue
                    if burst:
                        self._send(b"".join(burst))
                        burst = []
                    elif i:  # catching up: space the newest packages so a client reads them one by one
                        c.clock.sleep(CATCH_UP_SPACING_S)
                    self._send(data)
                if burst:
                    self._send(b"".join(burst))
        except OSError:
            pass


MAX_LINE_CHARS = 4096  # a dashboard command or a control request is far shorter; more is refused
MAX_PROGRAM_CHARS = 1 << 20  # a URScript program the fake will hold while waiting for its "end"


def _lines(sock: socket.socket):
    """The connection's lines; a line longer than MAX_LINE_CHARS ends the connection (as a
    controller drops a client that floods it), so nothing is buffered without bound."""
    reader = sock.makefile("r", encoding="utf-8", newline="\n")
    while True:
        line = reader.readline(MAX_LINE_CHARS + 1)
        if not line:
            return
        if len(line) > MAX_LINE_CHARS and not line.endswith("\n"):
            sock.sendall(b"error: line too long; closing\n")
            return
        yield line


class DashboardSession:
    BANNER = "Connected: Universal Robots Dashboard Server"

    def __init__(self, controller, sock: socket.socket):
        self.controller, self.sock = controller, sock

    def serve(self) -> None:
        try:
            self.sock.sendall((self.BANNER + "\n").encode())
            for line in _lines(self.sock):
                command = line.strip()
                if self.controller.stalled:
                    continue
                reply = self.reply(command)
                self.sock.sendall((reply + "\n").encode())
                if command == "quit":
                    break
        except (OSError, ValueError):
            pass
        finally:
            self.sock.close()

    def reply(self, command: str) -> str:
        """PolyScope 5's answer to one dashboard command, acting on the controller."""
        c = self.controller
        with c.lock:
            running = c.program_running
            safety = c.safety.upper()
            if command == "PolyscopeVersion":
                return "URSoftware {}.{}.{}.{} (Mar 01 2024)".format(*c.version)
            if command == "get serial number":
                return c.serial
            if command == "is in remote control":
                return "true"
            if command == "robotmode":
                return "Robotmode: RUNNING"
            if command in ("safetystatus", "safetymode"):
                return f"{command.capitalize()}: {'ROBOT_EMERGENCY_STOP' if safety == 'EMERGENCY_STOP' else safety}"
            if command == "running":
                return f"Program running: {str(running).lower()}"
            if command == "programState":
                return "PLAYING rtde_control" if running else "STOPPED <unnamed>"
            if command == "stop":  # answered "Stopped" whether or not a program ran; clients test for it
                if running:
                    c.log("dashboard: stop")
                    c.script.terminate()
                return "Stopped"
            if command == "unlock protective stop":
                if c.safety == "protective_stop":
                    c.safety = "normal"
                return "Protective stop releasing"
            if command == "restart safety":
                c.safety = "normal"
                return "Restarting safety"
            if command == "get robot model":
                return c.model_name
            if command in DASHBOARD_REPLIES:
                return DASHBOARD_REPLIES[command]
            if command.startswith(("popup ", "addToLog ")):
                return "showing popup" if command.startswith("popup") else "Added log message"
            return f"could not understand: '{command}'"


class ScriptSession:
    """Program text arrives in chunks; a program is complete at a top-level ``end`` line."""

    def __init__(self, controller, sock: socket.socket):
        self.controller, self.sock = controller, sock

    def serve(self) -> None:
        pending = ""
        try:
            while chunk := self.sock.recv(65536):
                pending += chunk.decode("utf-8", errors="replace")
                pending = self._take_programs(pending)
                if len(pending) > MAX_PROGRAM_CHARS:
                    self.controller.log(f"script: over {MAX_PROGRAM_CHARS} characters without a program's "
                                        "end; connection closed")
                    break
        except OSError:
            pass
        finally:
            self.sock.close()

    def _take_programs(self, text: str) -> str:
        lines = text.split("\n")
        start = None
        for i, line in enumerate(lines[:-1]):  # the last piece may be an unfinished line
            if start is None and (line.startswith("def ") or line.startswith("sec ")):
                start = i
            elif start is not None and line.rstrip() == "end":
                self.controller.load_program("\n".join(lines[start:i + 1]) + "\n")
                return self._take_programs("\n".join(lines[i + 1:]))
            elif start is None and line.strip():
                self.controller.log(f"script statement outside a program ignored: {line.strip()[:60]}")
        if start is None:
            return lines[-1]
        return "\n".join(lines[start:])


class ControlSession:
    def __init__(self, controller, sock: socket.socket):
        self.controller, self.sock = controller, sock

    def serve(self) -> None:
        try:
            for line in _lines(self.sock):
                try:
                    reply = self.controller.control(json.loads(line))
                except Exception as exc:  # a bad request must not kill the fake
                    reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
                self.sock.sendall((json.dumps(reply) + "\n").encode())
        except (OSError, ValueError):
            pass
        finally:
            self.sock.close()
