"""Run the fake UR controller in its own process and talk to its control port.

It has to be another process: ur_rtde's constructors hold the GIL while they wait for
the controller, so a fake in the same interpreter could never answer them. This module
is that process's entry point too: ``python -m cellcal.sims.fake_ur.process --host
127.0.7.1 [--cell-file CELL.yaml]``.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import selectors
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time

from cellcal.sims.fake_ur.controller import CONTROL_PORT, HOME_Q, FakeUrController
from cellcal.sims.fake_ur.control import FAULT_KINDS
from cellcal.sims.physics.clock import MAX_TIME_SCALE, checked_time_scale


class ControlClient:
    """One kept connection to the control port (for callers that ask often: the wiring of a
    networked cell); ``request`` raises RuntimeError if the fake says no, OSError if it is gone."""

    def __init__(self, host: str, port: int = CONTROL_PORT, timeout_s: float = 10.0, what: str = "fake UR controller"):
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        self.reader = self.sock.makefile("r", encoding="utf-8", newline="\n")
        self.host, self.what = host, what

    def request(self, **message) -> dict:
        self.sock.sendall((json.dumps(message) + "\n").encode())
        line = self.reader.readline()
        if not line:
            raise ConnectionError(f"{self.what} at {self.host} closed the control connection")
        reply = json.loads(line)
        if not reply.get("ok"):
            raise RuntimeError(f"{self.what} at {self.host}: {reply.get('error')}")
        return reply

    def interrupt(self) -> None:
        """End the connection under a request another thread is waiting on (it raises OSError)."""
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass

    def close(self) -> None:
        self.interrupt()
        self.reader.close()
        self.sock.close()


class FakeUrProcess:
    """``with FakeUrProcess("127.0.7.1", cell={...}) as fake: ...``; always ends the process.

    ``cell_file``: the controller obeys that cell file's hidden truth (built in the child
    from the file, so it is the truth the in-process cell and the run's score have)."""

    what = "fake UR controller"  # what the messages call it

    def __init__(self, host: str, *, robot: str | None = None, q0=None, cell: dict | None = None,
                 cell_file: str | None = None, plugins=(), control_port: int = CONTROL_PORT,
                 verbose: bool = False, arm: str | None = None, tool: int | None = None,
                 time_scale: float = 1.0):
        self.host, self.control_port = host, control_port
        self.args = [sys.executable, "-m", "cellcal.sims.fake_ur.process", "--host", host,
                     "--control-port", str(control_port), "--parent-pid", str(os.getpid())]
        if robot is not None or cell_file is None:
            self.args += ["--robot", robot or "ur10e"]
        if cell_file is not None:
            self.args += ["--cell-file", str(cell_file)]
        if q0 is not None:
            self.args += ["--q0", ",".join(repr(float(v)) for v in q0)]
        if cell is not None:
            self.args += ["--cell", json.dumps(cell)]
        for plugin in plugins:
            self.args += ["--plugin", plugin]
        if verbose:
            self.args.append("--verbose")
        if arm is not None:  # which robot of a two-robot cell file this controller is
            self.args += ["--arm", arm]
        if tool is not None:  # which tool of the cell file's tool table is mounted (default: its `mounted`)
            self.args += ["--tool", str(tool)]
        if time_scale != 1.0:  # simulated seconds per wall second
            self.args += ["--time-scale", repr(checked_time_scale(time_scale))]
        self.proc: subprocess.Popen | None = None
        self._stderr = None

    def start(self, timeout_s: float = 20.0) -> "FakeUrProcess":
        self._stderr = tempfile.TemporaryFile()
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=self._stderr,
                                     stdin=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout_s
        with selectors.DefaultSelector() as selector:
            selector.register(self.proc.stdout, selectors.EVENT_READ)
            while time.monotonic() < deadline:
                if selector.select(timeout=0.1):
                    line = self.proc.stdout.readline().decode(errors="replace")
                    if line.startswith("READY"):
                        return self
                    if not line:  # the process ended before it was ready
                        break
        self.stop()
        raise RuntimeError(f"{self.what} at {self.host} did not start: {self.stderr_text()[-2000:]}")

    def stderr_text(self) -> str:
        if self._stderr is None:
            return ""
        self._stderr.seek(0)
        return self._stderr.read().decode(errors="replace")

    def request(self, timeout_s: float = 5.0, **message) -> dict:
        """One JSON request on the control port; raises RuntimeError if the fake says no."""
        with socket.create_connection((self.host, self.control_port), timeout=timeout_s) as sock:
            sock.sendall((json.dumps(message) + "\n").encode())
            reply = json.loads(sock.makefile("r").readline())
        if not reply.get("ok"):
            raise RuntimeError(f"{self.what} at {self.host}: {reply.get('error')}")
        return reply

    def state(self) -> dict:
        return self.request(cmd="state")

    def client(self, timeout_s: float = 10.0) -> ControlClient:
        """A kept connection to the control port (close it when done)."""
        return ControlClient(self.host, self.control_port, timeout_s, self.what)

    def fault(self, kind: str, **when) -> None:
        """Inject a fault now, or with ``after_motion_s=...`` once the arm has moved that long."""
        self.request(cmd="fault", kind=kind, **when)

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill(self) -> None:
        """End it abruptly (SIGKILL): sockets vanish as when a controller loses power."""
        if self.alive:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=5)

    def stop(self, timeout_s: float = 5.0) -> None:
        if self.proc is None:
            return
        if self.alive:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.kill()
        if self.proc.stdout is not None:
            self.proc.stdout.close()

    def __enter__(self) -> "FakeUrProcess":
        return self.start() if self.proc is None else self

    def __exit__(self, *exc) -> None:
        self.stop()


