"""The operator panel over Modbus TCP: pymodbus client against the pymodbus cell server."""
import socket
import threading
import time

import pytest

from cellcal.drivers.interfaces import DeviceError, DeviceTimeout, ProtocolError
from cellcal.drivers.modbus.panel import ModbusExceptionResponse, ModbusPanel, PanelMap
from cellcal.drivers.registry import DriverConfigError
from cellcal.sims.net.modbus_server import ModbusCellServer

MARGIN_S = 2.0  # scheduling slack on top of a deadline: a 2-core machine with both cores busy wakes a waiter late


@pytest.fixture
def cell_server():
    with ModbusCellServer() as server:
        yield server


@pytest.fixture
def panel(cell_server):
    panel = ModbusPanel(port=cell_server.port, timeout_s=1.0)
    yield panel
    panel.close()


class SilentDevice:
    """Accepts Modbus connections and never answers: a hung PLC."""

    def __init__(self):
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.connections = []
        self.thread = threading.Thread(target=self._accept, daemon=True)
        self.thread.start()

    def _accept(self):
        try:
            while True:
                self.connections.append(self.listener.accept()[0])
        except OSError:
            return

    def close(self):
        self.listener.close()
        for c in self.connections:
            c.close()


# --- the panel map --------------------------------------------------------------------

def test_start_press_is_reported_once_then_cleared(cell_server, panel):
    assert panel.start_requested() is False
    cell_server.press_start()
    assert cell_server.start_request_pending() is True
    assert panel.start_requested() is True
    assert cell_server.start_request_pending() is False  # the daemon cleared coil 0
    assert panel.start_requested() is False


def test_abort_press_is_reported_once_then_cleared(cell_server, panel):
    cell_server.press_abort()
    assert panel.start_requested() is False  # an abort is not a start
    assert panel.abort_requested() is True
    assert cell_server.abort_request_pending() is False
    assert panel.abort_requested() is False


def test_routine_selector_reads_the_operators_choice(cell_server, panel):
    cell_server.select_routine(4)
    assert panel.routine_selector() == 4
    cell_server.select_routine(5)
    assert panel.routine_selector() == 5


def test_lamps_set_by_the_daemon_are_visible_on_the_panel(cell_server, panel):
    assert cell_server.lamps() == {"busy": False, "done": False, "fault": False}
    panel.set_lamps(busy=True)
    assert cell_server.lamps() == {"busy": True, "done": False, "fault": False}
    panel.set_lamps(busy=False, done=True)
    assert cell_server.lamps() == {"busy": False, "done": True, "fault": False}
    panel.set_lamps(fault=True)  # lamps not named keep their state
    assert cell_server.lamps() == {"busy": False, "done": True, "fault": True}


def test_result_code_is_written_and_run_counter_incremented(cell_server, panel):
    panel.set_result(0)
    assert (cell_server.result_code(), cell_server.run_counter()) == (0, 1)
    panel.set_result(4)
    assert (cell_server.result_code(), cell_server.run_counter()) == (4, 2)
    panel.set_result(7, increment_counter=False)
    assert (cell_server.result_code(), cell_server.run_counter()) == (7, 2)


def test_overridden_addresses_are_the_ones_used():
    overrides = dict(start_request_coil=17, abort_request_coil=18, busy_lamp_coil=32,
                     done_lamp_coil=33, fault_lamp_coil=34, routine_selector_register=10,
                     result_code_register=11, run_counter_register=12)
    with ModbusCellServer(panel_map=PanelMap(**overrides)) as server:
        panel = ModbusPanel(port=server.port, **overrides)
        server.press_start()
        server.select_routine(3)
        assert panel.start_requested() is True
        assert server.start_request_pending() is False
        assert panel.routine_selector() == 3
        panel.set_lamps(busy=True, fault=True)
        panel.set_result(9)
        assert server.lamps() == {"busy": True, "done": False, "fault": True}
        assert (server.result_code(), server.run_counter()) == (9, 1)
        panel.close()


def test_options_out_of_range_are_refused_naming_the_option():
    for options, key, value in (({"port": 70000}, "port", "70000"), ({"busy_lamp_coil": -1}, "busy_lamp_coil", "-1"),
                                ({"timeout_s": 0}, "timeout_s", "0")):
        with pytest.raises(DriverConfigError) as refused:
            ModbusPanel(**{"port": 502, **options})
        assert refused.value.key == key and refused.value.problem.startswith(f"{value} "), refused.value
    with pytest.raises(DriverConfigError, match="share an address"):
        ModbusPanel(port=502, done_lamp_coil=8)


