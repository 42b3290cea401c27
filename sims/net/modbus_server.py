"""The simulated cell's Modbus IO module: operator panel and trigger ring on one server.

A pymodbus TCP server on loopback, run by its own asyncio loop in a background
thread, so the real pymodbus client in :mod:`cellcal.drivers.modbus.panel` and
:mod:`cellcal.drivers.modbus.trigger` talks Modbus to it exactly as to a PLC.
Tests and the simulated cell play the operator and the light barrier through
the methods below: press buttons, read lamps, record edges.

The tables are separate (coils, discrete inputs, holding and input registers,
as on most IO modules); an address outside them gets exception response 2. The module
is one unit (``unit_id``): a request to another unit id gets exception response 0x0B
(gateway target device failed to respond), as from a Modbus TCP gateway with nothing
behind that id, and nothing is logged (pymodbus' simulator alone would log a KeyError
traceback and answer 0x04, server device failure).

Faults are injected per Modbus function, which on this module also tells the panel
from the trigger ring (the ring is its only input registers, function 4):
``exceptions[function] = code`` answers every such request with that exception
response, ``silent`` holds functions whose requests get no reply at all (a module that
stopped answering), and :meth:`drop_connections` cuts every client connection.
"""
from __future__ import annotations

import asyncio
import sys
import threading
from typing import Callable

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from cellcal.drivers.interfaces import Edge
from cellcal.drivers.modbus.panel import PanelMap
from cellcal.drivers.modbus.trigger import (HEADER_REGISTERS, LAYOUT_VERSION, MAX_RING_SIZE,
                                      RECORD_REGISTERS, SEQ_MODULUS, encode_record)
from cellcal.drivers.triggers.stream import EDGE_CODES

READ_COILS, WRITE_COIL, READ_HOLDING, WRITE_REGISTER, READ_INPUT = 1, 5, 3, 6, 4
SERVER_CALL_TIMEOUT_S = 5.0


class _OneUnit:
    """The server's datastore answering for one unit id only. pymodbus' simulator looks any
    other id up as unit 0 (a KeyError when there is none, which the server logs with its
    traceback); here such a request gets the exception code a datastore may return instead of
    values, 0x0B, which the request turns into its exception response."""

    def __init__(self, datastore, unit_id: int):
        self._datastore, self._unit_id = datastore, unit_id

    async def async_getValues(self, device_id: int, *args, **kwargs):  # noqa: N802 - pymodbus' name
        if device_id != self._unit_id:
            return ExcCodes.GATEWAY_NO_RESPONSE
        return await self._datastore.async_getValues(device_id, *args, **kwargs)

    async def async_setValues(self, device_id: int, *args, **kwargs):  # noqa: N802 - pymodbus' name
        if device_id != self._unit_id:
            return ExcCodes.GATEWAY_NO_RESPONSE
        return await self._datastore.async_setValues(device_id, *args, **kwargs)

    def __getattr__(self, name):  # device_ids() and whatever else the server asks of its datastore
        return getattr(self._datastore, name)


