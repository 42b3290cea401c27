"""The product as it ships: the sdist and the wheel built from a copy of the source tree (as
`make wheel` builds it), the wheel installed into a fresh venv, and its `cellcal` run from a
folder outside the repository.

The venv is made with ``--without-pip``, the wheel goes in with ``--no-deps``, and the
dependencies come from this test's own environment (the dev venv) through a ``.pth`` line
naming its site-packages: Python reads the ``.pth`` files of the venv's own site-packages
only, so the dev venv's editable-install finder (``__editable__...pth``) never runs, and the
venv's site-packages come first on ``sys.path``, so the wheel's cellcal (and its metadata)
win. That keeps the case at seconds, offline; the test checks that every module it imports
comes from the venv.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import tomllib
import zipfile
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
VERSION = PYPROJECT["project"]["version"]
# at the top of the repository: what a build must not see (a stale build/ would be packed)
NOT_SOURCE = {".git", ".venv", "build", "dist", "out", ".pytest_cache", ".hypothesis", "cellcal.egg-info"}
# what the sdist carries besides the packages (MANIFEST.in)
SDIST_EXTRAS = ("pyproject.toml", "README.md", "MANIFEST.in", "Makefile", "requirements.lock")


def _ignore(folder: str, names: list[str]) -> set[str]:
    top = Path(folder) == REPO
    return {n for n in names if n == "__pycache__" or n.endswith(".pyc") or (top and n in NOT_SOURCE)}


def _room_files(tree: Path) -> set[str]:
    """Every file of the product in a source tree, as the wheel names it (``cli/main.py`` ->
    ``cellcal/cli/main.py``): modules and data alike (test_packaging keeps package-data
    covering every file under the rooms)."""
    files = set()
    for package, folder in PYPROJECT["tool"]["setuptools"]["package-dir"].items():
        for path in (tree / folder).rglob("*"):
            if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc":
                files.add("/".join([*package.split("."), *path.relative_to(tree / folder).parts]))
    return files


def _run(args, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=kw.pop("timeout", 180),
                          **kw)
    assert proc.returncode == 0, f"{' '.join(map(str, args))}: exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return proc


def _backend_here() -> None:
    """The build backend of pyproject.toml in this environment, so nothing is fetched."""
    for text in PYPROJECT["build-system"]["requires"]:
        req = Requirement(text)
        try:
            found = metadata.version(req.name)
        except metadata.PackageNotFoundError:
            found = None
        if found is None or not req.specifier.contains(found):
            pytest.fail(f"this environment has {req.name} {found}, the build needs {text}: run `make` "
                        f"(requirements.lock pins it)")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """(source copy, wheel, sdist, wheel built from the sdist)."""
    _backend_here()
    work = tmp_path_factory.mktemp("build")
    source = work / "src"
    shutil.copytree(REPO, source, ignore=_ignore)
    pip_wheel = [sys.executable, "-m", "pip", "-qq", "wheel", "--no-deps", "--no-index", "--no-build-isolation",
                 "--check-build-dependencies"]
    _run([*pip_wheel, "-w", work / "wheel", "."], cwd=source)
    _run([sys.executable, "-c", "import sys; from setuptools import build_meta; build_meta.build_sdist(sys.argv[1])",
          work / "sdist"], cwd=source)
    (sdist,) = (work / "sdist").glob("*.tar.gz")
    _run([*pip_wheel, "-w", work / "from-sdist", sdist], cwd=work)
    (wheel,) = (work / "wheel").glob("*.whl")
    (again,) = (work / "from-sdist").glob("*.whl")
    return source, wheel, sdist, again


def _wheel_files(wheel: Path) -> set[str]:
    with zipfile.ZipFile(wheel) as z:
        return {n for n in z.namelist() if not n.split("/")[0].endswith(".dist-info")}


def test_the_wheel_holds_every_module_and_data_file_of_the_source_tree_and_nothing_else(built):
    source, wheel, _, _ = built
    assert wheel.name == f"cellcal-{VERSION}-py3-none-any.whl"
    expected, shipped = _room_files(source), _wheel_files(wheel)
    assert not expected - shipped, f"missing from the wheel: {sorted(expected - shipped)}"
    assert not shipped - expected, f"in the wheel but not in the source tree: {sorted(shipped - expected)}"
    with zipfile.ZipFile(wheel) as z:
        meta = z.read(f"cellcal-{VERSION}.dist-info/METADATA").decode()
        entry_points = z.read(f"cellcal-{VERSION}.dist-info/entry_points.txt").decode()
    assert "License-Expression: Apache-2.0" in meta and "Provides-Extra: ur" in meta
    assert "cellcal = cellcal.cli.main:main" in entry_points


def test_the_sdist_holds_the_source_and_builds_the_same_wheel(built):
    source, wheel, sdist, again = built
    with tarfile.open(sdist) as tar:
        names = {n.split("/", 1)[1] for n in tar.getnames() if "/" in n}
    rooms = PYPROJECT["tool"]["setuptools"]["package-dir"]
    in_tree = {str(Path(rooms[f"cellcal.{f.split('/')[1]}"], *f.split("/")[2:])) for f in _room_files(source)}
    tests = {str(p.relative_to(source)) for p in (source / "tests").rglob("*.py")}
    missing = (in_tree | tests | set(SDIST_EXTRAS)) - names
    assert not missing, f"missing from the sdist: {sorted(missing)}"
    assert _wheel_files(again) == _wheel_files(wheel)


@pytest.fixture(scope="module")
def venv(built, tmp_path_factory):
    """A fresh venv with the wheel alone installed, the dev venv's packages visible behind it."""
    _, wheel, _, _ = built
    folder = tmp_path_factory.mktemp("venv") / "cellcal"
    _run([sys.executable, "-m", "venv", "--without-pip", folder])
    python = folder / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", python, "-qq", "install", "--no-deps", "--no-index", wheel])
    site = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip())
    assert site.is_relative_to(folder)
    dev = dict.fromkeys(sysconfig.get_paths()[k] for k in ("purelib", "platlib"))
    (site / "zz-dev-venv-dependencies.pth").write_text("".join(f"{p}\n" for p in dev))
    return folder, site


