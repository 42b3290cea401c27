"""Kinematic identification from fixed points: the cell's own sockets and styli as the instrument.

A row of the point form says that at joint values q the target sat at (a socket) or touched
(a stylus ball) a fixed point whose position nobody measured. With the unknowns

    z = [kinematic parameters k | instrument -> base (only with position rows) | target offsets
         | one position per (setup, point), in the robot's base frame]

the residuals, all in mm (a distance's misfit counted in seating standard deviations, so it
weighs as much as one seating does per its own standard deviation), are

    socket row:    p(q; k, t) - c                       (3 per row)
    stylus row:    |p(q; k, t) - c| - r                  (1 per row: the tip lies on the ball)
    position row:  R_b p(q; k, t) + t_b - m              (3 per row, the tracker model of identify)
    distance:      (|c_a - c_b| - d) * seating_sd / sd   (per setup where both points occur)

The robot's base frame is where the points live: nothing in such data fixes it to the world,
so it is a convention, not a finding. Which kinematic parameters the data can determine is
judged by the same rank analysis the tracker identification uses (``identifiability.analyse``
on the scaled Jacobian, points and target offsets as the nuisance columns): parameters that
only move the base frame (the first joint's height, its zero, ...) are absorbed by the
points and held at nominal, as is every direction below the noise; estimates a person could
not trust after the fit are held as ``identify`` holds them. Dense Jacobians: fixture data
are hundreds or thousands of rows, not the hundreds of thousands a tracker logs.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from cellcal.solvers import identifiability, se3
from cellcal.solvers.fit_result import FitResult, from_solver
from cellcal.solvers.identifiability import HeldParameter
from cellcal.solvers.measurement_model import BASE_NAMES, Layout, Observations, jacobian
from cellcal.solvers.robot_model import KinematicModel

MIN_ROWS_PER_POINT = 3  # three coordinates of an unknown point; fewer rows cannot place it
MAX_FIT_MM = 50.0  # a mean misfit beyond this is wrong data (wrong unit, wrong robot), not an arm


class FixtureDataError(ValueError):
    """Point data no identification can use; the message says what to change."""


@dataclass(frozen=True)
class PointData:
    """Rows of the point form (and optionally measured positions) with their fixture's distances."""

    q: np.ndarray  # (N, nj) rad
    target: np.ndarray  # (N,) index into target_names
    target_names: tuple[str, ...]
    point: np.ndarray  # (N,) index into points, -1 on a row with a measured position
    points: tuple[tuple[str, str], ...]  # (setup, point id) of each unknown point
    xyz_mm: np.ndarray  # (N, 3) measured positions, NaN on point rows
    distances: tuple[tuple[int, int, float, float], ...] = ()  # (point a, point b, mm, sd mm) into points

    def __len__(self) -> int:
        return len(self.q)

    @property
    def is_point(self) -> np.ndarray:
        return self.point >= 0


@dataclass(frozen=True)
class FixtureOptions:
    seating_sd_mm: float = 0.05
    stylus_radius_mm: float | None = None  # None: sockets
    fixed: tuple[str, ...] = ()
    prior_mm: float = 1.0  # directions whose estimate would scatter more than this are held (as identify)
    max_std_mm: float = 2.0
    max_std_deg: float = 0.5
    plausible_mm: float = 10.0
    plausible_deg: float = 2.0


