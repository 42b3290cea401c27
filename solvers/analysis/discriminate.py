"""The experiment that tells tied explanations apart: model-discrimination design.

When several causes explain the data about equally (``ties``), only new measurements
can decide. Each explanation, fitted to the data (geometry plus its term, linearised
at the geometric fit as the analysis scores it), predicts every configuration the
robot can take. Suppose one explanation is true: the other, refitted to the data and
to what the true one predicts at new poses, misses them by some amount; the poses to
measure are those that make this refitted miss largest against the noise, for every
ordered pair at once since the truth is unknown (T-optimal design, Atkinson and
Fedorov 1975, maximin over the pairs, chosen greedily).

Adding rows X_c with misfit e_c to a least-squares fit with normal matrix M raises its
residual sum of squares by e_c^T (I + X_c M^-1 X_c^T)^-1 e_c, so every candidate's gain
comes from the current fit alone and the greedy pass costs one small solve per pick.

How many poses suffice: the summed squared difference of the two predictions,
refitted, over the noise variance (lambda) separates the two by sqrt(lambda) noise
standard deviations; at sqrt(lambda) >= 2 * 2.33 a decision at the midpoint errs with
probability below 1% (``DECIDE_LAMBDA``). The analysis itself names a cause only when
its held-out mean error beats the other's by ``MIN_MARGIN``, so the count also asks
for the wrong explanation's expected held-out mean over all data to exceed the true
one's by MARGIN_SAFETY times that margin; the true one's held-out error at a new pose
grows by its own prediction variance there (an explanation with many loosely
determined parameters, such as compliance from lumped mass moments, needs more poses).
A payload the cell can mount (``payload_kg``) doubles the candidates: each configuration
with the data's payload and with that one. Compliance predicts what a payload does only
when the robot file gives every link mass (without them its lumped mass moments say
nothing of a new mass); otherwise the offer is declined and the design says why.
"""
from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import numpy as np

from cellcal.solvers.analysis.analyze import Finding
from cellcal.solvers.analysis.naming import MIN_MARGIN
from cellcal.solvers.analysis.linearised_scorer import term_columns
from cellcal.solvers.analysis.effects import CAUSES, Context, JointBasis
from cellcal.solvers.analysis.effects import periodic_spline
from cellcal.solvers.analysis.effects.cyclic_joint_error import CyclicJointError, harmonics
from cellcal.solvers.identification.measurement_model import Observations, jacobian_chunks
from cellcal.solvers.identification.pose_design import clear_of_mount
from cellcal.solvers.analysis.ties import DECIDE_LAMBDA, MEAN_PER_SIGMA  # predictions 4.65 sigma apart: a midpoint decision errs < 1%

MARGIN_SAFETY = 1.5
N_CANDIDATES = 2000  # random configurations within the joint limits the design chooses from
LIMIT_MARGIN_RAD = np.deg2rad(2.0)  # keep clear of the joint limits
DEFAULT_SPAN_RAD = np.deg2rad(170.0)  # a robot file without limits


class ExperimentError(ValueError):
    """No experiment can be designed for this finding (nothing tied, or a tie no pose decides)."""


@dataclass(frozen=True)
class Experiment:
    q_rad: np.ndarray  # (n, nj) configurations to measure, most telling first
    target_names: tuple[str, ...]  # measure every one of them at each configuration
    models: tuple[str, ...]  # the tied explanations the poses are to tell apart
    sigma_mm: float  # noise per coordinate assumed (from the best held-out error)
    lambda_cum: np.ndarray  # (n,) after k+1 poses: min over pairs of the refitted miss^2 / sigma^2
    margin_cum: np.ndarray  # (n,) after k+1 poses: min over pairs of the wrong model's expected excess
    #                         held-out mean over all rows, as a fraction of the right one's
    miss_mm: np.ndarray  # (n,) per pose, rms over targets: the refitted miss of the closest pair
    needed: int | None  # poses expected to suffice for a decision; None: no number of such poses will
    payload_kg: np.ndarray | None = None  # (n,) payload to mount for each pose, when a payload change was offered
    note: str = ""  # why an offered payload change was not considered
    payload_offered_kg: float | None = None

    def summary(self) -> str:
        n = len(self.q_rad)
        pairs = " and ".join(self.models)
        head = (f"{n} poses to tell {pairs} apart: refitted to the other's predictions, one misses "
                f"them by {np.sqrt(np.mean(self.miss_mm**2)):.3f} mm rms (up to {self.miss_mm.max():.3f} mm; "
                f"noise {self.sigma_mm:.3f} mm per coordinate), {np.sqrt(self.lambda_cum[-1]):.1f} sigma "
                f"apart over all {n}")
        if self.payload_kg is not None:
            with_it = int(np.sum(self.payload_kg == self.payload_offered_kg))
            head += f"; {with_it} of them with the {self.payload_offered_kg:g} kg payload"
        if self.note:
            head += f" ({self.note})"
        if self.needed is None:
            return head + "; no number of such poses is expected to decide (the differences stay below the noise)"
        if self.needed <= n:
            return head + f"; the first {self.needed} should suffice for a decision"
        return head + f"; {n} are not expected to suffice, about {self.needed} such poses should"


