"""Two tools on sim-net, driven from the operator panel as a cell with a tool changer runs
(issue: daily use, section 5): the PLC writes which tool is mounted (``mounted: panel``),
each tool is calibrated and checked, a tool change between them while the service runs, a
start for a tool that is not mounted and a start with no tool on the flange.

What is compared with the hidden truth: each tool's written frame with that tool's real
frame; after the change back, the check of tool 1 against the frame written for tool 1
(not tool 2's, which the controller held just before): ok, nothing written.
"""
from __future__ import annotations

import numpy as np
import pytest
from support import daemon_harness
from support.cell_edits import edited_cell
from cellcal.daemon.service import ResultCode
from support.daemon_harness import Net, controller_tcp, plc_reads, press_start, until_the_run_ends

pytestmark = pytest.mark.slow

# each written frame against its tool's real one: tcp-laser's accuracy on sim-net is about
# 0.01-0.02 mm (docs/routines.md); 0.05 mm leaves room for another machine's rounding, and is far below
# the 20 mm between the two tools' tips, so a frame of the wrong tool cannot pass
WITHIN_MM = 0.05


def two_tool_cell(folder, host):
    """sim-net with the shipped tcp-laser section, a torch (1, the file's tool) and a spare
    torch 20 mm longer (2), the mounted one read from the panel."""
    def tools(doc):
        tool = doc.pop("tool")
        doc["tools"] = [{"id": 1, "name": "torch", **tool},
                        {"id": 2, "name": "spare", **tool, "tcp_m": [tool["tcp_m"][0], tool["tcp_m"][1],
                                                                     tool["tcp_m"][2] + 0.02]}]
        doc["mounted"] = "panel"
        doc["drivers"]["panel"]["timeout_s"] = 0.3
    return edited_cell(folder, "sim-net", tools, name="sim-net-two-tools.yaml", host=host)


@pytest.fixture(scope="module")
def net_cell():
    return two_tool_cell


def press(net: Net, routine: str, tool: int = 0) -> dict:
    """One run from the panel (`tool`: the tool selector); what a PLC reads afterwards."""
    counter = net.panel.run_counter()
    net.panel.select_tool(tool)
    press_start(net, routine)
    until_the_run_ends(net, counter)
    return plc_reads(net)


def refused(net: Net, routine: str, tool: int = 0) -> dict:
    """A start that must be refused: the arm never moves; what a PLC reads afterwards."""
    counter = net.panel.run_counter()
    q = net.state()["q"]
    net.panel.select_tool(tool)
    net.panel.select_routine(daemon_harness.SELECT[routine])
    net.panel.press_start()
    until_the_run_ends(net, counter, meanwhile=lambda: assert_still(net, q))
    return plc_reads(net)


def assert_still(net: Net, q) -> None:
    look = net.state()
    assert not look["moving"] and look["q"] == q


def stored_block(net: Net, block: int) -> list[float]:
    """Register block `block` as the controller holds it: the frame's six doubles, the generation."""
    inputs = net.control.request(cmd="inputs")["inputs"]
    first = 24 + 6 * block  # tool_frame_register 24, six doubles per block
    return [*(inputs[f"input_double_register_{first + i}"] for i in range(6)), inputs[f"input_int_register_{first}"]]


def real_tip_mm(net: Net, tool_id: int) -> np.ndarray:
    """The tool's real tip (flange frame, mm): the simulation's hidden truth, for scoring only."""
    return np.asarray(net.sim.truth.tools[tool_id].tcp_m, dtype=float) * 1e3


def test_two_tools_calibrated_checked_and_changed_from_the_panel(net, cellcal_daemon):
    daemon = cellcal_daemon(net)
    net.sim.mount_tool(1)

    first = press(net, "tcp-laser")
    assert first["code"] == ResultCode.OK and first["tool_id"] == 1, daemon.log()
    torch = controller_tcp(net)
    assert np.linalg.norm(torch[:3] * 1e3 - real_tip_mm(net, 1)) <= WITHIN_MM

    net.sim.mount_tool(2)  # a tool change while the service runs; the PLC writes register 28
    wrong = refused(net, "tcp-check", tool=1)  # the operator means the torch: it is not on the flange
    assert wrong["code"] == ResultCode.TOOL_NOT_MOUNTED and wrong["lamps"]["fault"], daemon.log()
    assert "names tool 1 (torch) but tool 2 (spare) is mounted" in daemon.log()

    spare = press(net, "tcp-laser", tool=2)
    assert spare["code"] == ResultCode.OK and spare["tool_id"] == 2, daemon.log()
    spare_frame = controller_tcp(net)
    assert np.linalg.norm(spare_frame[:3] * 1e3 - real_tip_mm(net, 2)) <= WITHIN_MM
    # the robot program's start after a tool change reads its tool's own register block
    # (docs/integrator.md "Persistent tool frame"): block 0 the torch's frame of run 1, block 1 the spare's of run 3
    for block, frame, run in ((0, torch, 1), (1, spare_frame, 3)):
        np.testing.assert_array_equal(stored_block(net, block), [*frame, run])
    check = press(net, "tcp-check")
    assert check["code"] == ResultCode.OK and check["verdict"] == "ok" and check["tool_id"] == 2, daemon.log()

    net.sim.mount_tool(1)  # back to the torch: the controller still holds the spare's frame
    np.testing.assert_array_equal(controller_tcp(net), spare_frame)
    back = press(net, "tcp-check")
    # checked against the torch's own frame (written by run 1), set before anything moved
    assert back["code"] == ResultCode.OK and back["verdict"] == "ok" and back["tool_id"] == 1, daemon.log()
    assert not back["lamps"]["done"]  # ok: nothing written
    np.testing.assert_array_equal(controller_tcp(net), torch)
    assert "tool 1 (torch) mounted: the controller's tool frame set to the last frame written for it (run 1)" \
        in daemon.log()
    # the beams are the cell's: the check of the torch measures against the beams the newest tcp-laser
    # found, the spare's (run 3), not the older one of its own tool (run 1)
    assert "run 5: the beams where tcp-laser run 3 found them" in daemon.log()

    net.sim.mount_tool(0)  # the flange bare: the tool changer's register reads 0
    bare = refused(net, "tcp-check")
    assert bare["code"] == ResultCode.TOOL_NOT_MOUNTED, daemon.log()
    assert "no tool is mounted (the panel's mounted-tool register reads 0)" in daemon.log()

    history = daemon.cli("tool", "history")["tool_frames"]
    assert [(row["run_id"], row["tool_id"]) for row in history] == [(1, 1), (3, 2)]
    assert daemon.stop() == 0
