"""The second robot brand end to end: a Franka FR3 through libfranka (pylibfranka, Franka's own
binding) on franky-sim's MuJoCo physics, a simulator we did not write, in the sim-franka cell.

The arm as built is off its drawing (the cell's ``sim_truth``: lengths by up to 0.3 mm, angles by
up to 0.02 deg), placed so in MuJoCo's bodies while the controller computes with the maker's
nominal kinematics; the tool is off its drawing by 1 mm and 0.5 deg. The routines run through
``cellcal run`` and through the service from the panel, with the same gates, result codes and
write-back as on the UR cells; faults are injected through the simulator (a collision reflex in
the middle of a sweep, the connection cut).

Every case here runs the arm in real time (franky-sim's physics and libfranka's 1 kHz loop use
about a core each on this machine), so the module keeps one simulated cell running for all of
them, and each case's routine sections are the shipped ones unless a case says otherwise.
"""
from __future__ import annotations

import json
import os
import time
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("pylibfranka", reason="the franka extra is not installed (pip install 'cellcal[franka]'): "
                                          "pylibfranka is missing")
pytest.importorskip("franky_sim", reason="the franka extra is not installed (pip install 'cellcal[franka]'): "
                                         "franky-sim is missing")

from cellcal.cli.main import main as cli_main  # noqa: E402
from cellcal.config.robot_files import load_robot  # noqa: E402
from cellcal.daemon.cells import load_cell  # noqa: E402
from cellcal.daemon.service import ResultCode  # noqa: E402
from cellcal.sims.fake_ur.process import ControlClient  # noqa: E402
from cellcal.sims.net.cell import SimCell  # noqa: E402
from cellcal.sims.physics.truth import truth_of_cell  # noqa: E402
from support import loopback  # noqa: E402
from support.cell_edits import edited_cell  # noqa: E402
from support.daemon_harness import Daemon, plc_reads  # noqa: E402
from support.service_panel import SELECT  # noqa: E402

pytestmark = pytest.mark.slow

# The tool routines on this arm: their fits have no model of the arm's own errors, so each pose puts the
# tool off by what the arm's 0.3 mm / 0.02 deg errors add up to there (0.1 mm rms over tcp-laser's
# +-45 deg tilts: its residual), and the fitted tip is off by their average over the poses. Measured
# (seed 7): tcp-laser 0.21 mm and 0.05 deg, tcp-npoint 0.16 mm; with the arm as drawn (the same cell,
# sim_truth's arm errors 0) tcp-laser lands within 0.006 mm and 0.004 deg, as close as on the UR cells.
# The bounds: the most the arm's errors move the tool tip and turn the flange at a pose of the routines'
# region (the cell's own truth evaluated below: 0.85 mm, 0.05 deg), plus the fit's own noise.
LATENCY_MS = (2.0, 3.0)  # the truth 2.5 ms; the fit's sd 0.6 ms
# the simulated arm's clock, simulated seconds per wall second: franky-sim's step and our cell take about
# 0.2 ms of a core and libfranka's loop in the driver about as much, so two cores keep up at 2 with the
# suite's other worker busy (the same results as real time: 0.208 against 0.205 mm for tcp-laser's tip)
FRANKA_TIME_SCALE = 2.0


@pytest.fixture(scope="module")
def franka(tmp_path_factory):
    """sim-franka on a loopback address of its own (``cellcal sim-cell``'s SimCell), for the module."""
    folder = tmp_path_factory.mktemp("sim-franka")
    host = loopback.allocate()
    try:
        path = edited_cell(folder, "sim-franka", {"drivers": {"panel": {"timeout_s": 0.3}}}, name="sim-franka.yaml",
                           host=host)
        cell = load_cell(path)
        sim = SimCell(cell, time_scale=FRANKA_TIME_SCALE).start()
        # the simulator is most of this module's load (0.8 of a core at twice real time): it yields to the
        # suite's other worker, whose fakes keep the wall-clock handshakes of ur_rtde, and runs slower then
        # (it follows its own clock; libfranka's client follows it)
        os.setpriority(os.PRIO_PROCESS, sim.fake_ur.proc.pid, 10)
    except BaseException:
        loopback.release(host)
        raise
    control = ControlClient(host)
    try:
        yield SimpleNamespace(path=path, cell=cell, sim=sim, host=host, control=control, panel=sim.modbus,
                              folder=folder)
    finally:
        control.close()
        sim.stop()
        loopback.release(host)


