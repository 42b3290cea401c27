"""A tool change in the simulated cells (issue 19, part D): the fake UR controller's
``mount_tool`` and the in-process world's, the tool changer's id on the robot's digital
inputs (read through the real UR driver over RTDE), the panel's mounted-tool register as
the cell's PLC writes it, and ``cellcal sim-cell --tool`` / ``--mount-tool``.

The cell: sim-net (or sim, in process) with a table of three tools whose id the tool changer
reports on digital inputs 16, 17 and 8, least significant first, so id 5 (0b101) is inputs 16
and 8, and the beams' inputs 0 and 1 stay the beams'.
"""
from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from cellcal.cli.main import main
from cellcal.config.cells import CellFileError
from cellcal.config.robot_files import load_robot
from cellcal.daemon.cells import load_cell
from cellcal.drivers.interfaces import DeviceError, Robot
from cellcal.sims.inproc.devices import SimPanel, SimRobot
from cellcal.sims.inproc.world import world_of_cell
from cellcal.sims.physics.arm_motion import JointMove
from cellcal.sims.physics.truth import BARE_FLANGE, truth_of_cell
from support.cell_edits import DELETE, edited_cell  # tests/support/cell_edits.py
from support.cli_run import refused  # tests/support/cli_run.py

# a pin (1), a torch 20 mm further out and 5 mm aside (2), a spare pin 10 mm longer (5): the
# real tips are 10-20 mm apart, far beyond the drawing's 1 mm error the sim draws them with
TOOLS = [{"id": 1, "name": "pin", "tcp_m": [0.0, 0.0, 0.150], "axis": [0.0, 0.0, 1.0], "radius_m": 0.003,
          "length_m": 0.1},
         {"id": 2, "name": "torch", "tcp_m": [0.0, 0.005, 0.170], "axis": [0.0, 0.0, 1.0], "radius_m": 0.004,
          "length_m": 0.12},
         {"id": 5, "name": "spare", "tcp_m": [0.0, 0.0, 0.160], "axis": [0.0, 0.0, 1.0], "radius_m": 0.003,
          "length_m": 0.1}]
ID_INPUTS = [16, 17, 8]
ID_MASK = (1 << 16) | (1 << 17) | (1 << 8)
ID_BITS = {0: 0, 1: 1 << 16, 2: 1 << 17, 5: (1 << 16) | (1 << 8)}  # what a tool changer wired so shows
EXACT_M = 1e-9  # the same arithmetic on the same doubles: only rounding separates the two sides


def tool_table(folder, base, mounted=None, host=None, name="tools.yaml"):
    """`base` with the three tools, the mounted one read from `mounted` (default: the robot's inputs)."""
    changes = {"tool": DELETE, "tools": TOOLS, "mounted": mounted or {"robot_inputs": ID_INPUTS}}
    return edited_cell(folder, base, changes, host=host, name=name)


def same_body(a, b) -> bool:
    return (np.array_equal(a.tcp_m, b.tcp_m) and np.array_equal(a.axis, b.axis)
            and (a.radius_m, a.length_m) == (b.radius_m, b.length_m))


def id_of(bits: int) -> int:
    """The tool id on the inputs, decoded as the service decodes it (least significant first)."""
    return sum(1 << i for i, bit in enumerate(ID_INPUTS) if bits >> bit & 1)


# -- the fake UR controller through the real driver ----------------------------------------------------

@pytest.fixture
def tool_fake(tmp_path, start_fake, connect):
    """A fake UR controller obeying the three-tool cell (tool 1 mounted), and the UR driver on it."""
    pytest.importorskip("rtde_control", reason="ur_rtde is not installed")
    from cellcal.drivers.ur.robot import UrRtdeRobot

    path = tool_table(tmp_path, "sim-net")
    fake = start_fake(cell_file=str(path))
    return fake, connect(UrRtdeRobot, fake.host), load_cell(path)


def inputs_after_change(robot, expected: int, within_s: float = 2.0) -> int:
    """The robot's inputs once they show `expected` on the id inputs (or the last read at the
    deadline). The stream delivers every controller cycle in order, so cycles computed before
    the change may still be on their way when the control port has answered: a few 2 ms cycles
    on an idle machine, longer on a loaded one (the 2 s bound is for a busy CI machine)."""
    deadline = time.monotonic() + within_s
    while True:
        bits = robot.digital_inputs()
        if bits & ID_MASK == expected or time.monotonic() > deadline:
            return bits
        time.sleep(0.004)


