"""parallel_axis_tilt: nominally parallel joint axes that are slightly tilted.

Classic DH cannot represent a small tilt between parallel axes (its common normal
jumps), so a DH fit stalls above the noise with residuals that follow the
parallel joints' angles. The extension is the Hayati beta on that joint pair: a
different rigid model with one more parameter, fitted like any other.
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers.geometry.robot_model import parallel_joint_pairs, with_hayati_beta
from cellcal.solvers.analysis.effects.base import Cause, Term


class ParallelAxisTilt(Cause):
    id = "parallel_axis_tilt"

    def unscorable(self, model, ctx):
        if not model.joint_elements or not parallel_joint_pairs(model):
            return f"{model.name} has no nominally parallel neighbouring joint axes"
        return None

    def terms(self, model, layout, x, obs, ctx):
        if not model.joint_elements:
            return []
        out = []
        for i in parallel_joint_pairs(model):
            if f"beta{i + 1}" in model.param_names:
                continue  # already modelled
            out.append(Term(self.id, {"joints": [i + 1, i + 2]}, (f"beta{i + 1}",),
                            model=with_hayati_beta(model, i), units=("rad",)))
        return out

    def magnitude(self, term, theta, joint_delta):
        return {"tilt_deg": float(np.rad2deg(abs(theta[0])))}
