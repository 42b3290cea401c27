"""A request to a unit id the simulated IO module is not: a real pymodbus client against the fake.

The fake is one unit (``unit_id``, 1 by default). pymodbus' simulator on its own looks any
other unit id up as unit 0, logs the KeyError with its traceback and answers exception 4
(server device failure); the fake answers exception 0x0B (gateway target device failed to
respond) at once, as a Modbus TCP gateway with nothing behind that id, logs nothing, leaves
its tables alone and keeps serving its own unit.
"""
from __future__ import annotations

import logging

import pytest
from pymodbus.client import ModbusTcpClient

from cellcal.drivers.modbus.panel import ModbusExceptionResponse, ModbusPanel
from cellcal.sims.net.modbus_server import ModbusCellServer

GATEWAY_TARGET_FAILED = 0x0B
OTHER_UNIT = 7


@pytest.fixture
def server():
    with ModbusCellServer() as cell_server:
        yield cell_server


@pytest.fixture
def client(server):
    c = ModbusTcpClient("127.0.0.1", port=server.port, timeout=1.0, retries=0)
    assert c.connect()
    yield c
    c.close()


REQUESTS = {  # every function the panel and the trigger ring use, addressed to another unit
    "read coils": lambda c: c.read_coils(0, count=1, device_id=OTHER_UNIT),
    "write coil": lambda c: c.write_coil(8, True, device_id=OTHER_UNIT),
    "read holding registers": lambda c: c.read_holding_registers(0, count=1, device_id=OTHER_UNIT),
    "write register": lambda c: c.write_register(1, 99, device_id=OTHER_UNIT),
    "read input registers": lambda c: c.read_input_registers(100, count=4, device_id=OTHER_UNIT),
    "broadcast read (unit 0)": lambda c: c.read_coils(0, count=1, device_id=0),
}


@pytest.mark.parametrize("what", sorted(REQUESTS))
def test_another_unit_gets_exception_0x0b_without_a_traceback_and_changes_nothing(server, client, caplog, what):
    caplog.set_level(logging.DEBUG, logger="pymodbus")
    lamps, code = server.lamps(), server.result_code()
    response = REQUESTS[what](client)
    assert response.isError() and response.exception_code == GATEWAY_TARGET_FAILED, response
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], [r.getMessage() for r in caplog.records]
    assert "Traceback" not in caplog.text and "KeyError" not in caplog.text
    assert (server.lamps(), server.result_code()) == (lamps, code)  # the write went nowhere
    # and the module's own unit is served on the same connection as before
    assert client.read_holding_registers(1, count=1, device_id=server.unit_id).registers == [code]


def test_a_panel_configured_with_the_wrong_unit_id_is_told_which_exception(server):
    """What the daemon sees when the cell file's unit_id is not the module's: the exception named."""
    panel = ModbusPanel(port=server.port, unit_id=OTHER_UNIT, timeout_s=1.0)
    try:
        with pytest.raises(ModbusExceptionResponse) as refused:
            panel.start_requested()
    finally:
        panel.close()
    assert refused.value.exception_code == GATEWAY_TARGET_FAILED
    assert "gateway target device failed to respond" in str(refused.value)


def test_a_module_on_another_unit_id_answers_that_id_only():
    with ModbusCellServer(unit_id=5) as server:
        c = ModbusTcpClient("127.0.0.1", port=server.port, timeout=1.0, retries=0)
        assert c.connect()
        try:
            server.select_routine(3)
            assert c.read_holding_registers(0, count=1, device_id=5).registers == [3]
            assert c.read_holding_registers(0, count=1, device_id=1).exception_code == GATEWAY_TARGET_FAILED
        finally:
            c.close()
