"""The command table: every sub-command is listed without being imported, and runs from its module."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from cellcal.cli import main as cli


def _registered_help(name: str) -> str:
    """The one-line help the command's own module registers."""
    sub = argparse.ArgumentParser().add_subparsers()
    module = __import__(cli.COMMANDS[name][0], fromlist=["add_parser"])
    module.add_parser(sub)
    (action,) = [a for a in sub._choices_actions if a.dest == name]
    return action.help


@pytest.mark.parametrize("name", sorted(cli.COMMANDS))
def test_the_table_lists_each_command_with_the_help_its_module_registers(name):
    assert cli.COMMANDS[name][1] == _registered_help(name)


def test_every_module_of_the_cli_room_is_a_command_or_shared():
    """A new sub-command module that is not in the table would never run."""
    from pathlib import Path
    room = Path(cli.__file__).parent
    modules = {".".join(("cellcal", *p.relative_to(room.parent).with_suffix("").parts))
               for p in room.rglob("*.py") if p.name not in ("__init__.py", "__main__.py")}
    shared = {"cellcal.cli.main", "cellcal.cli.common", "cellcal.cli.model_out", "cellcal.cli.discriminate",
              "cellcal.cli.identify_points",
              "cellcal.cli.sim.iso9283_campaign"}
    assert modules - shared == {m for m, _ in cli.COMMANDS.values()}


def test_help_imports_no_command_and_no_heavy_library():
    code = ("import sys\nfrom cellcal.cli.main import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "import json\nprint(json.dumps(sorted(sys.modules)), file=sys.stderr)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    loaded = set(json.loads(proc.stderr.strip().splitlines()[-1]))
    assert "sim-campaign" in proc.stdout and "identify" in proc.stdout
    heavy = {"numpy", "scipy", "matplotlib", "pymodbus", "yaml", "serial", "can"} & loaded
    ours = {m for m in loaded if m.startswith("cellcal.") and m not in ("cellcal.cli", "cellcal.cli.main")}
    assert not heavy and not ours, (heavy, ours)


def test_version_is_the_installed_distributions(capsys):
    from importlib import metadata
    with pytest.raises(SystemExit) as stop:
        cli.main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip() == f"cellcal {metadata.version('cellcal')}"


def test_an_unknown_command_is_bad_usage(capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(["idnetify", "--robot", "ur10e"])
    assert stop.value.code == 2
    assert "invalid choice: 'idnetify'" in capsys.readouterr().err


def test_a_command_runs_with_only_its_own_module_loaded_for_parsing():
    parser = cli.build_parser("identify")
    args = parser.parse_args(["identify", "--robot", "ur10e", "--data", "x.csv"])
    assert args.func.__module__ == "cellcal.cli.identify"