@dataclass(frozen=True)
class Unknowns:
    """Where each unknown lives in z."""

    model: KinematicModel
    n_targets: int
    n_points: int
    with_base: bool

    @property
    def n_kin(self) -> int:
        return self.model.n_params

    @property
    def base(self) -> slice:
        return slice(self.n_kin, self.n_kin + (6 if self.with_base else 0))

    def target(self, i: int) -> slice:
        s = self.base.stop + 3 * i
        return slice(s, s + 3)

    def point(self, i: int) -> slice:
        s = self.base.stop + 3 * self.n_targets + 3 * i
        return slice(s, s + 3)

    @property
    def size(self) -> int:
        return self.base.stop + 3 * (self.n_targets + self.n_points)

    @property
    def points_slice(self) -> slice:
        return slice(self.base.stop + 3 * self.n_targets, self.size)

    def is_angle(self) -> np.ndarray:
        out = np.zeros(self.size, bool)
        out[: self.n_kin] = self.model.param_is_angle
        if self.with_base:
            out[self.base.start + 3: self.base.stop] = True
        return out

    def names(self, target_names, points) -> tuple[str, ...]:
        base = BASE_NAMES if self.with_base else ()
        return (self.model.param_names + base + tuple(f"target.{t}.{c}" for t in target_names for c in "xyz")
                + tuple(f"point.{s}.{p}.{c}" for s, p in points for c in "xyz"))


@dataclass(frozen=True)
class FixtureIdentification(FitResult):
    """What :func:`identify_points` found. z as :class:`Unknowns` orders it (mm, rad)."""

    unknowns: Unknowns
    names: tuple[str, ...]
    z: np.ndarray
    z_nominal: np.ndarray  # nominal kinematics, targets and points (and base) fitted to the data
    free: np.ndarray  # bool over z: estimated
    std: np.ndarray  # standard deviation of each entry of z (0 where held)
    unidentifiable: tuple[str, ...]  # kinematic parameters the rank analysis held (what the data cannot see)
    absorbed: tuple[str, ...]  # of those, the ones the data cannot see at all (structurally)
    held_implausible: tuple[HeldParameter, ...]
    fixed: tuple[str, ...]
    conventions: tuple[str, ...]  # held, in words: never identified
    errors_mm: np.ndarray  # (N,) per row after the fit: distance from its point (or its measured position)
    errors_nominal_mm: np.ndarray  # the same for the nominal kinematics
    distance_misfit_mm: np.ndarray  # (D,) |c_a - c_b| - d per applied distance, after the fit
    noise_mm: float  # residual standard deviation per residual, mm
    structural_rank: int
    noise_rank: int
    condition: float
    seconds: float
    options: FixtureOptions = field(default_factory=FixtureOptions)

    @property
    def k(self) -> np.ndarray:
        return self.z[: self.unknowns.n_kin]

    @property
    def offsets(self) -> np.ndarray:
        return np.stack([self.z[self.unknowns.target(i)] for i in range(self.unknowns.n_targets)])

    @property
    def base(self) -> np.ndarray:
        """Instrument -> base (t mm, rotation vector); zero (the base frame itself) without position rows."""
        return self.z[self.unknowns.base] if self.unknowns.with_base else np.zeros(6)

    @property
    def point_positions(self) -> np.ndarray:
        return self.z[self.unknowns.points_slice].reshape(-1, 3)

    @property
    def held_at_nominal(self) -> tuple[str, ...]:
        names = set(self.unidentifiable) | set(self.fixed) | {h.name for h in self.held_implausible}
        return tuple(n for n in self.unknowns.model.param_names if n in names)

    def tracker_x(self, target_names) -> np.ndarray:
        """The result in the layout of ``measurement_model.Layout`` (kinematics, base, targets)."""
        layout = Layout(self.unknowns.model, tuple(target_names))
        x = layout.initial(self.base, self.offsets)
        x[: layout.n_kin] = self.k
        return x