def design(finding: Finding, ctx: Context, n: int, rng: np.random.Generator,
           n_candidates: int = N_CANDIDATES, payload_kg: float | None = None) -> Experiment:
    """n configurations within the joint limits that best tell apart the finding's tied explanations.

    payload_kg: a payload the cell can mount; every candidate configuration is then offered both
    with the data's payload and with this one, and the design takes whichever separates better.
    Only explanations that predict a payload's effect (compliance with every link mass in the
    robot file) can use it; otherwise the design says so and keeps the data's payload."""
    tied = finding.indistinguishable
    scorer = finding.scorer
    if len(tied) < 2 or scorer is None:
        raise ExperimentError("nothing to tell apart: the analysis found no explanations these data cannot separate")
    q_cand = _candidates(scorer.model, n_candidates, rng)
    usual_kg = 0.0 if ctx.payload_kg is None else float(ctx.payload_kg[-1])
    note = ""
    if payload_kg is not None:
        try:
            return _design(finding, ctx, n, np.tile(q_cand, (2, 1)),
                           np.repeat([usual_kg, payload_kg], len(q_cand)), payload_kg)
        except ExperimentError as exc:
            note = f"payload change not considered: {exc}"
    return _design(finding, ctx, n, q_cand, None, None, note)


def _design(finding: Finding, ctx: Context, n: int, q_cand: np.ndarray, pay_cand: np.ndarray | None,
            offered_kg: float | None, note: str = "") -> Experiment:
    """The greedy T-optimal choice among these candidates (each with its payload, or the data's)."""
    tied, scorer = finding.indistinguishable, finding.scorer
    model, fit, obs = scorer.model, scorer.geometric_fit, scorer.obs
    n_old, n_targets = len(obs), len(obs.target_names)
    obs_all = Observations(np.concatenate([obs.q, np.repeat(q_cand, n_targets, axis=0)]),
                           np.zeros((n_old + len(q_cand) * n_targets, 3)),
                           np.concatenate([obs.target, np.tile(np.arange(n_targets), len(q_cand))]),
                           obs.target_names)
    ctx_all = _extended(ctx, len(obs_all) - n_old, None if pay_cand is None else np.repeat(pay_cand, n_targets))
    terms = [_term_at(model, fit, obs_all, ctx_all, t.scored.terms[0]) for t in tied]
    estimated = [scorer.term_estimated(t.scored.terms[0]) for t in tied]
    x = _model_columns(model, fit, obs_all, terms, estimated)  # per model (rows, 3, p)
    old = slice(0, n_old)
    measured = -scorer.baseline_residuals_mm  # measured - predicted at the geometric fit
    mean = []  # each model's fitted prediction, relative to the geometric fit, at every row
    for xi in x:
        flat = xi[old].reshape(3 * n_old, -1)
        delta = np.linalg.lstsq(flat, measured.ravel(), rcond=None)[0]
        mean.append(xi @ delta)
    noise_mean_mm = min(t.scored.heldout_mean_mm for t in tied)  # the best explanation leaves about noise
    sigma = noise_mean_mm / MEAN_PER_SIGMA
    cand = lambda a: a[n_old:].reshape(len(q_cand), n_targets * 3, *a.shape[2:])  # noqa: E731 per pose
    pairs = [_Pair(i, j, x[j][old], mean[i][old], cand(x[j]), cand(mean[i]))
             for i, j in itertools.permutations(range(len(tied)), 2)]
    chosen, lambda_cum, margin_cum = [], [], []
    free = np.ones(len(q_cand), bool)
    for _ in range(min(n, len(q_cand))):
        gains, leverage = {}, {}
        for p in pairs:
            gains[p], leverage[p.fitted] = p.gains()
        total = np.stack([p.added + gains[p] for p in pairs])
        best = int(np.argmax(np.where(free, np.min(total, axis=0), -np.inf)))
        free[best] = False
        chosen.append(best)
        for p in pairs:
            p.add(best, gains[p][best], sigma**2 * leverage[p.true][best])
        lambda_cum.append(min(p.added for p in pairs) / sigma**2)
        margin_cum.append(min(p.excess_mm(noise_mean_mm, sigma) for p in pairs)
                          / (noise_mean_mm * (n_old + len(chosen) * n_targets)))
    lambda_cum, margin_cum = np.array(lambda_cum), np.array(margin_cum)
    closest = min(pairs, key=lambda p: p.added)
    return Experiment(q_cand[chosen], obs.target_names, tuple(t.label for t in tied), float(sigma), lambda_cum,
                  margin_cum, closest.miss_mm(), _needed(lambda_cum, margin_cum, n_old, n_targets),
                  None if pay_cand is None else pay_cand[chosen], note, offered_kg)


