"""Persistent write-back per tool (issue 19, section 2): each tool of a cell's tool table keeps
its frame for the robot program's start in a block of its own (its ``frame_block``, else its
place in the table), on the in-process simulated robot (four blocks, as a UR's input
registers from 24); a tool beyond the robot's blocks gets the running frame only, said in
words; a rollback puts back the block the write went to, and the running frame only when
the tool is mounted; a bad ``frame_block`` is refused with one message, nothing moved.
The same blocks on the fake UR over RTDE: tests/protocol/test_tool_blocks_ur.py."""
from __future__ import annotations

import argparse
import logging

import numpy as np
import pytest

from cellcal.cli import tool as tool_cmd
from cellcal.cli.main import main
from cellcal.config.cells import tool_blocks
from cellcal.daemon.cells import CellDrivers, load_cell, open_drivers
from cellcal.daemon.service import ResultCode, Service
from cellcal.daemon.store import Store
from cellcal.daemon.frame_writer import (no_block_note, read_frames, stored_json, tool_slot, tools_without_block,
                                       write_tool_frame)
from cellcal.drivers.interfaces import DeviceError, StoredToolFrame
from cellcal.sims.inproc.devices import SimRobot
from support.cell_edits import DELETE, edited_cell  # tests/support/cell_edits.py
from support.cli_run import refused  # tests/support/cli_run.py

PIN = {"id": 1, "name": "pin", "tcp_m": [0.0, 0.0, 0.150], "axis": [0.0, 0.0, 1.0], "radius_m": 0.003,
       "length_m": 0.1}
TORCH = {"id": 2, "name": "torch", "tcp_m": [0.0, 0.005, 0.170], "axis": [0.0, 0.0, 1.0], "radius_m": 0.004,
         "length_m": 0.12}
GRIPPER = {"id": 7, "name": "gripper finger", "tcp_m": [0.0, -0.004, 0.160], "axis": [0.0, 0.0, 1.0],
           "radius_m": 0.003, "length_m": 0.1}
# frames with every digit significant: the blocks hold doubles, so a kept write reads back bit for bit
FRAME_1 = np.array([0.0123456789, -0.0045, 0.1876, 0.01, -0.02, 0.003])
FRAME_2 = np.array([0.0011, 0.0052, 0.1712345678, -0.004, 0.0025, 0.0])
FRAME_3 = np.array([-0.0009, -0.0041, 0.1598, 0.0, 0.0031, -0.0007])
NONE_STORED = StoredToolFrame(np.zeros(6), 0)  # a block as after a controller restart


def table(tmp_path, tools, extra=None, name="tools.yaml"):
    """The shipped sim cell with the tool table `tools` instead of its one tool."""
    return edited_cell(tmp_path, "sim", {"tool": DELETE, "tools": tools, **(extra or {})}, name=name)


def blocks(robot) -> list[StoredToolFrame]:
    return [robot.stored_tool_frame(k) for k in range(robot.tool_frame_slots())]


# -- which tool gets which block -----------------------------------------------------------------------------

def test_each_tool_takes_the_block_of_its_place_in_the_table_unless_it_names_one(tmp_path):
    cell = load_cell(table(tmp_path, [PIN, TORCH, GRIPPER]))
    assert tool_blocks(cell.tools) == {1: 0, 2: 1, 7: 2}  # file order, 0-based; not the ids
    assert [tool_slot(cell, t) for t in (1, 2, 7)] == [0, 1, 2]
    named = load_cell(table(tmp_path, [{**PIN, "frame_block": 3}, TORCH, GRIPPER], name="named.yaml"))
    assert tool_blocks(named.tools) == {1: 3, 2: 1, 7: 2}
    assert tool_slot(load_cell("sim"), 1) == 0  # a file's one tool: the one block, as before tool tables
    assert tool_slot(cell, 9) is None  # a tool the table lacks has none


# -- two tools, two blocks -------------------------------------------------------------------------------------

def test_two_tools_frames_go_to_two_blocks_and_each_reads_back_exactly(tmp_path):
    cell = load_cell(table(tmp_path, [PIN, TORCH]))
    robot = SimRobot()
    assert robot.tool_frame_slots() == 4
    for tool_id, frame, run_id in ((1, FRAME_1, 11), (2, FRAME_2, 12)):
        before, written, failure = write_tool_frame(robot, frame, generation=run_id, slot=tool_slot(cell, tool_id))
        assert failure is None and before.stored.same_as(NONE_STORED)
        assert written.slot == tool_slot(cell, tool_id) and written.stored_json()["slot"] == written.slot
    assert StoredToolFrame(FRAME_1, 11).same_as(read_frames(robot, 0).stored)  # exactly: doubles in, doubles out
    assert StoredToolFrame(FRAME_2, 12).same_as(read_frames(robot, 1).stored)
    assert all(b.same_as(NONE_STORED) for b in blocks(robot)[2:])  # the blocks of no tool untouched
    np.testing.assert_array_equal(robot.tool_frame(), FRAME_2)  # the running program has the last tool written


