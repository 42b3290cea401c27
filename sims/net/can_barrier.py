"""A light barrier on CAN, simulated on python-can's virtual bus.

Sends the edge frames of :mod:`cellcal.drivers.triggers.can_bus` on a virtual channel;
a :class:`~cellcal.drivers.triggers.can_bus.CanTrigger` opened with
``interface="virtual"`` and the same channel receives them through python-can,
as it would from socketcan.
"""
from __future__ import annotations

import can

from cellcal.drivers.triggers.can_bus import DEFAULT_ARBITRATION_ID, SEQ_MODULUS, encode_trigger_frame
from cellcal.drivers.interfaces import Edge
from cellcal.drivers.triggers.stream import EDGE_CODES


class CanBarrier:
    """The device's node on the bus."""

    def __init__(self, channel: str, *, interface: str = "virtual",
                 arbitration_id: int = DEFAULT_ARBITRATION_ID, extended_id: bool = False):
        self.arbitration_id = arbitration_id
        self.extended_id = extended_id
        self.next_seq = 0
        self._bus = can.Bus(interface=interface, channel=channel)

    def send_edge(self, channel: int, edge: Edge, t_us: int, *, seq: int | None = None,
                  status: int = 0) -> None:
        """Send one edge frame; ``seq`` overrides the running frame number."""
        if seq is None:
            seq = self.next_seq
        self.next_seq = (seq + 1) % SEQ_MODULUS
        self.send_data(encode_trigger_frame(seq, channel, EDGE_CODES[edge], t_us, status))

    def send_data(self, data: bytes, *, arbitration_id: int | None = None) -> None:
        """Send a frame with arbitrary data bytes (a short or corrupt frame)."""
        self._bus.send(can.Message(
            arbitration_id=self.arbitration_id if arbitration_id is None else arbitration_id,
            is_extended_id=self.extended_id, data=data), timeout=1.0)

    def close(self) -> None:
        self._bus.shutdown()

    def __enter__(self) -> "CanBarrier":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
