"""The tool frame a UR robot program applies at its start, kept in RTDE input registers.

ur_rtde's ``setTcp`` changes the tool frame of the running program only: the next program
starts with the installation's TCP. So the frame is also written to general-purpose input
registers, which the controller holds until it restarts (inputs retain their last received
value, and keep it after the writer disconnects), and the robot program applies them with
``set_tcp`` when it starts (the README shows the lines):

    input_double_register_N .. N+5   x, y, z (m), rx, ry, rz (rad): flange -> TCP
    input_int_register_N             generation: the run whose frame it is; 0: none stored
    input_int_register_N+1           FORMAT_TAG: these registers hold a cellcal tool frame

N is 24 unless the cell file says otherwise (``tool_frame_register``): the fieldbus adapters
(EtherNet/IP, PROFINET) reserve registers 0-23, and ur_rtde's control script uses the lower
range itself.

ur_rtde's RTDEIOInterface is not used for this: it offers five double registers per range
(18-22 or 42-46) and writes each in its own package, so a program starting between two
writes would apply half of an old frame and half of a new one. Here one RTDE input recipe
holds all eight values, and one data package carries them: the controller applies it in one
cycle, so a program never sees a mixed frame. The registers are read back through an output
recipe on the same connection (RTDE outputs include the input registers).
"""
from __future__ import annotations

import socket
import struct
import time

import numpy as np

from cellcal.drivers.interfaces import DeviceError, DeviceTimeout, StoredToolFrame
from cellcal.drivers.ur.state import _Wire, TYPE_FORMATS, negotiate, output_recipe, rtde_connect, setup_errors

FORMAT_TAG = 0x43434631  # "CCF1" in ASCII: 1128482353
FIRST_REGISTER, FIRST_REGISTER_RANGE = 24, (24, 42)  # N+5 and N+1 must stay within 0..47
READ_BACK_HZ = 125.0  # every controller generation streams at this rate
SETTLE_S = 0.024  # controller time a write gets to show in the outputs: 3 packages at 125 Hz


def register_names(first: int) -> tuple[str, ...]:
    """The eight input registers, in the order of the frame, the generation and the tag."""
    return (*(f"input_double_register_{first + i}" for i in range(6)),
            f"input_int_register_{first}", f"input_int_register_{first + 1}")


def register_text(first: int) -> str:
    return f"input_double_register_{first}..{first + 5} and input_int_register_{first}..{first + 1}"


class ToolFrameRegisters:
    """Reads and writes the stored tool frame, each on a short RTDE connection of its own."""

    def __init__(self, host: str, *, device: str, first_register: int = FIRST_REGISTER, timeout_s: float = 3.0):
        low, high = FIRST_REGISTER_RANGE
        if not low <= int(first_register) <= high:
            raise ValueError(f"tool_frame_register must be in {low}..{high}, got {first_register}")
        self.host, self.device, self.timeout_s = host, device, timeout_s
        self.first = int(first_register)
        self.names = register_names(self.first)

    def read(self) -> StoredToolFrame:
        """The frame the registers hold now; a frame whose tag is not ours has generation 0."""
        wire, out_id, layout = self._open(writing=False)
        try:
            return self._stored(self._package(wire, out_id, layout, time.monotonic() + self.timeout_s)[1:])
        finally:
            _close(wire)

    def write(self, stored: StoredToolFrame) -> None:
        """Write the frame in one data package and wait until the controller shows it (or
        SETTLE_S of controller time passed: the caller reads back and compares)."""
        frame = np.asarray(stored.tool_frame, dtype=float)
        generation = int(stored.generation)
        if frame.shape != (6,) or not np.all(np.isfinite(frame)):
            raise ValueError(f"a stored tool frame must be 6 finite numbers, got {stored.tool_frame!r}")
        if not 0 <= generation < 2**31:
            raise ValueError(f"a generation must fit an int register (0..2**31-1), got {generation}")
        wire, out_id, layout, in_id = self._open(writing=True)
        try:
            deadline = time.monotonic() + self.timeout_s
            with setup_errors(self.device, "tool frame write"):
                wire.send("U", struct.pack(">B6dii", in_id, *frame, generation, FORMAT_TAG))
            wanted = (*frame, generation, FORMAT_TAG)
            first_t = None
            while True:
                values = self._package(wire, out_id, layout, deadline)
                first_t = values[0] if first_t is None else first_t
                if tuple(values[1:]) == wanted or values[0] >= first_t + SETTLE_S:
                    return
        finally:
            _close(wire)

    def _stored(self, values) -> StoredToolFrame:
        generation, tag = int(values[6]), int(values[7])
        return StoredToolFrame(np.array(values[:6], dtype=float), generation if tag == FORMAT_TAG else 0)

    def _open(self, writing: bool):
        """Connect, declare the read-back (and for a write the input) recipe, start."""
        sock = rtde_connect(self.host, self.device, self.timeout_s)
        wire = _Wire(sock)
        try:
            negotiate(wire, self.device)
            out_id, layout, _ = output_recipe(wire, self.device, READ_BACK_HZ, ("timestamp", *self.names))
            in_id = self._input_recipe(wire) if writing else None
            with setup_errors(self.device, "start"):
                started = wire.request("S")[0]
            if not started:
                raise DeviceError(self.device, "controller refused to start RTDE for the tool frame registers")
        except BaseException:
            sock.close()
            raise
        return (wire, out_id, layout, in_id) if writing else (wire, out_id, layout)

    def _input_recipe(self, wire: _Wire) -> int:
        with setup_errors(self.device, "input set-up"):
            reply = wire.request("I", ",".join(self.names).encode())
            recipe_id, types = reply[0], reply[1:].decode(errors="replace").split(",")
        if "IN_USE" in types:
            raise DeviceError(self.device, f"{register_text(self.first)} are in use by another RTDE client or a "
                                           "fieldbus adapter (EtherNet/IP, PROFINET, Modbus): the tool frame for "
                                           "the program's start cannot be stored; choose tool_frame_register")
        if recipe_id == 0 or len(types) != len(self.names) or any(t not in TYPE_FORMATS for t in types):
            raise DeviceError(self.device, f"the controller does not offer {register_text(self.first)} "
                                           f"as RTDE inputs (it answered {','.join(types)})")
        return recipe_id

    def _package(self, wire: _Wire, recipe_id: int, layout: struct.Struct, deadline: float) -> tuple:
        """(timestamp, the eight register values) of the next data package of our recipe."""
        while True:
            if time.monotonic() > deadline:
                raise DeviceTimeout(self.device, f"no RTDE data from the tool frame registers within "
                                                 f"{self.timeout_s:g} s")
            with setup_errors(self.device, "tool frame read-back"):
                kind, payload = wire.receive()
            if kind == "U" and payload and payload[0] == recipe_id:
                with setup_errors(self.device, "tool frame read-back"):
                    return layout.unpack(payload)[1:]


def _close(wire: _Wire) -> None:
    try:
        wire.send("P")  # polite: the controller stops streaming before the socket closes
    except OSError:
        pass
    try:
        wire.sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    wire.sock.close()
