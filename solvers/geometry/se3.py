"""Rigid-body helpers: rotations, homogeneous transforms, rigid fits.

Everything is vectorised over leading dimensions. Lengths are in whatever unit
the caller uses (the fits mm, inverse.py metres), angles in radians.
"""
from __future__ import annotations

import numpy as np

_AXES = {"x": 0, "y": 1, "z": 2}


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix of vectors ``v`` (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def rot(axis: str, angle) -> np.ndarray:
    """Rotation matrices about a principal axis, for an array of angles."""
    angle = np.asarray(angle, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(angle.shape + (3, 3))
    i = _AXES[axis]
    j, k = (i + 1) % 3, (i + 2) % 3
    out[..., i, i] = 1.0
    out[..., j, j] = c
    out[..., k, k] = c
    out[..., j, k] = -s
    out[..., k, j] = s
    return out


def homogeneous(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    rotation = np.asarray(rotation, dtype=float)
    translation = np.asarray(translation, dtype=float)
    shape = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    out = np.zeros(shape + (4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, vectorised; exact near zero."""
    rotvec = np.asarray(rotvec, dtype=float)
    theta = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    k = skew(rotvec)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def matrix_to_rotvec(matrix: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    m = np.asarray(matrix, dtype=float)
    flat = m.reshape(-1, 3, 3)
    return Rotation.from_matrix(flat).as_rotvec().reshape(m.shape[:-2] + (3,))


def left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian: R(r + dr) ~= exp([J_l(r) dr]x) R(r)."""
    rotvec = np.asarray(rotvec, dtype=float)
    theta = float(np.linalg.norm(rotvec))
    k = skew(rotvec)
    if theta < 1e-6:
        return np.eye(3) + 0.5 * k + (k @ k) / 6.0
    return (
        np.eye(3)
        + (1.0 - np.cos(theta)) / theta**2 * k
        + (theta - np.sin(theta)) / theta**3 * (k @ k)
    )


def orthonormalize(rotation: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (polar decomposition via SVD)."""
    u, _, vt = np.linalg.svd(np.asarray(rotation, dtype=float))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rigid_fit(source: np.ndarray, target: np.ndarray, weights=None):
    """Least-squares rotation R and translation t with target ~= R @ source + t (Kabsch)."""
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    cs = w @ source
    ct = w @ target
    h = (source - cs).T @ ((target - ct) * w[:, None])
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, ct - r @ cs


def rotvec_from_z(axis) -> np.ndarray:
    """The rotation vector of the smallest turn that takes z onto unit `axis`: a tool frame
    whose z is the tool's axis, with the rotation about it fixed by that convention."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    turn = np.cross([0.0, 0.0, 1.0], axis)
    sin, cos = float(np.linalg.norm(turn)), float(axis[2])
    if sin < 1e-12:
        return np.zeros(3) if cos > 0 else np.array([np.pi, 0.0, 0.0])
    return turn / sin * np.arctan2(sin, cos)


def turn_between(a, b) -> np.ndarray:
    """The rotation vector of the smallest turn that takes direction `a` onto direction `b`
    (both normalised here). Opposite directions have no single smallest turn: half a turn
    about the direction across `a` nearest the x axis (nearest y when `a` is along x), so
    ``turn_between(z, axis)`` is :func:`rotvec_from_z`'s turn."""
    a = np.asarray(a, dtype=float) / np.linalg.norm(a)
    b = np.asarray(b, dtype=float) / np.linalg.norm(b)
    turn = np.cross(a, b)
    sin, cos = float(np.linalg.norm(turn)), float(a @ b)
    if sin >= 1e-12:
        return turn / sin * np.arctan2(sin, cos)
    if cos > 0:
        return np.zeros(3)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    across = helper - (helper @ a) * a
    return np.pi * across / np.linalg.norm(across)


def with_z_axis(rotvec, axis) -> np.ndarray:
    """The orientation `rotvec` turned by the smallest rotation that takes its z axis onto
    `axis` (same frame as the orientation's columns): the rotation vector of ``T @ R``.
    What the orientation says about the turn about its z axis is kept: ``T`` turns about a
    direction across both axes, never about either."""
    rotation = rotvec_to_matrix(rotvec)
    turn = rotvec_to_matrix(turn_between(rotation[:, 2], axis))
    return matrix_to_rotvec(turn @ rotation)


def z_axis_lean(rotvec) -> tuple[float, float]:
    """How far the z axis of orientation `rotvec` leans from the z of the frame it is given
    in toward that frame's x and toward its y (rad): ``atan2(z.x, z.z)``, ``atan2(z.y, z.z)``.
    A lean toward x is a turn about y, so for small angles it is the rotation vector's ry,
    and the lean toward y is minus its rx."""
    z = rotvec_to_matrix(rotvec)[:, 2]
    return float(np.arctan2(z[0], z[2])), float(np.arctan2(z[1], z[2]))
