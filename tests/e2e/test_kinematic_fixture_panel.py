"""kinematic-fixture through ``cellcal daemon`` on the networked simulated cell, the plate moved by the
operator between placements (``move_by: operator``), everything a PLC does through a plain Modbus client
(docs/panel.md): start, the waiting lamp and the placement register, the confirm button (the simulated
operator moves the plate in the fake controller before the press lands), abort during the wait, and a
confirm pressed when nothing waits. The fake controller seats the real tool in the sockets where the
plate really lies, so a confirm without the plate there finds no socket (the in-process cases show it)."""
from __future__ import annotations

import time

import pytest
from pymodbus.client import ModbusTcpClient

from support import daemon_harness
from support.cell_edits import edited_cell
from cellcal.daemon.service import ResultCode
from cellcal.drivers.modbus.panel import PanelMap
from cellcal.routines.framework.records import read_dataset
from cellcal.routines.framework.registry import routine_class
from support.daemon_harness import Daemon, Net, plc_reads, until_the_run_ends

pytestmark = pytest.mark.slow  # a real-time run of 16 seats on the fake controller
MAP = PanelMap()
LOOK_S = 0.02


def plate_by_hand(folder, host):
    """sim-net with one plate moved by the operator between two placements, 4 seats per socket (16 in
    all: enough for the solver, every gate passed), on one wrist branch and with the arm's limits raised so the
    real-time run is short (about 20 s of motion)."""
    def edit(doc):
        doc["drivers"]["panel"]["timeout_s"] = 0.3
        doc["limits"].update(tcp_speed_m_s=1.0, tcp_accel_m_s2=10.0, joint_speed_rad_s=3.0, joint_accel_rad_s2=10.0)
        section = doc["kinematic_fixture"]
        section.update(placements=section["placements"][:2], orientations=4, search_speed_mm_s=20, wrist_flip=False,
                       move_by="operator", confirm_timeout_s=60)
    return edited_cell(folder, "sim-net", edit, name="sim-net-plate-by-hand.yaml", host=host)


@pytest.fixture(scope="module")
def net_cell():
    return plate_by_hand


@pytest.fixture(scope="module")
def cell(net, tmp_path_factory):
    daemon = Daemon(net, tmp_path_factory.mktemp("sim-net-plate"))
    try:
        yield net, daemon
    finally:
        daemon.stop()


class Plc:
    """A plain Modbus TCP client on the cell's IO module, as the cell's PLC or HMI is."""

    def __init__(self, net: Net):
        self.client = ModbusTcpClient(net.host, port=net.sim.addresses.modbus[1])
        self.client.connect()
        self.unit = net.sim.addresses.unit_id

    def press(self, coil: int) -> None:
        self.client.write_coil(coil, True, device_id=self.unit)

    def coil(self, coil: int) -> bool:
        return bool(self.client.read_coils(coil, count=1, device_id=self.unit).bits[0])

    def waiting(self) -> int:
        """The placement the waiting lamp asks for (0: the lamp is dark)."""
        lamp = self.coil(MAP.waiting_lamp_coil)
        return self.client.read_holding_registers(MAP.placement_register, count=1,
                                                  device_id=self.unit).registers[0] if lamp else 0

    def until(self, condition, what: str, timeout_s: float = daemon_harness.RUN_TIMEOUT_S) -> None:
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, what
            time.sleep(LOOK_S)

    def close(self) -> None:
        self.client.close()


@pytest.fixture
def plc(cell):
    plc = Plc(cell[0])
    yield plc
    plc.close()


def start(net: Net, plc: Plc) -> int:
    counter = net.panel.run_counter()
    net.panel.select_routine(daemon_harness.SELECT["kinematic-fixture"])
    plc.press(MAP.start_request_coil)
    return counter


def test_a_confirm_with_nothing_waiting_is_cleared_and_starts_nothing(cell, plc):
    net, _ = cell
    counter = net.panel.run_counter()
    plc.press(MAP.confirm_request_coil)
    plc.until(lambda: not plc.coil(MAP.confirm_request_coil), "the daemon never cleared the confirm press", 10.0)
    assert net.panel.run_counter() == counter and not net.state()["moving"] and plc.waiting() == 0


def test_abort_during_the_wait_ends_the_run_aborted(cell, plc):
    net, _ = cell
    q = net.state()["q"]
    counter = start(net, plc)
    plc.until(lambda: plc.waiting() == 1, "the routine never asked for placement 1")
    plc.press(MAP.abort_request_coil)
    until_the_run_ends(net, counter)
    reads = plc_reads(net)
    assert reads["code"] == ResultCode.ABORTED and not reads["lamps"]["busy"] and plc.waiting() == 0
    assert net.state()["q"] == q  # the arm waited at home: nothing moved


def test_the_operator_moves_the_plate_and_the_run_ends_ok(cell, plc):
    net, daemon = cell
    counter = start(net, plc)
    for step in (1, 2):
        plc.until(lambda: plc.waiting() == step, f"the routine never asked for placement {step}")
        assert not net.state()["moving"]  # parked (at home) while the plate is moved
        plc.press(MAP.confirm_request_coil)  # the simulated operator moves the plate there, then confirms
        plc.until(lambda: plc.waiting() != step, f"placement {step} was not taken")
    until_the_run_ends(net, counter)
    reads = plc_reads(net)
    runs = daemon.cli("runs", "list")
    open("/tmp/daemon_full.log", "w").write(daemon.log() + "\n".join(net.state()["messages"])); assert reads["code"] == ResultCode.OK, (runs, daemon.log()[-3000:])
    dataset = next((daemon.state_dir / "datasets").glob("kinematic-fixture-*.csv"))
    data = read_dataset(dataset, "kinematic-fixture", routine_class("kinematic-fixture").text_columns)
    assert sorted(set(data["setup"])) == ["p1", "p2"] and sorted(set(data["point"])) == ["s0", "s1"]
    assert len(data) == 16
