"""A cell as its cell file describes it: which robot, which drivers with which options, the
tool table, the beam, the safety box (the cell file's reader: :mod:`.cell_files`).

All lengths in metres, base frame unless said otherwise. A :class:`Cell` is valid by
construction: only :func:`cellcal.config.cell_files.read_cell` builds one from a file.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace

import numpy as np

from cellcal.solvers.geometry import se3
from cellcal.config.reader import ConfigError, Section

DEVICE_KINDS = ("robot", "trigger", "tracker", "panel")
# the cell file's own sections; every other one is a routine's
CELL_SECTIONS = frozenset({"cell", "drivers", "robots", "workspace", "limits", "tool", "tools", "mounted", "beams",
                           "stylus", "pivot", "sim_truth", "status_page", "plant"})
TOOL_IDS = (1, 255)  # a tool table's ids (the panel's tool register holds one)


class CellFileError(ConfigError):
    """A cell file that cannot be used, with the file, section and key in the message."""


@dataclass(frozen=True)
class DriverSpec:
    """One device of the cell: a registered driver name and the options it is built with."""

    name: str
    options: dict = field(default_factory=dict)


PLAUSIBLE_MM = 10.0  # a real tool is within this of its drawing (the plausibility gate) ...
PLAUSIBLE_DEG = 5.0  # ... and its axis within this of the drawn axis


@dataclass(frozen=True)
class Bands:
    """A tool's tolerance bands for a check (``tcp-check``): within the inner band the tool is
    fine (nothing written); within the outer one a well-determined shift is corrected (written
    back); beyond it, an alarm (nothing written). Position in mm, axis in degrees."""

    inner_mm: float = 0.1
    inner_deg: float = 0.1
    outer_mm: float = 1.0
    outer_deg: float = 1.0
    # the drift alarm (off when None): a check whose measured frame is this far from the last
    # full calibration's (tip mm, axis deg) ends in verdict "drift" (daemon/drift.py)
    drift_mm: float | None = None
    drift_deg: float | None = None


@dataclass(frozen=True)
class ToolSpec:
    """A tool as drawn: a cylinder (a pin, a grinding tool) ending in its TCP."""

    tcp_m: np.ndarray  # the tip in the flange frame
    axis: np.ndarray  # unit, flange frame, from the flange toward the tip
    radius_m: float
    length_m: float  # of the cylinder behind the tip
    bands: Bands = field(default_factory=Bands)
    id: int = 1  # its id in the cell's tool table (a file's ``tool`` is tool 1)
    name: str = "tool"
    sections: dict = field(default_factory=dict)  # routine section -> its keys that differ for this tool
    frame_block: int | None = None  # its block of the robot's stored tool frames (None: its place in the table)

    @property
    def tcp_pose(self) -> np.ndarray:
        """[x, y, z, rx, ry, rz]: the tool frame whose z is the tool axis (rotation about it
        by the smallest turn from the flange's z)."""
        return np.concatenate([self.tcp_m, se3.rotvec_from_z(self.axis)])


@dataclass(frozen=True)
class RobotSpec:
    """One robot of the cell: its model, home, driver, tool as drawn, and where its base is
    in the cell frame (robot a's base) as installed (the handshake measures it)."""

    name: str  # "a" or "b"
    robot: str  # model file or shipped name
    home_q_rad: tuple
    driver: DriverSpec
    tool: ToolSpec | None = None
    base_pose: np.ndarray = field(default_factory=lambda: np.zeros(6))  # [x, y, z, rx, ry, rz] m, rad

    @property
    def base_matrix(self) -> np.ndarray:
        """4x4: points in this robot's base frame -> the cell frame."""
        return se3.homogeneous(se3.rotvec_to_matrix(self.base_pose[3:]), self.base_pose[:3])


@dataclass(frozen=True)
class BeamSpec:
    point_m: np.ndarray
    direction: np.ndarray  # unit
    radius_m: float  # half the beam width
    channel: int
    level_when_blocked: bool


@dataclass(frozen=True)
class SimTruthSpec:
    """What a simulated cell really has, as the cell file states it or draws it from ``seed``.

    Only simulations and the scoring of their results read it; routines and solvers never.
    """

    seed: int = 0
    arm_length_error_mm: float = 0.0  # every length of the arm off its drawing by up to this
    arm_angle_error_deg: float = 0.0
    tool_tcp_m: np.ndarray | None = None  # the real tip in the flange frame (else drawn)
    tool_tcp_error_mm: float = 1.0  # how far the real tip is from the drawing (drawn)
    tool_axis: np.ndarray | None = None  # the real axis (else drawn)
    tool_tilt_deg: float = 0.5  # runout: how far the real axis is tilted from the drawing (drawn)
    fixture_error_mm: float = 0.5  # beams, stylus and pivot this far from where the file says (drawn)
    repeatability_mm: float = 0.03
    trigger_latency_s: float = 0.0
    trigger_jitter_s: float = 0.0
    base_error_mm: float = 5.0  # robot b's base this far from where [robots.b] says (drawn)
    base_error_deg: float = 0.5  # ... and turned this far


@dataclass(frozen=True)
class StatusPageSpec:
    """The daemon's read-only status page and JSON API (``status_page:``)."""

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 8037
    max_connections: int = 8
    rate_per_s: float = 20.0


@dataclass(frozen=True)
class MqttSpec:
    """Where the service publishes to the plant's MQTT broker (``plant: mqtt:``): the broker, the cell's
    topic (``TOPIC/state``, retained, and ``TOPIC/runs/<run id>``), and the credentials and TLS files
    (absolute paths; a password only in a file readable by the service user alone)."""

    host: str
    topic: str
    client_id: str
    port: int = 1883
    username: str | None = None
    password_file: str | None = None
    tls_ca: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    keepalive_s: int = 30
    outbox_limit: int = 10000  # finished runs kept for the broker, oldest dropped from the outbox beyond


@dataclass(frozen=True)
class OpcuaSpec:
    """The service's read-only OPC UA server (``plant: opcua:``)."""

    endpoint: str
    security: str = "none"  # or "Basic256Sha256_SignAndEncrypt"
    certificate: str | None = None
    private_key: str | None = None


@dataclass(frozen=True)
class PlantSpec:
    """What the service publishes to the plant (``plant:``); each part off when absent."""

    mqtt: MqttSpec | None = None
    opcua: OpcuaSpec | None = None


@dataclass(frozen=True)
class MountedSource:
    """Where the service learns which tool of the table is on the flange: ``file`` (``tool``,
    fixed by the cell file's ``mounted``), ``panel`` (the panel's mounted-tool register, written
    by the PLC or the tool changer) or ``robot_inputs`` (the tool changer's id on the robot's
    digital inputs ``bits``, least significant first; 0 there: no tool)."""

    kind: str
    tool: int = 0
    bits: tuple = ()

    def describe(self) -> str:
        if self.kind == "panel":
            return "the panel's mounted-tool register"
        if self.kind == "robot_inputs":
            return f"the tool changer's id on the robot's digital inputs {', '.join(map(str, self.bits))}"
        return "the cell file's `mounted`"


@dataclass
class Cell:
    """A validated cell file."""

    path: str
    name: str
    robot: str
    home_q_rad: tuple
    drivers: dict  # kind -> DriverSpec
    workspace_min_m: np.ndarray
    workspace_max_m: np.ndarray
    limits: dict
    tool: ToolSpec | None = None
    beams: tuple[BeamSpec, ...] = ()
    stylus: dict | None = None  # {"centre_m": (3,), "radius_m": r}
    pivot_m: np.ndarray | None = None
    sim_truth: SimTruthSpec | None = None
    routines: dict = field(default_factory=dict)  # section name -> mapping (the mounted tool's merged in)
    robots: dict = field(default_factory=dict)  # name -> RobotSpec; {"a"} alone in a one-robot cell
    tools: dict = field(default_factory=dict)  # id -> ToolSpec: the tool table (robot a's; `tool` is the mounted one)
    file_routines: dict = field(default_factory=dict)  # the routine sections as written, no tool's merged in
    mounted_source: "MountedSource" = None  # where the service learns which tool is mounted
    status_page: StatusPageSpec = field(default_factory=StatusPageSpec)  # the daemon's read-only page and API
    plant: PlantSpec = field(default_factory=PlantSpec)  # what the service publishes to the plant (off: none)

    def __post_init__(self):
        if self.mounted_source is None:
            self.mounted_source = MountedSource("file", self.tool.id if self.tool is not None else 0)

    def with_tool(self, tool_id: int) -> "Cell":
        """The same cell with tool `tool_id` of its table mounted: `tool` (and robot a's tool)
        is that tool, and its routine sections are merged over the file's own. Raises
        CellFileError for an id the table does not have."""
        if tool_id not in self.tools:
            have = ", ".join(map(str, self.tools)) or "none"
            raise CellFileError(f"no tool {tool_id} in this cell (its tools: {have})", source=self.path,
                                section="tools" if len(self.tools) > 1 else "tool")
        other = copy.deepcopy(self)
        other.tool = other.tools[tool_id]
        other.routines = merged_sections(other.file_routines, other.tool)
        other.robots["a"] = replace(other.robots["a"], tool=other.tool)
        return other

    def on_host(self, host: str) -> "Cell":
        """The same cell with every networked driver pointed at another address (parallel test cells)."""
        other = copy.deepcopy(self)  # one deepcopy: robot a's driver stays drivers["robot"]
        for spec in [*other.drivers.values(), *(r.driver for r in other.robots.values())]:
            if "host" in spec.options:
                spec.options["host"] = host
        return other

    def routine_section(self, name: str, error: type[ConfigError] | None = None) -> Section:
        """The routine's own section, to read with the same checks (empty when the file has none)."""
        return Section(self.path, name, self.routines.get(name, {}), error or CellFileError)


def merged_sections(file_routines: dict, tool: ToolSpec | None) -> dict:
    """The routine sections with `tool`'s own keys merged over the file's (key by key)."""
    merged = copy.deepcopy(file_routines)
    for section, keys in (tool.sections if tool is not None else {}).items():
        merged[section] = {**merged.get(section, {}), **copy.deepcopy(keys)}
    return merged


def tool_blocks(tools: dict) -> dict[int, int]:
    """Tool id -> its block of the robot's stored tool frames (the robot program's frame at its
    start; a UR: one block of input registers per tool): its ``frame_block``, else its place in
    the table (0-based, file order; a file's one ``tool``: 0)."""
    return {tool_id: place if tool.frame_block is None else tool.frame_block
            for place, (tool_id, tool) in enumerate(tools.items())}
