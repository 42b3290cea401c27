"""Options and files (issue 18, section 4): every numeric option is bounded where it is parsed,
output paths are checked before anything moves, cell files cannot be memory bombs, recorded
datasets are checked as the measurement CSV is, an edited dataset is noticed, and a plan the
cell cannot carry out is the same refusal for every routine.

The walk over the parsers below covers every option of every command, so the next numeric
option cannot be added unbounded; the rows of tests/unit/test_bad_input.py probe the
individual values.
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cellcal.cli.common import Bounded
from cellcal.cli.main import COMMANDS, build_parser, main

BOMB_TIMEOUT_S = 30.0  # a whole `cellcal` process (imports ~1 s); the bomb, expanded, would run for minutes


# -- every numeric option is bounded ---------------------------------------------------------------------


def _every_option():
    """(command words, action) for every option and positional of every sub-command, nested ones too."""
    def walk(parser, words):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, child in action.choices.items():
                    yield from walk(child, words + [name])
            elif not isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
                yield words, action
    root = build_parser(every=True)
    yield from walk(root, [])


OPTIONS = list(_every_option())


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def test_the_walk_reaches_every_command():
    assert {words[0] for words, _ in OPTIONS if words} == set(COMMANDS)


def test_every_numeric_option_of_every_command_has_a_bounded_type():
    """A number typed as int or float, or with a number as its default, parses through Bounded."""
    numeric = [(words, a) for words, a in OPTIONS if a.type in (int, float) or _is_number(a.default)]
    unbounded = [f"{' '.join(words)} {action.option_strings or action.dest}" for words, action in numeric
                 if not isinstance(action.type, Bounded)]
    assert unbounded == []


@pytest.mark.parametrize("words, action", [(w, a) for w, a in OPTIONS if isinstance(a.type, Bounded)],
                         ids=lambda v: " ".join(v) if isinstance(v, list) else "/".join(v.option_strings or [v.dest]))
def test_each_bounded_option_takes_its_default_and_refuses_what_is_outside(words, action):
    bounded: Bounded = action.type
    if action.default is not None:
        assert bounded.low <= action.default <= bounded.high  # the default is a value the option takes
    for text in ("nan", "inf", "-inf", "", "one", repr(bounded.high * 2 + 1), repr(bounded.low - 1)):
        with pytest.raises(argparse.ArgumentTypeError, match="must be"):
            bounded(text)
    if bounded.above:
        with pytest.raises(argparse.ArgumentTypeError):
            bounded(repr(bounded.low))
    edge = bounded.high if bounded.kind is float else int(bounded.high)
    assert bounded(str(edge)) == edge


# -- parse-time refusals: one line naming the option and its range, nothing run ---------------------------

PARSE_REFUSALS = [
    (["daemon", "--cell", "sim", "--poll-s", "-1"], "--poll-s", "0.005 to 10 s"),
    (["daemon", "--cell", "sim", "--poll-s", "0"], "--poll-s", "0.005 to 10 s"),
    (["daemon", "--cell", "sim", "--poll-s", "nan"], "--poll-s", "0.005 to 10 s"),
    (["daemon", "--cell", "sim", "--poll-s", "1e9"], "--poll-s", "0.005 to 10 s"),
    (["sim-data", "--poses", "100000000", "-o", "x.csv"], "--poses", "1 to 100000"),
    (["sim-data", "--poses", "1.5", "-o", "x.csv"], "--poses", "whole number"),
    (["sim-campaign", "--seed", "4294967296"], "--seed", "0 to 4294967295"),
    (["sim-campaign", "--iso9283", "--cycles", "2"], "--cycles", "3 to 1000"),
    (["runs", "show", "99999999999999999999999"], "ID", "1 to 9223372036854775807"),
    (["runs", "list", "--limit", "0"], "--limit", "1 to 1000000"),
    (["tool", "rollback", "-3", "--cell", "sim"], "RUN", "whole number"),
    (["identify", "--robot", "ur10e", "--data", "x.csv", "--folds", "1"], "--folds", "2 to 100"),
    (["compensate", "--robot", "ur5e", "--targets", "t.csv", "-o", "o.csv", "--max-correction-deg", "0"],
     "--max-correction-deg", "above 0"),
    (["compensate", "--robot", "ur5e", "--targets", "t.csv", "-o", "o.csv", "--seed-deg", "0", "1e3"],
     "--seed-deg", "-720 to 720 deg"),
    (["analyze", "--robot", "ur10e", "--data", "x.csv", "--discriminate", "1000000", "-o", "p.csv"],
     "--discriminate", "1 to 1000"),
]


@pytest.mark.parametrize("argv, option, bounds", PARSE_REFUSALS, ids=[" ".join(a[:3]) + " " + a[-1]
                                                                      for a, _, _ in PARSE_REFUSALS])
def test_an_option_out_of_bounds_ends_at_parsing_with_one_line(argv, option, bounds, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # nothing may be written: any file would land here
    with pytest.raises(SystemExit) as stop:
        main(argv)
    out, err = capsys.readouterr()
    assert stop.value.code == 2 and out == ""
    assert err.count("\n") == 1 and "Traceback" not in err
    assert f"argument {option}: must be" in err and bounds in err, err
    assert list(tmp_path.iterdir()) == []


def test_a_daemon_given_a_negative_poll_interval_never_starts(tmp_path):
    """The probe of the issue, as a process: it used to start, never poll and ignore SIGTERM."""
    proc = subprocess.run([sys.executable, "-m", "cellcal.cli.main", "daemon", "--cell", "sim-net", "--state-dir",
                           str(tmp_path / "state"), "--poll-s", "-1"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "--poll-s" in proc.stderr
    assert not (tmp_path / "state").exists()  # refused before the store was touched


# -- output paths are checked before anything moves ----------------------------------------------------------


@pytest.fixture
def nothing_moves(monkeypatch):
    """runner.measure replaced by a tripwire: a test that uses this fails if any motion is started."""
    from cellcal.routines.framework import runner

    calls = []
    monkeypatch.setattr(runner, "measure", lambda *a, **k: calls.append(a) or pytest.fail("the arm was moved"))
    return calls


@pytest.mark.parametrize("out, needle", [("afile", "exists and is not a folder"),
                                         ("/proc/cellcal-x", "cannot make the folder")])
def test_run_refuses_a_dataset_folder_it_cannot_write_before_moving(out, needle, tmp_path, monkeypatch, capsys,
                                                                    nothing_moves):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("x")
    assert main(["run", "tcp-npoint", "--out", out, "--json"]) == 2
    captured = capsys.readouterr()
    error = json.loads(captured.out)["error"]  # under --json stdout still carries one object
    assert error["code"] == 2 and f"--out {out}" in error["message"] and needle in error["message"]
    assert captured.err.count("\n") == 1 and nothing_moves == []


def test_a_dry_run_makes_no_dataset_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["run", "tcp-npoint", "--dry-run", "--out", "never"]) == 0
    assert not (tmp_path / "never").exists()


def test_an_output_file_probe_leaves_no_file_behind(tmp_path):
    from cellcal.cli.common import writable_file

    assert writable_file(tmp_path / "new.csv", "-o") == tmp_path / "new.csv"
    assert not (tmp_path / "new.csv").exists()  # made to see that it can be, and removed again


# -- a cell, robot or model file cannot be a memory bomb -------------------------------------------------


def _billion_laughs(levels: int = 9) -> str:
    """Nested aliases: ten lists of ten, `levels` deep; the last one expands to 10**(levels + 1) numbers."""
    lines = ["lol0: &lol0 [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]"]
    lines += [f"lol{i}: &lol{i} [{', '.join([f'*lol{i - 1}'] * 10)}]" for i in range(1, levels + 1)]
    return "\n".join(lines) + "\n"


@pytest.fixture
def bomb_cell(tmp_path) -> Path:
    """The shipped sim cell with the tool's TCP replaced by a billion laughs (a few hundred bytes)."""
    from cellcal.config.cell_files import shipped_cells

    text = shipped_cells()["sim"].read_text()
    assert "  tcp_m: [0.0, 0.0, 0.150]" in text
    path = tmp_path / "bomb.yaml"
    path.write_text(_billion_laughs() + text.replace("  tcp_m: [0.0, 0.0, 0.150]", "  tcp_m: *lol9"))
    return path


