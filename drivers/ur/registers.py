"""The tool frame a UR robot program applies at its start, kept in RTDE input registers.

ur_rtde's ``setTcp`` changes the tool frame of the running program only: the next program
starts with the installation's TCP. So the frame is also written to general-purpose input
registers, which the controller holds until it restarts (inputs retain their last received
value, and keep it after the writer disconnects), and the robot program applies them with
``set_tcp`` when it starts (docs/integrator.md shows the lines):

    input_double_register_N .. N+5   x, y, z (m), rx, ry, rz (rad): flange -> TCP
    input_int_register_N             generation: the run whose frame it is; 0: none stored
    input_int_register_N+1           FORMAT_TAG: these registers hold a cellcal tool frame

N is 24 unless the cell file says otherwise (``tool_frame_register``): the fieldbus adapters
(EtherNet/IP, PROFINET) reserve registers 0-23, and ur_rtde's control script uses the lower
range itself.

A cell with several tools keeps one such block per tool: block k (the tool's slot,
``cellcal.daemon.frame_writer.tool_slot``) starts at register N+6k, doubles N+6k..N+6k+5 and ints
N+6k (generation) and N+6k+1 (tag). The registers end at 47, so there are
:func:`block_count` blocks (N=24: 4); a tool beyond them keeps its frame only in the running
program.

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
LAST_REGISTER = 47  # the controller's general-purpose input registers are numbered 0..47
BLOCK_STRIDE = 6  # registers from one tool's block to the next (six doubles; the two ints fit within)
READ_BACK_HZ = 125.0  # every controller generation streams at this rate
SETTLE_S = 0.024  # controller time a write gets to show in the outputs: 3 packages at 125 Hz


def register_names(first: int) -> tuple[str, ...]:
    """The eight input registers, in the order of the frame, the generation and the tag."""
    return (*(f"input_double_register_{first + i}" for i in range(6)),
            f"input_int_register_{first}", f"input_int_register_{first + 1}")


def register_text(first: int) -> str:
    return f"input_double_register_{first}..{first + 5} and input_int_register_{first}..{first + 1}"


def block_count(first: int) -> int:
    """How many tool-frame blocks fit from register `first` up to the last input register."""
    return max(0, (LAST_REGISTER - (int(first) + 5)) // BLOCK_STRIDE + 1)


def block_first(first: int, slot: int) -> int:
    """The first register of block `slot` (0-based)."""
    return int(first) + BLOCK_STRIDE * int(slot)


class ToolFrameRegisters:
    """Reads and writes the stored tool frames, one block per slot (:func:`block_first`), each
    read or write on a short RTDE connection of its own."""

    def __init__(self, host: str, *, device: str, first_register: int = FIRST_REGISTER, timeout_s: float = 3.0):
        low, high = FIRST_REGISTER_RANGE
        if not low <= int(first_register) <= high:
            raise ValueError(f"tool_frame_register must be in {low}..{high}, got {first_register}")
        self.host, self.device, self.timeout_s = host, device, timeout_s
        self.first = int(first_register)
        self.names = register_names(self.first)  # block 0's
        self.slots = block_count(self.first)

    def text(self) -> str:
        """The blocks, for messages: "blocks for 4 tools from input register 24"."""
        return f"blocks for {self.slots} tool{'s' if self.slots != 1 else ''} from input register {self.first}"

    def _block(self, slot: int) -> int:
        slot = int(slot)
        if not 0 <= slot < self.slots:
            raise DeviceError(self.device, f"no tool frame block {slot}: the input registers hold {self.text()} "
                                           f"(blocks 0..{self.slots - 1})")
        return block_first(self.first, slot)

    def read(self, slot: int = 0) -> StoredToolFrame:
        """The frame block `slot` holds now; a frame whose tag is not ours has generation 0."""
        first = self._block(slot)
        wire, out_id, layout = self._open(writing=False, first=first)
        try:
            return self._stored(self._package(wire, out_id, layout, time.monotonic() + self.timeout_s)[1:])
        finally:
            _close(wire)

    def write(self, stored: StoredToolFrame, slot: int = 0) -> None:
        """Write the frame to block `slot` in one data package and wait until the controller
        shows it (or SETTLE_S of controller time passed: the caller reads back and compares)."""
        first = self._block(slot)
        frame = np.asarray(stored.tool_frame, dtype=float)
        generation = int(stored.generation)
        if frame.shape != (6,) or not np.all(np.isfinite(frame)):
            raise ValueError(f"a stored tool frame must be 6 finite numbers, got {stored.tool_frame!r}")
        if not 0 <= generation < 2**31:
            raise ValueError(f"a generation must fit an int register (0..2**31-1), got {generation}")
        wire, out_id, layout, in_id = self._open(writing=True, first=first)
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

    def _open(self, writing: bool, first: int | None = None):
        """Connect, declare the read-back (and for a write the input) recipe of the block from
        register `first` (default: block 0), start."""
        first = self.first if first is None else int(first)
        names = register_names(first)
        sock = rtde_connect(self.host, self.device, self.timeout_s)
        wire = _Wire(sock)
        try:
            negotiate(wire, self.device)
            out_id, layout, _ = output_recipe(wire, self.device, READ_BACK_HZ, ("timestamp", *names))
            in_id = self._input_recipe(wire, first) if writing else None
            with setup_errors(self.device, "start"):
                started = wire.request("S")[0]
            if not started:
                raise DeviceError(self.device, "controller refused to start RTDE for the tool frame registers")
        except BaseException:
            sock.close()
            raise
        return (wire, out_id, layout, in_id) if writing else (wire, out_id, layout)

    def _input_recipe(self, wire: _Wire, first: int) -> int:
        names = register_names(first)
        with setup_errors(self.device, "input set-up"):
            reply = wire.request("I", ",".join(names).encode())
            recipe_id, types = reply[0], reply[1:].decode(errors="replace").split(",")
        if "IN_USE" in types:
            choose = "choose tool_frame_register" if first == self.first else \
                "choose the tool's frame_block in the cell file's tool table, or tool_frame_register"
            raise DeviceError(self.device, f"{register_text(first)} are in use by another RTDE client or a "
                                           "fieldbus adapter (EtherNet/IP, PROFINET, Modbus): the tool frame for "
                                           f"the program's start cannot be stored; {choose}")
        if recipe_id == 0 or len(types) != len(names) or any(t not in TYPE_FORMATS for t in types):
            raise DeviceError(self.device, f"the controller does not offer {register_text(first)} "
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
