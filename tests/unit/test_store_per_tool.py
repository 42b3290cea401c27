"""The store and its commands per tool (issue 19, part 2): every run and every tool frame
written or restored belongs to a tool of the cell's table.

- migration 7 upgrades a store made by the schema-6 code: its old runs read as tool 1 (or the
  tool a run measured), its tool frames as their run's tool;
- ``begin_run`` records the run's tool (NULL for a cell that describes none), and the service
  gives it the tool the run is for;
- ``tool history`` names each row's tool and ``--tool`` filters; ``runs list|show`` carry it;
- ``tool rollback`` walks each tool's history on its own: without RUN it needs ``--tool``
  when several tools have write-backs not undone, and a RUN of another tool is refused.

The refusals run the real command line in process and assert status 2, one message naming
what to give, no traceback, and that nothing was recorded.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.daemon.service import ResultCode, Service
from cellcal.daemon.store import SCHEMA_VERSION, STORE_FILE, Store
from support.cell_edits import DELETE, edited_cell  # tests/support/cell_edits.py
from support.cli_run import one_message, run_cli  # tests/support/cli_run.py
from support.old_stores import old_store, upgraded  # tests/support/old_stores.py

PIN = {"id": 1, "name": "pin", "tcp_m": [0.0, 0.0, 0.150], "axis": [0.0, 0.0, 1.0], "radius_m": 0.003,
       "length_m": 0.1}
TORCH = {"id": 2, "name": "torch", "tcp_m": [0.0, 0.005, 0.170], "axis": [0.0, 0.0, 1.0], "radius_m": 0.004,
         "length_m": 0.12}

# each tool's frames: before its first write (index 0), then after each of its writes; 0.1 mm
# apart, so any mix-up between them shows in an exact comparison
PIN_FRAMES = [[0.0, 0.0, 0.150 + k * 1e-4, 0.0, 0.0, 0.0] for k in range(3)]
TORCH_FRAMES = [[0.0, 0.005, 0.170 + k * 1e-4, 0.0, 0.0, 0.0] for k in range(3)]


def two_tool_cell(tmp_path: Path, mounted: int = 1, name: str = "two.yaml") -> Path:
    """The shipped sim cell with a table of a pin (1) and a torch (2) instead of its one tool."""
    return edited_cell(tmp_path, "sim", {"tool": DELETE, "tools": [PIN, TORCH], "mounted": mounted},
                       name=name)


# -- migration 7 ------------------------------------------------------------------------------------


def schema_6_store(path: Path) -> None:
    """A store as the schema-6 code made and wrote it: its migrations, its INSERTs (no tool_id
    column anywhere but measured_frames). Run 1 wrote tool 1's frame; run 2 was a check that
    measured tool 2 and wrote its frame; run 3 measured nothing; a tool frame without a run."""
    with old_store(path, 6) as db:
        for routine in ("tcp-laser", "tcp-check", "identify"):
            db.execute("INSERT INTO runs (routine, cell, started_at, state) VALUES (?, 'sim', 1.0, 'done')", (routine,))
        db.execute("INSERT INTO measured_frames (run_id, tool_id, at, kind, routine, frame, determines, written) "
                   "VALUES (2, 2, 2.0, 'check', 'tcp-check', ?, '[\"tip\"]', 1)", (json.dumps(TORCH_FRAMES[1]),))
        for run_id, before, after in ((1, PIN_FRAMES[0], PIN_FRAMES[1]), (2, TORCH_FRAMES[0], TORCH_FRAMES[1]),
                                      (None, PIN_FRAMES[1], PIN_FRAMES[2])):
            db.execute("INSERT INTO tool_frames (run_id, at, action, frame_before, frame_after) "
                       "VALUES (?, 3.0, 'write', ?, ?)", (run_id, json.dumps(before), json.dumps(after)))


def test_a_schema_6_store_is_upgraded_and_its_old_rows_belong_to_tool_1_or_the_tool_they_measured(tmp_path):
    assert SCHEMA_VERSION >= 7
    schema_6_store(tmp_path / STORE_FILE)
    store = upgraded(tmp_path)
    try:
        assert [(r.id, r.tool_id) for r in store.runs()] == [(3, 1), (2, 2), (1, 1)]
        assert [(f["run_id"], f["tool_id"]) for f in store.tool_frames()] == [(1, 1), (2, 2), (None, 1)]
        assert [f["run_id"] for f in store.writes_not_undone(2)] == [2]
        assert store.run(1).state == "done" and store.measured_frames(2)[0]["frame"] == TORCH_FRAMES[1]
        run = store.begin_run("tcp-check", "sim", tool_id=2)  # the upgraded store takes new rows as usual
        assert store.run(run).tool_id == 2
    finally:
        store.close()
    again = Store.open(tmp_path)  # opened again: nothing left to migrate, the rows as they were
    try:
        assert again.db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        assert [r.tool_id for r in again.runs()] == [2, 1, 2, 1]
    finally:
        again.close()


# -- the store's rows per tool ----------------------------------------------------------------------


def test_begin_run_records_the_tool_and_a_cell_without_one_is_null(tmp_path):
    store = Store.open(tmp_path)
    try:
        one = store.begin_run("tcp-npoint", "sim")  # a file's one `tool` is tool 1
        two = store.begin_run("tcp-check", "two.yaml", tool_id=2)
        none = store.begin_run("identify", "tracker-only.yaml", tool_id=0)  # the service's 0: no tool
        later = store.begin_run("tcp-check", "two.yaml", tool_id=None)
        store.record_run_tool(later, 2)  # a tool known only after the run began
        assert [(r.id, r.tool_id) for r in store.runs()] == [(later, 2), (none, None), (two, 2), (one, 1)]
    finally:
        store.close()


def test_a_tool_frame_belongs_to_its_runs_tool_and_each_tools_history_is_walked_on_its_own(tmp_path):
    store = Store.open(tmp_path)
    try:
        pin1 = store.begin_run("tcp-npoint", "two.yaml", tool_id=1)
        store.record_tool_frame(pin1, "write", PIN_FRAMES[0], PIN_FRAMES[1])
        torch1 = store.begin_run("tcp-npoint", "two.yaml", tool_id=2)
        store.record_tool_frame(torch1, "write", TORCH_FRAMES[0], TORCH_FRAMES[1])
        pin2 = store.begin_run("tcp-npoint", "two.yaml", tool_id=1)
        store.record_tool_frame(pin2, "write", PIN_FRAMES[1], PIN_FRAMES[2])
        torch2 = store.begin_run("tcp-npoint", "two.yaml", tool_id=2)
        store.record_tool_frame(torch2, "write", TORCH_FRAMES[1], TORCH_FRAMES[2])
        assert [f["tool_id"] for f in store.tool_frames()] == [1, 2, 1, 2]
        assert [f["run_id"] for f in store.tool_frames(2)] == [torch1, torch2]
        # rolling back the pin's first write undoes the pin's later one, not the torch's (later still)
        store.record_tool_frame(pin1, "rollback", PIN_FRAMES[2], PIN_FRAMES[0])
        assert store.tool_frames()[-1]["tool_id"] == 1  # a rollback is the tool of the run it undoes
        assert [f["run_id"] for f in store.writes_not_undone(1)] == []
        assert [f["run_id"] for f in store.writes_not_undone(2)] == [torch1, torch2]
        assert [f["run_id"] for f in store.writes_not_undone()] == [torch1, torch2]
        store.record_tool_frame(None, "write", PIN_FRAMES[0], PIN_FRAMES[1], tool_id=1)  # no run: told
        assert store.tool_frames()[-1]["tool_id"] == 1
    finally:
        store.close()


def test_the_last_passed_result_is_looked_up_per_tool_when_asked(tmp_path):
    store = Store.open(tmp_path)
    try:
        for tool_id in (1, 2, 1):
            run = store.begin_run("tcp-laser", "two.yaml", tool_id=tool_id)
            store.db.execute("UPDATE runs SET state = 'done', passed_gates = 1, result_json = ? WHERE id = ?",
                             (json.dumps({"tool": tool_id}), run))
        assert store.last_passed_result("tcp-laser")[0] == 3  # any tool: the newest
        assert store.last_passed_result("tcp-laser", tool_id=2) == (2, {"tool": 2})
        assert store.last_passed_result("tcp-laser", tool_id=7) is None
    finally:
        store.close()


def test_the_service_records_the_tool_its_run_is_for_even_when_it_refuses(tmp_path):
    """Tool 2 mounted, the selector names tool 1: refused before anything moves (code 14), and
    the run's row is tool 2's, the tool on the flange."""
    cell = load_cell(two_tool_cell(tmp_path, mounted=2))
    store = Store.open(tmp_path / "state")
    with open_drivers(cell) as drivers:
        service = Service(cell, drivers, store, out_dir=tmp_path / "datasets")
        outcome = service.run("tcp-check", tool=1)
        assert outcome.code == ResultCode.TOOL_NOT_MOUNTED, outcome.reason
    try:
        assert store.run(outcome.run_id).tool_id == 2
    finally:
        store.close()


# -- the commands ---------------------------------------------------------------------------------


@pytest.fixture
def two_tool_store(tmp_path) -> tuple[Path, Path]:
    """(state folder, cell file): on the two-tool sim cell, runs 1 and 3 wrote the pin's frame,
    runs 2 and 4 the torch's; run 5, a check of the pin, wrote nothing."""
    cell = two_tool_cell(tmp_path)
    store = Store.open(tmp_path / "state")
    try:
        for tool_id, frames, k in ((1, PIN_FRAMES, 1), (2, TORCH_FRAMES, 1), (1, PIN_FRAMES, 2),
                                   (2, TORCH_FRAMES, 2)):
            run = store.begin_run("tcp-npoint", str(cell), tool_id=tool_id)
            store.finish_run(run, "done", 0, "written back")
            store.record_tool_frame(run, "write", frames[k - 1], frames[k])
        check = store.begin_run("tcp-check", str(cell), tool_id=1)
        store.finish_run(check, "done", 0, "tool check ok")
    finally:
        store.close()
    return tmp_path / "state", cell


