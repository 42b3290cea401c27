"""Forward and inverse kinematics of the TCP in metres, as a controller sees them.

The identification works in mm on many poses at once; routines plan and check motions
one pose at a time in the robot's own units (m, rad, rotation vectors). Both use the
same chains (``chain.forward``), so a plan is checked against the very geometry the
solvers use.
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.chain import forward
from cellcal.solvers.geometry.robot_model import KinematicModel


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
        turns = se3.matrix_to_rotvec(np.concatenate([(target_rot @ rot[0].T)[None],  # one call: scipy's is
                                                     np.einsum("nij,nkj->nik", rot[1:n + 1], rot[n + 1:])]))
        error = np.concatenate([pose[:3] - position[0], turns[0]])  # 30 us for one matrix or seven
        if np.abs(error).max() < tol_m:
            return q
        twist = np.concatenate([position[1:n + 1] - position[n + 1:], turns[1:]], axis=1) / (2 * h)
        jac = twist.T  # (6, n)
        damping = 1e-6
        dq = jac.T @ np.linalg.solve(jac @ jac.T + damping * np.eye(6), error)
        q = q + dq / max(1.0, np.abs(dq).max() / 0.3)
    return None


def inverse_many(model: KinematicModel, poses, q_seed, tool_pose=None, *, tol_m: float = 1e-9,
                 max_iter: int = 50) -> np.ndarray:
    """``inverse`` for many poses at once: (M, nj) joints near the seeds (one (nj,) seed for all, or
    (M, nj)) putting the TCP at each pose (M, 6); a row that does not converge there is NaN."""
    poses = np.atleast_2d(np.asarray(poses, dtype=float))
    m = len(poses)
    q = np.array(np.broadcast_to(np.asarray(q_seed, dtype=float), (m, model.n_joints)))
    n = q.shape[1]
    target_rot = se3.rotvec_to_matrix(poses[:, 3:])
    h = 1e-6
    steps = np.concatenate([np.zeros((1, n)), np.eye(n) * h, -np.eye(n) * h])
    done = np.zeros(m, bool)
    for _ in range(max_iter):
        live = np.flatnonzero(~done)
        if not len(live):
            break
        rot, position = tcp_frames(model, (q[live, None, :] + steps[None]).reshape(-1, n), tool_pose)
        rot, position = rot.reshape(len(live), 2 * n + 1, 3, 3), position.reshape(len(live), 2 * n + 1, 3)
        error = np.concatenate([poses[live, :3] - position[:, 0],
                                se3.matrix_to_rotvec(np.einsum("nij,nkj->nik", target_rot[live], rot[:, 0]))], axis=1)
        converged = np.abs(error).max(axis=1) < tol_m
        done[live[converged]] = True
        live, rot, position, error = live[~converged], rot[~converged], position[~converged], error[~converged]
        if not len(live):
            break
        dr = se3.matrix_to_rotvec(np.einsum("nmij,nmkj->nmik", rot[:, 1:n + 1], rot[:, n + 1:]).reshape(-1, 3, 3))
        twist = np.concatenate([position[:, 1:n + 1] - position[:, n + 1:], dr.reshape(len(live), n, 3)],
                               axis=2) / (2 * h)
        jac = twist.transpose(0, 2, 1)  # (n_live, 6, n)
        dq = np.einsum("nji,nj->ni", jac, np.linalg.solve(jac @ jac.transpose(0, 2, 1) + 1e-6 * np.eye(6),
                                                          error[:, :, None])[:, :, 0])
        q[live] += dq / np.maximum(1.0, np.abs(dq).max(axis=1) / 0.3)[:, None]
    q[~done] = np.nan
    return q


def dexterity(model: KinematicModel, q_rad, tool_pose=None, length_m: float = 1.0) -> np.ndarray:
    """(N,) smallest over largest singular value of the TCP's Jacobian at each joint row (position
    over length_m, rotation in rad): near 0 at a singularity (a stretched elbow, a straight wrist),
    where a small move of the TCP needs a large one of the joints."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    n = q.shape[1]
    h = 1e-6
    steps = np.concatenate([np.eye(n) * h, -np.eye(n) * h])
    rot, position = tcp_frames(model, (q[:, None, :] + steps[None]).reshape(-1, n), tool_pose)
    rot, position = rot.reshape(len(q), 2 * n, 3, 3), position.reshape(len(q), 2 * n, 3)
    dp = (position[:, :n] - position[:, n:]) / (2 * h) / length_m
    dr = se3.matrix_to_rotvec(np.einsum("nmij,nmkj->nmik", rot[:, :n], rot[:, n:]).reshape(-1, 3, 3)).reshape(
        len(q), n, 3) / (2 * h)
    s = np.linalg.svd(np.concatenate([dp, dr], axis=2), compute_uv=False)
    return s[:, -1] / s[:, 0]