def test_the_fake_urs_digital_inputs_carry_the_mounted_tools_id_over_rtde(tool_fake):
    fake, robot, _ = tool_fake
    assert inputs_after_change(robot, ID_BITS[1]) & ID_MASK == ID_BITS[1] and fake.state()["mounted_tool"] == 1
    for tool_id in (5, 2, 0, 1):
        reply = fake.request(cmd="mount_tool", tool=tool_id)
        assert reply["mounted_tool"] == tool_id and reply["digital_inputs"] & ID_MASK == ID_BITS[tool_id]
        bits = inputs_after_change(robot, ID_BITS[tool_id])
        assert bits & ID_MASK == ID_BITS[tool_id] and id_of(bits) == tool_id
        assert fake.state()["mounted_tool"] == tool_id


def test_a_tool_change_puts_the_other_tools_real_body_on_the_flange(tool_fake):
    fake, robot, cell = tool_fake
    model = load_robot(cell.robot)
    before = fake.request(cmd="tool")
    fake.request(cmd="mount_tool", tool=2)
    after = fake.request(cmd="tool")
    # the controller's truth is now the cell's with tool 2 mounted, as if started with it
    real = {i: truth_of_cell(cell.with_tool(i), model).tool for i in (1, 2)}
    report = fake.request(cmd="truth")["truth"]
    np.testing.assert_allclose(report["tool"]["tcp_mm"], real[2].tcp_m * 1e3, rtol=0, atol=EXACT_M * 1e3)
    assert report["tool"]["radius_mm"] == pytest.approx(4.0)
    # the arm did not move (same joints, same repeatability draw): the tip moved by exactly the two
    # real tools' difference, turned by the flange's rotation (which keeps lengths)
    assert after["q"] == before["q"] and after["repeat_offset_m"] == before["repeat_offset_m"]
    moved = np.linalg.norm(np.subtract(after["tool_tip_m"], before["tool_tip_m"]))
    assert moved == pytest.approx(np.linalg.norm(real[2].tcp_m - real[1].tcp_m), abs=EXACT_M)
    assert moved > 0.015  # ~20 mm: the torch, not the pin
    # the robot's own tool frame is the robot program's business: a tool change leaves it alone
    assert np.abs(robot.tool_frame() - fake.state()["tcp_offset"]).max() == 0.0


def test_a_tool_change_is_refused_while_the_arm_moves_and_nothing_changes(tool_fake):
    fake, robot, _ = tool_fake
    target = robot.actual_q() + np.array([0.3, 0, 0, 0, 0, 0])
    mover = threading.Thread(target=robot.move_j, args=(target, 0.2, 1.0))  # ~1.7 s of motion
    mover.start()
    try:
        deadline = time.monotonic() + 5.0
        while not fake.state()["moving"] and time.monotonic() < deadline:
            time.sleep(0.01)
        assert fake.state()["moving"]
        with pytest.raises(RuntimeError, match="the arm is moving: a tool is changed with the arm at rest"):
            fake.request(cmd="mount_tool", tool=2)
        assert fake.state()["mounted_tool"] == 1
    finally:
        mover.join(10.0)
    assert robot.digital_inputs() & ID_MASK == ID_BITS[1]
    assert fake.request(cmd="truth")["truth"]["tool"]["radius_mm"] == pytest.approx(3.0)  # still the pin


@pytest.mark.parametrize("tool, message", [
    (9, r"no tool 9 in this cell's tool table \(its tools: 1, 2, 5; 0: none\)"),
    ("2", "tool must be a tool id"),
    (None, "tool must be a tool id"),
])
def test_a_tool_the_table_lacks_is_refused_and_nothing_changes(tool_fake, tool, message):
    fake, robot, _ = tool_fake
    with pytest.raises(RuntimeError, match=message):
        fake.request(cmd="mount_tool", tool=tool)
    assert fake.state()["mounted_tool"] == 1 and robot.digital_inputs() & ID_MASK == ID_BITS[1]