def test_a_yaml_alias_bomb_in_a_cell_file_is_refused_at_load(bomb_cell):
    from cellcal.config.cells import CellFileError
    from cellcal.daemon.cells import load_cell

    started = time.perf_counter()
    with pytest.raises(CellFileError, match="aliases") as refused:
        load_cell(bomb_cell)
    # counted without expanding: the ~120 nodes written, not the 10**10 values they stand for. 2 s is
    # a hundred times that on a busy runner and a millionth of the expansion's time.
    assert time.perf_counter() - started < 2.0
    assert str(bomb_cell) in str(refused.value)


def test_a_yaml_alias_bomb_ends_the_command_with_status_2(bomb_cell):
    proc = subprocess.run([sys.executable, "-m", "cellcal.cli.main", "run", "tcp-laser", "--cell", str(bomb_cell),
                           "--dry-run"], capture_output=True, text=True, timeout=BOMB_TIMEOUT_S)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert "memory bomb" in proc.stderr and "Traceback" not in proc.stderr


def test_a_robot_file_bomb_and_a_self_containing_alias_are_refused(tmp_path, capsys):
    robot = tmp_path / "robot.yaml"
    robot.write_text(_billion_laughs())
    assert main(["identify", "--robot", str(robot), "--data", "x.csv"]) == 2
    assert "aliases" in capsys.readouterr().err
    loop = tmp_path / "loop.yaml"
    loop.write_text("cell: &x [1, *x]\n")
    assert main(["run", "tcp-laser", "--cell", str(loop), "--dry-run"]) == 2
    assert "refers to a node that contains it" in capsys.readouterr().err


