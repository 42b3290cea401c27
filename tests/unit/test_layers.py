"""The layer order of docs/architecture.md, kept by the suite rather than by memory.

``cli → (daemon, reports, …) → routines → (drivers, solvers)``; ``sims → drivers``;
``solvers`` imports nothing of ours; ``config`` (the readers of what people write)
compiles robot models with ``solvers``; ``measurements`` (the measurement CSV and the
vendor importers) is read by everyone above. Only the simulation commands of the
command line (``cli/sim/``) know ``sims``. Every import of every module counts,
including those inside functions, relative (``from ..x``) and absolute
(``cellcal.x``). The installed package maps ``cellcal.X`` onto the top-level folders,
so no static tool sees these arrows without an install; this test does.
"""
from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = ("solvers", "config", "measurements", "programs", "drivers", "sims", "routines", "daemon", "reports",
           "cli")

# folder -> the folders of ours it may import from
ALLOWED = {
    "solvers": set(),
    "config": {"solvers"},
    "measurements": {"solvers"},
    "programs": {"solvers", "config"},  # robot programs read and rewritten (cellcal compensate --program)
    "drivers": {"config"},
    "sims": {"drivers", "solvers", "config"},
    "routines": {"drivers", "solvers", "config", "measurements"},
    "daemon": {"routines", "drivers", "solvers", "config"},
    "reports": {"routines", "solvers", "config", "measurements"},
    "cli": {"daemon", "reports", "routines", "drivers", "solvers", "config", "measurements", "programs", "sims"},
}
# The daemon builds simulated devices by name through the driver registry; only the
# commands that are about simulation (serve the fakes, simulate a campaign, the demo) import sims.
CLI_FOLDER_THAT_MAY_IMPORT_SIMS = "sim"
# A routine gets its devices from the cell file: it may know the interfaces, never an adapter.
ROUTINES_MAY_IMPORT_FROM_DRIVERS = {"interfaces"}

# Inside a folder, its rooms (sub-packages) -> the rooms of the same folder each may import.
# A module directly in the folder (not in a room) is its own room, "" here, above all of them.
# solvers: what knows no robot, then geometry, then what fits it (kinematic identification and
# tool frames side by side), fixtures on identification, the analysis on all of those, and
# compensation of what the analysis adds. routines: the framework never knows a routine.
ROOMS = {
    "solvers": {
        "estimation": set(),
        "geometry": {"estimation"},
        "identification": {"estimation", "geometry"},
        "tool_frames": {"estimation", "geometry"},
        "fixtures": {"estimation", "geometry", "identification"},
        "analysis": {"estimation", "geometry", "identification", "fixtures"},
        "compensation": {"estimation", "geometry", "identification", "analysis"},
    },
    "routines": {
        "framework": set(),
        "": {"framework"},
    },
}


def modules():
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            yield folder, path


def imported(path: Path, folder: str):
    """(top-level folder, module path inside it, line) of every import of ours in `path`."""
    package = [folder, *path.relative_to(ROOT / folder).parent.parts]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                parts = base + (node.module.split(".") if node.module else [])
                if not node.module:  # from . import x, y
                    for alias in node.names:
                        yield parts[0], parts[1:] + [alias.name], node.lineno
                    continue
            elif node.module and node.module.split(".")[0] == "cellcal":
                parts = node.module.split(".")[1:]
            else:
                continue
            yield parts[0], parts[1:], node.lineno
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == "cellcal" and len(parts) > 1:
                    yield parts[1], parts[2:], node.lineno


def room(folder: str, inside: list[str]) -> str:
    """The room of a module at `inside` (its path below the folder, as parts); "" for none."""
    rooms = ROOMS.get(folder, {})
    return inside[0] if len(inside) > 1 and inside[0] in rooms else ""


