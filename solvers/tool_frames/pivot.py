"""The pivot (N-point) tool centre and the tool axis from moves along it: pure maths.

Pivot: the centre of a tool's tip rounding rests in one fixed socket from N orientations,
so for each flange pose (R_i, p_i) ``R_i t + p_i = c`` with t the tip centre in the flange
frame and c the socket's seat in the base frame. That is linear in (t, c): least squares,
one seat that did not sit right removed at a time (its residual beyond k robust standard
deviations), and the design judged before anything moves by the error it leaves for a
given pose noise (:func:`pivot_design`).

Axis: with the orientation held, the tool is translated along its own axis and a fixed
ball is touched from opposite sides on two lines across the axis at two heights. The
midpoint of each opposite pair is where the axis crosses that line (the tool and ball
radii cancel), so per search line ``m = o + h (R^T e) . a`` with h the height back from
the tip, e the line's direction, R the flange rotation and a the axis in the flange
frame: linear in the lines' offsets o and in a's part across the drawn axis
(:func:`fit_axis`).

Lengths are in mm (the maths holds in any unit; the routines pass mm and the results' names
say mm); angles in radians. Both fits are closed form: they report status 1 and success, or
success False with the reason when the design is singular (:mod:`cellcal.solvers.estimation.fit_result`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from cellcal.solvers.estimation.fit_result import FitResult, degenerate, solved

MAD_TO_SIGMA = 1.4826  # median absolute deviation of a normal variable -> its standard deviation
SINGULAR_CONDITION = 1e12  # a design conditioned worse than this determines nothing


def pivot_matrix(rotations) -> np.ndarray:
    """The (3N, 6) design of ``R_i t - c = -p_i`` in the unknowns (t, c)."""
    rotations = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
    n = len(rotations)
    a = np.zeros((3 * n, 6))
    a[:, :3] = rotations.reshape(3 * n, 3)
    a[:, 3:] = -np.tile(np.eye(3), (n, 1))
    return a


@dataclass(frozen=True)
class PlanQuality:
    """What a set of poses can give before they are measured: the condition number of
    the design and the standard deviations it leaves for a noise of ``sigma`` per axis."""

    condition: float
    std: np.ndarray  # per unknown of interest
    expected_error: float  # sqrt of the summed variances: the 1-sigma RMS length of the error


def _design(a: np.ndarray, sigma: float, take: slice) -> PlanQuality:
    singular = np.linalg.svd(a, compute_uv=False)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")
    if not np.isfinite(condition) or condition > SINGULAR_CONDITION:
        n = len(range(*take.indices(a.shape[1])))
        return PlanQuality(float("inf"), np.full(n, np.inf), float("inf"))
    cov = np.linalg.inv(a.T @ a)[take, take] * sigma**2
    std = np.sqrt(np.diag(cov))
    return PlanQuality(condition, std, float(np.sqrt(np.trace(cov))))


def pivot_design(rotations, sigma: float) -> PlanQuality:
    """Condition and the tip centre's expected error for flange rotations `rotations`
    with seats scattered by `sigma` per axis."""
    return _design(pivot_matrix(rotations), sigma, slice(0, 3))


def smallest_setting(expected_error, target: float, low: float, high: float) -> float | None:
    """The smallest x in [low, high] with ``expected_error(x) <= target`` (the error falls
    as x grows), or None when even `high` does not reach it."""
    if expected_error(high) > target:
        return None
    if expected_error(low) <= target:
        return low
    return float(brentq(lambda x: expected_error(x) - target, low, high, xtol=1e-3))


@dataclass(frozen=True)
class PivotFit(FitResult):
    """The tip centre and the seat; covariance of (t, c) from the kept residuals."""

    tool_point: np.ndarray  # t: the tip centre in the flange frame
    pivot_point: np.ndarray  # c: the seat in the base frame
    residuals_mm: np.ndarray  # (N, 3) R_i t + p_i - c for every seat, rejected ones included
    kept: np.ndarray  # (N,) bool
    rejected: list  # seat indices in the order they were rejected
    scale: float  # the per-axis standard deviation outliers were judged against
    std: np.ndarray  # (3,) of t, from the kept residuals
    pivot_std: np.ndarray  # (3,) of c
    condition: float  # of the kept seats' design


def _solve_pivot(rotations, positions, kept):
    a = pivot_matrix(rotations[kept])
    b = -positions[kept].reshape(-1)
    x, *_ = np.linalg.lstsq(a, b, rcond=None)
    return x[:3], x[3:], a


def fit_pivot(rotations, positions, *, noise_floor: float, k: float = 4.0, min_kept: int = 4) -> PivotFit:
    """Least squares of ``R_i t + p_i = c`` with iterative outlier rejection.

    The scale is the larger of the residuals' robust standard deviation per axis
    (1.4826 x their median absolute value) and `noise_floor` (the stated pose noise, so
    that unusually tidy data do not turn a normal seat into an outlier). The seat whose
    residual length is largest is rejected while it exceeds k x that scale and more than
    `min_kept` seats remain; then everything is refitted.
    """
    rotations = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    n = len(rotations)
    if n < 3 or len(positions) != n:
        raise ValueError(f"a pivot fit needs at least 3 seats with one position each, got {n} and {len(positions)}")
    kept = np.ones(n, dtype=bool)
    rejected: list[int] = []
    while True:
        t, c, a = _solve_pivot(rotations, positions, kept)
        residuals = np.einsum("nij,j->ni", rotations, t) + positions - c
        scale = max(MAD_TO_SIGMA * float(np.median(np.abs(residuals[kept]))), float(noise_floor))
        lengths = np.linalg.norm(residuals, axis=1)
        worst = int(np.argmax(np.where(kept, lengths, -1.0)))
        if kept.sum() > min_kept and lengths[worst] > k * scale:
            kept[worst] = False
            rejected.append(worst)
            continue
        break
    dof = 3 * int(kept.sum()) - 6
    ssr = float(np.sum(residuals[kept] ** 2))
    sigma_fit = np.sqrt(ssr / dof) if dof > 0 else float("nan")
    cov = np.linalg.pinv(a.T @ a) * sigma_fit**2
    singular = np.linalg.svd(a, compute_uv=False)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")
    seats = f"{int(kept.sum())} of {n} seats"
    if condition <= SINGULAR_CONDITION:
        ended = solved(f"tip centre and seat solved by linear least squares over {seats}")
    else:
        ended = degenerate(f"the {seats} do not determine the tip centre: their orientations turn about one "
                           f"axis at most (condition {condition:.3g})")
    return PivotFit(t, c, residuals, kept, rejected, scale, np.sqrt(np.diag(cov)[:3]), np.sqrt(np.diag(cov)[3:]),
                    condition, covariance=cov, **ended)


# -- the tool axis from moves along it -------------------------------------------------------------

def across(axis) -> np.ndarray:
    """Two unit vectors (2, 3) completing unit `axis` to a right-handed orthonormal basis."""
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(axis, u)])


def axis_matrix(line, rotations, directions, heights, drawn_axis) -> tuple[np.ndarray, np.ndarray]:
    """The design of ``m = o_line + h (R^T e) . a`` in (o_0 .. o_{L-1}, two tilts across the
    drawn axis), and the part of each row the drawn axis predicts (moved to the data side)."""
    line = np.asarray(line, dtype=int)
    rotations = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
    directions = np.asarray(directions, dtype=float).reshape(-1, 3)
    heights = np.asarray(heights, dtype=float)
    n_lines = int(line.max()) + 1
    in_flange = np.einsum("nji,nj->ni", rotations, directions)  # R^T e
    a = np.zeros((len(line), n_lines + 2))
    a[np.arange(len(line)), line] = 1.0
    a[:, n_lines:] = heights[:, None] * (in_flange @ across(drawn_axis).T)
    predicted = heights * (in_flange @ (np.asarray(drawn_axis, dtype=float) / np.linalg.norm(drawn_axis)))
    return a, predicted


def _offset_scale(a: np.ndarray, n_lines: int) -> np.ndarray:
    """Column scales bringing the offsets' columns to the tilts' size (a unitless condition)."""
    scale = np.ones(a.shape[1])
    size = np.linalg.norm(a[:, :n_lines], axis=0)
    scale[:n_lines] = np.linalg.norm(a[:, n_lines:], axis=0).mean() / np.where(size > 0, size, 1.0)
    return scale


def axis_design(line, rotations, directions, heights, drawn_axis, sigma: float) -> PlanQuality:
    """Condition and the axis direction's expected error (rad) for midpoints scattered by
    `sigma`; the offsets' columns are scaled to the tilts' so the condition is unitless."""
    a, _ = axis_matrix(line, rotations, directions, heights, drawn_axis)
    n_lines = a.shape[1] - 2
    scale = _offset_scale(a, n_lines)
    d = _design(a * scale, sigma, slice(n_lines, n_lines + 2))
    return PlanQuality(d.condition, d.std * scale[n_lines:], d.expected_error)


@dataclass(frozen=True)
class AxisFit(FitResult):
    """The tool axis; covariance of (the line offsets, the two tilts) from the residuals."""

    axis: np.ndarray  # unit, flange frame, from the flange toward the tip
    tilt: np.ndarray  # (2,) rad: the axis' part across the drawn axis (on `across(drawn_axis)`)
    tilt_std: np.ndarray  # (2,) rad, from the residuals
    offsets: np.ndarray  # (L,) each line's offset
    residuals_mm: np.ndarray  # (M,) per midpoint
    condition: float  # of the design, offsets scaled to the tilts


def fit_axis(line, rotations, directions, heights, midpoints, drawn_axis) -> AxisFit:
    """The tool axis in the flange frame from crossing midpoints (see the module docstring).

    `line` (M,) indexes each midpoint's offset o = e . (ball - R t_tip): one per flange
    orientation and line direction, shared by the heights (that sharing is what measures
    the tilt); `heights` are back from the tip along the axis.
    """
    a, predicted = axis_matrix(line, rotations, directions, heights, drawn_axis)
    b = np.asarray(midpoints, dtype=float) - predicted
    n_lines = a.shape[1] - 2
    if a.shape[0] <= a.shape[1]:
        raise ValueError(f"{a.shape[0]} midpoints cannot determine {n_lines} line offsets and two tilts with a check")
    x, *_ = np.linalg.lstsq(a, b, rcond=None)
    residuals = b - a @ x
    tilt = x[n_lines:]
    if float(tilt @ tilt) >= 1.0:
        raise ValueError("the measured tilt is not a direction (the midpoints do not fit an axis)")
    drawn = np.asarray(drawn_axis, dtype=float) / np.linalg.norm(drawn_axis)
    axis = np.sqrt(1.0 - tilt @ tilt) * drawn + tilt @ across(drawn)
    dof = a.shape[0] - a.shape[1]
    cov = np.linalg.pinv(a.T @ a) * float(residuals @ residuals) / dof
    singular = np.linalg.svd(a * _offset_scale(a, n_lines), compute_uv=False)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")
    if condition <= SINGULAR_CONDITION:
        ended = solved(f"axis and {n_lines} line offsets solved by linear least squares over {a.shape[0]} midpoints")
    else:
        ended = degenerate(f"the {a.shape[0]} midpoints do not determine the axis' tilt and the line offsets "
                           f"(condition {condition:.3g})")
    return AxisFit(axis, tilt, np.sqrt(np.diag(cov)[n_lines:]), x[:n_lines], residuals, condition,
                   covariance=cov, **ended)