def test_a_fake_started_with_tool_2_has_the_truth_a_tool_change_to_2_gives(tmp_path, start_fake):
    path = tool_table(tmp_path, "sim-net")
    changed, started = start_fake(cell_file=str(path)), start_fake(cell_file=str(path), tool=2)
    changed.request(cmd="mount_tool", tool=2)
    assert changed.request(cmd="truth") == started.request(cmd="truth")
    assert changed.state()["mounted_tool"] == started.state()["mounted_tool"] == 2


# -- the in-process world ----------------------------------------------------------------------------


@pytest.fixture
def world(tmp_path):
    cell = load_cell(tool_table(tmp_path, "sim"))
    return cell, world_of_cell(cell)


def test_the_in_process_world_changes_tools_as_the_fake_does(world):
    cell, world = world
    robot = SimRobot(world)
    model = load_robot(cell.robot)
    assert world.mounted_tool == 1 and robot.digital_inputs() & ID_MASK == ID_BITS[1]
    tip_1 = world.tool_tip_m()
    world.mount_tool(5)
    assert world.mounted_tool == 5 and id_of(robot.digital_inputs()) == 5
    assert robot.digital_inputs() & ID_MASK == ID_BITS[5]
    # the truth of the cell with tool 5 mounted, its report ("drawn") included
    started_with_5 = truth_of_cell(cell.with_tool(5), model)
    assert same_body(world.truth.tool, started_with_5.tool) and world.truth.drawn == started_with_5.drawn
    real_1, real_5 = world.truth.tools[1], world.truth.tools[5]
    assert np.linalg.norm(world.tool_tip_m() - tip_1) == pytest.approx(np.linalg.norm(real_5.tcp_m - real_1.tcp_m),
                                                                       abs=EXACT_M)
    world.mount_tool(0)  # none: the bare flange, and no id on the inputs
    assert world.truth.tool is BARE_FLANGE and robot.digital_inputs() & ID_MASK == 0


def test_the_in_process_panel_reports_the_worlds_tool_as_the_cells_plc_would(world):
    _, world = world
    panel = SimPanel(world)
    assert panel.mounted_tool() == 1
    world.mount_tool(2)
    assert panel.mounted_tool() == 2
    panel.mounted = 5  # a test playing a PLC that says otherwise
    assert panel.mounted_tool() == 5 and world.mounted_tool == 2


def test_the_in_process_world_refuses_a_tool_change_while_moving_or_for_a_tool_it_lacks(world):
    _, world = world
    with pytest.raises(ValueError, match=r"no tool 3 in this cell's tool table \(its tools: 1, 2, 5; 0: none\)"):
        world.mount_tool(3)
    world.arm.start(JointMove(world.arm.q, world.arm.q + 0.2, 0.5, 1.0))
    with pytest.raises(DeviceError, match="the arm is moving"):
        world.mount_tool(2)
    world.run_motion(5.0)
    assert world.mounted_tool == 1
    world.mount_tool(2)  # at rest again: taken
    assert world.mounted_tool == 2


def test_a_robot_without_inputs_says_so():
    class NoInputs(SimRobot):
        digital_inputs = Robot.digital_inputs  # the interface's default

    with pytest.raises(DeviceError, match="this robot reports no digital inputs"):
        NoInputs().digital_inputs()


# -- the networked cell: the PLC's register, and sim-cell from another shell -----------------------


def test_sim_cell_mount_tool_tells_the_controller_and_writes_the_panels_mounted_tool_register(tmp_path, loopback):
    """The panel is read with the service's own Modbus driver, as the service reads it."""
    from cellcal.drivers.modbus.panel import ModbusPanel
    from cellcal.sims.net.cell import SimCell

    cell = load_cell(tool_table(tmp_path, "sim-net", mounted="panel")).on_host(loopback())
    options = cell.drivers["panel"].options
    with SimCell(cell) as sim:
        panel = ModbusPanel(options["host"], port=options["port"])
        try:
            assert panel.mounted_tool() == 1 == sim.tool_id  # the PLC's word at the start: the first tool
            assert sim.fake_ur.request(cmd="truth")["truth"] == json.loads(json.dumps(sim.truth.report()))
            sim.mount_tool(2)
            assert panel.mounted_tool() == 2 == sim.fake_ur.state()["mounted_tool"] == sim.tool_id
            # the truth a test scores with is the controller's, tool 2's now (the same file, the same
            # function, the same doubles: equal to the last bit after JSON's exact round trip of floats)
            assert sim.fake_ur.request(cmd="truth")["truth"] == json.loads(json.dumps(sim.truth.report()))
            assert sim.truth.tool is sim.truth.tools[2]
            with pytest.raises(CellFileError, match=r"no tool 4 in this cell \(its tools: 1, 2, 5\)"):
                sim.mount_tool(4)
            assert panel.mounted_tool() == 2 == sim.fake_ur.state()["mounted_tool"]
        finally:
            panel.close()


