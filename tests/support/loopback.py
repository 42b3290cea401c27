"""Loopback addresses of a test's own, for fakes that listen on fixed ports.

The fake UR controller's ports are fixed (30004, 29999, 30003 and its control port), and
the shipped networked cells put the Modbus IO module and the tracker on fixed ports too, so
two fakes running at once need two addresses. Linux routes all of 127.0.0.0/8 to the
loopback device: each address handed out here is one that no other test process on this
machine holds at the moment, whether it is a pytest-xdist worker of the same run or another
run altogether (another checkout, a bench).

An address is held by binding a Unix socket in the abstract namespace named after it: the
kernel lets one socket at a time have a name and drops it when the holder closes it or
ends, even when killed, so nothing is left behind on disk and no crashed run keeps an
address. The search starts at a random place in 127.64.0.0/10 (about four million
addresses, clear of 127.0.0.0/16, where the shipped cell files and the demo listen), so a
run does not reuse an address a run just before it left sockets in TIME_WAIT on.

``tests/conftest.py`` makes fixtures of it (``loopback``, ``loopback_host``); module fixtures
and the benches use :func:`held` or :func:`allocate` and :func:`release`.
"""
from __future__ import annotations

import contextlib
import secrets
import socket
import threading

FIRST, COUNT = 64 << 16, 64 << 16  # 127.64.0.0 .. 127.127.255.255, as offsets below 127.0.0.0
_LOCK_PREFIX = "\0cellcal-tests-loopback-"
_held: dict[str, socket.socket] = {}
_mutex = threading.Lock()


def _address(offset: int) -> str:
    n = FIRST + offset % COUNT
    return f"127.{n >> 16 & 255}.{n >> 8 & 255}.{n & 255}"


def allocate() -> str:
    """A loopback address that this process holds until :func:`release` (or its end)."""
    start = secrets.randbelow(COUNT)
    with _mutex:
        for k in range(COUNT):
            host = _address(start + k)
            if host.endswith((".0", ".255")) or host in _held:  # network and broadcast look-alikes
                continue
            claim = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                claim.bind(_LOCK_PREFIX + host)
            except OSError:  # another process holds it
                claim.close()
                continue
            _held[host] = claim
            return host
    raise RuntimeError("no free loopback address in 127.64.0.0/10")


def release(host: str) -> None:
    """Give `host` back (no-op for an address this process does not hold)."""
    with _mutex:
        claim = _held.pop(host, None)
    if claim is not None:
        claim.close()


@contextlib.contextmanager
def held():
    """``with held() as host:`` an address of its own for the block."""
    host = allocate()
    try:
        yield host
    finally:
        release(host)