class _Problem:
    """Residuals (mm) and their dense Jacobian over z for one PointData."""

    def __init__(self, model: KinematicModel, data: PointData, options: FixtureOptions, with_base: bool):
        self.model, self.data, self.options = model, data, options
        self.u = Unknowns(model, len(data.target_names), len(data.points), with_base)
        self.layout = Layout(model, data.target_names)
        self.rows_p = np.flatnonzero(data.is_point)
        self.rows_m = np.flatnonzero(~data.is_point)
        self.contact = options.stylus_radius_mm is not None
        self.per_row = 1 if self.contact else 3
        self.n_res = self.per_row * len(self.rows_p) + 3 * len(self.rows_m) + len(data.distances)

    def _x(self, z, base=True) -> np.ndarray:
        u = self.u
        x = self.layout.initial(z[u.base] if (u.with_base and base) else None,
                                np.stack([z[u.target(i)] for i in range(u.n_targets)]))
        x[: u.n_kin] = z[: u.n_kin]
        return x

    def _obs(self, rows) -> Observations:
        d = self.data
        return Observations(d.q[rows], np.zeros((len(rows), 3)), d.target[rows], d.target_names)

    def evaluate(self, z, with_jac=True):
        """Residuals (n_res,) and d residuals / d z (n_res, size), mm."""
        u, d = self.u, self.data
        res = np.empty(self.n_res)
        jac = np.zeros((self.n_res, u.size)) if with_jac else None
        at = 0
        keep = np.r_[np.arange(u.n_kin), self.layout.n_kin + 6 + np.arange(3 * u.n_targets)]
        zcols = np.r_[np.arange(u.n_kin), u.target(0).start + np.arange(3 * u.n_targets)]
        if len(self.rows_p):
            obs = self._obs(self.rows_p)
            p, jp = jacobian(self.layout, self._x(z, base=False), obs)
            c = z[u.points_slice].reshape(-1, 3)[d.point[self.rows_p]]
            diff = p - c
            n = len(self.rows_p)
            if self.contact:
                dist = np.linalg.norm(diff, axis=1)
                res[at: at + n] = dist - self.options.stylus_radius_mm
                if with_jac:
                    unit = diff / np.maximum(dist, 1e-9)[:, None]
                    jac[at: at + n][:, zcols] = np.einsum("nc,ncx->nx", unit, jp[:, :, keep])
                    cols = u.point(0).start + 3 * d.point[self.rows_p][:, None] + np.arange(3)
                    jac[at + np.arange(n)[:, None], cols] = -unit
            else:
                res[at: at + 3 * n] = diff.ravel()
                if with_jac:
                    jac[at: at + 3 * n][:, zcols] = jp[:, :, keep].reshape(3 * n, -1)
                    cols = u.point(0).start + 3 * d.point[self.rows_p][:, None] + np.arange(3)
                    jac[at + 3 * np.arange(n)[:, None] + np.arange(3), cols] = -1.0
            at += self.per_row * n
        if len(self.rows_m):
            obs = self._obs(self.rows_m)
            p, jm = jacobian(self.layout, self._x(z), obs)
            n = len(self.rows_m)
            res[at: at + 3 * n] = (p - d.xyz_mm[self.rows_m]).ravel()
            if with_jac:
                flat = jm.reshape(3 * n, -1)
                jac[at: at + 3 * n][:, zcols] = flat[:, keep]
                jac[at: at + 3 * n, u.base] = flat[:, self.layout.base]
            at += 3 * n
        pts = z[u.points_slice].reshape(-1, 3)
        for a, b, mm, sd in d.distances:
            w = self.options.seating_sd_mm / sd
            diff = pts[a] - pts[b]
            dist = float(np.linalg.norm(diff))
            res[at] = w * (dist - mm)
            if with_jac:
                unit = diff / max(dist, 1e-9)
                jac[at, u.point(a)] = w * unit
                jac[at, u.point(b)] = -w * unit
            at += 1
        return (res, jac) if with_jac else res

    def row_errors(self, z) -> np.ndarray:
        """Per data row: distance of the target from its point (stylus: from the ball's surface), or
        from its measured position."""
        u, d = self.u, self.data
        out = np.empty(len(d))
        if len(self.rows_p):
            p, _ = jacobian(self.layout, self._x(z, base=False), self._obs(self.rows_p))
            dist = np.linalg.norm(p - z[u.points_slice].reshape(-1, 3)[d.point[self.rows_p]], axis=1)
            out[self.rows_p] = np.abs(dist - self.options.stylus_radius_mm) if self.contact else dist
        if len(self.rows_m):
            p, _ = jacobian(self.layout, self._x(z), self._obs(self.rows_m))
            out[self.rows_m] = np.linalg.norm(p - d.xyz_mm[self.rows_m], axis=1)
        return out

    def distance_misfits(self, z) -> np.ndarray:
        pts = z[self.u.points_slice].reshape(-1, 3)
        return np.array([np.linalg.norm(pts[a] - pts[b]) - mm for a, b, mm, _ in self.data.distances])

    def fit(self, z0, free, tol: float = 1e-12) -> tuple[np.ndarray, object]:
        idx = np.flatnonzero(free)

        def full(v):
            z = z0.copy()
            z[idx] = v
            return z

        def fun(v):
            return self.evaluate(full(v), with_jac=False)

        def jac(v):
            return self.evaluate(full(v))[1][:, idx]

        sol = least_squares(fun, z0[idx], jac=jac, method="lm" if len(idx) <= self.n_res else "trf",
                            x_scale=self.scale()[idx], ftol=tol, xtol=tol, gtol=tol)
        return full(sol.x), sol

    def scale(self) -> np.ndarray:
        """1 for mm, 1/reach for rad: one unit of each unknown moves a target about 1 mm."""
        p, _ = jacobian(self.layout, self._x(self.start(), base=False), self._obs(np.arange(len(self.data))))
        reach = max(float(np.median(np.linalg.norm(p, axis=1))), 1.0)
        return np.where(self.u.is_angle(), 1.0 / reach, 1.0)

    def start(self, k=None, fixed_points=None) -> np.ndarray:
        """Nominal (or given) kinematics; base by a rigid fit of the position rows; targets and points by
        linear least squares (R_i t - c = -o_i per point row: the pivot calibration, all points at once).
        fixed_points: {point index: position} kept as given."""
        u, d = self.u, self.data
        z = np.zeros(u.size)
        z[: u.n_kin] = self.model.nominal if k is None else k
        x = self.layout.initial()
        x[: u.n_kin] = z[: u.n_kin]
        rot_b, t_b = np.eye(3), np.zeros(3)
        if u.with_base and len(self.rows_m):
            zero = self.layout.initial()
            zero[: u.n_kin] = z[: u.n_kin]
            p, _ = jacobian(self.layout, zero, self._obs(self.rows_m))
            if len(self.rows_m) >= 3:
                rot_b, t_b = se3.rigid_fit(p, d.xyz_mm[self.rows_m])
            z[u.base] = np.concatenate([t_b, se3.matrix_to_rotvec(rot_b)])
        rows = np.arange(len(d))
        rot, org = _frames(self.model, self.layout, x, d, rows)
        fixed_points = fixed_points or {}
        unknown_pts = [i for i in range(u.n_points) if i not in fixed_points]
        col_pt = {p: 3 * u.n_targets + 3 * j for j, p in enumerate(unknown_pts)}
        a = np.zeros((3 * len(d), 3 * u.n_targets + 3 * len(unknown_pts)))
        b = np.zeros(3 * len(d))
        for i in rows:
            a[3 * i: 3 * i + 3, 3 * d.target[i]: 3 * d.target[i] + 3] = rot[i]
            if d.point[i] >= 0:
                goal = -org[i]
                if d.point[i] in fixed_points:
                    goal = goal + fixed_points[d.point[i]]
                else:
                    a[3 * i: 3 * i + 3, col_pt[d.point[i]]: col_pt[d.point[i]] + 3] = -np.eye(3)
            else:
                goal = (d.xyz_mm[i] - t_b) @ rot_b - org[i]
            b[3 * i: 3 * i + 3] = goal
        sol = np.linalg.lstsq(a, b, rcond=None)[0]
        for t in range(u.n_targets):
            z[u.target(t)] = sol[3 * t: 3 * t + 3]
        for p in range(u.n_points):
            z[u.point(p)] = fixed_points[p] if p in fixed_points else sol[col_pt[p]: col_pt[p] + 3]
        return z