class _Pair:
    """One explanation (`true`, its predictions `mean`) taken as the truth, another (`fitted`, its
    columns `x`) refitted to it."""

    def __init__(self, true: int, fitted: int, x_old, mean_old, x_cand, mean_cand):
        self.true, self.fitted = true, fitted
        flat = x_old.reshape(-1, x_old.shape[-1])
        self.scale = np.linalg.norm(flat, axis=0)
        self.scale[self.scale == 0] = 1.0
        flat = flat / self.scale
        self.x_cand, self.mean_cand = x_cand / self.scale, mean_cand
        self.normal = flat.T @ flat + 1e-9 * np.eye(flat.shape[1])
        self.rhs = flat.T @ mean_old.ravel()
        self.beta = np.linalg.solve(self.normal, self.rhs)
        self.added = 0.0  # residual sum of squares the chosen poses added, mm^2
        self.chosen: list[int] = []
        self.true_variance: list[float] = []  # the true model's prediction variance at each chosen pose, mm^2

    def gains(self) -> tuple[np.ndarray, np.ndarray]:
        """Rise of the residual sum of squares if each candidate pose were added, mm^2; and the
        fitted model's leverage there (its prediction variance over the noise variance, summed
        over the pose's rows): what measuring a pose adds to its held-out error beyond noise."""
        e = self.mean_cand - self.x_cand @ self.beta  # (candidates, rows)
        c, rows, p = self.x_cand.shape
        m_inv_xt = np.linalg.solve(self.normal, self.x_cand.reshape(c * rows, p).T)  # (p, c * rows)
        s = np.eye(rows) + self.x_cand @ m_inv_xt.T.reshape(c, rows, p).transpose(0, 2, 1)
        gains = np.einsum("cr,cr->c", e, np.linalg.solve(s, e[:, :, None])[:, :, 0])
        return gains, np.trace(s, axis1=1, axis2=2) - rows

    def add(self, c: int, gain_mm2: float, true_variance_mm2: float) -> None:
        """Measure candidate c: its gain and the true model's prediction variance there as computed."""
        self.added += float(gain_mm2)
        self.true_variance.append(true_variance_mm2)
        xc = self.x_cand[c]
        self.normal = self.normal + xc.T @ xc
        self.rhs = self.rhs + xc.T @ self.mean_cand[c]
        self.beta = np.linalg.solve(self.normal, self.rhs)
        self.chosen.append(c)

    def _misses(self) -> np.ndarray:
        """(chosen, targets) length of the refitted model's miss at each chosen pose and target, mm."""
        e = self.mean_cand[self.chosen] - self.x_cand[self.chosen] @ self.beta
        return np.linalg.norm(e.reshape(len(self.chosen), -1, 3), axis=2)

    def excess_mm(self, noise_mean_mm: float, sigma_mm: float) -> float:
        """Expected rise of the refitted model's summed held-out error lengths at the chosen poses
        over the true model's, mm (the true one's rises by its prediction variance there)."""
        misses = self._misses()
        wrong = np.sum(np.sqrt(misses**2 + noise_mean_mm**2) - noise_mean_mm)
        per_row = np.repeat(np.array(self.true_variance) / misses.shape[1], misses.shape[1])
        right = np.sum(noise_mean_mm * (np.sqrt(1.0 + per_row / (3.0 * sigma_mm**2)) - 1.0))
        return float(wrong - right)

    def miss_mm(self) -> np.ndarray:
        """(chosen,) rms over targets of the refitted model's miss at each chosen pose, mm."""
        return np.sqrt(np.mean(self._misses() ** 2, axis=1))


