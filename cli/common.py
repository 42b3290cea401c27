"""What every ``cellcal`` sub-command shares: the usage error and the progress line.

A sub-command raises :class:`UsageError` for bad usage or input found after
argument parsing (``cli`` turns it into exit status 2 with one message), and
reports progress with :func:`print_progress`, on stderr, so that with ``--json``
stdout carries the JSON object alone. Every numeric option is bounded where it is
parsed (:class:`Bounded`, from :func:`number` and :func:`whole`), and every output
path is checked before a command moves anything or computes for long
(:func:`writable_file`, :func:`writable_folder`).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path


class UsageError(Exception):
    """Bad usage or input detected after parsing; exit status 2."""


class ReportError(UsageError):
    """The result was printed, but the report folder given cannot be written; exit status 2
    (the command's stdout already carries the result, so no error object follows it)."""


def print_progress(message: str) -> None:
    """One progress line on stderr, shown at once."""
    print(f"cellcal: {message}", file=sys.stderr, flush=True)


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``n`` and the noun in the number it takes: ``1 row``, ``2 rows``, ``0 rows``."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


def output_folder(path, option: str) -> Path:
    """A folder results may be written to, made if missing; a UsageError saying why not."""
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise UsageError(f"{option} {folder}: exists and is not a folder") from None
    except OSError as exc:
        raise UsageError(f"{option} {folder}: cannot make the folder: {exc.strerror or exc}") from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UsageError(f"{option} {folder}: the folder is not writable")
    return folder


def output_file(path, option: str) -> Path:
    """A file path results may be written to: its folder exists and is writable, and it is not a folder."""
    file = Path(path)
    if file.is_dir():
        raise UsageError(f"{option} {file}: is a folder; give a file name")
    parent = file.parent
    if not parent.is_dir():
        raise UsageError(f"{option} {file}: the folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UsageError(f"{option} {file}: the folder {parent} is not writable")
    return file


STATE_HELP = "the store's folder (default: $STATE_DIRECTORY, else /var/lib/cellcal)"


def open_store(args, create: bool = False):
    """The results store the daemon keeps (``--state-dir`` or ``$STATE_DIRECTORY``). Only the daemon
    creates it (`create`, after checking this user can write the folder and its files); the commands
    that read it never make a store or a folder. A missing or unusable store: UsageError."""
    from cellcal.daemon.store import Store, StoreError, state_dir  # only the commands that read records need it
    try:
        return Store.open(state_dir(args.state_dir), create=create)
    except StoreError as exc:
        raise UsageError(str(exc)) from None


def service_state_folder(args):
    """The daemon's state folder, made if missing, it and its store files writable by this user;
    else UsageError naming the file, its owner and the fix."""
    from cellcal.daemon.store import StoreError, check_state_folder, state_dir
    try:
        return check_state_folder(state_dir(args.state_dir), create=True)
    except StoreError as exc:
        raise UsageError(str(exc)) from None


# -- numeric options, bounded where they are parsed ---------------------------------------------------------

class Bounded:
    """An argparse ``type=``: a number within a range, refused at parse time otherwise.

    Text that does not parse, NaN, an infinity and a value outside ``low .. high`` (with
    ``above``: low itself excluded) end the command before it runs, argparse's way: one
    line ``cellcal COMMAND: error: argument --OPTION: must be ..., got '...'`` and status
    2. Every numeric option of every command has one (tests/unit/test_option_bounds.py
    walks the parsers), so no command meets a value it was not written for.
    """

    def __init__(self, kind: type, low: float, high: float, *, above: bool = False, unit: str = ""):
        if kind not in (int, float) or not low < high:
            raise ValueError(f"a bounded option needs int or float and low < high, got {kind}, {low}, {high}")
        self.kind, self.low, self.high, self.above, self.unit = kind, low, high, above, unit
        self.__name__ = "whole number" if kind is int else "number"  # argparse's name for the type

    def describe(self) -> str:
        what = "a whole number" if self.kind is int else "a number"
        unit = f" {self.unit}" if self.unit else ""
        if self.above:
            return f"{what} above {_shown(self.low)} and at most {_shown(self.high)}{unit}"
        return f"{what} from {_shown(self.low)} to {_shown(self.high)}{unit}"

    def __call__(self, text: str):
        try:
            value = self.kind(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {self.describe()}, got {text!r}") from None
        if not (math.isfinite(value) and self.low <= value <= self.high) or (self.above and value == self.low):
            raise argparse.ArgumentTypeError(f"must be {self.describe()}, got {text!r}")
        return value

    def __repr__(self) -> str:
        return f"Bounded({self.describe()})"


def _shown(value: float) -> str:
    if isinstance(value, int) or (float(value).is_integer() and abs(value) < 1e16):
        return str(int(value))
    return f"{value:g}"


def number(low: float, high: float, *, above: bool = False, unit: str = "") -> Bounded:
    """A finite number in ``low .. high`` (``above``: greater than low)."""
    return Bounded(float, low, high, above=above, unit=unit)


def whole(low: int, high: int, *, unit: str = "") -> Bounded:
    """A whole number in ``low .. high``."""
    return Bounded(int, low, high, unit=unit)


SEED = whole(0, 2**32 - 1)  # numpy's default_rng takes any, but a seed people can write down and repeat
RECORD_ID = whole(1, 2**63 - 1)  # a run's id in the store (SQLite's INTEGER)


# -- output paths, checked before anything moves or computes ----------------------------------------------

def writable_file(path, option: str) -> Path:
    """A file path results may be written to, checked by creating it (then removed again when it
    did not exist): the folder exists and takes new files, the path is no folder. One UsageError
    naming the option and why not; checking only permissions misses /proc, read-only mounts and
    root's view of them."""
    file = output_file(path, option)
    if file.exists():
        if not os.access(file, os.W_OK):
            raise UsageError(f"{option} {file}: the file exists and is not writable")
        return file
    try:
        with open(file, "x", encoding="utf-8"):
            pass
    except OSError as exc:
        raise UsageError(f"{option} {file}: cannot create the file: {exc.strerror or exc}") from None
    file.unlink()
    return file


def writable_folder(path, option: str) -> Path:
    """A folder results may be written to, made if missing, checked by creating a file in it."""
    import tempfile

    folder = output_folder(path, option)
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise UsageError(f"{option} {folder}: cannot write in the folder: {exc.strerror or exc}") from None
    return folder
