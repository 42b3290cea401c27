"""Run the fake UR controller in its own process and talk to its control port.

It has to be another process: ur_rtde's constructors hold the GIL while they wait for
the controller, so a fake in the same interpreter could never answer them.
"""
from __future__ import annotations

import json
import os
import selectors
import signal
import socket
import subprocess
import sys
import tempfile
import time

from .fake_ur import CONTROL_PORT


class FakeUrProcess:
    """``with FakeUrProcess("127.0.7.1", cell={...}) as fake: ...``; always ends the process."""

    def __init__(self, host: str, *, robot: str = "ur10e", q0=None, cell: dict | None = None,
                 plugins=(), control_port: int = CONTROL_PORT, verbose: bool = False):
        self.host, self.control_port = host, control_port
        self.args = [sys.executable, "-m", "cellcal.sims.fake_ur", "--host", host, "--robot", robot,
                     "--control-port", str(control_port), "--parent-pid", str(os.getpid())]
        if q0 is not None:
            self.args += ["--q0", ",".join(repr(float(v)) for v in q0)]
        if cell is not None:
            self.args += ["--cell", json.dumps(cell)]
        for plugin in plugins:
            self.args += ["--plugin", plugin]
        if verbose:
            self.args.append("--verbose")
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
        raise RuntimeError(f"fake UR controller at {self.host} did not start: {self.stderr_text()[-2000:]}")

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
            raise RuntimeError(f"fake UR controller at {self.host}: {reply.get('error')}")
        return reply

    def state(self) -> dict:
        return self.request(cmd="state")

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