def test_aliases_that_share_a_block_are_still_read(tmp_path):
    """Anchors are how people share a block (and what yaml.safe_dump writes for a value held twice)."""
    from cellcal.config.reader import read_yaml

    path = tmp_path / "shared.yaml"
    path.write_text("a: &speeds {v: 0.25, a: 2.5}\nb: *speeds\nc: [*speeds, *speeds]\n")
    assert read_yaml(path) == {"a": {"v": 0.25, "a": 2.5}, "b": {"v": 0.25, "a": 2.5},
                               "c": [{"v": 0.25, "a": 2.5}] * 2}


def _shipped_yaml() -> list[Path]:
    from cellcal.config.reader import shipped

    return sorted(p for folder in ("cells", "robots") for p in shipped(folder).values())


@pytest.mark.parametrize("path", _shipped_yaml(), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_libyaml_and_pyyamls_own_parser_read_every_shipped_file_alike(path):
    """read_yaml parses with libyaml where PyYAML has it; its own parser is the fallback, and
    both give the same data (numbers compared exactly: both convert the same text)."""
    from cellcal.config.reader import _StrictLoader, _StrictPyLoader

    text = path.read_text()
    assert _StrictLoader(text).get_single_data() == _StrictPyLoader(text).get_single_data()


@pytest.mark.parametrize("loader", ["_StrictLoader", "_StrictPyLoader"])
def test_both_parsers_read_1e3_as_a_number_and_refuse_a_repeated_key(loader):
    from cellcal.config import reader

    def read(text: str):
        strict = getattr(reader, loader)(text)
        strict.name = "t.yaml"  # as read_yaml names it
        return strict.get_single_data()

    assert read("a: 1e3\nb: -2.5E-4\n") == {"a": 1000.0, "b": -2.5e-4}
    with pytest.raises(reader._RepeatedKey, match="t.yaml:2: b: key given twice"):
        read("b: 1\nb: 2\n")


def test_a_device_is_no_cell_file(capsys):
    assert main(["run", "tcp-laser", "--cell", "/dev/zero", "--dry-run"]) == 2
    assert "not a regular file" in capsys.readouterr().err


# -- recorded datasets: checked like measurement files, edits noticed --------------------------------------


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """A tcp-laser dataset recorded on the in-process simulated cell (~3 s)."""
    folder = tmp_path_factory.mktemp("runs")
    assert main(["run", "tcp-laser", "--out", str(folder), "--json"]) == 0
    (path,) = folder.glob("tcp-laser-*.csv")
    return path


def _edited(recorded: Path, tmp_path: Path, change) -> Path:
    """The dataset with its data rows passed through change(columns, rows) -> rows."""
    lines = recorded.read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    columns = lines[at].split(",")
    out = tmp_path / recorded.name
    out.write_text("\n".join(lines[: at + 1] + change(columns, lines[at + 1:])) + "\n")
    return out


def _set(column: str, value: str, row: int = 3):
    def change(columns, rows):
        fields = rows[row].split(",")
        fields[columns.index(column)] = value
        return rows[:row] + [",".join(fields)] + rows[row + 1:]
    return change


@pytest.mark.parametrize("column, value, code, needle", [
    ("flange_x_m", "nan", 2, "'nan' is not finite"),
    ("flange_x_m", "1e300", 2, "over 100 m away"),
    ("t_s", "inf", 2, "'inf' is not finite"),
    ("q2_rad", "40", 2, "beyond two turns"),
    ("flange_rx", "1e300", 2, "beyond any number a run records"),
])
def test_run_from_a_dataset_with_an_impossible_value_names_file_line_and_column(recorded, tmp_path, capsys, column,
                                                                                 value, code, needle):
    path = _edited(recorded, tmp_path, _set(column, value))
    with _no_warnings():
        assert main(["run", "tcp-laser", "--from", str(path)]) == code
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "Traceback" not in err
    # the 4th data row was spoiled: its line is the column line's (1-based) + 4
    column_line = 1 + next(i for i, s in enumerate(path.read_text().splitlines()) if not s.startswith("#"))
    assert f"{path}:{column_line + 4}: column {column!r}" in err and needle in err, err


class _no_warnings:
    """No RuntimeWarning (numpy's overflow and invalid-value warnings) is raised inside: one would
    become an exception, and the command an internal error."""

    def __enter__(self):
        import warnings
        self._catch = warnings.catch_warnings()
        self._catch.__enter__()
        warnings.simplefilter("error", RuntimeWarning)

    def __exit__(self, *exc):
        return self._catch.__exit__(*exc)


def test_run_from_a_dataset_with_only_blocked_edges_fails_its_gates_without_solver_noise(recorded, tmp_path, capsys):
    path = _edited(recorded, tmp_path, lambda columns, rows: [r for r in rows if ",blocked," in r])
    with _no_warnings():
        assert main(["run", "tcp-laser", "--from", str(path), "--json"]) == 1
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert doc["passed_gates"] is False and "Residuals" not in err and "Warning" not in err


def test_run_from_a_dataset_with_every_row_twice_says_its_deviations_are_too_small(recorded, tmp_path, capsys):
    path = _edited(recorded, tmp_path, lambda columns, rows: [r for r in rows for _ in (0, 1)])
    assert main(["run", "tcp-laser", "--from", str(path), "--json"]) in (0, 1)
    doc = json.loads(capsys.readouterr().out)
    note = next(n for n in doc["notes"] if "repeat an earlier row" in n)
    rows = len(path.read_text().splitlines()) - 9  # 8 header lines and the column line
    assert f"{rows // 2} of {rows} rows" in note and "too small" in note


def test_run_from_a_dataset_keeps_nan_where_the_routine_allows_it(recorded, capsys):
    """tcp-laser writes height_mm nan for travel and approach moves: a recorded dataset re-solves."""
    assert "nan" in recorded.read_text()
    assert main(["run", "tcp-laser", "--from", str(recorded), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["routine"] == "tcp-laser"


@pytest.fixture
def store_with(recorded, tmp_path):
    """A store in which run 1 recorded a copy of the dataset (path and sha256, as the daemon records)."""
    from cellcal.daemon.store import Store
    from cellcal.routines.framework import runner
    from cellcal.daemon.cells import load_cell

    dataset = tmp_path / "datasets" / recorded.name
    dataset.parent.mkdir()
    dataset.write_bytes(recorded.read_bytes())
    store = Store.open(tmp_path / "state", create=True)
    try:
        run_id = store.begin_run("tcp-laser", "sim")
        store.record_result(run_id, runner.solve_file("tcp-laser", load_cell("sim"), dataset))
    finally:
        store.close()
    return tmp_path / "state", dataset, run_id


def test_runs_show_says_whether_the_dataset_still_matches_its_checksum(store_with, capsys):
    state, dataset, run_id = store_with
    assert main(["runs", "show", str(run_id), "--state-dir", str(state), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["dataset_check"] == "matches"
    dataset.write_text(dataset.read_text().replace("blocked", "cleared", 1))  # one edge edited after the run
    assert main(["runs", "show", str(run_id), "--state-dir", str(state)]) == 0
    assert f"dataset: {dataset} (CHANGED since it was recorded" in capsys.readouterr().out
    assert main(["runs", "show", str(run_id), "--state-dir", str(state), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["dataset_check"] == "changed"
    dataset.unlink()
    assert main(["runs", "show", str(run_id), "--state-dir", str(state), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["dataset_check"] == "missing"


def test_run_from_says_when_the_store_recorded_the_dataset_otherwise(store_with, capsys):
    state, dataset, run_id = store_with
    assert main(["run", "tcp-laser", "--from", str(dataset), "--state-dir", str(state), "--json"]) == 0
    assert "changed since" not in capsys.readouterr().err  # as recorded: not a word
    dataset.write_text(dataset.read_text().replace("blocked", "cleared", 1))
    main(["run", "tcp-laser", "--from", str(dataset), "--state-dir", str(state), "--json"])
    err = capsys.readouterr().err
    assert f"warning: {dataset}: changed since run {run_id} recorded it" in err


def test_run_from_never_makes_a_store(recorded, tmp_path, capsys):
    assert main(["run", "tcp-laser", "--from", str(recorded), "--state-dir", str(tmp_path / "typo"), "--json"]) == 0
    assert not (tmp_path / "typo").exists()


# -- a plan the cell cannot carry out: input at fault, the same for every routine -----------------------------


@pytest.fixture(scope="module")
def far_stylus(tmp_path_factory) -> Path:
    """The sim cell with its stylus out of the arm's reach (1.2 m out, at the edge of a UR10e's 1.3 m)."""
    from support.cell_edits import edited_cell  # tests/support/cell_edits.py

    return edited_cell(tmp_path_factory.mktemp("far"), "sim", {"stylus": {"centre_m": [-1.15, -0.4, 0.4]}})


@pytest.mark.parametrize("routine, needle", [("tcp-stylus", "reduce tilt_deg"), ("tcf", "cannot be reached")])
def test_a_stylus_out_of_reach_is_a_refused_plan_for_both_routines(far_stylus, routine, needle, capsys):
    assert main(["run", routine, "--cell", str(far_stylus), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "plan refused, nothing moved" in err and needle in err and err.count("\n") == 1


def test_a_routine_whose_driver_the_cell_lacks_is_refused_as_input(tmp_path, capsys):
    from support.cell_edits import DELETE, edited_cell

    cell = edited_cell(tmp_path, "sim", {"drivers": {"tracker": DELETE}})
    assert main(["run", "tracker", "--cell", str(cell), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "needs a tracker in [drivers]" in err and "nothing moved" in err and err.count("\n") == 1


@pytest.mark.parametrize("routine", ["tcp-stylus", "tcf"])
def test_the_service_refuses_an_unreachable_stylus_with_limits(far_stylus, routine, tmp_path):
    """In the service a refused plan is result code LIMITS (12), whatever routine refused it; nothing moved."""
    from cellcal.daemon.cells import load_cell, open_drivers
    from cellcal.daemon.service import ResultCode, Service
    from cellcal.daemon.store import Store

    cell = load_cell(far_stylus)
    with open_drivers(cell) as drivers:
        q_before = list(drivers.robot.actual_q())
        service = Service(cell, drivers, Store.open(tmp_path / "state"), out_dir=tmp_path / "datasets")
        outcome = service.run(routine)
        assert outcome.code is ResultCode.LIMITS and int(outcome.code) == 12, outcome
        assert outcome.state == "refused", outcome
        assert list(drivers.robot.actual_q()) == q_before
        service.store.close()


# -- ISO 9283: what the standard's definitions exclude is refused, what it does not call its test is said --


def _iso_rows(tmp_path: Path, change=None, cycles: int = 4) -> Path:
    """A small ISO 9283 data set (ur5e, P1..P5, `cycles` cycles numbered from 1) with rows changed by
    change(columns, rows) -> rows."""
    import numpy as np

    from cellcal.config.robot_files import load_robot
    from cellcal.measurements.writer import write_measurements
    from cellcal.solvers.geometry.chain import forward

    model = load_robot("ur5e")
    q5 = np.deg2rad([[0, -90, 90, -90, -90, 0], [10, -80, 80, -90, -90, 0], [20, -100, 95, -85, -90, 0],
                     [-10, -95, 100, -95, -90, 0], [-20, -85, 85, -90, -90, 10]])
    order = np.tile(np.arange(5), cycles)
    _, p = forward(model.chains["flange"], model.nominal, q5[order])
    noise = np.random.default_rng(1).normal(scale=0.02, size=p.shape)  # every cycle its own position
    path = tmp_path / "iso.csv"
    write_measurements(path, q_rad=q5[order], xyz_mm=p + noise,
                       extra={"pose": [f"P{i + 1}" for i in order],
                              "cycle": list(np.repeat(np.arange(1, cycles + 1), 5))})
    if change is not None:
        lines = path.read_text().splitlines()
        columns = lines[0].split(",")
        path.write_text("\n".join([lines[0]] + change(columns, lines[1:])) + "\n")
    return path


def _field(column, value, row=0):
    def change(columns, rows):
        fields = rows[row].split(",")
        fields[columns.index(column)] = value
        return rows[:row] + [",".join(fields)] + rows[row + 1:]
    return change


@pytest.mark.parametrize("change, needle", [
    (_field("pose", "P6"), "'P6' is not a test pose of ISO 9283"),
    (_field("cycle", "1.5"), "'1.5' is not a cycle number"),
    (lambda c, rows: rows + [rows[0]], "pose P1 in cycle 1 again (first at line 2)"),
    (lambda c, rows: rows[:10], "measured in 2 cycles; repeatability needs at least 3"),
], ids=["pose P6", "cycle 1.5", "a duplicate (pose, cycle)", "two cycles"])
def test_iso9283_refuses_what_the_standard_defines_away(tmp_path, capsys, change, needle):
    path = _iso_rows(tmp_path, change)
    assert main(["iso9283", "--robot", "ur5e", "--data", str(path), "--json"]) == 2
    out, err = capsys.readouterr()
    assert needle in json.loads(out)["error"]["message"] and err.count("\n") == 1 and str(path) in err


def test_iso9283_warns_of_fewer_than_30_cycles_a_pose_left_out_and_copied_rows(tmp_path, capsys):
    def copied(columns, rows):  # P5 never measured; cycle 2 a copy of cycle 1 under a new number
        rows = [r for r in rows if ",P5," not in r]
        return rows + [r.rsplit(",", 1)[0] + ",9" for r in rows if r.endswith(",1")]

    path = _iso_rows(tmp_path, copied)
    assert main(["iso9283", "--robot", "ur5e", "--data", str(path), "--json"]) == 0
    warnings = json.loads(capsys.readouterr().out)["warnings"]
    assert any("5 cycles; ISO 9283 asks for 30" in w for w in warnings), warnings
    assert any("no rows for P5" in w for w in warnings)
    assert any("4 measured positions repeat earlier ones exactly" in w and "too small" in w for w in warnings)


def test_iso9283_with_30_clean_cycles_has_nothing_to_warn_of(tmp_path, capsys):
    path = _iso_rows(tmp_path, cycles=30)
    assert main(["iso9283", "--robot", "ur5e", "--data", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["warnings"] == []


def test_identify_warns_when_every_row_is_there_twice(tmp_path, capsys):
    import numpy as np

    from cellcal.measurements.writer import write_measurements

    rng = np.random.default_rng(0)
    q = rng.uniform(-1.0, 1.0, (20, 6))
    xyz = rng.uniform(-500.0, 500.0, (20, 3))
    path = tmp_path / "twice.csv"
    write_measurements(path, q_rad=np.repeat(q, 2, axis=0), xyz_mm=np.repeat(xyz, 2, axis=0))
    main(["identify", "--robot", "ur5e", "--data", str(path), "--json"])  # the fit's outcome is not the point
    err = capsys.readouterr().err
    assert "20 of 40 rows repeat an earlier row exactly (line 3 is line 2 again)" in err and "too small" in err


def test_the_range_in_a_refusal_reads_in_plain_numbers():
    """What the user reads: the range in plain numbers (no 9.22e+18 for a whole number)."""
    from cellcal.cli.common import RECORD_ID, number

    assert RECORD_ID.describe() == f"a whole number from 1 to {2**63 - 1}"
    assert number(0.0, 1000.0, above=True, unit="mm").describe() == "a number above 0 and at most 1000 mm"
    assert math.isclose(number(0.005, 10.0, unit="s")("0.5"), 0.5)
