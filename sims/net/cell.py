"""Every fake of a networked cell file, started and stopped together (``cellcal sim-cell``).

A cell file such as ``sim-net.yaml`` describes a cell reached through the real client
libraries (ur_rtde, pymodbus, a tracker socket). This command stands up what those
clients talk to, on the addresses the cell file gives: the fake UR controller (its own
process, :class:`~cellcal.sims.fake_ur.process.FakeUrProcess`: ur_rtde's constructors
hold the GIL), and in threads here the Modbus IO module (operator panel and trigger
ring) and the tracker server.

The fake controller obeys the cell file's hidden truth (``sim_truth``: the arm as
built, the real tool, the beams and fixtures where they really are, the sensors'
latency and jitter), built in its process from the same file with the same function as
the in-process cell and the run's score, so both cells are scored against one truth.

The light barrier is wired twice, as on a real cell that feeds one sensor to both the
controller and an IO module. The controller samples the sensor on its digital inputs
once per 2 ms cycle (the ``ur_digital_input`` trigger reads them from RTDE). The IO
module has its own clock and stamps each edge when the sensor switches: a wiring thread
here asks the fake controller for every switch at its exact time (the crossing between
cycles plus the sensor's latency and jitter, on the controller's clock) and records it
in the Modbus trigger ring. The IO module's clock is therefore the controller's, so
edges from either source line up with the robot's samples. The tracker measures the
real tool tip (a target at the tip), in the robot base frame.

A cell of two robots gets a second fake controller for robot b, on its own loopback
address (the UR ports are fixed), obeying robot b's part of the same truth. Robot a's real
needle tip is relayed to it every :data:`PARTNER_RELAY_S`, so robot b's contact search
meets robot a's tip as it does in process.

A tool change (:meth:`SimCell.mount_tool`, or :func:`mount_tool_on_running` from another
process: ``cellcal sim-cell --mount-tool ID``) puts another tool of the cell's table on robot
a's flange as it really is, shows its id on the robot's digital inputs where the cell file
wires the tool changer there, and writes it to the panel's mounted-tool register as the
cell's PLC would (written at the start as well).

The operator who moves a kinematic-fixture plate by hand (``move_by: operator``) is simulated at the
IO module: a confirm press while the waiting lamp asks for placement k first moves the plate to
where placement k really lies (:meth:`SimCell.place_plate`, the fake controller's ``place_plate``).

Every fake reports the controller's clock (:class:`~cellcal.sims.physics.clock.SimClock`),
which may run faster than the wall (``time_scale``, ``cellcal sim-cell --time-scale K``): the
controller cycles K times as often, the tracker stamps its readings with the controller's time,
the trigger ring gets the controller's switching times, and the relay runs every
:data:`PARTNER_RELAY_S` of that time. Clients see an arm that moves K times as fast in wall time,
with the same timestamps a real-time run has.

A cell whose robot driver is ``franka`` (``sim-franka.yaml``) gets the simulated Franka arm instead of
the fake UR controller (:mod:`cellcal.sims.franka`: franky-sim's MuJoCo FR3 in the cell's truth, which
pylibfranka drives on port 1337 of the robot's address), with the same control port: the wiring, the
tracker and the operator's hands on the plate reach it as they reach the fake UR controller.

A cell file that does not describe such a cell is refused with a CellFileError naming
the section; a fake that cannot start (a port in use) raises SimCellError.
"""
from __future__ import annotations

import dataclasses
import errno
import socket
import sys
import threading

import numpy as np

from cellcal.config.cells import Cell, CellFileError
from cellcal.config.robot_files import load_robot
from cellcal.drivers.interfaces import DeviceError, Edge
from cellcal.drivers.modbus.panel import ModbusLink, PanelMap
from cellcal.sims.fake_ur.controller import CONTROL_PORT, DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT
from cellcal.sims.fake_ur.process import ControlClient, FakeUrProcess
from cellcal.sims.net.modbus_server import ModbusCellServer
from cellcal.sims.net.tracker_server import TrackerServer
from cellcal.sims.physics.clock import SimClock
from cellcal.sims.physics.truth import CellTruth, truth_of_cell