def _frames(model, layout, x, data, rows):
    from cellcal.solvers.chain import forward
    rot = np.empty((len(rows), 3, 3))
    org = np.empty((len(rows), 3))
    chains: dict[str, list[int]] = {}
    for i, t in enumerate(data.target_names):
        chains.setdefault(model.chain_for(t), []).append(i)
    for chain, targets in chains.items():
        sel = np.flatnonzero(np.isin(data.target[rows], targets))
        if len(sel):
            rot[sel], org[sel] = forward(model.chains[chain], x[: layout.n_kin], data.q[rows][sel])
    return rot, org


def check_points(data: PointData) -> None:
    """Refuse point data that cannot be solved, before any fit (the callers name lines; this is the net)."""
    counts = np.bincount(data.point[data.is_point], minlength=len(data.points))
    few = np.flatnonzero(counts < MIN_ROWS_PER_POINT)
    if few.size:
        s, p = data.points[few[0]]
        raise FixtureDataError(f"point {p!r} of setup {s!r} has {counts[few[0]]} rows; an unknown point needs at "
                               f"least {MIN_ROWS_PER_POINT}")


def identify_points(model: KinematicModel, data: PointData, options: FixtureOptions = FixtureOptions(),
                    progress=None) -> FixtureIdentification:
    """Identify the kinematic parameters the data determine, the target offsets and every point."""
    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    check_points(data)
    unknown = sorted(set(options.fixed) - set(model.param_names))
    if unknown:
        raise ValueError(f"cannot fix unknown parameter(s) {', '.join(unknown)}")
    prob = _Problem(model, data, options, with_base=bool((~data.is_point).any()))
    u = prob.u
    names = u.names(data.target_names, data.points)
    nuisance = np.zeros(u.size, bool)
    nuisance[u.n_kin:] = True
    # before: nominal kinematics, the rest fitted
    before_z, _ = prob.fit(prob.start(), nuisance)
    scale = prob.scale()
    errors_before = prob.row_errors(before_z)
    say(f"nominal model: mean error {errors_before.mean():.3f} mm over {len(data)} rows at "
        f"{len(data.points)} points")
    candidates = np.zeros(u.size, bool)
    candidates[: u.n_kin] = True
    for name in options.fixed:
        candidates[model.index(name)] = False
    _, j0 = prob.evaluate(before_z)
    structural = identifiability.analyse(j0 * scale, nuisance, candidates)
    first_z, _ = prob.fit(before_z, structural.keep)
    r1, j1 = prob.evaluate(first_z)
    dof = max(prob.n_res - int(structural.keep.sum()), 1)
    noise = float(np.sqrt(r1 @ r1 / dof))
    _check_fit(prob.row_errors(first_z))
    noisy = identifiability.analyse(j1 * scale, nuisance, candidates, noise_mm=noise, prior_mm=options.prior_mm)
    say(f"identifiable: {structural.rank} of {int(candidates.sum())} geometric parameters structurally, "
        f"{noisy.rank} above the noise ({noise * 1000:.1f} um)")
    free = noisy.keep.copy()
    z, sol = prob.fit(before_z, free)
    z, sol, free, cov, noise, held = _hold_untrustworthy(prob, before_z, z, sol, free, scale, options, names, say)
    std = np.zeros(u.size)
    std[free] = np.sqrt(np.clip(np.diag(cov), 0, None))
    full_cov = np.zeros((u.size, u.size))
    full_cov[np.ix_(free, free)] = cov
    unident = tuple(n for i, n in enumerate(model.param_names) if candidates[i] and not noisy.keep[i])
    absorbed = tuple(n for i, n in enumerate(model.param_names) if candidates[i] and not structural.keep[i])
    errors = prob.row_errors(z)
    _check_fit(errors)
    _, jf = prob.evaluate(z)
    sv = np.linalg.svd(jf[:, free] * scale[free], compute_uv=False)
    message = str(sol.message).rstrip(".")
    if held:
        message += "; held at nominal after the fit because the data cannot pin them down: " + ", ".join(
            h.name for h in held)
    return FixtureIdentification(
        unknowns=u, names=names, z=z, z_nominal=before_z, free=free, std=std, unidentifiable=unident,
        absorbed=absorbed, held_implausible=tuple(held), fixed=tuple(options.fixed),
        conventions=_conventions(u, absorbed), errors_mm=errors, errors_nominal_mm=errors_before,
        distance_misfit_mm=prob.distance_misfits(z), noise_mm=noise, structural_rank=structural.rank,
        noise_rank=noisy.rank, condition=float(sv[0] / sv[-1]) if len(sv) and sv[-1] > 0 else float("inf"),
        seconds=time.perf_counter() - t0, options=options, covariance=full_cov, **from_solver(sol))


