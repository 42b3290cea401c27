"""A light barrier on a serial line, simulated through a pseudo-terminal pair.

The barrier writes ``$TRG`` sentences (see :mod:`cellcal.drivers.triggers.serial_line`)
into the master end; the adapter opens the slave end by its tty path with
pyserial, exactly as it would open ``/dev/ttyUSB0``. Tests also use it to send
corrupt bytes and to hang the line up.
"""
from __future__ import annotations

import os
import tty

from cellcal.drivers.interfaces import Edge
from cellcal.drivers.triggers.serial_line import SEQ_MODULUS, format_trigger_sentence


class SerialBarrier:
    """The device end of a pseudo-terminal; :attr:`tty_path` is the end to open."""

    def __init__(self):
        self._master_fd, self._slave_fd = os.openpty()
        # raw: no echo back into the master, no CR/LF translation on the way
        tty.setraw(self._slave_fd)
        self.tty_path = os.ttyname(self._slave_fd)
        self.next_seq = 0

    def send_edge(self, channel: int, edge: Edge, t_us: int, *, seq: int | None = None) -> bytes:
        """Send one edge; ``seq`` overrides the running sentence number. Returns the bytes."""
        if seq is None:
            seq = self.next_seq
        self.next_seq = (seq + 1) % SEQ_MODULUS
        sentence = format_trigger_sentence(seq, channel, edge, t_us)
        self.send_bytes(sentence)
        return sentence

    def send_bytes(self, data: bytes) -> None:
        """Send raw bytes (a corrupt or truncated sentence, line noise)."""
        view = memoryview(data)
        while view:
            view = view[os.write(self._master_fd, view):]

    def hang_up(self) -> None:
        """Drop the line: the reading side gets an I/O error, as when a cable is pulled."""
        if self._master_fd >= 0:
            os.close(self._master_fd)
            self._master_fd = -1

    def close(self) -> None:
        self.hang_up()
        if self._slave_fd >= 0:
            os.close(self._slave_fd)
            self._slave_fd = -1

    def __enter__(self) -> "SerialBarrier":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
