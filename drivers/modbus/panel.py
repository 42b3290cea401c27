"""The operator panel on a Modbus TCP device (docs/panel.md), through pymodbus.

The panel is a small PLC or IO module: the daemon is the Modbus client, polls the
start/abort coils and the routine selector, and drives the lamps, the result code
and the run counter. Every address can be overridden from the cell file, because
the panel is whatever IO module the integrator had at hand.

:class:`ModbusLink` is the one place that turns pymodbus' return values and
exceptions into the cell's errors; the Modbus trigger uses it too.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from cellcal.config.reader import Section
from cellcal.drivers.interfaces import DeviceError, DeviceTimeout, OperatorPanel, ProtocolError
from cellcal.drivers.registry import DriverConfigError

# Modbus application protocol v1.1b3, section 7
EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}

REGISTER_MAX = 0xFFFF


class ModbusExceptionResponse(DeviceError):
    """The device answered a request with a Modbus exception (e.g. no such address)."""

    def __init__(self, device: str, what: str, exception_code: int):
        super().__init__(device, what)
        self.exception_code = exception_code


class ModbusLink:
    """One Modbus TCP connection to one unit, with a deadline on every request.

    pymodbus retries are switched off so that ``timeout_s`` is the real bound on
    each request; a lost connection is re-opened by the next request.
    """

    def __init__(self, device: str, host: str, port: int, unit_id: int, timeout_s: float):
        self.device = device
        self.host = host
        self.port = port
        self.unit_id = unit_id
        self.timeout_s = timeout_s
        self._client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0)

    def connect(self) -> None:
        if not self._client.connect():
            raise DeviceError(self.device, f"cannot connect to {self.host}:{self.port} "
                                           f"(refused, unreachable or no answer within "
                                           f"{self.timeout_s:g} s)")

    def close(self) -> None:
        self._client.close()

    def read_coils(self, address: int, count: int = 1) -> list[bool]:
        response = self._call(f"reading coil {_span(address, count)}",
                              self._client.read_coils, address, count=count)
        bits = list(response.bits)
        if len(bits) < count:
            raise ProtocolError(self.device, f"reading coil {_span(address, count)}: "
                                             f"{len(bits)} bits in reply")
        return [bool(b) for b in bits[:count]]

    def write_coil(self, address: int, value: bool) -> None:
        self._call(f"writing coil {address}", self._client.write_coil, address, bool(value))

    def read_holding_registers(self, address: int, count: int = 1) -> list[int]:
        return self._registers(f"reading holding register {_span(address, count)}",
                               self._client.read_holding_registers, address, count)

    def read_input_registers(self, address: int, count: int = 1) -> list[int]:
        return self._registers(f"reading input register {_span(address, count)}",
                               self._client.read_input_registers, address, count)

    def write_register(self, address: int, value: int) -> None:
        if not 0 <= value <= REGISTER_MAX:
            raise ValueError(f"{self.device}: register value {value} outside 0..65535")
        self._call(f"writing holding register {address}", self._client.write_register,
                   address, value)

    def _registers(self, what: str, read, address: int, count: int) -> list[int]:
        registers = list(self._call(what, read, address, count=count).registers)
        if len(registers) != count:
            raise ProtocolError(self.device, f"{what}: {len(registers)} registers in reply")
        return registers

    def _call(self, what: str, request, *args, **kwargs):
        was_connected = self._client.connected
        started = time.monotonic()
        try:
            response = request(*args, device_id=self.unit_id, **kwargs)
        except ConnectionException as exc:
            if was_connected:
                raise DeviceError(self.device, f"connection to {self.host}:{self.port} lost "
                                               f"while {what}") from exc
            raise DeviceError(self.device, f"cannot connect to {self.host}:{self.port} "
                                           f"while {what}") from exc
        except ModbusIOException as exc:
            self._client.close()  # a late reply must not be taken for the next request's
            if time.monotonic() - started >= 0.9 * self.timeout_s:
                raise DeviceTimeout(self.device, f"no reply within {self.timeout_s:g} s "
                                                 f"while {what}") from exc
            raise ProtocolError(self.device, f"bad reply while {what}: {exc}") from exc
        except ModbusException as exc:
            raise ProtocolError(self.device, f"{what}: {exc}") from exc
        except OSError as exc:  # e.g. a reset pymodbus does not wrap
            self._client.close()
            raise DeviceError(self.device, f"connection to {self.host}:{self.port} lost "
                                           f"while {what}: {exc.strerror or exc}") from exc
        if response.isError():
            code = int(getattr(response, "exception_code", 0))
            name = EXCEPTION_NAMES.get(code, "unknown exception")
            raise ModbusExceptionResponse(
                self.device, f"exception response {code} ({name}) to {what} at unit "
                             f"{self.unit_id}", code)
        return response


def _span(address: int, count: int) -> str:
    return str(address) if count == 1 else f"{address}..{address + count - 1}"


@dataclass(frozen=True)
class PanelMap:
    """Addresses of the panel's coils and holding registers (defaults: docs/panel.md)."""

    start_request_coil: int = 0
    abort_request_coil: int = 1
    busy_lamp_coil: int = 8
    done_lamp_coil: int = 9
    fault_lamp_coil: int = 10
    routine_selector_register: int = 0
    result_code_register: int = 1
    run_counter_register: int = 2
    # the outcome of the last run (written before the result code and the counter)
    verdict_register: int = 20
    tool_id_register: int = 21
    change_x_register: int = 22
    change_y_register: int = 23
    change_z_register: int = 24
    tilt_x_register: int = 25
    tilt_y_register: int = 26
    tool_selector_register: int = 27  # written by the panel: the tool the start is for (0: the mounted one)
    mounted_tool_register: int = 28  # written by the PLC or tool changer: the tool on the flange (0: none)
    # a routine waiting for the operator (kinematic-fixture's plate moved by hand): the confirm button,
    # the waiting lamp, and which placement the plate is to go to (1, 2, ...; 0 while none waits)
    confirm_request_coil: int = 2
    waiting_lamp_coil: int = 11
    placement_register: int = 29

    @classmethod
    def of_options(cls, options) -> "PanelMap":
        """The addresses a cell file's panel options set, the defaults for the rest (other options,
        host or port, are not addresses and are left out)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in options.items() if k in names})

    def coils(self) -> list[int]:
        return [self.start_request_coil, self.abort_request_coil, self.busy_lamp_coil,
                self.done_lamp_coil, self.fault_lamp_coil, self.confirm_request_coil, self.waiting_lamp_coil]

    def holding_registers(self) -> list[int]:
        return [self.routine_selector_register, self.result_code_register,
                self.run_counter_register, *self.outcome_registers().values(), self.tool_selector_register,
                self.mounted_tool_register, self.placement_register]

    def outcome_registers(self) -> dict[str, int]:
        """The outcome registers by their name in :meth:`OperatorPanel.set_outcome` -> address."""
        return {"verdict": self.verdict_register, "tool_id": self.tool_id_register,
                "change_x": self.change_x_register, "change_y": self.change_y_register,
                "change_z": self.change_z_register, "tilt_x": self.tilt_x_register,
                "tilt_y": self.tilt_y_register}


class ModbusPanel(OperatorPanel):
    """Operator panel on a Modbus TCP server; options as a cell file gives them.

    Connects at construction so that a wrong host or port fails at start-up; a
    connection lost later is re-opened by the next call.
    """

    @staticmethod
    def check_options(**options) -> None:
        """Refuse an option out of range, naming it (also run by the registry at cell load)."""
        o = Section.of_options(DriverConfigError, **options)
        o.port()
        o.integer("unit_id", low=0, high=255)
        o.timeout("timeout_s")
        addresses = {f.name: o.integer(f.name, low=0, high=REGISTER_MAX) for f in dataclasses.fields(PanelMap)}
        panel_map = PanelMap(**addresses)
        if len(set(panel_map.coils())) < len(panel_map.coils()) or \
                len(set(panel_map.holding_registers())) < len(panel_map.holding_registers()):
            o.fail(None, f"two panel signals share an address ({panel_map})")

    def __init__(self, host: str = "127.0.0.1", port: int = 502, *, unit_id: int = 1,
                 timeout_s: float = 1.0, name: str = "panel",
                 start_request_coil: int = 0, abort_request_coil: int = 1,
                 busy_lamp_coil: int = 8, done_lamp_coil: int = 9, fault_lamp_coil: int = 10,
                 routine_selector_register: int = 0, result_code_register: int = 1,
                 run_counter_register: int = 2, verdict_register: int = 20, tool_id_register: int = 21,
                 change_x_register: int = 22, change_y_register: int = 23, change_z_register: int = 24,
                 tilt_x_register: int = 25, tilt_y_register: int = 26, tool_selector_register: int = 27,
                 mounted_tool_register: int = 28, confirm_request_coil: int = 2, waiting_lamp_coil: int = 11,
                 placement_register: int = 29):
        given = locals()
        addresses = {f.name: given[f.name] for f in dataclasses.fields(PanelMap)}
        self.check_options(port=port, unit_id=unit_id, timeout_s=timeout_s, **addresses)
        self.map = PanelMap(**addresses)
        self.name = name
        self.device = f"{name} (Modbus TCP {host}:{port}, unit {unit_id})"
        self._link = ModbusLink(self.device, host, port, unit_id, timeout_s)
        self._link.connect()

    def start_requested(self) -> bool:
        return self._take_request(self.map.start_request_coil)

    def abort_requested(self) -> bool:
        return self._take_request(self.map.abort_request_coil)

    def _take_request(self, coil: int) -> bool:
        # the daemon owns clearing: the button sets the coil, reading it consumes it
        if not self._link.read_coils(coil)[0]:
            return False
        self._link.write_coil(coil, False)
        return True

    def confirm_requested(self) -> bool:
        return self._take_request(self.map.confirm_request_coil)

    def set_waiting(self, step: int) -> None:
        if isinstance(step, bool) or not isinstance(step, int) or not 0 <= step <= REGISTER_MAX:
            raise ValueError(f"{self.device}: placement {step!r} outside 0..65535")
        # the placement first: a PLC that sees the lamp light reads which placement it is for
        self._link.write_register(self.map.placement_register, step)
        self._link.write_coil(self.map.waiting_lamp_coil, step != 0)

    def routine_selector(self) -> int:
        return self._link.read_holding_registers(self.map.routine_selector_register)[0]

    def tool_selector(self) -> int:
        return self._link.read_holding_registers(self.map.tool_selector_register)[0]

    def mounted_tool(self) -> int:
        return self._link.read_holding_registers(self.map.mounted_tool_register)[0]

    def set_lamps(self, *, busy: bool | None = None, done: bool | None = None,
                  fault: bool | None = None) -> None:
        for coil, value in ((self.map.busy_lamp_coil, busy), (self.map.done_lamp_coil, done),
                            (self.map.fault_lamp_coil, fault)):
            if value is not None:
                self._link.write_coil(coil, value)

    def set_result(self, code: int, increment_counter: bool = True) -> None:
        if isinstance(code, bool) or not isinstance(code, int) or not 0 <= code <= REGISTER_MAX:
            raise ValueError(f"{self.device}: result code {code!r} outside 0..65535")
        self._link.write_register(self.map.result_code_register, code)
        if increment_counter:
            # the daemon is the counter's only writer, so read-modify-write is safe
            counter = self._link.read_holding_registers(self.map.run_counter_register)[0]
            self._link.write_register(self.map.run_counter_register, (counter + 1) & REGISTER_MAX)

    def set_outcome(self, registers: dict[str, int]) -> None:
        where = self.map.outcome_registers()
        for name, value in registers.items():
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= REGISTER_MAX:
                raise ValueError(f"{self.device}: outcome register {name} value {value!r} outside 0..65535")
            self._link.write_register(where[name], value)

    def close(self) -> None:
        self._link.close()
