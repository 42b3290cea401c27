"""Forward and inverse kinematics of the TCP in metres, as a controller sees them.

The identification works in mm on many poses at once; routines plan and check motions
one pose at a time in the robot's own units (m, rad, rotation vectors). Both use the
same chains (``chain.forward``), so a plan is checked against the very geometry the
solvers use.
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers import se3
from cellcal.solvers.chain import forward
from cellcal.solvers.robot_model import KinematicModel


def tcp_frames(model: KinematicModel, q_rad, tool_pose=None, params=None) -> tuple[np.ndarray, np.ndarray]:
    """TCP rotations (N, 3, 3) and positions (N, 3) in metres for joint rows `q_rad` (N, nj);
    `tool_pose` is the flange -> TCP frame [x, y, z, rx, ry, rz] (m, rad)."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    chain = model.chains[model.default_chain]
    rot, org = forward(chain, model.nominal if params is None else params, q)
    position = org / 1000.0
    if tool_pose is not None:
        tool = np.asarray(tool_pose, dtype=float)
        tool_rot = se3.rotvec_to_matrix(tool[3:])
        position = position + np.einsum("nij,j->ni", rot, tool[:3])
        rot = np.einsum("nij,jk->nik", rot, tool_rot)
    return rot, position


def tcp_poses(model: KinematicModel, q_rad, tool_pose=None) -> np.ndarray:
    """TCP poses [x, y, z, rx, ry, rz] (N, 6)."""
    rot, position = tcp_frames(model, q_rad, tool_pose)
    return np.concatenate([position, se3.matrix_to_rotvec(rot)], axis=1)


def inverse(model: KinematicModel, pose, q_seed, tool_pose=None, *, tol_m: float = 1e-9,
            max_iter: int = 50) -> np.ndarray | None:
    """Joints near `q_seed` putting the TCP at `pose` (damped least squares on a central-
    difference Jacobian), or None when it does not converge there."""
    pose = np.asarray(pose, dtype=float)
    target_rot = se3.rotvec_to_matrix(pose[3:])
    q = np.array(q_seed, dtype=float)
    n = len(q)
    h = 1e-6
    steps = np.concatenate([np.zeros((1, n)), np.eye(n) * h, -np.eye(n) * h])
    for _ in range(max_iter):
        rot, position = tcp_frames(model, q + steps, tool_pose)
        error = np.concatenate([pose[:3] - position[0],
                                se3.matrix_to_rotvec(target_rot @ rot[0].T)])
        if np.abs(error).max() < tol_m:
            return q
        twist = np.concatenate([position[1:n + 1] - position[n + 1:],
                                se3.matrix_to_rotvec(np.einsum("nij,nkj->nik", rot[1:n + 1], rot[n + 1:]))],
                               axis=1) / (2 * h)
        jac = twist.T  # (6, n)
        damping = 1e-6
        dq = jac.T @ np.linalg.solve(jac @ jac.T + damping * np.eye(6), error)
        q = q + dq / max(1.0, np.abs(dq).max() / 0.3)
    return None