def _conventions(u: Unknowns, absorbed) -> tuple[str, ...]:
    out = []
    if not u.with_base:
        out.append("base frame: the points are given in the robot's base frame as the nominal model places it; "
                   "nothing in fixture data ties it to the world (its position and rotation are a convention)")
    if absorbed:
        out.append(f"{', '.join(absorbed)}: held at nominal; this data cannot see them at all (a move of each is "
                   "taken up exactly by the base frame the points are given in, the target offset or another "
                   "parameter)")
    return tuple(out)


def _check_fit(errors: np.ndarray) -> None:
    mean = float(np.mean(errors))
    if not np.isfinite(mean) or mean > MAX_FIT_MM:
        raise FixtureDataError(
            f"the calibrated model still misses its points by {mean:.4g} mm on average: something is wrong with "
            "the data, not the arm (joint values in the wrong unit, rows under the wrong point or setup, another "
            "robot's file?)")


def _covariance(prob: _Problem, z, free):
    res, jac = prob.evaluate(z)
    j = jac[:, free]
    dof = max(len(res) - int(free.sum()), 1)
    s2 = float(res @ res) / dof
    return np.linalg.pinv(j.T @ j) * s2, float(np.sqrt(s2))


def _hold_untrustworthy(prob, before_z, z, sol, free, scale, options, names, say):
    """Hold at nominal, one at a time, the kinematic estimates beyond the trust bounds of identify."""
    u = prob.u
    free = free.copy()
    is_angle = u.is_angle()
    max_std, plausible = identifiability.trust_bounds(
        is_angle, scale, float(np.percentile(prob.row_errors(before_z), 95)), options.max_std_mm,
        np.deg2rad(options.max_std_deg), options.plausible_mm, np.deg2rad(options.plausible_deg))
    checked = np.zeros(u.size, bool)
    checked[: u.n_kin] = True
    held: list[HeldParameter] = []
    while True:
        cov, noise = _covariance(prob, z, free)
        idx = np.flatnonzero(free)
        std = np.zeros(u.size)
        std[idx] = np.sqrt(np.clip(np.diag(cov), 0, None))
        failing = identifiability.failures(names, is_angle, free & checked, z, before_z, std, max_std, plausible)
        if not failing:
            return z, sol, free, cov, noise, held
        worst = max(failing, key=lambda f: f.ratio)
        f = int(np.searchsorted(idx, worst.index))
        pick = identifiability.to_hold(cov / np.outer(scale[idx], scale[idx]), f, idx < u.n_kin, worst.spread)
        j = int(idx[pick]) if pick is not None else worst.index
        rms = float(np.sqrt(np.mean(prob.row_errors(z) ** 2)))
        free[j] = False
        value = float(z[j])
        z0 = z.copy()
        z0[j] = before_z[j]
        z, sol = prob.fit(z0, free)
        held.append(HeldParameter(name=names[j], reason=worst.reason, value=value, std=float(std[j]),
                                  nominal=float(before_z[j]), is_angle=bool(is_angle[j]), partners=(),
                                  rms_rise_mm=float(np.sqrt(np.mean(prob.row_errors(z) ** 2))) - rms))
        say(f"held {names[j]} at nominal: {worst.reason}")


