"""The tool, the beams and the trigger latency from the edges a crossed-beam light barrier saw.

Model (lengths in mm, base frame unless said otherwise). The tool is a capsule: a core
segment from the centre of its rounded tip, ``front = tip - r_tool * axis``, back along
its axis for ``length - r_tool``, swollen by the tool radius. A beam is a line (a point
and a direction) with a half width; the barrier switches when the capsule's core comes
within ``reach = r_tool + half width`` of the beam's line. So every edge, blocked or
cleared, says one thing: at the instant the tool really crossed, the distance from the
core segment to the beam's line was that beam's reach.

The instant is not the edge's timestamp: the barrier reports late by a latency that is
the same for every edge. The flange pose at the edge's stamp, moved back along the
recorded velocity by the latency, is where the tool was when it crossed. A sweep and
its return cross the same place in opposite directions, so a latency shifts the two
apparently apart by twice the speed times the latency, and nothing else does: the
latency is identified by the data, not assumed.

Unknowns: the tip (3, flange frame), the axis direction (2: its tilt from the drawn
axis), each beam's position across its line (2 per beam; the direction is taken from the
cell file: a turn about a vertical axis of a beam crossed only near one place moves
nothing the sweeps see), each beam's reach (1 per beam), the latency (1). The rotation
of the tool frame about its own axis is not a property of a round tool: it is fixed by
the convention of :func:`cellcal.solvers.geometry.se3.rotvec_from_z`. The tool radius cannot be told from the
beam's half width (only their sum acts); the tip is the drawn radius ahead of the
fitted front centre.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from cellcal.solvers.geometry import se3
from cellcal.solvers.estimation.fit_result import FitResult, from_solver

NULL_RTOL = 1e-7  # singular values of the column-scaled Jacobian below this (relative) are null directions
STEP = {"mm": 1e-4, "rad": 1e-7, "ms": 1e-4}


@dataclass(frozen=True)
class LaserGeometry:
    """What the fit starts from and holds: the drawn tool, the beams as the cell file has them."""

    tool_radius_mm: float
    tool_length_mm: float
    tip_mm: np.ndarray  # (3,) flange frame, the drawing
    axis: np.ndarray  # (3,) unit, flange frame, the drawing (from the flange toward the tip)
    beam_points_mm: np.ndarray  # (K, 3) base frame
    beam_directions: np.ndarray  # (K, 3) unit; held
    reach_mm: np.ndarray  # (K,) tool radius + half beam width, as drawn


@dataclass(frozen=True)
class LaserEdges:
    """One row per edge: the flange at the edge's stamp, its velocity, the beam that switched."""

    flange_rotation: np.ndarray  # (N, 3, 3)
    flange_mm: np.ndarray  # (N, 3)
    velocity_mm_s: np.ndarray  # (N, 3)
    beam: np.ndarray  # (N,) index into the geometry's beams
    move: np.ndarray  # (N,) motion each edge came from (edges of one motion share its repeatability)


@dataclass(frozen=True)
class LaserFit(FitResult):
    """The fitted tool, beams and latency; status, message, success and nfev are least_squares' own,
    covariance that of x (the noise model's, see :func:`fit`)."""

    names: tuple[str, ...]
    units: tuple[str, ...]  # "mm", "rad" or "ms" per parameter
    x: np.ndarray  # every parameter, in its unit (offsets from the geometry for beams, absolute otherwise)
    std: np.ndarray
    tip_mm: np.ndarray
    axis: np.ndarray
    beam_points_mm: np.ndarray  # (K, 3): the fitted point of each beam (direction held)
    reach_mm: np.ndarray
    latency_s: float
    latency_std_s: float
    residuals_mm: np.ndarray  # (N,)
    sigma_mm: np.ndarray  # (N,) expected noise per edge
    condition: float  # of the column-scaled normal equations
    undetermined: tuple[str, ...]  # parameters the data do not determine (null directions)
    tip_std_mm: np.ndarray  # (3,)
    axis_std_deg: float  # of the axis direction (the larger of the two tilts)

    @property
    def tool_frame(self) -> np.ndarray:
        """[x, y, z, rx, ry, rz] (m, rad): origin at the tip, z along the axis, the rotation about
        the axis by convention (:func:`cellcal.solvers.geometry.se3.rotvec_from_z`)."""
        return np.concatenate([self.tip_mm / 1e3, se3.rotvec_from_z(self.axis)])


def perpendicular_pair(direction) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors across `direction`: the first horizontal (z x d, or x when d is
    vertical), the second completing the right-handed set (upward for a horizontal d)."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    first = np.cross([0.0, 0.0, 1.0], d)
    if np.linalg.norm(first) < 1e-9:
        first = np.cross(d, [0.0, 1.0, 0.0])
    first /= np.linalg.norm(first)
    return first, np.cross(d, first)


