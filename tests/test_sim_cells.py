"""Cell files, the in-process simulated cell and the same cell over loopback (sim-net).

A light-barrier sweep is the measurement every TCP routine rests on: the trigger's edge
times, matched against the robot's sample stream, must put the TCP on the beam. The
in-process cell times edges between controller cycles (with the sensor's latency and
jitter); the networked cell sees them at the first controller cycle with the new level,
so both must agree to within one cycle's travel.
"""
from __future__ import annotations

import itertools
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cellcal.daemon.cells import CellFileError, load_cell, open_drivers, shipped_cells
from cellcal.daemon.cli import main as cli_main
from cellcal.drivers.interfaces import DeviceError, Edge, RobotState
from cellcal.sims.truth import segment_line_distance

SPEEDS_M_S = (0.02, 0.04, 0.1)
SWEEP_HALF_M = 0.015  # the sweep runs this far either side of the beam
_HOSTS = (f"127.9.{os.getpid() % 250 + 1}.{n}" for n in itertools.cycle(range(1, 255)))


# -- helpers ---------------------------------------------------------------------------

def shipped_text(name: str) -> str:
    return shipped_cells()[name].read_text()


def write_cell(tmp_path: Path, text: str, name: str = "cell.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def without_sections(text: str, *names: str) -> str:
    """A cell file's text without the named top-level sections."""
    kept, skipping = [], False
    for line in text.splitlines(keepends=True):
        if line[:1].strip() and not line.startswith("#"):
            skipping = line.split(":")[0] in names
        if not skipping:
            kept.append(line)
    return "".join(kept)


def net_cell_file(tmp_path: Path, host: str) -> Path:
    """The shipped sim-net cell moved to another loopback address."""
    return write_cell(tmp_path, shipped_text("sim-net").replace("127.0.0.1", host), "sim-net.yaml")


def sweep_through_beam(robot, trigger, beam, speeds=SPEEDS_M_S, timeout_s: float = 5.0):
    """Down through `beam` (a BeamSpec) with the controller's TCP, at each speed, from the
    same start; the edges of each sweep on the beam's channel."""
    home = robot.actual_tcp_pose()
    z_beam = beam.point_m[2]
    start = np.concatenate([[beam.point_m[0], beam.point_m[1], z_beam + SWEEP_HALF_M], home[3:]])
    end = np.concatenate([[beam.point_m[0], beam.point_m[1], z_beam - SWEEP_HALF_M], home[3:]])
    sweeps = []
    for speed in speeds:
        robot.move_l(start, 0.25, 1.0)
        trigger.events()  # edges of the way back up are not this sweep's
        robot.move_l(end, speed, 1.0)
        events, deadline = [], time.monotonic() + timeout_s
        while len(events) < 2 and time.monotonic() < deadline:
            events += [e for e in trigger.events(timeout_s=0.5) if e.channel == beam.channel]
        assert [e.edge for e in events] == [Edge.BLOCKED, Edge.CLEARED], f"sweep at {speed} m/s: {events}"
        sweeps.append(events)
    return sweeps


def sweep_tool_across_beams(robot, trigger, cell, speed: float):
    """The tool, set to its drawing, swept along x across the beams' crossing with its tip
    5 mm below the beam plane: each beam is blocked and cleared once by the tool's body."""
    robot.set_tcp(cell.tool.tcp_pose)
    crossing = cell.beams[0].point_m
    home = robot.actual_tcp_pose()
    start = np.concatenate([crossing + [-0.02, 0.0, -0.005], home[3:]])
    end = np.concatenate([crossing + [0.02, 0.0, -0.005], home[3:]])
    robot.move_l(start, 0.25, 1.0)
    trigger.events()
    robot.move_l(end, speed, 1.0)
    return trigger.events(timeout_s=0.5)


def tcp_at(robot, t_s: float) -> np.ndarray:
    """The TCP position at a time, interpolated in the robot's sample stream."""
    samples = robot.samples()
    t = np.array([s.t_s for s in samples])
    xyz = np.array([s.tcp_pose[:3] for s in samples])
    assert t[0] <= t_s <= t[-1], "the edge lies outside the buffered samples"
    return np.array([np.interp(t_s, t, xyz[:, k]) for k in range(3)])


def distance_to_beam(beam: dict, position: np.ndarray) -> float:
    d = np.asarray(beam["direction"], dtype=float)
    d /= np.linalg.norm(d)
    off = position - np.asarray(beam["point_m"])
    return float(np.linalg.norm(off - (off @ d) * d))


# -- cell files ------------------------------------------------------------------------

def test_shipped_cells_load():
    for name in ("sim", "sim-net"):
        cell = load_cell(name)
        assert cell.robot == "ur10e" and len(cell.home_q_rad) == 6
    assert {spec.name for spec in load_cell("sim").drivers.values()} == {"sim"}
    assert "sim" not in {spec.name for spec in load_cell("sim-net").drivers.values()}


@pytest.mark.parametrize("old, new, section, key, what", [
    ("  tcp_speed_m_s: 0.25", "  tcp_speed_m_s: 0.25\n  tcp_sped_m_s: 0.3", "limits", "tcp_sped_m_s",
     "unknown key"),
    ("  min_m: [-1.2, -1.0, 0.05]", "  min_m: low", "workspace", "min_m", "not a list of 3 numbers"),
    ("radius_m: 0.0002, channel: 1}", "radius_m: -0.001, channel: 1}", "beams[1]", "radius_m", "out of range"),
    ("  radius_m: 0.003", "  radius_m: 0.003\n  radius: 0.003", "tool", "radius", "unknown key"),
    ("  trigger: {driver: sim}", "  trigger: {driver: laser}", "drivers.trigger", "driver",
     "no trigger driver named 'laser'"),
    ("  trigger_jitter_s: 0.0005", "  trigger_jitter_s: yes", "sim_truth", "trigger_jitter_s", "is not a number"),
])
def test_load_cell_names_file_section_and_key(tmp_path, old, new, section, key, what):
    text = shipped_text("sim")
    assert old in text
    path = write_cell(tmp_path, text.replace(old, new))
    with pytest.raises(CellFileError) as info:
        load_cell(path)
    message = str(info.value)
    assert message.startswith(str(path)) and f"[{section}.{key}]" in message and what in message, message


@pytest.mark.parametrize("old, new, key, what", [
    ("port: 5030}", "prot: 5030}", "prot", "unknown option (options of the socket tracker driver: "),
    ("port: 5030}", "port: 70000}", "port", "70000 is out of range (must be in 1..65535)"),
    ("port: 5030}", "port: 5030, connect_timeout_s: 0}", "connect_timeout_s", "out of range"),
])
def test_load_cell_checks_driver_options_naming_file_section_and_key(tmp_path, old, new, key, what):
    text = shipped_text("sim-net")
    line = next(t for t in text.splitlines() if t.startswith("  tracker:"))
    path = write_cell(tmp_path, text.replace(line, line.replace(old, new)))
    with pytest.raises(CellFileError) as info:
        load_cell(path)
    message = str(info.value)
    assert message.startswith(str(path)) and f"[drivers.tracker.{key}]" in message and what in message, message


def test_load_cell_refuses_a_missing_section_and_a_repeated_key(tmp_path):
    text = shipped_text("sim")
    with pytest.raises(CellFileError, match=r"section \[limits\] is missing"):
        load_cell(write_cell(tmp_path, text.replace("limits:", "limits_old:"), "a.yaml"))
    with pytest.raises(CellFileError, match="given twice"):
        load_cell(write_cell(tmp_path, text.replace("  seed: 7", "  seed: 7\n  seed: 8"), "b.yaml"))


# -- the in-process cell ---------------------------------------------------------------

@pytest.fixture
def sim_cell():
    cell = load_cell("sim")
    with open_drivers(cell) as drivers:
        yield cell, drivers


@pytest.mark.parametrize("speed", SPEEDS_M_S)
def test_edges_put_the_real_tool_on_the_real_beams(sim_cell, speed):
    """The truth decides: where the edge says, less the sensor's true latency, the real tool
    body (the arm as built, the tool as it really is) touches the real beam."""
    cell, drivers = sim_cell
    world, truth = drivers.world, drivers.world.truth
    t0 = time.perf_counter()
    events = sweep_tool_across_beams(drivers.robot, drivers.trigger, cell, speed)
    assert time.perf_counter() - t0 < 5.0  # simulated time: no real waiting
    assert sorted((e.channel, e.edge.value) for e in events) == [
        (0, "blocked"), (0, "cleared"), (1, "blocked"), (1, "cleared")], events
    samples = drivers.robot.samples()
    t = np.array([s.t_s for s in samples])
    q = np.array([s.q_rad for s in samples])
    beams = {b.channel: b for b in truth.beams}
    for event in events:
        assert event.device_time
        t_true = event.t_s - truth.trigger_latency_s
        q_then = np.array([np.interp(t_true, t, q[:, j]) for j in range(q.shape[1])])
        body = world.tool_body(q_then)
        beam = beams[event.channel]
        d = beam.direction / np.linalg.norm(beam.direction)
        gap = segment_line_distance(body[0], body[1], beam.point_m, d) - beam.radius_m - truth.tool.radius_m
        assert abs(gap) <= speed * truth.trigger_jitter_s + 2e-6, (event, gap)
    # and the drawing is not the truth: the nominal beam would put the edges elsewhere
    assert np.linalg.norm(truth.beams[0].point_m - cell.beams[0].point_m) > 1e-4


def test_sim_robot_refuses_what_the_cell_forbids(sim_cell):
    cell, drivers = sim_cell
    robot, home = drivers.robot, drivers.robot.actual_tcp_pose()
    with pytest.raises(DeviceError, match="outside the workspace box"):
        robot.move_l(np.concatenate([[home[0], home[1], 0.01], home[3:]]), 0.1, 1.0)
    with pytest.raises(DeviceError, match="above the cell's limit"):
        robot.move_l(home, cell.limits["tcp_speed_m_s"] * 2, 1.0)
    with pytest.raises(DeviceError, match="above the cell's limit"):
        robot.move_j(robot.actual_q(), 10.0, 1.0)
    assert np.allclose(robot.actual_tcp_pose(), home)  # nothing moved


def test_protective_stop_halts_the_move_and_blocks_the_next(sim_cell):
    _, drivers = sim_cell
    robot, world = drivers.robot, drivers.world
    home = robot.actual_tcp_pose()
    world.protective_stop(after_motion_s=0.2)
    with pytest.raises(DeviceError, match="protective stop"):
        robot.move_l(np.concatenate([home[:3] + [0, 0, -0.1], home[3:]]), 0.1, 1.0)
    assert robot.state() is RobotState.PROTECTIVE_STOP
    assert 0.015 < home[2] - robot.actual_tcp_pose()[2] < 0.03  # stopped after about 0.2 s
    with pytest.raises(DeviceError, match="not ready"):
        robot.move_l(home, 0.1, 1.0)
    world.reset_protective_stop()
    robot.move_l(home, 0.1, 1.0)
    assert np.allclose(robot.actual_tcp_pose()[:3], home[:3], atol=1e-9)


def test_sim_panel_and_tracker(sim_cell):
    _, drivers = sim_cell
    panel, tracker = drivers.panel, drivers.tracker
    assert not panel.start_requested()
    panel.press_start()
    assert panel.start_requested() and not panel.start_requested()  # once per press
    panel.set_lamps(busy=True)
    panel.set_result(0)
    assert panel.lamps["busy"] and panel.run_counter == 1
    measured = tracker.measure("smr1")
    # the target is on the real tool tip, 150 mm out from the flange the controller reports
    assert np.linalg.norm(measured.position_m - drivers.world.tool_tip_m()) < 10 * measured.quality
    assert np.linalg.norm(measured.position_m - drivers.robot.actual_tcp_pose()[:3]) > 0.14
    with pytest.raises(DeviceError, match="target not found"):
        tracker.measure("smr9")


# -- the same cell over loopback -------------------------------------------------------

def test_sim_net_sweep_matches_the_in_process_cell(tmp_path):
    from cellcal.sims.net_cell import SimCell

    # the in-process cell with a point probe at the controller's TCP and the beams as drawn,
    # as the networked fakes have them
    text = without_sections(shipped_text("sim"), "tool", "sim_truth") + "sim_truth: {fixture_error_mm: 0.0}\n"
    in_process = load_cell(write_cell(tmp_path, text))
    with open_drivers(in_process) as drivers:
        local = [[tcp_at(drivers.robot, e.t_s) for e in events]
                 for events in sweep_through_beam(drivers.robot, drivers.trigger, in_process.beams[0])]
    net = load_cell("sim-net").on_host(next(_HOSTS))
    with SimCell(net):
        with open_drivers(net) as drivers:
            remote = [[tcp_at(drivers.robot, e.t_s) for e in events]
                      for events in sweep_through_beam(drivers.robot, drivers.trigger, net.beams[0])]
    for speed, a, b in zip(SPEEDS_M_S, local, remote):
        for p_local, p_net in zip(a, b):
            assert np.linalg.norm(p_local - p_net) < 0.0005, (speed, p_local, p_net)


def test_sim_cell_command_prints_one_line_and_stops_on_sigterm(tmp_path):
    host = next(_HOSTS)
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.daemon.cli", "sim-cell",
                             "--cell", str(net_cell_file(tmp_path, host))],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line == (f"cellcal sim-cell: listening: ur {host} (30004, 29999, 30003), "
                        f"modbus {host}:5020, tracker {host}:5030\n"), proc.stderr.read() if not line else line
        with socket.create_connection((host, 5030), timeout=2.0):
            pass
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=5.0) == 0
        assert proc.stdout.read() == ""  # exactly one line
        for port in (5020, 5030, 30004):  # every port released
            with pytest.raises(OSError):
                socket.create_connection((host, port), timeout=1.0).close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_sim_cell_command_exit_codes(tmp_path, capsys):
    bad = write_cell(tmp_path, shipped_text("sim-net").replace("limits:", "limits:\n  tcp_speed_m_sx: 1"))
    assert cli_main(["sim-cell", "--cell", str(bad)]) == 2
    assert "[limits.tcp_speed_m_sx]: unknown key" in capsys.readouterr().err
    host = next(_HOSTS)
    with socket.socket() as occupant:
        occupant.bind((host, 5020))
        occupant.listen()
        assert cli_main(["sim-cell", "--cell", str(net_cell_file(tmp_path, host))]) == 1
    assert f"cannot listen on {host}:5020: in use" in capsys.readouterr().err
