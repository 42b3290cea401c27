"""The routine framework: the motion guard, the dataset on disk, the routine registry.

Every routine is also driven end to end through a robot that records every command it
receives: none outside the cell's limits may ever reach it.
"""
from __future__ import annotations

import copy

import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.drivers.interfaces import DeviceError, RobotState
from cellcal.routines.framework import registry, runner
from cellcal.routines.framework.base import Move, PlanRefused
from cellcal.routines.framework.guard import ArmState, GuardedRobot, MotionGuard
from cellcal.routines.framework.records import Dataset, read_dataset
from cellcal.measurements.table import DatasetError
from cellcal.solvers.geometry.inverse import tcp_poses
from support.routine_checks import RecordingRobot, within_limits  # tests/support/routine_checks.py


@pytest.fixture(scope="module")
def cell():
    return load_cell("sim")


@pytest.fixture(scope="module")
def guard(cell):
    return MotionGuard(cell, load_robot(cell.robot))


def home_state(cell) -> ArmState:
    return ArmState(np.asarray(cell.home_q_rad, dtype=float), cell.tool.tcp_pose)


def home_tcp(cell, guard) -> np.ndarray:
    return home_state(cell).tcp_pose(guard.model)


@pytest.mark.parametrize("make_move, needles", [
    (lambda c, tcp: Move.linear("down to the table", np.r_[tcp[:3] - [0, 0, 0.6], tcp[3:]], 0.1, 1.0),
     ["down to the table", "leaves the workspace box"]),
    (lambda c, tcp: Move.linear("fast sweep", np.r_[tcp[:3] + [0.01, 0, 0], tcp[3:]], 0.5, 1.0),
     ["fast sweep", "tcp_speed_m_s = 0.25"]),
    (lambda c, tcp: Move.joint("wrist wind-up", np.r_[c.home_q_rad[:5], 7.0], 0.5, 1.0),
     ["wrist wind-up", "joint 6", "outside its limits"]),
    (lambda c, tcp: Move.joint("jerk", c.home_q_rad, 0.5, 50.0),
     ["jerk", "joint_accel_rad_s2 = 4"]),
    (lambda c, tcp: Move.contact("long probe", [0, 0, -1], 0.01, 0.2),
     ["long probe", "contact_travel_m = 0.05"]),
])
def test_guard_refuses_a_move_naming_it_and_the_limit(cell, guard, make_move, needles):
    with pytest.raises(PlanRefused) as err:
        guard.check(make_move(cell, home_tcp(cell, guard)), home_state(cell))
    for needle in needles:
        assert needle in str(err.value), str(err.value)


def test_guard_checks_the_path_of_a_joint_move_not_only_its_ends(cell, guard):
    """Shoulder swung far round: both ends in the box, the TCP's path through the wall behind."""
    q_from = np.asarray(cell.home_q_rad, dtype=float)
    q_to = q_from.copy()
    q_to[0] += np.deg2rad(170)
    path = tcp_poses(guard.model, q_from + np.linspace(0, 1, 50)[:, None] * (q_to - q_from), cell.tool.tcp_pose)
    boxed = MotionGuard.__new__(MotionGuard)
    boxed.__dict__.update(guard.__dict__)
    boxed.low = np.minimum(path[0, :3], path[-1, :3]) - 0.01  # a box holding both ends only
    boxed.high = np.maximum(path[0, :3], path[-1, :3]) + 0.01
    assert np.any(path[:, :3] < boxed.low) or np.any(path[:, :3] > boxed.high)
    with pytest.raises(PlanRefused, match="the TCP on the way"):
        boxed.check(Move.joint("swing", q_to, 0.5, 1.0), home_state(cell))


def test_a_refused_command_never_reaches_the_robot(cell, guard):
    with open_drivers(cell) as drivers:
        recording = RecordingRobot(drivers.robot)
        guarded = GuardedRobot(recording, guard)
        tcp = drivers.robot.actual_tcp_pose()
        with pytest.raises(PlanRefused):
            guarded.run(Move.linear("through the floor", np.r_[tcp[:3] - [0, 0, 0.9], tcp[3:]], 0.1, 1.0))
        with pytest.raises(PlanRefused):
            guarded.run(Move.contact("endless search", [1, 0, 0], 0.01, 1.0))
        assert recording.commands == [] and guarded.sent == []
        assert np.allclose(drivers.robot.actual_tcp_pose(), tcp)


# the handshake needs a cell of two robots: test_handshake checks both robots' commands alike
@pytest.mark.parametrize("name", [n for n in registry.available() if n != "handshake"])
def test_every_routine_sends_only_commands_within_the_cell_limits(cell, name, tmp_path):
    if name == "tcp-check":  # a check needs the beams known (else refused before moving): as installed, stated
        cell = copy.deepcopy(cell)
        cell.routines["tcp_check"] = {"beam_std_mm": 0.5}
    prepared = runner.prepare(name, cell)
    model = load_robot(cell.robot)
    with open_drivers(cell) as drivers:
        recording = RecordingRobot(drivers.robot)
        drivers.robot = recording
        runner.measure(prepared, drivers, tmp_path, lambda message: None)
    assert recording.commands, "the routine sent nothing"
    tool = cell.tool.tcp_pose
    for command in recording.commands:
        assert not within_limits(cell, model, command, tool), command


