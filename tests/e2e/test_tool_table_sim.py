"""A cell with a tool table, end to end on the in-process simulated cell: `cellcal run
tcp-npoint --tool ID` measures the tool it is told is mounted, and each tool's result is
scored against that tool's hidden truth (issue 19, section 2, first slice)."""
from __future__ import annotations

import json

import numpy as np

from cellcal.cli.main import main
from cellcal.config.robot_files import load_robot
from cellcal.daemon.cells import load_cell
from cellcal.sims.physics.truth import truth_of_cell
from support.cell_edits import DELETE, edited_cell  # tests/support/cell_edits.py

# a pin (1) and a longer, thicker torch (2) 20 mm further out and 5 mm aside: the two real
# tips are ~20 mm apart, far beyond any routine's error
TOOLS = [{"id": 1, "name": "pin", "tcp_m": [0.0, 0.0, 0.150], "axis": [0.0, 0.0, 1.0], "radius_m": 0.003,
          "length_m": 0.1},
         {"id": 2, "name": "torch", "tcp_m": [0.0, 0.005, 0.170], "axis": [0.0, 0.0, 1.0], "radius_m": 0.004,
          "length_m": 0.12, "sections": {"tcp_npoint": {"approach_mm": 6}}}]
TARGET_MM = 0.05  # the sim cell's tcp_npoint target_mm: the design's refused above it (the routine's own bound)


def run_json(argv, capsys) -> dict:
    code = main(argv)
    out = capsys.readouterr()
    assert code == 0, out.err
    return json.loads(out.out)


def test_run_tool_2_measures_tool_2_and_tool_1_stays_tool_1(tmp_path, capsys):
    path = edited_cell(tmp_path, "sim", {"tool": DELETE, "tools": TOOLS}, name="two-tools.yaml")
    cell = load_cell(path)
    model = load_robot(cell.robot)
    real = {i: truth_of_cell(cell.with_tool(i), model).tool.tcp_m * 1e3 for i in (1, 2)}
    found = {}
    for tool_id, argv in ((2, ["--tool", "2"]), (1, [])):  # 1: the file's mounted tool, by default
        result = run_json(["run", "tcp-npoint", "--cell", str(path), "--json", "--out", str(tmp_path / "runs"),
                           *argv], capsys)
        assert result["tool_id"] == tool_id and result["passed_gates"]
        found[tool_id] = np.asarray(result["tool_frame"]["pose_m_rad"][:3]) * 1e3
        # scored against the mounted tool's truth, within the routine's usual accuracy
        assert result["sim_truth"]["position_error_mm"] <= TARGET_MM
        np.testing.assert_allclose(result["sim_truth"]["tool"]["tcp_mm"], real[tool_id])
        assert np.linalg.norm(found[tool_id] - real[tool_id]) <= TARGET_MM  # the same, checked here
    # the two results are the two tools: ~20 mm apart, each far from the other tool's tip
    assert np.linalg.norm(found[1] - found[2]) > 15.0
    assert np.linalg.norm(found[2] - real[1]) > 15.0 and np.linalg.norm(found[1] - real[2]) > 15.0