def _exit_with_parent(parent_pid: int, controller: FakeUrController) -> None:
    while os.getppid() == parent_pid:
        time.sleep(0.5)
    controller.close()


def time_scale_arg(text: str) -> float:
    """An argparse type: a time scale (0 < K <= MAX_TIME_SCALE)."""
    try:
        return checked_time_scale(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cellcal.sims.fake_ur.process",
                                     description="A fake UR e-Series controller on one loopback address.")
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to serve on (127.x.y.z)")
    parser.add_argument("--robot", help="robot model file or shipped name (ur5e, ur10e; default: the cell "
                                        "file's robot, else ur10e)")
    parser.add_argument("--q0", help="initial joints, rad, comma separated")
    parser.add_argument("--cell", help="cell models as JSON: {\"models\": [{\"kind\": \"beam\", ...}]}")
    parser.add_argument("--cell-file", help="a cell file whose hidden truth (sim_truth) the controller obeys")
    parser.add_argument("--plugin", action="append", default=[],
                        help="module:factory called with the controller, e.g. to add input sources")
    parser.add_argument("--fault", action="append", default=[], metavar="KIND[@AFTER_MOTION_S]",
                        help=f"inject a fault at once or after the arm moved that long ({', '.join(FAULT_KINDS)})")
    parser.add_argument("--arm", default="a", choices=("a", "b"),
                        help="which robot of a two-robot cell file this controller is (default a)")
    parser.add_argument("--tool", type=int, help="with --cell-file: the id of the tool of its table that is "
                                                  "mounted (default: the file's `mounted`)")
    parser.add_argument("--time-scale", type=time_scale_arg, default=1.0, metavar="K",
                        help=f"run the controller's clock K times faster than the wall (0 < K <= "
                             f"{MAX_TIME_SCALE:g}; default 1, real time)")
    parser.add_argument("--control-port", type=int, default=CONTROL_PORT)
    parser.add_argument("--verbose", action="store_true", help="log controller messages to stderr")
    parser.add_argument("--parent-pid", type=int, help="exit when this process ends (no orphans after a crash)")
    args = parser.parse_args(argv)
    q0 = HOME_Q if args.q0 is None else [float(v) for v in args.q0.split(",")]
    controller = FakeUrController(args.host, robot=args.robot, q0=q0, cell=json.loads(args.cell or "{}"),
                                  cell_file=args.cell_file, control_port=args.control_port, verbose=args.verbose,
                                  arm=args.arm, tool=args.tool, time_scale=args.time_scale)
    for plugin in args.plugin:
        module, _, attr = plugin.partition(":")
        getattr(importlib.import_module(module), attr)(controller)
    for fault in args.fault:
        kind, _, after = fault.partition("@")
        controller.control({"cmd": "fault", "kind": kind, **({"after_motion_s": float(after)} if after else {})})
    # closed from a thread of its own: the handler runs in the main thread, which may hold the lock
    # of the event controller.wait() waits on, and closing there would deadlock
    signal.signal(signal.SIGTERM, lambda *_: threading.Thread(target=controller.close, daemon=True).start())
    if args.parent_pid:
        threading.Thread(target=_exit_with_parent, args=(args.parent_pid, controller), daemon=True).start()
    controller.start()
    print(f"READY {args.host}", flush=True)
    try:
        controller.wait()
    except KeyboardInterrupt:
        pass
    controller.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
