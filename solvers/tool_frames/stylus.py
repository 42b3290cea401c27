"""A cylindrical tool touched on a fixed stylus ball: what the contacts determine, and the fit.

Units inside are mm and rad. Contacts come in as flange poses (rotations (N, 3, 3) and
origins (N, 3) mm in the base frame, the controller's kinematics at the recorded joints).

Geometry. The tool is a cylinder whose axis is the line {c + s u} in the flange frame (u
unit, from the flange toward the end); its end point, the TCP, is c + t u. The stylus is a
ball of radius r_s centred at S in the base frame. At contact i, with flange pose (R_i, p_i),
the ball's centre in the flange frame is s_i = R_i^T (S - p_i), and

* side contact (ball on the mantle): |(I - u u^T)(s_i - c)| = R, with R = r_tool + r_s;
* face contact (ball on the end, on the axis): (s_i - c).u = t + r_s for a flat end face, or
  |s_i - (c + (t - r_tool) u)| = R for a round end of the tool's own radius.

Side contacts determine the axis line (two offsets and two angles), S and R, and nothing
else: sliding the tool along its axis or turning it about the axis leaves every distance to
the axis unchanged. Face contacts add t. The turn about the axis is never measured: the tool
frame's z is the axis and its turn about z is the convention of ``se3.rotvec_from_z`` (the
smallest turn from flange z), which is what a round tool's frame means.

The fine fit is one ``scipy.optimize.least_squares`` over x = [c1, c2, a1, a2, Sx, Sy, Sz,
R?, t?] with the analytic Jacobian below: c = c0 + c1 e1 + c2 e2, u = (u0 + a1 e1 + a2 e2)
/ |.|, where (c0, u0) is the start line and e1, e2 span the plane normal to u0. With a robust
loss the fit only finds the outliers (its scale annealed from the misfit at the start down
to the noise); contacts beyond ``reject_k`` robust sigmas are left out and the rest refitted
by plain least squares, so the result is the plain fit of the contacts kept.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares

from cellcal.solvers.geometry import se3
from cellcal.solvers.estimation.fit_result import FitResult, from_solver

SIDE, FACE = 0, 1
LOSSES = ("linear", "soft_l1", "huber", "cauchy")
END_SHAPES = ("round", "flat")
ANGLE_LENGTH_MM = 50.0  # an angle of 1 rad counts as this many mm when columns are compared


@dataclass(frozen=True)
class Contacts:
    """Recorded contacts: flange poses and what each contact touched."""

    rotation: np.ndarray  # (N, 3, 3) flange -> base
    position_mm: np.ndarray  # (N, 3) flange origin in the base frame
    kind: np.ndarray  # (N,) SIDE or FACE

    def __len__(self) -> int:
        return len(self.kind)

    def rows(self, mask) -> "Contacts":
        return Contacts(self.rotation[mask], self.position_mm[mask], self.kind[mask])

    def stylus_in_flange(self, stylus_mm: np.ndarray) -> np.ndarray:
        return np.einsum("nji,nj->ni", self.rotation, stylus_mm - self.position_mm)


@dataclass(frozen=True)
class Line:
    """A tool axis in the flange frame: a point on it and its unit direction (mm)."""

    point_mm: np.ndarray
    direction: np.ndarray

    def foot(self, point_mm: np.ndarray) -> np.ndarray:
        """The point of the line nearest `point_mm` (..., 3)."""
        return self.point_mm + ((point_mm - self.point_mm) @ self.direction)[..., None] * self.direction


# -- coarse: Chang et al.'s four-point TCP and the axis from axial moves -----------------------------

def four_point(rotation: np.ndarray, position_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The flange point that touched one fixed point from every pose, and that fixed point.

    Solves R_i t + p_i = P for t (flange) and P (base) by linear least squares (at least
    three well-spread orientations). Returns (t, P, RMS of the closure in mm).
    """
    n = len(rotation)
    a = np.concatenate([rotation, np.broadcast_to(-np.eye(3), (n, 3, 3))], axis=2).reshape(3 * n, 6)
    b = -position_mm.reshape(3 * n)
    x, *_ = np.linalg.lstsq(a, b, rcond=None)
    closure = (a @ x - b).reshape(n, 3)
    return x[:3], x[3:], float(np.sqrt(np.mean(np.sum(closure**2, axis=1))))


