"""The UR adapter and the real ur_rtde client against the fake UR controller over loopback.

Each test starts its own fake in another process on its own loopback address (the
controller ports are fixed, so parallel tests cannot share one); fixtures stop every
fake and close every adapter even when a test fails (start_fake, connect and fake are
tests/protocol/conftest.py's).
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytest.importorskip("rtde_control", reason="ur_rtde is not installed")

from cellcal.config.robot_files import load_robot  # noqa: E402
from cellcal.drivers.interfaces import DeviceError, Edge, RobotState  # noqa: E402
from cellcal.drivers.ur.robot import UrRtdeRobot  # noqa: E402
from cellcal.drivers.ur.trigger import UrDigitalInputTrigger  # noqa: E402
from cellcal.solvers.geometry.chain import forward  # noqa: E402
from cellcal.solvers.geometry.se3 import matrix_to_rotvec, rotvec_to_matrix  # noqa: E402

MARGIN_S = 2.0  # scheduling slack on top of a deadline: a 2-core machine with both cores busy wakes a waiter late


def rotation_error_rad(rotvec_a, rotvec_b) -> float:
    return float(np.linalg.norm(matrix_to_rotvec(rotvec_to_matrix(rotvec_b) @ rotvec_to_matrix(rotvec_a).T)))


@pytest.fixture
def robot(fake, connect) -> UrRtdeRobot:
    return connect(UrRtdeRobot, fake.host)


def test_move_j_reaches_the_target_joints(robot, fake):
    target = robot.actual_q() + np.array([0.4, -0.2, 0.3, -0.25, 0.2, -0.5])
    robot.move_j(target, 1.5, 3.0)
    assert np.abs(robot.actual_q() - target).max() < 1e-6
    assert np.abs(np.array(fake.state()["q"]) - target).max() < 1e-6
    assert robot.state() is RobotState.READY


def test_move_l_reaches_the_tcp_pose(robot):
    start = robot.actual_tcp_pose()
    turn = rotvec_to_matrix([0.1, -0.05, 0.2]) @ rotvec_to_matrix(start[3:])
    target = np.concatenate([start[:3] + [0.06, -0.04, 0.05], matrix_to_rotvec(turn)])
    robot.move_l(target, 0.25, 1.2)
    reached = robot.actual_tcp_pose()
    assert np.linalg.norm(reached[:3] - target[:3]) < 1e-5
    assert rotation_error_rad(reached[3:], target[3:]) < 1e-5


def test_set_tcp_moves_the_reported_tcp_as_our_forward_kinematics_predict(robot):
    tool = np.array([0.012, -0.034, 0.187, 0.3, -0.2, 0.1])
    robot.set_tcp(tool)
    assert np.abs(robot.tool_frame() - tool).max() < 1e-12
    q = robot.actual_q()
    model = load_robot("ur10e")
    flange_rot, flange_mm = forward(model.chains["flange"], model.nominal, q[None])
    expected_position = flange_mm[0] / 1000.0 + flange_rot[0] @ tool[:3]
    expected_rotation = matrix_to_rotvec(flange_rot[0] @ rotvec_to_matrix(tool[3:]))
    reported = robot.actual_tcp_pose()
    assert np.linalg.norm(reported[:3] - expected_position) < 1e-6
    assert rotation_error_rad(reported[3:], expected_rotation) < 1e-6


def test_state_samples_are_timestamped_monotonic_and_arrive_at_500_hz(start_fake, connect):
    robot = connect(UrRtdeRobot, start_fake(time_scale=1.0).host)  # the wall's clock: 500 Hz as a real arm
    t_start = robot.samples()[-1].t_s
    deadline = time.monotonic() + 10.0
    while robot.samples()[-1].t_s < t_start + 1.0 and time.monotonic() < deadline:
        time.sleep(0.05)
    samples = robot.samples(since_t_s=t_start)
    times = np.array([s.t_s for s in samples])
    assert np.all(np.diff(times) > 0)
    assert np.allclose(np.diff(times), 0.002, atol=1e-9)  # every controller cycle, none lost
    in_one_second = np.count_nonzero(times <= t_start + 1.0)
    assert 450 <= in_one_second <= 550
    assert all(s.q_rad.shape == (6,) and s.tcp_pose.shape == (6,) for s in samples)


def test_move_until_contact_stops_on_a_plane_and_on_a_stylus_tip(start_fake, connect):
    fake = start_fake()
    robot = connect(UrRtdeRobot, fake.host)
    start = robot.actual_tcp_pose()
    plane_z = start[2] - 0.015
    fake.request(cmd="add_model", model={"kind": "plane", "point_m": [0, 0, plane_z], "normal": [0, 0, 1]})
    result = robot.move_until_contact([0, 0, -0.02], timeout_s=5.0)
    assert result.contact
    assert abs(result.tcp_pose[2] - plane_z) < 0.5e-3
    assert abs(fake.state()["tcp_pose"][2] - plane_z) < 0.5e-3

    robot.move_l(start, 0.25, 1.2)
    stylus_centre = start[:3] + [0.002, -0.0015, -0.010]  # above the plane, a little off the TCP's path
    stylus_radius = 0.004
    fake.request(cmd="add_model", model={"kind": "sphere", "centre_m": stylus_centre.tolist(),
                                         "radius_m": stylus_radius})
    result = robot.move_until_contact([0, 0, -0.02], timeout_s=5.0)
    assert result.contact
    assert abs(np.linalg.norm(result.tcp_pose[:3] - stylus_centre) - stylus_radius) < 0.5e-3


def test_move_until_contact_without_a_contact_stops_at_the_timeout(robot, fake):
    timeout_s = 0.6
    t0, controller_t0_s = time.monotonic(), robot.samples()[-1].t_s
    result = robot.move_until_contact([0.0, 0.03, 0.0], timeout_s=timeout_s)
    elapsed = time.monotonic() - t0
    assert not result.contact
    # never before its timeout on the controller's clock, the clock the search moves by
    assert robot.samples()[-1].t_s - controller_t0_s >= timeout_s
    # after it, stopping the program is one dashboard command (command_timeout_s); the fake's clock is the wall's
    assert elapsed < timeout_s + robot.command_timeout_s, elapsed
    time.sleep(0.2)
    assert not fake.state()["moving"]
    target = robot.actual_q() + 0.05  # the robot takes commands again afterwards
    robot.move_j(target, 1.0, 2.0)
    assert np.abs(robot.actual_q() - target).max() < 1e-6


def test_a_contact_search_on_a_faster_clock_travels_no_farther_than_its_timeout_allows(start_fake, connect):
    """The fake's clock twice the wall's: a search that meets nothing stops after timeout_s of the
    controller's time, so it travels speed x timeout_s as on a real arm, not twice as far."""
    time_scale = 2.0
    fake = start_fake(time_scale=time_scale)
    robot = connect(UrRtdeRobot, fake.host)
    speed_m_s, timeout_s = 0.03, 2.0
    start = robot.actual_tcp_pose()
    result = robot.move_until_contact([0.0, speed_m_s, 0.0], timeout_s=timeout_s)
    assert not result.contact
    travel_m, planned_m = float(np.linalg.norm(result.tcp_pose[:3] - start[:3])), speed_m_s * timeout_s
    # at least the plan's travel less the ramp up to speed (half of speed / contact accel at each end);
    # below the midpoint between the plan (1x) and what a deadline on the wall clock lets it run (2x): the
    # rest is the stop's latency (one dashboard command; 30 mm is 1 s of the controller's time, 0.5 s of the wall)
    ramp_m = speed_m_s ** 2 / robot.contact_accel_m_s2
    assert planned_m - ramp_m <= travel_m < (1 + time_scale) / 2 * planned_m, travel_m


