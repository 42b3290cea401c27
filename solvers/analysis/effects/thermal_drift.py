"""thermal_drift: links grow or shrink as the robot warms.

Every link length scales by (1 + k dT). To first order (k dT is 1e-4 at most)
the target moves by k dT * sum_l L_l dp/dL_l, one column per data set. dT comes
from ``temp_c`` when the data has it, else from a warm-up curve
1 - exp(-t / tau) over ``t_s`` with tau from a small grid (the time constant of
an arm's warm-up is tens of minutes to hours).
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers.identification.measurement_model import jacobian_chunks
from cellcal.solvers.analysis.effects.base import Cause, Term

WARMUP_TAU_S = (600.0, 1800.0, 3600.0, 7200.0)


class ThermalDrift(Cause):
    id = "thermal_drift"

    def _growth_direction(self, layout, x, obs):
        lengths = np.flatnonzero(~layout.model.param_is_angle)
        out = np.empty((len(obs), 3))
        for rows, _, j in jacobian_chunks(layout, x, obs):
            out[rows] = j[:, :, lengths] @ x[lengths]
        return out

    def terms(self, model, layout, x, obs, ctx):
        drivers = []
        if ctx.temp_c is not None and np.ptp(ctx.temp_c) > 0.1:
            drivers.append(({"driver": "temp_c"}, ctx.temp_c - np.median(ctx.temp_c), "1/K"))
        elif ctx.t_s is not None and np.ptp(ctx.t_s) > 60.0:
            t = ctx.t_s - ctx.t_s.min()
            for tau in WARMUP_TAU_S:
                if tau < 3 * t.max():
                    drivers.append(({"driver": "t_s", "tau_s": tau}, 1.0 - np.exp(-t / tau), "1"))
        if not drivers:
            return []
        growth = self._growth_direction(layout, x, obs)
        return [Term(self.id, where, ("k",), cart_basis=(growth * dt[:, None])[:, :, None], units=(unit,),
                     extra={"dT": dt})
                for where, dt, unit in drivers]

    def unscorable(self, model, ctx):
        if ctx.temp_c is not None and np.ptp(ctx.temp_c) > 0.1:
            return None
        if ctx.t_s is not None and np.ptp(ctx.t_s) > 60.0:
            return None
        if ctx.temp_c is None and ctx.t_s is None:
            return "needs a temp_c or t_s column (temperature or time of each measurement)"
        return ("needs temp_c varying by more than 0.1 K or t_s spanning more than 60 s; "
                "these data have neither")

    def magnitude(self, term, theta, joint_delta):
        k = float(theta[0])
        if term.units == ("1/K",):
            return {"expansion_ppm_per_K": k * 1e6,
                    "growth_ppm_over_data": k * 1e6 * float(np.ptp(term.extra["dT"]))}
        return {"growth_ppm_at_end": k * 1e6 * float(term.extra["dT"].max()), "tau_s": term.where["tau_s"]}