def violations():
    for folder, path in modules():
        where = path.relative_to(ROOT)
        for target, rest, line in imported(path, folder):
            if target == folder:
                if folder in ROOMS:
                    mine = room(folder, list(path.relative_to(ROOT / folder).parts))
                    if mine not in ROOMS[folder]:
                        yield f"{where}:{line}: a module of {folder}/ outside its rooms ({sorted(ROOMS[folder])})"
                        continue
                    theirs = room(folder, rest + ["x"]) if rest else ""
                    if theirs != mine and theirs not in ROOMS[folder][mine]:
                        yield (f"{where}:{line}: {folder}/{mine or '.'} imports {folder}/{theirs or '.'} "
                               f"(allowed: {sorted(ROOMS[folder][mine]) or 'nothing'})")
                continue
            if target not in ALLOWED[folder]:
                yield f"{where}:{line}: {folder} imports {target} (allowed: {sorted(ALLOWED[folder]) or 'nothing'})"
            elif folder == "cli" and target == "sims" and \
                    path.relative_to(ROOT / folder).parts[0] != CLI_FOLDER_THAT_MAY_IMPORT_SIMS:
                yield f"{where}:{line}: the command line imports sims outside the simulation commands (cli/sim/)"
            elif folder == "routines" and target == "drivers" and (rest[:1] or [""])[0] \
                    not in ROUTINES_MAY_IMPORT_FROM_DRIVERS:
                yield f"{where}:{line}: a routine imports drivers.{'.'.join(rest)}, not only the interfaces"


def test_every_import_follows_the_layer_order():
    found = list(violations())
    assert not found, "\n".join(found)


def test_the_layer_test_sees_imports_of_every_kind(tmp_path, monkeypatch):
    """A check that cannot fail checks nothing: plant each kind of wrong arrow and see it caught."""
    fake_root = tmp_path
    for folder in FOLDERS:
        (fake_root / folder).mkdir()
    (fake_root / "solvers" / "a.py").write_text("def f():\n    from ..daemon import cli\n")
    (fake_root / "drivers" / "b.py").write_text("import cellcal.solvers.geometry.se3\n")
    (fake_root / "daemon" / "cells.py").write_text("from cellcal.sims.inproc.world import SimWorld\n")
    (fake_root / "cli" / "run.py").write_text("from cellcal.sims.net.cell import SimCell\n")
    (fake_root / "cli" / "sim").mkdir()
    (fake_root / "cli" / "sim" / "cell.py").write_text("from cellcal.sims.net.cell import SimCell\n")
    (fake_root / "routines" / "c.py").write_text("from ..drivers.ur.robot import UrRtdeRobot\n")
    (fake_root / "routines" / "d.py").write_text("from ..drivers.interfaces import Robot\nfrom . import e\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", fake_root)
    found = list(violations())
    assert len(found) == 5, found
    for needle in ("solvers imports daemon", "drivers imports solvers", "daemon imports sims",
                   "command line imports sims outside", "drivers.ur.robot"):
        assert any(needle in f for f in found), (needle, found)


def test_the_layer_test_sees_a_wrong_arrow_between_the_rooms_of_a_folder(tmp_path, monkeypatch):
    """Plant, for every room, an import of each room above it (or beside it), and see each caught;
    the allowed arrows of the same files stay quiet."""
    for folder in FOLDERS:
        (tmp_path / folder).mkdir()
    planted = []
    for folder, rooms in ROOMS.items():
        for mine, allowed in rooms.items():
            here = tmp_path / folder / mine if mine else tmp_path / folder
            here.mkdir(exist_ok=True)
            lines = []
            for theirs in rooms:
                if theirs == mine:
                    continue
                module = f"cellcal.{folder}.{theirs}.m" if theirs else f"cellcal.{folder}.m"
                lines.append(f"import {module}")
                if theirs not in allowed:
                    planted.append(f"{folder}/{mine or '.'} imports {folder}/{theirs or '.'}")
            (here / f"planted_{mine or 'top'}.py").write_text("\n".join(lines) + "\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    found = list(violations())
    assert len(found) == len(planted), found
    for needle in planted:
        assert any(needle in f for f in found), (needle, found)


def test_every_room_named_exists_and_every_sub_package_is_a_room():
    for folder, rooms in ROOMS.items():
        packages = {p.parent.name for p in (ROOT / folder).glob("*/__init__.py")}
        assert packages == {r for r in rooms if r}, (folder, packages)


@pytest.mark.parametrize("folder", FOLDERS)
def test_each_layer_has_modules(folder):
    assert any(f == folder for f, _ in modules())
