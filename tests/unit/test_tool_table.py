"""The cell file's tool table (issue 19, section 2, first slice): reading it, mounting a tool
(Cell.with_tool), each tool's hidden truth in the simulated cells, and every bad table
refused with one message naming file, section and key, nothing moved."""
from __future__ import annotations

import json

import numpy as np
import pytest

from cellcal.cli.main import main
from cellcal.config.cells import Bands, CellFileError
from cellcal.config.robot_files import load_robot
from cellcal.daemon.cells import load_cell
from cellcal.sims.fake_ur.controller import FakeUrController
from cellcal.sims.physics.truth import truth_of_cell
from support.cell_edits import DELETE, edited_cell  # tests/support/cell_edits.py
from support.cli_run import refused  # tests/support/cli_run.py

PIN = {"id": 1, "name": "pin", "tcp_m": [0.0, 0.0, 0.150], "axis": [0.0, 0.0, 1.0], "radius_m": 0.003,
       "length_m": 0.1}
TORCH = {"id": 2, "name": "torch", "tcp_m": [0.0, 0.005, 0.170], "axis": [0.0, 0.0, 1.0], "radius_m": 0.004,
         "length_m": 0.12, "bands": {"inner_mm": 0.2, "outer_mm": 2.0},
         "sections": {"tcp_npoint": {"spread_deg": 25}}}


def two_tools(tmp_path, extra=None, name="two.yaml", tools=None):
    """The shipped sim cell with a table of a pin (1) and a torch (2) instead of its one tool."""
    changes = {"tool": DELETE, "tools": tools if tools is not None else [PIN, TORCH], **(extra or {})}
    if changes["tools"] is DELETE:  # no table after all (the shipped file has none to delete)
        del changes["tools"]
    return edited_cell(tmp_path, "sim", changes, name=name)


# -- reading ------------------------------------------------------------------------------------------

def test_a_file_with_one_tool_is_a_table_of_one_tool_1():
    cell = load_cell("sim")
    assert list(cell.tools) == [1] and cell.tool is cell.tools[1]
    assert (cell.tool.id, cell.tool.name, cell.tool.sections) == (1, "tool", {})
    assert cell.robots["a"].tool is cell.tool
    assert cell.routines == cell.file_routines  # no tool section merged: the routines read what the file says


def test_a_table_of_two_tools_mounts_the_first_unless_told(tmp_path):
    cell = load_cell(two_tools(tmp_path))
    assert list(cell.tools) == [1, 2] and cell.tool.id == 1 and cell.tool.name == "pin"
    torch = cell.tools[2]
    np.testing.assert_array_equal(torch.tcp_m, [0.0, 0.005, 0.170])
    assert (torch.radius_m, torch.length_m) == (0.004, 0.12)
    assert torch.bands == Bands(inner_mm=0.2, outer_mm=2.0)  # the rest at their defaults
    assert cell.tools[1].bands == Bands()
    mounted = load_cell(two_tools(tmp_path, {"mounted": 2}, name="m2.yaml"))
    assert mounted.tool.id == 2 and mounted.robots["a"].tool.id == 2
    assert mounted.routines["tcp_npoint"]["spread_deg"] == 25


def test_with_tool_mounts_the_tool_and_merges_its_sections_over_the_files(tmp_path):
    cell = load_cell(two_tools(tmp_path))
    torch = cell.with_tool(2)
    assert torch.tool.id == 2 and torch.robots["a"].tool.id == 2
    npoint, own = torch.routines["tcp_npoint"], cell.routines["tcp_npoint"]
    assert npoint["spread_deg"] == 25 and own["spread_deg"] == 30  # the tool's key wins, the file's stays
    assert {k: v for k, v in npoint.items() if k != "spread_deg"} == \
        {k: v for k, v in own.items() if k != "spread_deg"}  # every other key as the file has it
    assert torch.routines["tcp_laser"] == cell.routines["tcp_laser"]  # a section the tool leaves alone
    back = torch.with_tool(1)  # mounting the first again drops the torch's keys
    assert back.tool.id == 1 and back.routines["tcp_npoint"] == own
    assert cell.tool.id == 1  # the cell it came from is unchanged