def rollbacks(folder: Path) -> list[tuple[int, int, list]]:
    store = Store.open(folder)
    try:
        return [(f["run_id"], f["tool_id"], f["frame_after"]) for f in store.tool_frames() if f["action"] == "rollback"]
    finally:
        store.close()


def test_tool_history_names_each_rows_tool_and_filters_by_tool(two_tool_store, capsys):
    state, _ = two_tool_store
    code, out, _ = run_cli(capsys, "tool", "history", "--state-dir", str(state))
    lines = out.splitlines()
    assert code == 0 and len(lines) == 4
    assert ["tool 1 (pin)" in lines[0], "tool 2 (torch)" in lines[1], "run 3" in lines[2]] == [True] * 3
    code, out, _ = run_cli(capsys, "tool", "history", "--tool", "2", "--json", "--state-dir", str(state))
    rows = json.loads(out)["tool_frames"]
    assert code == 0 and [(r["run_id"], r["tool_id"], r["tool_name"]) for r in rows] == [(2, 2, "torch"),
                                                                                         (4, 2, "torch")]
    code, out, _ = run_cli(capsys, "tool", "history", "--tool", "3", "--state-dir", str(state))
    assert code == 0 and out.strip() == "no tool frame of tool 3 written yet (tools with frames written: 1, 2)"


