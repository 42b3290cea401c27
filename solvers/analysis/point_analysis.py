"""The discrepancy analysis of point-form data: sockets the tool sat in, balls it touched.

``analyze`` scores every candidate effect on the rigid model linearised at its geometric fit
(``LinearisedScorer``). For measured positions that fit is ``identify``'s; for point rows it is
the fixture calibration (``fixture_identify.identify_points``), and what point rows measure
differs in two ways, both carried by :class:`PointGeometry`:

- each point's position is an unknown of its own, estimated with the geometry in every fold
  (``point_columns``: d residual / d point = -I), so a held-out row is scored against its point
  as the fold's training rows place it. The rows of a point therefore need not share a fold.
- a contact measures one number, the distance from the ball's surface: its residual and every
  column of its row are projected on the ball's normal there (``projector``), so a held-out
  error is that distance and nothing along the surface counts.

The analysis sees the rows as positions in the base frame as the fitted kinematics place it:
``observations`` gives each socket row its fitted point, each contact row the point of the
ball's surface nearest its fitted tip (so predicted - measured is the row's residual). The
instrument frame is the identity and held (there is none); the fixture's distances, which
fix the arm's scale, are not rows of their own here: the parameters only they determine (the
scale, with the base frame's convention) are held at the fixture calibration's values, and
the analysis judges effects on everything else.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.estimation import identifiability
from cellcal.solvers.fixtures.fixture_identify import FixtureIdentification
from cellcal.solvers.fixtures.point_problem import PointData
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian_chunks


@dataclass(frozen=True)
class PointGeometry:
    """The geometric baseline of point-form data, in the shape ``analyze`` reads a geometric fit."""

    layout: Layout
    x: np.ndarray  # kinematics and target offsets of the fixture calibration, base frame the identity
    free: np.ndarray  # over x: the kinematic parameters estimated here, and the target offsets (base held)
    residuals_mm: np.ndarray  # (N, 3) predicted - measured, as ``observations`` gives the measured
    point: np.ndarray  # (N,) each row's point
    n_points: int
    normals: np.ndarray | None  # (N, 3) contacts: the ball's outward normal at each row; None: sockets
    fixture_fit: FixtureIdentification
    held_without_distances: tuple[str, ...]  # estimated by the fixture fit, held at its values here: the rows
    #                                        alone (the distances are no rows) do not determine them above the noise

    @property
    def n_point_columns(self) -> int:
        return 3 * self.n_points

    def point_columns(self, rows) -> np.ndarray:
        """d residual / d point positions of these rows, (n, 3, 3 n_points)."""
        idx = np.arange(len(self.point))[rows]
        out = np.zeros((len(idx), 3, self.n_point_columns))
        for c in range(3):
            out[np.arange(len(idx)), c, 3 * self.point[idx] + c] = -1.0
        return self.project(rows, out)

    def project(self, rows, columns: np.ndarray) -> np.ndarray:
        """Columns (n, 3, m) of these rows as the rows measure them: along the normal for contacts."""
        if self.normals is None:
            return columns
        n = self.normals[rows]
        return n[:, :, None] * np.einsum("ni,nim->nm", n, columns)[:, None, :]


def observations(fit: FixtureIdentification, data: PointData) -> Observations:
    """The point rows as positions in the base frame (see the module's text)."""
    u = fit.unknowns
    points = fit.z[u.points_slice].reshape(-1, 3)[data.point]
    if fit.options.stylus_radius_mm is None:
        return Observations(data.q, points, data.target, data.target_names)
    tip = _tips(fit, data)
    normal = _normals(tip, points)
    return Observations(data.q, points + fit.options.stylus_radius_mm * normal, data.target, data.target_names)


def _tips(fit: FixtureIdentification, data: PointData) -> np.ndarray:
    layout = Layout(fit.unknowns.model, data.target_names)
    x = _x(fit, layout)
    obs = Observations(data.q, np.zeros((len(data), 3)), data.target, data.target_names)
    out = np.empty((len(data), 3))
    for rows, p, _ in jacobian_chunks(layout, x, obs, kinematic=False):
        out[rows] = p
    return out


def _normals(tip: np.ndarray, centre: np.ndarray) -> np.ndarray:
    d = tip - centre
    return d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]


