"""A check of a tool against its stored frame from a few crossings of a crossed-beam light barrier.

The model is :mod:`.tcp_laser`'s (a capsule tool, beams as lines with a reach, one trigger
latency for every edge), started at the stored frame, with fewer unknowns: a check has
fewer motions than a calibration, so it fits only what its motions determine and holds the
rest where it was last found:

* the tip (3, flange frame) and the latency and each beam's reach, always (a sweep and its
  return cross each beam on both sides in both directions);
* the axis' tilt (2) only when the sweeps cut the tool at two heights or more
  (``tilt=True``); otherwise the axis is held at the stored frame's;
* each beam's position across its line, horizontally (1 per beam), only when the tool is
  crossed at two turns about the vertical (``beam_across=True``): a tip offset turns with the
  flange, a beam's offset does not. The beams' height is always held: nothing upright tells
  it from the tool's length.

What is held is not known exactly: a held beam position carries the uncertainty it was
found with (`beam_std_mm`), and that goes straight into what it trades against (the tip
along the beams' normal, its length along the axis). It is added to the covariance of the
estimates as a systematic term, so a check whose beams are known only as installed says
that its tip is not determined well enough to judge.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from cellcal.solvers.estimation.fit_result import FitResult, from_solver
from cellcal.solvers.tool_frames.tcp_laser import NULL_RTOL, LaserEdges, LaserGeometry, _Model, axis_pair, edge_sigma_mm


@dataclass(frozen=True)
class CheckFit(FitResult):
    """The checked tool: tip, axis and their covariance (the held beams' uncertainty included);
    status, message, success and nfev are least_squares' own, covariance that of x's fitted part."""

    names: tuple[str, ...]  # the fitted parameters
    x: np.ndarray
    std: np.ndarray
    tip_mm: np.ndarray  # (3,) flange frame
    tip_cov_mm2: np.ndarray  # (3, 3)
    tilt_rad: np.ndarray | None  # (2,) of the axis from the stored axis, along axis_pair; None: held
    tilt_cov_rad2: np.ndarray | None  # (2, 2)
    axis: np.ndarray  # unit, flange frame
    latency_s: float
    latency_std_s: float
    residuals_mm: np.ndarray
    sigma_mm: np.ndarray
    condition: float
    undetermined: tuple[str, ...]


def _free(k: int, tilt: bool, beam_across: bool) -> list[int]:
    """Indices into :class:`.tcp_laser._Model`'s parameters that the check fits."""
    free = [0, 1, 2] + ([3, 4] if tilt else [])
    if beam_across:
        free += [5 + 2 * i for i in range(k)]
    free += [5 + 2 * k + i for i in range(k)] + [5 + 3 * k]
    return free


def fit(edges: LaserEdges, geometry: LaserGeometry, repeatability_mm: float, jitter_s: float, *,
        tilt: bool, beam_across: bool, beam_std_mm: float) -> CheckFit:
    """Weighted least squares of the edges with the parameters a check determines (see the
    module's doc); the noise model is :func:`.tcp_laser.fit`'s, plus `beam_std_mm` (1 sigma,
    per direction) on every held beam position."""
    model = _Model(edges, geometry)
    k = model.k
    free = _free(k, tilt, beam_across)
    held_beams = [5 + 2 * i + j for i in range(k) for j in (0, 1) if not (j == 0 and beam_across)]
    x0 = model.start()
    sigma = edge_sigma_mm(edges, geometry, repeatability_mm, jitter_s)
    n, p = len(sigma), len(free)
    if n <= p:
        raise ValueError(f"{n} edges cannot determine {p} unknowns")

    def full(xf):
        x = x0.copy()
        x[free] = xf
        return x

    sol = least_squares(lambda xf: model.residuals(full(xf)) / sigma, x0[free],
                        jac=lambda xf: model.jacobian(full(xf))[:, free] / sigma[:, None],
                        method="lm", xtol=1e-12, ftol=1e-12)
    x = full(sol.x)
    res = model.residuals(x)
    j_all = model.jacobian(x) / sigma[:, None]
    jw = j_all[:, free]
    norms = np.linalg.norm(jw, axis=0)
    js = jw / np.where(norms > 0, norms, 1.0)
    _, sv, vt = np.linalg.svd(js, full_matrices=False)
    condition = float((sv[0] / sv[-1]) ** 2) if sv[-1] > 0 else float("inf")
    null = vt[sv < NULL_RTOL * sv[0]]
    names = tuple(model.names[i] for i in free)
    undetermined = tuple(name for j, name in enumerate(names)
                         if norms[j] == 0 or (len(null) and np.max(np.abs(null[:, j])) > 0.1))
    noise = model.noise_covariance(x, repeatability_mm, jitter_s) / np.outer(sigma, sigma)
    chi2 = float(np.sum((res / sigma) ** 2)) / (n - p)
    try:
        gain = np.linalg.solve(jw.T @ jw, jw.T)
        cov = max(1.0, chi2) * gain @ noise @ gain.T
        if held_beams and beam_std_mm > 0:
            sens = -gain @ j_all[:, held_beams]  # d estimate / d held beam offset
            cov = cov + beam_std_mm**2 * sens @ sens.T
    except np.linalg.LinAlgError:
        cov = np.full((p, p), np.inf)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    tip, axis, _, _, latency = model.unpack(x)
    tilt_rad = tilt_cov = None
    if tilt:
        e1, e2 = axis_pair(geometry.axis)
        tilt_rad = np.array([np.arctan2(axis @ e, axis @ geometry.axis) for e in (e1, e2)])
        tilt_cov = cov[3:5, 3:5]
    return CheckFit(names, x, std, tip, cov[:3, :3], tilt_rad, tilt_cov, axis, float(latency),
                    float(std[-1]) / 1e3, res, sigma, condition, undetermined, covariance=cov, **from_solver(sol))


def largest_std(cov) -> float:
    """The standard deviation along the worst-determined direction of a covariance."""
    cov = np.asarray(cov, dtype=float)
    if not np.all(np.isfinite(cov)):
        return float("inf")
    return float(np.sqrt(max(float(np.max(np.linalg.eigvalsh(cov))), 0.0)))
