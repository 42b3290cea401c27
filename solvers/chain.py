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

ROTATIONS = ("rx", "ry", "rz")
TRANSLATIONS = ("tx", "ty", "tz")
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


def _apply(rot: np.ndarray, org: np.ndarray, el: Element, v: np.ndarray):
    """Right-multiply frames (rot, org) by the elementary transform of value v."""
    i = el.axis
    if el.is_rotation:
        j, k = (i + 1) % 3, (i + 2) % 3
        c, s = np.cos(v)[..., None], np.sin(v)[..., None]
        new = rot.copy()
        new[..., :, j] = c * rot[..., :, j] + s * rot[..., :, k]
        new[..., :, k] = -s * rot[..., :, j] + c * rot[..., :, k]
        return new, org
    return rot, org + v[..., None] * rot[..., :, i]


def forward(chain: Chain, params: np.ndarray, q: np.ndarray, keep_frames: bool = False):
    """End frames of the chain for every pose.

    Returns (rot (..., N, 3, 3), org (..., N, 3)) and, with keep_frames, the list of
    frames *before* each element plus the frame after the last one (before ``end``).
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    params = np.asarray(params, dtype=float)
    lead = params.shape[:-1] + (q.shape[0],)
    rot = np.broadcast_to(np.eye(3), lead + (3, 3)).copy()
    org = np.zeros(lead + (3,))
    frames = []
    for el, v in zip(chain.elements, chain.values(params, q)):
        if keep_frames:
            frames.append((rot, org))
        rot, org = _apply(rot, org, el, v)
    if keep_frames:
        frames.append((rot, org))
    end = chain.end
    org = org + rot @ end[:3, 3]
    rot = rot @ end[:3, :3]
    if keep_frames:
        return rot, org, frames
    return rot, org


def point_jacobians(chain: Chain, params: np.ndarray, q: np.ndarray, offset: np.ndarray,
                    n_params: int, n_joints: int):
    """Position of a point fixed in the end frame and its derivatives.

    offset: (N, 3) point coordinates in the end frame (one per pose).
    Returns p (N, 3), dp/dparams (N, 3, n_params), dp/dq (N, 3, n_joints),
    end rotation (N, 3, 3).
    """
    rot, org, frames = forward(chain, params, q, keep_frames=True)
    p = org + np.einsum("nij,nj->ni", rot, offset)
    jp = np.zeros(p.shape[:1] + (3, n_params))
    jq = np.zeros(p.shape[:1] + (3, n_joints))
    for el, (r, o) in zip(chain.elements, frames):
        axis = r[..., :, el.axis]
        col = np.cross(axis, p - o) if el.is_rotation else axis
        if el.param >= 0:
            jp[:, :, el.param] += col
        for j, c in el.joints:
            jq[:, :, j] += c * col
    return p, jp, jq, rot