@pytest.mark.parametrize("fault, state", [("protective_stop", RobotState.PROTECTIVE_STOP),
                                          ("emergency_stop", RobotState.EMERGENCY_STOP)])
def test_safety_stop_during_a_move_raises_naming_the_robot_and_the_arm_stays_put(robot, fake, fault, state):
    target = robot.actual_q() + np.array([1.0, 0, 0, 0, 0, 0])
    fake.fault(fault, after_motion_s=0.2)
    with pytest.raises(DeviceError) as raised:
        robot.move_j(target, 0.5, 1.0)
    assert f"UR robot at {fake.host}" in str(raised.value)
    assert f"{fault.replace('_', ' ')} during move_j" in str(raised.value)
    first = fake.state()
    time.sleep(0.3)
    second = fake.state()
    assert not second["moving"]
    assert np.abs(np.array(first["q"]) - second["q"]).max() == 0.0
    assert np.abs(np.array(second["q"]) - target).max() > 0.5  # stopped well short of the target
    assert robot.state() is state


def test_stop_from_another_thread_ends_the_move_and_the_robot_takes_commands_again(robot, fake):
    target = robot.actual_q() + np.array([1.0, 0, 0, 0, 0, 0])
    threading.Timer(0.4, robot.stop).start()
    with pytest.raises(DeviceError, match="move_j ended before its target"):
        robot.move_j(target, 0.5, 1.0)
    time.sleep(0.1)
    first = fake.state()
    time.sleep(0.2)
    assert not fake.state()["moving"] and fake.state()["q"] == first["q"]
    robot.move_j(target, 1.0, 2.0)
    assert np.abs(robot.actual_q() - target).max() < 1e-6