def test_a_write_for_tool_2_leaves_tool_1s_block_alone_and_a_failed_one_restores_only_its_own(tmp_path):
    cell = load_cell(table(tmp_path, [PIN, TORCH]))
    robot = SimRobot()
    write_tool_frame(robot, FRAME_1, generation=3, slot=tool_slot(cell, 1))
    _, _, failure = write_tool_frame(robot, FRAME_2, generation=4, slot=tool_slot(cell, 2))
    assert failure is None
    assert StoredToolFrame(FRAME_1, 3).same_as(robot.stored_tool_frame(0))

    original = robot.store_tool_frame

    def drops_rz(stored, slot=0):  # a controller that does not keep one value of block 1
        frame = np.array(stored.tool_frame, dtype=float)
        frame[5] = 0.5 if slot == 1 and stored.generation == 5 else frame[5]
        original(StoredToolFrame(frame, stored.generation), slot)
    robot.store_tool_frame = drops_rz
    _, _, failure = write_tool_frame(robot, FRAME_3, generation=5, slot=tool_slot(cell, 2))
    assert failure is not None and "(block 1)" in failure and "old frame restored" in failure
    assert StoredToolFrame(FRAME_2, 4).same_as(robot.stored_tool_frame(1))  # its own old frame back
    assert StoredToolFrame(FRAME_1, 3).same_as(robot.stored_tool_frame(0))  # tool 1's never touched
    np.testing.assert_array_equal(robot.tool_frame(), FRAME_2)


# -- the registers run out ---------------------------------------------------------------------------------------

def test_a_tool_beyond_the_robots_blocks_gets_the_running_frame_only_and_a_note(tmp_path):
    cell = load_cell(table(tmp_path, [PIN, TORCH, {**GRIPPER, "frame_block": 4}]))  # the sim keeps blocks 0..3
    robot = SimRobot()
    slot = tool_slot(cell, 7)
    before, written, failure = write_tool_frame(robot, FRAME_3, generation=9, slot=slot)
    assert failure is None and before.stored is None and written.stored is None and written.stored_json() is None
    np.testing.assert_array_equal(robot.tool_frame(), FRAME_3)  # the running program has it
    assert all(b.same_as(NONE_STORED) for b in blocks(robot))  # no block written, tool 1's and 2's untouched
    note = no_block_note(robot, 7, slot)
    assert note == ("tool 7 has no register block on this robot (it would take block 4; blocks for 4 tools, as a "
                    "UR's from input register 24): its frame lasts until the program stops, and the robot program "
                    "keeps its installation's TCP for it at its next start")
    assert tools_without_block(cell, robot) == [note]  # what the daemon says once at its start
    assert no_block_note(robot, 2, tool_slot(cell, 2)) is None


def test_a_robot_that_keeps_no_stored_frame_gets_the_running_frame_and_no_note_per_tool(tmp_path):
    class NoRegisters(SimRobot):  # a robot without input registers: the interface's defaults
        def tool_frame_slots(self):
            return 0

    robot, cell = NoRegisters(), load_cell(table(tmp_path, [PIN, TORCH]))
    before, written, failure = write_tool_frame(robot, FRAME_2, generation=2, slot=tool_slot(cell, 2))
    assert failure is None and written.stored is None and before.stored is None
    np.testing.assert_array_equal(robot.tool_frame(), FRAME_2)
    assert no_block_note(robot, 2, 1) is None and tools_without_block(cell, robot) == []


def test_the_in_process_robot_refuses_a_block_it_does_not_have():
    robot = SimRobot()
    with pytest.raises(DeviceError, match=r"no tool frame block 4: it keeps blocks for 4 tools"):
        robot.store_tool_frame(StoredToolFrame(FRAME_1, 1), 4)
    with pytest.raises(DeviceError, match=r"no tool frame block -1"):
        robot.stored_tool_frame(-1)


# -- the service: the block of the run's tool ---------------------------------------------------------------------

def _service(cell, drivers, tmp_path):
    return Service(cell, drivers, Store.open(tmp_path / "state"), out_dir=tmp_path / "datasets")


