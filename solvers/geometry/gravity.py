"""Gravity torques about the joints of a serial arm, with known or unknown masses.

With masses and centres of mass (a robot file may give them) the torque about
joint j is  tau_j = z_j . sum_{k>=j} (c_k - o_j) x m_k g.  Without them the same
torque is a linear combination of "mass-moment" regressors per downstream link k:
z_j . ((o_k - o_j) x g) (the link's mass) and z_j . ((R_k e_a) x g), a = x, y, z
(its mass times centre-of-mass offset), so compliance times torque stays linear
in identifiable lumped coefficients and no CAD masses are needed.
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers.geometry.chain import forward
from cellcal.solvers.estimation.lsq import chunks
from cellcal.solvers.geometry.robot_model import KinematicModel


def joint_frames(model: KinematicModel, params: np.ndarray, q: np.ndarray):
    """Axes and origins of the joints, and the links' own frames, for every pose.

    Returns axis (N, nj, 3), origin (N, nj, 3), link_rot (N, nj, 3, 3), link_org (N, nj, 3),
    all in the base frame, mm.
    """
    if not model.joint_elements:
        raise ValueError(f"{model.name}: joint frames are only defined for serial models")
    chain = model.chains[model.default_chain]
    _, _, frames = forward(chain, params, q, keep_frames=True)
    axis = np.stack([frames[e][0][..., :, 2] for e in model.joint_elements], axis=-2)
    origin = np.stack([frames[e][1] for e in model.joint_elements], axis=-2)
    link_rot = np.stack([frames[e][0] for e in model.link_ends], axis=-3)
    link_org = np.stack([frames[e][1] for e in model.link_ends], axis=-2)
    return axis, origin, link_rot, link_org


def gravity_torques(model: KinematicModel, params: np.ndarray, q: np.ndarray, masses_kg, coms_mm,
                    payload_kg=None, payload_com_mm=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Gravity torque about each joint (N, nj), N m, for known link masses.

    payload_kg: scalar or (N,) mass on the flange at payload_com_mm in the last link's frame.
    """
    q = np.atleast_2d(q)
    out = np.empty((len(q), model.n_joints))
    per_row = payload_kg is not None and np.ndim(payload_kg) > 0
    for rows in chunks(len(q)):  # every link frame of every pose at once would be large
        out[rows] = _gravity_torques(model, params, q[rows], masses_kg, coms_mm,
                                     payload_kg[rows] if per_row else payload_kg, payload_com_mm)
    return out


def _gravity_torques(model, params, q, masses_kg, coms_mm, payload_kg, payload_com_mm) -> np.ndarray:
    axis, origin, link_rot, link_org = joint_frames(model, params, q)
    n, nj = axis.shape[:2]
    masses = np.array(masses_kg, dtype=float)
    coms = np.einsum("nkij,kj->nki", link_rot, np.asarray(coms_mm, dtype=float)) + link_org
    g = np.asarray(model.gravity, dtype=float)
    weights = np.broadcast_to(masses, (n, nj)).copy()
    points = coms
    if payload_kg is not None:
        pay = np.broadcast_to(np.asarray(payload_kg, dtype=float), (n,))
        pay_point = link_rot[:, -1] @ np.asarray(payload_com_mm, dtype=float) + link_org[:, -1]
        weights = np.concatenate([weights, pay[:, None]], axis=1)
        points = np.concatenate([points, pay_point[:, None]], axis=1)
        owner = np.r_[np.arange(nj), nj - 1]
    else:
        owner = np.arange(nj)
    tau = np.zeros((n, nj))
    for j in range(nj):
        down = owner >= j
        arm_m = (points[:, down] - origin[:, j, None]) * 1e-3
        force = weights[:, down, None] * g
        tau[:, j] = np.einsum("ni,ni->n", axis[:, j], np.cross(arm_m, force).sum(axis=1))
    return tau


def torque_regressors(model: KinematicModel, params: np.ndarray, q: np.ndarray, joint: int) -> np.ndarray:
    """Mass-moment regressors of the gravity torque about one joint (N, 4 * links downstream).

    Columns (per downstream link k): mass at the link origin, then the mass times
    centre-of-mass offset along the link frame's x, y, z. Units: m times m/s^2, so a
    coefficient in kg (or kg m) gives N m.
    """
    q = np.atleast_2d(q)
    return np.concatenate([_torque_regressors(model, params, q[rows], joint) for rows in chunks(len(q))]) \
        if len(q) else np.zeros((0, 4 * (model.n_joints - joint)))


def _torque_regressors(model, params, q, joint) -> np.ndarray:
    axis, origin, link_rot, link_org = joint_frames(model, params, q)
    g = np.asarray(model.gravity, dtype=float)
    z = axis[:, joint]
    cols = []
    for k in range(joint, model.n_joints):
        lever = (link_org[:, k] - origin[:, joint]) * 1e-3
        cols.append(np.einsum("ni,ni->n", z, np.cross(lever, g)))
        for a in range(3):
            cols.append(np.einsum("ni,ni->n", z, np.cross(link_rot[:, k, :, a], g)))
    return np.stack(cols, axis=1)


def tree_sites(model: KinematicModel, params: np.ndarray, q: np.ndarray):
    """Joints of any model (trees, coupled and passive joints) with what hangs below them.

    Returns a list, one entry per distinct joint rotation, of dicts:
    ``theta`` (parameter index of the rotation), ``bend`` (parameter index of the next
    rotation about x, the joint's bending axis, or -1), ``chain``, ``element``, ``axis``,
    ``bend_axis``, ``origin``, ``bend_origin`` (N, 3) and ``points``: the downstream link
    points (N, 3) mm, each counted once however many chains carry it, and ``point_keys``: what
    identifies each point across joints (one link's mass loads every joint above it) and
    ``point_rots`` (N, 3, 3): the link frame at each point (a centre of mass off the point
    lies along its axes).
    """
    sites: dict[int, dict] = {}
    for name, chain in model.chains.items():
        end_rot, end, frames = forward(chain, params, q, keep_frames=True)
        els = chain.elements
        points = []  # (key, element, (rotation, position)) along this chain
        for e, el in enumerate(els):
            if not (el.kind == "rz" and el.joints and el.param >= 0):
                continue
            after = e + 2 if e + 1 < len(els) and els[e + 1].kind == "tz" else e + 1
            points.append((id(el), e, frames[after]))
        points.append((("end", name), len(els), (end_rot, end)))
        for key, e, _ in points[:-1]:
            el = els[e]
            site = sites.setdefault(key, {"theta": el.param, "chain": name, "element": e,
                                          "axis": frames[e][0][..., :, 2], "origin": frames[e][1],
                                          "bend": -1, "points": {}})
            nxt = e + 2
            if nxt < len(els) and els[nxt].kind == "rx" and els[nxt].param >= 0:
                site.update(bend=els[nxt].param, bend_axis=frames[nxt][0][..., :, 0],
                            bend_origin=frames[nxt][1])
            for pkey, pe, p in points:
                if pe > e:
                    site["points"][pkey] = p
    return [dict(s, points=[p for _, p in s["points"].values()], point_rots=[r for r, _ in s["points"].values()],
                 point_keys=list(s["points"])) for s in sites.values()]


def point_mass_regressors(axis: np.ndarray, origin: np.ndarray, points, gravity) -> np.ndarray:
    """Gravity torque about an axis per unit mass at each point (N, len(points)), N m / kg."""
    g = np.asarray(gravity, dtype=float)
    return np.stack([np.einsum("ni,ni->n", axis, np.cross((p - origin) * 1e-3, g)) for p in points], axis=1)