def tcp_laser_from(cell, q, tmp_path) -> list:
    """tcp-laser's commands, run with the arm left at joints `q` (put there as a stop ramp leaves
    it: a controller would refuse such a target); every one checked against the cell's limits."""
    prepared = runner.prepare("tcp-laser", cell)
    model = load_robot(cell.robot)
    with open_drivers(cell) as drivers:
        arm = drivers.world.arm
        arm.q = np.asarray(q, dtype=float)
        arm.set_tcp(arm.tcp_offset)
        recording = RecordingRobot(drivers.robot)
        drivers.robot = recording
        runner.measure(prepared, drivers, tmp_path, lambda message: None)
    assert all(not within_limits(cell, model, c, cell.tool.tcp_pose) for c in recording.commands)
    return recording.commands


def test_a_wrist_left_beyond_its_limits_is_unwound_before_the_plans_first_move(cell, tmp_path):
    """A run aborted during a wrist's turn can leave joint 6 a little beyond a full turn (-360.02
    deg against limits of +-360): the next run turns it back by a turn, the same pose, before its
    plan's first move, instead of refusing that move for a joint outside its limits."""
    q = np.asarray(cell.home_q_rad, dtype=float).copy()
    q[5] = load_robot(cell.robot).joint_limits[5, 0] - np.deg2rad(0.02)  # where the abort left it
    kind, target, _, _ = tcp_laser_from(cell, q, tmp_path)[0]
    assert kind == "joint"
    # a whole turn back: joint 6 at -0.02 deg, the other joints where they were (the same pose)
    np.testing.assert_allclose(target, [*q[:5], q[5] + 2 * np.pi], atol=1e-12)


def test_an_arm_left_away_from_home_goes_home_before_the_plans_first_cartesian_move(cell, tmp_path):
    """A run aborted between two orientations leaves the wrist half a turn on: a straight line from
    there to the plan's first pose would wind it past its limit. Every plan is checked from home,
    so the run goes there first, by a joint move whose path is checked as any other."""
    home = np.asarray(cell.home_q_rad, dtype=float)
    commands = tcp_laser_from(cell, home + np.radians([5.0, -3.0, 4.0, 10.0, -8.0, -170.0]), tmp_path)
    kind, target, _, _ = commands[0]
    assert kind == "joint"
    np.testing.assert_array_equal(target, home)
    assert commands[1][0] != "joint" or not np.array_equal(commands[1][1], home)


def test_a_dataset_round_trips_with_its_header(tmp_path):
    data = Dataset("tcp-laser", {"t_s": np.array([0.1, 0.2]), "edge": np.array(["blocked", "cleared"])},
                   {"speed_m_s": 0.04, "tool_frame_before": np.zeros(6)}, cell="sim", robot="ur10e")
    path = data.write(tmp_path / "a" / "run.csv")
    back = read_dataset(path, "tcp-laser", text_columns=("edge",))
    assert back.complete and back.cell == "sim" and back.robot == "ur10e" and back.version
    assert back.meta == {"speed_m_s": 0.04, "tool_frame_before": [0.0] * 6}
    np.testing.assert_array_equal(back["t_s"], [0.1, 0.2])
    assert list(back["edge"]) == ["blocked", "cleared"]
    assert [p.name for p in path.parent.iterdir()] == ["run.csv"]  # no temporary file left behind


def test_a_dataset_of_another_routine_or_a_broken_one_is_refused_naming_the_line(tmp_path):
    path = Dataset("tcp-stylus", {"x_m": np.array([1.0])}).write(tmp_path / "s.csv")
    with pytest.raises(DatasetError, match="a dataset of routine 'tcp-stylus', not of 'tcp-laser'"):
        read_dataset(path, "tcp-laser")
    text = path.read_text().replace("\n1.0\n", "\nabc\n")
    path.write_text(text)
    with pytest.raises(DatasetError, match=r"s.csv:\d+: column 'x_m': 'abc' is not a number"):
        read_dataset(path, "tcp-stylus")
    (tmp_path / "plain.csv").write_text("x_mm,y_mm\n1,2\n")
    with pytest.raises(DatasetError, match="not a cellcal routine dataset"):
        read_dataset(tmp_path / "plain.csv")


def test_a_routine_section_the_cell_cannot_run_is_refused_at_load(tmp_path):
    from cellcal.config.cell_files import shipped_cells
    from cellcal.config.cells import CellFileError

    text = shipped_cells()["sim"].read_text() + "\nhandshake:\n  points: 12\n"
    (tmp_path / "c.yaml").write_text(text)
    # the handshake's section in a cell of one robot
    with pytest.raises(CellFileError, match=r"\[handshake\].*two robots"):
        load_cell(tmp_path / "c.yaml")


def test_run_refuses_a_device_fault_with_one_message_and_no_dataset(cell, tmp_path, monkeypatch):
    names = registry.available()
    if not names:
        pytest.skip("no routine installed")
    prepared = runner.prepare(names[0], cell)
    with open_drivers(cell) as drivers:
        drivers.world.protective_stop(after_motion_s=0.05)
        with pytest.raises(DeviceError):
            runner.measure(prepared, drivers, tmp_path, lambda message: None)
        assert drivers.robot.state() is RobotState.PROTECTIVE_STOP
    assert list(tmp_path.iterdir()) == []
