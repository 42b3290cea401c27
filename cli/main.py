"""The ``cellcal`` command line (contract: docs/cli.md).

Exit status: 0 success, 2 bad usage or bad input (one clear message; argparse's refusals
and a file that cannot be read or written included), 1 a failure of the cell or the
computation, or a defect of cellcal ("internal error", its traceback only with
``CELLCAL_DEBUG=1`` or ``cellcal --debug``). With ``--json`` stdout carries one JSON object
and nothing else, on an error too; progress goes to stderr.

Each sub-command is a module of its own with ``add_parser(sub)``; the table below
names it and its one-line help, and the module is imported only when its command
runs (``cellcal --help`` imports none of them: no numpy, matplotlib or pymodbus).
"""
from __future__ import annotations

import argparse
import functools
import importlib
import json
import os
import sys
import traceback
from importlib import metadata

# name -> (module, one-line help). The help must be the one the module registers
# (tests/unit/test_cli_commands.py keeps the two equal).
COMMANDS: dict[str, tuple[str, str]] = {
    "identify": ("cellcal.cli.identify", "kinematic calibration from measured target positions"),
    "analyze": ("cellcal.cli.analyze", "find, name and size the effect the rigid model misses"),
    "compensate": ("cellcal.cli.compensate",
                   "correct targets with a calibrated model: joints and Cartesian targets"),
    "iso9283": ("cellcal.cli.iso9283", "pose accuracy AP and repeatability RP at the cube points, per ISO 9283"),
    "import": ("cellcal.cli.import_data", "convert a vendor or data-set export to the measurement CSV"),
    "run": ("cellcal.cli.run", "run a calibration routine on a cell"),
    "daemon": ("cellcal.cli.daemon", "the service: run routines from the operator panel, write back tool frames"),
    "runs": ("cellcal.cli.runs", "the runs recorded in the store"),
    "tool": ("cellcal.cli.tool", "tool frames written to the controller"),
    "service": ("cellcal.cli.service", "install the daemon as a systemd service on this machine"),
    "plant": ("cellcal.cli.plant", "the cells publishing to one MQTT broker: their state and last result"),
    "demo": ("cellcal.cli.sim.demo", "the whole product on the simulated network cell (make demo)"),
    "sim-campaign": ("cellcal.cli.sim.campaign", "simulated tracker campaign: plan, measure, identify, validate"),
    "sim-data": ("cellcal.cli.sim.data", "write a measurement CSV from the simulated cell, with hidden effects"),
    "sim-cell": ("cellcal.cli.sim.cell", "serve the fakes of a networked simulated cell until stopped"),
}


DEBUG_VARIABLE = "CELLCAL_DEBUG"  # set (to anything but 0): an internal error prints its traceback too


class ArgumentsRefused(SystemExit):
    """argparse refused the command line (status 2); ``line`` is what it printed on stderr."""

    def __init__(self, line: str):
        super().__init__(2)
        self.line = line


class _Parser(argparse.ArgumentParser):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if self.add_help:  # `cellcal COMMAND --version` as well as `cellcal --version` (not in the help)
            self.add_argument("--version", action="version", version=f"cellcal {version()}",
                              help=argparse.SUPPRESS if " " in self.prog else "print cellcal's version and exit")

    def error(self, message):  # argparse's own errors: exit 2 with one line
        line = f"{self.prog}: error: {message}"
        print(line, file=sys.stderr)
        raise ArgumentsRefused(line)


@functools.cache
def version() -> str:
    try:
        return metadata.version("cellcal")
    except metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def build_parser(command: str | None = None, *, every: bool = False) -> argparse.ArgumentParser:
    """The parser; the full sub-parser only for `command` (or for all with `every`), the others
    as a name and its help, so that listing the commands imports none of them."""
    parser = _Parser(prog="cellcal", description="Calibration for robot cells.")
    parser.add_argument("--debug", action="store_true",
                        help=f"on an internal error (a defect of cellcal) print the Python traceback as well "
                             f"(as {DEBUG_VARIABLE}=1 does)")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser, metavar="COMMAND")
    for name, (module, summary) in COMMANDS.items():
        if every or name == command:
            importlib.import_module(module).add_parser(sub)
        else:
            sub.add_parser(name, help=summary, add_help=False)
    return parser