def test_with_tool_of_an_id_the_table_lacks_names_the_ids_there_are(tmp_path):
    with pytest.raises(CellFileError, match=r"\[tools\]: no tool 7 in this cell \(its tools: 1, 2\)"):
        load_cell(two_tools(tmp_path)).with_tool(7)


def test_each_tool_has_its_own_truth_and_mounting_changes_nothing_else(tmp_path):
    cell = load_cell(two_tools(tmp_path))
    model = load_robot(cell.robot)
    pin, torch = truth_of_cell(cell, model), truth_of_cell(cell.with_tool(2), model)
    assert set(pin.tools) == {1, 2}
    np.testing.assert_array_equal(pin.tool.tcp_m, pin.tools[1].tcp_m)
    np.testing.assert_array_equal(torch.tool.tcp_m, pin.tools[2].tcp_m)
    # each tool within the file's error model of its own drawing: tool_tcp_error_mm 1.0, tool_tilt_deg 0.5
    for tool_id, real in pin.tools.items():
        drawn = cell.tools[tool_id]
        assert np.linalg.norm(real.tcp_m - drawn.tcp_m) * 1e3 == pytest.approx(1.0)
        assert np.degrees(np.arccos(real.axis @ drawn.axis)) == pytest.approx(0.5)
    # tool 2's error is drawn from its own stream: not tool 1's error moved over
    assert not np.allclose(pin.tools[2].tcp_m - cell.tools[2].tcp_m, pin.tools[1].tcp_m - cell.tools[1].tcp_m)
    for a, b in zip(pin.beams, torch.beams):  # the fixtures and the arm do not move with the tool
        np.testing.assert_array_equal(a.point_m, b.point_m)
    np.testing.assert_array_equal(pin.arm_params, torch.arm_params)
    # tool 1 of a table is the one tool of the same file without a table, exactly
    one = truth_of_cell(load_cell("sim"), model)
    np.testing.assert_array_equal(one.tool.tcp_m, pin.tool.tcp_m)
    np.testing.assert_array_equal(one.beams[0].point_m, pin.beams[0].point_m)


def test_the_fake_ur_controller_mounts_the_tool_it_is_told(tmp_path):
    path = two_tools(tmp_path)
    controller = FakeUrController("127.0.0.1", cell_file=str(path), tool=2)  # built, never started
    truth = truth_of_cell(load_cell(path).with_tool(2), load_robot("ur10e"))
    np.testing.assert_array_equal(controller.truth.tool.tcp_m, truth.tool.tcp_m)
    assert controller.truth.tool.radius_m == 0.004


def test_run_dry_run_says_which_tool_is_mounted(tmp_path, capsys):
    path = two_tools(tmp_path)
    for argv, tool_id in (([], 1), (["--tool", "2"], 2)):
        assert main(["run", "tcp-npoint", "--cell", str(path), "--dry-run", "--json", *argv]) == 0
        assert json.loads(capsys.readouterr().out)["tool_id"] == tool_id


# -- bad input: one message naming file, section and key; nothing moved (a dry run plans only) ------

