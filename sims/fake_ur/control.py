"""The fake UR controller's fake-only JSON port (30199): read the true arm state and the
hidden truth, the RTDE input registers as held, the sensors' exact edge times; play a
robot program's start; put the arm somewhere; change the tool on the flange (``mount_tool``);
move the kinematic-fixture plate to another placement (``place_plate``, the operator's part);
and inject faults (a protective or emergency
stop, optionally once the arm has moved for a while, dropped connections, a stalled
controller, an RTDE input it does not keep). A mixin of :class:`.controller.FakeUrController`,
whose state it reads under the controller's lock."""
from __future__ import annotations

import numpy as np

from cellcal.drivers.ur.registers import FIRST_REGISTER, FORMAT_TAG, block_first, register_names
from cellcal.sims.physics.truth import beam_blocked, real_tool_tip

FAULT_KINDS = ("protective_stop", "emergency_stop", "drop", "stall", "resume", "exit", "ignore_input")


class ControlPort:
    """What the controller answers on its fake-only port."""

    def program_start(self, first: int) -> dict:
        """What the robot program's first lines do (docs/integrator.md, persistent tool frame): apply the
        stored tool frame with set_tcp when the registers hold one of ours, else keep the TCP."""
        with self.lock:
            names = register_names(first)
            values = [self.inputs.get(n, 0) for n in names]
            applied = values[7] == FORMAT_TAG and values[6] > 0
            if applied:
                self.arm.set_tcp(np.array(values[:6], dtype=float))
            self.log(f"program start: stored tool frame {'applied' if applied else 'none, TCP kept'}")
            return {"ok": True, "applied": bool(applied), "generation": int(values[6]),
                    "tcp_offset": self.arm.tcp_offset.tolist()}

    def edges(self, first: int, wait_s: float = 0.0) -> dict:
        """The sensors' edges numbered `first` or later, each at its exact switching time on the
        controller's clock, waiting up to `wait_s` for one (without holding the controller)."""
        with self._cycle_cond:
            self._cycle_cond.wait_for(lambda: self.sensors.count > first or self.closing, max(wait_s, 0.0))
        with self.lock:
            return {"ok": True, "t_s": self.t_s, "next": self.sensors.count,
                    "edges": [[n, e.t_s, e.channel, e.edge.value] for n, e in self.sensors.since(first)]}

    def control(self, request: dict) -> dict:
        """The fake-only port: inspect the truth, add cell models, inject faults."""
        cmd = request.get("cmd")
        if cmd == "edges":
            return self.edges(int(request.get("first", 0)), min(float(request.get("wait_s", 0.0)), 5.0))
        with self.lock:
            if cmd == "state":
                arm = self.arm
                return {"ok": True, "t_s": self.t_s, "q": arm.q.tolist(), "qd": arm.qd.tolist(),
                        "tcp_pose": arm.tcp_pose.tolist(), "tcp_offset": arm.tcp_offset.tolist(),
                        "moving": arm.moving, "safety": self.safety, "program_running": self.program_running,
                        "digital_inputs": self.digital_inputs, "digital_outputs": self.digital_outputs,
                        "mounted_tool": self.mounted_tool, "stalled": self.stalled,
                        "messages": list(self.messages)[-20:]}
            if cmd == "truth":  # what the controller obeys, as a simulated run's report gives it
                return {"ok": True, "truth": self.truth.report(), "arm_params": self.truth.arm_params.tolist()}
            if cmd == "tool":
                return {"ok": True, "t_s": self.t_s, "q": self.arm.q.tolist(),
                        "tool_tip_m": real_tool_tip(self.truth, self.physics, self.arm.q, self._body).tolist(),
                        "tool_body_m": [p.tolist() for p in self._body],
                        "repeat_offset_m": self._repeat_offset_m.tolist()}
            if cmd == "fault":
                kind = request.get("kind")
                if kind not in FAULT_KINDS:
                    return {"ok": False, "error": f"unknown fault {kind!r} (kinds: {', '.join(FAULT_KINDS)})"}
                self.faults.append(dict(request))
                self._fire_faults()
                return {"ok": True}
            if cmd == "inputs":  # the RTDE input registers as the controller holds them
                return {"ok": True, "inputs": {k: v for k, v in self.inputs.items() if "register" in k}}
            if cmd == "program_start":  # the program of the tool whose frame is in block `block` (0: the first)
                return self.program_start(block_first(int(request.get("register", FIRST_REGISTER)),
                                                      int(request.get("block", 0))))
            if cmd == "partner" and self._partner_base is not None:  # robot a's real tip now (its base frame)
                rotation, origin = self._partner_base[:3, :3], self._partner_base[:3, 3]
                self._partner = (rotation.T @ (np.asarray(request["tip_m"], float) - origin),
                                 rotation.T @ np.asarray(request["axis"], float))
                return {"ok": True}
            if cmd == "add_model":
                self.cell.add(request["model"])
                return {"ok": True}
            if cmd == "set_q":
                if self.arm.moving:
                    return {"ok": False, "error": "the arm is moving"}
                q = np.asarray(request.get("q"), dtype=float)
                limits = self.arm.kin.model.joint_limits
                if q.shape != self.arm.q.shape or not np.all(np.isfinite(q)):
                    return {"ok": False, "error": f"q must be {len(self.arm.q)} finite numbers"}
                if limits is not None and np.any((q < limits[:, 0]) | (q > limits[:, 1])):
                    return {"ok": False, "error": "q is outside the joint limits"}
                self.arm.q = q
                self.arm.set_tcp(self.arm.tcp_offset)
                self._body = self.tool_body()  # put there, not moved: no edges
                self._blocked = {id(b): beam_blocked(b, self._body, self._tool_radius_m) for b in self.truth.beams}
                self.sensors.reset({b.channel: self._blocked[id(b)] for b in self.truth.beams})
                return {"ok": True}
            if cmd == "mount_tool":  # a tool change: {tool: ID} of the cell's table, 0 none
                return self.mount_tool(request.get("tool"))
            if cmd == "bend_tool":  # the mounted tool's real tip moved: {shift_m: [x, y, z]}, flange frame
                return self.bend_tool(request.get("shift_m"))
            if cmd == "place_plate":  # the operator moves the kinematic-fixture plate: {step: placement 1, 2, ...}
                return self.place_plate(request.get("step"))
            if cmd == "set_tcp":  # the controller's tool frame changed behind the service's back (a test's bent tool)
                if self.arm.moving:
                    return {"ok": False, "error": "the arm is moving"}
                tcp = np.asarray(request.get("tcp"), dtype=float)
                if tcp.shape != (6,) or not np.all(np.isfinite(tcp)):
                    return {"ok": False, "error": "tcp must be 6 finite numbers (m, rad)"}
                self.arm.set_tcp(tcp)
                return {"ok": True}
        return {"ok": False, "error": f"unknown command {cmd!r} (state, truth, tool, edges, inputs, "
                                          "program_start, fault, add_model, set_q, set_tcp, mount_tool, bend_tool, place_plate)"}

    def _fire_faults(self) -> None:
        for fault in list(self.faults):
            after = fault.get("after_motion_s")
            if after is not None and self.arm.moving_s < float(after):
                continue
            self.faults.remove(fault)
            kind = fault["kind"]
            if kind in ("protective_stop", "emergency_stop"):
                self._safety_stop(kind, fault.get("why", "injected fault"))
            elif kind in ("stall", "resume"):
                self.stalled = kind == "stall"
                if kind == "resume":
                    self.ignored_inputs.clear()
            elif kind == "ignore_input":
                self.ignored_inputs.add(str(fault.get("name")))
            elif kind == "drop":
                self._close_clients()
            elif kind == "exit":
                self._stopped.set()
