"""One block of RTDE input registers per tool (issue 19, section 2) on the fake UR controller
over loopback, driven by the real ur_rtde client: block k from input register N+6k, each
read back bit for bit and applied by the program of its tool at its start; a write to one
block leaves the others alone; a tool beyond the blocks that fit below register 48 gets the
running frame only; a block held by another client is refused naming its registers; and the
integrator page's BeforeStart lines for a tool changer read the registers the driver writes."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from cellcal.daemon.frame_writer import no_block_note, read_frames, write_tool_frame
from cellcal.drivers.interfaces import DeviceError, StoredToolFrame
from cellcal.drivers.ur.registers import FORMAT_TAG, ToolFrameRegisters, block_count, block_first, register_names

pytest.importorskip("rtde_control", reason="ur_rtde is not installed")

from cellcal.drivers.ur.robot import UrRtdeRobot  # noqa: E402

FRAME_1 = np.array([0.0123456789, -0.0045, 0.1876, 0.01, -0.02, 0.003])
FRAME_2 = np.array([0.0011, 0.0052, 0.1712345678, -0.004, 0.0025, 0.0])


def test_the_blocks_that_fit_below_register_48():
    # the doubles of block k are N+6k .. N+6k+5, and the last input register is 47
    assert [block_count(n) for n in (24, 29, 30, 36, 42)] == [4, 3, 3, 2, 1]
    assert [block_first(24, k) for k in range(4)] == [24, 30, 36, 42]
    assert register_names(block_first(24, 3))[5] == "input_double_register_47"


def test_two_tools_frames_in_two_blocks_read_back_exactly_and_each_program_applies_its_own(fake, connect):
    robot = connect(UrRtdeRobot, fake.host)
    assert robot.tool_frame_slots() == 4 and robot.tool_frame_slots_text() == "blocks for 4 tools from input register 24"
    robot.store_tool_frame(StoredToolFrame(FRAME_1, 7), 0)
    held = fake.request(cmd="inputs")["inputs"]
    robot.store_tool_frame(StoredToolFrame(FRAME_2, 8), 1)
    assert StoredToolFrame(FRAME_1, 7).same_as(robot.stored_tool_frame(0))  # block 0 untouched by block 1's write
    assert StoredToolFrame(FRAME_2, 8).same_as(robot.stored_tool_frame(1))
    assert robot.stored_tool_frame(2).generation == 0  # no tool's yet
    now = fake.request(cmd="inputs")["inputs"]
    block_0, block_1 = register_names(24), register_names(30)
    assert [now[n] for n in block_0] == [held[n] for n in block_0]
    assert [now[n] for n in block_1] == [*FRAME_2.tolist(), 8, FORMAT_TAG]  # bit for bit, as the controller holds it
    for block, frame, generation in ((0, FRAME_1, 7), (1, FRAME_2, 8)):
        started = fake.request(cmd="program_start", block=block)  # the program of the tool at that block
        assert started["applied"] and started["generation"] == generation
        assert started["tcp_offset"] == frame.tolist()


def test_write_back_to_tool_2s_block_leaves_tool_1s_alone(fake, connect):
    robot = connect(UrRtdeRobot, fake.host)
    assert write_tool_frame(robot, FRAME_1, generation=3, slot=0)[2] is None
    before, written, failure = write_tool_frame(robot, FRAME_2, generation=4, slot=1)
    assert failure is None and before.stored.generation == 0 and written.stored_json()["slot"] == 1
    assert StoredToolFrame(FRAME_2, 4).same_as(read_frames(robot, 1).stored)
    assert StoredToolFrame(FRAME_1, 3).same_as(read_frames(robot, 0).stored)
    np.testing.assert_array_equal(robot.tool_frame(), FRAME_2)


def test_a_tool_beyond_the_blocks_gets_the_running_frame_only(fake, connect):
    robot = connect(UrRtdeRobot, fake.host, tool_frame_register=42)  # room for one block: 42..47
    assert robot.tool_frame_slots() == 1
    before, written, failure = write_tool_frame(robot, FRAME_2, generation=5, slot=1)
    assert failure is None and written.stored is None
    np.testing.assert_array_equal(robot.tool_frame(), FRAME_2)
    assert robot.stored_tool_frame(0).generation == 0  # block 0 not written
    assert no_block_note(robot, 2, 1).startswith("tool 2 has no register block on this robot (it would take "
                                                 "block 1; blocks for 1 tool from input register 42)")
    with pytest.raises(DeviceError, match=r"no tool frame block 1: the input registers hold blocks for 1 tool"):
        robot.store_tool_frame(StoredToolFrame(FRAME_2, 5), 1)


def test_a_block_held_by_another_client_is_refused_naming_its_registers(fake, connect):
    robot = connect(UrRtdeRobot, fake.host)
    other = ToolFrameRegisters(fake.host, device="a PLC")
    wire = other._open(writing=True, first=block_first(24, 1))[0]  # holds block 1's input recipe
    try:
        with pytest.raises(DeviceError, match=r"input_double_register_30\.\.35 .* are in use .*frame_block"):
            robot.store_tool_frame(StoredToolFrame(FRAME_2, 6), 1)
        robot.store_tool_frame(StoredToolFrame(FRAME_1, 6), 0)  # another tool's block is free
        assert StoredToolFrame(FRAME_1, 6).same_as(robot.stored_tool_frame(0))
        assert robot.stored_tool_frame(1).generation == 0  # nothing written there
    finally:
        wire.sock.close()


def test_the_documented_tool_changer_lines_read_the_block_the_driver_writes():
    """The integrator page's BeforeStart script for a tool changer computes its registers from a base
    register variable; evaluated for each block, they are the driver's names."""
    text = (Path(__file__).resolve().parents[2] / "docs" / "integrator.md").read_text()
    script = text[text.index("# cellcal: apply this tool's stored frame"):]
    script = script[:script.index("```")]
    base = re.search(r"^\s*(\w+) = 24 \+ 6 \* (\w+)", script, re.M)
    assert base, script
    variable = base.group(1)
    floats = re.findall(rf"read_input_float_register\({variable}(?: \+ (\d))?\)", script)
    ints = re.findall(rf"read_input_integer_register\({variable}(?: \+ (\d))?\)", script)
    for block in range(4):
        first = 24 + 6 * block
        names = register_names(block_first(24, block))
        assert [f"input_double_register_{first + int(k or 0)}" for k in floats] == list(names[:6])
        assert {f"input_int_register_{first + int(k or 0)}" for k in ints} == set(names[6:])
    assert f"read_input_integer_register({variable} + 1) == {FORMAT_TAG}" in script
    assert f"read_input_integer_register({variable}) > 0" in script