def test_runs_list_and_show_carry_each_runs_tool(two_tool_store, capsys):
    state, cell = two_tool_store
    code, out, _ = run_cli(capsys, "runs", "list", "--json", "--state-dir", str(state))
    assert code == 0 and [(r["id"], r["tool_id"]) for r in json.loads(out)["runs"]] == [(5, 1), (4, 2), (3, 1),
                                                                                        (2, 2), (1, 1)]
    code, out, _ = run_cli(capsys, "runs", "list", "--state-dir", str(state))
    assert code == 0 and " tool 2   tcp-npoint " in out.splitlines()[1], out
    code, out, _ = run_cli(capsys, "runs", "show", "4", "--json", "--state-dir", str(state))
    assert code == 0 and json.loads(out)["tool_id"] == 2
    code, out, _ = run_cli(capsys, "runs", "show", "4", "--state-dir", str(state))
    assert code == 0 and out.startswith(f"run 4: tcp-npoint on {cell}, tool 2: done")


REFUSED = {  # argv after `tool rollback`: what the one message must say
    "several tools, neither RUN nor --tool": (
        [], ["write-backs of 2 tools are not undone", "tool 1 (pin): latest run 3", "tool 2 (torch): latest run 4",
             "give --tool ID"]),
    "a RUN of another tool than --tool": (
        ["4", "--tool", "1"], ["run 4 wrote the frame of tool 2, not of tool 1 (--tool)", "nothing changed"]),
    "a tool with no write-back": (
        ["--tool", "3"], ["no write-back of tool 3 to undo", "none recorded", "tools with write-backs to undo: 1, 2"]),
}


