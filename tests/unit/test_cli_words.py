"""What the command line says: help for every argument, ``--version``, one JSON object on
stdout for every outcome under ``--json`` (argparse's refusals, files that cannot be used,
defects), the records' JSON, the words of a run's verdict, counts in the right number, and
the routine selector values wherever the docs list them (issue 18, section 6).
"""
from __future__ import annotations

import argparse
import json
import re
from importlib import metadata
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cellcal.cli import main as cli
from cellcal.cli.main import build_parser, main

ROOT = Path(__file__).resolve().parents[2]


# -- help for every argument --------------------------------------------------------------------------------


def arguments_without_help(parser: argparse.ArgumentParser, path: str = "cellcal") -> list[str]:
    """Every argument, option and sub-command of `parser` (and its sub-parsers) that --help
    would list without a line saying what it is. ``--version`` after a command is left out of
    the help on purpose (it is the top level's)."""
    missing = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helped = {choice.dest: choice.help for choice in action._choices_actions}
            for name, sub in action.choices.items():
                if not helped.get(name):
                    missing.append(f"{path} {name}")
                missing += arguments_without_help(sub, f"{path} {name}")
        elif isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            continue
        elif not action.help or action.help == argparse.SUPPRESS:
            missing.append(f"{path} {'/'.join(action.option_strings) or action.dest}")
    return missing


def test_every_argument_of_every_command_has_help():
    parser = build_parser(every=True)
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert set(commands) == set(cli.COMMANDS)  # the walk reaches every command in the table
    assert arguments_without_help(parser) == []


def test_the_help_check_finds_an_argument_without_help():
    parser = argparse.ArgumentParser(prog="cellcal")
    runs = parser.add_subparsers().add_parser("runs", help="records").add_subparsers()
    p = runs.add_parser("list", help="the runs")
    p.add_argument("--limit", type=int, help="how many")
    p.add_argument("--json", action="store_true")
    runs.add_parser("show")
    assert arguments_without_help(parser) == ["cellcal runs list --json", "cellcal runs show"]


@pytest.mark.parametrize("argv", [["--version"], ["daemon", "--version"], ["runs", "list", "--version"],
                                  ["run", "--version"]])
def test_version_at_the_top_and_after_a_command(argv, capsys):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip() == f"cellcal {metadata.version('cellcal')}"


# -- one JSON object for every outcome ------------------------------------------------------------------------


@pytest.mark.parametrize("argv,fragment", [
    (["run", "--json"], "the following arguments are required: ROUTINE"),
    (["identify", "--robot", "ur10e", "--json"], "--data"),
    (["identify", "--robot", "ur10e", "--data", "x.csv", "--regularize", "maybe", "--json"], "invalid choice"),
    (["runs", "show", "seven", "--json"], "argument ID"),  # not a number
    (["runs", "list", "--jso", "--colour"], "unrecognized arguments: --colour"),  # an abbreviation of --json
    (["--json"], "the following arguments are required: COMMAND"),
])
def test_an_argparse_refusal_with_json_prints_one_error_object(argv, fragment, capsys):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    out, err = capsys.readouterr()
    assert stop.value.code == 2
    line = err.strip()
    assert len(err.splitlines()) == 1 and fragment in line and "Traceback" not in err
    assert json.loads(out) == {"error": {"code": 2, "message": line}}


def test_an_argparse_refusal_without_json_leaves_stdout_empty(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["run"])
    out, err = capsys.readouterr()
    assert stop.value.code == 2 and out == "" and err.startswith("cellcal run: error: ")


def _ends(exc: BaseException, capsys, monkeypatch, *options: str, debug_env: str | None = None):
    """What `cellcal [options] runs list --json` does when the command raises `exc`."""
    if debug_env is None:
        monkeypatch.delenv("CELLCAL_DEBUG", raising=False)
    else:
        monkeypatch.setenv("CELLCAL_DEBUG", debug_env)

    def raiser(args):
        raise exc

    monkeypatch.setattr("cellcal.cli.runs.cmd_runs_list", raiser)
    status = main([*options, "runs", "list", "--json"])
    out, err = capsys.readouterr()
    return status, json.loads(out), err


@pytest.mark.parametrize("exc,why", [
    (FileNotFoundError(2, "No such file or directory", "/data/cal.csv"), "No such file or directory"),
    (PermissionError(13, "Permission denied", "/data/cal.csv"), "Permission denied"),
    (IsADirectoryError(21, "Is a directory", "/data/cal.csv"), "Is a directory"),
])
def test_a_file_that_cannot_be_used_is_bad_input_naming_the_path(exc, why, capsys, monkeypatch):
    status, doc, err = _ends(exc, capsys, monkeypatch)
    assert status == 2 == doc["error"]["code"]
    assert err == f"cellcal: error: /data/cal.csv: {why}\n"
    assert doc["error"]["message"] == f"error: /data/cal.csv: {why}"