def test_the_service_writes_the_mounted_tools_block_and_says_when_a_tool_has_none(tmp_path, caplog):
    path = table(tmp_path, [PIN, TORCH, {**GRIPPER, "frame_block": 4}], {"mounted": 2})
    cell = load_cell(path)
    with open_drivers(cell) as drivers:
        service = _service(cell, drivers, tmp_path)
        with caplog.at_level(logging.WARNING, logger="cellcal.daemon"):
            service.announce_tool_blocks()
        said = [r.getMessage() for r in caplog.records]
        assert said == [no_block_note(drivers.robot, 7, 4)]  # once, for the one tool without a block

        outcome = service.run("tcp-npoint")
        assert (outcome.state, outcome.code) == ("done", ResultCode.OK), outcome.reason
        robot = drivers.robot
        assert StoredToolFrame(outcome.result.tool_frame, outcome.run_id).same_as(robot.stored_tool_frame(1))
        assert robot.stored_tool_frame(0).same_as(NONE_STORED)  # tool 1's block: not this run's tool
        row = service.store.tool_frames()[-1]
        assert row["stored_after"]["slot"] == 1 and row["stored_before"] == stored_json(NONE_STORED, 1)
        assert "no register block" not in outcome.reason
        service.store.close()

    gripper = load_cell(table(tmp_path, [PIN, TORCH, {**GRIPPER, "frame_block": 4}], {"mounted": 7},
                              name="gripper.yaml"))
    with open_drivers(gripper) as drivers:
        service = _service(gripper, drivers, tmp_path / "g")
        outcome = service.run("tcp-npoint")
        assert (outcome.state, outcome.code) == ("done", ResultCode.OK), outcome.reason  # never an error
        np.testing.assert_array_equal(drivers.robot.tool_frame(), outcome.result.tool_frame)
        assert all(b.same_as(NONE_STORED) for b in blocks(drivers.robot))
        assert "tool 7 has no register block on this robot (it would take block 4" in outcome.reason
        assert service.store.run(outcome.run_id).reason == outcome.reason  # the store keeps the words too
        row = service.store.tool_frames()[-1]
        assert row["stored_before"] is None and row["stored_after"] is None
        service.store.close()


# -- rollback: the block it was written to -------------------------------------------------------------------------

def _rollback(tmp_path, monkeypatch, cell, robot, run=None):
    monkeypatch.setattr(tool_cmd, "load_cell", lambda path: cell)
    monkeypatch.setattr(tool_cmd, "open_drivers", lambda c: CellDrivers(robot=robot))
    monkeypatch.setattr(tool_cmd, "_check_same_robot", lambda *args: None)
    args = argparse.Namespace(state_dir=str(tmp_path / "state"), run=run, tool=2, cell=cell.path, json=False)
    try:
        return tool_cmd.cmd_tool_rollback(args)
    finally:
        robot._closed = False  # the drivers were closed on leaving; look at what the controller holds


def _two_writes_of_tool_2(tmp_path, cell, robot) -> int:
    """Tool 1 written once, tool 2 twice (FRAME_2 then FRAME_3); the id of tool 2's second run."""
    store = Store.open(tmp_path / "state")
    try:
        for tool_id, frame in ((1, FRAME_1), (2, FRAME_2), (2, FRAME_3)):
            run_id = store.begin_run("tcp-npoint", cell.path, tool_id)
            before, written, failure = write_tool_frame(robot, frame, generation=run_id, slot=tool_slot(cell, tool_id))
            assert failure is None
            store.record_tool_frame(run_id, "write", before.running, written.running, before.stored_json(),
                                    written.stored_json(), tool_id)
        return run_id
    finally:
        store.close()


def test_rollback_of_the_mounted_tool_restores_its_block_and_the_running_frame(tmp_path, monkeypatch, capsys):
    cell = load_cell(table(tmp_path, [PIN, TORCH], {"mounted": 2}))
    robot = SimRobot()
    last = _two_writes_of_tool_2(tmp_path, cell, robot)
    assert _rollback(tmp_path, monkeypatch, cell, robot) == 0
    assert StoredToolFrame(FRAME_2, last - 1).same_as(robot.stored_tool_frame(1))  # tool 2's block, as before
    assert StoredToolFrame(FRAME_1, last - 2).same_as(robot.stored_tool_frame(0))  # tool 1's untouched
    np.testing.assert_array_equal(robot.tool_frame(), FRAME_2)  # tool 2 is on the flange: its running frame too
    assert "generation" in capsys.readouterr().out
    store = Store.open(tmp_path / "state")
    row = store.tool_frames()[-1]
    store.close()
    assert (row["action"], row["tool_id"]) == ("rollback", 2)
    assert row["stored_after"] == stored_json(StoredToolFrame(FRAME_2, last - 1), 1)