class ModbusCellServer:
    """Panel map (docs/panel.md, or an overridden map) and trigger ring on one unit.

    Use as a context manager, or call :meth:`start` and :meth:`stop`. ``port=0``
    binds an ephemeral port; :attr:`port` tells which.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, *, unit_id: int = 1,
                 panel_map: PanelMap = PanelMap(), trigger_base_register: int = 100,
                 ring_size: int = 16):
        if not 1 <= ring_size <= MAX_RING_SIZE or ring_size & (ring_size - 1):
            raise ValueError(f"ring_size {ring_size} is not a power of two in 1..{MAX_RING_SIZE}")
        self.host = host
        self.port = port
        self.unit_id = unit_id
        self.panel_map = panel_map
        self.trigger_base_register = trigger_base_register
        self.ring_size = ring_size
        self._event_counter = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: ModbusTcpServer | None = None
        self._edge_lock = threading.Lock()
        # fault injection, read by the server's loop: replace the objects, do not mutate them
        self.exceptions: dict[int, int] = {}  # function code -> exception code answered instead
        self.silent: frozenset[int] = frozenset()  # function codes left without a reply
        # the simulated operator: called with the placement asked for when the confirm button is
        # pressed while the waiting lamp is lit, before the press reaches the table (the plate is
        # moved first, then confirmed); the lamp and the placement as the daemon last wrote them
        self.on_confirm: Callable[[int], None] | None = None
        self._waiting, self._placement = False, 0

    def _device(self) -> SimDevice:
        n_coils = (max(self.panel_map.coils()) // 16 + 1) * 16
        n_holding = max(self.panel_map.holding_registers()) + 1
        trigger_registers = [0, self.ring_size, LAYOUT_VERSION, 0] + [0] * (
            RECORD_REGISTERS * self.ring_size)
        return SimDevice(self.unit_id, simdata=(
            [SimData(0, values=[False] * n_coils, datatype=DataType.BITS)],
            [SimData(0, values=[False] * 16, datatype=DataType.BITS)],
            [SimData(0, count=n_holding, values=0, datatype=DataType.REGISTERS)],
            [SimData(self.trigger_base_register, values=trigger_registers,
                     datatype=DataType.REGISTERS)],
        ))

    # -- life cycle ------------------------------------------------------------------

    def start(self) -> "ModbusCellServer":
        if self._thread is not None:
            raise RuntimeError("Modbus cell server already started")
        device = self._device()
        started = threading.Event()
        failure: list[BaseException] = []
        self._loop = asyncio.new_event_loop()

        async def listen():
            self._server = ModbusTcpServer([device], address=(self.host, self.port),
                                           trace_pdu=self._faulty_reply, trace_packet=self._withheld)
            self._server.context = _OneUnit(self._server.context, self.unit_id)
            await self._server.serve_forever(background=True)
            self.port = self._server.transport.sockets[0].getsockname()[1]

        def run():
            asyncio.set_event_loop(self._loop)
            try:
                self._loop.run_until_complete(listen())
            except BaseException as exc:  # reported to the starting thread
                failure.append(exc)
                started.set()
                return
            started.set()
            self._loop.run_forever()

        self._thread = threading.Thread(target=run, name=f"modbus-server-{self.port}",
                                        daemon=True)
        self._thread.start()
        if not started.wait(SERVER_CALL_TIMEOUT_S) or failure:
            self._thread = None
            raise RuntimeError(f"Modbus cell server did not start on {self.host}:{self.port}: "
                               f"{failure[0] if failure else 'timeout'}")
        return self

    def stop(self) -> None:
        """Close the listener and every client connection (a clean power-off)."""
        if self._thread is None:
            return
        loop = self._loop
        try:
            asyncio.run_coroutine_threadsafe(self._server.shutdown(), loop).result(
                SERVER_CALL_TIMEOUT_S)
        finally:
            loop.call_soon_threadsafe(loop.stop)
            self._thread.join(SERVER_CALL_TIMEOUT_S)
            self._thread = None
            loop.close()

    def __enter__(self) -> "ModbusCellServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- fault injection -------------------------------------------------------------

    def _faulty_reply(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        if not sending:
            self._watch(pdu)
            return pdu
        code = self.exceptions.get(pdu.function_code & 0x7F) if sending else None
        if code is None:
            return pdu
        return ExceptionResponse(pdu.function_code & 0x7F, code, device_id=pdu.dev_id,
                                 transaction=pdu.transaction_id)

    def _watch(self, request: ModbusPDU) -> None:
        """A request as it arrives: the daemon's waiting lamp and placement noted, the operator's
        confirm acted on (:attr:`on_confirm`) while the lamp is lit."""
        m, code = self.panel_map, request.function_code
        try:
            if code == WRITE_REGISTER and request.address == m.placement_register:
                self._placement = int(request.registers[0])
            elif code == WRITE_COIL and request.address == m.waiting_lamp_coil:
                self._waiting = bool(request.bits[0])
            elif code == WRITE_COIL and request.address == m.confirm_request_coil and request.bits[0]:
                self._operator_confirms()
        except Exception as exc:  # never the server's loop: the press still lands, the plate stays
            print(f"cellcal sim-cell: the simulated operator failed: {exc}", file=sys.stderr)

    def _operator_confirms(self) -> None:
        if self._waiting and self.on_confirm is not None:
            self.on_confirm(self._placement)

    def _withheld(self, sending: bool, packet: bytes) -> bytes:
        # a Modbus TCP frame: 7 bytes of MBAP header, then the function code
        if sending and len(packet) > 7 and packet[7] & 0x7F in self.silent:
            return b""
        return packet

    def clear_faults(self) -> None:
        self.exceptions, self.silent = {}, frozenset()

    def drop_connections(self) -> None:
        """Cut every client connection (a cable pulled and plugged back in); they may reconnect."""
        def cut():
            for connection in list(self._server.active_connections.values()):
                connection.close()
        self._loop.call_soon_threadsafe(cut)

    # -- the operator's side of the panel --------------------------------------------

    def press_start(self) -> None:
        self._set(WRITE_COIL, self.panel_map.start_request_coil, [True])

    def press_abort(self) -> None:
        self._set(WRITE_COIL, self.panel_map.abort_request_coil, [True])

    def press_confirm(self) -> None:
        """The operator has done what the waiting lamp asks (the plate moved, :attr:`on_confirm`)."""
        self._operator_confirms()
        self._set(WRITE_COIL, self.panel_map.confirm_request_coil, [True])

    def select_routine(self, routine: int) -> None:
        self._set(WRITE_REGISTER, self.panel_map.routine_selector_register, [routine])

    def select_tool(self, tool: int) -> None:
        self._set(WRITE_REGISTER, self.panel_map.tool_selector_register, [tool])

    def set_mounted_tool(self, tool: int) -> None:
        """The PLC's or the tool changer's side: the tool on the flange (0: none) in the
        mounted-tool register (map key ``mounted_tool``)."""
        self._set(WRITE_REGISTER, self.panel_map.mounted_tool_register, [tool])

    def mounted_tool(self) -> int:
        return self._get(READ_HOLDING, self.panel_map.mounted_tool_register)[0]

    def start_request_pending(self) -> bool:
        return bool(self._get(READ_COILS, self.panel_map.start_request_coil)[0])

    def abort_request_pending(self) -> bool:
        return bool(self._get(READ_COILS, self.panel_map.abort_request_coil)[0])

    def confirm_request_pending(self) -> bool:
        return bool(self._get(READ_COILS, self.panel_map.confirm_request_coil)[0])

    def waiting(self) -> int:
        """The placement a routine waits for the operator to move the plate to (0: none waits), as
        the waiting lamp and the placement register say."""
        lit = bool(self._get(READ_COILS, self.panel_map.waiting_lamp_coil)[0])
        return self._get(READ_HOLDING, self.panel_map.placement_register)[0] if lit else 0

    def lamps(self) -> dict[str, bool]:
        m = self.panel_map
        return {name: bool(self._get(READ_COILS, coil)[0]) for name, coil in
                (("busy", m.busy_lamp_coil), ("done", m.done_lamp_coil),
                 ("fault", m.fault_lamp_coil))}

    def result_code(self) -> int:
        return self._get(READ_HOLDING, self.panel_map.result_code_register)[0]

    def outcome(self) -> dict[str, int]:
        """The outcome registers' raw values by name (daemon/outcome.py decodes them)."""
        return {name: self._get(READ_HOLDING, address)[0]
                for name, address in self.panel_map.outcome_registers().items()}

    def run_counter(self) -> int:
        return self._get(READ_HOLDING, self.panel_map.run_counter_register)[0]

    # -- the light barrier's side of the trigger ring --------------------------------

    def record_edge(self, channel: int, edge: Edge, t_us: int, *,
                    edge_code: int | None = None) -> int:
        """Store one timestamped edge as the IO module would; returns its event number.

        ``edge_code`` overrides the encoded edge, to simulate a corrupt record.
        """
        with self._edge_lock:
            seq = self._event_counter
            slot = seq % self.ring_size
            code = EDGE_CODES[edge] if edge_code is None else edge_code
            record = encode_record(seq, channel, code, t_us % 2**32)
            # the record first, then the counter: a client never sees a counter
            # pointing at a slot not yet written
            self._set(READ_INPUT, self.trigger_base_register + HEADER_REGISTERS
                      + RECORD_REGISTERS * slot, record)
            self._event_counter = (seq + 1) % SEQ_MODULUS
            self._set(READ_INPUT, self.trigger_base_register, [self._event_counter])
            return seq

    # -- access to the running server's tables ---------------------------------------

    def _get(self, function_code: int, address: int, count: int = 1) -> list:
        return self._run(self._server.async_getValues(self.unit_id, function_code,
                                                      address, count))

    def _set(self, function_code: int, address: int, values: list) -> None:
        self._run(self._server.async_setValues(self.unit_id, function_code, address, values))

    def _run(self, coroutine):
        if self._thread is None:
            coroutine.close()
            raise RuntimeError("Modbus cell server is not running")
        return asyncio.run_coroutine_threadsafe(coroutine, self._loop).result(SERVER_CALL_TIMEOUT_S)
