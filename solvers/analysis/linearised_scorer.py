"""Held-out errors of geometry plus effect terms on the model linearised at the geometric
fit: how ``analyze`` scores every candidate explanation, and how the tie rule and the
discriminating design measure how far apart two explanations lie on the data."""
from __future__ import annotations

import numpy as np

from cellcal.solvers.estimation import crossval, identifiability
from cellcal.solvers.analysis.effects import Term
from cellcal.solvers.analysis.effects.base import part_penalty, penalised_parts
from cellcal.solvers.analysis.extended_model import embed, norm_scale, param_columns, stack_param_bases
from cellcal.solvers.identification.identify import Identification
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian_chunks
from cellcal.solvers.analysis.robust_scoring import LINEAR, RobustScoring

NESTED_RTOL = 0.02  # one term's columns lie in another's span to this relative residual (2%)
RIDGE = 1e-8  # on the normal matrix of unit-length columns, in the steps the search scores (``search_step``)
EMPTY_RTOL = 1e-12  # a column this much shorter (squared) than the longest has no rows in a training


class LinearisedScorer:
    """Held-out errors of geometry plus effect terms, one Gauss-Newton step from the geometric fit.

    A term's parameters enter only where this data can separate them from the
    geometry. The Jacobian columns of the geometry and of every term are computed a
    block of rows at a time and kept only as one R factor per fold (with the baseline
    residuals as last column): every candidate's identifiability analysis and fold
    steps come from these small factors, and the held-out errors of many candidates
    take one more pass over the rows together.
    """

    def __init__(self, model, geometric_fit: Identification, obs: Observations, folds: np.ndarray,
                 prior_mm: float, terms=(), robust: RobustScoring = LINEAR):
        self.model, self.geometric_fit, self.obs, self.folds, self.prior_mm = model, geometric_fit, obs, folds, prior_mm
        self.robust = robust
        self.baseline_residuals_mm = geometric_fit.residuals_mm
        # the geometry's columns: its free parameters; with point-form data each row's point besides, estimated
        # with the geometry in every fold and eliminated (crossval.PointFoldFactors)
        self._points = getattr(geometric_fit, "point_jacobian", None)  # point_analysis.PointGeometry
        self.n_geometry = int(geometric_fit.free.sum())
        # a term with extra["columns_of"] (a spline at another penalty weight) shares that term's columns
        self.terms = [t for t in terms if "columns_of" not in t.extra]
        self._at: dict[int, slice] = {}
        col = self.n_geometry
        for t in self.terms:
            self._at[id(t)] = slice(col, col + t.size)
            col += t.size
        for t in terms:
            if "columns_of" in t.extra:
                self._at[id(t)] = self._at[id(t.extra["columns_of"])]
        self._estimated: dict[bytes, np.ndarray] = {}
        self._penalised: dict = {}  # (terms' ids, cols) -> where their parts' penalties sit (``penalty``)
        self.n_columns = col
        self._structural: dict[int, np.ndarray] = {}  # columns of terms that change the rigid model, (N, 3, m)
        if self._points is None:
            self.factors = crossval.FoldFactors(folds, col)
            for rows, j in self._columns():
                self.factors.add(rows, *robust.weighted(rows, j, self.baseline_residuals_mm[rows]))
        else:
            self.factors = crossval.PointFoldFactors(folds, col, geometric_fit.point, geometric_fit.n_points)
            for add in (self.factors.add, self.factors.add_projected):  # the second pass: R of all rows
                for rows, j, pj in self._columns():
                    jw, rw = robust.weighted(rows, np.concatenate([j, pj], axis=2), self.baseline_residuals_mm[rows])
                    add(rows, jw[:, :, :col], rw, jw[:, :, col:])
        self.r = self.factors.r_all()[:col, :col]  # R factor of all columns, all rows (points projected out)
        # each column's size over the rows (with points: as the rows measure it, not projected)
        self._norms = np.linalg.norm(self.r, axis=0) if self._points is None else self.factors.column_norms()[:col]
        self.scale = norm_scale(self._norms, len(obs))

    def _columns(self):
        """(rows, [geometry | every term] columns (n, 3, n_columns)) over all rows in blocks; with point-form
        data (rows, columns, d residual / d the row's point (n, 3, 3))."""
        fit, obs = self.geometric_fit, self.obs
        for rows, _, jx, jq in jacobian_chunks(fit.layout, fit.x, obs, with_joints=True):
            out = np.empty((len(jx), 3, self.n_columns))
            out[:, :, : self.n_geometry] = jx[:, :, fit.free]
            for t in self.terms:
                out[:, :, self._at[id(t)]] = self._term_columns(t, rows, jx, jq)
            if self._points is None:
                yield rows, out
            else:  # what the rows measure (a contact: the distance along the ball's normal)
                yield rows, fit.project(rows, out), self._points(rows)

    def _heldout(self, steps: np.ndarray) -> np.ndarray:
        if self._points is None:
            return crossval.heldout_errors(self._columns(), self.baseline_residuals_mm, self.factors, steps)
        return self.factors.heldout_errors(self._columns(), self.baseline_residuals_mm, steps)

    def _term_columns(self, term: Term, rows, jacobian_x, jacobian_q) -> np.ndarray:
        """d p / d theta of a term at the geometric fit, for these rows (n, 3, m)."""
        return term_columns(self.model, self.geometric_fit, self.obs, term, rows, jacobian_x, jacobian_q,
                            self._structural)

    def term_estimated(self, term: Term) -> np.ndarray:
        """Indices, among the term's own parameters, of those these data separate from the geometry."""
        return np.flatnonzero(np.isin(self._term_cols(term), self.estimated((term,))[self.n_geometry:]))

    def _term_cols(self, term: Term) -> np.ndarray:
        """Columns of a term, or of the scored parts it was composed of."""
        return np.concatenate([np.arange(self.n_columns)[self._at[id(t)]]
                               for t in term.extra.get("parts", (term,))]).astype(int)

    def _cols(self, terms: tuple[Term, ...]) -> np.ndarray:
        return np.concatenate([np.arange(self.n_geometry)] + [self._term_cols(t) for t in terms]).astype(int)

    def estimated(self, terms: tuple[Term, ...]) -> np.ndarray:
        """Columns (into all columns) of geometry and of the terms' parameters this data separates from it
        (decided once for a set of columns: a spline's weights share theirs)."""
        cols = self._cols(terms)
        key = cols.tobytes()
        if key not in self._estimated:
            self._estimated[key] = self._separated(cols)
        return self._estimated[key]

    def _separated(self, cols: np.ndarray) -> np.ndarray:
        r = np.linalg.qr(self.r[:, cols], mode="r")  # R factor of these columns alone
        geometry = np.arange(len(cols)) < self.n_geometry
        keep = identifiability.analyse(r / self.scale[cols], geometry, ~geometry, noise_mm=None,
                                       prior_mm=self.prior_mm, with_condition=False, n_rows=3 * len(self.obs)).keep
        keep[geometry] = True
        return cols[keep]

    def heldout_errors_many(self, term_sets) -> np.ndarray:
        """(len(term_sets), N) held-out error of each measurement, for each set of terms with geometry."""
        return self._heldout(np.concatenate([self.factors.steps(self.estimated(tuple(ts))) for ts in term_sets]))

    def steps(self, terms: tuple[Term, ...]) -> np.ndarray:
        """(1, folds, p) each fold's step with geometry and these terms, for ``heldout_errors_of_steps``.
        Terms with a penalty of their own (``base.penalised_parts``) are stepped as the search scores them
        (``search_step``)."""
        cols = self.estimated(tuple(terms))
        if not penalised_parts(terms):
            return self.factors.steps(cols)
        out = np.zeros((1, len(self.factors.ids), self.factors.p))
        for k in range(len(self.factors.ids)):
            normal, grad = self.factors.training(k)
            normal = normal[np.ix_(cols, cols)]
            out[0, k, cols] = search_step(normal, grad[cols], self.penalty(terms, cols, np.diagonal(normal)))
        return out

    def penalty(self, terms, cols: np.ndarray, diagonal: np.ndarray) -> np.ndarray | None:
        """(..., len(cols), len(cols)) the penalties of these terms' parts on the columns cols
        (``base.part_penalty`` of the normal matrices' diagonals over cols, (..., len(cols))), or None when no
        part carries one."""
        parts = penalised_parts(terms)
        if not parts:
            return None
        key = (tuple(map(id, terms)), np.asarray(cols).tobytes())
        if key not in self._penalised:  # where each part's penalty sits among cols, found once
            placed = []
            for part, lam in parts:
                own = self._term_cols(part)
                at = np.flatnonzero(np.isin(cols, own))
                placed.append((part, lam, at, np.searchsorted(own, cols[at])))
            self._penalised[key] = placed
        placed = self._penalised[key]
        diagonal = np.asarray(diagonal, dtype=float)
        out = np.zeros(diagonal.shape + (len(cols),))
        for part, lam, at, kept in placed:
            out[..., at[:, None], at[None, :]] += part_penalty(part, lam, diagonal[..., at], kept)
        return out

    def heldout_errors_of_steps(self, steps: np.ndarray) -> np.ndarray:
        """(len(steps), N) held-out error of each measurement for each set of fold steps (folds, p)."""
        return self._heldout(steps)

    def mean_mm(self, errors: np.ndarray) -> np.ndarray:
        """Held-out score of errors along the last axis (``RobustScoring.mean_mm``)."""
        return self.robust.mean_mm(errors)

    def heldout_errors_mm(self, terms: tuple[Term, ...]) -> np.ndarray:
        """(N,) held-out error of each measurement with geometry and these terms."""
        return self.heldout_errors_many([terms])[0]

    def separation_mm2(self, fitted: Term, refitted: Term) -> float:
        """Residual sum of squares (mm^2) left on these data when geometry + `refitted` is fitted to
        what geometry + `fitted`, fitted to the data, predicts: how far apart the data put the two
        explanations (the T-criterion of the design already measured). Computed in the space of the
        R factor of [columns | residuals], which keeps every inner product of those vectors."""
        full = self.factors.r_all()
        fitted_cols, refitted_cols = full[:, self.estimated((fitted,))], full[:, self.estimated((refitted,))]
        predicted = fitted_cols @ np.linalg.lstsq(fitted_cols, full[:, self.n_columns], rcond=None)[0]
        miss = predicted - refitted_cols @ np.linalg.lstsq(refitted_cols, predicted, rcond=None)[0]
        return float(miss @ miss)

    def is_nested(self, inner: Term, outer: Term) -> bool:
        """Does geometry + outer span every column of inner? (Then outer explains nothing
        that inner cannot, wherever the two tie.)"""
        a = self.r[:, self._cols((outer,))]
        cols = self._term_cols(inner)
        b = self.r[:, cols]
        coef = np.linalg.lstsq(a, b, rcond=None)[0]
        # relative to inner's own size over the rows (with points: before they are projected out)
        size = np.linalg.norm(b) if self._points is None else np.sqrt(np.sum(self._norms[cols] ** 2))
        return bool(np.linalg.norm(a @ coef - b) <= NESTED_RTOL * size)


