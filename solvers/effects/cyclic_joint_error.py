"""cyclic_joint_error: periodic transmission or encoder error.

Delta q_j = A_j sin(n q_j + phi_j) = a sin(n q_j) + b cos(n q_j), for small whole
numbers n (gear eccentricity n = 1, encoder mounting n = 2, ...).
"""
from __future__ import annotations

import numpy as np

from .base import Cause, JointBasis, Term

ORDERS = (1, 2, 3)
MIN_RANGE_RAD = np.deg2rad(60.0)  # a joint that barely moves shows no period


class CyclicJointError(Cause):
    id = "cyclic_joint_error"

    def terms(self, model, layout, x, obs, ctx):
        out = []
        for j in range(model.n_joints):
            qj = obs.q[:, j]
            if np.ptp(qj) < MIN_RANGE_RAD:
                continue
            for n in ORDERS:
                basis = JointBasis.single(np.stack([np.sin(n * qj), np.cos(n * qj)], axis=1), j, model.n_joints)
                out.append(Term(self.id, {"joint": j + 1, "order": n}, (f"s{j + 1}_{n}", f"c{j + 1}_{n}"),
                                joint_basis=basis, units=("rad", "rad")))
        return out

    def magnitude(self, term, theta, joint_delta):
        a, b = theta
        return {"amplitude_deg": float(np.rad2deg(np.hypot(a, b))), "order": term.where["order"],
                "phase_deg": float(np.rad2deg(np.arctan2(b, a)))}
