"""``cellcal service install --cell CELL [--root DIR] [--force]``: the daemon as a systemd service.

Puts the two files the service needs where its unit expects them:

* ``ROOT/etc/systemd/system/cellcal.service``: the unit that ships with cellcal
  (``config/cellcal.service``), its ``ExecStart`` pointing at the ``cellcal`` executable of
  the install this command runs from (the venv's ``bin/``, e.g. ``/opt/cellcal/bin/cellcal``);
* ``ROOT/etc/cellcal/cell.yaml``: the cell file, a path or the name of a shipped cell, with
  any robot model file it names by a relative path beside it (the cell file finds its model
  files relative to itself).

The cell file is loaded and checked first, as the daemon would load it, including that
this install can run its drivers (``ur_rtde`` needs the ``ur`` extra). A different cell file
(or model file) already in place is replaced only with ``--force``; an identical one is
left as it is. The unit is cellcal's own and is always rewritten: local changes belong in a
drop-in (``systemctl edit cellcal``). Bad input: one message, exit status 2, nothing written.
ROOT (default ``/``) lets an image or a test be prepared; the unit's paths stay those of
the running system.
"""
from __future__ import annotations

import os
import re
import sys
import tempfile
from dataclasses import dataclass
from importlib import resources
from pathlib import Path, PurePosixPath

from cellcal.cli.common import UsageError
from cellcal.config.cell_files import resolve_cell
from cellcal.config.cells import CellFileError
from cellcal.config.reader import read_yaml
from cellcal.daemon.cells import load_cell
from cellcal.drivers import registry
from cellcal.drivers.registry import DriverConfigError

UNIT_NAME = "cellcal.service"
UNIT_PATH = PurePosixPath("/etc/systemd/system") / UNIT_NAME
CELL_PATH = PurePosixPath("/etc/cellcal/cell.yaml")  # the unit's `cellcal daemon --cell`
STATE_DIR = "/var/lib/cellcal"  # the unit's StateDirectory=cellcal


@dataclass
class _File:
    dest: Path  # under ROOT
    content: bytes
    replaceable: bool  # ours (the unit): rewritten; the site's (cell, models): only with --force
    what: str


def unit_template() -> str:
    """The unit file as shipped."""
    return (resources.files("cellcal.config") / UNIT_NAME).read_text(encoding="utf-8")


def executable() -> Path:
    """The ``cellcal`` console script of the running install: beside its Python, unresolved
    (a venv's ``bin/python`` is a link to the system's interpreter, its ``cellcal`` is not)."""
    return Path(os.path.abspath(sys.executable)).parent / "cellcal"


def _systemd_word(text: str) -> str:
    """One word of a unit's command line: quoted when needed, specifiers and variables escaped."""
    text = text.replace("%", "%%").replace("$", "$$")
    if re.fullmatch(r"[A-Za-z0-9_@%+=:,./-]+", text):
        return text
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def render_unit(cellcal: Path | str) -> str:
    """The shipped unit with ExecStart running `cellcal`."""
    text = unit_template()
    starts = re.findall(r"^ExecStart=(\S+)", text, flags=re.M)
    if len(starts) != 1 or f" daemon --cell {CELL_PATH}" not in text:
        raise RuntimeError(f"the shipped {UNIT_NAME} has no single `ExecStart=... daemon --cell {CELL_PATH}`")
    return re.sub(r"^ExecStart=\S+", lambda _: f"ExecStart={_systemd_word(str(cellcal))}", text, flags=re.M)


def _unit_user(unit: str) -> str:
    found = re.search(r"^User=(\S+)", unit, flags=re.M)
    return found.group(1) if found else "root"


def _model_files(cell_file: Path) -> list[str]:
    """Robot model files the cell file names by a relative path (the loader reads them beside
    it), as written."""
    doc = read_yaml(cell_file, CellFileError)
    arms = [("cell", doc.get("cell") or {})]
    arms += [(f"robots.{name}", spec or {}) for name, spec in (doc.get("robots") or {}).items()]
    files = []
    for section, spec in arms:
        robot = str(spec.get("robot", ""))
        if not ("/" in robot or robot.endswith((".yaml", ".yml"))) or PurePosixPath(robot).is_absolute():
            continue  # a shipped model, or a file that stays where it is
        if ".." in PurePosixPath(robot).parts:
            raise CellFileError(f"{robot}: a model file outside the cell file's folder would not be found "
                                f"beside {CELL_PATH}; move it beside the cell file, or give its absolute path",
                                source=str(cell_file), section=section, key="robot")
        files.append(robot)
    return files


def _check_drivers_installed(cell) -> None:
    """What the daemon would find missing when it opens the devices (an extra not installed)."""
    places = [(f"drivers.{kind}", kind, spec) for kind, spec in cell.drivers.items()]
    places += [(f"robots.{name}.driver", "robot", r.driver) for name, r in cell.robots.items() if name != "a"]
    for section, kind, spec in places:
        check = getattr(registry.factory(kind, spec.name), "check_installed", None)
        if check is None:
            continue
        try:
            check()
        except DriverConfigError as exc:
            raise exc.located(cell.path, section, CellFileError) from None