def test_connection_refused_raises_device_error_within_5_s(loopback_host):
    host, connect_timeout_s = loopback_host, 2.0  # nothing listens there
    t0 = time.monotonic()
    with pytest.raises(DeviceError) as raised:
        UrRtdeRobot(host, connect_timeout_s=connect_timeout_s)
    # the probe's own limit, well short of the ur_rtde child's start-up wait (connect_timeout_s + 10 s)
    assert time.monotonic() - t0 < connect_timeout_s + MARGIN_S
    assert f"UR robot at {host}" in str(raised.value)
    assert "refused" in str(raised.value)


def test_controller_killed_during_a_move_raises_device_error_without_hanging(robot, fake):
    target = robot.actual_q() + np.array([1.5, 0, 0, 0, 0, 0])
    killed_at = []
    threading.Timer(0.4, lambda: (killed_at.append(time.monotonic()), fake.kill())).start()
    with pytest.raises(DeviceError) as raised:
        robot.move_j(target, 0.5, 1.0)
    # the stream notices a lost link within stale_after_s; the move's own deadline (2 x 3.5 s + 2 s) is far off
    assert time.monotonic() - killed_at[0] < robot.state_stream.stale_after_s + MARGIN_S
    assert f"UR robot at {fake.host}" in str(raised.value)
    assert robot.state() is RobotState.DISCONNECTED
    with pytest.raises(DeviceError):
        robot.actual_q()


@pytest.mark.parametrize("fault, words", [("stall", "no state from the controller"),
                                          ("drop", "connection to the controller lost")])
def test_stalled_or_dropped_controller_fails_the_move_within_a_second(robot, fake, fault, words):
    target = robot.actual_q() + np.array([1.5, 0, 0, 0, 0, 0])
    fault_after_s = 0.2
    fake.fault(fault, after_motion_s=fault_after_s)
    t0 = time.monotonic()
    with pytest.raises(DeviceError) as raised:
        robot.move_j(target, 0.5, 1.0)
    # silence is a failure after stale_after_s; the move's own deadline (2 x 3.5 s + 2 s) is far off
    assert time.monotonic() - t0 < fault_after_s + robot.state_stream.stale_after_s + MARGIN_S
    assert words in str(raised.value) and "during move_j" in str(raised.value)