def test_a_defect_is_an_internal_error_without_a_traceback(capsys, monkeypatch):
    status, doc, err = _ends(KeyError("frame_before"), capsys, monkeypatch)
    assert status == 1 == doc["error"]["code"]
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert err.startswith("cellcal: internal error: KeyError: 'frame_before'") and "CELLCAL_DEBUG=1" in err
    # an OSError that names no file (a socket's, say) is no bad input: a defect as well
    status, doc, err = _ends(ConnectionRefusedError(111, "Connection refused"), capsys, monkeypatch)
    assert status == 1 and err.startswith("cellcal: internal error: ConnectionRefusedError")


@pytest.mark.parametrize("options,env", [((), "1"), (("--debug",), None)])
def test_cellcal_debug_prints_the_traceback_of_a_defect(options, env, capsys, monkeypatch):
    status, doc, err = _ends(KeyError("frame_before"), capsys, monkeypatch, *options, debug_env=env)
    assert status == 1 == doc["error"]["code"]
    assert "Traceback (most recent call last)" in err and "raise exc" in err
    assert err.splitlines()[-1].startswith("cellcal: internal error: KeyError")


def test_debug_zero_is_off(capsys, monkeypatch):
    _, _, err = _ends(KeyError("x"), capsys, monkeypatch, debug_env="0")
    assert "Traceback" not in err


# -- the records: runs list / show, tool history / rollback -----------------------------------------------------


FRAME_BEFORE = [0.001, -0.002, 0.15, 0.0, 0.0, 0.0]
FRAME_WRITTEN = [0.0012, -0.0021, 0.1492, 0.0084, 0.0008, 0.0]


def _result(passed: bool):
    from cellcal.routines.framework.base import Gate, Parameter, Result

    return Result("tcp-laser", [Parameter("tcp_z_mm", 149.2, 0.01, "mm")], np.zeros(4), 0.01, 3.0,
                  [Gate("residual", passed, 0.01, 0.02, "residual within the noise" if passed else "too large")],
                  tool_frame=np.array(FRAME_WRITTEN))


@pytest.fixture
def store_dir(tmp_path):
    """A store with three runs on the shipped `sim` cell: 1 written back, 2 passed every gate
    but the controller did not keep the frame (code 32), 3 failed a gate."""
    from cellcal.daemon.cells import load_cell
    from cellcal.daemon.store import Store

    cell = str(load_cell("sim").path)
    store = Store.open(tmp_path / "state")
    try:
        for passed, state, code in ((True, "done", 0), (True, "fault", 32), (False, "fault", 31)):
            run_id = store.begin_run("tcp-laser", cell)
            store.record_result(run_id, _result(passed))
            if code == 0:
                store.record_tool_frame(run_id, "write", FRAME_BEFORE, FRAME_WRITTEN)
            store.finish_run(run_id, state, code, "test")
    finally:
        store.close()
    return tmp_path / "state"