UR_PORTS = (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT)
FRANKA_PORTS = (1337, 1338)  # libfranka's robot and gripper ports
EDGE_WAIT_S = 0.2  # how long one request for new edges waits (the wiring's shutdown time)
PARTNER_RELAY_S = 0.02  # how often (simulated time) robot a's real tip is passed to robot b's controller


class SimCellError(RuntimeError):
    """A fake of the cell could not start (port in use, fake controller failed)."""


@dataclasses.dataclass(frozen=True)
class NetAddresses:
    """Where each fake of a networked cell listens, read from the cell's driver options."""

    ur_host: str  # the robot controller's address (a UR's, or a Franka's with ``robot_driver: franka``)
    modbus: tuple[str, int] | None
    tracker: tuple[str, int] | None
    trigger_base_register: int = 100
    panel_map: PanelMap = PanelMap()
    unit_id: int = 1
    tracker_targets: tuple = ("smr1",)
    other_ur_hosts: tuple = ()  # (robot name, host) of the cell's robots besides a
    panel: bool = False  # the IO module serves the operator panel (not only the trigger ring)
    robot_driver: str = "ur_rtde"  # which controller is faked: a UR's (ur_rtde) or a Franka's (franka)

    @classmethod
    def of(cls, cell: Cell) -> "NetAddresses":
        drivers = cell.drivers

        def fail(kind: str, what: str):
            raise CellFileError(what, source=cell.path, section=f"drivers.{kind}")

        robot = drivers["robot"]
        if robot.name not in ("ur_rtde", "franka"):
            fail("robot", f"sim-cell serves a UR controller (driver ur_rtde) or a simulated Franka arm (driver "
                          f"franka), not driver {robot.name!r}")
        if not isinstance(robot.options.get("host"), str):
            fail("robot", "host: missing (the address the simulated controller serves on)")
        if robot.name == "franka" and len(cell.robots) > 1:
            fail("robot", "a simulated Franka cell has one robot")
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
                panel_map = PanelMap.of_options(spec.options)
        tracker, targets = None, ("smr1",)
        spec = drivers.get("tracker")
        if spec is not None:
            if spec.name != "socket":
                fail("tracker", f"sim-cell serves a tracker socket, not driver {spec.name!r}")
            tracker = (spec.options.get("host", "127.0.0.1"), spec.options.get("port", 5025))
        others = []
        for name, spec in cell.robots.items():
            if name == "a":
                continue
            where = f"robots.{name}.driver"
            if spec.driver.name != "ur_rtde" or not isinstance(spec.driver.options.get("host"), str):
                raise CellFileError("sim-cell serves a UR controller per robot: driver ur_rtde with a host",
                                    source=cell.path, section=where)
            if spec.driver.options["host"] in (robot.options["host"], *(h for _, h in others)):
                raise CellFileError(f"host {spec.driver.options['host']}: each robot's controller needs its own "
                                    "address (the UR ports are fixed)", source=cell.path, section=where)
            others.append((name, spec.driver.options["host"]))
        return cls(robot.options["host"], modbus, tracker, base, panel_map, unit, targets, tuple(others),
                   drivers.get("panel") is not None, robot.name)

    @property
    def robot_ports(self) -> tuple:
        return FRANKA_PORTS if self.robot_driver == "franka" else UR_PORTS

    def listening_line(self) -> str:
        brand = "franka" if self.robot_driver == "franka" else "ur"
        parts = [f"{brand} {self.ur_host} ({', '.join(map(str, self.robot_ports))})"]
        parts += [f"robot {name}: ur {host}" for name, host in self.other_ur_hosts]
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


