"""The small interfaces every piece of cell hardware sits behind.

Modelled on python-can's ``BusABC``: a handful of methods, SI units at the
boundary (metres, radians, rotation vectors, seconds), and backends chosen by
name from the cell file through :mod:`cellcal.drivers.registry`, so routines
never import a concrete driver or simulator.

Every call that waits has a deadline and raises :class:`DeviceError` (or a
subclass) naming the device and what happened; nothing blocks forever.
"""
from __future__ import annotations

import abc
import enum
from dataclasses import dataclass

import numpy as np


class DeviceError(RuntimeError):
    """A device fault: connection refused or lost, timeout, bad message, stop."""

    def __init__(self, device: str, what: str):
        super().__init__(f"{device}: {what}")
        self.device = device
        self.what = what


class DeviceTimeout(DeviceError):
    """A wait ran past its deadline."""


class ProtocolError(DeviceError):
    """A malformed, truncated, out-of-order or badly checksummed message."""


class RobotState(enum.Enum):
    READY = "ready"
    PROGRAM_RUNNING = "program running"
    PROTECTIVE_STOP = "protective stop"
    EMERGENCY_STOP = "emergency stop"
    DISCONNECTED = "disconnected"


@dataclass(frozen=True)
class RobotSample:
    """One sample of the robot's state stream."""

    t_s: float  # controller time
    q_rad: np.ndarray  # (n_joints,)
    tcp_pose: np.ndarray  # (6,) x, y, z [m], rotation vector [rad], base frame
    digital_inputs: int = 0  # bit field, for triggers wired to the robot's own inputs


@dataclass(frozen=True)
class StoredToolFrame:
    """The tool frame a robot keeps for its program to apply at start (survives the program).

    ``generation`` says whose frame it is: 0 means none is stored (the program keeps the
    installation's TCP); the daemon writes the run id of the result it writes back.
    """

    tool_frame: np.ndarray  # (6,) flange -> TCP [x, y, z, rx, ry, rz] (m, rad)
    generation: int

    def same_as(self, other: "StoredToolFrame | None") -> bool:
        """Exactly equal: the values travel as IEEE doubles, so a kept write reads back bit for bit."""
        return (other is not None and self.generation == other.generation
                and bool(np.array_equal(np.asarray(self.tool_frame, float), np.asarray(other.tool_frame, float))))


@dataclass(frozen=True)
class ContactResult:
    contact: bool
    tcp_pose: np.ndarray  # where motion stopped (6,)
    q_rad: np.ndarray


class Robot(abc.ABC):
    """An arm that moves in joint or Cartesian space and reports its state."""

    name = "robot"

    @abc.abstractmethod
    def move_j(self, q_rad, speed_rad_s: float, accel_rad_s2: float) -> None:
        """Joint move; returns when the arm is there (or raises)."""

    @abc.abstractmethod
    def move_l(self, tcp_pose, speed_m_s: float, accel_m_s2: float) -> None:
        """Linear move of the TCP to pose [x, y, z, rx, ry, rz]; returns when there."""

    @abc.abstractmethod
    def move_until_contact(self, direction_m_s, timeout_s: float) -> ContactResult:
        """Move along a TCP velocity until a contact stops the arm, or `timeout_s` of the
        controller's time (its samples' clock, as the motion's) runs out."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop any motion now (decelerating); safe to call at any time."""

    @abc.abstractmethod
    def actual_q(self) -> np.ndarray:
        ...

    @abc.abstractmethod
    def actual_tcp_pose(self) -> np.ndarray:
        ...

    @abc.abstractmethod
    def samples(self, since_t_s: float | None = None) -> list[RobotSample]:
        """Timestamped samples of the state stream received since a time (or all buffered)."""

    @abc.abstractmethod
    def set_tcp(self, tool_frame) -> None:
        """Set the controller's tool frame (flange -> TCP) [x, y, z, rx, ry, rz]."""

    @abc.abstractmethod
    def tool_frame(self) -> np.ndarray:
        """The controller's current tool frame."""

    @abc.abstractmethod
    def state(self) -> RobotState:
        ...

    def recover(self) -> bool:
        """Clear a protective stop from the PC where the robot allows it (a Franka's reflex:
        libfranka's automatic error recovery); True when the robot is ready after it. The service
        calls it only when the operator presses start. A robot whose stops are cleared at the
        robot itself (a UR's, on its teach pendant) clears nothing and returns False."""
        return False

    def digital_inputs(self) -> int:
        """The robot's digital inputs now, as a bit field: bit n is input n, numbered as UR's
        RTDE ``actual_digital_input_bits`` numbers them (0-7 standard, 8-15 configurable,
        16-17 on the tool flange). A tool changer wired to them carries its tool id there."""
        raise DeviceError(self.name, "this robot reports no digital inputs")

    def tool_frame_slots(self) -> int:
        """How many tool frames this robot keeps for its program's start, one per slot
        (0, 1, ...: a tool changer's tools each have their own); 0 when it keeps none."""
        return 0

    def tool_frame_slots_text(self) -> str:
        """Where those slots are, in the words of the robot's own documentation (for messages)."""
        slots = self.tool_frame_slots()
        return f"it keeps {slots} tool frame{'s' if slots != 1 else ''}" if slots else \
            "it keeps no tool frame for its program's start"

    def stored_tool_frame(self, slot: int = 0) -> StoredToolFrame | None:
        """The tool frame the robot program applies at its start from slot `slot`, or None when
        this robot keeps none (then only :meth:`set_tcp` reaches the controller)."""
        return None

    def store_tool_frame(self, stored: StoredToolFrame, slot: int = 0) -> None:
        """Make ``stored`` the frame the robot program applies at its next start from slot `slot`."""
        raise DeviceError(self.name, "this robot keeps no tool frame for its program's start")

    def close(self) -> None:
        """Release connections; idempotent."""


