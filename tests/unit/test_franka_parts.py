"""The parts of the Franka driver and of the simulated Franka arm that need no running simulator:
the arm as a physics engine's bodies, the nests' contact, the driver's trajectories and options."""
from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.config.robot_files import load_robot
from cellcal.drivers.franka.host import rotation_of, rotvec, trapezoid
from cellcal.drivers.registry import DriverConfigError, check
from cellcal.sims.franka.arm import CONTACT_STIFFNESS_N_M, NEST_FACES, Contacts
from cellcal.sims.inproc.world import PivotSocket
from cellcal.sims.physics.arm_motion import ArmKinematics, joint_body_frames


def chain_of(frames, flange, q) -> np.ndarray:
    """The flange a body tree puts where its joints are at q (each joint turns about its body's z)."""
    m = np.eye(4)
    for frame, angle in zip(frames, q):
        turn = np.eye(4)
        turn[:3, :3] = rotation_of([0.0, 0.0, angle])
        m = m @ frame @ turn
    return m @ flange


@pytest.mark.parametrize("seed", [0, 1])
def test_body_frames_are_the_arm_the_truth_draws(seed):
    """joint_body_frames of a perturbed arm, chained with the joints' turns, is our own kinematics of the
    same parameters to rounding (the simulated Franka checks its MuJoCo bodies against the same)."""
    model = load_robot("franka-fr3")
    rng = np.random.default_rng(seed)
    errors = np.where(model.param_is_angle, np.deg2rad(0.02), 0.3)
    params = np.asarray(model.nominal, float) + rng.uniform(-1, 1, len(model.nominal)) * errors
    frames, flange = joint_body_frames(model, params)
    ours = ArmKinematics(model, params)
    for q in rng.uniform(-1.0, 1.0, (5, 7)):
        m = chain_of(frames, flange, q)
        r, p = ours.flange(q)
        # a 1 m chain of 7 rotations: rounding near 1e-15 per product, far below 1e-12
        assert np.abs(m[:3, :3] - r).max() < 1e-12 and np.abs(m[:3, 3] - p).max() < 1e-12


def test_body_frames_refuse_an_arm_that_is_no_chain_of_z_turns():
    """An arm whose joint 3 also turns with joint 2 (coupled, as some arms' wrists are) has no such body
    tree: refused, saying why."""
    import dataclasses
    from types import SimpleNamespace

    model = load_robot("franka-fr3")
    chain = model.chains["flange"]
    driven = [i for i, el in enumerate(chain.elements) if el.joints]
    elements = list(chain.elements)
    elements[driven[2]] = dataclasses.replace(elements[driven[2]], joints=((2, 1.0), (1, 0.5)))
    coupled = SimpleNamespace(name="coupled", n_joints=model.n_joints,
                              chains={"flange": dataclasses.replace(chain, elements=tuple(elements))})
    with pytest.raises(ValueError, match="not a chain of joints turning about z"):
        joint_body_frames(coupled, model.nominal)
    joint_body_frames(model, model.nominal)  # the arm itself is one


def socket() -> PivotSocket:
    return PivotSocket(np.array([0.4, 0.1, 0.2]), 0.003)


def pushed(contacts, centre) -> np.ndarray:
    """The force on a tool at rest whose tip's rounding is centred at `centre`, its shank straight up."""
    return contacts.force((np.asarray(centre, float), np.asarray(centre, float) + [0.0, 0.0, 0.1]), np.zeros(3))[0]


def test_a_seated_tip_feels_no_force_and_a_pressed_one_is_pushed_back_along_the_axis():
    """At the seat the rounding touches every face without pressing; pressed 10 um down, the faces
    push it straight back up with the nest's stiffness (three faces' worth, shared by all twelve)."""
    nest = socket()
    contacts = Contacts([nest], nest.tool_radius_m)
    assert np.allclose(pushed(contacts, nest.seat_m), 0.0, atol=1e-9)
    pressed = pushed(contacts, nest.seat_m - [0.0, 0.0, 1e-5])
    assert abs(pressed[0]) < 1e-9 and abs(pressed[1]) < 1e-9
    # each face pushes k/4 x depth along its normal; depth = 1e-5 sin(45 deg); the normals' z: sin(45 deg)
    expected = NEST_FACES * CONTACT_STIFFNESS_N_M * 3.0 / NEST_FACES * 1e-5 * math.sin(math.pi / 4) ** 2
    assert pressed[2] == pytest.approx(expected, rel=1e-9)


def test_off_the_seat_the_faces_push_the_tip_home():
    """A rounding low in the nest and off its axis is pushed back towards the axis and up: a compliant
    arm slides into the seat."""
    nest = socket()
    contacts = Contacts([nest], nest.tool_radius_m)
    for direction in ([1.0, 0.0], [0.0, 1.0], [-0.6, 0.8]):
        off = np.array([*direction, 0.0]) * 5e-4 - [0.0, 0.0, 2e-4]
        force = pushed(contacts, nest.seat_m + off)
        assert force[:2] @ np.asarray(direction) < 0 and force[2] > 0, (direction, force)


