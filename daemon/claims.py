"""One service per store, per panel and per robot: claims the kernel gives back when their holder ends.

Two services on one store would mark each other's live run ``interrupted``; two on one
operator panel would split its presses between them; a command that drives the robot while
the service holds it fails deep inside the robot's client library. So before it touches
anything, ``cellcal daemon`` claims

- its state folder: an advisory lock (``fcntl.flock``) on ``DIR/cellcal.lock``, which holds
  the holder's pid, kept for the service's whole life;
- each device of the cell that other processes can reach, by its address as the cell file
  gives it: every robot (``robot HOST``) and the operator panel (``panel HOST:PORT unit N``).
  A claim is a Unix socket bound in Linux's abstract namespace under the device's name
  (``cellcal:robot:HOST``): one socket at a time can have a name, and the kernel drops it when
  its holder closes it or ends, even when killed, so a crash leaves no stale claim. The
  socket listens, so another process learns the holder's pid by connecting to it
  (``SO_PEERCRED``) and its command line from ``/proc/PID/cmdline``.

``cellcal run`` and ``cellcal tool rollback`` take the same robot claims around the time they
hold the robot's connection. In-process simulated devices (no ``host`` among their driver
options) are nobody else's to reach and need no claim; the state folder's lock applies to
every cell. A refused claim is an :class:`InUseError` naming the holder (exit status 1).
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import inspect
import ipaddress
import os
import socket
import struct
import threading
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

from cellcal.drivers import registry

LOCK_FILE = "cellcal.lock"
_PREFIX = "cellcal:"
_NAME_MAX = 100  # abstract socket names are at most 107 bytes; longer identities are hashed
_CMDLINE_MAX = 240


@dataclass(frozen=True)
class Holder:
    """The process that holds a claim, as far as this process can see it."""

    pid: int | None  # None: not visible (another PID namespace) or not recorded
    cmdline: str | None = None
    argv: tuple[str, ...] = ()

    @classmethod
    def of(cls, pid: int | None) -> "Holder":
        if not pid:
            return cls(None)
        try:
            raw = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:  # ended since, or not ours to read
            return cls(pid)
        argv = tuple(w.decode(errors="replace") for w in raw.split(b"\0") if w)
        text = " ".join(argv)
        if len(text) > _CMDLINE_MAX:
            text = text[:_CMDLINE_MAX - 3] + "..."
        return cls(pid, text or None, argv)

    @property
    def is_service(self) -> bool:
        """``cellcal daemon`` (the installed script, or ``python -m cellcal.cli.main daemon``)."""
        argv = self.argv or tuple((self.cmdline or "").split())
        return "daemon" in argv and any("cellcal" in word for word in argv[:argv.index("daemon")])

    def text(self) -> str:
        if self.pid is None:
            return "another process (its pid is not visible from here)"
        where = f"pid {self.pid}" + (f": {self.cmdline}" if self.cmdline else "")
        if self.is_service:
            return f"the cellcal service ({where})"
        return f"another process ({where})"


class InUseError(RuntimeError):
    """Another process holds the state folder or a device this command needs (exit status 1)."""

    def __init__(self, what: str, holder: Holder):
        self.what, self.holder = what, holder
        if holder.is_service:
            advice = "stop it first (systemctl stop cellcal, or end that process)"
        else:
            advice = "wait for it to end, or stop it"
        super().__init__(f"{holder.text()} holds {what}; {advice}; nothing was changed")


# -- the state folder -----------------------------------------------------------------------------


class FolderLock:
    """``flock`` on ``FOLDER/cellcal.lock`` (which must exist), with this process's pid in it."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> "FolderLock":
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = _pid_in(fd)
            os.close(fd)
            raise InUseError(f"the state folder {self.folder}", Holder.of(pid)) from None
        except BaseException:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # drops the lock; the file stays (removing it would race a new holder)
            self._fd = None