class Edge(enum.Enum):
    BLOCKED = "blocked"  # beam interrupted / contact made
    CLEARED = "cleared"  # beam free again / contact released


@dataclass(frozen=True)
class TriggerEvent:
    t_s: float  # the source's own timestamp where the device has one, else arrival time
    channel: int  # beam or input number
    edge: Edge
    device_time: bool  # True when t_s is the device's clock, False when it is arrival time


class TriggerInput(abc.ABC):
    """Timestamped edge events from a light barrier or touch trigger."""

    name = "trigger"

    @abc.abstractmethod
    def events(self, timeout_s: float = 0.0) -> list[TriggerEvent]:
        """Events since the last call, waiting up to timeout_s for the first one."""

    def close(self) -> None:
        """Release the port/connection; idempotent."""


@dataclass(frozen=True)
class TrackerMeasurement:
    t_s: float
    position_m: np.ndarray  # (3,) in the instrument frame
    orientation: np.ndarray | None  # (4,) qw, qx, qy, qz for 6-DoF targets
    status: str  # "ok", or the instrument's reason the value is doubtful
    quality: float  # instrument's own figure (e.g. expected std, m); nan if unknown


class Tracker(abc.ABC):
    """A laser tracker (or other 3-D/6-D instrument) that measures one target on request."""

    name = "tracker"

    @abc.abstractmethod
    def measure(self, target: str = "smr1", timeout_s: float = 5.0) -> TrackerMeasurement:
        ...

    def close(self) -> None:
        """Release the connection; idempotent."""


class OperatorPanel(abc.ABC):
    """Start/abort buttons, routine selector, lamps and result code (spec: panel.md)."""

    name = "panel"

    @abc.abstractmethod
    def start_requested(self) -> bool:
        """True once per press; the request is cleared when read."""

    @abc.abstractmethod
    def abort_requested(self) -> bool:
        """True once per press; the request is cleared when read."""

    @abc.abstractmethod
    def routine_selector(self) -> int:
        ...

    @abc.abstractmethod
    def set_lamps(self, *, busy: bool | None = None, done: bool | None = None,
                  fault: bool | None = None) -> None:
        ...

    @abc.abstractmethod
    def set_result(self, code: int, increment_counter: bool = True) -> None:
        ...

    def tool_selector(self) -> int:
        """The tool the operator means (its id in the cell's tool table); 0: whichever tool is
        mounted. A panel without a tool selector returns 0."""
        return 0

    def mounted_tool(self) -> int:
        """The tool on the flange as the PLC or the tool changer reports it (its id in the
        cell's tool table; 0: none), read at each start when the cell file says ``mounted:
        panel``."""
        raise DeviceError(getattr(self, "name", "panel"), "this panel reports no mounted tool")

    def set_outcome(self, registers: dict[str, int]) -> None:
        """What a run found, for a PLC or robot program to act on (docs/panel.md "Outcome
        registers"): register name -> raw 16-bit value, written before the result code and the
        run counter. A panel without such registers ignores it."""

    def confirm_requested(self) -> bool:
        """True once per press of the confirm button (the operator has done what a waiting
        routine asked); the request is cleared when read. A panel without one never confirms."""
        return False

    def set_waiting(self, step: int) -> None:
        """The waiting lamp and what the operator is asked to do: `step` (1, 2, ...: the
        placement the plate is to be moved to) while a routine waits for the confirm button, 0
        when none waits. A panel without a waiting lamp ignores it."""

    def close(self) -> None:
        """Release the connection; idempotent."""


class OperatorTimeout(DeviceTimeout):
    """The operator did not confirm within the time a routine gives (nothing measured since)."""


class Operator(abc.ABC):
    """Someone at the cell a routine can ask to do something and wait for: move a fixture, then
    confirm. The service asks through the panel (the confirm button, the waiting lamp), ``cellcal
    run`` on the terminal (Enter)."""

    name = "operator"

    @abc.abstractmethod
    def confirm(self, message: str, *, step: int, timeout_s: float) -> None:
        """Ask the operator to do what `message` says and return once they confirm. `step` numbers
        what is asked (1, 2, ...: a panel shows it, a simulated cell acts on it). Raises
        :class:`OperatorTimeout` after `timeout_s` without a confirm, and the run's stop (the
        routine's abort) when the run is aborted meanwhile."""