def test_above_the_rim_and_beside_it_there_is_no_wall():
    """The faces end at the rim: a tip passing over the opening 1 mm above the top touches nothing, one
    beside it on the top face is pushed up, one on the rim's edge is pushed out from it."""
    nest = socket()
    r = nest.tool_radius_m
    contacts = Contacts([nest], r)
    rim_height = nest.rim_radius_m / math.tan(nest.half_angle_rad)
    top = nest.apex_m[2] + rim_height
    assert not pushed(contacts, nest.apex_m + [0.0054, 0.0, rim_height + r + 0.001]).any()
    beside = pushed(contacts, [*(nest.apex_m[:2] + [0.010, 0.0]), top + r - 1e-4])
    assert beside[2] == pytest.approx(CONTACT_STIFFNESS_N_M * 1e-4) and abs(beside[0]) < 1e-9
    edge_dir = np.array([-1.0, 0.0, 1.0]) / math.sqrt(2)  # from the rim's edge up and in, towards the axis
    on_edge = np.array([nest.apex_m[0] + nest.rim_radius_m, nest.apex_m[1], top]) + edge_dir * (r - 1e-4)
    force = pushed(contacts, on_edge)
    assert np.allclose(force / np.linalg.norm(force), edge_dir, atol=1e-9), force


def test_a_ball_meets_the_shank_and_pushes_where_it_touches():
    """The stylus (a ball) touching the tool's side 50 mm behind the tip pushes it sideways there."""
    from cellcal.sims.physics.scene import ContactSphere

    ball = ContactSphere(np.array([0.4, 0.1, 0.25]), 0.0005)
    contacts = Contacts([ball], 0.003)
    tip = np.array([0.4 - 0.0035 + 1e-5, 0.1, 0.2])  # the shank's surface 10 um into the ball, 50 mm up
    force, at = contacts.force((tip, tip + [0.0, 0.0, 0.1]), np.zeros(3))
    assert force[0] == pytest.approx(-CONTACT_STIFFNESS_N_M * 1e-5) and abs(force[1]) < 1e-9 and abs(force[2]) < 1e-9
    assert at == pytest.approx([tip[0], 0.1, 0.25])


def test_trapezoid_profile():
    """The driver's profile: starts and ends at rest on the target, never above the speed."""
    total, s = trapezoid(0.1, 0.04, 2.5)
    assert total == pytest.approx(0.1 / 0.04 + 0.04 / 2.5)
    t = np.linspace(0.0, total, 2001)
    x = np.array([s(v) for v in t]) * 0.1
    assert x[0] == 0.0 and x[-1] == pytest.approx(0.1)
    assert np.diff(x).max() / (t[1] - t[0]) <= 0.04 * (1 + 1e-9)
    short_total, _ = trapezoid(0.0005, 0.04, 2.5)  # shorter than 2.5 x 0.016^2 m: a triangle
    assert short_total == pytest.approx(2 * math.sqrt(0.0005 / 2.5))
    assert trapezoid(0.0, 0.04, 2.5)[0] == 0.0


def test_rotation_round_trip():
    for v in ([0.0, 0.0, 0.0], [0.1, -0.2, 0.3], [0.0, 3.1, 0.0]):
        assert np.allclose(rotvec(rotation_of(v)), v, atol=1e-12)


@pytest.mark.parametrize("options, key", [
    ({"host": "10.0.0.2", "contact_force_n": 0.0}, "contact_force_n"),
    ({"host": "10.0.0.2", "seat_s": -1.0}, "seat_s"),
    ({"host": "10.0.0.2", "seat_force_n": 80.0}, "seat_force_n"),
    ({"host": "10.0.0.2", "tool_frame_register": 24}, "tool_frame_register"),
    ({}, "host"),
])
def test_driver_options_are_checked_at_load(options, key):
    """A Franka driver option out of range, unknown or missing is refused at cell load, naming it."""
    with pytest.raises(DriverConfigError) as caught:
        check("robot", "franka", options)
    assert caught.value.key == key or key in str(caught.value)


def test_the_driver_kinematics_are_the_robot_files():
    """The driver solves linear moves with Franka's published kinematics: the same arm as the robot files
    franka-fr3 and franka-panda (to rounding), and its inverse lands on the pose asked for."""
    from cellcal.drivers.franka.host import forward, inverse

    rng = np.random.default_rng(3)
    for name in ("franka-fr3", "franka-panda"):
        ours = ArmKinematics(load_robot(name))
        for q in rng.uniform(-1.0, 1.0, (5, 7)):
            r, p = ours.flange(q)
            m = forward(q)
            assert np.abs(m[:3, :3] - r).max() < 1e-12 and np.abs(m[:3, 3] - p).max() < 1e-12
    tool = np.eye(4)
    tool[:3, 3] = [0.0, 0.01, 0.15]
    q0 = np.array([0.0, -0.7854, 0.0, -2.3562, 0.0, 1.5708, 0.7854])
    target = forward(q0) @ tool
    target[:3, 3] += [0.05, -0.02, -0.03]
    target[:3, :3] = target[:3, :3] @ rotation_of([0.2, 0.0, 0.3])
    q = inverse(target, q0, tool)
    assert q is not None
    reached = forward(q) @ tool
    # the solver stops at 1e-10 m and rad; the matrices then agree to that times a few
    assert np.abs(reached - target).max() < 1e-9
    assert abs(q[2] - q0[2]) < 0.5  # the least motion: the elbow stays near where it was