# --- failures ---------------------------------------------------------------------------

def test_connection_refused_names_the_panel_and_address(loopback_host):
    host, port = loopback_host, 5020  # an address of the test's own: nothing listens there
    timeout_s = 1.0
    started = time.monotonic()
    with pytest.raises(DeviceError) as err:
        ModbusPanel(host, port=port, timeout_s=timeout_s)
    assert time.monotonic() - started < timeout_s + MARGIN_S  # refused at once; the link's timeout_s bounds it
    assert type(err.value) is DeviceError
    assert err.value.device == f"panel (Modbus TCP {host}:{port}, unit 1)"
    assert f"cannot connect to {host}:{port}" in str(err.value)


def test_connection_lost_mid_operation_is_named_and_recovered(cell_server):
    panel = ModbusPanel(port=cell_server.port)
    panel.set_lamps(busy=True)
    port = cell_server.port
    cell_server.stop()  # the PLC goes away with the connection open
    with pytest.raises(DeviceError) as err:
        panel.start_requested()
    assert type(err.value) is DeviceError
    assert f"connection to 127.0.0.1:{port} lost while reading coil 0" in str(err.value)
    with ModbusCellServer(port=port) as back:  # same address again: the next call reconnects
        back.press_start()
        assert panel.start_requested() is True
    panel.close()


def test_silent_device_times_out_within_the_deadline():
    device = SilentDevice()
    try:
        timeout_s = 2.0  # a retry, at 2 x timeout_s, then lies a whole MARGIN_S past the first attempt
        panel = ModbusPanel(port=device.port, timeout_s=timeout_s)
        started = time.monotonic()
        with pytest.raises(DeviceTimeout) as err:
            panel.start_requested()
        elapsed = time.monotonic() - started
        # not before 0.9 x timeout_s (the link's own test for a timeout); a retry would take a second timeout_s
        assert 0.9 * timeout_s <= elapsed < 2 * timeout_s, elapsed
        assert f"no reply within {timeout_s:g} s while reading coil 0" in str(err.value)
        panel.close()
    finally:
        device.close()


def test_exception_response_for_an_address_the_device_lacks(cell_server):
    # the server's holding registers are 0..2; a cell file pointing elsewhere is caught
    panel = ModbusPanel(port=cell_server.port, result_code_register=999)
    with pytest.raises(ModbusExceptionResponse) as err:
        panel.set_result(1)
    assert err.value.exception_code == 2
    assert not isinstance(err.value, (DeviceTimeout, ProtocolError))
    assert ("exception response 2 (illegal data address) to writing holding register 999"
            in str(err.value))
    assert err.value.device.startswith("panel (Modbus TCP 127.0.0.1:")
    panel.close()


def test_result_code_outside_a_register_is_refused_before_sending(cell_server, panel):
    with pytest.raises(ValueError, match="result code 70000 outside 0..65535"):
        panel.set_result(70000)
    assert cell_server.run_counter() == 0


# --- waiting for the operator: the confirm button, the waiting lamp, the placement register ---------

def test_a_confirm_press_is_reported_once_and_the_waiting_lamp_carries_the_placement(cell_server, panel):
    assert panel.confirm_requested() is False and cell_server.waiting() == 0
    panel.set_waiting(2)
    assert cell_server.waiting() == 2  # lamp (coil 11) lit, register 29 at 2
    cell_server.press_confirm()
    assert cell_server.confirm_request_pending() is True
    assert panel.confirm_requested() is True
    assert cell_server.confirm_request_pending() is False  # the daemon cleared coil 2
    panel.set_waiting(0)
    assert cell_server.waiting() == 0


def test_the_simulated_operator_moves_the_plate_only_for_a_press_the_lamp_asks_for(cell_server, panel):
    """A press from any Modbus client (the PLC's) reaches the simulated operator before the coil is set,
    with the placement the daemon last wrote; with the lamp dark it moves nothing."""
    from pymodbus.client import ModbusTcpClient
    moved = []
    cell_server.on_confirm = moved.append
    with ModbusTcpClient("127.0.0.1", port=cell_server.port) as plc:
        plc.write_coil(PanelMap().confirm_request_coil, True, device_id=1)
        assert moved == [] and panel.confirm_requested() is True  # pressed, nothing to move
        panel.set_waiting(3)
        plc.write_coil(PanelMap().confirm_request_coil, True, device_id=1)
        assert moved == [3] and panel.confirm_requested() is True