def axis_from_axial_moves(rotation: np.ndarray, position_mm: np.ndarray, groups: np.ndarray,
                          toward: np.ndarray) -> np.ndarray:
    """The axis direction (flange frame) from side contacts made at one orientation and
    several heights along the axis (Chang et al.'s TCF from axial moves).

    Within a group the flange only translates, and every contact meets the same generatrix,
    so R^T p moves along the axis: its principal direction is u. Groups are combined weighted
    by their spread; the sign is chosen toward `toward` (the drawn axis).
    """
    total = np.zeros(3)
    for g in np.unique(groups):
        sel = groups == g
        if sel.sum() < 2:
            continue
        pts = np.einsum("nji,nj->ni", rotation[sel], position_mm[sel])
        centred = pts - pts.mean(axis=0)
        _, s, vt = np.linalg.svd(centred, full_matrices=False)
        u = vt[0] if vt[0] @ toward >= 0 else -vt[0]
        total += u * s[0] ** 2
    if not np.any(total):
        raise ValueError("no group of axial moves with two contacts or more")
    return total / np.linalg.norm(total)


@dataclass(frozen=True)
class Estimate:
    """What is known of the tool and the stylus at some stage (mm, flange and base frames)."""

    line: Line
    tip_mm: np.ndarray | None  # None: not yet determined along the axis
    stylus_mm: np.ndarray


def coarse(rotation, position_mm, kind: np.ndarray, groups: np.ndarray, approach: np.ndarray,
           stylus_radius_mm: float, radius_mm: float, drawn_axis: np.ndarray) -> Estimate:
    """The start of the fine fit from the coarse contacts.

    `kind` marks each row "coarse-face" (end-face touches at several orientations: the
    four-point TCP and the stylus), "axial" (side touches at one orientation per group and
    several heights: the axis direction) or anything else (ignored). The axis passes where
    the axial contacts put it: at contact the ball's centre lies `radius_mm` from the axis
    along the approach direction (base `approach`, unit).
    """
    face, axial = kind == "coarse-face", kind == "axial"
    if face.sum() < 3 or axial.sum() < 2:
        raise ValueError("the coarse stage needs three end-face touches and two axial moves or more")
    point, stylus, _ = four_point(rotation[face], position_mm[face])
    u = axis_from_axial_moves(rotation[axial], position_mm[axial], groups[axial], drawn_axis)
    s = np.einsum("nji,nj->ni", rotation[axial], stylus - position_mm[axial])
    toward = np.einsum("nji,nj->ni", rotation[axial], approach[axial])
    toward -= (toward @ u)[:, None] * u
    toward /= np.linalg.norm(toward, axis=1)[:, None]
    feet = s - radius_mm * toward
    feet -= (feet @ u)[:, None] * u
    tip = point - u * stylus_radius_mm
    line = Line(tip - (tip @ u) * u + feet.mean(axis=0), u)
    return Estimate(line, line.foot(tip), stylus)


