"""The measurement model of a calibration: instrument frame -> base -> chain -> target.

    p_meas = R_b @ (R_end(q; k) @ t_target + o_end(q; k)) + t_b

The full unknown vector is ``x = [kinematic parameters k, base (tx, ty, tz mm,
rotation vector rad), one 3-vector offset per target in the end frame (mm)]``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.chain import forward, point_jacobians_by_component
from cellcal.solvers.estimation.lsq import chunks
from cellcal.solvers.geometry.robot_model import KinematicModel

BASE_NAMES = ("base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz")


@dataclass(frozen=True)
class Observations:
    """Measured target positions with the joint values they were taken at."""

    q: np.ndarray  # (N, n_joints) rad, as the controller reports them
    xyz_mm: np.ndarray  # (N, 3), in the instrument frame
    target: np.ndarray  # (N,) int index into target_names
    target_names: tuple[str, ...] = ("tcp",)

    def __post_init__(self):
        if len(self.q) != len(self.xyz_mm) or len(self.q) != len(self.target):
            raise ValueError("q, xyz_mm and target must have one row per measurement")

    def __len__(self) -> int:
        return len(self.q)

    def subset(self, rows) -> "Observations":
        rows = rows if isinstance(rows, slice) else np.asarray(rows)
        return Observations(self.q[rows], self.xyz_mm[rows], self.target[rows], self.target_names)


@dataclass(frozen=True)
class Layout:
    """Where each unknown lives in the full vector x."""

    model: KinematicModel
    target_names: tuple[str, ...]

    @property
    def n_kin(self) -> int:
        return self.model.n_params

    @property
    def base(self) -> slice:
        return slice(self.n_kin, self.n_kin + 6)

    def target(self, i: int) -> slice:
        start = self.n_kin + 6 + 3 * i
        return slice(start, start + 3)

    @property
    def size(self) -> int:
        return self.n_kin + 6 + 3 * len(self.target_names)

    @property
    def names(self) -> tuple[str, ...]:
        tgt = tuple(f"target.{t}.{c}" for t in self.target_names for c in "xyz")
        return self.model.param_names + BASE_NAMES + tgt

    @property
    def is_angle(self) -> np.ndarray:
        base = np.array([False] * 3 + [True] * 3)
        return np.concatenate([self.model.param_is_angle, base, np.zeros(3 * len(self.target_names), bool)])

    def initial(self, base: np.ndarray | None = None, offsets: np.ndarray | None = None) -> np.ndarray:
        x = np.zeros(self.size)
        x[: self.n_kin] = self.model.nominal
        if base is not None:
            x[self.base] = base
        if offsets is not None:
            for i in range(len(self.target_names)):
                x[self.target(i)] = offsets[i]
        return x

    def offsets(self, x: np.ndarray) -> np.ndarray:
        return np.stack([x[self.target(i)] for i in range(len(self.target_names))])


def _groups(layout: Layout, obs: Observations):
    """Rows of obs grouped by the chain their target hangs on."""
    chains: dict[str, list[int]] = {}
    for i, t in enumerate(layout.target_names):
        chains.setdefault(layout.model.chain_for(t), []).append(i)
    for chain_name, targets in chains.items():
        rows = np.flatnonzero(np.isin(obs.target, targets))
        if len(rows):
            yield layout.model.chains[chain_name], rows


def end_frames(model: KinematicModel, params: np.ndarray, q: np.ndarray, chain: str | None = None):
    """Rotation and origin of a chain's end frame in the base frame, for each pose."""
    return forward(model.chains[chain or model.default_chain], params, q)


def predict_base(layout: Layout, x: np.ndarray, obs: Observations) -> np.ndarray:
    """Target positions in the robot base frame (mm)."""
    k = x[: layout.n_kin]
    offsets = layout.offsets(x)
    out = np.empty((len(obs), 3))
    for block in chunks(len(obs)):
        sub = obs.subset(block)
        part = out[block]
        for chain, rows in _groups(layout, sub):
            rot, org = forward(chain, k, sub.q[rows])
            part[rows] = org + np.einsum("nij,nj->ni", rot, offsets[sub.target[rows]])
    return out


def predict(layout: Layout, x: np.ndarray, obs: Observations) -> np.ndarray:
    """Target positions in the instrument frame (mm)."""
    b = x[layout.base]
    r = se3.rotvec_to_matrix(b[3:])
    return predict_base(layout, x, obs) @ r.T + b[:3]


def jacobian_chunks(layout: Layout, x: np.ndarray, obs: Observations, with_joints: bool = False,
                    kinematic: bool = True):
    """``jacobian`` a block of rows at a time: yields (rows slice, p, d p / d x[, d p / d q])."""
    for block in chunks(len(obs)):
        yield (block, *jacobian(layout, x, obs.subset(block), with_joints, kinematic))


def jacobian(layout: Layout, x: np.ndarray, obs: Observations, with_joints: bool = False,
             kinematic: bool = True):
    """Predicted positions (N, 3) and d p / d x as (N, 3, size).

    With ``with_joints`` also d p / d q (N, 3, n_joints), for effect models that
    act through joint values. ``kinematic=False`` leaves the kinematic columns (and
    d p / d q) zero, for fits of base and target offsets alone: much less work.
    """
    n = len(obs)
    k = x[: layout.n_kin]
    b = x[layout.base]
    rb = se3.rotvec_to_matrix(b[3:])
    offsets = layout.offsets(x)
    nj = layout.model.n_joints
    # built component-major, (unknown, coordinate, pose): every operation runs along the poses
    p_base = np.empty((3, n))
    jac = np.zeros((layout.size, 3, n))
    jq = np.zeros((nj, 3, n)) if with_joints else None
    for chain, rows in _groups(layout, obs):
        whole = len(rows) == n
        at = slice(None) if whole else rows
        if kinematic:
            p, jp, jqq, axes = point_jacobians_by_component(chain, k, obs.q[rows], offsets[obs.target[rows]],
                                                             layout.n_kin, nj)
            jac[: layout.n_kin, :, at] = jp
            if with_joints:
                jq[:, :, at] = jqq
        else:
            rot, org = forward(chain, k, obs.q[rows])
            axes = [rot[..., c].T for c in range(3)]
            p = (org + np.einsum("nij,nj->ni", rot, offsets[obs.target[rows]])).T
        p_base[:, at] = p
        for i in np.unique(obs.target[rows]):
            mine = obs.target[rows] == i
            cols = layout.target(i)
            for c in range(3):
                if mine.all():
                    jac[cols.start + c][:, at] = axes[c]
                else:
                    jac[cols.start + c][:, rows[mine]] = axes[c][:, mine]
    # everything so far is in the base frame: rotate into the instrument frame
    jac = np.matmul(rb, jac)
    rp = rb @ p_base
    jac[layout.base.start: layout.base.start + 3] = np.eye(3)[:, :, None]
    left = se3.left_jacobian(b[3:])
    for c in range(3):  # -[rp]x J_l: column c is J_l[:, c] x rp
        jac[layout.base.start + 3 + c] = np.cross(left[:, c], rp, axisb=0).T
    p = (rp + b[:3, None]).T
    jac = np.ascontiguousarray(jac.transpose(2, 1, 0))
    if with_joints:
        jq = np.ascontiguousarray(np.matmul(rb, jq).transpose(2, 1, 0))
    return (p, jac, jq) if with_joints else (p, jac)