def _x(fit: FixtureIdentification, layout: Layout) -> np.ndarray:
    u = fit.unknowns
    x = layout.initial(base=np.zeros(6), offsets=np.stack([fit.z[u.target(i)] for i in range(u.n_targets)]))
    x[: u.n_kin] = fit.z[: u.n_kin]
    return x


def geometry(fit: FixtureIdentification, data: PointData, obs: Observations) -> PointGeometry:
    """The fixture calibration as ``analyze``'s geometric baseline of ``obs`` (= ``observations(fit, data)``)."""
    if (~data.is_point).any():
        raise ValueError("point rows and measured positions in one analysis: analyze the point rows alone")
    u = fit.unknowns
    layout = Layout(u.model, data.target_names)
    x = _x(fit, layout)
    free = np.zeros(layout.size, bool)
    free[: u.n_kin] = fit.free[: u.n_kin]
    for i in range(len(data.target_names)):
        free[layout.target(i)] = True
    contact = fit.options.stylus_radius_mm is not None
    normals = _normals(_tips(fit, data), fit.z[u.points_slice].reshape(-1, 3)[data.point]) if contact else None
    # without the distances, which fix the arm's scale, a direction may be seen by nothing else: hold
    # what the rows alone do not determine above their noise (the points estimated with them)
    draft = PointGeometry(layout, x, free, np.zeros((len(data), 3)), data.point, len(data.points), normals, fit, ())
    kept = _rows_alone_keep(draft, obs)
    held = tuple(n for i, n in enumerate(u.model.param_names) if free[i] and not kept[i])
    free[: u.n_kin] &= kept[: u.n_kin]
    residuals = np.empty((len(data), 3))
    for rows, p, _ in jacobian_chunks(layout, x, obs, kinematic=False):
        residuals[rows] = p - obs.xyz_mm[rows]
    if contact:
        residuals = np.einsum("ni,nj,nj->ni", normals, normals, residuals)
    return PointGeometry(layout, x, free, residuals, data.point, len(data.points), normals, fit, held)


def _rows_alone_keep(g: PointGeometry, obs: Observations) -> np.ndarray:
    """Mask over x: the free columns the rows alone determine above their noise, with the points
    estimated (the rule ``identify`` applies: a direction whose estimate would scatter more than the
    fixture fit's prior is held), in mm for lengths and mm at the arm's reach for angles."""
    fit = g.fixture_fit
    free = np.flatnonzero(g.free)
    blocks, tips = [], []
    for rows, p, j in jacobian_chunks(g.layout, g.x, obs):
        cols = np.concatenate([g.project(rows, j[:, :, free]), g.point_columns(rows)], axis=2)
        blocks.append(cols.reshape(-1, cols.shape[2]))
        tips.append(p)
    j = np.concatenate(blocks)
    reach = max(float(np.median(np.linalg.norm(np.concatenate(tips), axis=1))), 1.0)
    is_angle = np.r_[g.layout.is_angle[free], np.zeros(g.n_point_columns, bool)]
    j = j / np.where(is_angle, 1.0 / reach, 1.0)
    nuisance = np.zeros(j.shape[1], bool)
    nuisance[len(free):] = True  # the points and the target offsets are always estimated
    nuisance[: len(free)] = free >= g.layout.n_kin
    keep = identifiability.analyse(j, nuisance, ~nuisance, noise_mm=fit.noise_mm, prior_mm=fit.options.prior_mm,
                                   with_condition=False).keep
    out = g.free.copy()
    out[free] = keep[: len(free)]
    return out