# -- the fine fit ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Setup:
    """What the fit holds fixed: the start line, the stylus radius, the end's shape."""

    start: Line
    stylus_radius_mm: float
    radius_mm: float  # contact radius R = tool + stylus radius: start value, or fixed
    fit_radius: bool = True
    end_shape: str = "round"

    def basis(self) -> tuple[np.ndarray, np.ndarray]:
        u0 = self.start.direction
        e1 = np.cross(u0, [1.0, 0.0, 0.0] if abs(u0[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        return e1, np.cross(u0, e1)


@dataclass(frozen=True)
class StylusFit(FitResult):
    """The tool axis, tip and stylus. status and message are those of the last least_squares solve
    (the plain fit of the contacts kept), nfev counts the evaluations of every solve (those of the
    side contacts' fit the end face starts from included); covariance is of x,
    from the kept contacts' residual variance."""

    names: tuple[str, ...]
    x: np.ndarray
    line: Line
    tip_mm: np.ndarray | None  # None without face contacts: not determined along the axis
    stylus_mm: np.ndarray
    radius_mm: float
    residuals_mm: np.ndarray  # of every contact given, kept or not
    kept: np.ndarray  # bool: used in the final fit
    jacobian: np.ndarray  # of the kept contacts, at x
    sigma_mm: float  # residual RMS of the kept contacts (dof-corrected)
    setup: "Setup"  # the parameterisation x refers to
    notes: list[str] = field(default_factory=list)


def names_of(setup: Setup, with_face: bool) -> tuple[str, ...]:
    names = ["axis.offset1_mm", "axis.offset2_mm", "axis.tilt1_rad", "axis.tilt2_rad",
             "stylus.x_mm", "stylus.y_mm", "stylus.z_mm"]
    if setup.fit_radius:
        names.append("radius_mm")
    if with_face:
        names.append("tip.along_axis_mm")
    return tuple(names)


def _unpack(x: np.ndarray, setup: Setup, with_face: bool):
    e1, e2 = setup.basis()
    c = setup.start.point_mm + x[0] * e1 + x[1] * e2
    v = setup.start.direction + x[2] * e1 + x[3] * e2
    norm = float(np.linalg.norm(v))
    s = x[4:7]
    k = 7
    radius = setup.radius_mm
    if setup.fit_radius:
        radius, k = x[k], k + 1
    t = x[k] if with_face else 0.0
    return c, v / norm, norm, s, radius, t, e1, e2


def residuals(x: np.ndarray, contacts: Contacts, setup: Setup, with_face: bool, jac: bool = False):
    """Residuals (N,) in mm and, with `jac`, their Jacobian (N, len(x))."""
    c, u, norm, stylus, radius, t, e1, e2 = _unpack(x, setup, with_face)
    s = contacts.stylus_in_flange(stylus)
    w = s - c
    along = w @ u
    side = contacts.kind == SIDE
    face = ~side
    r = np.empty(len(contacts))
    d = w - along[:, None] * u
    dist = np.linalg.norm(d, axis=1)
    r[side] = dist[side] - radius
    r_tool = radius - setup.stylus_radius_mm
    if setup.end_shape == "flat":
        r[face] = along[face] - t - setup.stylus_radius_mm
    else:
        centre = c + (t - r_tool) * u
        e = s - centre
        sign = np.where(e @ u < 0.0, -1.0, 1.0)  # a ball behind the end's centre is no contact
        e_norm = sign * np.linalg.norm(e, axis=1)
        r[face] = e_norm[face] - radius
    if not jac:
        return r
    n_x = len(x)
    j = np.zeros((len(contacts), n_x))
    proj = (np.eye(3) - np.outer(u, u)) / norm  # du/dv
    du = np.stack([proj @ e1, proj @ e2], axis=1)  # (3, 2): du/da1, du/da2
    basis = np.stack([e1, e2], axis=1)  # (3, 2): dc/dc1, dc/dc2
    k_r = 7 if setup.fit_radius else None
    k_t = n_x - 1 if with_face else None
    # side: f = |P(w)| - R; df/dw = nhat, df/du = -(w.u) nhat, df/dS = R_i nhat
    nhat = d[side] / np.maximum(dist[side], 1e-12)[:, None]
    j[side, 0:2] = -nhat @ basis
    j[side, 2:4] = -(along[side, None] * (nhat @ du))
    j[side, 4:7] = np.einsum("nij,nj->ni", contacts.rotation[side], nhat)
    if k_r is not None:
        j[side, k_r] = -1.0
    if np.any(face):
        if setup.end_shape == "flat":
            j[face, 0:2] = -(u @ basis)
            j[face, 2:4] = w[face] @ du
            j[face, 4:7] = np.einsum("nij,j->ni", contacts.rotation[face], u)
            if k_t is not None:
                j[face, k_t] = -1.0
        else:
            ehat = e[face] / np.where(np.abs(e_norm[face]) > 1e-12, e_norm[face], 1e-12)[:, None]
            j[face, 0:2] = -ehat @ basis
            j[face, 2:4] = -(t - r_tool) * (ehat @ du)
            j[face, 4:7] = np.einsum("nij,nj->ni", contacts.rotation[face], ehat)
            if k_r is not None:
                j[face, k_r] = ehat @ u - 1.0
            if k_t is not None:
                j[face, k_t] = -(ehat @ u)
    return r, j


def scales(names) -> np.ndarray:
    """About how many mm one unit of each parameter moves a contact: 1 for lengths,
    ANGLE_LENGTH_MM for angles (rad). Columns divided by it compare like with like."""
    return np.array([ANGLE_LENGTH_MM if n.endswith("_rad") else 1.0 for n in names])


def fit(contacts: Contacts, setup: Setup, stylus_start_mm: np.ndarray, *, loss: str = "linear",
        noise_mm: float = 0.02, reject_k: float = 5.0) -> StylusFit:
    """The fine fit of every contact given (side and face).

    With a robust `loss` (``cauchy`` redescends: a contact far off stops pulling), fits with it
    start from the start, its scale halved from three robust sigmas of the misfit there down to
    three `noise_mm`; then contacts beyond `reject_k`
    robust sigmas are left out and the rest refitted plainly, until the kept set settles. So
    the result is the plain fit of the contacts kept: clean ones weigh as in a clean run.
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {', '.join(LOSSES)}")
    with_face = bool(np.any(contacts.kind == FACE))
    side = contacts.kind == SIDE
    nfev_before = 0  # of the side contacts' fit the end face starts from
    if with_face and side.sum() > len(names_of(setup, False)):
        # the side contacts alone fix the axis and the stylus: start the end face from them
        first = fit(contacts.rows(side), setup, stylus_start_mm, loss=loss, noise_mm=noise_mm, reject_k=reject_k)
        setup = replace(setup, start=first.line, radius_mm=first.radius_mm if setup.fit_radius else setup.radius_mm)
        stylus_start_mm = first.stylus_mm
        nfev_before = first.nfev
    names = names_of(setup, with_face)
    x0 = np.zeros(len(names))
    x0[4:7] = stylus_start_mm
    if setup.fit_radius:
        x0[7] = setup.radius_mm
    if with_face:  # start t where the face contacts put it along the start line
        s = contacts.rows(contacts.kind == FACE).stylus_in_flange(stylus_start_mm)
        x0[-1] = float(np.median((s - setup.start.point_mm) @ setup.start.direction)) - setup.stylus_radius_mm
    if len(contacts) < len(names):
        raise ValueError(f"{len(contacts)} contacts cannot determine {len(names)} parameters")
    x_scale = 1.0 / scales(names)
    kept = np.ones(len(contacts), bool)
    notes = []
    solutions = []  # every least_squares result, in order: the last is the fit's

    def solve(x_start, rows, how, f_scale=1.0):
        sub = contacts.rows(rows)
        solutions.append(least_squares(lambda x: residuals(x, sub, setup, with_face),
                                       x_start, jac=lambda x: residuals(x, sub, setup, with_face, jac=True)[1],
                                       method="trf", loss=how, f_scale=f_scale, x_scale=x_scale,
                                       xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200))
        return solutions[-1].x

    if loss == "linear":
        x = solve(x0, kept, "linear")
    else:
        # from the start, the loss's scale halved step by step from the misfit down to the
        # noise (graduated non-convexity): a plain fit first would let the outliers drag the
        # start into a wrong valley, the noise's scale at once would stall far from the minimum
        floor, x = 3.0 * noise_mm, x0
        scale = max(3.0 * _robust_sigma(residuals(x, contacts, setup, with_face)), floor)
        while True:
            x = solve(x, kept, loss, scale)
            if scale <= floor:
                break
            scale = max(scale / 2.0, floor)
        for _ in range(10):  # leave out what lies beyond reject_k sigmas, refit plainly, until that settles
            r = residuals(x, contacts, setup, with_face)
            now = np.abs(r) <= reject_k * max(_robust_sigma(r[kept]), 0.25 * noise_mm)
            settled = np.array_equal(now, kept)
            kept = now
            x = solve(x, kept, "linear")
            if settled:
                break
        if not kept.all():
            notes.append(f"{int((~kept).sum())} of {len(kept)} contacts left out as outliers (beyond {reject_k:g} "
                         f"robust sigmas of the fit, {reject_k * _robust_sigma(r[kept]):.4f} mm)")
    r_all = residuals(x, contacts, setup, with_face)
    _, j = residuals(x, contacts.rows(kept), setup, with_face, jac=True)
    dof = max(int(kept.sum()) - len(x), 1)
    sigma = float(np.sqrt(np.sum(r_all[kept] ** 2) / dof))
    covariance = sigma**2 * np.linalg.pinv(j.T @ j)
    c, u, _, stylus, radius, t, _, _ = _unpack(x, setup, with_face)
    line = Line(c, u)
    ended = {**from_solver(solutions[-1]), "nfev": nfev_before + sum(int(sol.nfev) for sol in solutions)}
    return StylusFit(names, x, line, c + t * u if with_face else None, stylus, float(radius), r_all, kept,
                     j, sigma, setup, notes, covariance=covariance, **ended)


def best_fit(contacts: Contacts, starts: list[Estimate], stylus_radius_mm: float, radius_mm: float,
             fit_radius: bool = True, end_shape: str = "round", **options) -> StylusFit:
    """:func:`fit` from each start; the fit whose contacts sit best (least median |residual|).

    A start a few millimetres off (the four-point TCP of touches of which one went wrong)
    can lead to a wrong minimum; the drawing as a second start rules that out cheaply."""
    best = None
    for start in starts:
        setup = Setup(start.line, stylus_radius_mm, radius_mm, fit_radius, end_shape)
        result = fit(contacts, setup, start.stylus_mm, **options)
        score = float(np.median(np.abs(result.residuals_mm)))
        if best is None or score < best[0]:
            best = (score, result)
    return best[1]


def _robust_sigma(r: np.ndarray) -> float:
    """The standard deviation the median absolute deviation implies (normal errors)."""
    return 1.4826 * float(np.median(np.abs(r - np.median(r))))


def tool_frame(line: Line, tip_mm: np.ndarray) -> np.ndarray:
    """The flange -> TCP frame [x, y, z (m), rotation vector] with z along the axis."""
    return np.concatenate([np.asarray(tip_mm) / 1000.0, se3.rotvec_from_z(line.direction)])


def summary(result: StylusFit, anchor_mm: np.ndarray, null_space=None, h: float = 1e-7) -> list[tuple]:
    """What a person reads, as (name, value, std, unit, determined): the TCP (mm) when face
    contacts fixed it, else the axis point nearest `anchor_mm` (the drawn tip); the axis as
    the tool frame's rx, ry (deg; its rz is the convention, not a result); the stylus (mm);
    the contact radius. Standard deviations by first-order propagation of the covariance; a
    value that moves along a direction of `null_space` (columns) is not determined."""
    with_face, setup = result.tip_mm is not None, result.setup

    def values(x):
        c, u, _, stylus, radius, t, _, _ = _unpack(x, setup, with_face)
        point = c + t * u if with_face else Line(c, u).foot(anchor_mm)
        return np.r_[point, np.degrees(se3.rotvec_from_z(u)[:2]), stylus, [radius] if setup.fit_radius else []]

    steps = h / scales(result.names)
    d = np.stack([(values(result.x + e) - values(result.x - e)) / (2 * e[i])
                  for i, e in enumerate(np.diag(steps))], axis=1)
    std = np.sqrt(np.abs(np.diag(d @ result.covariance @ d.T)))
    seen = np.ones(len(std), bool) if null_space is None or not np.size(null_space) else \
        np.abs(d @ null_space).max(axis=1) < 1e-4 * np.abs(d).max(axis=1).clip(1e-12)
    point = "tcp" if with_face else "axis_near_drawn_tip"
    names = [f"{point}.x", f"{point}.y", f"{point}.z", "tool.rx", "tool.ry", "stylus.x", "stylus.y", "stylus.z",
             "contact_radius"]
    units = ["mm"] * 3 + ["deg"] * 2 + ["mm"] * 4
    if not setup.fit_radius:
        names, units = names[:-1], units[:-1]
    return [(n, float(v), float(sd), unit, bool(ok))
            for n, v, sd, unit, ok in zip(names, values(result.x), std, units, seen)]
