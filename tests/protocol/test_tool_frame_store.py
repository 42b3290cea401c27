"""The tool frame the robot program applies at its start: RTDE input registers on the fake UR
controller over loopback (written in one package, read back, applied at the program's start),
write-back's restore of the old frames on a mismatch, and ``cellcal tool rollback``.
"""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
import pytest

from cellcal.cli import tool as tool_cmd
from cellcal.daemon.cells import CellDrivers
from cellcal.daemon.store import Store
from cellcal.daemon.frame_writer import read_frames, write_tool_frame
from cellcal.drivers.interfaces import DeviceError, StoredToolFrame
from cellcal.drivers.ur.registers import FORMAT_TAG, ToolFrameRegisters, register_names
from cellcal.sims.inproc.devices import SimRobot

pytest.importorskip("rtde_control", reason="ur_rtde is not installed")

from cellcal.drivers.ur.robot import UrRtdeRobot  # noqa: E402

FRAME_A = np.array([0.0123456789, -0.0045, 0.1876, 0.01, -0.02, 0.003])
FRAME_B = np.array([0.0119, -0.0051, 0.1881, 0.012, -0.018, 0.0])


@pytest.fixture
def ur(fake, connect):
    return connect(UrRtdeRobot, fake.host), fake


def test_the_stored_frame_goes_in_one_package_reads_back_exactly_and_applies_at_the_program_start(ur):
    robot, fake = ur
    assert robot.stored_tool_frame().generation == 0  # a controller after its restart holds none
    assert not fake.request(cmd="program_start")["applied"]
    stored = StoredToolFrame(FRAME_A, 17)
    robot.store_tool_frame(stored)
    assert stored.same_as(robot.stored_tool_frame())
    held = fake.request(cmd="inputs")["inputs"]
    names = register_names(24)
    assert [held[n] for n in names[:6]] == FRAME_A.tolist()  # bit for bit
    assert (held[names[6]], held[names[7]]) == (17, FORMAT_TAG)
    started = fake.request(cmd="program_start")
    assert started["applied"] and started["generation"] == 17
    assert started["tcp_offset"] == FRAME_A.tolist()


def test_write_back_through_the_fake_and_a_mismatch_restores_both_old_frames(ur):
    robot, fake = ur
    before, written, failure = write_tool_frame(robot, FRAME_A, generation=3)
    assert failure is None and before.stored.generation == 0
    now = read_frames(robot)
    np.testing.assert_array_equal(now.running, FRAME_A)
    assert StoredToolFrame(FRAME_A, 3).same_as(now.stored) and written.stored.same_as(now.stored)

    fake.fault("ignore_input", name="input_double_register_27")  # the controller does not keep rx
    _, _, failure = write_tool_frame(robot, FRAME_B, generation=4)
    assert failure is not None and "stored tool frame reads back" in failure and "old frame restored" in failure
    now = read_frames(robot)
    np.testing.assert_array_equal(now.running, FRAME_A)
    assert StoredToolFrame(FRAME_A, 3).same_as(now.stored)


def test_registers_held_by_another_client_are_refused_naming_them(ur):
    robot, fake = ur
    other = ToolFrameRegisters(fake.host, device="another RTDE client")
    wire = other._open(writing=True)[0]  # holds the input recipe, as a PLC writing these registers would
    try:
        with pytest.raises(DeviceError, match=r"input_double_register_24\.\.29 .* are in use"):
            robot.store_tool_frame(StoredToolFrame(FRAME_A, 5))
        assert robot.stored_tool_frame().generation == 0  # nothing written
    finally:
        wire.sock.close()


class _Cell:
    name = path = "test cell"
    drivers: dict = {}  # no device another process could reach: nothing to claim
    robots: dict = {}


def test_rollback_restores_the_running_and_the_stored_frame_from_before_the_write(tmp_path, monkeypatch):
    robot = SimRobot()
    robot.set_tcp(FRAME_A)
    robot.store_tool_frame(StoredToolFrame(FRAME_A, 2))
    store = Store.open(tmp_path)
    run_id = store.begin_run("tcp-laser", "test cell")
    before, written, failure = write_tool_frame(robot, FRAME_B, generation=run_id)
    assert failure is None
    store.record_tool_frame(run_id, "write", before.running, written.running, before.stored_json(),
                            written.stored_json())
    store.close()
    monkeypatch.setattr(tool_cmd, "load_cell", lambda path: _Cell())
    monkeypatch.setattr(tool_cmd, "open_drivers", lambda cell: CellDrivers(robot=robot))
    args = argparse.Namespace(state_dir=str(tmp_path), run=None, tool=None, cell="test cell", json=False)
    assert tool_cmd.cmd_tool_rollback(args) == 0
    robot._closed = False  # the drivers were closed on leaving; look at what the controller holds
    np.testing.assert_array_equal(robot.tool_frame(), FRAME_A)
    assert StoredToolFrame(FRAME_A, 2).same_as(robot.stored_tool_frame())
    store = Store.open(tmp_path)
    last = store.tool_frames()[-1]
    store.close()
    assert last["action"] == "rollback" and last["stored_after"] == {"tool_frame": FRAME_A.tolist(), "generation": 2,
                                                                     "slot": 0}  # the block it went back to
    assert last["stored_before"] == {"tool_frame": FRAME_B.tolist(), "generation": run_id, "slot": 0}


def test_the_documented_script_reads_the_registers_and_the_tag_the_driver_writes():
    text = (Path(__file__).resolve().parents[2] / "docs" / "integrator.md").read_text()
    script = text[text.index("# cellcal: apply the stored tool frame"):]
    script = script[:script.index("```")]
    floats = [int(n) for n in re.findall(r"read_input_float_register\((\d+)\)", script)]
    ints = {int(n) for n in re.findall(r"read_input_integer_register\((\d+)\)", script)}
    names = register_names(24)
    assert [f"input_double_register_{n}" for n in floats] == list(names[:6])
    assert {f"input_int_register_{n}" for n in ints} == set(names[6:])
    assert f"read_input_integer_register(25) == {FORMAT_TAG}" in script
    assert "read_input_integer_register(24) > 0" in script
