"""RTDE wire format as a UR controller speaks it on port 30004, for the fake controller.

Packets are big-endian ``[uint16 size][uint8 type][payload]`` with size counting the
3-byte header. A client negotiates the protocol version (``V``), asks the controller
version (``v``), declares output recipes (``O``: frequency + variable names, answered
with the RTDE type of each name) and input recipes (``I``: names, answered with a recipe
id and the types), starts the stream (``S``) and then exchanges data packages (``U``).

The type names are the controller's own (RTDE guide): clients such as ur_rtde decode
with their own tables and only look for ``NOT_FOUND`` / ``IN_USE`` in the reply, but a
client that does decode by the reply (UR's Python rtde module) needs the real names.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field

HEADER = struct.Struct(">HB")

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

# struct format of each RTDE type (big-endian, no padding)
TYPE_FORMATS = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}


def _output_types() -> dict[str, str]:
    types = {
        "timestamp": "DOUBLE", "target_q": "VECTOR6D", "target_qd": "VECTOR6D",
        "target_qdd": "VECTOR6D", "target_current": "VECTOR6D", "target_moment": "VECTOR6D",
        "actual_q": "VECTOR6D", "actual_qd": "VECTOR6D", "actual_current": "VECTOR6D",
        "actual_current_window": "VECTOR6D", "actual_current_as_torque": "VECTOR6D",
        "joint_control_output": "VECTOR6D", "actual_TCP_pose": "VECTOR6D",
        "actual_TCP_speed": "VECTOR6D", "actual_TCP_force": "VECTOR6D",
        "target_TCP_pose": "VECTOR6D", "target_TCP_speed": "VECTOR6D",
        "actual_digital_input_bits": "UINT64", "joint_temperatures": "VECTOR6D",
        "actual_execution_time": "DOUBLE", "robot_mode": "INT32", "joint_mode": "VECTOR6INT32",
        "safety_mode": "INT32", "safety_status": "INT32", "actual_tool_accelerometer": "VECTOR3D",
        "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
        "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
        "actual_robot_current": "DOUBLE", "actual_joint_voltage": "VECTOR6D",
        "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
        "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D",
        "robot_status_bits": "UINT32", "safety_status_bits": "UINT32", "analog_io_types": "UINT32",
        "standard_analog_input0": "DOUBLE", "standard_analog_input1": "DOUBLE",
        "standard_analog_output0": "DOUBLE", "standard_analog_output1": "DOUBLE",
        "io_current": "DOUBLE", "tool_mode": "UINT32", "tool_analog_input_types": "UINT32",
        "tool_analog_input0": "DOUBLE", "tool_analog_input1": "DOUBLE",
        "tool_output_voltage": "INT32", "tool_output_current": "DOUBLE",
        "tool_temperature": "DOUBLE", "tcp_force_scalar": "DOUBLE", "payload": "DOUBLE",
        "payload_cog": "VECTOR3D", "payload_inertia": "VECTOR6D", "ft_raw_wrench": "VECTOR6D",
        "script_control_line": "UINT32", "output_bit_registers0_to_31": "UINT32",
        "output_bit_registers32_to_63": "UINT32", "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
    }
    for i in range(48):
        for direction in ("input", "output"):
            types[f"{direction}_int_register_{i}"] = "INT32"
            types[f"{direction}_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        types[f"input_bit_register_{i}"] = "BOOL"
        types[f"output_bit_register_{i}"] = "BOOL"
    return types


OUTPUT_TYPES = _output_types()

INPUT_TYPES = {
    **{f"input_int_register_{i}": "INT32" for i in range(48)},
    **{f"input_double_register_{i}": "DOUBLE" for i in range(48)},
    **{f"input_bit_register_{i}": "BOOL" for i in range(64, 128)},
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
    "external_force_torque": "VECTOR6D",
}


def packet(kind: int, payload: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


@dataclass
class Recipe:
    """One declared recipe: its id, variable names, RTDE types and struct layout."""

    recipe_id: int
    names: list[str]
    types: list[str]
    frequency_hz: float = 0.0  # output recipes only
    layout: struct.Struct = field(init=False)

    def __post_init__(self):
        self.layout = struct.Struct(">B" + "".join(TYPE_FORMATS.get(t, "") for t in self.types))

    @property
    def valid(self) -> bool:
        return all(t in TYPE_FORMATS for t in self.types)

    def type_reply(self) -> bytes:
        return bytes([self.recipe_id]) + ",".join(self.types).encode()

    def pack(self, values: dict) -> bytes:
        """A data package of this (output) recipe from a snapshot of the controller state."""
        flat: list = [self.recipe_id]
        for name, kind in zip(self.names, self.types):
            value = values[name]
            if kind.startswith("VECTOR"):
                flat.extend(value)
            else:
                flat.append(value)
        return packet(DATA_PACKAGE, self.layout.pack(*flat))

    def unpack(self, payload: bytes) -> dict:
        """Field values of an (input) data package, the recipe id byte included in payload.

        A short package (a client may send fewer trailing fields) yields the fields it holds.
        """
        out = {}
        offset = 1
        for name, kind in zip(self.names, self.types):
            fmt = ">" + TYPE_FORMATS[kind]
            size = struct.calcsize(fmt)
            if offset + size > len(payload):
                break
            value = struct.unpack_from(fmt, payload, offset)
            out[name] = value if kind.startswith("VECTOR") else value[0]
            offset += size
        return out


def parse_output_setup(payload: bytes, recipe_id: int) -> Recipe:
    """``O`` request: double frequency then comma-separated names (trailing comma allowed)."""
    (frequency,) = struct.unpack_from(">d", payload, 0)
    names = [n for n in payload[8:].decode(errors="replace").split(",") if n]
    return Recipe(recipe_id, names, [OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names], frequency)


def parse_input_setup(payload: bytes, recipe_id: int, in_use: set[str]) -> Recipe:
    """``I`` request: comma-separated names; a field another connection owns is ``IN_USE``."""
    names = [n for n in payload.decode(errors="replace").split(",") if n]
    types = ["IN_USE" if n in in_use else INPUT_TYPES.get(n, "NOT_FOUND") for n in names]
    return Recipe(recipe_id, names, types)