def run_cli(capsys, *args) -> tuple[int, dict]:
    code = cli_main(["run", *args, "--json"])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if out.strip() else {"stderr": err[-3000:]})


def at_rest(franka) -> dict:
    deadline = time.monotonic() + 20.0
    while franka.control.request(cmd="state")["moving"]:
        assert time.monotonic() < deadline, "the arm did not come to rest"
        time.sleep(0.05)
    return franka.control.request(cmd="state")


def arm_errors(cell) -> tuple[float, float]:
    """The most the arm's own errors move the real tool tip (mm) and turn the flange (deg) from where
    the nominal arm puts them, over random poses within 0.6 rad of home (the routines' working region):
    what they can add to any pose a routine measures."""
    from cellcal.sims.physics.arm_motion import ArmKinematics

    model = load_robot(cell.robot)
    truth = truth_of_cell(cell, model)
    real, drawn = ArmKinematics(model, truth.arm_params), ArmKinematics(model)
    rng = np.random.default_rng(0)
    home = np.asarray(cell.home_q_rad, dtype=float)
    tip = turn = 0.0
    for _ in range(200):
        q = home + rng.uniform(-0.6, 0.6, len(home))
        (r1, p1), (r0, p0) = real.flange(q), drawn.flange(q)
        tip = max(tip, float(np.linalg.norm((p1 + r1 @ truth.tool.tcp_m) - (p0 + r0 @ truth.tool.tcp_m))))
        turn = max(turn, float(np.degrees(np.arccos(np.clip((np.trace(r0.T @ r1) - 1) / 2, -1.0, 1.0)))))
    return tip * 1e3, turn


def test_tcp_laser_and_npoint_through_cellcal_run(franka, capsys):
    """tcp-laser and tcp-npoint through ``cellcal run --cell sim-franka``: their gates pass, the tool
    lands within the arm's own error of the hidden truth, the trigger's latency is found."""
    bound, turn = arm_errors(franka.cell)
    assert 0.3 < bound < 1.5 and 0.02 < turn < 0.2, (bound, turn)  # the cell's arm errors, as this file assumes
    code, laser = run_cli(capsys, "tcp-laser", "--cell", str(franka.path), "--out", str(franka.folder))
    assert code == 0 and laser["passed_gates"], laser
    score = laser["sim_truth"]
    # off by the arm's errors, at most, and by the fit's own noise (3 of its standard deviations)
    assert score["position_error_mm"] <= bound + 3 * laser["tcp_std_mm"], score
    assert score["axis_error_deg"] <= turn + 3 * laser["axis_std_deg"], score
    latency = next(p["value"] for p in laser["parameters"] if p["name"] == "latency_ms")
    assert LATENCY_MS[0] <= latency <= LATENCY_MS[1], latency
    assert laser["written_back"] is False  # `cellcal run` writes nothing to the controller
    code, npoint = run_cli(capsys, "tcp-npoint", "--cell", str(franka.path), "--out", str(franka.folder))
    assert code == 0 and npoint["passed_gates"], npoint
    assert npoint["sim_truth"]["position_error_mm"] <= bound, npoint["sim_truth"]
    assert npoint["sim_truth"]["position_error_mm"] <= 0.3  # the cell's tcp_npoint.target_mm