def test_beam_edges_on_the_robot_inputs_are_timed_on_the_controller_clock(start_fake, connect):
    fake = start_fake()
    robot = connect(UrRtdeRobot, fake.host)
    start = robot.actual_tcp_pose()
    beam_x, radius = start[0] + 0.03, 0.001
    fake.request(cmd="add_model", model={"kind": "beam", "point_m": [beam_x, start[1], start[2]],
                                         "direction": [0, 0, 1], "radius_m": radius, "channel": 2})
    own = connect(UrDigitalInputTrigger, fake.host, channels=(2,))
    shared = connect(UrDigitalInputTrigger, stream=robot.state_stream, channels=(2,))
    robot.move_l(np.concatenate([start[:3] + [0.06, 0, 0], start[3:]]), 0.1, 1.0)
    events = []
    deadline = time.monotonic() + 5.0  # the trigger's own connection may lag the robot's
    while len(events) < 2 and time.monotonic() < deadline:
        events += own.events(timeout_s=0.5)
    assert [e.edge for e in events] == [Edge.BLOCKED, Edge.CLEARED]
    assert all(e.channel == 2 and e.device_time for e in events)
    assert [e.t_s for e in shared.events()] == [e.t_s for e in events]
    by_time = {s.t_s: s.tcp_pose[0] for s in robot.samples()}
    step_m = 0.1 * 0.002  # one controller cycle at 0.1 m/s
    for event, edge_x in zip(events, (beam_x - radius, beam_x + radius)):
        # the event is the first controller cycle with the new level: the edge lies within the last step
        assert -1e-9 <= by_time[event.t_s] - edge_x <= step_m + 1e-9


def test_adapter_sets_digital_outputs_through_the_io_interface(robot, fake):
    robot.set_digital_output(4, True)
    robot.set_digital_output(10, True)
    robot.set_digital_output(4, False)
    assert fake.state()["digital_outputs"] == 1 << 10


def test_io_interface_sets_digital_outputs_seen_in_the_state_stream(fake):
    import rtde_io
    import rtde_receive

    receive = rtde_receive.RTDEReceiveInterface(fake.host, -1.0, ["timestamp", "actual_digital_output_bits"])
    io = rtde_io.RTDEIOInterface(fake.host)
    try:
        assert io.setStandardDigitalOut(3, True)
        assert io.setConfigurableDigitalOut(1, True)
        deadline = time.monotonic() + 1.0
        while receive.getActualDigitalOutputBits() != (1 << 3) | (1 << 9) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert receive.getActualDigitalOutputBits() == (1 << 3) | (1 << 9)
        assert fake.state()["digital_outputs"] == (1 << 3) | (1 << 9)
    finally:
        io.disconnect()
        receive.disconnect()


def test_control_script_on_the_upper_register_range_is_served(fake):
    import rtde_control
    import rtde_receive

    flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT | rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
    control = rtde_control.RTDEControlInterface(fake.host, -1.0, flags)
    receive = rtde_receive.RTDEReceiveInterface(fake.host, -1.0, ["timestamp", "actual_q"])
    try:
        target = np.array(receive.getActualQ()) + 0.1
        assert control.moveJ(target.tolist(), 1.0, 2.0)
        assert np.abs(np.array(fake.state()["q"]) - target).max() < 1e-9
        assert "register offsets 24/24" in " ".join(fake.state()["messages"])
    finally:
        control.stopScript()
        control.disconnect()
        receive.disconnect()


def exact_cell(tmp_path):
    """The sim-net cell file with the arm's repeatability 0 (it goes exactly where it is sent),
    its truth and its path."""
    from support.cell_edits import edited_cell
    from cellcal.config.cell_files import read_cell
    from cellcal.sims.physics.truth import truth_of_cell

    path = edited_cell(tmp_path, "sim-net", {"sim_truth": {"repeatability_mm": 0.0}})
    cell = read_cell(path)
    assert cell.sim_truth.repeatability_mm == 0.0
    return cell, truth_of_cell(cell, load_robot(cell.robot)), path


