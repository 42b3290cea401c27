"""Joint configurations for simulated campaigns, planned on the nominal model.

Planning uses only what a real planner has (the nominal model); the simulated
arm then executes the configurations with its hidden true geometry.
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers.geometry.chain import forward, point_jacobians
from cellcal.solvers.geometry.robot_model import KinematicModel

DEFAULT_SPAN = np.deg2rad(170.0)


def _limits(model: KinematicModel) -> np.ndarray:
    if model.joint_limits is None:
        return np.tile([-DEFAULT_SPAN, DEFAULT_SPAN], (model.n_joints, 1))
    lim = model.joint_limits.copy()
    return np.clip(lim, -DEFAULT_SPAN, DEFAULT_SPAN)


def full_workspace(model: KinematicModel, n: int, rng: np.random.Generator, *,
                   min_height_mm: float = -200.0, min_radius_mm: float = 300.0,
                   margin_deg: float = 5.0) -> np.ndarray:
    """n configurations spread over the joint space whose flange stays clear of
    the floor (z above min_height_mm) and of the robot's own column."""
    lim = _limits(model)
    margin = np.deg2rad(margin_deg)
    lo, hi = lim[:, 0] + margin, lim[:, 1] - margin
    chain = model.chains[model.default_chain]
    out = []
    while sum(len(o) for o in out) < n:
        q = rng.uniform(lo, hi, size=(4 * n, model.n_joints))
        _, org = forward(chain, model.nominal, q)
        ok = (org[:, 2] > min_height_mm) & (np.linalg.norm(org[:, :2], axis=1) > min_radius_mm)
        out.append(q[ok])
    return np.concatenate(out)[:n]


def constrained_volume(model: KinematicModel, n: int, rng: np.random.Generator, *,
                       centre_mm, cube_mm: float = 20.0, max_tilt_deg: float = 60.0,
                       offset_mm=(0.0, 0.0, 100.0)) -> np.ndarray:
    """n configurations that put a point ``offset_mm`` on the flange inside a cube
    of side ``cube_mm`` around ``centre_mm`` (base frame), with the tool axis
    within ``max_tilt_deg`` of straight down and every arm configuration (elbow,
    shoulder, wrist branch) the joint limits allow: the limited measurement space of
    Liu et al. ("L2-Regularization-Based Kinematic Parameter Identification for Industrial
    Robots in Limited Measurement Space", Actuators 2025), where orientation and branch
    are all the variety there is."""
    chain = model.chains[model.default_chain]
    offset = np.asarray(offset_mm, dtype=float)
    centre = np.asarray(centre_mm, dtype=float)
    nj = model.n_joints
    k = model.nominal
    lim = _limits(model)
    cos_tilt = np.cos(np.deg2rad(max_tilt_deg))
    out = []
    for _ in range(50):  # batches of candidates, each solved with damped Newton steps
        q = rng.uniform(lim[:, 0], lim[:, 1], size=(20 * n, nj))
        goal = centre + rng.uniform(-cube_mm / 2, cube_mm / 2, size=(len(q), 3))
        offsets = np.broadcast_to(offset, goal.shape)
        for _ in range(40):
            p, _, jq, rot = point_jacobians(chain, k, q, offsets, len(k), nj)
            err = goal - p
            step = np.einsum("nij,nj->ni", np.linalg.pinv(jq, rcond=1e-8), err)
            q = q + step / np.maximum(1.0, np.abs(step).max(axis=1) / 0.3)[:, None]
        p, _, _, rot = point_jacobians(chain, k, q, offsets, len(k), nj)
        ok = ((np.linalg.norm(goal - p, axis=1) < 1e-3) & (-rot[:, 2, 2] >= cos_tilt)
              & np.all((q > lim[:, 0]) & (q < lim[:, 1]), axis=1))
        out.extend(q[ok])
        if len(out) >= n:
            return np.array(out[:n])
    raise ValueError(f"only {len(out)} of {n} configurations reach the cube at {centre.tolist()} mm")


def joint_sweeps(model: KinematicModel, steps: int, span_deg, home=None) -> np.ndarray:
    """A one-joint-at-a-time campaign: each joint in turn through `steps` evenly spaced angles over
    +/- span_deg[j] about home (within its limits), the others at home; (n_joints * steps, n_joints)."""
    lim = _limits(model)
    home = np.zeros(model.n_joints) if home is None else np.asarray(home, dtype=float)
    out = []
    for j, span in enumerate(np.deg2rad(np.asarray(span_deg, dtype=float))):
        q = np.tile(home, (steps, 1))
        q[:, j] = np.linspace(max(lim[j, 0], home[j] - span), min(lim[j, 1], home[j] + span), steps)
        out.append(q)
    return np.concatenate(out)
