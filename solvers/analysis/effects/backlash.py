"""backlash: lost motion in a joint's transmission.

Delta q_j = (b_j / 2) * s_j, with s_j = +-1 the direction joint j approached the
pose from (the sign of its last change, from the row order of the data).
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers.analysis.effects.base import Cause, JointBasis, Term


class Backlash(Cause):
    id = "backlash"

    def terms(self, model, layout, x, obs, ctx):
        out = []
        for j in range(model.n_joints):
            s = ctx.direction[:, j]
            if np.count_nonzero(s > 0) < 3 or np.count_nonzero(s < 0) < 3:
                continue  # always approached from one side: backlash is a constant offset
            basis = JointBasis.single(0.5 * s, j, model.n_joints)
            out.append(Term(self.id, {"joint": j + 1}, (f"b{j + 1}",), joint_basis=basis, units=("rad",)))
        return out  # several joints together: the analysis' forward search combines them (``search_places``)

    def search_places(self, terms):
        return (list(terms), []) if terms else None

    def magnitude(self, term, theta, joint_delta):
        if "joint" in term.where:
            return {"backlash_deg": float(np.rad2deg(abs(theta[0])))}
        return {f"joint{j}_backlash_deg": float(np.rad2deg(abs(b)))
                for j, b in zip(term.where["joints"], theta)}
