"""Kinematic identification: Levenberg-Marquardt with rank handling and an L2 prior.

    min_x  sum_i rho(|p_i(x) - m_i|^2) + lam * sum_j ((k_j - k_j,nominal) / s_j)^2

over geometric parameters k, the instrument -> base transform and the target
offsets. Parameters this data cannot separate are held at nominal and reported
(``identifiability``). ``regularize="cv"`` picks lam by grouped k-fold
cross-validation (Liu et al., "L2-Regularization-Based Kinematic Parameter
Identification for Industrial Robots in Limited Measurement Space", Actuators 2025);
``"none"`` is plain least squares over the
identifiable parameters.

After the fit every estimated kinematic parameter and target offset must be one a
person can trust (``_hold_untrustworthy``): a standard deviation within a bound
per kind and a value within a plausible distance of nominal. A direction the data
hardly sees can move strongly correlated parameters far while the predicted
positions barely change (a target near the last joint axis makes d5, alpha5 and
the offset along that axis nearly one quantity); such parameters are held at
nominal, one at a time, and the fit repeated, and they are reported by name with
the values that were rejected. The result reads like scipy's ``OptimizeResult``:
``x``, ``status``, ``message`` and named fields.

Files of hundreds of thousands of rows are routine (a tracker logging at 10 Hz), so
no step holds a whole Jacobian: the fits (``kinematic_fit``) run on normal equations,
the identifiability analysis on an R factor and the cross-validation on one R factor
per fold, each accumulated a block of rows at a time.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from cellcal.solvers.estimation import crossval, identifiability
from cellcal.solvers.estimation.fit_result import FitResult
from cellcal.solvers.estimation.identifiability import CorrelatedGroup, HeldParameter
from cellcal.solvers.estimation.identifiability import human as _human
from cellcal.solvers.identification.kinematic_fit import Fit, at_start, covariance, f_scale_of, fit, initial_base_and_targets, register, scales
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian_chunks, predict
from cellcal.solvers.geometry.robot_model import KinematicModel

LOSSES = ("linear", "soft_l1", "huber", "cauchy")
REGULARIZE = ("cv", "none")
DEFAULT_LAMBDAS = tuple(np.logspace(-6, 4, 21))


@dataclass(frozen=True)
class IdentifyOptions:
    regularize: str = "cv"
    loss: str = "linear"
    folds: int = 5
    lambdas: tuple[float, ...] = DEFAULT_LAMBDAS  # 0 is always tried as well
    prior_mm: float = 1.0  # directions that would scatter more than this are not estimated
    fixed: tuple[str, ...] = ()  # parameter names held at nominal by the caller
    seed: int = 0
    # After the fit, an estimate is reported as identified only within these bounds; beyond them
    # it is held at nominal (``_hold_untrustworthy``). Standard deviations, 1 sigma:
    max_std_mm: float = 2.0  # less certain than this, a length cannot tell a mm-size assembly error from none
    max_std_deg: float = 0.5  # an axis this uncertain moves a target ~9 mm at 1 m reach: no finding
    # Distance from nominal (target offsets: from the nominal model's own fit of them), widened to
    # what the nominal model's 95th-percentile error allows (mm; over the reach for angles):
    plausible_mm: float = 10.0  # a manufactured arm's lengths and offsets are within a few mm of the drawing
    plausible_deg: float = 2.0  # and its joint axes within tenths of a degree of their nominal directions

    def __post_init__(self):
        if self.regularize not in REGULARIZE:
            raise ValueError(f"regularize must be one of {REGULARIZE}, got {self.regularize!r}")
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {self.loss!r}")
        if self.folds < 2:
            raise ValueError("folds must be at least 2")
        if not (np.isfinite(self.prior_mm) and self.prior_mm > 0):
            raise ValueError(f"prior_mm must be a positive number of mm, got {self.prior_mm}")
        for name in ("max_std_mm", "max_std_deg", "plausible_mm", "plausible_deg"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


@dataclass(frozen=True)
class Identification(FitResult):
    """What identify() found, with named fields in the manner of scipy's OptimizeResult: status,
    success and nfev of the final fit, as scipy.optimize.least_squares reports them (status > 0:
    converged), its message in words with what was held after it; covariance of x in x's units
    (0 in the rows and columns of what was held)."""

    layout: Layout
    # full unknown vector as Layout orders it: kinematic parameters (lengths mm, angles rad),
    # base (mm, rotation vector rad), target offsets (mm); layout.is_angle says which are rad
    x: np.ndarray
    x_nominal: np.ndarray  # nominal kinematics with base/targets fitted: the "before" model
    free: np.ndarray  # bool mask over x: estimated here
    std: np.ndarray  # standard deviation of each entry of x, in x's units (0 where held)
    unidentifiable: tuple[str, ...]  # kinematic parameters held at nominal by the analysis before the fit
    held_implausible: tuple[HeldParameter, ...]  # held at nominal after a fit put them beyond trust
    uncertain: tuple[str, ...]  # estimated, still beyond the bounds, and nothing left to hold for them
    correlated: tuple[CorrelatedGroup, ...]  # estimates the data sees mostly in combination
    weakly_identifiable: tuple[str, ...]  # estimated, below the noise on their own
    fixed: tuple[str, ...]  # parameters held at nominal by request
    lam: float
    cv_curve: tuple[tuple[float, float], ...]  # (lambda, held-out mean error mm)
    residuals_mm: np.ndarray  # (N, 3) on the calibration data, predicted - measured
    residuals_nominal_mm: np.ndarray  # (N, 3) of the before model
    noise_mm: float  # residual standard deviation per coordinate
    first_pass_noise_mm: float  # the same from the first fit, which judged the directions against it
    structural_rank: int  # geometric directions the poses separate at all
    noise_rank: int  # of those, directions above the noise
    condition: float
    seconds: float

    @property
    def held_at_nominal(self) -> tuple[str, ...]:
        """Every geometric parameter reported at its nominal value, in parameter order."""
        names = set(self.unidentifiable) | set(self.fixed) | {h.name for h in self.held_implausible}
        return tuple(n for n in self.layout.model.param_names if n in names)

    def predict(self, obs: Observations) -> np.ndarray:
        return predict(self.layout, self.x, obs)

    def errors(self, obs: Observations, nominal: bool = False) -> np.ndarray:
        x = self.x_nominal if nominal else self.x
        return np.linalg.norm(predict(self.layout, x, obs) - obs.xyz_mm, axis=1)


class IdentificationError(ValueError):
    """Data no identification can use, or a fit that shows the data are wrong; the message
    says what to check."""


MIN_SPREAD_MM = 1.0  # measured positions spanning less than this carry no geometry
MAX_FIT_MM = 50.0  # a calibrated model leaving a larger mean error means the data are wrong, not the arm


def check_data(layout: Layout, obs: Observations) -> None:
    """Refuse data that cannot determine a calibration, before any fitting."""
    spread = float(np.ptp(obs.xyz_mm, axis=0).max()) if len(obs) else 0.0
    if spread < MIN_SPREAD_MM:
        raise IdentificationError(f"the measured positions span only {spread:.3g} mm: degenerate data "
                                  f"(at least {MIN_SPREAD_MM:g} mm of spread is needed; is the instrument "
                                  "reading a fixed or empty value?)")
    n_unknown = 6 + 3 * len(layout.target_names)
    if 3 * len(obs) <= n_unknown:
        per_target = np.bincount(obs.target, minlength=len(layout.target_names))
        raise IdentificationError(
            f"{len(obs)} rows measure {len(layout.target_names)} targets: the base and target offsets alone are "
            f"{n_unknown} unknowns against {3 * len(obs)} measured coordinates (fewest rows on one target: "
            f"{per_target.min()}); measure each target at several poses")


def check_fit(errors_mm: np.ndarray) -> None:
    """Refuse a fit so poor that the data, not the arm, must be wrong."""
    mean = float(np.mean(errors_mm))
    if not np.isfinite(mean) or mean > MAX_FIT_MM:
        raise IdentificationError(
            f"the calibrated model still misses the measurements by {mean:.4g} mm on average: something is "
            "wrong with the data, not the arm (joint values in the wrong unit, joints in the wrong order, "
            "another robot's file, positions in m instead of mm?)")


def identify(model: KinematicModel, obs: Observations, options: IdentifyOptions = IdentifyOptions(),
             x_start: np.ndarray | None = None, progress=None) -> Identification:
    """Identify geometric parameters, base and target offsets from measured positions."""
    return identify_variants(model, obs, (options,), x_start, progress)[0]


SHARED = ("loss", "fixed", "prior_mm")  # options the first stage depends on


def identify_variants(model: KinematicModel, obs: Observations, variants, x_start: np.ndarray | None = None,
                      progress=None) -> list[Identification]:
    """``identify`` under several options that differ only in how the final fit is regularised
    and trusted: the nominal fit, the identifiability analysis and the first fit, which do not
    depend on those, are made once. Cross-validating variants must share folds and seed."""
    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    variants = tuple(variants)
    if any(getattr(v, k) != getattr(variants[0], k) for v in variants for k in SHARED):
        raise ValueError(f"identify_variants: the options must agree in {', '.join(SHARED)}")
    cv = {(v.folds, v.seed) for v in variants if v.regularize == "cv"}
    if len(cv) > 1:
        raise ValueError("identify_variants: cross-validating variants must share folds and seed")
    layout = Layout(model, obs.target_names)
    unknown = sorted(set(variants[0].fixed) - set(model.param_names))
    if unknown:
        raise ValueError(f"cannot fix unknown parameter(s) {', '.join(unknown)}; "
                         f"the model's parameters are {', '.join(model.param_names)}")
    check_data(layout, obs)
    start = _first_stage(layout, obs, variants[0], x_start, next(iter(cv), None), say)
    return [_final_stage(start, obs, v, say, t0) for v in variants]


@dataclass(frozen=True)
class _Start:
    """What every variant of an identification shares: the nominal fit, the analysis, the first fit."""

    layout: Layout
    before: Fit
    scale: np.ndarray
    candidates: np.ndarray
    structural: identifiability.Identifiability
    noisy: identifiability.Identifiability
    first: Fit
    noise: float
    factors: crossval.FoldFactors  # scaled Jacobian and residuals at the first fit, per fold
    r1: np.ndarray  # R factor of the scaled Jacobian at the first fit
    cache: dict  # Gram matrices of [J | r] at points fits start from


def _first_stage(layout, obs, options, x_start, cv, say) -> _Start:
    model = layout.model
    if x_start is None:
        x_start = initial_base_and_targets(layout, obs)
    nuisance = np.zeros(layout.size, bool)
    nuisance[layout.n_kin:] = True
    loss = options.loss
    # before: nominal kinematics, only base and targets estimated
    before = fit(layout, obs, x_start, nuisance, loss=loss, f_scale=1.0 if loss == "linear" else
                 f_scale_of(predict(layout, x_start, obs) - obs.xyz_mm))
    x0 = before.x
    scale = scales(layout, x0, obs)
    say(f"nominal model: mean error {before.errors.mean():.3f} mm over {len(obs)} measurements")

    candidates = np.zeros(layout.size, bool)
    candidates[: layout.n_kin] = True
    for name in options.fixed:
        candidates[model.index(name)] = False

    n_rows = 3 * len(obs)  # the scaled Jacobian's rows; its R factor stands in for it
    r0, gram0 = at_start(layout, x0, obs, scale)
    cache = {x0.tobytes(): gram0}
    structural = identifiability.analyse(r0, nuisance, candidates, n_rows=n_rows)
    # first pass over every structurally identifiable parameter: a noise estimate
    first = fit(layout, obs, x0, structural.keep, scale=scale, loss=loss, f_scale=f_scale_of(before.residuals_mm),
                cache=cache)
    check_fit(first.errors)
    dof = max(3 * len(obs) - int(structural.keep.sum()), 1)
    resid = first.residuals_mm.ravel()
    noise = float(np.sqrt(resid @ resid / dof)) if loss == "linear" else 1.4826 * float(
        np.median(np.abs(resid)))
    # the scaled Jacobian at the first fit, as R factors per cross-validation fold
    folds = crossval.fold_ids(obs.q, cv[0], cv[1]) if cv else np.zeros(len(obs), int)
    factors = crossval.FoldFactors(folds, layout.size)
    for rows, p, j in jacobian_chunks(layout, first.x, obs):
        factors.add(rows, j * scale, first.residuals_mm[rows])
    r1 = factors.r_all()[: layout.size, : layout.size]
    noisy = identifiability.analyse(r1, nuisance, candidates, noise_mm=noise, prior_mm=options.prior_mm,
                                    n_rows=n_rows)
    say(f"identifiable: {structural.rank} of {int(candidates.sum())} geometric parameters "
        f"structurally, {noisy.rank} above the noise ({noise * 1000:.1f} um)")
    return _Start(layout, before, scale, candidates, structural, noisy, first, noise, factors, r1, cache)


def _final_stage(start: _Start, obs, options, say, t0) -> Identification:
    layout, before, scale, first, noisy = start.layout, start.before, start.scale, start.first, start.noisy
    model, x0, loss = layout.model, start.before.x, options.loss
    f_scale = max(2.5 * start.noise, 1e-6)
    cv_curve: list[tuple[float, float]] = []
    lam = 0.0
    if options.regularize == "none":
        free = noisy.keep
    else:
        free = start.structural.keep
        lam, cv_curve = _choose_lambda(layout, obs, first, start.factors, free, scale, options, say)
    unident = tuple(n for i, n in enumerate(model.param_names) if start.candidates[i] and not free[i])

    def refit(mask: np.ndarray) -> Fit:
        return fit(layout, obs, x0, mask, lam=lam, scale=scale, loss=loss, f_scale=f_scale, cache=start.cache)

    final = refit(free)
    trust = _hold_untrustworthy(layout, obs, before, final, free, lam, scale, options, refit, say)
    final, free = trust.fit, trust.free
    std = np.zeros(layout.size)
    std[free] = np.sqrt(np.clip(np.diag(trust.cov), 0, None))
    cov = np.zeros((layout.size, layout.size))
    cov[np.ix_(free, free)] = trust.cov
    # estimated, but only as well as the prior allows: below the noise on their own
    weak = tuple(n for i, n in enumerate(model.param_names) if free[i] and not noisy.keep[i])
    sv = np.linalg.svd(start.r1[:, free], compute_uv=False)
    message = final.message.rstrip(".")
    if trust.held:
        message += ("; held at nominal after the fit because the data cannot pin them down: "
                    + ", ".join(h.name for h in trust.held))
    if trust.uncertain:
        message += "; beyond the trust bounds with nothing left to hold: " + ", ".join(trust.uncertain)
    return Identification(
        layout=layout, x=final.x, x_nominal=x0, free=free, std=std, unidentifiable=unident,
        held_implausible=trust.held, uncertain=trust.uncertain,
        correlated=_correlated_groups(layout, obs, final.x, x0, free, trust.cov),
        weakly_identifiable=weak, fixed=tuple(options.fixed), lam=float(lam), cv_curve=tuple(cv_curve),
        residuals_mm=final.residuals_mm, residuals_nominal_mm=before.residuals_mm, noise_mm=trust.noise_mm,
        first_pass_noise_mm=start.noise, structural_rank=start.structural.rank, noise_rank=noisy.rank,
        condition=float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf"),
        status=final.status, message=message, success=final.success, nfev=final.nfev, covariance=cov,
        seconds=time.perf_counter() - t0,
    )


@dataclass(frozen=True)
class _Trusted:
    fit: Fit
    free: np.ndarray
    cov: np.ndarray  # over the free entries of x
    noise_mm: float
    held: tuple[HeldParameter, ...]
    uncertain: tuple[str, ...]


def _hold_untrustworthy(layout, obs, before: Fit, final: Fit, free, lam, scale, options, refit,
                        say) -> _Trusted:
    """Hold at nominal, one at a time, the estimates a person could not trust; refit after each.

    A kinematic parameter or target offset fails when its standard deviation exceeds the
    bound for its kind or its value lies further from nominal than is plausible (target
    offsets, which have no nominal, are measured from the nominal model's fit of them).
    The estimate furthest past its bound is dealt with first: the kinematic parameter with
    the largest share in the direction the data hardly sees (``identifiability.to_hold``) is
    held and the fit repeated with the same prior weight, until every estimate passes.
    A direction the data hardly sees is one whose move changes the predictions little at
    poses like these, so holding it changes the held-out error little (and drops the noise
    it carried), while the table then says only what the data supports.
    Target offsets are never held (every calibration needs them); one still failing when
    no kinematic parameter is left to hold for it is reported as uncertain.
    """
    free = free.copy()
    ref = before.x  # nominal kinematics; base and targets as the nominal model fits them
    # the plausible distance is widened to what the nominal model's own error allows
    max_std, plausible = identifiability.trust_bounds(
        layout.is_angle, scale, float(np.percentile(before.errors, 95)), options.max_std_mm,
        np.deg2rad(options.max_std_deg), options.plausible_mm, np.deg2rad(options.plausible_deg))
    checked = np.ones(layout.size, bool)
    checked[layout.base] = False
    held: list[HeldParameter] = []
    uncertain: list[str] = []
    while True:
        cov, noise = covariance(layout, obs, final.x, free, lam, scale)
        idx = np.flatnonzero(free)
        std = np.zeros(layout.size)
        std[idx] = np.sqrt(np.clip(np.diag(cov), 0, None))
        failing = identifiability.failures(layout.names, layout.is_angle, free & checked, final.x, ref, std,
                                           max_std, plausible, set(uncertain))
        if not failing:
            return _Trusted(final, free, cov, noise, tuple(held), tuple(uncertain))
        worst = max(failing, key=lambda f: f.ratio)
        holdable = idx < layout.n_kin
        f = int(np.searchsorted(idx, worst.index))
        pick = identifiability.to_hold(cov / np.outer(scale[idx], scale[idx]), f, holdable, worst.spread)
        if pick is None:
            uncertain.append(layout.names[worst.index])
            continue
        j = int(idx[pick])
        corr = identifiability.correlation(cov)[pick]
        partners = tuple(layout.names[k] for n, k in enumerate(idx)
                         if n != pick and abs(corr[n]) > identifiability.CORRELATED_R)
        reason = worst.reason if j == worst.index else f"moved with {layout.names[worst.index]}: {worst.reason}"
        free[j] = False
        refitted = refit(free)
        held.append(HeldParameter(
            name=layout.names[j], reason=reason, value=float(final.x[j]), std=float(std[j]),
            nominal=float(ref[j]), is_angle=bool(layout.is_angle[j]), partners=partners,
            rms_rise_mm=refitted.rms_mm - final.rms_mm))
        say(f"held {layout.names[j]} at nominal (fit gave {_human(final.x[j], layout.is_angle[j])} "
            f"+- {_human(std[j], layout.is_angle[j])}): {reason}")
        final = refitted


def _correlated_groups(layout, obs, x, ref, free, cov) -> tuple[CorrelatedGroup, ...]:
    """Estimates with |r| > CORRELATED_R, each group with what its joint move off nominal does
    at the targets (rms over the calibration poses)."""
    p = predict(layout, x, obs)

    def effect_mm(members) -> float:
        moved = x.copy()
        moved[members] = ref[members]
        return float(np.sqrt(np.mean(np.sum((p - predict(layout, moved, obs)) ** 2, axis=1))))

    base = np.zeros(layout.size, bool)
    base[layout.base] = True
    return identifiability.correlated_groups(layout.names, np.flatnonzero(free), cov, base, effect_mm)


def _choose_lambda(layout, obs, first: Fit, factors: "crossval.FoldFactors", free, scale, options, say):
    """Grouped k-fold CV over the lambda grid; returns (lambda, curve).

    Every fold and lambda is solved on the model linearised at the unregularised
    fit over the same parameters (``first``): one regularised Gauss-Newton step
    from it on the fold's training rows. The parameter changes involved are far
    inside the range where the kinematics is linear, so this is each fold's own
    solution to second order, and the whole grid costs a few small solves per
    fold instead of one nonlinear fit per fold and lambda. factors: the scaled
    Jacobian and residuals at ``first``, as R factors per fold.
    """
    grid = sorted(set([0.0, *options.lambdas]))
    idx = np.flatnonzero(free)
    # the prior acts on kinematic parameters only, in scaled units (mm at the target)
    prior = (idx < layout.n_kin).astype(float)
    dev = prior * (first.x[idx] - layout.initial()[idx]) / scale[idx]
    steps = factors.steps(idx, prior, dev, grid)
    columns = ((rows, j * scale) for rows, _, j in jacobian_chunks(layout, first.x, obs))
    errs = crossval.heldout_errors(columns, first.residuals_mm, factors, steps)
    curve = [(float(lam), float(e)) for lam, e in zip(grid, errs.mean(axis=1))]
    best = min(curve, key=lambda c: c[1])
    say(f"cross-validation: lambda {best[0]:.3g}, held-out mean {best[1]:.3f} mm")
    return best[0], curve


__all__ = ["DEFAULT_LAMBDAS", "LOSSES", "REGULARIZE", "Fit", "Identification", "IdentificationError",
           "IdentifyOptions", "check_data", "check_fit", "fit", "identify", "identify_variants",
           "initial_base_and_targets", "register", "scales"]
