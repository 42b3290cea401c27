"""The simulated arm's single-pose kinematics (sims/physics/arm_motion.py ArmKinematics): the walk
that folds the elements no joint drives into one rigid transform agrees with the solvers' chain,
and its Jacobian with the derivative of the pose, on every shipped arm, nominal and as built."""
from __future__ import annotations

import numpy as np
import pytest

from cellcal.config.reader import shipped
from cellcal.config.robot_files import load_robot
from cellcal.sims.physics.arm_motion import ArmKinematics, log_so3
from cellcal.solvers.geometry.chain import forward

SERIAL_ARMS = sorted(name for name in shipped("robots") if "flange" in load_robot(name).chains)


@pytest.mark.parametrize("name", SERIAL_ARMS)
def test_the_walk_and_its_jacobian_agree_with_the_chain_on_every_arm(name):
    model = load_robot(name)
    rng = np.random.default_rng(7)
    # as built: every parameter off its nominal by up to 1 % (mm and rad alike)
    params = model.nominal + rng.normal(0.0, 0.01, model.nominal.shape)
    kin = ArmKinematics(model, params)
    tool = np.array([0.012, -0.034, 0.187, 0.3, -0.2, 0.1])
    for q in rng.uniform(-np.pi, np.pi, (5, model.n_joints)):
        rot, org_mm = forward(model.chains["flange"], params, q[None])
        flange_rot, flange_m = kin.flange(q)
        # the same products in another order: rounding of a few 1e-16 per element, summed over 24
        assert np.abs(flange_rot - rot[0]).max() < 1e-12
        assert np.abs(flange_m * 1000.0 - org_mm[0]).max() < 1e-9  # mm, on ~1000 mm lengths
        r, p, jac = kin.jacobian(q, tool)
        h = 1e-6  # central differences: truncation h^2 x (reach ~1.5 m) ~ 1e-12, rounding eps/h ~ 1e-10
        numeric = np.zeros_like(jac)
        for j in range(model.n_joints):
            dq = np.zeros(model.n_joints)
            dq[j] = h
            (r_plus, p_plus), (r_minus, p_minus) = kin.tcp_frame(q + dq, tool), kin.tcp_frame(q - dq, tool)
            numeric[:3, j] = (p_plus - p_minus) / (2 * h)
            numeric[3:, j] = log_so3(r_plus @ r_minus.T) / (2 * h)
        assert np.abs(jac - numeric).max() < 1e-8


def test_joints_about_x_and_y_and_a_sliding_joint_are_walked_as_the_chain_does():
    """The shipped arms turn every joint about z; a chain may also turn one about x or y, slide
    one, or couple two (the walk turns its frame so each driven element acts on z)."""
    from types import SimpleNamespace

    from cellcal.solvers.geometry.chain import Chain, Element

    elements = (Element("rz", 0, joints=((0, 1.0),)), Element("tz", 1), Element("rx", 2),
                Element("rx", -1, 0.3, joints=((1, 1.0),)), Element("tx", 3), Element("ty", -1, 40.0),
                Element("ry", 4, joints=((2, 1.0), (1, -0.5))), Element("tx", 5), Element("tz", 6, joints=((3, 1000.0),)),
                Element("ry", -1, -0.7), Element("rz", 7, joints=((4, 1.0),)), Element("tx", -1, 25.0))
    end = np.eye(4)
    end[:3, 3] = [5.0, -3.0, 80.0]
    chain = Chain(elements, end)
    params = np.array([0.1, 300.0, -0.2, 450.0, 0.05, 380.0, 20.0, -0.15])
    model = SimpleNamespace(name="made up", chains={"flange": chain}, n_joints=5, nominal=params)
    kin = ArmKinematics(model)  # checks the walk against forward at four poses, or refuses
    rng = np.random.default_rng(11)
    for q in rng.uniform(-2.0, 2.0, (5, 5)):
        rot, org_mm = forward(chain, params, q[None])
        flange_rot, flange_m = kin.flange(q)
        assert np.abs(flange_rot - rot[0]).max() < 1e-12
        assert np.abs(flange_m * 1000.0 - org_mm[0]).max() < 1e-9
        r, p, jac = kin.jacobian(q, np.zeros(6))
        h = 1e-6  # as above
        for j in range(5):
            dq = np.zeros(5)
            dq[j] = h
            (r_plus, p_plus), (r_minus, p_minus) = kin.tcp_frame(q + dq, np.zeros(6)), kin.tcp_frame(q - dq, np.zeros(6))
            assert np.abs(jac[:3, j] - (p_plus - p_minus) / (2 * h)).max() < 1e-8
            assert np.abs(jac[3:, j] - log_so3(r_plus @ r_minus.T) / (2 * h)).max() < 1e-8