def test_sim_cell_mount_tool_from_another_shell(tmp_path, loopback, capsys):
    from cellcal.sims.net.cell import SimCell

    path = tool_table(tmp_path, "sim-net", host=loopback())  # the id on inputs 16, 17, 8; a panel as well
    with SimCell(load_cell(path)) as sim:
        assert main(["sim-cell", "--cell", str(path), "--mount-tool", "5"]) == 0
        out, err = capsys.readouterr()
        assert out == "cellcal sim-cell: tool 5 (spare) mounted; robot digital inputs 0x10100; panel register 28: 5\n"
        assert err == ""
        assert sim.modbus.mounted_tool() == 5 == sim.fake_ur.state()["mounted_tool"]
        assert main(["sim-cell", "--cell", str(path), "--mount-tool", "0"]) == 0
        assert sim.modbus.mounted_tool() == 0 == sim.fake_ur.state()["mounted_tool"]
        out = capsys.readouterr().out
        assert out == "cellcal sim-cell: no tool mounted; robot digital inputs 0x0; panel register 28: 0\n"


def test_sim_cell_starts_with_the_tool_it_is_told(tmp_path, loopback):
    """What ``cellcal sim-cell --tool 2`` starts (SimCell of the cell with tool 2 mounted)."""
    from cellcal.sims.net.cell import SimCell

    cell = load_cell(tool_table(tmp_path, "sim-net", mounted="panel")).on_host(loopback())
    with SimCell(cell.with_tool(2)) as sim:
        assert sim.fake_ur.state()["mounted_tool"] == 2 == sim.modbus.mounted_tool()


def no_sim_cell(tmp, loopback):
    return tool_table(tmp, "sim-net", host=loopback(), name="idle.yaml")  # nothing listens there


# the bad-input table's way (tests/unit/test_bad_input.py): exit status, one line on stderr naming what
# is wrong, nothing on stdout, no traceback
CASES = [
    ("sim-cell --tool a tool the cell lacks", lambda t, lb: ["sim-cell", "--cell", tool_table(t, "sim-net"),
                                                          "--tool", "7"],
     2, ["[tools]", "no tool 7 in this cell (its tools: 1, 2, 5)"]),
    ("sim-cell --tool 2 on a one-tool cell", lambda t, lb: ["sim-cell", "--cell", "sim-net", "--tool", "2"],
     2, ["[tool]", "no tool 2 in this cell (its tools: 1)"]),
    ("sim-cell --tool as text", lambda t, lb: ["sim-cell", "--tool", "torch"], 2,
     ["argument --tool", "'torch' is not a tool id"]),
    ("sim-cell --mount-tool 256", lambda t, lb: ["sim-cell", "--mount-tool", "256"], 2,
     ["argument --mount-tool", "1..255 (0: no tool)"]),
    ("sim-cell --tool and --mount-tool", lambda t, lb: ["sim-cell", "--tool", "1", "--mount-tool", "2"], 2,
     ["not allowed with argument"]),
    ("sim-cell --mount-tool a tool the cell lacks", lambda t, lb: ["sim-cell", "--cell", no_sim_cell(t, lb),
                                                                "--mount-tool", "3"],
     2, ["[tools]", "no tool 3 in this cell"]),
    ("sim-cell --mount-tool with no sim-cell running", lambda t, lb: ["sim-cell", "--cell", no_sim_cell(t, lb),
                                                                   "--mount-tool", "2"],
     1, ["no fake UR controller answers on", "is `cellcal sim-cell` running for this cell file?"]),
]


@pytest.mark.parametrize("name, argv, code, needles", CASES, ids=[c[0] for c in CASES])
def test_bad_sim_cell_tool_input_gets_one_message(tmp_path, loopback, capsys, name, argv, code, needles):
    refused(capsys, argv(tmp_path, loopback), code, needles)
