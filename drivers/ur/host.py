"""The child process that owns ur_rtde's control and IO interfaces for :mod:`.process`.

ur_rtde 1.6.5 is unsafe to run inside the daemon's own interpreter:

* its constructors hold Python's GIL while they wait for the controller, so a controller
  that accepts but never answers freezes every thread of the process;
* its destructors sleep 0.5 s each, also holding the GIL;
* after a dropped connection RTDEControlInterface reconnects from its receive thread,
  starts a second receive thread without stopping the first, and the two race until
  the process crashes (segfault) if the controller is reachable again.

So the interfaces live here, and the parent sees an EOF when this process dies. The
protocol on the inherited socket (``multiprocessing.connection`` framing, both ends ours):

* parent -> child: ``{"host", "frequency_hz"}`` once, then ``("call", id, "control.moveJ", args)``
  or ``("exit",)``;
* child -> parent: ``("ready",)`` or ``("error", text)``, then ``("result", id, value)`` or
  ``("raised", id, text)`` per call.

Each call runs in its own thread, so a call that blocks inside the controller (say
moveUntilContact) does not hold up the others. The process leaves with ``os._exit``:
there is nothing to flush, and ur_rtde's destructors are what must not run.
"""
from __future__ import annotations

import argparse
import os
import socket
import threading
from multiprocessing.connection import Connection

# ur_rtde is the `ur` extra of the package, not a dependency of every install
UR_RTDE_MODULES = ("rtde_control", "rtde_io")
UR_RTDE_MISSING = "the UR driver needs ur_rtde: pip install 'cellcal[ur]'"


class Host:
    def __init__(self, conn: Connection, config: dict):
        self.conn, self.config = conn, config
        self.send_lock = threading.Lock()
        self.interfaces: dict = {}

    def send(self, message) -> None:
        with self.send_lock:
            self.conn.send(message)

    def connect(self) -> None:
        try:
            import rtde_control
        except ModuleNotFoundError as exc:  # the parent checks first; this is the backstop
            raise RuntimeError(f"{UR_RTDE_MISSING} ({exc})") from None

        self.interfaces["control"] = rtde_control.RTDEControlInterface(self.config["host"],
                                                                       self.config["frequency_hz"])

    def interface(self, name: str):
        if name == "io" and "io" not in self.interfaces:  # opened on first use: few cells need it
            import rtde_io

            self.interfaces["io"] = rtde_io.RTDEIOInterface(self.config["host"])
        return self.interfaces[name]

    def call(self, call_id: int, target: str, args) -> None:
        try:
            name, _, method = target.partition(".")
            value = getattr(self.interface(name), method)(*args)
            if isinstance(value, tuple):
                value = list(value)
            message = ("result", call_id, value)
        except Exception as exc:  # reported to the parent, which raises DeviceError
            message = ("raised", call_id, f"{type(exc).__name__}: {exc}")
        try:
            self.send(message)
        except OSError:
            os._exit(0)

    def serve(self) -> None:
        while True:
            try:
                message = self.conn.recv()
            except (EOFError, OSError):
                os._exit(0)
            if message[0] == "exit":
                os._exit(0)
            if message[0] == "call":
                threading.Thread(target=self.call, args=message[1:], daemon=True, name=message[2]).start()


def main() -> None:
    parser = argparse.ArgumentParser(description="ur_rtde interfaces in a child process (internal)")
    parser.add_argument("--fd", type=int, required=True)
    args = parser.parse_args()
    conn = Connection(socket.socket(fileno=args.fd).detach())
    try:
        config = conn.recv()
        host = Host(conn, config)
        try:
            host.connect()
        except Exception as exc:  # ur_rtde raises bare RuntimeErrors
            conn.send(("error", str(exc)))
            os._exit(1)
        conn.send(("ready",))
        host.serve()
    except (EOFError, OSError):
        pass
    os._exit(0)


if __name__ == "__main__":
    main()
