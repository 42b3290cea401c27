"""trigger_latency: a light barrier or touch trigger reports late.

The joint values recorded at the report are those of a moment tau after the real
event, so the position at the event is q - tau * dq/dt: one unknown, seen in data
that carries the joint velocity at each trigger (columns dq1_rad_s ... dqN_rad_s).
Trigger positions then move with sweep speed and flip with sweep direction.
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers.analysis.effects.base import Cause, JointBasis, Term


class TriggerLatency(Cause):
    id = "trigger_latency"

    def terms(self, model, layout, x, obs, ctx):
        if ctx.dq_rad_s is None or not np.any(ctx.dq_rad_s):
            return []
        basis = JointBasis(-ctx.dq_rad_s, np.eye(model.n_joints)[:, :, None])  # every joint, one parameter
        return [Term(self.id, {}, ("tau",), joint_basis=basis, units=("s",))]

    def unscorable(self, model, ctx):
        if ctx.dq_rad_s is None:
            return "needs the joint velocities at the trigger: columns dq1_rad_s .. dqN_rad_s"
        if not np.any(ctx.dq_rad_s):
            return "the joint velocity columns dq1_rad_s .. are all zero: measured at rest, no latency shows"
        return None

    def magnitude(self, term, theta, joint_delta):
        return {"latency_ms": float(theta[0]) * 1e3}
