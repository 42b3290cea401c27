"""Two robots' base-to-base transform from their needle tips meeting: pure maths.

At each meeting i, robot a's needle tip and robot b's touch, so with the flange poses
(R_ai, p_ai) in a's base frame and (R_bi, p_bi) in b's, the unknown tips t_a and t_b
(each in its flange frame) and b's base in a's frame (R, T)::

    R_ai t_a + p_ai = R (R_bi t_b + p_bi) + T

Three equations per meeting, twelve unknowns, solved in one fit: the tips are not taken
from a separate TCP calibration, so their errors cannot leak into the frame. The start is
closed-form: the meeting points with the tips as drawn, matched by the SVD (Kabsch /
Umeyama without scale) rotation and translation. Then nonlinear least squares
(:func:`scipy.optimize.least_squares`) on all twelve, the rotation as a small turn about
the start so the parameterisation has no singularity, and standard deviations from the
Jacobian at the solution and the residual's own scale.

What the points can and cannot give is said before fitting: fewer than four, or points
on one plane, are refused with the numbers. (With the needles' orientations varied, this
fit itself stays determined on a plane; the points are still required to span the
workspace in depth, so the frame is checked where it is used rather than extrapolated
off a plane.) :func:`design` gives the condition and the expected errors of a planned set
before anything moves.

Lengths in mm, angles in radians.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from cellcal.solvers.geometry import se3
from cellcal.solvers.estimation.fit_result import FitResult, from_solver

MIN_POINTS = 4
N_UNKNOWNS = 12  # turn (3), translation (3), tip a (3), tip b (3)
MIN_REDUNDANCY = 6  # below this many spare equations the residual cannot tell the noise: the stated one is used
NAMES = ("rx", "ry", "rz", "x", "y", "z", "tip_a_x", "tip_a_y", "tip_a_z", "tip_b_x", "tip_b_y", "tip_b_z")


class HandshakeRefused(ValueError):
    """A point set that cannot determine the frame; the message says why and by how much."""


@dataclass(frozen=True)
class PointSet:
    """How a set of meeting points is spread: extents along its principal axes (RMS, mm)
    and their ratio (the conditioning number of the centred points)."""

    n: int
    spread_mm: np.ndarray  # RMS distance from the centroid along each principal axis, largest first
    normal: np.ndarray  # the axis of least spread (the normal of the best plane)
    condition: float  # spread_mm[0] / spread_mm[2]

    @property
    def out_of_plane_mm(self) -> float:
        return float(self.spread_mm[2])


def point_set(points_mm) -> PointSet:
    points = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    centred = points - points.mean(axis=0)
    _, singular, vt = np.linalg.svd(centred, full_matrices=False) if len(points) else (None, np.zeros(3), np.eye(3))
    spread = np.zeros(3)
    spread[: len(singular)] = singular / np.sqrt(max(len(points), 1))
    condition = float(spread[0] / spread[2]) if spread[2] > 0 else float("inf")
    return PointSet(len(points), spread, vt[-1] if len(vt) == 3 else np.array([0.0, 0.0, 1.0]), condition)


def check_points(points_mm, min_out_of_plane_mm: float) -> PointSet:
    """The point set, or HandshakeRefused: fewer than four, or within `min_out_of_plane_mm`
    (RMS) of one plane."""
    ps = point_set(points_mm)
    if ps.n < MIN_POINTS:
        raise HandshakeRefused(f"{ps.n} meeting points: the frame and both tips need at least {MIN_POINTS} "
                               "points not on one plane")
    if ps.out_of_plane_mm < min_out_of_plane_mm:
        raise HandshakeRefused(
            f"the {ps.n} meeting points lie on one plane (normal {np.round(ps.normal, 3).tolist()}): they stand "
            f"{ps.out_of_plane_mm:.3f} mm RMS out of it against {ps.spread_mm[0]:.1f} and {ps.spread_mm[1]:.1f} mm "
            f"in it (condition {ps.condition:.3g}); at least {min_out_of_plane_mm:g} mm out of plane is needed: a "
            "frame checked on one plane only is extrapolated across it, and four coplanar points leave the "
            "published four-point solution without an answer")
    return ps


@dataclass(frozen=True)
class HandshakeFit(FitResult):
    """b's base in a's frame and both tips; status, message, success and nfev are least_squares' own,
    covariance that of the twelve unknowns in the order of NAMES (the turn about a's axes)."""

    rotation: np.ndarray  # 3x3: robot b's base frame -> robot a's
    translation_mm: np.ndarray  # b's base origin in a's frame
    tip_a_mm: np.ndarray  # a's needle tip, a's flange frame
    tip_b_mm: np.ndarray
    std: np.ndarray  # (12,) in the order of NAMES: turn (rad, about a's axes), mm
    residuals_mm: np.ndarray  # (N, 3)
    sigma0_mm: float  # the residuals' per-axis standard deviation (the fit's own noise estimate)
    sigma_used_mm: float  # the noise the standard deviations are scaled with
    condition: float  # of the column-scaled Jacobian
    start_rotation: np.ndarray  # the closed-form start
    start_translation_mm: np.ndarray
    points: PointSet

    @property
    def pose(self) -> np.ndarray:
        """b's base in a's frame as [x, y, z, rx, ry, rz] (m, rad)."""
        return np.concatenate([self.translation_mm / 1e3, se3.matrix_to_rotvec(self.rotation)])


def _unpack(x, rotation0):
    return se3.rotvec_to_matrix(x[:3]) @ rotation0, x[3:6], x[6:9], x[9:12]


def residuals(x, rotation0, ra, pa, rb, pb) -> np.ndarray:
    """(N*3,): a's tip minus b's tip carried into a's frame, per meeting."""
    rotation, translation, tip_a, tip_b = _unpack(x, rotation0)
    at_a = np.einsum("nij,j->ni", ra, tip_a) + pa
    at_b = (np.einsum("nij,j->ni", rb, tip_b) + pb) @ rotation.T + translation
    return (at_a - at_b).ravel()


def jacobian(x, rotation0, ra, pa, rb, pb) -> np.ndarray:
    rotation, _, _, tip_b = _unpack(x, rotation0)
    n = len(ra)
    carried = (np.einsum("nij,j->ni", rb, tip_b) + pb) @ rotation.T  # R v_i
    jl = se3.left_jacobian(x[:3])
    jac = np.zeros((n, 3, N_UNKNOWNS))
    jac[:, :, :3] = np.einsum("nij,jk->nik", se3.skew(carried), jl)  # -d(R v)/dw = [R v]x J_l
    jac[:, :, 3:6] = -np.eye(3)
    jac[:, :, 6:9] = ra
    jac[:, :, 9:12] = -np.einsum("ij,njk->nik", rotation, rb)
    return jac.reshape(3 * n, N_UNKNOWNS)


def _scaled_condition(jac: np.ndarray) -> float:
    norms = np.linalg.norm(jac, axis=0)
    singular = np.linalg.svd(jac / np.where(norms > 0, norms, 1.0), compute_uv=False)
    return float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")


def closed_form(ra, pa, rb, pb, tip_a_mm, tip_b_mm) -> tuple[np.ndarray, np.ndarray]:
    """The SVD start: the meeting points with the tips as guessed, matched rigidly."""
    at_a = np.einsum("nij,j->ni", ra, tip_a_mm) + pa
    at_b = np.einsum("nij,j->ni", rb, tip_b_mm) + pb
    return se3.rigid_fit(at_b, at_a)


@dataclass(frozen=True)
class PlanQuality:
    """What planned meetings can give before they are made, for a per-axis noise sigma."""

    condition: float
    std: np.ndarray  # (12,) as HandshakeFit.std
    position_mm: float  # 1-sigma RMS error of b's base origin
    rotation_deg: float  # 1-sigma RMS turn of the frame


def _covariance(jac: np.ndarray, sigma: float) -> np.ndarray:
    return np.linalg.pinv(jac.T @ jac) * sigma**2


def design(ra, pa, rb, pb, tip_a_mm, tip_b_mm, sigma_mm: float) -> PlanQuality:
    """The condition and expected errors of meetings at planned flange poses (mm, as the
    controllers' models put them), the tips as drawn."""
    ra, pa, rb, pb = (np.asarray(v, dtype=float) for v in (ra, pa, rb, pb))
    rotation, translation = closed_form(ra, pa, rb, pb, tip_a_mm, tip_b_mm)
    x = np.concatenate([np.zeros(3), translation, tip_a_mm, tip_b_mm])
    jac = jacobian(x, rotation, ra, pa, rb, pb)
    condition = _scaled_condition(jac)
    cov = _covariance(jac, sigma_mm)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return PlanQuality(condition, std, float(np.sqrt(np.trace(cov[3:6, 3:6]))),
                  float(np.degrees(np.sqrt(np.trace(cov[:3, :3])))))


def fit_handshake(ra, pa, rb, pb, tip_a_mm, tip_b_mm, *, min_out_of_plane_mm: float = 1.0,
                  sigma_prior_mm: float | None = None) -> HandshakeFit:
    """Fit b's base in a's frame and both tips to N meetings (flange rotations (N, 3, 3) and
    positions (N, 3) mm of each robot in its own base frame); `tip_*_mm` are the drawn tips
    (the start). The standard deviations scale with the residual's own noise, or with
    `sigma_prior_mm` (per axis, stated) when fewer than MIN_REDUNDANCY equations are spare.
    Raises HandshakeRefused for a point set that cannot determine it."""
    ra, pa, rb, pb = (np.asarray(v, dtype=float) for v in (ra, pa, rb, pb))
    tip_a_mm, tip_b_mm = np.asarray(tip_a_mm, dtype=float), np.asarray(tip_b_mm, dtype=float)
    points = check_points(np.einsum("nij,j->ni", ra, tip_a_mm) + pa, min_out_of_plane_mm)
    rotation0, translation0 = closed_form(ra, pa, rb, pb, tip_a_mm, tip_b_mm)
    x0 = np.concatenate([np.zeros(3), translation0, tip_a_mm, tip_b_mm])
    args = (rotation0, ra, pa, rb, pb)
    solution = least_squares(residuals, x0, jac=jacobian, args=args, method="lm", xtol=1e-14, ftol=1e-14)
    x = solution.x
    rotation, translation, tip_a, tip_b = _unpack(x, rotation0)
    r = residuals(x, *args)
    jac = jacobian(x, *args)
    dof = len(r) - N_UNKNOWNS
    sigma0 = float(np.sqrt(r @ r / max(dof, 1)))
    sigma = sigma_prior_mm if sigma_prior_mm is not None and dof < MIN_REDUNDANCY else sigma0
    # the turn's std about a's axes: at the solution w = x[:3], dR = J_l(w) dw
    cov = _covariance(jac, sigma)
    jl = se3.left_jacobian(x[:3])
    cov[:3, :3] = jl @ cov[:3, :3] @ jl.T
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return HandshakeFit(rotation, translation, tip_a, tip_b, std, r.reshape(-1, 3), sigma0, float(sigma),
                        _scaled_condition(jac),
                        rotation0, translation0, points, covariance=cov, **from_solver(solution))
