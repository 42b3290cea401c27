"""What the routine tests use to watch the robot: every command it receives, and an
independent check of each against the cell's limits (tests/unit/test_routine_framework.py
for one robot, tests/e2e/test_handshake.py for both robots of a two-robot cell)."""
from __future__ import annotations

import numpy as np

from cellcal.solvers.geometry.inverse import tcp_poses


class RecordingRobot:
    """A robot that records every command it receives, passing them on to a real one."""

    def __init__(self, robot):
        self.robot, self.commands = robot, []

    def __getattr__(self, name):
        return getattr(self.robot, name)

    def move_j(self, q, speed, accel):
        self.commands.append(("joint", np.array(q), speed, accel))
        return self.robot.move_j(q, speed, accel)

    def move_l(self, pose, speed, accel):
        self.commands.append(("linear", np.array(pose), speed, accel))
        return self.robot.move_l(pose, speed, accel)

    def move_until_contact(self, velocity, timeout_s):
        self.commands.append(("contact", np.array(velocity), timeout_s, None))
        return self.robot.move_until_contact(velocity, timeout_s)


def within_limits(cell, model, command, tool_pose) -> list[str]:
    """An independent check of one command that reached the robot; the broken limits."""
    kind, target, speed, accel = command
    limits, broken = cell.limits, []
    low, high = cell.workspace_min_m - 1e-9, cell.workspace_max_m + 1e-9
    if kind == "joint":
        if speed > limits["joint_speed_rad_s"] or accel > limits["joint_accel_rad_s2"]:
            broken.append("joint speed/accel")
        if np.any(target < model.joint_limits[:, 0]) or np.any(target > model.joint_limits[:, 1]):
            broken.append("joint limits")
        if np.any(tcp_poses(model, target, tool_pose)[0, :3] < low) or \
                np.any(tcp_poses(model, target, tool_pose)[0, :3] > high):
            broken.append("box")
    elif kind == "linear":
        if speed > limits["tcp_speed_m_s"] or accel > limits["tcp_accel_m_s2"]:
            broken.append("tcp speed/accel")
        if np.any(target[:3] < low) or np.any(target[:3] > high):
            broken.append("box")
    else:
        if np.linalg.norm(target) > limits["tcp_speed_m_s"] or np.linalg.norm(target) * speed > \
                limits["contact_travel_m"] + 1e-9:
            broken.append("contact speed/travel")
    return broken
