"""joint_compliance: joints deflect under gravity (gearbox and link elasticity).

Delta q_j = c_j * tau_j(q, payload). With every link mass in the robot file the
torque is computed and c_j (rad/N m) is the one unknown; without masses tau_j is
a combination of mass-moment regressors (``solvers.geometry.gravity``) and the lumped
coefficients c_j * m_k, c_j * m_k * r_k are identified instead, so the analysis
never needs CAD masses. The size reported is the deflection itself, place by place
only where the data determine it (``physical_sizes``).
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers.geometry.gravity import gravity_torques, point_mass_regressors, torque_regressors, tree_sites
from cellcal.solvers.analysis.effects.base import Cause, JointBasis, Term
from cellcal.solvers.analysis.effects import elastic_mount
from cellcal.solvers.analysis.effects.elastic_mount import mount_columns

MIN_TORQUE_SPREAD = 1e-6  # a joint whose gravity torque never changes (vertical axis) has no candidate


class JointCompliance(Cause):
    id = "joint_compliance"

    def _known_masses(self, model):
        links = model.links
        return (len(links) == model.n_joints and all(l.mass_kg is not None and l.com_mm is not None
                                                        for l in links))

    def _columns(self, model, k, q, ctx, joint, torques=None):
        if self._known_masses(model):
            return torques[:, joint, None], ("compliance",), ("rad/Nm",)
        cols = torque_regressors(model, k, q, joint)
        names = [f"moment{i}" for i in range(cols.shape[1])]
        if ctx.payload_kg is not None and np.ptp(ctx.payload_kg) > 0:
            # payload adds its own mass moment at the flange, in proportion to its mass
            cols = np.hstack([cols, cols[:, -4:] * ctx.payload_kg[:, None]])  # last link = flange
            names += [f"payload_moment{i}" for i in range(4)]
        return cols, tuple(names), ("rad",) * len(names)

    def _tree_terms(self, model, layout, x, obs):
        """Trees (and coupled or passive joints): each joint's rotation and its bending axis
        deflect by point-mass gravity torques of everything downstream (masses unknown)."""
        k = x[: layout.n_kin]
        by_chain: dict[str, dict] = {}
        every_point = {}
        for site in tree_sites(model, k, obs.q):
            every_point.update(zip(site["point_keys"], site["points"]))
            if not site["points"]:
                continue
            basis = {}
            names = []
            for axis_key, origin_key, param in (("axis", "origin", site["theta"]),
                                               ("bend_axis", "bend_origin", site["bend"])):
                if param < 0:
                    continue
                cols = point_mass_regressors(site[axis_key], site[origin_key], site["points"], model.gravity)
                keep = np.ptp(cols, axis=0) > MIN_TORQUE_SPREAD
                if keep.any():
                    basis[param] = cols[:, keep]
                    names += [f"{model.param_names[param]}.m{i}" for i in range(int(keep.sum()))]
            if basis:
                group = by_chain.setdefault(model.param_names[site["theta"]].split(".")[0], {"basis": [], "names": []})
                group["basis"].append(basis)
                group["names"] += names
        # the whole tree also tilts on its mount (``elastic_mount``): with the root branch, and with all
        mount = mount_columns(model, layout, x, obs, list(every_point.values()))
        out = []
        for i, (where, group) in enumerate(by_chain.items()):
            out.append(self._param_term(model, {"branch": where}, group["basis"], group["names"], len(obs),
                                        mount=mount if i == 0 else None))
        if len(out) > 1:  # every branch, and the mount's pivot where the data put it: the tilt also shifts the
            # base horizontally (constant columns: one linear solve per step of the full fit, ``extended_model``)
            pivot = mount_columns(model, layout, x, obs, list(every_point.values()), shifts=elastic_mount.PIVOT_SHIFT)
            out.append(self._param_term(model, {"branches": list(by_chain)},
                                        [b for g in by_chain.values() for b in g["basis"]],
                                        [n for g in by_chain.values() for n in g["names"]], len(obs), multi=True,
                                        mount=pivot))
        return out

    def _param_term(self, model, where, bases, names, n_rows, multi=False, mount=None):
        """One term moving the frames' parameters (bases: [{param: (N, k)}], columns side by side),
        and with mount = (columns, names, places) from ``mount_columns`` the mount's tilt after them."""
        n_param = len(names)
        if mount is not None and mount[1]:
            names = list(names) + mount[1]
        m = len(names)
        param_basis: dict[int, np.ndarray] = {}
        col = 0
        for basis in bases:
            for p, cols in basis.items():
                block = param_basis.setdefault(p, np.zeros((n_rows, m)))
                block[:, col: col + cols.shape[1]] = cols
                col += cols.shape[1]
        # what each moved parameter is called, for the report: torso.theta2 -> torso.joint2
        labels = {p: model.param_names[p].replace("theta", "joint").replace("alpha", "bend_before")
                  for p in param_basis}
        if m == n_param:
            return Term(self.id, where, tuple(names), param_basis=param_basis, units=("rad",) * m, multi=multi,
                        extra={"labels": labels})
        cols, _, places = mount
        cart = np.zeros((n_rows, 3, m))
        cart[:, :, n_param:] = cols
        tilt = {}
        for label, d in places.items():
            tilt[label] = np.zeros((n_rows, m))
            tilt[label][:, n_param:] = d
        return Term(self.id, where, tuple(names), param_basis=param_basis, cart_basis=cart,
                    units=("rad",) * n_param + ("mm",) * (m - n_param), multi=multi,
                    extra={"labels": labels, "mount_places": tilt})

    def terms(self, model, layout, x, obs, ctx):
        if not model.joint_elements:
            return self._tree_terms(model, layout, x, obs)
        k = x[: layout.n_kin]
        torques = None
        if self._known_masses(model):  # every joint's torque in one pass over the rows
            torques = gravity_torques(model, k, obs.q, [l.mass_kg for l in model.links],
                                      [l.com_mm for l in model.links], payload_kg=ctx.payload_kg)
        out = []
        for j in range(model.n_joints):
            cols, names, units = self._columns(model, k, obs.q, ctx, j, torques)
            if np.ptp(cols, axis=0).max() < MIN_TORQUE_SPREAD:
                continue
            basis = JointBasis.single(cols, j, model.n_joints)
            out.append(Term(self.id, {"joint": j + 1}, tuple(f"c{j + 1}.{n}" for n in names),
                            joint_basis=basis, units=units))
        return out  # several joints together: the analysis' forward search combines them (``search_places``)

    def search_places(self, terms):
        """A serial arm's joints, one term each (a tree's branches compete as they are)."""
        singles = [t for t in terms if "joint" in t.where and t.joint_basis is not None]
        return (singles, []) if singles and len(singles) == len(terms) else None

    def places(self, term):
        """Every deflecting place of the term: a tree's frame rotations and bending axes, a
        serial arm's joints; with known masses each joint's compliance (rad/N m) is a theta entry."""
        if term.param_basis:
            return ([(term.extra["labels"][p], basis) for p, basis in term.param_basis.items()]
                    + list(term.extra.get("mount_places", {}).items())), {}
        joints = [term.where["joint"]] if "joint" in term.where else term.where["joints"]
        basis = term.joint_basis
        out = [(f"joint{j}", basis.values @ basis.mix[:, j - 1, :]) for j in joints]
        compliance = {f"joint{j}": term.names.index(f"c{j}.compliance") for j in joints
                      if f"c{j}.compliance" in term.names}
        return out, compliance

    def magnitude(self, term, theta, joint_delta):
        if term.param_basis or term.multi:  # several places: no number per place here, the split
            return {}  # may be arbitrary; ``places`` sizes each where the data determine it
        j = term.where["joint"]
        d = np.rad2deg(joint_delta[:, j - 1])
        out = {f"joint{j}_deflection_rms_deg": float(np.sqrt(np.mean(d**2))),
               f"joint{j}_deflection_max_deg": float(np.abs(d).max())}
        if term.units == ("rad/Nm",):
            out["compliance_rad_per_Nm"] = float(theta[0])
        out["deflection_rms_deg"] = out[f"joint{j}_deflection_rms_deg"]
        return out
