"""Particle-swarm baseline for kinematic identification (Chang et al., "A Stylus-Based
Calibration Method for Robotic Belt Grinding Tools", Appl. Sci. 2025, Tables 2 and 3).

The swarm searches the same unknown vector as ``cellcal.solvers.identification.identify``
(kinematic parameters, instrument -> base transform, target offsets) and scores
each particle by the RMS position error over the calibration poses, the seed's
"root mean square error function". RMS and least squares share their minimiser,
so the swarm and our Levenberg-Marquardt solve the same problem; only the search
differs.

Mapping of the seed's Table 2 onto our unknowns (all boxes centred on the start
that a coarse calibration would give: nominal kinematics, and base and target
offsets from ``initial_base_and_targets``):

* kinematic parameter errors: lengths (d, a) +-5 mm, angles (theta, alpha) +-2 deg;
* target offsets (TCP in the flange frame): the seed's tool position range, +-10 mm;
* base translation (robot base origin in the instrument frame): +-5 mm, the seed's
  range for the other externally located point (the stylus in the base frame);
* base rotation: +-2 deg, the seed's tool orientation range, applied as
  ``R = R_start @ Exp(delta)`` so that it turns the robot about its own base origin
  and does not drag the robot metres across the room as a rotation about the
  instrument origin would; the box then stays meaningful for both halves of the base.

Only kinematic parameters that the nominal Jacobian of these poses can separate
(``structural_mask``) are searched; the rest (e.g. theta1, d1 against the base,
the last link against the target offset) are held at nominal. The seed holds
link 1 fixed for the same reason. Searching exactly redundant directions would
only spend the swarm on flat directions, so this choice favours the baseline.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from cellcal.solvers.estimation import identifiability
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.chain import forward
from cellcal.solvers.identification.identify import initial_base_and_targets, scales
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian

# (particles x poses) frames evaluated per forward() call: large enough to amortise the
# per-element Python loop, small enough that the (M, N, 3, 3) temporaries stay in cache.
_FRAMES_PER_CALL = 8192


@dataclass(frozen=True)
class PSOConfig:
    """Table 3 settings and Table 2 ranges of Chang et al. (2025) (mm, deg)."""

    particles: int = 200
    inertia: float = 0.8
    c1: float = 1.49
    c2: float = 1.49
    iterations: int = 500
    threshold_mm: float = 1e-6  # stop once the best RMS is at or below this (Table 3 epsilon)
    length_mm: float = 5.0
    angle_deg: float = 2.0
    base_mm: float = 5.0
    base_deg: float = 2.0
    target_mm: float = 10.0
    seed: int = 0


@dataclass(frozen=True)
class PSOResult:
    x: np.ndarray  # best full unknown vector in cellcal's layout
    rms_mm: float  # its fitness: RMS position error over the calibration poses
    iterations: int
    evaluations: int  # fitness evaluations (particles x (iterations + 1))
    seconds: float  # wall clock
    cpu_seconds: float  # this process' CPU time: steadier than the wall clock on a shared machine
    history: np.ndarray  # best RMS after initialisation and after each iteration
    searched: tuple[str, ...]  # names of the searched unknowns
    at_bound: int  # searched coordinates of the best particle within 0.1 % of a box edge


def batch_predict(layout: Layout, xs: np.ndarray, obs: Observations) -> np.ndarray:
    """Predicted target positions (M, N, 3) in the instrument frame for M unknown vectors.

    The population counterpart of ``measurement_model.predict``: one ``forward`` call
    per target (and chunk of particles) evaluates every particle at every pose.
    """
    xs = np.atleast_2d(xs)
    m, n = len(xs), len(obs)
    out = np.empty((m, n, 3))
    k = xs[:, : layout.n_kin]
    rb = se3.rotvec_to_matrix(xs[:, layout.base][:, 3:])
    tb = xs[:, layout.base][:, :3]
    for ti, name in enumerate(layout.target_names):
        rows = np.flatnonzero(obs.target == ti)
        if not len(rows):
            continue
        chain = layout.model.chains[layout.model.chain_for(name)]
        off = xs[:, layout.target(ti)]
        step = max(1, _FRAMES_PER_CALL // len(rows))
        for s in range(0, m, step):
            sl = slice(s, s + step)
            rot, org = forward(chain, k[sl], obs.q[rows])
            p = org + np.einsum("mnij,mj->mni", rot, off[sl])
            out[sl, rows] = np.einsum("mij,mnj->mni", rb[sl], p) + tb[sl, None, :]
    return out


def structural_mask(layout: Layout, obs: Observations, x: np.ndarray) -> np.ndarray:
    """Kinematic parameters these poses can separate at x (bool over the n_kin entries).

    The structural (noise-free) step of ``identify``: a property of the nominal model
    and the joint values, not of the measured positions.
    """
    _, j = jacobian(layout, x, obs)
    j = j.reshape(-1, layout.size) * scales(layout, x, obs)
    nuisance = np.zeros(layout.size, bool)
    nuisance[layout.n_kin:] = True
    candidates = ~nuisance
    return identifiability.analyse(j, nuisance, candidates).keep[: layout.n_kin]


class _Encoding:
    """Particle coordinates <-> full unknown vectors, and the Table 2 box."""

    def __init__(self, layout: Layout, x_start: np.ndarray, kin_free: np.ndarray, cfg: PSOConfig):
        self.layout, self.x_start = layout, x_start
        self.kin_idx = np.flatnonzero(kin_free)
        self.r_start = se3.rotvec_to_matrix(x_start[layout.base][3:])
        ang = np.deg2rad(cfg.angle_deg)
        kin_half = np.where(layout.model.param_is_angle[self.kin_idx], ang, cfg.length_mm)
        n_tgt = len(layout.target_names)
        half = np.concatenate([kin_half, np.full(3, cfg.base_mm), np.full(3, np.deg2rad(cfg.base_deg)),
                               np.full(3 * n_tgt, cfg.target_mm)])
        # centre: nominal kinematics (x_start holds them), start base, zero base rotation delta
        centre = np.concatenate([x_start[self.kin_idx], x_start[layout.base][:3], np.zeros(3),
                                 x_start[layout.n_kin + 6:]])
        self.lo, self.hi, self.centre = centre - half, centre + half, centre
        names = layout.names
        self.names = tuple([names[i] for i in self.kin_idx] + list(names[layout.n_kin:]))

    def decode(self, z: np.ndarray) -> np.ndarray:
        lay, nk = self.layout, len(self.kin_idx)
        xs = np.tile(self.x_start, (len(z), 1))
        xs[:, self.kin_idx] = z[:, :nk]
        rot = self.r_start @ se3.rotvec_to_matrix(z[:, nk + 3: nk + 6])
        xs[:, lay.base] = np.concatenate([z[:, nk: nk + 3], se3.matrix_to_rotvec(rot)], axis=1)
        xs[:, lay.n_kin + 6:] = z[:, nk + 6:]
        return xs


def run_pso(layout: Layout, obs: Observations, cfg: PSOConfig = PSOConfig(),
            x_start: np.ndarray | None = None, kin_free: np.ndarray | None = None,
            progress=None) -> PSOResult:
    """Global-best PSO as in Algorithm 1 of Chang et al. (2025); timing covers the start and the mask."""
    t0, c0 = time.perf_counter(), time.process_time()
    say = progress or (lambda msg: None)
    if x_start is None:
        x_start = initial_base_and_targets(layout, obs)
    if kin_free is None:
        kin_free = structural_mask(layout, obs, x_start)
    enc = _Encoding(layout, x_start, kin_free, cfg)
    rng = np.random.default_rng(cfg.seed)
    m, d = cfg.particles, len(enc.lo)

    def fitness(z):
        r = batch_predict(layout, enc.decode(z), obs) - obs.xyz_mm
        return np.sqrt(np.einsum("mni,mni->m", r, r) / len(obs))

    # uniform in the box; one particle at the centre so the swarm starts no worse than
    # the coarse calibration it refines (the seed's ranges are centred on it)
    x = rng.uniform(enc.lo, enc.hi, (m, d))
    x[0] = enc.centre
    v = (rng.uniform(enc.lo, enc.hi, (m, d)) - x) / 2.0  # SPSO-2007 style start, stays in scale
    f = fitness(x)
    pbest, pbest_f = x.copy(), f.copy()
    g = int(np.argmin(f))
    history = [float(f[g])]
    evaluations, it = m, 0
    while it < cfg.iterations and pbest_f[g] > cfg.threshold_mm:
        r1, r2 = rng.random((m, d)), rng.random((m, d))
        v = cfg.inertia * v + cfg.c1 * r1 * (pbest - x) + cfg.c2 * r2 * (pbest[g] - x)
        # the seed clips positions to the Table 2 range and leaves velocities as they are
        x = np.clip(x + v, enc.lo, enc.hi)
        f = fitness(x)
        evaluations += m
        better = f < pbest_f
        pbest[better], pbest_f[better] = x[better], f[better]
        g = int(np.argmin(pbest_f))
        history.append(float(pbest_f[g]))
        it += 1
        if it % 50 == 0 or it == cfg.iterations:
            say(f"PSO iteration {it}/{cfg.iterations}: best RMS {pbest_f[g]:.4f} mm")
    best = pbest[g]
    edge = 1e-3 * (enc.hi - enc.lo)
    at_bound = int(np.sum((best - enc.lo < edge) | (enc.hi - best < edge)))
    return PSOResult(x=enc.decode(best[None])[0], rms_mm=float(pbest_f[g]), iterations=it,
                     evaluations=evaluations, seconds=time.perf_counter() - t0,
                     cpu_seconds=time.process_time() - c0,
                     history=np.array(history), searched=enc.names, at_bound=at_bound)
