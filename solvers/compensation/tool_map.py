"""A program's tool points, as the controller knows them, in a calibrated model's end frame, and what
the calibration leaves unknown about them.

A calibration measures targets (an SMR, a probe ball) and identifies each one's offset in its own
end frame, which is a convention: the parameters of the last frames that no measured point can
separate from the target offsets (a turn of the end frame about a measured point moves nothing
that was measured) are held at their nominal values, and the offsets absorb what is left. So the
calibrated offset of a target drawn at (0, 0, 100) mm comes out at, say, (0.38, 0.07, 99.77): right
for that point, and not a statement about the flange.

A program names its tool as the controller knows it: a point in the flange frame of the drawing
(``set_tcp``, the controller's TCP). The model file records the drawn offset of each measured
target (``calibration.drawn_targets``: the TCP a program sets to use that target). A tool point
``p`` is mapped to the calibrated end frame through the nearest measured target ``i``:

    p_model = t_i + (p - d_i)

exact at the target itself; away from it, the calibration's unseen turn of the end frame makes an
error that grows with the lever arm ``|p - d_i|``. ``ToolMap.bound_mm`` states it per target and
configuration, at 95 %:

* the unseen directions: for each kinematic parameter the calibration held at its nominal value,
  the change of every parameter (geometry, instrument frame, target offsets) that leaves every
  measured target where it was (the parameter's column minus its least-squares projection on the
  estimated ones, over ``FRAME_SAMPLES`` configurations): how the true arm may differ from the
  calibrated one without any measurement showing it;
* their size: the spread of the estimated parameters around their nominal values (angles and
  lengths apart; the median distance over 0.6745, the standard deviation of a normal spread, which
  one poorly determined estimate does not inflate), the arm's own manufacturing spread, taken for
  the held ones as well; a spread estimated from m parameters is itself uncertain, so a direction
  counts Student's t quantile of m degrees of freedom over 1.96 times that spread (2.18 / 1.96 for
  12 estimated angles);
* the estimates' own uncertainty (what of it moves the measured targets rigidly is left out: the
  controller's base frame is fitted at them and takes it up): the calibration's covariance of what it estimated (the model
  file's ``calibration.covariance``), as directions of its eigenvectors scaled by the root of
  their eigenvalues. A parameter the data barely determine (a wrist offset nearly in line with the
  target) may be estimated tenths of a degree off and still put the measured target right: the
  covariance says how far off, and the lever arm what that does at another point;
* at a tool point and configuration, each direction moves the point by its position Jacobian times
  the direction; 1.96 times the root of the summed squares is at least the 95 % quantile of the
  distance for normal errors of any covariance shape (1.96 exactly when one direction dominates);
* the calibrated model's own error at the measured targets (``OWN_FACTOR`` times its held-out mean
  distance) is added in quadrature.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian

FRAME_SAMPLES = 256  # configurations the unseen directions are worked out over (a Halton sequence)
HELD_RAD, HELD_MM = 1e-9, 1e-9  # a parameter this close to its nominal value was held there, not estimated
Z95 = 1.96  # the 95 % factor for the distance a combination of normal errors moves a point (module docstring)
# 95 % of a three-dimensional normal error's distances lie within 1.75 times their mean (Maxwell); 2 rounds up
OWN_FACTOR = 2.0


@dataclass(frozen=True)
class ToolMap:
    """How the controller's tool points map into a calibrated model's end frame (module docstring)."""

    drawn: np.ndarray | None  # (T, 3) mm: each measured target as the controller knows it; None: not recorded
    offsets: np.ndarray  # (T, 3) mm: the calibrated offsets of the same targets
    layout: Layout  # the calibrated model's unknowns
    x: np.ndarray  # their calibrated values
    unseen: np.ndarray  # (K, layout.size): unseen and uncertain directions, each scaled to its expected size
    own_mm: float | None  # 95 % error of the calibrated model at its measured targets (None: not recorded)
    sd_deg: float | None  # the estimated angles' spread around nominal (what the held ones are taken to have)
    sd_mm: float | None  # and the lengths'

    def nearest(self, tool_mm) -> int:
        """The measured target a tool point (controller's flange frame) is mapped through."""
        reference = self.offsets if self.drawn is None else self.drawn
        return int(np.argmin(np.linalg.norm(reference - np.asarray(tool_mm, dtype=float), axis=1)))

    def to_model(self, tool_mm) -> np.ndarray:
        """(3,) mm: the tool point in the calibrated end frame. Without drawn targets the tool point is
        taken as given in that frame (the calibrated offsets are the controller's TCPs)."""
        tool = np.asarray(tool_mm, dtype=float)
        if self.drawn is None:
            return tool
        i = self.nearest(tool)
        return self.offsets[i] + (tool - self.drawn[i])

    def frame_points(self, tool_mm) -> tuple[np.ndarray, np.ndarray]:
        """(model point, controller point) mm: where the controller's base frame is fitted
        (``compensate.controller_frame``): the measured target nearest the tool, as calibrated and as
        the controller knows it; without drawn targets the tool point itself, in both."""
        if self.drawn is None:
            tool = np.asarray(tool_mm, dtype=float)
            return tool, tool
        i = self.nearest(tool_mm)
        return self.offsets[i], self.drawn[i]

    def bound_mm(self, q: np.ndarray, tool_mm) -> np.ndarray | None:
        """(N,) mm: the 95 % bound of where the tool point lands at joints q (N, nj), compensated with
        this model: the unseen directions' lever arm and the model's own error (module docstring).
        None when the spread of the parameters is unknown (no parameter was estimated)."""
        if self.sd_deg is None and self.sd_mm is None:
            return None
        q = np.atleast_2d(np.asarray(q, dtype=float))
        i = self.nearest(tool_mm)
        point = self.to_model(tool_mm)
        layout = Layout(self.layout.model, ("tool",))
        n_fixed = self.layout.n_kin + 6
        x = np.concatenate([self.x[:n_fixed], point])
        unseen = np.concatenate([self.unseen[:, :n_fixed], self.unseen[:, self.layout.target(i)]], axis=1)
        lever = np.empty(len(q))
        step = 4096  # rows per Jacobian: (rows, 3, size) floats, a few MB
        for start in range(0, len(q), step):
            rows = q[start:start + step]
            obs = Observations(rows, np.zeros((len(rows), 3)), np.zeros(len(rows), int), ("tool",))
            moved = np.einsum("nij,kj->nki", jacobian(layout, x, obs)[1], unseen)  # (n, K, 3) mm per direction
            lever[start:start + step] = Z95 * np.sqrt(np.einsum("nki,nki->n", moved, moved))
        own = 0.0 if self.own_mm is None else self.own_mm
        return np.sqrt(lever ** 2 + own ** 2)


def held_at_nominal(calibrated, source) -> np.ndarray:
    """(n_kin,) bool: the calibrated model's kinematic parameters held at their value in ``source`` (the
    nominal model it was calibrated from), not estimated; a parameter ``source`` lacks (a structural
    effect's) was estimated."""
    nominal = dict(zip(source.param_names, source.nominal))
    model = calibrated.model
    return np.array([name in nominal and abs(value - nominal[name]) <= (HELD_RAD if angle else HELD_MM)
                     for name, value, angle in zip(model.param_names, calibrated.k, model.param_is_angle)], dtype=bool)


def tool_map(calibrated, source, drawn=None, heldout_mean_mm=None, covariance=None,
             samples: int = FRAME_SAMPLES) -> ToolMap:
    """The ``ToolMap`` of a ``CalibratedModel``: ``source`` the nominal model it was calibrated from
    (what tells the held parameters from the estimated ones), ``drawn`` (T, 3) mm the measured targets
    as the controller knows them (None: not recorded), ``heldout_mean_mm`` the model's held-out mean
    error (None: not recorded), ``covariance`` (layout.size, layout.size) the estimates' covariance in
    the layout's units (None: not recorded)."""
    from scipy.special import stdtrit  # Student's t quantile (scipy.stats would cost 0.3 s of import)

    from cellcal.solvers.compensation.compensate import joint_sample

    layout, x = calibrated.layout, calibrated.x
    model = layout.model
    nominal = dict(zip(source.param_names, source.nominal))
    held = held_at_nominal(calibrated, source)
    deviation = np.array([value - nominal.get(name, value) for name, value in zip(model.param_names, calibrated.k)])
    estimated = ~held & np.array([name in nominal for name in model.param_names])

    def spread(kind):
        values = deviation[estimated & kind]
        return (float(np.median(np.abs(values)) / 0.6745), len(values)) if len(values) else (None, 0)

    (sd_rad, m_rad), (sd_mm, m_mm) = spread(model.param_is_angle), spread(~model.param_is_angle)

    def scale(sd_kind, m):  # the spread, widened for its own uncertainty (module docstring)
        return np.nan if sd_kind is None else sd_kind * stdtrit(m, 0.975) / Z95

    sd = np.where(model.param_is_angle, scale(sd_rad, m_rad), scale(sd_mm, m_mm))
    q = joint_sample(model, samples)
    n_t = len(calibrated.target_names)
    obs = Observations(np.repeat(q, n_t, axis=0), np.zeros((len(q) * n_t, 3)), np.tile(np.arange(n_t), len(q)),
                       calibrated.target_names)
    jac = jacobian(layout, x, obs)[1].reshape(-1, layout.size)
    free = np.ones(layout.size, bool)
    free[: layout.n_kin] = ~held
    unseen = []
    for k in np.flatnonzero(held & np.isfinite(sd)):
        fit = np.linalg.lstsq(jac[:, free], jac[:, k], rcond=None)[0]
        direction = np.zeros(layout.size)
        direction[k] = 1.0
        direction[free] = -fit
        unseen.append(sd[k] * direction)
    if covariance is not None:
        value, vector = np.linalg.eigh(0.5 * (covariance + covariance.T))
        keep = value > value.max(initial=0.0) * 1e-12  # the rest is rounding: directions nothing moves
        unseen += list((vector[:, keep] * np.sqrt(value[keep])).T)
    unseen = np.array(unseen).reshape(-1, layout.size)
    # what moves every measured target rigidly is absorbed by the controller's frame, fitted at them over the
    # same kind of spread (compensate.controller_frame): taken out of each direction, as an instrument frame change
    rigid = np.linalg.lstsq(jac[:, layout.base], jac @ unseen.T, rcond=None)[0]
    unseen[:, layout.base] -= rigid.T
    own = None if heldout_mean_mm is None else OWN_FACTOR * float(heldout_mean_mm)
    drawn = None if drawn is None else np.asarray(drawn, dtype=float).reshape(n_t, 3)
    return ToolMap(drawn, np.asarray(calibrated.offsets, dtype=float), layout, x, unseen, own,
                   None if sd_rad is None else float(np.rad2deg(sd_rad)), sd_mm)


def fit_covariance(layout: Layout, x: np.ndarray, obs: Observations, residuals_mm: np.ndarray,
                   free: np.ndarray) -> np.ndarray:
    """(layout.size, layout.size): the covariance of the ``free`` entries of x (0 elsewhere) of a fit with
    these training residuals (N, 3) mm: the inverse of the geometry's Gauss-Newton matrix over obs times
    the residual variance per coordinate (what a fit whose residuals include a fitted effect's leaves)."""
    idx = np.flatnonzero(free)
    jac = jacobian(layout, x, obs)[1].reshape(-1, layout.size)[:, idx]
    dof = max(residuals_mm.size - len(idx), 1)
    cov = np.zeros((layout.size, layout.size))
    cov[np.ix_(idx, idx)] = np.linalg.pinv(jac.T @ jac) * float(np.sum(np.square(residuals_mm))) / dof
    return cov