@pytest.fixture(scope="module")
def outside(tmp_path_factory):
    folder = tmp_path_factory.mktemp("elsewhere")
    assert not folder.resolve().is_relative_to(REPO)
    return folder


def _env(venv_folder: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON") and k != "VIRTUAL_ENV"}
    env["PATH"] = f"{venv_folder / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    return env


def cellcal(venv, outside, *args, timeout=180) -> subprocess.CompletedProcess:
    folder, _ = venv
    return _run([folder / "bin" / "cellcal", *args], cwd=outside, env=_env(folder), timeout=timeout)


PROVENANCE = r"""
import importlib, json, sys
from importlib import metadata
import cellcal
from cellcal.config.cell_files import shipped_cells
from cellcal.config.robot_files import shipped_robots
files = {m: importlib.import_module(m).__file__ for m in json.loads(sys.argv[1])}
print(json.dumps({
    "namespace": list(cellcal.__path__), "files": files,
    "metadata": str(metadata.distribution("cellcal").locate_file("cellcal")),
    "version": metadata.version("cellcal"),
    "shipped": [str(p) for p in [*shipped_cells().values(), *shipped_robots().values()]],
    "finders": [type(f).__module__ for f in sys.meta_path],
}))
"""


def test_every_module_imports_from_the_venv_not_from_the_repository(built, venv, outside):
    _, wheel, _, _ = built
    folder, site = venv
    modules = sorted(n[:-3].replace("/", ".").removesuffix(".__init__") for n in _wheel_files(wheel)
                     if n.endswith(".py") and not n.endswith("__main__.py"))
    proc = _run([folder / "bin" / "python", "-c", PROVENANCE, json.dumps(modules)], cwd=outside, env=_env(folder))
    found = json.loads(proc.stdout)
    assert found["namespace"] == [str(site / "cellcal")]
    elsewhere = {m: f for m, f in found["files"].items() if not Path(f).is_relative_to(site)}
    assert not elsewhere, f"imported from outside the venv: {elsewhere}"
    assert len(found["files"]) == len(modules)
    assert Path(found["metadata"]).is_relative_to(site) and found["version"] == VERSION
    assert found["shipped"] and all(Path(p).is_relative_to(site) for p in found["shipped"])
    assert not any("editable" in f for f in found["finders"]), found["finders"]


def test_version_and_help_from_outside_the_repository(venv, outside):
    assert cellcal(venv, outside, "--version").stdout.strip() == f"cellcal {VERSION}"
    assert "service" in cellcal(venv, outside, "--help").stdout


def test_a_routine_runs_on_the_simulated_cell_and_finds_the_frame(venv, outside):
    result = json.loads(cellcal(venv, outside, "run", "tcp-laser", "--cell", "sim", "--json", "--out", "runs").stdout)
    assert result["routine"] == "tcp-laser" and result["passed_gates"] is True, result.get("reasons")
    assert all(g["passed"] for g in result["gates"])
    frame = result["tool_frame"]
    assert abs(frame["z_mm"] - 150.0) < 5.0  # the drawn 150 mm pin, as found
    assert result["sim_truth"]["position_error_mm"] < 0.1
    assert (outside / result["dataset"]).is_file() and Path(result["dataset"]).parts[0] == "runs"


def test_a_shipped_robot_is_identified_from_generated_data(venv, outside):
    cellcal(venv, outside, "sim-data", "--robot", "ur10e", "--poses", "60", "--seed", "3", "-o", "x.csv")
    found = json.loads(cellcal(venv, outside, "identify", "--robot", "ur10e", "--data", "x.csv", "--json").stdout)
    assert found["success"] is True and found["parameters"]


def test_service_install_points_the_unit_at_the_venv(venv, outside):
    folder, _ = venv
    root = outside / "root"
    root.mkdir()
    out = cellcal(venv, outside, "service", "install", "--cell", "sim", "--root", root).stdout
    unit = root / "etc/systemd/system/cellcal.service"
    assert f"ExecStart={folder}/bin/cellcal daemon --cell /etc/cellcal/cell.yaml" in unit.read_text().splitlines()
    assert (root / "etc/cellcal/cell.yaml").is_file() and "systemctl enable --now cellcal" in out
    analyze = shutil.which("systemd-analyze")
    if analyze:  # the unit as systemd reads it, its ExecStart the venv's real executable
        proc = subprocess.run([analyze, "verify", "--man=no", str(unit)], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0 and "cellcal.service" not in proc.stdout + proc.stderr, proc.stderr
