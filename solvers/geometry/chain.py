"""Kinematic chains as products of elementary transforms.

A chain is a sequence of elementary motions (rotation or translation about/along
the x, y or z axis of the current frame). Each element's value is either a
geometric parameter (an entry of the parameter vector) or a constant, plus a
linear combination of joint values (so coupled joints such as Fanuc's J2/J3 or a
passive joint q = -(q1 + q2) need no special code). Serial DH/MDH arms and
trees (several chains sharing parameters) both compile to this form, and one
forward/Jacobian implementation serves them all.

Forward kinematics is vectorised over poses and, for population-based
baselines, over parameter sets: ``params`` may be (P,) or (M, P).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_AXIS = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class Element:
    kind: str  # one of rx ry rz tx ty tz
    param: int = -1  # index into the parameter vector, -1 for a constant
    constant: float = 0.0  # value when param == -1
    joints: tuple[tuple[int, float], ...] = ()  # (joint index, coefficient) added to the value

    @property
    def axis(self) -> int:
        return _AXIS[self.kind[1]]

    @property
    def is_rotation(self) -> bool:
        return self.kind[0] == "r"


@dataclass(frozen=True)
class Chain:
    """One chain from the robot base frame to an end frame (flange or hand)."""

    elements: tuple[Element, ...]
    end: np.ndarray = field(default_factory=lambda: np.eye(4))  # fixed transform after the last element

    def values(self, params: np.ndarray, q: np.ndarray) -> list[np.ndarray]:
        """Element values, each broadcast to params' leading dims x poses."""
        params = np.asarray(params, dtype=float)
        lead = params.shape[:-1]
        out = []
        for el in self.elements:
            v = params[..., el.param] if el.param >= 0 else np.full(lead, el.constant)
            v = np.asarray(v)[..., None]  # (..., 1) broadcasts against poses
            for j, c in el.joints:
                v = v + c * q[:, j]
            out.append(np.broadcast_to(v, lead + (q.shape[0],)))
        return out


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for vectors stored component-major, (3, N)."""
    return np.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _frames(chain: Chain, params: np.ndarray, q: np.ndarray, keep_frames: bool):
    """End frame as its three axes and origin, each (..., 3, N): component-major, so that every
    operation runs along the poses; with keep_frames the same before each element plus after
    the last one (before ``end``).

    Each elementary rotation recombines two axes, each translation moves the origin along one.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    params = np.asarray(params, dtype=float)
    lead = params.shape[:-1]
    n = q.shape[0]
    axes = [np.broadcast_to(np.eye(3)[i][:, None], lead + (3, n)) for i in range(3)]
    org = np.zeros(lead + (3, n))
    frames = []
    for el in chain.elements:
        if keep_frames:
            frames.append((axes, org))
        i = el.axis
        v = np.asarray(params[..., el.param] if el.param >= 0 else el.constant)[..., None]
        for j, c in el.joints:
            v = v + c * q[:, j]
        v = v[..., None, :]  # (..., 1, N or 1): broadcasts over the three coordinates and the poses
        if el.is_rotation:
            j, k = (i + 1) % 3, (i + 2) % 3
            c, s = np.cos(v), np.sin(v)
            axes = list(axes)
            axes[j], axes[k] = c * axes[j] + s * axes[k], -s * axes[j] + c * axes[k]
        else:
            org = org + v * axes[i]
    if keep_frames:
        frames.append((axes, org))
    end = chain.end
    if not np.array_equal(end, np.eye(4)):
        org = org + axes[0] * end[0, 3] + axes[1] * end[1, 3] + axes[2] * end[2, 3]
        axes = [axes[0] * end[0, c] + axes[1] * end[1, c] + axes[2] * end[2, c] for c in range(3)]
    return axes, org, frames


def _pose_major(axes, org):
    """Frames as the rest of the code keeps them: rot (..., N, 3, 3), org (..., N, 3)."""
    return np.stack([np.swapaxes(a, -1, -2) for a in axes], axis=-1), np.swapaxes(org, -1, -2).copy()


def forward(chain: Chain, params: np.ndarray, q: np.ndarray, keep_frames: bool = False):
    """End frames of the chain for every pose.

    Returns (rot (..., N, 3, 3), org (..., N, 3)) and, with keep_frames, the list of
    frames *before* each element plus the frame after the last one (before ``end``).
    """
    axes, org, frames = _frames(chain, params, q, keep_frames)
    rot, org = _pose_major(axes, org)
    if keep_frames:
        return rot, org, [_pose_major(a, o) for a, o in frames]
    return rot, org


def point_jacobians(chain: Chain, params: np.ndarray, q: np.ndarray, offset: np.ndarray,
                    n_params: int, n_joints: int):
    """Position of a point fixed in the end frame and its derivatives.

    offset: (N, 3) point coordinates in the end frame (one per pose).
    Returns p (N, 3), dp/dparams (N, 3, n_params), dp/dq (N, 3, n_joints),
    end rotation (N, 3, 3).
    """
    p, jp, jq, axes = point_jacobians_by_component(chain, params, q, offset, n_params, n_joints)
    rot, p = _pose_major(axes, p)
    return p, np.transpose(jp, (2, 1, 0)), np.transpose(jq, (2, 1, 0)), rot


def point_jacobians_by_component(chain: Chain, params: np.ndarray, q: np.ndarray, offset: np.ndarray,
                                 n_params: int, n_joints: int):
    """``point_jacobians`` component-major: p (3, N), dp/dparams (n_params, 3, N),
    dp/dq (n_joints, 3, N) and the end frame's axes (three (3, N) arrays)."""
    axes, org, frames = _frames(chain, params, q, keep_frames=True)
    offset = np.asarray(offset, dtype=float)
    p = org + axes[0] * offset[:, 0] + axes[1] * offset[:, 1] + axes[2] * offset[:, 2]
    n = p.shape[-1]
    jp = np.zeros((n_params, 3, n))
    jq = np.zeros((n_joints, 3, n))
    for el, (a, o) in zip(chain.elements, frames):
        axis = a[el.axis]
        col = _cross(axis, p - o) if el.is_rotation else axis
        if el.param >= 0:
            jp[el.param] += col
        for j, c in el.joints:
            jq[j] += c * col
    return p, jp, jq, axes


def pose_jacobians(chain: Chain, params: np.ndarray, q: np.ndarray, offset: np.ndarray, n_joints: int):
    """End rotation (N, 3, 3), position of a point fixed in the end frame (N, 3), and its
    linear and angular velocity per unit joint rate, each (N, 3, n_joints): the joint part
    of ``point_jacobians`` plus the orientation, in one pass (inverse kinematics needs no
    parameter columns)."""
    axes, org, frames = _frames(chain, params, q, keep_frames=True)
    offset = np.asarray(offset, dtype=float)
    p = org + axes[0] * offset[:, 0] + axes[1] * offset[:, 1] + axes[2] * offset[:, 2]
    n = p.shape[-1]
    jq = np.zeros((n_joints, 3, n))
    jw = np.zeros((n_joints, 3, n))
    for el, (a, o) in zip(chain.elements, frames):
        if not el.joints:
            continue
        axis = a[el.axis]
        col = _cross(axis, p - o) if el.is_rotation else axis
        for j, c in el.joints:
            jq[j] += c * col
            if el.is_rotation:
                jw[j] += c * axis
    rot, p = _pose_major(axes, p)
    return rot, p, np.transpose(jq, (2, 1, 0)), np.transpose(jw, (2, 1, 0))