BAD = [
    ("duplicate id", {}, [PIN, {**TORCH, "id": 1}], ["[tools[1].id]", "tool 1 is already in the table"]),
    ("id out of range", {}, [PIN, {**TORCH, "id": 256}], ["[tools[1].id]", "256 is out of range"]),
    ("id zero", {}, [{**PIN, "id": 0}], ["[tools[0].id]", "out of range"]),
    ("id missing", {}, [{k: v for k, v in PIN.items() if k != "id"}], ["[tools[0].id]", "missing"]),
    ("mounted names no tool", {"mounted": 3}, None, ["[mounted]", "no tool 3 in [tools]", "1, 2"]),
    ("bands inverted", {}, [PIN, {**TORCH, "bands": {"inner_mm": 0.5, "outer_mm": 0.2}}],
     ["[tools[1].bands.outer_mm]", "not wider than the inner band"]),
    ("band negative", {}, [PIN, {**TORCH, "bands": {"inner_deg": -0.1}}], ["[tools[1].bands.inner_deg]", "above 0"]),
    ("outer band beyond the plausibility gate", {}, [PIN, {**TORCH, "bands": {"outer_mm": 12}}],
     ["[tools[1].bands.outer_mm]", "at most 10"]),
    ("a tool section no routine's", {}, [PIN, {**TORCH, "sections": {"tcp_lazer": {"speed_mm_s": 30}}}],
     ["[tools[1].sections.tcp_lazer]", "no routine's section", "tcp_laser"]),
    ("a cell section as a tool's", {}, [PIN, {**TORCH, "sections": {"beams": {}}}],
     ["[tools[1].sections.beams]", "no routine's section"]),
    ("a tool section not a mapping", {}, [PIN, {**TORCH, "sections": {"tcp_laser": 5}}],
     ["[tools[1].sections.tcp_laser]", "expected a mapping"]),
    ("a misspelt key in a tool", {}, [PIN, {**TORCH, "radius_mm": 4}], ["[tools[1].radius_mm]", "unknown key"]),
    ("tool and tools together", {"tool": {}}, None,  # the file's own [tool] kept beside the table
     ["[tools]", "not both"]),
    ("mounted without a table", {"tools": DELETE, "tool": {k: v for k, v in PIN.items() if k not in ("id", "name")},
                                 "mounted": 1}, None, ["[mounted]", "has none"]),
    ("an empty table", {}, [], ["[tools]", "non-empty list"]),
    ("mounted neither an id nor a source", {"mounted": "plc"}, None,
     ["[mounted]", "'plc'", "expected a tool id", "`panel`", "robot_inputs"]),
    ("a tool changer input out of range", {"mounted": {"robot_inputs": [8, 18]}}, None,
     ["[mounted.robot_inputs]", "0..17"]),
    ("a tool changer input twice", {"mounted": {"robot_inputs": [8, 8]}}, None,
     ["[mounted.robot_inputs]", "different"]),
    ("too few tool changer inputs for the ids", {"mounted": {"robot_inputs": [8, 9]}}, [PIN, {**TORCH, "id": 5}],
     ["[mounted.robot_inputs]", "ids up to 3", "tool 5"]),
    ("a misspelt key of the tool changer", {"mounted": {"robot_input": [8]}}, None,
     ["[mounted.robot_inputs]", "missing"]),
    ("a tool changer input the beams' trigger uses", {
        "mounted": {"robot_inputs": [1, 16]},  # the shipped beams are on channels 0 and 1
        "drivers": {"trigger": {"driver": "ur_digital_input", "host": "127.0.0.1", "channels": [0, 1]}}},
     None, ["[mounted.robot_inputs]", "input 1 carries the trigger"]),
    ("the mounted tool from a panel the cell lacks", {"mounted": "panel", "drivers": {"panel": DELETE}}, None,
     ["[mounted]", "no panel"]),
    ("sim_truth's tool frame without a tool 1", {"sim_truth": {"tool_tcp_m": [0.0, 0.0, 0.15]}},
     [{**TORCH, "sections": {}}], ["[sim_truth.tool_tcp_m]", "no tool 1"]),
]


@pytest.mark.parametrize("name, extra, tools, needles", BAD, ids=[b[0] for b in BAD])
def test_a_bad_tool_table_gets_one_message(tmp_path, capsys, name, extra, tools, needles):
    path = two_tools(tmp_path, extra, tools=tools)
    refused(capsys, ["run", "tcp-npoint", "--cell", path, "--dry-run"], 2, [str(path), *needles])  # input at fault