def _needed(lambda_cum, margin_cum, n_old: int, n_targets: int) -> int | None:
    """Poses for a decision: the statistical bound and the analysis' own margin both met."""
    target = MARGIN_SAFETY * MIN_MARGIN
    for k in range(len(lambda_cum)):
        if lambda_cum[k] >= DECIDE_LAMBDA and margin_cum[k] >= target:
            return k + 1
    n = len(lambda_cum)
    if lambda_cum[-1] <= 0 or margin_cum[-1] <= 0:
        return None
    # beyond n, poses like these: lambda grows by its mean per pose, and the wrong model's summed excess
    # by a per pose (in noise means), so that the margin over all rows is k a / (n_old + k T)
    per_pose = margin_cum[-1] * (n_old + n * n_targets) / n
    if per_pose <= target * n_targets:
        return None
    by_margin = target * n_old / (per_pose - target * n_targets)
    by_lambda = DECIDE_LAMBDA * n / lambda_cum[-1]
    return int(np.ceil(max(by_margin, by_lambda, n + 1)))


def _candidates(model, n: int, rng: np.random.Generator) -> np.ndarray:
    """Random configurations within the robot file's joint limits (a margin inside them) that keep the
    arm on its side of the mounting plane (``pose_design.clear_of_mount``)."""
    if model.joint_limits is None:
        lim = np.tile([-DEFAULT_SPAN_RAD, DEFAULT_SPAN_RAD], (model.n_joints, 1))
    else:
        lim = np.asarray(model.joint_limits, dtype=float)
    lo, hi = lim[:, 0] + LIMIT_MARGIN_RAD, lim[:, 1] - LIMIT_MARGIN_RAD
    out, kept = [], 0
    for _ in range(20):
        q = rng.uniform(lo, np.maximum(hi, lo), size=(n, model.n_joints))
        q = q[clear_of_mount(model, q)]
        out.append(q)
        kept += len(q)
        if kept >= n:
            break
    if not kept:
        raise ExperimentError(f"{model.name}: no configuration within the joint limits keeps the arm above its "
                          f"mounting plane")
    return np.concatenate(out)[:n]


def _extended(ctx: Context, n_new: int, payload_kg: np.ndarray | None) -> Context:
    """The data's context continued over new rows: approach direction unknown, no time passing,
    the last temperature, standing still; the last payload, or payload_kg (n_new,) when given."""
    last = lambda a: None if a is None else np.concatenate([a, np.repeat(a[-1:], n_new, axis=0)])  # noqa: E731
    payload = last(ctx.payload_kg)
    if payload_kg is not None:
        before = np.zeros(len(ctx.direction)) if ctx.payload_kg is None else ctx.payload_kg
        payload = np.concatenate([before, payload_kg])
    return Context(np.concatenate([ctx.direction, np.zeros((n_new, ctx.direction.shape[1]))]), last(ctx.t_s),
                   last(ctx.temp_c), payload,
                   None if ctx.dq_rad_s is None else np.concatenate([ctx.dq_rad_s,
                                                                     np.zeros((n_new, ctx.dq_rad_s.shape[1]))]))


def _term_at(model, fit, obs_all: Observations, ctx_all: Context, term):
    """The same candidate term evaluated on the data and the new rows together. A cyclic error is
    sin and cos of its orders (or periodic splines) in its joints' angles; any other term is built
    again by its cause (its basis depends on the configurations and the context alone) and found by
    place and names."""
    if term.cause == CyclicJointError.id:
        nj = model.n_joints

        def single(where):  # one place: a joint's spline, or one order
            j = where["joint"] - 1
            if "spline_knots" in where:
                return JointBasis.single(periodic_spline.basis(obs_all.q[:, j], where["spline_knots"]), j, nj)
            return JointBasis.single(harmonics(obs_all.q[:, j], [where["order"]]), j, nj)

        parts = term.extra.get("parts")
        basis = single(term.where) if not parts else JointBasis.side_by_side(
            [(single(p.where), p.size) for p in parts], len(obs_all), nj)
        return dataclasses.replace(term, joint_basis=basis)
    for t in CAUSES[term.cause].terms(model, fit.layout, fit.x, obs_all, ctx_all):
        if t.where == term.where and t.names == term.names:
            return t
    raise ExperimentError(f"{term.label()} cannot be evaluated at new poses (with a payload change: its model "
                      f"does not predict what a payload does without every link mass in the robot file)")


def _model_columns(model, fit, obs_all: Observations, terms, estimated) -> list[np.ndarray]:
    """Per explanation: d p / d (free geometry, estimated term parameters) at every row (rows, 3, p)."""
    out = [np.empty((len(obs_all), 3, int(fit.free.sum()) + len(e))) for e in estimated]
    structural: dict = {}
    for rows, _, jx, jq in jacobian_chunks(fit.layout, fit.x, obs_all, with_joints=True):
        geometry = jx[:, :, fit.free]
        for o, t, e in zip(out, terms, estimated):
            o[rows] = np.concatenate([geometry, term_columns(model, fit, obs_all, t, rows, jx, jq,
                                                             structural)[:, :, e]], axis=2)
    return out