@pytest.mark.parametrize("case", list(REFUSED))
def test_a_rollback_that_cannot_tell_whose_write_to_undo_is_refused_and_changes_nothing(two_tool_store, capsys,
                                                                                     case):
    state, cell = two_tool_store
    argv, needles = REFUSED[case]
    code, out, err = run_cli(capsys, "tool", "rollback", *argv, "--cell", str(cell), "--state-dir", str(state))
    line = one_message(err)
    assert code == 2 and out == ""
    assert all(needle in line for needle in needles), line
    assert rollbacks(state) == []  # nothing recorded, nothing connected


def test_rollbacks_walk_back_each_tools_history_on_its_own(two_tool_store, tmp_path, capsys):
    state, cell = two_tool_store
    rollback = ["tool", "rollback", "--cell", str(cell), "--state-dir", str(state), "--json"]
    # the same cell with the torch mounted (a copy: same cell, same robot), to give the torch its
    # running frame back too (these writes kept no stored frame for the program's start)
    torch_cell = str(two_tool_cell(tmp_path, mounted=2, name="torch.yaml"))
    torch_rollback = ["tool", "rollback", "--cell", torch_cell, "--state-dir", str(state), "--json"]
    code, out, err = run_cli(capsys, *rollback, "--tool", "1")  # the pin's latest: run 3, back to its frame 1
    assert code == 0 and json.loads(out)["restored"]["run_id"] == 3
    assert "next rollback without RUN undoes run 1's write-back (tool 1)" in err
    code, out, err = run_cli(capsys, *rollback, "--tool", "1")  # then run 1, not the torch's run 4
    assert code == 0 and json.loads(out)["restored"]["run_id"] == 1
    assert "every recorded write-back of tool 1 is now undone" in err
    code, out, _ = run_cli(capsys, *torch_rollback)  # only the torch has writes left: no --tool needed
    assert code == 0 and json.loads(out)["restored"]["run_id"] == 4
    code, out, _ = run_cli(capsys, *torch_rollback, "2", "--tool", "2")  # a named run of that tool
    assert code == 0 and json.loads(out)["restored"]["run_id"] == 2
    assert rollbacks(state) == [(3, 1, PIN_FRAMES[1]), (1, 1, PIN_FRAMES[0]), (4, 2, TORCH_FRAMES[1]),
                                (2, 2, TORCH_FRAMES[0])]
    code, out, err = run_cli(capsys, *rollback[:-1], "--tool", "1")  # without --json: the message on stderr
    assert code == 2 and out == ""
    assert "no write-back of tool 1 to undo" in one_message(err) and "rolled back already" in err
    assert len(rollbacks(state)) == 4


def test_the_run_report_names_the_tool(tmp_path):
    from cellcal.reports.run import write_run_report
    from cellcal.routines.framework.base import Gate, Parameter, Result

    result = Result("tcp-check", [Parameter("tcp_z_mm", 170.1, 0.01, "mm")], np.zeros(4), 0.01, 1.0,
                    [Gate("residual", True, 0.01, 0.02, "within the noise")], tool_frame=np.array(TORCH_FRAMES[1]))
    page = write_run_report(tmp_path, 7, result, tool_id=2).read_text()
    assert "<h1>Run 7: tcp-check</h1><p>tool 2</p>" in page