def _mount_tool(cell: Cell, tool_id: int, connect) -> dict:
    """Tell robot a's fake controller (a control connection from `connect()`) to mount tool
    `tool_id` of `cell`'s table (0: none)."""
    if tool_id != 0:
        cell.with_tool(tool_id)  # CellFileError naming the table, for an id it does not have
    try:
        client = connect()
    except OSError as exc:
        raise SimCellError(f"no fake UR controller answers on {cell.drivers['robot'].options['host']}:"
                           f"{CONTROL_PORT} ({exc.strerror or exc}): is `cellcal sim-cell` running for this "
                           "cell file?") from None
    try:
        return client.request(cmd="mount_tool", tool=int(tool_id))
    except RuntimeError as exc:  # the controller refused: the arm moving
        raise SimCellError(f"tool {tool_id} not mounted: {exc}") from None
    except (OSError, ValueError) as exc:
        raise SimCellError(f"the fake UR controller's control connection failed: {exc}") from None
    finally:
        client.close()


def mount_tool_on_running(cell: Cell, tool_id: int, timeout_s: float = 5.0) -> dict:
    """A tool change on the `cellcal sim-cell` of `cell` running in another process, as the
    operator at the tool changer does it: robot a's fake controller (its control port) mounts
    tool `tool_id` (0: none), then the panel's mounted-tool register is written over Modbus TCP
    as the cell's PLC writes it. Raises CellFileError for an id the table lacks, SimCellError
    when the sim-cell does not answer or refuses. Returns the controller's reply, with the
    panel register written (``panel_register``, None without a panel)."""
    addresses = NetAddresses.of(cell)
    reply = _mount_tool(cell, tool_id, lambda: ControlClient(addresses.ur_host, CONTROL_PORT, timeout_s))
    reply["panel_register"] = None
    if addresses.panel and addresses.modbus is not None:
        plc = ModbusLink("the panel's IO module", *addresses.modbus, addresses.unit_id, timeout_s)
        try:
            plc.connect()
            plc.write_register(addresses.panel_map.mounted_tool_register, int(tool_id))
        except DeviceError as exc:
            raise SimCellError(f"tool {tool_id} is mounted, and the panel's mounted-tool register was not "
                               f"written: {exc}") from None
        finally:
            plc.close()
        reply["panel_register"] = addresses.panel_map.mounted_tool_register
    return reply


