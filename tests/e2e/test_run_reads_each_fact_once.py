"""One run reads each fact once: a tool check started from the panel, in process on the
simulated cell, after a tcp-laser calibration (so the check measures against the beams that
calibration found, taken from the store). Counted while the check runs:

* the controller's tool frame (``Robot.tool_frame``): before the run, and the read-back after
  the write of the corrected frame; nothing else;
* the robot model file: loaded once (the run's context carries the model);
* the routine's section of the cell file: parsed once (the run's context carries its options).
"""
from __future__ import annotations


from cellcal.config import robot_files
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.daemon.service import ResultCode, Service
from cellcal.daemon.store import Store
from cellcal.routines.framework.registry import routine_class
from support.cell_edits import edited_cell
from support.service_panel import press

def test_a_check_from_the_panel_reads_the_frame_twice_the_model_and_its_section_once(tmp_path, monkeypatch):
    cell = load_cell(edited_cell(tmp_path, "sim", {"sim_truth": {"seed": 5, "fixture_error_mm": 0.0}}))
    robot_file = robot_files.resolve_robot(cell.robot)
    counts = {"tool_frame": 0, "robot_model": 0, "section": 0}
    counting = [False]

    real_read_yaml = robot_files.read_yaml

    def read_yaml(path, *args, **kwargs):
        if counting[0] and str(path) == str(robot_file):
            counts["robot_model"] += 1
        return real_read_yaml(path, *args, **kwargs)

    monkeypatch.setattr(robot_files, "read_yaml", read_yaml)
    check = routine_class("tcp-check")
    real_read_options = check.read_options.__func__

    def read_options(cls, section, cell):
        if counting[0]:
            counts["section"] += 1
        return real_read_options(cls, section, cell)

    monkeypatch.setattr(check, "read_options", classmethod(read_options))

    with open_drivers(cell) as drivers:
        robot, panel = drivers.robot, drivers.panel
        real_tool_frame = robot.tool_frame

        def tool_frame():
            if counting[0]:
                counts["tool_frame"] += 1
            return real_tool_frame()

        robot.tool_frame = tool_frame
        service = Service(cell, drivers, Store.open(tmp_path / "state"), out_dir=tmp_path / "state" / "datasets")
        calibration = press(service, panel, "tcp-laser")
        assert calibration.code == ResultCode.OK, calibration.reason
        drivers.world.bend_tool([0.3e-3, 0.0, 0.0])  # the real tool 0.3 mm off its frame: the check corrects it

        counting[0] = True
        checked = press(service, panel, "tcp-check")
        counting[0] = False
    assert (checked.code, checked.result.verdict) == (ResultCode.OK, "corrected"), checked.reason
    assert f"the beams where tcp-laser run {calibration.run_id} found them" in checked.result.extra["beams_from"] \
        or checked.result.extra["beams_from"].startswith("tcp_check.beams"), checked.result.extra
    print("reads during the check:", counts)
    assert counts == {"tool_frame": 2, "robot_model": 1, "section": 1}, counts