def axis_pair(axis) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors across the drawn axis along which its tilt is counted: flange x and y
    made perpendicular to it (for an axis along flange z, exactly x and y)."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    first = np.array([1.0, 0.0, 0.0]) - a[0] * a
    if np.linalg.norm(first) < 1e-6:
        first = np.array([0.0, 1.0, 0.0]) - a[1] * a
    first /= np.linalg.norm(first)
    return first, np.cross(a, first)


def segment_line_offset(front, back, point, direction) -> np.ndarray:
    """From each line (point, unit direction) across to the nearest point of its segment front-back."""
    def across(p):
        off = p - point
        return off - np.sum(off * direction, axis=-1, keepdims=True) * direction

    u, w = across(front), across(back)
    v = w - u
    vv = np.sum(v * v, axis=-1)
    t = np.clip(-np.sum(u * v, axis=-1) / np.where(vv < 1e-30, 1.0, vv), 0.0, 1.0)
    t = np.where(vv < 1e-30, 0.0, t)
    return u + t[:, None] * v


def edge_sigma_mm(edges: LaserEdges, geometry: LaserGeometry, repeatability_mm: float,
                  jitter_s: float) -> np.ndarray:
    """Expected noise of each edge across its beam: the arm's repeatability (one axis) and
    the trigger's timing jitter times the speed across the beam."""
    axis = np.einsum("nij,j->ni", edges.flange_rotation, geometry.axis)
    d = geometry.beam_directions[edges.beam]
    normal = np.cross(axis, d)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    across = np.abs(np.sum(edges.velocity_mm_s * normal, axis=1))
    return np.sqrt(repeatability_mm**2 + (across * jitter_s) ** 2)


class _Model:
    """The parameter vector and the edges' residuals (mm) as a function of it."""

    def __init__(self, edges: LaserEdges, geometry: LaserGeometry):
        self.edges, self.g = edges, geometry
        k = len(geometry.beam_points_mm)
        self.e1, self.e2 = axis_pair(geometry.axis)
        self.across = [perpendicular_pair(d) for d in geometry.beam_directions]
        names = ["tip_x_mm", "tip_y_mm", "tip_z_mm", "axis_tilt_x_rad", "axis_tilt_y_rad"]
        units = ["mm", "mm", "mm", "rad", "rad"]
        for i in range(k):
            names += [f"beam{i}_across_mm", f"beam{i}_up_mm"]
            units += ["mm", "mm"]
        names += [f"beam{i}_reach_mm" for i in range(k)] + ["latency_ms"]
        units += ["mm"] * k + ["ms"]
        self.names, self.units = tuple(names), tuple(units)
        self.k = k

    def start(self) -> np.ndarray:
        return np.concatenate([self.g.tip_mm, np.zeros(2), np.zeros(2 * self.k), self.g.reach_mm, [0.0]])

    def unpack(self, x):
        tip = x[:3]
        a = self.g.axis + x[3] * self.e1 + x[4] * self.e2
        a = a / np.linalg.norm(a)
        off = x[5:5 + 2 * self.k].reshape(self.k, 2)
        points = np.array([p + o[0] * m[0] + o[1] * m[1]
                           for p, o, m in zip(self.g.beam_points_mm, off, self.across)])
        reach = x[5 + 2 * self.k:5 + 3 * self.k]
        return tip, a, points, reach, x[-1] / 1e3

    def residuals(self, x) -> np.ndarray:
        return np.linalg.norm(self.offsets(x), axis=1) - self.unpack(x)[3][self.edges.beam]

    def offsets(self, x) -> np.ndarray:
        """(N, 3): from each edge's beam line across to the tool's core at the instant it crossed."""
        tip, a, points, _, latency = self.unpack(x)
        e, r = self.edges, self.g.tool_radius_mm
        flange = e.flange_mm - latency * e.velocity_mm_s
        front = flange + np.einsum("nij,j->ni", e.flange_rotation, tip - r * a)
        back = front - (self.g.tool_length_mm - r) * np.einsum("nij,j->ni", e.flange_rotation, a)
        return segment_line_offset(front, back, points[e.beam], self.g.beam_directions[e.beam])

    def noise_covariance(self, x, repeatability_mm: float, jitter_s: float) -> np.ndarray:
        """Covariance (N, N) of the residuals: a repeatability offset shared by the edges of
        each motion, and each edge's jitter along its motion."""
        e = self.edges
        shift = []
        for j in range(3):
            step = np.zeros(3)
            step[j] = STEP["mm"]
            plus = _Model(LaserEdges(e.flange_rotation, e.flange_mm + step, e.velocity_mm_s, e.beam, e.move), self.g)
            minus = _Model(LaserEdges(e.flange_rotation, e.flange_mm - step, e.velocity_mm_s, e.beam, e.move), self.g)
            shift.append((plus.residuals(x) - minus.residuals(x)) / (2 * STEP["mm"]))
        shift = np.column_stack(shift)  # d residual / d position of the tool, per edge
        same = e.move[:, None] == e.move[None, :]
        timing = np.sum(shift * e.velocity_mm_s, axis=1) * jitter_s
        return repeatability_mm**2 * (shift @ shift.T) * same + np.diag(timing**2)

    def jacobian(self, x) -> np.ndarray:
        """Central differences (the model is cheap and smooth where edges happen)."""
        cols = []
        for j, unit in enumerate(self.units):
            h = STEP[unit]
            xp, xm = x.copy(), x.copy()
            xp[j] += h
            xm[j] -= h
            cols.append((self.residuals(xp) - self.residuals(xm)) / (2 * h))
        return np.column_stack(cols)


