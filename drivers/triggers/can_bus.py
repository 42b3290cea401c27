"""Light barrier / touch trigger events over CAN, through python-can.

One data frame per edge, timestamped by the device's own microsecond clock.
Standard (11-bit) identifier 0x1A0 by default; the cell file may choose another
or a 29-bit one. Eight data bytes, little-endian as in CANopen:

=====  =============  ===========================================================
byte   name           meaning
=====  =============  ===========================================================
0      seq            frame number, +1 per edge, wraps 255 -> 0
1      channel        input number 0..255
2      edge           1 beam blocked / contact made, 2 cleared / released
3      status         bit 0: the device's own edge queue overflowed (edges lost);
                      bits 1..7 reserved, 0
4..7   t_us           device time of the edge in us, unsigned 32-bit, wraps
=====  =============  ===========================================================

CAN checks the frame itself (CRC, acknowledgement), so there is no checksum
here. Frames with other identifiers, remote and error frames are not ours and
are skipped. Faults raise :class:`ProtocolError` naming the bus: a data length
other than 8, an unknown edge code, the overflow bit, a sequence gap or repeat
(a one-byte counter, so more than 255 lost frames in a row go unseen: the
device time check then usually catches it) and a device time going backwards.

``interface="socketcan"`` in production; ``interface="virtual"`` with any
channel name is python-can's in-process bus, which the tests use.
"""
from __future__ import annotations

import struct
import time
from typing import Iterator

import can

from cellcal.drivers.interfaces import DeviceError, ProtocolError
from cellcal.config.reader import Section
from cellcal.drivers.registry import DriverConfigError
from cellcal.drivers.triggers.stream import EDGES_BY_CODE, RecordTrigger, TriggerRecord

DEFAULT_ARBITRATION_ID = 0x1A0
SEQ_MODULUS = 256
STATUS_OVERFLOW = 0x01
_FRAME = struct.Struct("<BBBBI")


def encode_trigger_frame(seq: int, channel: int, edge_code: int, t_us: int,
                         status: int = 0) -> bytes:
    """The eight data bytes of one edge frame (used by the simulated barrier)."""
    return _FRAME.pack(seq % SEQ_MODULUS, channel, edge_code, status, t_us % 2**32)


def parse_trigger_frame(data: bytes, device: str) -> TriggerRecord:
    if len(data) != _FRAME.size:
        raise ProtocolError(device, f"truncated frame: {len(data)} data bytes, expected 8")
    seq, channel, edge_code, status, t_us = _FRAME.unpack(bytes(data))
    if status & STATUS_OVERFLOW:
        raise ProtocolError(device, f"device reports lost edges (queue overflow) before "
                                    f"frame {seq}")
    edge = EDGES_BY_CODE.get(edge_code)
    if edge is None:
        raise ProtocolError(device, f"frame {seq}: unknown edge code {edge_code}")
    return TriggerRecord(seq=seq, channel=channel, edge=edge, t_us=t_us)


class CanTrigger(RecordTrigger):
    """Device-timestamped trigger events from CAN frames with one identifier.

    ``channel`` is python-can's (``can0``), not the barrier's input number.
    """

    @staticmethod
    def check_options(**options) -> None:
        """Refuse an option out of range, naming it (also run by the registry at cell load)."""
        o = Section.of_options(DriverConfigError, **options)
        o.text("channel")
        o.text("interface")
        extended = o.flag("extended_id", False)
        o.integer("arbitration_id", low=0, high=0x1FFFFFFF if extended else 0x7FF)

    def __init__(self, channel: str = "can0", *, interface: str = "socketcan",
                 arbitration_id: int = DEFAULT_ARBITRATION_ID, extended_id: bool = False,
                 bitrate: int | None = None, name: str = "trigger"):
        id_max = 0x1FFFFFFF if extended_id else 0x7FF
        self.check_options(channel=channel, interface=interface, arbitration_id=arbitration_id,
                           extended_id=extended_id)
        self.name = name
        super().__init__(f"{name} (CAN {interface} {channel}, id {arbitration_id:#x})",
                         SEQ_MODULUS)
        self.arbitration_id = arbitration_id
        self.extended_id = extended_id
        options = {} if bitrate is None else {"bitrate": bitrate}
        try:
            self._bus = can.Bus(interface=interface, channel=channel, can_filters=[
                {"can_id": arbitration_id, "can_mask": id_max, "extended": extended_id}],
                **options)
        except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
            raise DeviceError(self.device, f"cannot open CAN interface: {exc}") from exc

    def _records(self, wait_until: float) -> Iterator[TriggerRecord]:
        while True:
            try:
                frame = self._bus.recv(timeout=max(0.0, wait_until - time.monotonic()))
            except (can.CanError, OSError) as exc:
                raise DeviceError(self.device, f"CAN bus lost: {exc}") from exc
            if frame is None:
                return
            if (frame.is_error_frame or frame.is_remote_frame
                    or frame.arbitration_id != self.arbitration_id
                    or frame.is_extended_id != self.extended_id):
                continue
            record = parse_trigger_frame(frame.data, self.device)
            wait_until = 0.0  # something arrived: only drain what is already there
            yield record

    def close(self) -> None:
        self._bus.shutdown()