def refit_points(model: KinematicModel, k, offsets, base, data: PointData, known: dict,
                 options: FixtureOptions) -> tuple[np.ndarray, np.ndarray]:
    """Validation: kinematics k, target offsets and instrument frame base (None: no position rows in the
    calibration) held as calibrated; the points of data not in ``known`` ({point index: position}: those
    the calibration placed) fitted anew with their distances. Returns (per-row errors mm, point positions)."""
    with_base = bool((~data.is_point).any())
    if with_base and base is None:
        raise FixtureDataError("validation rows with measured positions need a calibration that had some (the "
                               "instrument frame is otherwise unknown)")
    prob = _Problem(model, data, options, with_base)
    u = prob.u
    z = prob.start(np.asarray(k, float), known)
    if with_base:
        z[u.base] = base
    for t in range(u.n_targets):
        z[u.target(t)] = offsets[t]
    free = np.zeros(u.size, bool)
    for p in range(u.n_points):
        if p not in known:
            free[u.point(p)] = True
    if free.any():
        z, _ = prob.fit(z, free)
    return prob.row_errors(z), z[u.points_slice].reshape(-1, 3)


PREDICT_TOL = 1e-6  # relative tolerance of the contact prediction's fit of the balls and the target


@dataclass(frozen=True)
class SeatPrediction:
    """What a planned set of seats should give, from the nominal model at the planned joints."""

    condition: float  # of the scaled Jacobian of what the seats determine
    mean_error_mm: float  # predicted 1-sigma position error of the calibrated arm over q_eval (RMS), mm
    rank: int  # kinematic parameters estimated (above the noise)
    estimated: tuple[str, ...]