def unit_scales(d2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(scale, empty) of columns with squared lengths d2 (the Gram's diagonal, (..., n)): each column's
    length, and whether it is EMPTY_RTOL shorter (squared) than the longest of its training (no rows
    there: scale 1, left out of the solve)."""
    empty = d2 <= EMPTY_RTOL * d2.max(axis=-1, keepdims=True)
    return np.sqrt(np.where(empty, 1.0, d2)), empty


def search_step(normal: np.ndarray, grad: np.ndarray, penalty: np.ndarray | None = None) -> np.ndarray:
    """The step the search scores a choice by (``selection.Scores.sum_squares``), from one training's normal
    equations: columns scaled to unit length, a column without rows in this training left at 0, the
    vanishing RIDGE, and the terms' own penalties (penalty (n, n); None: none). A fold's choice is
    scored as it was chosen: a plain solve of the same equations steps wild along directions the training
    barely sees (a spline's knot interval that a fold's training holds a pose or two of), which the
    search never scored."""
    d, empty = unit_scales(np.diagonal(normal))
    a = normal / d[:, None] / d[None, :]
    a = np.where(empty[:, None] | empty[None, :], 0.0, a) + np.diag(RIDGE + empty * 1.0)
    if penalty is not None:
        a = a + penalty / d[:, None] / d[None, :]
    g = np.where(empty, 0.0, grad / d)
    return -crossval._solve(a, g) / d


def term_columns(model, fit: Identification, obs: Observations, term: Term, rows, jacobian_x, jacobian_q,
                 structural: dict) -> np.ndarray:
    """d p / d theta of a term at the fit, for these rows of obs (n, 3, m). A term that changes the
    rigid model has its columns computed once over all rows and kept in `structural`."""
    if term.model is not None:  # one new rigid parameter: its Jacobian column in the new layout
        if id(term) not in structural:
            layout = Layout(term.model, obs.target_names)
            x = embed(fit.x, fit.layout.n_kin, term.model.n_params - model.n_params)
            columns = np.empty((len(obs), 3, term.size))
            for block, _, j in jacobian_chunks(layout, x, obs):
                columns[block] = j[:, :, model.n_params: term.model.n_params]
            structural[id(term)] = columns
        return structural[id(term)][rows]
    columns = np.zeros((len(jacobian_x), 3, term.size))
    if term.joint_basis is not None:
        columns += term.joint_basis[rows].columns(jacobian_q)
    if term.cart_basis is not None:
        columns += term.cart_basis[rows]
    if term.param_basis:
        params, basis = stack_param_bases(term.param_basis)
        columns += param_columns(jacobian_x, (params, basis[rows]))
    return columns