def fit(edges: LaserEdges, geometry: LaserGeometry, repeatability_mm: float, jitter_s: float) -> LaserFit:
    """Weighted least squares of every edge's constraint.

    The noise model: each motion ends off by the arm's repeatability (`repeatability_mm`,
    per axis, 1 sigma), one offset shared by every edge of that motion; each edge's stamp
    is off by the trigger's jitter (`jitter_s`, 1 sigma). Edges are weighted by their
    expected noise; the covariance of the estimates is that of this model (the shared
    offsets included), scaled up when the residuals are larger than it expects."""
    model = _Model(edges, geometry)
    sigma = edge_sigma_mm(edges, geometry, repeatability_mm, jitter_s)
    n, p = len(sigma), len(model.names)
    if n <= p:
        raise ValueError(f"{n} edges cannot determine {p} unknowns")
    sol = least_squares(lambda x: model.residuals(x) / sigma, model.start(),
                        jac=lambda x: model.jacobian(x) / sigma[:, None], method="lm", xtol=1e-12, ftol=1e-12)
    x = sol.x
    res = model.residuals(x)
    jw = model.jacobian(x) / sigma[:, None]
    norms = np.linalg.norm(jw, axis=0)
    js = jw / np.where(norms > 0, norms, 1.0)
    _, sv, vt = np.linalg.svd(js, full_matrices=False)
    condition = float((sv[0] / sv[-1]) ** 2) if sv[-1] > 0 else float("inf")
    null = vt[sv < NULL_RTOL * sv[0]]
    undetermined = tuple(name for j, name in enumerate(model.names)
                         if norms[j] == 0 or (len(null) and np.max(np.abs(null[:, j])) > 0.1))
    noise = model.noise_covariance(x, repeatability_mm, jitter_s) / np.outer(sigma, sigma)
    chi2 = float(np.sum((res / sigma) ** 2)) / (n - p)
    try:
        gain = np.linalg.solve(jw.T @ jw, jw.T)
        cov = max(1.0, chi2) * gain @ noise @ gain.T
    except np.linalg.LinAlgError:
        cov = np.full((p, p), np.inf)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    tip, axis, points, reach, latency = model.unpack(x)
    axis_std = float(np.degrees(max(std[3], std[4])))
    return LaserFit(model.names, model.units, x, std, tip, axis, points, reach, latency, float(std[-1]) / 1e3,
                    res, sigma, condition, undetermined, std[:3], axis_std, covariance=cov, **from_solver(sol))


def crossing_offsets(edges: LaserEdges, geometry: LaserGeometry, fit: LaserFit) -> np.ndarray:
    """(N, 3) mm, base frame: from each edge's fitted beam line across to the fitted tool's core
    at the instant the tool crossed (its length is the beam's reach plus the edge's residual)."""
    return _Model(edges, geometry).offsets(fit.x)


# -- geometry the plan is drawn with ----------------------------------------------------------

def crossing_point(points, directions) -> np.ndarray:
    """The point nearest to every line (point, direction) in the least-squares sense: where
    crossed beams cross (the middle of their common perpendicular when they miss)."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for p, d in zip(np.asarray(points, float), np.asarray(directions, float)):
        d = d / np.linalg.norm(d)
        m = np.eye(3) - np.outer(d, d)
        a += m
        b += m @ p
    return np.linalg.lstsq(a, b, rcond=None)[0]


def beam_normals(axis_base, directions) -> np.ndarray:
    """Unit normals (K, 3) of the tool axis and each beam: the direction the distance
    between the two lines is measured along."""
    n = np.cross(np.asarray(axis_base, float), np.asarray(directions, float))
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def sweep_direction(axis_base, directions, steps: int = 180) -> tuple[np.ndarray, float]:
    """The horizontal direction that crosses every beam most squarely for a tool along
    `axis_base`, and the smallest |cosine| it has with a beam's normal."""
    normals = beam_normals(axis_base, directions)
    angles = np.linspace(0.0, np.pi, steps, endpoint=False)
    candidates = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(steps)])
    worst = np.min(np.abs(candidates @ normals.T), axis=1)
    best = int(np.argmax(worst))
    return candidates[best], float(worst[best])