def predict_seats(model: KinematicModel, data: PointData, options: FixtureOptions, q_eval: np.ndarray,
                  noise_mm: float) -> SeatPrediction:
    """The 1-sigma error a calibration from these seats should leave at the poses q_eval, with seating
    noise noise_mm per axis and the fixture's distances as given: the covariance of the unknowns the
    seats determine (structurally), propagated to the target's position (base frame as the nominal
    model places it, a convention the data do not see)."""
    prob = _Problem(model, data, options, with_base=False)
    u = prob.u
    z = prob.start()
    nuisance = np.zeros(u.size, bool)
    nuisance[u.n_kin:] = True
    if prob.contact:  # the linear start is a socket's: each ball's centre and the target fitted to the contacts
        z, _ = prob.fit(z, nuisance, tol=PREDICT_TOL)  # the normals to 1e-6 are more than a prediction needs
    _, j = prob.evaluate(z)
    scale = prob.scale()
    # what the fit would estimate: the directions above the noise (as identify_points decides)
    keep = identifiability.analyse(j * scale, nuisance, ~nuisance, noise_mm=noise_mm, prior_mm=options.prior_mm).keep
    js = j[:, keep] * scale[keep]
    # rows' noise: seating noise_mm per axis; distance rows carry their own weight already
    u_, s, vt = np.linalg.svd(js, full_matrices=False)
    cov = (vt.T / s**2) @ vt * noise_mm**2 * np.outer(scale[keep], scale[keep])
    je_k = _tip_jacobian(model, u, z, q_eval)[1][:, :, keep]
    var = np.einsum("nip,pq,niq->n", je_k, cov, je_k)
    return SeatPrediction(condition=float(s[0] / s[-1]) if s[-1] > 0 else float("inf"),
                          mean_error_mm=float(np.sqrt(np.mean(var))), rank=int(keep[: u.n_kin].sum()),
                          estimated=tuple(np.array(model.param_names)[keep[: u.n_kin]]))