def test_a_fake_given_a_cell_file_touches_with_the_real_tool_on_the_real_stylus(start_fake, connect, tmp_path):
    """With the cell's truth (repeatability 0 here, so the arm goes exactly where the controller
    puts it), moveUntilContact ends where the real tool, on the arm as built, touches the real
    stylus: the controller backs off to the last cycle before the contact, so the real gap is
    between 0 and one cycle's travel; the drawing (tool and stylus as the file says) would put
    the contact elsewhere."""
    from cellcal.sims.physics.arm_motion import ArmKinematics
    from cellcal.sims.physics.truth import segment_point_distance

    cell, truth, path = exact_cell(tmp_path)
    fake = start_fake(cell_file=str(path))
    robot = connect(UrRtdeRobot, fake.host)
    robot.set_tcp(cell.tool.tcp_pose)
    stylus, speed = cell.stylus["centre_m"], 0.01
    robot.move_l(np.concatenate([stylus + [0.0, 0.0, 0.01], robot.actual_tcp_pose()[3:]]), 0.25, 1.0)
    result = robot.move_until_contact([0.0, 0.0, -speed], timeout_s=5.0)
    assert result.contact
    physics = ArmKinematics(load_robot(cell.robot), truth.arm_params)
    front, back = truth.tool.segment(*physics.flange(result.q_rad))
    gap = segment_point_distance(front, back, truth.stylus.centre_m) - truth.stylus.radius_m - truth.tool.radius_m
    assert -1e-9 <= gap <= speed * 0.002 + 1e-6, gap
    assert np.allclose(fake.request(cmd="tool")["tool_body_m"][0], front, atol=1e-9)
    drawn_front = robot.actual_tcp_pose()[:3] - np.array([0.0, 0.0, -1.0]) * cell.tool.radius_m
    drawn_gap = np.linalg.norm(drawn_front - stylus) - cell.stylus["radius_m"] - cell.tool.radius_m
    assert abs(drawn_gap - gap) > 0.1e-3, (drawn_gap, gap)


def test_a_fake_given_a_cell_file_seats_the_tool_in_the_pivot_as_the_in_process_cell_does(start_fake, connect,
                                                                                         tmp_path):
    """A contact search onto the real pivot's socket: the tip slides into the seat (the cell's
    compliance), so the real tip's rounding rests centred on the seat, and the controller
    reports the same pose as the in-process cell built from the same file."""
    from cellcal.sims.inproc.devices import SimRobot
    from cellcal.sims.inproc.world import world_of_cell

    cell, truth, path = exact_cell(tmp_path)
    fake = start_fake(cell_file=str(path))
    robots = [connect(UrRtdeRobot, fake.host), SimRobot(world_of_cell(cell))]
    results = []
    for robot in robots:
        robot.set_tcp(cell.tool.tcp_pose)
        robot.move_l(np.concatenate([cell.pivot_m + [0.0, 0.0, 0.005], robot.actual_tcp_pose()[3:]]), 0.25, 1.0)
        results.append(robot.move_until_contact([0.0, 0.0, -0.01], timeout_s=5.0))
    assert all(r.contact for r in results)
    seat = truth.pivot_m + [0.0, 0.0, truth.tool.radius_m]
    assert np.linalg.norm(np.array(fake.request(cmd="tool")["tool_body_m"][0]) - seat) < 1e-6
    assert np.linalg.norm(results[0].tcp_pose[:3] - results[1].tcp_pose[:3]) < 1e-6
    assert np.linalg.norm(results[0].tcp_pose[:3] - (cell.pivot_m + [0.0, 0.0, 0.005])) > 0.004  # it went down