def test_run_with_a_tool_the_cell_lacks_is_refused_before_anything_moves(tmp_path, capsys):
    path = two_tools(tmp_path)
    assert main(["run", "tcp-npoint", "--cell", str(path), "--tool", "9", "--out", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err
    assert "no tool 9 in this cell (its tools: 1, 2)" in err and "Traceback" not in err
    assert not (tmp_path / "runs").exists()  # nothing measured, no dataset


def test_a_bad_option_in_a_tools_section_is_refused_when_that_tool_is_mounted(tmp_path, capsys):
    path = two_tools(tmp_path, tools=[PIN, {**TORCH, "sections": {"tcp_npoint": {"spread_deg": "wide"}}}])
    assert main(["run", "tcp-npoint", "--cell", str(path), "--tool", "2", "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "[tcp_npoint.spread_deg]" in err and "'wide' is not a number" in err and "Traceback" not in err


def test_a_two_robot_cell_keeps_one_tool_per_robot(tmp_path, capsys):
    path = edited_cell(tmp_path, "sim-dual", {"tools": [PIN]}, name="two-robots.yaml")
    assert main(["run", "handshake", "--cell", str(path), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "[tools]" in err and "no tool table there" in err


# -- where the service learns which tool is mounted ------------------------------------------------

class _Inputs:
    """A robot whose digital inputs read `bits` (an int), or fail."""

    def __init__(self, bits):
        self.bits = bits

    def digital_inputs(self):
        if isinstance(self.bits, Exception):
            raise self.bits
        return self.bits


def test_the_mounted_tool_comes_from_the_file_the_panel_or_the_tool_changers_inputs(tmp_path):
    from types import SimpleNamespace

    from cellcal.daemon.cells import NoToolMounted, mounted_tool
    from cellcal.drivers.interfaces import DeviceError
    fixed = load_cell(two_tools(tmp_path, {"mounted": 2}, name="fixed.yaml"))
    assert fixed.mounted_source.kind == "file" and mounted_tool(fixed, SimpleNamespace()) == 2
    assert load_cell("sim").mounted_source.tool == 1  # a file's one tool is tool 1, fixed

    panel = load_cell(two_tools(tmp_path, {"mounted": "panel"}, name="panel.yaml"))
    assert panel.mounted_source.kind == "panel" and panel.tool.id == 1  # the table's first until read
    for register, expected in ((2, 2), (1, 1)):
        assert mounted_tool(panel, SimpleNamespace(panel=SimpleNamespace(mounted_tool=lambda r=register: r))) \
            == expected
    with pytest.raises(NoToolMounted, match="reads 0"):
        mounted_tool(panel, SimpleNamespace(panel=SimpleNamespace(mounted_tool=lambda: 0)))
    with pytest.raises(NoToolMounted, match="reads tool 7, which this cell file's tool table lacks"):
        mounted_tool(panel, SimpleNamespace(panel=SimpleNamespace(mounted_tool=lambda: 7)))

    changer = load_cell(two_tools(tmp_path, {"mounted": {"robot_inputs": [16, 17]}}, name="changer.yaml"))
    assert changer.mounted_source.bits == (16, 17)
    # bit 16 is the id's least significant bit, 17 the next; other inputs (0-15) do not count
    for bits, expected in ((1 << 16, 1), (1 << 17 | 0xFFFF, 2)):
        assert mounted_tool(changer, SimpleNamespace(robot=_Inputs(bits))) == expected
    with pytest.raises(NoToolMounted, match="no tool is mounted"):
        mounted_tool(changer, SimpleNamespace(robot=_Inputs(0xFFFF)))
    with pytest.raises(NoToolMounted, match="reads tool 3"):
        mounted_tool(changer, SimpleNamespace(robot=_Inputs(3 << 16)))
    with pytest.raises(DeviceError):
        mounted_tool(changer, SimpleNamespace(robot=_Inputs(DeviceError("robot", "lost"))))