def test_runs_list_json_is_one_object_saying_what_passed_and_what_was_written(store_dir, capsys):
    assert main(["runs", "list", "--json", "--state-dir", str(store_dir)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) == {"runs"}
    assert [(r["id"], r["passed_gates"], r["written_back"]) for r in doc["runs"]] == [
        (3, False, False), (2, True, False), (1, True, True)]
    assert not any("write_back" in r for r in doc["runs"])


def test_runs_show_says_whether_the_frame_was_written(store_dir, capsys):
    assert main(["runs", "show", "2", "--json", "--state-dir", str(store_dir)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert (doc["passed_gates"], doc["written_back"], doc["result"]["passed_gates"]) == (True, False, True)
    assert main(["runs", "show", "2", "--state-dir", str(store_dir)]) == 0
    assert "passed every gate; no tool frame written back" in capsys.readouterr().out
    assert main(["runs", "show", "1", "--state-dir", str(store_dir)]) == 0
    assert "passed every gate; its tool frame was written back" in capsys.readouterr().out


def test_tool_history_json_is_one_object(store_dir, capsys):
    assert main(["tool", "history", "--json", "--state-dir", str(store_dir)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) == {"tool_frames"} and len(doc["tool_frames"]) == 1
    entry = doc["tool_frames"][0]
    assert (entry["run_id"], entry["action"], entry["frame_after"]) == (1, "write", FRAME_WRITTEN)


def test_tool_rollback_json_says_what_was_restored(store_dir, capsys):
    assert main(["tool", "rollback", "1", "--cell", "sim", "--json", "--state-dir", str(store_dir)]) == 0
    out = capsys.readouterr().out
    doc = json.loads(out)
    assert set(doc) == {"restored"} and doc["restored"]["run_id"] == 1
    frame = doc["restored"]["tool_frame"]
    # the frame from before run 1, as written: the numbers are the stored ones, converted to mm and degrees
    assert frame["pose_m_rad"] == FRAME_BEFORE and frame["z_mm"] == pytest.approx(150.0, abs=1e-9)
    assert "program_start_generation" in doc["restored"]


# -- a run's verdict ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def laser_run(tmp_path_factory):
    """`cellcal run tcp-laser --cell sim --json`, once (about 4 s)."""
    out = tmp_path_factory.mktemp("runs")
    import contextlib
    import io

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        status = main(["run", "tcp-laser", "--cell", "sim", "--json", "--out", str(out)])
    return status, json.loads(buffer.getvalue())


def test_run_json_says_it_passed_the_gates_and_wrote_nothing(laser_run):
    status, doc = laser_run
    assert status == 0 and doc["passed_gates"] is True, doc["reasons"]
    assert doc["written_back"] is False and "write_back" not in doc


def test_run_text_says_nothing_was_written(laser_run, capsys):
    _, doc = laser_run
    assert main(["run", "tcp-laser", "--from", doc["dataset"]]) == 0
    out = capsys.readouterr().out
    assert out.startswith("tcp-laser: PASSED every gate: may be written back")
    assert "nothing written to the controller (cellcal run never writes" in out


# -- words --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n,text", [(0, "0 rows"), (1, "1 row"), (2, "2 rows")])
def test_counted_puts_the_noun_in_its_number(n, text):
    from cellcal.cli.common import counted

    assert counted(n, "row") == text
    assert counted(n, "more row") == text.replace(" row", " more row")


def test_compensate_counts_one_row_in_the_singular(tmp_path, capsys):
    targets = tmp_path / "targets.csv"
    targets.write_text("x_mm,y_mm,z_mm\n4000,0,0\n600,200,400\n")  # 4 m: beyond a UR10e's reach
    assert main(["compensate", "--robot", "ur10e", "--targets", str(targets), "-o", str(tmp_path / "o.csv"),
                 "--seed-deg", "0", "-90", "90", "0", "90", "0"]) == 0
    out = capsys.readouterr().out
    assert "compensated 1 of 2 targets" in out and "; 1 row not ok;" in out


@pytest.mark.parametrize("unit,value,words", [
    ("rad", "57.3", "57.3 rad is beyond two turns, further than any joint turns (degrees under a _rad header?)"),
    ("deg", "800", "800 deg is beyond two turns, further than any joint turns (|value| must be at most 720)"),
])
def test_a_joint_value_beyond_two_turns_is_refused_in_plain_words(tmp_path, unit, value, words):
    from cellcal.measurements.reader import read_measurements
    from cellcal.measurements.table import DatasetError

    data = tmp_path / "data.csv"
    joints = ",".join(f"q{j}_{unit}" for j in range(1, 7))
    data.write_text(f"{joints},x_mm,y_mm,z_mm\n{value},0,0,0,0,0,1,2,3\n")
    with pytest.raises(DatasetError) as refused:
        read_measurements(data, 6)
    assert f"data.csv:2: column 'q1_{unit}': {words}" in str(refused.value)


# -- the routine selector wherever the docs list it ----------------------------------------------------------


def _selector_values() -> dict[int, str]:
    from cellcal.daemon.service import panel_routines

    return {int(k): v for k, v in panel_routines().items()}


def test_the_integrator_page_lists_every_routine_selector_value():
    text = " ".join((ROOT / "docs" / "integrator.md").read_text(encoding="utf-8").split())
    listed = re.search(r"holding register 0: ([^)]*)\)", text)
    assert listed, "docs/integrator.md no longer lists the selector values after 'holding register 0:'"
    pairs = {int(n): name for n, name in re.findall(r"(\d+) ([a-z][a-z-]*)", listed.group(1))}
    assert pairs == _selector_values()


def test_the_protocol_page_spans_the_selector_values():
    text = (ROOT / "docs" / "protocols.md").read_text(encoding="utf-8")
    row = next(line for line in text.splitlines() if "`routine_selector_register`" in line)
    values = _selector_values()
    first, last = min(values), max(values)
    assert f"{first} {values[first]} … {last} {values[last]}" in row, row


def test_a_file_of_another_kind_is_not_echoed_in_the_message(tmp_path, capsys):
    """A password file given as a robot model by mistake: its first line is no key of ours and
    is not printed; a typo of a key still is (the person needs to see what they typed)."""
    secret = "root:$y$j9T$notahash:19000:0:99999:7:::"
    shadow = tmp_path / "shadow"
    shadow.write_text(secret + "\n")
    typo = tmp_path / "typo.yaml"
    typo.write_text("name: x\nlnks: []\n")
    for path, shown in ((shadow, None), (typo, "[lnks]: unknown key")):
        assert main(["identify", "--robot", str(path), "--data", str(tmp_path / "none.csv")]) == 2
        err = capsys.readouterr().err
        assert "notahash" not in err and "root:" not in err
        if shown:
            assert shown in err, err
        else:
            assert "a key that is no name (not shown)" in err, err
