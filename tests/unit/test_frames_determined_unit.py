"""A routine writes only what it determined: the frame-composition helper
(routines/framework/tool_frame.py and its maths in solvers/geometry/se3.py), the gates that compare only what
a result determined (routines/framework/gates.py), the words that print a tool frame next to the
axis tilts (routines/framework/base.py frame_text), and the frames owed back to a cell's other robots
(routines/framework/frames_owed.py).

The end-to-end chain (tcp-laser, then tcp-npoint, then tcf through the service on the
simulated cell) is tests/e2e/test_frames_determined.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from cellcal.config.cells import ToolSpec
from cellcal.drivers.interfaces import DeviceError, RobotState
from cellcal.routines.framework import gates, tool_frame
from cellcal.routines.framework.frames_owed import FramesOwed
from cellcal.routines.framework.base import Result, frame_text
from cellcal.solvers.geometry import se3

RNG = np.random.default_rng(18)
EXACT = 1e-12  # pure rotation algebra in float64: nothing but rounding separates the two sides


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def random_units(n: int) -> np.ndarray:
    return np.array([unit(v) for v in RNG.normal(size=(n, 3))])


def turn_about(rotvec_before, rotvec_after) -> np.ndarray:
    """The rotation vector of the turn that takes orientation `before` to `after` (flange frame)."""
    return se3.matrix_to_rotvec(se3.rotvec_to_matrix(rotvec_after) @ se3.rotvec_to_matrix(rotvec_before).T)


# -- solvers/geometry/se3.py --------------------------------------------------------------------------


@pytest.mark.parametrize("a, b", list(zip(random_units(6), random_units(6))))
def test_turn_between_is_the_smallest_turn_taking_one_direction_onto_the_other(a, b):
    turn = se3.turn_between(a, b)
    np.testing.assert_allclose(se3.rotvec_to_matrix(turn) @ a, b, atol=EXACT)
    # the smallest such turn: its angle is the angle between them, about an axis across both
    assert np.linalg.norm(turn) == pytest.approx(np.arccos(np.clip(a @ b, -1, 1)), abs=1e-9)
    assert abs(turn @ a) < 1e-9 and abs(turn @ b) < 1e-9


@pytest.mark.parametrize("a", [[0, 0, 1], [1, 0, 0], [0.3, -0.2, 0.9]])
def test_turn_between_opposite_directions_is_a_half_turn_and_from_z_it_is_rotvec_from_z(a):
    a = unit(a)
    half = se3.turn_between(a, -a)
    np.testing.assert_allclose(se3.rotvec_to_matrix(half) @ a, -a, atol=EXACT)
    assert np.linalg.norm(half) == pytest.approx(np.pi) and abs(half @ a) < EXACT
    for b in [*random_units(4), np.array([0.0, 0.0, -1.0])]:
        np.testing.assert_allclose(se3.turn_between([0, 0, 1], b), se3.rotvec_from_z(b), atol=EXACT)


@pytest.mark.parametrize("rotvec, axis", list(zip(RNG.normal(scale=0.8, size=(6, 3)), random_units(6))))
def test_with_z_axis_puts_z_on_the_axis_and_keeps_the_turn_about_it(rotvec, axis):
    turned = se3.with_z_axis(rotvec, axis)
    np.testing.assert_allclose(se3.rotvec_to_matrix(turned)[:, 2], axis, atol=1e-12)
    # the turn applied is about a direction across the old z and the new one: no twist about either
    turn = turn_about(rotvec, turned)
    z_before = se3.rotvec_to_matrix(rotvec)[:, 2]
    assert abs(turn @ z_before) < 1e-9 and abs(turn @ axis) < 1e-9
    np.testing.assert_allclose(se3.with_z_axis(rotvec, z_before), rotvec, atol=1e-12)  # already there: unchanged


def test_z_axis_lean_is_the_axis_tilt_not_the_rotation_vector():
    """Issue 18's numbers: the frame printed as rx 0.4838 ry 0.0486 deg while the parameters said
    axis_tilt_x_deg 0.0486 / axis_tilt_y_deg -0.4838: a lean toward x is a turn about y."""
    toward_x, toward_y = np.degrees(se3.z_axis_lean(np.radians([0.4838, 0.0486, 0.0])))
    # at half a degree the lean and the rotation vector part differ by ~1e-6 deg (second order)
    assert toward_x == pytest.approx(0.0486, abs=1e-5) and toward_y == pytest.approx(-0.4838, abs=1e-5)


# -- routines/framework/tool_frame.py ------------------------------------------------------------------

DRAWN = np.array([0.0, 0.0, 0.150, 0.0, 0.0, 0.0])
# a calibrated frame on the controller: tip off the drawing, axis tilted 0.5 deg, turned 30 deg about it
CONTROLLER = np.concatenate([[0.0004, -0.0003, 0.1492],
                             se3.matrix_to_rotvec(se3.rotvec_to_matrix(np.radians([0.3, -0.4, 0.0]))
                                                  @ se3.rot("z", np.radians(30.0)))])
FOUND_TIP = np.array([0.0006, -0.0002, 0.1489])
FOUND_AXIS = unit([0.004, 0.007, 1.0])


def test_the_reference_is_the_controllers_frame_when_one_is_known():
    ref = tool_frame.reference(CONTROLLER, DRAWN)
    assert ref.from_controller and np.array_equal(ref.pose, CONTROLLER) and ref.notes == ()
    assert "controller's tool frame from before the run" in ref.source


@pytest.mark.parametrize("before", [None, np.zeros(6), [0.0] * 6, [float("nan")] * 6])
def test_without_a_known_controller_frame_the_reference_is_the_drawing_and_a_note_says_so(before):
    ref = tool_frame.reference(before, DRAWN)
    assert not ref.from_controller and np.array_equal(ref.pose, DRAWN)
    assert len(ref.notes) == 1 and "no tool frame of the controller's" in ref.notes[0] and "drawn" in ref.notes[0]


def test_a_cell_file_option_stands_in_for_the_drawing_but_never_over_a_known_controller_frame():
    stated_tip = np.array([0.0, 0.0, 0.149])
    ref = tool_frame.reference(None, DRAWN, tip_m=stated_tip, tip_option="tcp_mm of [tcf]")
    assert np.array_equal(ref.pose[:3], stated_tip) and "tcp_mm of [tcf]" in ref.source
    ref = tool_frame.reference(None, DRAWN, axis=FOUND_AXIS, axis_option="tool_axis of [tcp_npoint]")
    np.testing.assert_allclose(ref.axis, FOUND_AXIS, atol=1e-12)
    ref = tool_frame.reference(CONTROLLER, DRAWN, tip_m=stated_tip, tip_option="tcp_mm of [tcf]")
    assert np.array_equal(ref.pose, CONTROLLER)
    assert len(ref.notes) == 1 and ref.notes[0].startswith("tcp_mm of [tcf] is not used")


def test_tip_only_keeps_the_whole_orientation():
    ref = tool_frame.reference(CONTROLLER, DRAWN)
    frame, notes = tool_frame.compose(tool_frame.TIP_ONLY, ref, tip_m=FOUND_TIP)
    assert np.array_equal(frame[:3], FOUND_TIP) and np.array_equal(frame[3:], CONTROLLER[3:])
    assert "determines the tip only" in notes[0] and "keeps the orientation" in notes[0]


def test_axis_only_keeps_the_tip_and_turns_the_orientation_onto_the_axis_keeping_its_turn_about_it():
    ref = tool_frame.reference(CONTROLLER, DRAWN)
    frame, notes = tool_frame.compose(tool_frame.AXIS_ONLY, ref, axis=FOUND_AXIS)
    assert np.array_equal(frame[:3], CONTROLLER[:3])
    np.testing.assert_allclose(se3.rotvec_to_matrix(frame[3:])[:, 2], FOUND_AXIS, atol=1e-12)
    assert abs(turn_about(CONTROLLER[3:], frame[3:]) @ ref.axis) < 1e-9  # no turn about the axis
    assert "determines the axis only" in notes[0] and "keeps the TCP position" in notes[0]


def test_tip_and_axis_take_both_and_keep_the_turn_about_the_axis():
    ref = tool_frame.reference(CONTROLLER, DRAWN)
    frame, notes = tool_frame.compose(tool_frame.TIP_AND_AXIS, ref, tip_m=FOUND_TIP, axis=FOUND_AXIS)
    assert np.array_equal(frame[:3], FOUND_TIP)
    np.testing.assert_allclose(frame[3:], se3.with_z_axis(CONTROLLER[3:], FOUND_AXIS), atol=0)
    assert "turn of the tool frame about the tool axis is not measured" in notes[0]
    # with the drawing along the flange's z as the reference, the frame is the old convention's
    frame, _ = tool_frame.compose(tool_frame.TIP_AND_AXIS, tool_frame.reference(None, DRAWN), tip_m=FOUND_TIP,
                                  axis=FOUND_AXIS)
    np.testing.assert_allclose(frame[3:], se3.rotvec_from_z(FOUND_AXIS), atol=1e-12)


@pytest.mark.parametrize("determines, given", [
    (tool_frame.NOTHING, {}), (frozenset({"roll"}), {}), (tool_frame.TIP_ONLY, {}),
    (tool_frame.AXIS_ONLY, {"tip_m": FOUND_TIP, "axis": FOUND_AXIS}),
])
def test_compose_refuses_what_does_not_make_a_frame(determines, given):
    with pytest.raises(ValueError):
        tool_frame.compose(determines, tool_frame.reference(CONTROLLER, DRAWN), **given)


# -- routines/framework/gates.py -----------------------------------------------------------------------

TOOL = ToolSpec(np.array([0.0, 0.0, 0.150]), np.array([0.0, 0.0, 1.0]), 0.003, 0.1)


def moved(frame, mm: float = 0.0, deg: float = 0.0) -> np.ndarray:
    """`frame` with its tip moved `mm` along x and its axis tilted `deg` (about its own y)."""
    out = np.array(frame, dtype=float)
    out[0] += mm / 1e3
    rotation = se3.rotvec_to_matrix(out[3:])
    out[3:] = se3.matrix_to_rotvec(se3.rotvec_to_matrix(np.radians(deg) * rotation[:, 1]) @ rotation)
    return out


# (what the result determines, tip moved mm, axis tilted deg, the previous gate passes, the words)
PREVIOUS_CASES = [
    (tool_frame.TIP_ONLY, 0.5, 3.0, True, "the axis is not compared"),  # 3 deg is above the 1 deg limit
    (tool_frame.TIP_ONLY, 2.5, 0.0, False, "the tip 2.500 mm"),
    (tool_frame.AXIS_ONLY, 5.0, 0.3, True, "the TCP position is not compared"),  # 5 mm is above 2 mm
    (tool_frame.AXIS_ONLY, 0.0, 1.5, False, "the axis 1.500 deg"),
    (tool_frame.TIP_AND_AXIS, 0.5, 3.0, False, "the tip 0.500 mm and the axis 3.000 deg"),
    (tool_frame.TIP_AND_AXIS, 2.5, 0.3, False, "the tip 2.500 mm"),
    (tool_frame.TIP_AND_AXIS, 0.5, 0.3, True, "limits 2 mm, 1 deg"),
]


@pytest.mark.parametrize("determines, mm, deg, passes, words", PREVIOUS_CASES)
def test_the_previous_gate_compares_only_what_the_result_determined(determines, mm, deg, passes, words):
    gate = gates.agrees_with_previous(moved(CONTROLLER, mm, deg), CONTROLLER, determines=determines)
    assert gate.passed is passes and words in gate.why, gate.why
    assert (gate.value, gate.limit) == ((pytest.approx(deg), 1.0) if determines == tool_frame.AXIS_ONLY
                                        else (pytest.approx(mm), 2.0))


@pytest.mark.parametrize("determines, mm, deg, passes, words", [
    (tool_frame.TIP_ONLY, 1.0, 8.0, True, "the axis is not compared"),  # 8 deg is above the 5 deg limit
    (tool_frame.AXIS_ONLY, 15.0, 1.0, True, "the TCP position is not compared"),  # 15 mm is above 10 mm
    (tool_frame.AXIS_ONLY, 0.0, 6.0, False, "is the right tool mounted"),
    (tool_frame.TIP_AND_AXIS, 1.0, 8.0, False, "the tip 1.000 mm and the axis 8.000 deg"),
])
def test_the_plausibility_gate_compares_only_what_the_result_determined(determines, mm, deg, passes, words):
    gate = gates.plausible_tool(moved(TOOL.tcp_pose, mm, deg), TOOL, determines=determines)
    assert gate.passed is passes and words in gate.why, gate.why


def test_the_previous_gate_with_no_controller_frame_compares_nothing():
    for previous in (None, np.zeros(6)):
        gate = gates.agrees_with_previous(moved(CONTROLLER, 50.0, 20.0), previous, determines=tool_frame.TIP_ONLY)
        assert gate.passed and "no previous tool frame" in gate.why


# -- words: the frame beside the axis tilts ---------------------------------------------------


def test_frame_text_says_rotation_vector_and_prints_the_axis_lean_beside_it():
    frame = np.concatenate([[0.0, 0.0, 0.150], np.radians([0.4838, 0.0486, 0.0])])
    text = frame_text(frame)
    assert "rotation vector rx 0.4838 ry 0.0486 rz 0.0000 deg" in text
    assert "(z axis leans 0.0486 deg toward x, -0.4838 deg toward y)" in text
    base = {"x_mm": 1.0, "y_mm": 2.0, "z_mm": 3.0, "rx_deg": 0.1, "ry_deg": 0.2, "rz_deg": 0.3}
    assert "leans" not in frame_text(base, lean=False)


def test_the_run_json_says_what_the_tool_frame_determines():
    result = Result("tcp-npoint", [], np.zeros((8, 3)), 0.02, 1.0, [], tool_frame=CONTROLLER,
                    determines=tool_frame.TIP_ONLY)
    assert result.as_json()["determines"] == ["tip"]
    assert "determines" not in Result("tracker", [], np.zeros(3), 0.02, 1.0, []).as_json()


# -- routines/framework/frames_owed.py: the other robots' frames, owed back by the service --------------


class FakeRobot:
    """A robot whose controller takes a tool frame only when ready (as a UR in a safety stop)."""

    def __init__(self, frame):
        self.frame, self.ready = np.asarray(frame, dtype=float), True

    def state(self):
        return RobotState.READY if self.ready else RobotState.PROTECTIVE_STOP

    def tool_frame(self):
        return self.frame.copy()

    def set_tcp(self, pose):
        if not self.ready:
            raise DeviceError("robot b", "protective stop")
        self.frame = np.asarray(pose, dtype=float)


def test_a_frame_owed_comes_back_once_the_robot_is_ready_and_the_oldest_one_is_owed():
    robot = FakeRobot(CONTROLLER)
    owed, events = FramesOwed(), []
    owed.owe(1, {"b": robot})
    robot.set_tcp(DRAWN)  # the routine set the needle as drawn ...
    robot.ready = False  # ... and the robot stopped before it could have its frame back
    owed.give_back({"b": robot}, lambda kind, message: events.append((kind, message)))
    assert owed and np.array_equal(robot.frame, DRAWN) and events == []
    assert owed.waiting(("a", "b")) == "robot b's tool frame from before run 1 is not yet back on its controller"
    assert owed.waiting(("a",)) is None  # a routine that does not move robot b is not held up
    owed.owe(2, {"b": robot})  # a later run's "before" is the drawing the fault left: not owed over the real one
    robot.ready = True
    owed.give_back({"b": robot}, lambda kind, message: events.append((kind, message)))
    assert not owed and np.array_equal(robot.frame, CONTROLLER)
    assert events == [("tool_frame_given_back", "run 1, robot b")]


def test_a_robot_that_has_its_frame_is_owed_nothing_and_nothing_is_sent():
    robot = FakeRobot(CONTROLLER)
    owed = FramesOwed()
    owed.owe(3, {"b": robot})
    robot.set_tcp = None  # any command would fail: none may be sent
    owed.give_back({"b": robot})
    assert not owed