def _command_in(argv: list[str]) -> str | None:
    """The sub-command named on the line: the first word that is not an option."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def _asks_for_json(argv: list[str]) -> bool:
    """Whether the command line has ``--json`` (or an abbreviation argparse would take for it)."""
    words = argv[:argv.index("--")] if "--" in argv else argv
    return any(len(w) >= 3 and "--json".startswith(w) for w in words)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = _command_in(argv)
    parser = build_parser(command)
    try:
        args = parser.parse_args(argv)
    except ArgumentsRefused as refused:  # the line is on stderr; with --json the error object too
        if _asks_for_json(argv):
            print(json.dumps({"error": {"code": refused.code, "message": refused.line}}))
        raise
    # Load both BLAS libraries (numpy's and scipy's) before limiting them: threadpoolctl
    # limits only what is loaded, and the solvers' matrices are small, so BLAS threads only
    # contend (several times slower on 2 cores).
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits
    with threadpool_limits(limits=1, user_api="blas"):
        return _run(args)


def _run(args) -> int:
    try:
        return args.func(args)
    except KeyboardInterrupt:
        return _error(args, 1, "interrupted")
    except Exception as exc:  # noqa: BLE001 - sorted into exit codes below
        code, message, json_object = _classify(exc)
        if code is None:  # none of ours and no file's: a defect of cellcal
            if getattr(args, "debug", False) or os.environ.get(DEBUG_VARIABLE, "") not in ("", "0"):
                traceback.print_exc(file=sys.stderr)
                hint = "please report it with the traceback above"
            else:
                hint = f"please report it; {DEBUG_VARIABLE}=1 (or cellcal --debug) prints the traceback"
            code, message = 1, f"internal error: {type(exc).__name__}: {exc} ({hint})"
        return _error(args, code, message, json_object)


def _classify(exc: Exception) -> tuple[int | None, str, bool]:
    """(exit status, message, whether --json gets an error object) for an exception of ours, or
    for a file that could not be read or written; (None, "", True) for anything else.
    Imported here, not at the top: the command that raised has loaded these modules already."""
    import numpy as np

    from cellcal.cli.common import ReportError, UsageError
    from cellcal.config.reader import ConfigError
    from cellcal.daemon.claims import InUseError
    from cellcal.drivers.interfaces import DeviceError
    from cellcal.measurements.table import DatasetError
    from cellcal.routines.framework.base import RoutineError

    if isinstance(exc, ReportError):  # the result is already on stdout: only the line on stderr
        return 2, f"error: {exc}", False
    if isinstance(exc, (DatasetError, ConfigError, UsageError)):
        return 2, f"error: {exc}", True
    if isinstance(exc, DeviceError):
        return 1, f"device fault, motion stopped: {exc}", True
    if isinstance(exc, InUseError):  # another process holds the store or a device: nothing was done
        return 1, f"in use: {exc}", True
    if isinstance(exc, RoutineError):
        return 1, f"routine failed: {exc}", True
    if isinstance(exc, (ValueError, np.linalg.LinAlgError, RuntimeError, MemoryError)):
        return 1, f"computation failed: {exc or type(exc).__name__}", True
    if isinstance(exc, OSError) and exc.filename is not None:  # a path given that cannot be used
        path = exc.filename if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
        return 2, f"error: {path}: {exc.strerror or exc}", True
    return None, "", True


def _error(args, code: int, message: str, json_object: bool = True) -> int:
    """One line on stderr; with --json also one error object on stdout (docs/cli.md)."""
    print(f"cellcal: {message}", file=sys.stderr)
    if json_object and getattr(args, "json", False):
        print(json.dumps({"error": {"code": code, "message": message}}))
    return code


if __name__ == "__main__":
    sys.exit(main())
