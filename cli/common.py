"""What every ``cellcal`` sub-command shares: the usage error and the progress line.

A sub-command raises :class:`UsageError` for bad usage or input found after
argument parsing (``cli`` turns it into exit status 2 with one message), and
reports progress with :func:`print_progress`, on stderr, so that with ``--json``
stdout carries the JSON object alone.
"""
from __future__ import annotations

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


def check_positive(option: str, value: float) -> None:
    """A finite number above zero, or a UsageError naming the option."""
    if not (math.isfinite(value) and value > 0):
        raise UsageError(f"{option} must be a positive number, got {value!r}")


def check_seed(seed: int) -> None:
    if not 0 <= seed < 2**32:
        raise UsageError(f"--seed must be a whole number from 0 to {2**32 - 1}, got {seed}")


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


def check_folds(folds: int) -> None:
    """Cross-validation needs at least two folds."""
    if folds < 2:
        raise UsageError(f"--folds must be at least 2, got {folds}")


STATE_HELP = "the store's folder (default: $STATE_DIRECTORY, else /var/lib/cellcal)"


def open_store(args):
    """The results store the daemon keeps (``--state-dir`` or ``$STATE_DIRECTORY``); bad folder: UsageError."""
    from cellcal.daemon.store import Store, StoreError, state_dir  # only the commands that read records need it
    try:
        return Store.open(state_dir(args.state_dir))
    except StoreError as exc:
        raise UsageError(str(exc)) from None
