"""NMEA-style line framing shared by the serial trigger and tracker protocols:
``<body>*XX`` where XX is the XOR of the body's bytes in two hex digits."""
from __future__ import annotations

import re
from functools import reduce

from cellcal.drivers.interfaces import ProtocolError

_HEX2 = re.compile(rb"[0-9A-Fa-f]{2}")


def xor_checksum(body: bytes) -> int:
    return reduce(lambda a, b: a ^ b, body, 0)


def framed(body: bytes) -> bytes:
    """body, ``*XX`` and the CR LF terminator."""
    return body + b"*%02X\r\n" % xor_checksum(body)


def checked_body(line: bytes, start: int, device: str, noun: str, shown: int) -> bytes:
    """The bytes from `start` up to ``*`` of a line whose checksum is right; one
    ProtocolError naming the device otherwise (`noun`: "line" or "sentence")."""
    star = line.rfind(b"*")
    if star < start:
        raise ProtocolError(device, f"truncated {noun} (no checksum): {line[:shown]!r}")
    body, checksum = line[start:star], line[star + 1:]
    if not _HEX2.fullmatch(checksum):
        raise ProtocolError(device, f"malformed checksum field {checksum[:8]!r}")
    computed = xor_checksum(body)
    if int(checksum, 16) != computed:
        raise ProtocolError(device, f"bad checksum: {noun} says {checksum.decode()}, computed {computed:02X}")
    return body