def _pid_in(fd: int) -> int | None:
    try:
        text = os.pread(fd, 64, 0).decode(errors="replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None  # None: the holder has not written it yet


# -- devices --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Device:
    """A device other processes can reach: what to call it, and the claim's name."""

    label: str  # "robot 10.0.0.2", "panel 10.0.0.3:502 unit 1"
    key: str  # "robot:10.0.0.2", "panel:10.0.0.3:502:1"


def _address(host: str) -> str:
    """One spelling per address: IP literals normalised, names resolved where they resolve."""
    text = str(host).strip().lower().rstrip(".")
    try:
        return str(ipaddress.ip_address(text))
    except ValueError:
        pass
    try:
        return socket.gethostbyname(text)
    except OSError:  # not resolvable here: the driver will say so when it connects
        return text


def _options(kind: str, spec) -> dict:
    """The driver's options as it will be built: the cell file's over the driver's defaults."""
    parameters = inspect.signature(registry.factory(kind, spec.name)).parameters
    options = {name: p.default for name, p in parameters.items() if p.default is not inspect.Parameter.empty}
    options.update(spec.options)
    return options


def devices(cell, kinds: tuple[str, ...] = ("robot", "panel")) -> list[Device]:
    """The cell's devices of `kinds` that other processes can reach (their options name a host):
    every robot of the cell, the operator panel (its host, port and unit id)."""
    specs = []
    drivers = cell.drivers
    if "robot" in kinds:
        if "robot" in drivers:
            specs.append(("robot", drivers["robot"]))
        specs += [("robot", r.driver) for name, r in sorted(cell.robots.items()) if name != "a"]
    if "panel" in kinds and "panel" in drivers:
        specs.append(("panel", drivers["panel"]))
    out = []
    for kind, spec in specs:
        options = _options(kind, spec)
        if not options.get("host"):
            continue  # in process: no one else can reach it
        host = _address(options["host"])
        if kind == "panel":
            port, unit = options.get("port"), options.get("unit_id")
            device = Device(f"panel {options['host']}:{port} unit {unit}", f"panel:{host}:{port}:{unit}")
        else:
            device = Device(f"robot {options['host']}", f"robot:{host}")
        if device not in out:
            out.append(device)
    return out


class DeviceClaim:
    """The abstract Unix socket named after a device, bound and listening while held."""

    def __init__(self, device: Device):
        self.device = device
        key = _PREFIX + device.key
        if len(key.encode()) > _NAME_MAX:
            key = _PREFIX + hashlib.sha256(device.key.encode()).hexdigest()
        self.name = "\0" + key
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None

    def acquire(self) -> "DeviceClaim":
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind(self.name)
        except OSError as exc:
            sock.close()
            if exc.errno != errno.EADDRINUSE:
                raise
            raise InUseError(self.device.label, Holder.of(_peer_pid(self.name))) from None
        sock.listen(8)
        self._sock = sock
        self._thread = threading.Thread(target=self._answer, name=f"claim {self.device.label}", daemon=True)
        self._thread.start()
        return self

    def _answer(self) -> None:
        """Accept and close: whoever connects has read this process's pid from the connection."""
        while True:
            try:
                conn, _ = self._sock.accept()
            except OSError:  # shut down: released
                return
            conn.close()

    def release(self) -> None:
        if self._sock is None:
            return
        try:
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the accepting thread
        except OSError:
            pass
        self._thread.join(2.0)
        self._sock.close()  # the name is free from here on
        self._sock = None


def _peer_pid(name: str) -> int | None:
    """The pid of the process listening on abstract socket `name` (SO_PEERCRED), or None."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(1.0)
        try:
            probe.connect(name)
            pid, _uid, _gid = struct.unpack("3i", probe.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                                   struct.calcsize("3i")))
        except OSError:  # released meanwhile, or not answering
            return None
    return pid or None  # 0: in a PID namespace this process cannot see


# -- what the commands take -----------------------------------------------------------------------


@contextmanager
def held(cell=None, *, state_folder: str | Path | None = None, kinds: tuple[str, ...] = ("robot",)):
    """``with held(cell, kinds=("robot",)):`` the claims, in order (the state folder first,
    then each device of `kinds`), released on leaving; InUseError naming the holder of the
    first that another process holds (those taken before it are given back)."""
    with ExitStack() as stack:
        if state_folder is not None:
            lock = FolderLock(state_folder).acquire()
            stack.callback(lock.release)
        for device in ([] if cell is None else devices(cell, kinds)):
            claim = DeviceClaim(device).acquire()
            stack.callback(claim.release)
        yield