def _writable(folder: Path) -> bool:
    """Whether `folder` can be written or made: its nearest existing ancestor is a writable folder."""
    while not folder.exists():
        folder = folder.parent
    return folder.is_dir() and os.access(folder, os.W_OK | os.X_OK)


def _write(file: _File) -> None:
    """Atomically: a partial unit or cell file never stands in its place."""
    file.dest.parent.mkdir(parents=True, exist_ok=True, mode=0o755)
    with tempfile.NamedTemporaryFile(dir=file.dest.parent, prefix=f".{file.dest.name}.", delete=False) as out:
        out.write(file.content)
    try:
        os.chmod(out.name, 0o644)
        os.replace(out.name, file.dest)
    except BaseException:
        os.unlink(out.name)
        raise


def install(cell: str, root: str = "/", force: bool = False) -> list[tuple[str, _File]]:
    """Check everything, then write; (what happened, file) per file. UsageError or
    CellFileError, with nothing written, when something is wrong."""
    top = Path(root)
    if not top.is_dir():
        raise UsageError(f"--root {root}: no such folder")
    source = resolve_cell(cell)
    loaded = load_cell(source)  # CellFileError naming file, section and key
    _check_drivers_installed(loaded)
    program = executable()
    if not (program.is_file() and os.access(program, os.X_OK)):
        raise UsageError(f"no cellcal executable beside {sys.executable} ({program}): run `cellcal service "
                         f"install` from the venv cellcal is installed in (docs/integrator.md: Installing on the cell PC)")

    def under_root(path: PurePosixPath) -> Path:
        return top / path.relative_to("/")

    unit = render_unit(program)
    files = [_File(under_root(UNIT_PATH), unit.encode(), True, "unit"),
             _File(under_root(CELL_PATH), source.read_bytes(), False, "cell file")]
    for model in _model_files(source):
        files.append(_File(under_root(CELL_PATH.parent / model), (source.parent / model).read_bytes(), False,
                           "robot model"))

    plan, refused = [], []
    for file in files:
        if file.dest.is_dir():
            raise UsageError(f"{file.dest}: is a folder; nothing written")
        if not file.dest.exists():
            plan.append(("written", file))
        elif file.dest.read_bytes() == file.content:
            plan.append(("unchanged", file))
        elif file.replaceable or force:
            plan.append(("replaced", file))
        else:
            refused.append(file)
    if refused:
        names = ", ".join(str(f.dest) for f in refused)
        raise UsageError(f"{names}: exists and differs from what {cell} installs; nothing written "
                         f"(--force replaces it)")
    for _, file in plan:
        if not _writable(file.dest.parent):
            raise UsageError(f"{file.dest.parent}: not writable (run as root, or give --root); nothing written")
    for action, file in plan:
        if action != "unchanged":
            try:
                _write(file)
            except OSError as exc:
                raise UsageError(f"{file.dest}: cannot write: {exc.strerror or exc}") from None
    return plan


def cmd_service_install(args) -> int:
    plan = install(args.cell, args.root, args.force)
    unit = next(f for _, f in plan if f.what == "unit")
    width = max(len(action) for action, _ in plan)
    print(f"cellcal service install: cell {args.cell}")
    for action, file in plan:
        print(f"  {action:<{width}}  {file.dest}  ({file.what})")
    start = re.search(r"^ExecStart=.*$", unit.content.decode(), flags=re.M).group(0)
    print(f"  {start}")
    user = _unit_user(unit.content.decode())
    where = "" if Path(args.root).resolve() == Path("/") else f" (on the system whose root is {args.root})"
    print(f"next, as root{where}:")
    print(f"  id {user} >/dev/null 2>&1 || useradd --system --home {STATE_DIR} --shell /usr/sbin/nologin {user}")
    print("  systemctl daemon-reload")
    print("  systemctl enable --now cellcal")
    print("  journalctl -u cellcal -f     # what it says")
    return 0


def add_parser(sub) -> None:
    service = sub.add_parser("service", help="install the daemon as a systemd service on this machine",
                             description="The daemon as a systemd service.").add_subparsers(dest="what",
                                                                                           required=True)
    p = service.add_parser("install", help="write the systemd unit and the cell file where the unit reads it",
                           description=f"Check the cell file, then write {UNIT_PATH} (ExecStart: this install's "
                                       f"cellcal) and {CELL_PATH}. Nothing is written when anything is wrong.")
    p.add_argument("--cell", required=True, metavar="CELL",
                   help="cell file, or the name of a shipped cell")
    p.add_argument("--root", default="/", metavar="DIR",
                   help="write below DIR instead of / (an image; the unit's paths stay those of the running "
                        "system)")
    p.add_argument("--force", action="store_true",
                   help="replace a different cell file (or robot model file) already installed")
    p.set_defaults(func=cmd_service_install)
