"""Does the effect fitted on one data set hold on another? (``cellcal analyze --validate``)

The finding of :func:`.analyze.analyze` on data set A carried to data set B (another time, pose set
or target): A's kinematics and effect parameters held, only B's own frame and target offsets fitted.
When B was taken in A's setup (a test set of the same session: the same instrument frame, the same
targets), nothing is fitted on B (``same_setup``): refitting 9 parameters on a small B flatters both
scores, most the one with fewer rows per parameter.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from cellcal.solvers.estimation import lsq
from cellcal.solvers.analysis.analyze import Finding
from cellcal.solvers.analysis.effects import CAUSES, Context, JointBasis, Term
from cellcal.solvers.identification.identify import identify
from cellcal.solvers.analysis.extended_model import ExtendedModel, norm_scale
from cellcal.solvers.identification.measurement_model import Layout, Observations
from cellcal.solvers.analysis.robust_scoring import RobustScoring


class TransferError(ValueError):
    """The second data set cannot test the finding (its message says what is missing)."""


@dataclass(frozen=True)
class Transfer:
    """The finding of data set A tried on data set B (another time, pose set or target).

    Kinematics (and the effect's parameters) as fitted on A; only what B must set itself,
    the instrument -> base frame and the target offsets, fitted on B."""

    baseline_errors_mm: np.ndarray  # (M,) B's errors with A's geometric fit
    extended_errors_mm: np.ndarray | None  # (M,) with A's geometry + effect fit; None: nothing named on A
    carried: str  # label of the effect carried over ("" when none)
    coverage_per_joint: tuple[float, ...]  # fraction of B's rows whose angle lies within A's range, per joint
    coverage_all: float  # fraction of B's rows with every joint within A's ranges
    note: str = ""
    same_setup: bool = False  # True: B scored with A's frame and target offsets (nothing fitted on B)

    @property
    def baseline_mean_mm(self) -> float:
        return float(self.baseline_errors_mm.mean())

    @property
    def extended_mean_mm(self) -> float | None:
        return None if self.extended_errors_mm is None else float(self.extended_errors_mm.mean())

    @property
    def gain_pct(self) -> float | None:
        if self.extended_errors_mm is None:
            return None
        return 100.0 * (1.0 - self.extended_mean_mm / self.baseline_mean_mm)


def transfer(model, finding: Finding, obs_a: Observations, obs_b: Observations, ctx_b: Context,
             loss: str = "linear", same_setup: bool = False) -> Transfer:
    """Score A's finding on B: A's geometric fit, and A's fit of geometry plus the named effect,
    each with B's frame and target offsets refitted on B (everything else as on A), or with
    ``same_setup`` as fitted on A (nothing fitted on B; TransferError for a target of B that A
    does not measure); B's rows inside A's joint ranges (``coverage``). When B cannot show the
    effect (it leaves a place of the effect without the motion its basis needs) only the geometry
    is scored, and the note says why."""
    lo, hi = obs_a.q.min(0), obs_a.q.max(0)
    inside = (obs_b.q >= lo) & (obs_b.q <= hi)
    layout = Layout(model, obs_b.target_names)
    if same_setup:
        unknown = sorted(set(obs_b.target_names) - set(obs_a.target_names))
        if unknown:
            raise TransferError(f"target(s) {', '.join(unknown)} of the second data set are not measured in the "
                                "first, so a setup shared with it gives them no offset")
        which = [obs_a.target_names.index(t) for t in obs_b.target_names]

        def setup_of(x_a, n_kin):  # A's base and the offsets of B's targets (after n_kin kinematic entries)
            return np.concatenate([x_a[n_kin: n_kin + 6], *(x_a[n_kin + 6 + 3 * i: n_kin + 9 + 3 * i] for i in which)])

        x_geo = np.concatenate([finding.baseline.x[: model.n_params], setup_of(finding.baseline.x, model.n_params)])
        refit = _as_fitted
    else:
        start = identify(model, obs_b)  # B's own fit: where its frame and targets start from
        x_geo = np.concatenate([finding.baseline.x[: model.n_params], start.x[layout.n_kin:]])
        refit = _frame_refit
    baseline = refit(layout, obs_b, x_geo, (), np.zeros(0), loss)
    extended, carried, note = None, "", ""
    if finding.cause == "none":
        note = ("no effect named on the first data set: nothing to carry over; the geometric fit alone is "
                "scored on the second")
    else:
        named = finding.extended
        ext_layout, x_ext = layout, x_geo.copy()
        structural = [t for t in named.terms if t.model is not None]
        if structural:  # a different rigid model: its extra parameters as fitted on A
            ext_layout = Layout(structural[-1].model, obs_b.target_names)
            x_ext = np.concatenate([named.x[: ext_layout.n_kin], x_geo[layout.n_kin:]])
        else:
            x_ext[: model.n_params] = named.x[: model.n_params]
        if same_setup:  # the frame and offsets the extended fit put on A
            x_ext[ext_layout.n_kin:] = setup_of(named.x, ext_layout.n_kin)
        carried = named.label
        try:
            terms = tuple(_term_on_rows(t, model, layout, x_ext, obs_b, ctx_b) for t in named.terms
                          if t.model is None)
        except TransferError as exc:  # B cannot show the effect: the geometry alone is scored, and why said
            carried, note = "", str(exc)
        else:
            extended = refit(ext_layout, obs_b, x_ext, terms, named.theta, loss)
    return Transfer(baseline, extended, carried, tuple(float(f) for f in inside.mean(0)),
                    float(inside.all(1).mean()), note, same_setup)


def _term_on_rows(term: Term, model, layout: Layout, x: np.ndarray, obs: Observations, ctx: Context) -> Term:
    """The same term (same parameters, same meaning of theta) with its basis at other rows."""
    if term.extra.get("parts"):  # several single parts side by side (cyclic orders of several joints)
        parts = [_term_on_rows(p, model, layout, x, obs, ctx) for p in term.extra["parts"]]
        basis = JointBasis.side_by_side([(p.joint_basis, p.size) for p in parts], len(obs), model.n_joints)
        return dataclasses.replace(term, joint_basis=basis, extra={})
    basis = term.joint_basis
    if hasattr(basis, "values_of") and term.cart_basis is None and not term.param_basis:
        joint = int(np.nonzero(basis.mix)[1][0])  # a function of one joint's angle: evaluate it at B's angles
        return dataclasses.replace(term, joint_basis=JointBasis.of_angle(obs.q[:, joint], basis.values_of, joint,
                                                                         model.n_joints, term.size))
    same = [t for t in CAUSES[term.cause].terms(model, layout, x, obs, ctx)
            if t.where == term.where and t.names == term.names]
    if not same:
        raise TransferError(f"{term.label()} cannot be evaluated on the second data set: it does not move the "
                            "place of the effect enough (or lacks the columns it needs, e.g. payload, time or "
                            "temperature); only the geometry is scored: measure it with that joint moving as in "
                            "the first")
    return same[0]


def _as_fitted(layout: Layout, obs: Observations, x: np.ndarray, terms: tuple[Term, ...], theta: np.ndarray,
               loss: str) -> np.ndarray:
    """(M,) errors with everything as given: nothing fitted on these rows."""
    model = ExtendedModel(layout, obs, x, np.zeros(layout.size, bool), terms)
    return np.linalg.norm(model.residuals_mm(np.asarray(theta, dtype=float)[: model.n_theta]), axis=1)


def _frame_refit(layout: Layout, obs: Observations, x: np.ndarray, terms: tuple[Term, ...], theta: np.ndarray,
                 loss: str) -> np.ndarray:
    """(M,) errors after fitting only the base frame and target offsets (kinematics and theta held)."""
    free = np.zeros(layout.size, bool)
    free[layout.n_kin:] = True
    model = ExtendedModel(layout, obs, x, free, terms)
    n = model.n_free
    theta = np.asarray(theta, dtype=float)[: model.n_theta]
    first = lsq.RFactor(n)
    for _, j in model.jacobian_chunks(np.concatenate([x[free], theta])):
        first.add(j[:, :, :n].reshape(-1, n))
    scale = norm_scale(np.linalg.norm(first.r, axis=0), len(obs))
    f_scale = RobustScoring.of(loss, model.residuals_mm(np.concatenate([x[free], theta]))).f_scale_mm

    def evaluate(z_free, jac):
        z = np.concatenate([z_free, theta])
        ne = lsq.NormalEquations(n, loss, f_scale)
        if jac:
            for _, j, residuals in model.jacobian_chunks(z, with_residuals=True):
                ne.add(j[:, :, :n].reshape(-1, n), residuals.ravel())
        else:
            ne.add(None, model.residuals_mm(z).ravel())
        return ne

    sol = lsq.levenberg_marquardt(evaluate, x[free], 1.0 / scale, ftol=1e-10, xtol=1e-10, gtol=1e-8)
    return np.linalg.norm(model.residuals_mm(np.concatenate([sol.x, theta])), axis=1)