def test_kinematic_fixture_through_cellcal_run(franka, capsys):
    """kinematic-fixture through ``cellcal run --cell sim-franka``, then ``cellcal analyze`` on its
    dataset: 64 seats in the plate's sockets at four placements, each found by force and seated by
    admittance in MuJoCo; its gates pass and the calibrated arm is nearer the truth over the whole
    workspace than the drawing. Measured: 0.040 mm
    mean over 300 random poses against the drawing's 0.568 (seed 7, real time and twice as fast alike);
    the design's own expected error is 0.24 mm (1 sigma) at the 0.03 mm it assumes: the bound."""
    code, result = run_cli(capsys, "kinematic-fixture", "--cell", str(franka.path), "--out", str(franka.folder))
    assert code == 0 and result["passed_gates"], result
    score = result["sim_truth"]
    # as on the UR cell (tests/e2e/test_kinematic_fixture.py): within 2x the plan's own promise and the
    # goal of 0.15 mm; and well below the drawing's error
    design = result["design"]
    assert score["workspace_mean_mm"] < min(2.0 * design["expected_error_mm"], 0.15), (score, design)
    assert score["workspace_mean_mm"] < score["workspace_nominal_mean_mm"] / 4, score
    # what the model misses in the seats, through the CLI on the run's own dataset: the arm sags under
    # gravity in MuJoCo, but its joints are rigid and measured, so the sag is in the joints the model is
    # given, not between them: no cause is named (held-out 0.002 mm, the seating's scatter)
    plate = franka.folder / "bar.yaml"
    plate.write_text(json.dumps({"points": ["s0", "s1"], "distances_mm": [["s0", "s1", 200.0, 0.02]],
                                 "seating_sd_mm": 0.03}))
    code = cli_main(["analyze", "--robot", "franka-fr3", "--data", result["dataset"], "--fixture", str(plate), "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err[-2000:]
    finding = json.loads(out)
    assert finding["cause"] == "none", finding


def press(franka, routine: str) -> dict:
    """One run from the panel, to its end; what a PLC reads then."""
    counter = franka.panel.run_counter()
    franka.panel.select_routine(SELECT[routine])
    franka.panel.press_start()
    deadline = time.monotonic() + 400.0
    while franka.panel.run_counter() == counter:
        assert time.monotonic() < deadline, "the run did not end"
        time.sleep(0.05)
    return plc_reads(franka)


def until_ready(daemon) -> None:
    """Until the service says (its JSON API's /api/v1/state) the robot is ready and owed no frame: a
    lost robot reconnected, a frame a faulted run left changed given back."""
    import re
    import urllib.request

    url = re.search(r"JSON API \(read-only\): (http://\S+/)", daemon.log()).group(1) + "api/v1/state"
    deadline = time.monotonic() + 60.0
    while True:
        with urllib.request.urlopen(url, timeout=5) as answer:
            state = json.loads(answer.read())
        if state["devices"]["robot"] == "ready" and state["frame_owed_by_run"] is None:
            return
        assert time.monotonic() < deadline, (state, daemon.log())
        time.sleep(0.2)


def controller_frame(franka) -> np.ndarray:
    return np.asarray(at_rest(franka)["tcp_offset"], dtype=float)


def test_service_writes_the_frame_back_through_set_ee_and_keeps_it_on_faults(franka):
    """From the panel through the service: tcp-laser's frame written back with set_EE and read back
    from the controller, and tcp-check's verdict on it. Then a collision reflex once the arm has moved
    0.3 s in a motion of a check (injected through the simulator) and a cut connection each end a run
    with the robot-fault code, nothing written and the frame on the controller kept (given back once
    the robot is ready: a run sets its own frame to measure with); the start after a reflex clears it
    (libfranka's error recovery) and checks, and after the cut the service reconnects and checks."""
    daemon = Daemon(franka, franka.folder)
    try:
        before = controller_frame(franka)
        reads = press(franka, "tcp-laser")
        assert reads["code"] == ResultCode.OK, daemon.log()
        written = daemon.cli("runs", "show", "1")
        frame = np.asarray(written["result"]["tool_frame"]["pose_m_rad"], dtype=float)
        on_controller = controller_frame(franka)
        # set_EE carries the frame as doubles and the controller keeps it so: read back to rounding
        assert np.abs(on_controller - frame).max() < 1e-9, (on_controller, frame)
        assert np.abs(on_controller - before).max() > 1e-4  # the drawn frame it replaced
        reads = press(franka, "tcp-check")
        assert reads["code"] == ResultCode.OK and reads["verdict"] == "ok", (reads, daemon.log())

        for fault in ("reflex", "drop"):
            franka.control.request(cmd="fault", kind=fault, after_motion_s=0.3)
            reads = press(franka, "tcp-check")
            assert reads["code"] == ResultCode.ROBOT_FAULT, (fault, daemon.log())
            if fault == "reflex":  # it stays until a start recovers it
                assert franka.control.request(cmd="state")["reflex"] is not None
            if fault == "drop":
                until_ready(daemon)  # reconnected, the frame given back
                assert np.abs(controller_frame(franka) - on_controller).max() < 1e-9
            reads = press(franka, "tcp-check")  # the start after it: recovered, reconnected; the check passes
            assert reads["code"] == ResultCode.OK and reads["verdict"] == "ok", (fault, reads, daemon.log())
            # the frame written before the faults is the one on the controller (an "ok" check writes none)
            assert np.abs(controller_frame(franka) - on_controller).max() < 1e-9, fault
        assert franka.control.request(cmd="state")["reflex"] is None
        assert "protective stop cleared" in daemon.log()
    finally:
        daemon.stop()