def _tip_jacobian(model: KinematicModel, u: Unknowns, z: np.ndarray, q_eval) -> tuple[np.ndarray, np.ndarray]:
    """The first target's position (N, 3) at joints q_eval and its derivative over z (N, 3, size), base
    frame as the kinematics place it."""
    layout = Layout(model, ("t",))
    x = layout.initial(base=np.zeros(6), offsets=z[u.target(0)][None])
    x[: u.n_kin] = z[: u.n_kin]
    obs = Observations(np.asarray(q_eval, dtype=float), np.zeros((len(q_eval), 3)), np.zeros(len(q_eval), int),
                       ("t",))
    p, je = jacobian(layout, x, obs)
    zcols = np.r_[np.arange(u.n_kin), layout.n_kin + 6 + np.arange(3)]
    je_z = np.zeros((len(q_eval), 3, u.size))
    je_z[:, :, np.r_[np.arange(u.n_kin), u.target(0).start + np.arange(3)]] = je[:, :, zcols]
    return p, je_z


def random_joints(model: KinematicModel, n: int = 200) -> np.ndarray:
    """n joint rows uniform within the joint limits (at most +-180 deg), the same every call: where a
    calibration's use over the workspace is judged without a hidden truth."""
    limits = model.joint_limits if model.joint_limits is not None else np.tile([-np.pi, np.pi], (model.n_joints, 1))
    return np.random.default_rng(0).uniform(np.maximum(limits[:, 0], -np.pi), np.minimum(limits[:, 1], np.pi),
                                           (n, model.n_joints))


WORTH_RATIO = 0.5  # a calibration is worth using away from its fixtures when its uncertainty there is at most
#                   half the correction it makes (it then at least halves the nominal arm's error)


@dataclass(frozen=True)
class WorkspaceJudgement:
    """What a fixture calibration is worth away from its fixtures, from the data alone."""

    expected_error_mm: float  # 1-sigma error of the calibrated target over the poses (RMS), from the fit's covariance
    correction_mm: float  # RMS of how far the calibration moves the target from the nominal model there
    poses: int

    @property
    def trustworthy(self) -> bool:
        """The calibration's own uncertainty there is at most half the correction it makes: what is left
        of the nominal arm's error is then at most about half of it (the uncertainty is what remains)."""
        return self.expected_error_mm <= WORTH_RATIO * self.correction_mm

    def describe(self) -> str:
        """What the calibration is worth away from the fixture's points, with a warning when little."""
        line = (f"over the workspace ({self.poses} random poses): the calibration moves the target by "
                f"{self.correction_mm:.3f} mm rms, known to {self.expected_error_mm:.3f} mm (1 sigma, from the fit)")
        if not self.trustworthy:
            line += ("\nWARNING: the data leave the arm's geometry uncertain by more than half the correction they "
                     "make: away from the fixture's points the calibrated arm is not much better than nominal (or "
                     "there is little to correct); add a known distance (two sockets or balls), more placements and "
                     "wider turns")
        return line


def judge_workspace(model: KinematicModel, result: FixtureIdentification, q_eval=None) -> WorkspaceJudgement:
    """The fit's covariance carried to the target over random poses (``random_joints``), next to the
    correction the fit makes there: a calibration whose uncertainty exceeds its correction (e.g. the
    arm's scale left to one small ball's radius) makes the arm no better away from the fixture, however
    well it fits and validates at the fixture's points."""
    q_eval = random_joints(model) if q_eval is None else np.asarray(q_eval, dtype=float)
    u = result.unknowns
    p_fit, j = _tip_jacobian(model, u, result.z, q_eval)
    z0 = result.z.copy()
    z0[: u.n_kin] = model.nominal
    p_nom, _ = _tip_jacobian(model, u, z0, q_eval)
    var = np.einsum("nip,pq,niq->n", j, result.covariance, j)
    moved = p_fit - p_nom
    moved = moved - moved.mean(axis=0)  # a shift of everything is the base frame's convention, not a correction
    return WorkspaceJudgement(float(np.sqrt(np.mean(var))), float(np.sqrt(np.mean(np.sum(moved**2, axis=1)))),
                              len(q_eval))
