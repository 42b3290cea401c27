"""A stylus plate in both simulated cells (in process, and the fake controller behind sim-net): its balls
where the truth placed them, a contact when the real tip's rounding meets a ball (sphere on sphere), no
settling; the socket bar of the shipped cell untouched."""
from __future__ import annotations

import numpy as np

from support.cell_edits import edited_cell  # tests/support/cell_edits.py

from cellcal.config.cell_files import read_cell
from cellcal.sims.fake_ur.controller import FakeUrController
from cellcal.sims.inproc.world import FixtureBall, PivotSocket, world_of_cell
from cellcal.sims.physics.truth import pivot_rest_q

CONTACT_MM = 9.0  # the fixture's stylus_radius_mm: the ball (6 mm) and the sim tool's tip rounding (3 mm)
GAP_M = 1e-6  # either side of touching: far below the 0.02 mm a 10 mm/s search moves in one 2 ms cycle


def _stylus_cell(folder):
    return edited_cell(folder, "sim", lambda doc: doc["kinematic_fixture"]["fixture"].update(
        stylus_radius_mm=CONTACT_MM))


def test_the_shipped_sim_cell_keeps_its_socket_bar():
    world = world_of_cell(read_cell("sim"))
    assert world.sockets and all(isinstance(s, PivotSocket) for s in world.sockets)


def test_both_simulated_cells_hold_the_same_balls_as_the_truth_placed_them(tmp_path):
    path = _stylus_cell(tmp_path)
    cell = read_cell(path)
    world = world_of_cell(cell)
    controller = FakeUrController(cell_file=str(path))
    assert len(world.sockets) == 8 and all(isinstance(b, FixtureBall) for b in world.sockets)  # 4 placements x 2
    for a, b in zip(world.sockets, controller.sockets):
        assert np.array_equal(a.centre_m, b.centre_m) and a.radius_m == b.radius_m
    # the ball is the contact radius less the tip's (true as drawn); each placement off its drawing by the
    # truth's fixture_error_mm (0.5 mm) and its yaw error (0.2 deg at 0.2 m: 0.7 mm), 3 sigma
    assert world.sockets[0].radius_m == np.float64(CONTACT_MM / 1e3 - cell.tool.radius_m)
    drawn = cell.routines["kinematic_fixture"]["placements"][0]["at_m"]
    assert np.linalg.norm(world.sockets[0].centre_m - drawn) < 1e-3 * (0.5 + 3 * 0.7)


def test_the_fake_controller_stops_a_search_where_the_tip_meets_a_ball_and_does_not_settle(tmp_path):
    controller = FakeUrController(cell_file=str(_stylus_cell(tmp_path)))
    truth, ball = controller.truth, controller.sockets[0]
    reach = ball.radius_m + truth.tool.radius_m
    normal = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    q_home = controller.arm.q.copy()
    for gap, touching in ((GAP_M, False), (-GAP_M, True)):
        controller.arm.q = pivot_rest_q(truth, controller.physics, q_home, ball.centre_m + (reach + gap) * normal,
                                        np.zeros(3))
        assert controller._touching(controller.arm.tcp_pose[:3]) is touching
    assert controller._pivot_touch[0] == "ball"  # what was met: a ball, which _settle leaves alone
    assert controller._settle(controller._pivot_touch[1]) is None


def test_a_socket_answers_a_centre_far_from_it_as_the_full_section_does():
    """The socket's quick answer for a centre beyond its section's box (every control cycle asks
    every seat) is the answer of the distance to the whole section, near the box's edges too."""
    socket = PivotSocket(np.array([0.4, -0.1, 0.05]), tool_radius_m=0.003)
    rng = np.random.default_rng(7)
    depth = socket.rim_radius_m / np.tan(socket.half_angle_rad)
    reach = socket.face_radius_m + 0.01
    centres = socket.apex_m + rng.uniform([-reach, -reach, -0.01], [reach, reach, depth + 0.01], size=(4000, 3))

    def full_section(centre, radius):  # the section's distance with no shortcut
        d = centre - socket.apex_m
        p = np.array([np.hypot(d[0], d[1]), d[2]])
        ends = (((0.0, 0.0), (socket.rim_radius_m, depth)),
                ((socket.rim_radius_m, depth), (socket.face_radius_m, depth)))
        gap = min(np.linalg.norm(a + np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1) * (b - a) - p)
                  for a, b in (tuple(map(np.array, e)) for e in ends))
        return None if gap > radius else ("seat" if p[0] < socket.rim_radius_m else "face")

    answers = [socket.touch(c, 0.003) for c in centres]
    assert answers == [full_section(c, 0.003) for c in centres]
    assert answers.count(None) > 100 and answers.count("seat") + answers.count("face") > 100  # both sides met
