"""Every fake of a networked cell file, started and stopped together (``cellcal sim-cell``).

A cell file such as ``sim-net.yaml`` describes a cell reached through the real client
libraries (ur_rtde, pymodbus, a tracker socket). This command stands up what those
clients talk to, on the addresses the cell file gives: the fake UR controller (its own
process, :class:`~cellcal.sims.fake_ur_process.FakeUrProcess`: ur_rtde's constructors
hold the GIL), and in threads here the Modbus IO module (operator panel and trigger
ring) and the tracker server.

The light barrier is wired twice, as on a real cell that feeds one sensor to both the
controller and an IO module: the fake controller sees the beam on its digital input,
and a wiring thread here reads the controller's RTDE stream (every cycle, lossless)
and records each edge of that input in the Modbus trigger ring, stamped with the
controller's clock. The IO module's clock is therefore the controller's, so edges from
either source line up with the robot's samples. The tracker measures the TCP position
of the latest controller cycle, in the robot base frame.

A cell file that does not describe such a cell is refused with a CellFileError naming
the section; a fake that cannot start (a port in use) raises SimCellError.
"""
from __future__ import annotations

import dataclasses
import errno
import socket

import numpy as np

from ..config.cells import Cell, CellFileError
from ..drivers.interfaces import Edge, RobotSample
from ..drivers.modbus_panel import PanelMap
from ..drivers.ur_rtde_state import UrStateStream
from .fake_ur import CONTROL_PORT, DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT
from .fake_ur_process import FakeUrProcess
from .modbus_server import ModbusCellServer
from .tracker_server import TrackerServer

UR_PORTS = (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT)
WIRING_VARIABLES = ("timestamp", "actual_TCP_pose", "actual_digital_input_bits")


class SimCellError(RuntimeError):
    """A fake of the cell could not start (port in use, fake controller failed)."""


@dataclasses.dataclass(frozen=True)
class NetAddresses:
    """Where each fake of a networked cell listens, read from the cell's driver options."""

    ur_host: str
    modbus: tuple[str, int] | None
    tracker: tuple[str, int] | None
    trigger_base_register: int = 100
    panel_map: PanelMap = PanelMap()
    unit_id: int = 1
    tracker_targets: tuple = ("smr1",)

    @classmethod
    def of(cls, cell: Cell) -> "NetAddresses":
        drivers = cell.drivers

        def fail(kind: str, what: str):
            raise CellFileError(what, source=cell.path, section=f"drivers.{kind}")

        robot = drivers["robot"]
        if robot.name != "ur_rtde":
            fail("robot", f"sim-cell serves a UR controller: driver must be ur_rtde, not {robot.name!r}")
        if not isinstance(robot.options.get("host"), str):
            fail("robot", "host: missing (the address the fake UR controller serves on)")
        modbus, base, unit, panel_map = None, 100, 1, PanelMap()
        for kind in ("panel", "trigger"):
            spec = drivers.get(kind)
            if spec is None or (kind == "trigger" and spec.name == "ur_digital_input"):
                continue  # no device, or one the fake controller serves itself
            if spec.name != "modbus":
                fail(kind, f"sim-cell serves a Modbus {kind}, not driver {spec.name!r}")
            address = (spec.options.get("host", "127.0.0.1"), spec.options.get("port", 502))
            if modbus is not None and address != modbus:
                fail(kind, f"the panel and the trigger ring are one IO module: same host and port as "
                           f"the panel ({modbus[0]}:{modbus[1]}), not {address[0]}:{address[1]}")
            modbus = address
            unit = spec.options.get("unit_id", unit)
            if kind == "trigger":
                base = spec.options.get("base_register", 100)
            else:
                fields = {f.name for f in dataclasses.fields(PanelMap)}
                panel_map = PanelMap(**{k: v for k, v in spec.options.items() if k in fields})
        tracker, targets = None, ("smr1",)
        spec = drivers.get("tracker")
        if spec is not None:
            if spec.name != "socket":
                fail("tracker", f"sim-cell serves a tracker socket, not driver {spec.name!r}")
            tracker = (spec.options.get("host", "127.0.0.1"), spec.options.get("port", 5025))
        return cls(robot.options["host"], modbus, tracker, base, panel_map, unit, targets)

    def listening_line(self) -> str:
        parts = [f"ur {self.ur_host} ({', '.join(map(str, UR_PORTS))})"]
        if self.modbus:
            parts.append(f"modbus {self.modbus[0]}:{self.modbus[1]}")
        if self.tracker:
            parts.append(f"tracker {self.tracker[0]}:{self.tracker[1]}")
        return "cellcal sim-cell: listening: " + ", ".join(parts)


