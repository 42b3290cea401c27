"""The discrepancy analysis of point-form data: sockets the tool sat in, balls it touched.

``analyze`` scores every candidate effect on the rigid model linearised at its geometric fit
(``LinearisedScorer``). For measured positions that fit is ``identify``'s; for point rows it is
the fixture calibration (``fixture_identify.identify_points``), and what point rows measure
differs in two ways, both carried by :class:`PointGeometry`:

- each point's position is an unknown of its own, estimated with the geometry in every fold
  (``point_jacobian``: d residual / d point = -I), so a held-out row is scored against its point
  as the fold's training rows place it. The rows of a point therefore need not share a fold.
  Each point's three columns touch its own rows only: the scorer eliminates them in every
  training (``crossval.PointFoldFactors``) instead of carrying them as columns of their own.
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

    def point_jacobian(self, rows) -> np.ndarray:
        """d residual / d the position of each of these rows' own point, (n, 3, 3)."""
        n = len(np.arange(len(self.point))[rows])
        return self.project(rows, -np.broadcast_to(np.eye(3), (n, 3, 3)))

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
    j = np.empty((len(obs), 3, len(free)))
    tips = np.empty((len(obs), 3))
    for rows, p, jr in jacobian_chunks(g.layout, g.x, obs):
        j[rows] = g.project(rows, jr[:, :, free])
        tips[rows] = p
    reach = max(float(np.median(np.linalg.norm(tips, axis=1))), 1.0)
    j = j / np.where(g.layout.is_angle[free], 1.0 / reach, 1.0)
    # the points projected out of their own rows (the target offsets are always estimated: the nuisance);
    # the R factor of what is left has the singular values and subsets of the columns with the points
    pj = g.point_jacobian(slice(None))
    s = np.zeros((g.n_points, 3, len(free)))
    n = np.zeros((g.n_points, 3, 3))
    np.add.at(s, g.point, np.einsum("nci,ncp->nip", pj, j))
    np.add.at(n, g.point, np.einsum("nci,ncj->nij", pj, pj))
    j = j - pj @ (np.linalg.pinv(n, hermitian=True) @ s)[g.point]
    nuisance = free >= g.layout.n_kin
    r = np.linalg.qr(j.reshape(-1, len(free)), mode="r")
    keep = identifiability.analyse(r, nuisance, ~nuisance, noise_mm=fit.noise_mm, prior_mm=fit.options.prior_mm,
                                   with_condition=False, n_rows=3 * len(obs)).keep
    out = g.free.copy()
    out[free] = keep
    return out