def test_rollback_of_a_tool_not_mounted_restores_only_its_block(tmp_path, monkeypatch, capsys):
    cell = load_cell(table(tmp_path, [PIN, TORCH], {"mounted": 1}))
    robot = SimRobot()
    last = _two_writes_of_tool_2(tmp_path, cell, robot)
    robot.set_tcp(FRAME_1)  # tool 1 mounted again: the running program has its frame
    assert _rollback(tmp_path, monkeypatch, cell, robot) == 0
    assert StoredToolFrame(FRAME_2, last - 1).same_as(robot.stored_tool_frame(1))
    assert StoredToolFrame(FRAME_1, last - 2).same_as(robot.stored_tool_frame(0))
    np.testing.assert_array_equal(robot.tool_frame(), FRAME_1)  # the mounted tool's frame left alone
    said = capsys.readouterr()
    assert "tool 2 is not mounted: only its block" in said.err
    # the restored frame is not said to be on the controller: it went to tool 2's block, for its next mounting
    assert "restored tool 2" in said.out and "into its block of stored frames only, for its next mounting" in said.out
    store = Store.open(tmp_path / "state")
    row = store.tool_frames()[-1]
    store.close()
    assert row["frame_before"] == FRAME_3.tolist() and row["frame_after"] == FRAME_2.tolist()  # tool 2's frames


def test_rollback_of_a_row_from_before_tool_tables_restores_block_0(tmp_path, monkeypatch):
    cell = load_cell(table(tmp_path, [PIN, TORCH], {"mounted": 2}))
    robot = SimRobot()
    robot.store_tool_frame(StoredToolFrame(FRAME_1, 2), 0)
    store = Store.open(tmp_path / "state")
    run_id = store.begin_run("tcp-npoint", cell.path, 2)
    old = {"tool_frame": FRAME_1.tolist(), "generation": 2}  # as rows were written before the slot was kept
    store.record_tool_frame(run_id, "write", FRAME_1, FRAME_2, old, {**old, "generation": run_id}, 2)
    store.close()
    robot.store_tool_frame(StoredToolFrame(FRAME_2, run_id), 0)
    assert _rollback(tmp_path, monkeypatch, cell, robot) == 0
    assert StoredToolFrame(FRAME_1, 2).same_as(robot.stored_tool_frame(0))
    assert robot.stored_tool_frame(1).same_as(NONE_STORED)


def test_rollback_of_a_tool_not_mounted_whose_write_kept_no_block_changes_nothing(tmp_path, monkeypatch, capsys):
    cell = load_cell(table(tmp_path, [PIN, {**TORCH, "frame_block": 5}], {"mounted": 1}))
    robot = SimRobot()
    store = Store.open(tmp_path / "state")
    run_id = store.begin_run("tcp-npoint", cell.path, 2)
    before, written, _ = write_tool_frame(robot, FRAME_2, generation=run_id, slot=tool_slot(cell, 2))
    store.record_tool_frame(run_id, "write", before.running, written.running, before.stored_json(),
                            written.stored_json(), 2)
    store.close()
    robot.set_tcp(FRAME_1)
    with pytest.raises(tool_cmd.UsageError, match="tool 2 is not mounted and its write-back of run 1 kept no frame"):
        _rollback(tmp_path, monkeypatch, cell, robot)
    np.testing.assert_array_equal(robot.tool_frame(), FRAME_1)
    assert all(b.same_as(NONE_STORED) for b in blocks(robot))


# -- bad frame_block: one message naming file, section and key; nothing moved (a dry run plans only) -----------

BAD = [
    ("frame_block named twice", [{**PIN, "frame_block": 2}, {**TORCH, "frame_block": 2}],
     ["[tools[1].frame_block]", "block 2 is tool 1's (tool 1 names it too)"]),
    ("frame_block another tool has by its place", [PIN, TORCH, {**GRIPPER, "frame_block": 1}],
     ["[tools[2].frame_block]", "block 1 is tool 2's (tool 2 has it by its place in the table)"]),
    ("frame_block taken before its place's owner comes", [{**PIN, "frame_block": 1}, TORCH],
     ["[tools[0].frame_block]", "block 1 is tool 2's (tool 2 has it by its place in the table)"]),
    ("frame_block negative", [PIN, {**TORCH, "frame_block": -1}], ["[tools[1].frame_block]", "out of range"]),
    ("frame_block beyond any tool table", [PIN, {**TORCH, "frame_block": 255}],
     ["[tools[1].frame_block]", "255 is out of range"]),
    ("frame_block as text", [PIN, {**TORCH, "frame_block": "second"}],
     ["[tools[1].frame_block]", "not an integer"]),
]


@pytest.mark.parametrize("name, tools, needles", BAD, ids=[b[0] for b in BAD])
def test_a_bad_frame_block_gets_one_message(tmp_path, capsys, name, tools, needles):
    path = table(tmp_path, tools)
    refused(capsys, ["run", "tcp-npoint", "--cell", path, "--dry-run"], 2, [str(path), *needles])  # input at fault


def test_frame_block_is_a_tool_tables_key_only(tmp_path, capsys):
    path = edited_cell(tmp_path, "sim", {"tool": {"frame_block": 1}}, name="one.yaml")
    assert main(["run", "tcp-npoint", "--cell", str(path), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "[tool.frame_block]" in err and "unknown key" in err