def check_free(host: str, port: int) -> None:
    """Raise SimCellError when something already listens on (host, port)."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a port in TIME_WAIT is free
    try:
        probe.bind((host, port))
    except OSError as exc:
        what = "in use" if exc.errno == errno.EADDRINUSE else exc.strerror
        raise SimCellError(f"cannot listen on {host}:{port}: {what}") from None
    finally:
        probe.close()


class SimCell:
    """The fakes of one networked cell, started and stopped together (a context manager)."""

    def __init__(self, cell: Cell):
        self.cell = cell
        self.addresses = NetAddresses.of(cell)
        self.fake_ur: FakeUrProcess | None = None
        self.modbus: ModbusCellServer | None = None
        self.tracker: TrackerServer | None = None
        self._stream: UrStateStream | None = None
        self._latest: RobotSample | None = None
        self._beam_levels: dict[int, bool] = {}

    def start(self) -> "SimCell":
        a = self.addresses
        for port in (*UR_PORTS, CONTROL_PORT):
            check_free(a.ur_host, port)
        for address in (a.modbus, a.tracker):
            if address is not None:
                check_free(*address)
        try:
            self.fake_ur = FakeUrProcess(a.ur_host, robot=self.cell.robot, q0=self.cell.home_q_rad,
                                         cell={"models": [b.as_model() for b in self.cell.beams]})
            try:
                self.fake_ur.start()
            except RuntimeError as exc:
                raise SimCellError(str(exc)) from None
            if a.modbus is not None:
                self.modbus = ModbusCellServer(*a.modbus, unit_id=a.unit_id, panel_map=a.panel_map,
                                               trigger_base_register=a.trigger_base_register).start()
            self._stream = UrStateStream(a.ur_host, device="sim-cell beam wiring", variables=WIRING_VARIABLES)
            self._latest = self._stream.latest()
            self._stream.add_listener(self._on_sample)
            if a.tracker is not None:
                self.tracker = TrackerServer(self._tracker_position, host=a.tracker[0], port=a.tracker[1]).start()
        except BaseException:
            self.stop()
            raise
        return self

    def _on_sample(self, sample: RobotSample) -> None:
        """Copy each edge of a beam's controller input into the IO module's trigger ring."""
        self._latest = sample
        for beam in self.cell.beams:
            level = bool(sample.digital_inputs >> beam.channel & 1)
            previous, self._beam_levels[beam.channel] = self._beam_levels.get(beam.channel), level
            if previous is None or level == previous or self.modbus is None:
                continue
            blocked = level == beam.level_when_blocked
            self.modbus.record_edge(beam.channel, Edge.BLOCKED if blocked else Edge.CLEARED,
                                    int(round(sample.t_s * 1e6)))

    def _tracker_position(self, target: str) -> np.ndarray | None:
        if target not in self.addresses.tracker_targets or self._latest is None:
            return None
        return np.asarray(self._latest.tcp_pose[:3], dtype=float)

    def stop(self) -> None:
        """Stop everything that was started, in reverse order; idempotent."""
        if self.tracker is not None:
            self.tracker.stop()
            self.tracker = None
        if self._stream is not None:
            self._stream.close()
            self._stream = None
        if self.modbus is not None:
            self.modbus.stop()
            self.modbus = None
        if self.fake_ur is not None:
            self.fake_ur.stop()
            self.fake_ur = None

    def __enter__(self) -> "SimCell":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
