"""joint_compliance: joints deflect under gravity (gearbox and link elasticity).

Delta q_j = c_j * tau_j(q, payload). With every link mass in the robot file the
torque is computed and c_j (rad/N m) is the one unknown; without masses tau_j is
a combination of mass-moment regressors (``solvers.gravity``) and the lumped
coefficients c_j * m_k, c_j * m_k * r_k are identified instead, so the analysis
never needs CAD masses. The size reported is the deflection itself.
"""
from __future__ import annotations

import numpy as np

from ..gravity import gravity_torques, torque_regressors
from .base import Cause, Term

MIN_TORQUE_SPREAD = 1e-6  # a joint whose gravity torque never changes (vertical axis) has no candidate


class JointCompliance(Cause):
    id = "joint_compliance"

    def _known_masses(self, model):
        links = model.links
        return (len(links) == model.n_joints and all(l.mass_kg is not None and l.com_mm is not None
                                                        for l in links))

    def _columns(self, model, k, q, ctx, joint):
        if self._known_masses(model):
            tau = gravity_torques(model, k, q, [l.mass_kg for l in model.links],
                                  [l.com_mm for l in model.links],
                                  payload_kg=ctx.payload_kg)[:, joint]
            return tau[:, None], ("compliance",), ("rad/Nm",)
        cols = torque_regressors(model, k, q, joint)
        names = [f"moment{i}" for i in range(cols.shape[1])]
        if ctx.payload_kg is not None and np.ptp(ctx.payload_kg) > 0:
            # payload adds its own mass moment at the flange, in proportion to its mass
            cols = np.hstack([cols, cols[:, -4:] * ctx.payload_kg[:, None]])  # last link = flange
            names += [f"payload_moment{i}" for i in range(4)]
        return cols, tuple(names), ("rad",) * len(names)

    def terms(self, model, layout, x, obs, ctx):
        if not model.joint_elements:
            return []
        k = x[: layout.n_kin]
        out, all_cols, all_joints = [], [], []
        for j in range(model.n_joints):
            cols, names, units = self._columns(model, k, obs.q, ctx, j)
            if np.ptp(cols, axis=0).max() < MIN_TORQUE_SPREAD:
                continue
            basis = np.zeros((len(obs), model.n_joints, cols.shape[1]))
            basis[:, j, :] = cols
            out.append(Term(self.id, {"joint": j + 1}, tuple(f"c{j + 1}.{n}" for n in names),
                            joint_basis=basis, units=units))
            all_cols.append(basis)
            all_joints.append(j + 1)
        if len(all_cols) > 1:
            basis = np.concatenate(all_cols, axis=2)
            names = tuple(n for t in out for n in t.names)
            out.append(Term(self.id, {"joints": all_joints}, names, joint_basis=basis,
                            units=tuple(u for t in out for u in t.units), multi=True))
        return out

    def magnitude(self, term, theta, joint_delta):
        joints = [term.where["joint"]] if "joint" in term.where else term.where["joints"]
        out = {}
        for j in joints:
            d = np.rad2deg(joint_delta[:, j - 1])
            out[f"joint{j}_deflection_rms_deg"] = float(np.sqrt(np.mean(d**2)))
            out[f"joint{j}_deflection_max_deg"] = float(np.abs(d).max())
        if term.units == ("rad/Nm",):
            out["compliance_rad_per_Nm"] = float(theta[0])
        if len(joints) == 1:
            out["deflection_rms_deg"] = out[f"joint{joints[0]}_deflection_rms_deg"]
        return out
