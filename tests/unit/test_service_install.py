"""``cellcal service install``: the unit and the cell file where the unit expects them, under
--root (never the test machine's own /etc), and the unit as systemd reads it."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cellcal.cli import service
from cellcal.cli.main import main
from support.cell_edits import edited_cell
from cellcal.config.cell_files import shipped_cells

UNIT = Path("etc/systemd/system/cellcal.service")
CELL = Path("etc/cellcal/cell.yaml")
CELLCAL = Path(os.path.abspath(sys.executable)).parent / "cellcal"  # this install's (not resolved)


def install(root: Path, *args: str) -> int:
    return main(["service", "install", "--root", str(root), *args])


def files_under(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def exec_start(unit_text: str) -> str:
    (line,) = re.findall(r"^ExecStart=(.*)$", unit_text, flags=re.M)
    return line


def systemd_verify(unit: Path) -> None:
    """`systemd-analyze verify` on the unit file as installed: exit 0 and nothing said about it
    (unknown keys and bad values are only warnings, so the output counts too). The executable
    must exist on this machine; the unit's user need not."""
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed here (apt-get install systemd)")
    proc = subprocess.run([analyze, "verify", "--man=no", str(unit)], capture_output=True, text=True,
                          timeout=60, env={**os.environ, "SYSTEMD_LOG_COLOR": "0"})
    about_it = [line for line in (proc.stdout + proc.stderr).splitlines() if unit.name in line or str(unit) in line]
    assert proc.returncode == 0 and not about_it, proc.stdout + proc.stderr


@pytest.fixture
def root(tmp_path):
    folder = tmp_path / "root"
    folder.mkdir()
    return folder


def test_installs_the_unit_and_the_cell_where_the_unit_reads_it(root, capsys):
    assert install(root, "--cell", "sim") == 0
    out = capsys.readouterr().out
    unit = (root / UNIT).read_text(encoding="utf-8")
    assert exec_start(unit) == f"{CELLCAL} daemon --cell /etc/cellcal/cell.yaml"
    assert (root / CELL).read_bytes() == shipped_cells()["sim"].read_bytes()
    assert set(files_under(root)) == {str(UNIT), str(CELL)}
    for path in (UNIT, CELL):
        assert (root / path).stat().st_mode & 0o777 == 0o644
        assert f"written  {root / path}" in out
    # the rest of the unit is the shipped one, and it says what comes next
    assert unit == service.unit_template().replace("ExecStart=/opt/cellcal/bin/cellcal ", f"ExecStart={CELLCAL} ")
    for step in ("useradd --system --home /var/lib/cellcal --shell /usr/sbin/nologin cellcal",
                 "systemctl daemon-reload", "systemctl enable --now cellcal"):
        assert step in out
    systemd_verify(root / UNIT)


def test_the_shipped_unit_runs_the_documented_venv_and_reads_the_installed_cell():
    template = service.unit_template()
    assert exec_start(template) == "/opt/cellcal/bin/cellcal daemon --cell /etc/cellcal/cell.yaml"
    assert "install -m" not in template and "/opt/cellcal/.venv" not in template
    page = (Path(__file__).resolve().parents[2] / "docs" / "integrator.md").read_text(encoding="utf-8")
    assert "python3 -m venv /opt/cellcal" in page and "cellcal service install --cell" in page


def test_the_same_cell_again_is_unchanged(root, capsys):
    assert install(root, "--cell", "sim-net") == 0
    before = files_under(root)
    capsys.readouterr()
    assert install(root, "--cell", "sim-net") == 0
    assert f"unchanged  {root / CELL}" in capsys.readouterr().out
    assert files_under(root) == before


def test_a_different_cell_file_is_replaced_only_with_force(root, capsys):
    (root / CELL).parent.mkdir(parents=True)
    (root / CELL).write_text("# the site's own cell\n")
    assert install(root, "--cell", "sim") == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "exists and differs" in err and "--force" in err
    assert files_under(root) == {str(CELL): b"# the site's own cell\n"}  # the unit was not written either

    assert install(root, "--cell", "sim", "--force") == 0
    assert f"replaced  {root / CELL}" in capsys.readouterr().out
    assert (root / CELL).read_bytes() == shipped_cells()["sim"].read_bytes()


