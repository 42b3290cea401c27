"""What the wheel is made of, checked against the source tree, so a new subpackage or data file
cannot be forgotten (tests/e2e/test_install.py builds and installs the wheel itself).

pyproject.toml maps ``cellcal.X`` onto each top-level folder (``package-dir``) and lists the
packages one by one; setuptools ships exactly those packages' modules and the files that
``package-data`` names, nothing else (``include-package-data = false``).
"""
from __future__ import annotations

import glob
import re
import sys
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
SETUPTOOLS = PYPROJECT["tool"]["setuptools"]
# top-level folders with an __init__.py that are not part of the product
NOT_SHIPPED = {"tests", "bench"}


def _rooms() -> dict[str, Path]:
    """package -> folder, from package-dir (``cellcal.cli`` -> ``cli``)."""
    return {package: ROOT / folder for package, folder in SETUPTOOLS["package-dir"].items()}


def _source_files(folder: Path):
    for path in sorted(folder.rglob("*")):
        if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc":
            yield path


def _package_of(path: Path) -> tuple[str, Path]:
    """The package a file belongs to (the nearest folder above it with an __init__.py) and its folder."""
    for package, room in _rooms().items():
        if room in path.parents:
            folder = path.parent
            while not (folder / "__init__.py").exists():
                folder = folder.parent
            return ".".join([package, *folder.relative_to(room).parts]), folder
    raise AssertionError(f"{path} is in no room of package-dir")


def test_every_top_level_package_folder_is_a_room_of_package_dir():
    folders = {p.parent.name for p in ROOT.glob("*/__init__.py")} - NOT_SHIPPED
    mapped = set(SETUPTOOLS["package-dir"].values())
    assert folders == mapped, "a top-level package folder is not mapped onto cellcal.X in pyproject.toml " \
                              f"(or a mapped one has no __init__.py): {sorted(folders ^ mapped)}"
    assert all(package == f"cellcal.{folder}" for package, folder in SETUPTOOLS["package-dir"].items())


def test_the_packages_list_is_every_folder_with_an_init_under_the_rooms():
    found = {".".join([package, *init.parent.relative_to(room).parts])
             for package, room in _rooms().items() for init in room.rglob("__init__.py")}
    listed = set(SETUPTOOLS["packages"])
    assert not found - listed, f"add to [tool.setuptools] packages in pyproject.toml: {sorted(found - listed)}"
    assert not listed - found, f"listed in pyproject.toml but no folder with an __init__.py: {sorted(listed - found)}"
    assert SETUPTOOLS["packages"] == sorted(SETUPTOOLS["packages"]), "keep the packages list sorted"


def test_a_folder_of_modules_has_an_init_py():
    """Without one its modules would never ship (setuptools takes only the listed packages)."""
    lost = sorted(str(folder.relative_to(ROOT)) for room in _rooms().values()
                  for folder in [room, *(p for p in room.rglob("*") if p.is_dir())]
                  if "__pycache__" not in folder.parts and any(folder.glob("*.py"))
                  and not (folder / "__init__.py").exists())
    assert not lost, f"folders with modules but no __init__.py: {lost}"


def test_every_data_file_under_the_rooms_is_covered_by_package_data():
    """A file other than a module ships only if package-data names it (a data folder is no
    package of its own: it belongs to the package above it)."""
    package_data = PYPROJECT["tool"]["setuptools"].get("package-data", {})
    assert SETUPTOOLS.get("include-package-data") is False, \
        "include-package-data must stay off: the wheel gets package-data only, MANIFEST.in is for the sdist"
    uncovered = []
    for room in _rooms().values():
        for path in _source_files(room):
            if path.suffix == ".py":
                continue
            package, folder = _package_of(path)
            shipped = {Path(folder, match).resolve() for pattern in package_data.get(package, ())
                       for match in glob.glob(pattern, root_dir=folder)}
            if path.resolve() not in shipped:
                uncovered.append(f"{path.relative_to(ROOT)} (package {package})")
    assert not uncovered, f"add to [tool.setuptools.package-data] in pyproject.toml: {uncovered}"


def test_what_the_program_reads_at_run_time_is_package_data():
    """The shipped robots and cells are found through importlib.resources, the unit too."""
    from cellcal.cli.service import unit_template
    from cellcal.config.cell_files import shipped_cells
    from cellcal.config.robot_files import shipped_robots

    assert {"ur10e", "ur5e", "abb-irb4600"} <= set(shipped_robots())
    assert {"sim", "sim-net"} <= set(shipped_cells())
    assert "ExecStart=" in unit_template()


def test_metadata_has_no_deprecated_forms():
    """An SPDX license string (PEP 639) and a setuptools floor that understands it."""
    assert isinstance(PYPROJECT["project"]["license"], str)
    (backend,) = [Requirement(r) for r in PYPROJECT["build-system"]["requires"] if r.startswith("setuptools")]
    assert not backend.specifier.contains("76.9") and backend.specifier.contains("77.0.0")


def _lock() -> dict[str, str]:
    pins = {}
    for line in (ROOT / "requirements.lock").read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.startswith("#"):
            name, version = re.fullmatch(r"([A-Za-z0-9._-]+)==(\S+)", line.strip()).groups()
            pins[re.sub(r"[-_.]+", "-", name).lower()] = version
    return pins


def test_the_lock_file_pins_every_requirement_within_pyproject_ranges():
    """requirements.lock pins one tested point inside the ranges pyproject.toml keeps."""
    pins = _lock()
    project = PYPROJECT["project"]
    wanted = [*project["dependencies"], *project["optional-dependencies"]["dev"],
              *project["optional-dependencies"]["ur"], *PYPROJECT["build-system"]["requires"]]
    for text in wanted:
        req = Requirement(text)
        name = re.sub(r"[-_.]+", "-", req.name).lower()
        assert name in pins, f"{req.name} is not pinned in requirements.lock (make lock)"
        assert req.specifier.contains(pins[name], prereleases=True), \
            f"requirements.lock pins {req.name}=={pins[name]}, outside pyproject's {text!r} (make lock)"


def test_without_the_ur_extra_the_ur_driver_says_what_to_install(monkeypatch):
    """Before anything is opened, and placed in the cell file as any driver problem."""
    from cellcal.daemon.cells import CellFileError, load_cell, open_drivers
    from cellcal.drivers.registry import DriverConfigError
    from cellcal.drivers.ur.robot import UrRtdeRobot

    monkeypatch.setitem(sys.modules, "rtde_control", None)  # what find_spec reports for a missing module
    with pytest.raises(DriverConfigError) as refused:
        UrRtdeRobot("192.0.2.1")  # TEST-NET: nothing would answer there
    assert refused.value.problem == "the UR driver needs ur_rtde: pip install 'cellcal[ur]'"
    with pytest.raises(CellFileError, match=r"sim-net.yaml: \[drivers.robot.driver\]: the UR driver needs "
                                            r"ur_rtde: pip install 'cellcal\[ur\]'$"):
        open_drivers(load_cell("sim-net"))