class SimCell:
    """The fakes of one networked cell, started and stopped together (a context manager)."""

    def __init__(self, cell: Cell, time_scale: float = 1.0):
        self.cell = cell
        self.addresses = NetAddresses.of(cell)
        # the controller's clock, as the tracker last read it with the tip
        self.clock = SimClock(time_scale, source=lambda: self._tracker_t_s)
        self._tracker_t_s = 0.0
        self.fake_ur: FakeUrProcess | None = None
        self.modbus: ModbusCellServer | None = None
        self.tracker: TrackerServer | None = None
        self._wiring: threading.Thread | None = None
        self._wiring_client: ControlClient | None = None
        self._tracker_client: ControlClient | None = None
        self._tracker_lock = threading.Lock()
        self._stopping = threading.Event()
        self.other_urs: dict[str, FakeUrProcess] = {}
        self._relay: threading.Thread | None = None
        self._relay_clients: list[ControlClient] = []
        self._tool_id: int | None = None  # after a tool change: the tool mounted since
        self._plate_client: ControlClient | None = None  # the simulated operator's hands on the plate
        self._plate_lock = threading.Lock()
        self._truth: CellTruth | None = None

    def start(self) -> "SimCell":
        a = self.addresses
        for host in (a.ur_host, *(h for _, h in a.other_ur_hosts)):
            for port in (*a.robot_ports, CONTROL_PORT):
                check_free(host, port)
        for address in (a.modbus, a.tracker):
            if address is not None:
                check_free(*address)
        try:
            if a.robot_driver == "franka":  # franky-sim's MuJoCo arm, in the cell's truth (sims.franka)
                from cellcal.sims.franka.process import FrankaSimProcess

                self.fake_ur = FrankaSimProcess(a.ur_host, cell_file=self.cell.path, time_scale=self.clock.time_scale)
            else:
                self.fake_ur = FakeUrProcess(a.ur_host, robot=self.cell.robot, q0=self.cell.home_q_rad,
                                             cell_file=self.cell.path,  # the tool the cell has mounted (with_tool)
                                             tool=self.cell.tool.id if self.cell.tool is not None else None,
                                             time_scale=self.clock.time_scale)
            try:
                self.fake_ur.start()
            except RuntimeError as exc:
                raise SimCellError(str(exc)) from None
            self._start_other_robots()
            if a.modbus is not None:
                self.modbus = ModbusCellServer(*a.modbus, unit_id=a.unit_id, panel_map=a.panel_map,
                                               trigger_base_register=a.trigger_base_register).start()
                if a.panel:  # the PLC reports the tool on the flange (the cell's `mounted: panel` reads it)
                    self.modbus.set_mounted_tool(self.tool_id)
                    self.modbus.on_confirm = self.place_plate  # the operator moves the plate, then confirms
                self._stopping.clear()
                self._wiring_client = self.fake_ur.client()
                self._wiring = threading.Thread(target=self._wire_edges, args=(self._wiring_client, self.modbus),
                                                name="sim-cell beam wiring", daemon=True)
                self._wiring.start()
            if a.tracker is not None:
                self._tracker_client = self.fake_ur.client()
                self.tracker = TrackerServer(self._tracker_position, host=a.tracker[0], port=a.tracker[1],
                                             clock=self.clock).start()
        except BaseException:
            self.stop()
            raise
        return self

    @property
    def tool_id(self) -> int:
        """The id of the tool on robot a's flange (0: none, or a cell without a tool)."""
        return self._tool_id if self._tool_id is not None else (self.cell.tool.id if self.cell.tool is not None else 0)

    @property
    def truth(self) -> CellTruth:
        """The hidden truth the fake controller obeys, with the tool now mounted: built here from
        the same cell file with the same function as in the controller's process, for a test to
        score against (never for a routine)."""
        if self._truth is None:
            self._truth = truth_of_cell(self.cell, load_robot(self.cell.robot))
        return self._truth if self._truth.tool_id == self.tool_id else self._truth.with_tool(self.tool_id)

    def mount_tool(self, tool_id: int) -> dict:
        """A tool change on robot a, as at the cell's tool changer: tool `tool_id` of the cell's
        table as it really is goes on the flange (0: none) and the tool changer's id shows on the
        robot's digital inputs where the cell file wires it (the fake UR controller's
        ``mount_tool``); then, as the cell's PLC would, the panel's mounted-tool register says
        so. Raises CellFileError for an id the table does not have, SimCellError when the
        controller refuses (the arm moving). Returns the controller's reply."""
        if self.fake_ur is None:
            raise SimCellError("the simulated cell is not running")
        reply = _mount_tool(self.cell, tool_id, self.fake_ur.client)
        if self.modbus is not None and self.addresses.panel:
            self.modbus.set_mounted_tool(tool_id)
        self._tool_id = tool_id
        return reply

    def place_plate(self, step: int) -> dict:
        """The operator moves the kinematic-fixture plate to placement `step` (1, 2, ...) as it really
        lies there (a plate moved by hand, ``move_by: operator``): the fake controller's
        ``place_plate``. Done by the IO module when the confirm button is pressed while the waiting
        lamp asks for a placement. Returns the controller's reply."""
        if self.fake_ur is None:
            raise SimCellError("the simulated cell is not running")
        with self._plate_lock:
            if self._plate_client is None:
                self._plate_client = self.fake_ur.client()
            return self._plate_client.request(cmd="place_plate", step=int(step))

    def _start_other_robots(self) -> None:
        """A fake controller for each robot besides a, and the relay of robot a's tip to them."""
        for name, host in self.addresses.other_ur_hosts:
            spec = self.cell.robots[name]
            fake = FakeUrProcess(host, robot=spec.robot, q0=spec.home_q_rad, cell_file=self.cell.path, arm=name,
                                 time_scale=self.clock.time_scale)
            self.other_urs[name] = fake
            try:
                fake.start()
            except RuntimeError as exc:
                raise SimCellError(str(exc)) from None
        if self.other_urs:
            self._relay_clients = [self.fake_ur.client(), *(f.client() for f in self.other_urs.values())]
            self._relay = threading.Thread(target=self._relay_tip, name="sim-cell needle relay", daemon=True)
            self._relay.start()

    def _relay_tip(self) -> None:
        """Pass robot a's real needle tip and axis (its base frame) to the other controllers."""
        source, *targets = self._relay_clients
        try:
            while not self.clock.wait(self._stopping, PARTNER_RELAY_S):
                tool = source.request(cmd="tool")
                front, back = (np.asarray(p, dtype=float) for p in tool["tool_body_m"])
                axis = (front - back) / np.linalg.norm(front - back)
                for target in targets:
                    target.request(cmd="partner", tip_m=tool["tool_tip_m"], axis=axis.tolist())
        except (OSError, RuntimeError, ValueError):
            if not self._stopping.is_set():
                print("cellcal sim-cell: the needle relay lost a fake UR controller", file=sys.stderr)

    def _wire_edges(self, client: ControlClient, modbus: ModbusCellServer) -> None:
        """Record every switch of the sensors in the IO module's trigger ring at its exact time."""
        first = 0
        try:
            while not self._stopping.is_set():
                reply = client.request(cmd="edges", first=first, wait_s=EDGE_WAIT_S)
                for n, t_s, channel, edge in reply["edges"]:
                    if n != first:
                        print(f"cellcal sim-cell: trigger wiring lost edges {first}..{n - 1}", file=sys.stderr)
                    modbus.record_edge(int(channel), Edge(edge), int(round(t_s * 1e6)))
                    first = n + 1
                first = max(first, reply["next"])
        except (OSError, RuntimeError, ValueError):
            if not self._stopping.is_set():  # the fake controller ended; sim-cell notices and exits
                print("cellcal sim-cell: trigger wiring lost the fake UR controller", file=sys.stderr)

    def _tracker_position(self, target: str) -> np.ndarray | None:
        """The real tool tip, where a target sits (None for a target the cell does not have)."""
        if target not in self.addresses.tracker_targets or self._tracker_client is None:
            return None
        with self._tracker_lock:
            reply = self._tracker_client.request(cmd="tool")
            self._tracker_t_s = float(reply["t_s"])
            return np.asarray(reply["tool_tip_m"], dtype=float)

    def stop(self) -> None:
        """Stop everything that was started, in reverse order; idempotent."""
        self._stopping.set()
        if self.tracker is not None:
            self.tracker.stop()
            self.tracker = None
        if self._tracker_client is not None:
            self._tracker_client.close()
            self._tracker_client = None
        if self._wiring is not None:
            self._wiring_client.interrupt()  # ends a request the wiring waits on
            self._wiring.join(EDGE_WAIT_S + 5.0)
            self._wiring = None
        if self._wiring_client is not None:
            self._wiring_client.close()
            self._wiring_client = None
        if self._relay is not None:
            for client in self._relay_clients:
                client.interrupt()
            self._relay.join(PARTNER_RELAY_S + 5.0)
            self._relay = None
        for client in self._relay_clients:
            client.close()
        self._relay_clients = []
        for fake in self.other_urs.values():
            fake.stop()
        self.other_urs = {}
        if self.modbus is not None:
            self.modbus.stop()
            self.modbus = None
        with self._plate_lock:
            if self._plate_client is not None:
                self._plate_client.close()
                self._plate_client = None
        if self.fake_ur is not None:
            self.fake_ur.stop()
            self.fake_ur = None

    def __enter__(self) -> "SimCell":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