def test_a_stale_unit_is_rewritten_without_force(root, capsys):
    (root / UNIT).parent.mkdir(parents=True)
    (root / UNIT).write_text("[Service]\nExecStart=/opt/cellcal/.venv/bin/cellcal daemon\n")
    assert install(root, "--cell", "sim") == 0
    assert f"replaced  {root / UNIT}" in capsys.readouterr().out
    assert exec_start((root / UNIT).read_text()).startswith(str(CELLCAL))


@pytest.mark.parametrize("cell, says", [
    ("no-such-cell", "no-such-cell: no such file, and not a shipped cell (shipped: sim,"),
    ("bad.yaml", "bad.yaml: section [limits] is missing"),
    ("broken.yaml", "broken.yaml:3: not valid YAML"),
])
def test_bad_input_is_one_message_exit_2_and_nothing_written(root, tmp_path, monkeypatch, capsys, cell, says):
    monkeypatch.chdir(tmp_path)
    text = shipped_cells()["sim"].read_text()
    (tmp_path / "bad.yaml").write_text(re.sub(r"(?ms)^limits:.*?(?=^\S)", "", text))
    (tmp_path / "broken.yaml").write_text("cell:\n  name: [unclosed\n")
    assert install(root, "--cell", cell) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"cellcal: error: {says}"), err
    assert files_under(root) == {}


def test_bad_root_and_missing_cell_option_are_bad_usage(tmp_path, capsys):
    assert install(tmp_path / "missing", "--cell", "sim") == 2
    assert "--root" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        main(["service", "install"])
    assert stop.value.code == 2
    assert "--cell" in capsys.readouterr().err


def test_a_cell_whose_ur_driver_this_install_cannot_run_is_refused(root, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "rtde_control", None)
    assert install(root, "--cell", "sim-net") == 2
    assert "[drivers.robot.driver]: the UR driver needs ur_rtde: pip install 'cellcal[ur]'" in capsys.readouterr().err
    assert files_under(root) == {}


def test_a_model_file_the_cell_names_by_a_relative_path_goes_beside_it(root, tmp_path, capsys):
    site = tmp_path / "site"
    (site / "models").mkdir(parents=True)
    shutil.copy(shipped_cells()["sim"].parent.parent / "robots" / "ur10e.yaml", site / "models" / "ur10e-cal.yaml")
    edited_cell(site, "sim", {"cell": {"robot": "models/ur10e-cal.yaml"}}, name="my-cell.yaml")
    assert install(root, "--cell", str(site / "my-cell.yaml")) == 0
    assert "etc/cellcal/models/ur10e-cal.yaml" in capsys.readouterr().out
    from cellcal.daemon.cells import load_cell
    installed = load_cell(root / CELL)  # finds its model where the daemon will look
    assert installed.robot == str(root / "etc/cellcal/models/ur10e-cal.yaml")

    edited_cell(site, "sim", {"cell": {"robot": "../site/models/ur10e-cal.yaml"}}, name="outside.yaml")
    assert install(tmp_path / "root", "--cell", str(site / "outside.yaml"), "--force") == 2
    assert "outside the cell file's folder" in capsys.readouterr().err


def test_exec_start_is_quoted_when_the_install_path_needs_it(tmp_path):
    program = tmp_path / "opt 100%" / "bin" / "cellcal"
    program.parent.mkdir(parents=True)
    program.write_text("#!/bin/sh\n")
    program.chmod(0o755)
    unit = service.render_unit(program)
    quoted = str(program).replace("%", "%%")
    assert exec_start(unit) == f'"{quoted}" daemon --cell /etc/cellcal/cell.yaml'
    path = tmp_path / "cellcal.service"
    path.write_text(unit)
    systemd_verify(path)
