"""The simulated Franka arm of a cell (:mod:`.arm`) in its own process, with a fake-only control port.

It has to be another process: libfranka's client (pylibfranka) holds Python's GIL while it waits
for the robot, so a simulator in the client's interpreter could never answer it. This module is
that process's entry point: ``python -m cellcal.sims.franka.process --host 127.0.9.1 --cell-file
CELL.yaml``; it prints ``READY host`` once libfranka clients can connect (port 1337 on `host`, as
a Franka controller serves) and the control port listens.

The control port (JSON lines, the fake UR controller's protocol, so the networked cell's wiring
and tracker read either: :class:`cellcal.sims.fake_ur.process.ControlClient`) answers ``state``,
``truth``, ``tool`` (the real tip and body now), ``edges`` (the beams' switches at their exact
controller times), ``place_plate`` (the operator moves the kinematic-fixture plate) and ``fault``
(``reflex``, optionally ``after_motion_s``; ``drop``: the client's connection is cut).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np

from cellcal.sims.fake_ur.process import FakeUrProcess
from cellcal.sims.physics.clock import MAX_TIME_SCALE, checked_time_scale

CONTROL_PORT = 30199  # as the fake UR controller's: one fake per loopback address
FAULT_KINDS = ("reflex", "drop")
FRANKA_PORT = 1337  # libfranka's command port


class ControlServer:
    """The fake-only JSON port of one simulated arm (a thread per client)."""

    def __init__(self, arm, host: str, port: int = CONTROL_PORT):
        self.arm = arm
        self.listener = socket.create_server((host, port), reuse_port=False)
        self._thread = threading.Thread(target=self._accept, daemon=True, name="franka control port")

    def start(self) -> "ControlServer":
        self._thread.start()
        return self

    def _accept(self) -> None:
        while True:
            try:
                sock, _ = self.listener.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(sock,), daemon=True).start()

    def _serve(self, sock: socket.socket) -> None:
        try:
            for line in sock.makefile("r"):
                try:
                    reply = self.control(json.loads(line))
                except Exception as exc:  # a bad request must not end the simulator
                    reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
                sock.sendall((json.dumps(reply) + "\n").encode())
        except (OSError, ValueError):
            pass
        finally:
            sock.close()

    def control(self, request: dict) -> dict:
        arm, cmd = self.arm, request.get("cmd")
        if cmd == "edges":
            first, wait_s = int(request.get("first", 0)), min(max(float(request.get("wait_s", 0.0)), 0.0), 5.0)
            with arm.cond:
                arm.cond.wait_for(lambda: arm.sensors.count > first, wait_s)
                return {"ok": True, "t_s": arm.t_s, "next": arm.sensors.count,
                        "edges": [[n, e.t_s, e.channel, e.edge.value] for n, e in arm.sensors.since(first)]}
        with arm.lock:
            if cmd == "state":
                return {"ok": True, "t_s": arm.t_s, "q": arm.q().tolist(), "reflex": arm.reflex,
                        "tcp_offset": arm.end_effector_pose().tolist(),
                        "force_n": arm.force_n.tolist(), "moving": bool(arm.server.current_motion_id),
                        "plate_step": arm.plate_step, "messages": arm.messages[-20:]}
            if cmd == "truth":
                return {"ok": True, "truth": arm.truth.report(), "arm_params": arm.truth.arm_params.tolist()}
            if cmd == "tool":
                return {"ok": True, "t_s": arm.t_s, "q": arm.q().tolist(), "tool_tip_m": arm.tool_tip().tolist(),
                        "tool_body_m": [p.tolist() for p in arm.tool_body()]}
            if cmd == "place_plate":
                return arm.place_plate(request.get("step"))
            if cmd == "fault":
                if request.get("kind") not in FAULT_KINDS:
                    return {"ok": False, "error": f"unknown fault {request.get('kind')!r} "
                                                  f"(kinds: {', '.join(FAULT_KINDS)})"}
                arm.faults.append(dict(request))
                return {"ok": True}
            if cmd == "mount_tool":
                return {"ok": False, "error": "the simulated Franka cell has no tool changer"}
        return {"ok": False, "error": f"unknown command {cmd!r} (state, truth, tool, edges, place_plate, fault)"}

    def close(self) -> None:
        self.listener.close()


class FrankaSimProcess(FakeUrProcess):
    """``with FrankaSimProcess("127.0.9.1", cell_file=...) as sim: ...``; always ends the process. Started,
    asked and stopped as the fake UR controller's process is (the same control protocol)."""

    what = "simulated Franka arm"

    def __init__(self, host: str, *, cell_file: str, control_port: int = CONTROL_PORT, time_scale: float = 1.0):
        self.host, self.control_port = host, control_port
        self.args = [sys.executable, "-m", "cellcal.sims.franka.process", "--host", host, "--cell-file",
                     str(cell_file), "--control-port", str(control_port), "--parent-pid", str(os.getpid())]
        if time_scale != 1.0:
            self.args += ["--time-scale", repr(checked_time_scale(time_scale))]
        self.proc: subprocess.Popen | None = None
        self._stderr = None

    def start(self, timeout_s: float = 60.0) -> "FrankaSimProcess":  # MuJoCo and pinocchio take a while to load
        return super().start(timeout_s)


def _exit_with_parent(parent_pid: int, arm) -> None:
    while os.getppid() == parent_pid:
        time.sleep(0.5)
    arm.close()


def main(argv=None) -> int:
    from cellcal.config.cell_files import read_cell
    from cellcal.config.robot_files import load_robot
    from cellcal.sims.franka.arm import CellArm
    from cellcal.sims.physics.truth import truth_of_cell
    from cellcal.solvers.geometry import se3

    parser = argparse.ArgumentParser(prog="python -m cellcal.sims.franka.process",
                                     description="A simulated Franka arm (franky-sim, MuJoCo) in a cell's hidden truth.")
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to serve on (127.x.y.z)")
    parser.add_argument("--cell-file", required=True, help="the cell file whose hidden truth (sim_truth) the arm obeys")
    parser.add_argument("--control-port", type=int, default=CONTROL_PORT)
    parser.add_argument("--time-scale", type=checked_time_scale, default=1.0, metavar="K",
                        help=f"simulated seconds per wall second, where the machine keeps up (0 < K <= "
                             f"{MAX_TIME_SCALE:g}; default 1)")
    parser.add_argument("--parent-pid", type=int, help="exit when this process ends")
    args = parser.parse_args(argv)
    cell = read_cell(args.cell_file)
    model = load_robot(cell.robot)
    # the end effector as Desk has it configured: the cell's tool as drawn (the hand's own without a tool)
    end_effector = se3.homogeneous(se3.rotvec_to_matrix(cell.tool.tcp_pose[3:]), cell.tool.tcp_pose[:3]) \
        if cell.tool is not None else None
    arm = CellArm(truth_of_cell(cell, model), model, host=args.host, q0=np.asarray(cell.home_q_rad, float),
                  seed=cell.sim_truth.seed if cell.sim_truth is not None else 0, time_scale=args.time_scale,
                  end_effector=end_effector)
    control = ControlServer(arm, args.host, args.control_port).start()
    signal.signal(signal.SIGTERM, lambda *_: arm.close())
    if args.parent_pid:
        threading.Thread(target=_exit_with_parent, args=(args.parent_pid, arm), daemon=True).start()
    print(f"READY {args.host}", flush=True)
    try:
        arm.run()
    except KeyboardInterrupt:
        pass
    finally:
        control.close()
        arm.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
