"""Stylus bench: the tcp-stylus fit against the seed's particle swarm on the same contacts.

One run of ``cellcal run tcp-stylus`` on the simulated cell (or a recorded dataset with
``--dataset``) gives the contacts. On them:

* cellcal: the routine's whole solve (coarse start, robust least squares, rank and gates),
  and the fit of the side contacts alone (the data the seed's swarm sees);
* the seed's swarm (Chang et al. 2025, Algorithm 1 with Table 3's settings from
  ``bench/pso.py``: 200 particles, w 0.8, c1 = c2 = 1.49, 500 iterations, stop at 1e-6),
  minimising the seed's fitness, the RMS of (distance to the axis - radius) over the side
  contacts, over Table 2's box round the coarse start: the 6 tool parameters (+-10 mm,
  +-2 deg) and the 3 stylus coordinates (+-5 mm), and with ``--dh`` (default) also the 20
  DH parameters of links 2-6 (+-5 mm, +-2 deg), the seed's 29.

Each is scored against the simulation's hidden truth: the axis line's distance from the true
one at the true tip (mm), the axis angle (deg) and, where end-face touches fix it, the TCP's
full error (mm). Times are CPU seconds of this process, cellcal's the median of repeats.

    python -m bench.stylus_bench [--dataset CSV] [--no-dh] [--iterations N] [--seed N]

Progress to stderr, the table to stdout, every number to bench/results/stylus.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

if __package__ in (None, ""):  # run as a file: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one BLAS thread, as the other benches

import numpy as np

from bench.pso import PSOConfig
from cellcal.config.robot_files import load_robot
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.routines.framework import registry, runner
from cellcal.routines.framework.records import read_dataset
from cellcal.solvers.geometry import se3
from cellcal.solvers.tool_frames import stylus as fitting
from cellcal.solvers.tool_frames import stylus_design as design
from cellcal.solvers.geometry.chain import forward
from cellcal.sims.physics.truth import truth_of_cell

RESULTS = Path(__file__).resolve().parent / "results" / "stylus.json"
SEED_MINUTES = (5.0, 7.0)  # the seed's time for 200 contacts (Section 4.1), hardware not named


def say(msg: str) -> None:
    print(f"[stylus-bench] {msg}", file=sys.stderr, flush=True)


def cpu(fn, repeats=1):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.process_time()
        out = fn()
        times.append(time.process_time() - t0)
    return out, float(np.median(times))


def score(point_mm, direction, tip_mm, truth) -> dict:
    """Errors of an axis line (flange frame) and, if given, of a TCP against the truth."""
    u = np.asarray(direction) / np.linalg.norm(direction)
    true_tip = truth.tool.tcp_m * 1e3
    d = true_tip - np.asarray(point_mm)
    out = {"axis_line_mm": float(np.linalg.norm(d - (d @ u) * u)),
           "axis_deg": float(np.degrees(np.arcsin(min(1.0, np.linalg.norm(np.cross(u, truth.tool.axis))))))}
    out["tcp_mm"] = None if tip_mm is None else float(np.linalg.norm(true_tip - tip_mm))
    return out


def swarm(fitness, lo, hi, centre, cfg: PSOConfig):
    """The seed's Algorithm 1 with ``cfg`` (Table 3): global best, positions clipped to the
    box, velocities left as they are, one particle started at the centre (the coarse start),
    as ``bench.pso.run_pso`` does for point measurements. Returns (best, fitness, iterations)."""
    rng = np.random.default_rng(cfg.seed)
    m, d = cfg.particles, len(lo)
    x = rng.uniform(lo, hi, (m, d))
    x[0] = centre
    v = (rng.uniform(lo, hi, (m, d)) - x) / 2.0
    f = fitness(x)
    pbest, pbest_f = x.copy(), f.copy()
    g, it = int(np.argmin(f)), 0
    while it < cfg.iterations and pbest_f[g] > cfg.threshold_mm:
        r1, r2 = rng.random((m, d)), rng.random((m, d))
        v = cfg.inertia * v + cfg.c1 * r1 * (pbest - x) + cfg.c2 * r2 * (pbest[g] - x)
        x = np.clip(x + v, lo, hi)
        f = fitness(x)
        better = f < pbest_f
        pbest[better], pbest_f[better] = x[better], f[better]
        g, it = int(np.argmin(pbest_f)), it + 1
    return pbest[g], float(pbest_f[g]), it


def seed_fitness(model, q, rotation, position_mm, frame0, stylus0, radius_mm, dh_idx):
    """The seed's RMS fitness for particles z = [tool twist (mm, rad), stylus shift (mm),
    DH parameters of `dh_idx` (nominal + z)]; the tool frame's z is the cylinder's axis."""
    chain = model.chains[model.default_chain]
    r0, p0 = se3.rotvec_to_matrix(frame0[3:]), frame0[:3]

    def fitness(z):
        rot_t = r0 @ se3.rotvec_to_matrix(z[:, 3:6])  # (M, 3, 3)
        point = p0 + np.einsum("ij,mj->mi", r0, z[:, :3])
        axis = rot_t[:, :, 2]
        stylus = stylus0 + z[:, 6:9]
        if len(dh_idx):
            params = np.tile(model.nominal, (len(z), 1))
            params[:, dh_idx] += z[:, 9:]
            rot, pos = forward(chain, params, q)  # (M, N, 3, 3), (M, N, 3)
        else:
            rot, pos = rotation[None], position_mm[None]
        s = np.einsum("mnji,mnj->mni", rot, stylus[:, None, :] - pos)
        w = s - point[:, None, :]
        along = np.einsum("mni,mi->mn", w, axis)
        dist = np.linalg.norm(w - along[..., None] * axis[:, None, :], axis=2)
        return np.sqrt(np.mean((dist - radius_mm) ** 2, axis=1))
    return fitness


def run_swarm(name, model, data, side, start, radius_mm, truth, cfg, with_dh):
    """The seed's swarm over Table 2's box round the coarse start; its best particle scored."""
    frame0 = np.r_[start.line.point_mm, se3.rotvec_from_z(start.line.direction)]
    dh_idx = np.array([model.index(f"{p}{i}") for i in range(2, 7) for p in ("theta", "d", "a", "alpha")]) \
        if with_dh else np.array([], int)
    half = np.r_[[cfg.target_mm] * 3, [np.deg2rad(cfg.base_deg)] * 3, [cfg.base_mm] * 3,
                 np.where(model.param_is_angle[dh_idx], np.deg2rad(cfg.angle_deg), cfg.length_mm)]
    fitness = seed_fitness(model, data.q[side], data.rotation[side], data.position_mm[side], frame0,
                           start.stylus_mm, radius_mm, dh_idx)
    say(f"{name}: {len(half)} unknowns, {cfg.particles} particles, up to {cfg.iterations} iterations")
    (best, rms, iterations), seconds = cpu(lambda: swarm(fitness, -half, half, np.zeros(len(half)), cfg))
    rot_t = se3.rotvec_to_matrix(frame0[3:]) @ se3.rotvec_to_matrix(best[3:6])
    point = frame0[:3] + se3.rotvec_to_matrix(frame0[3:]) @ best[:3]
    at_edge = int(np.sum(np.abs(np.abs(best) - half) < 1e-3 * half))
    return {"method": name, "unknowns": len(half), "cpu_s": seconds, "fitness_rms_mm": rms,
            "iterations": iterations, "at_box_edge": at_edge, **score(point, rot_t[:, 2], None, truth)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", help="a recorded tcp-stylus dataset of the sim cell (else one is measured)")
    ap.add_argument("--cell", default="sim")
    ap.add_argument("--no-dh", dest="dh", action="store_false", help="skip the 29-unknown swarm (the slow one)")
    ap.add_argument("--iterations", type=int, default=PSOConfig.iterations)
    ap.add_argument("--seed", type=int, default=0, help="the swarm's seed")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    cell = load_cell(args.cell)
    model = load_robot(cell.robot)
    if args.dataset:
        dataset = read_dataset(args.dataset, "tcp-stylus", ("kind",))
        truth = truth_of_cell(cell, model)
    else:
        say(f"measuring the contacts on {cell.path} (a minute or two of simulation)")
        prepared = runner.prepare("tcp-stylus", cell)
        with open_drivers(cell) as drivers:
            dataset = runner.measure(prepared, drivers, Path("out/bench"), lambda m: None)
            truth = drivers.world.truth
    options = registry.read_options("tcp-stylus", cell)
    cls = registry.routine_class("tcp-stylus")
    data = design.Recorded.of(model, dataset.stack(*(f"q{i}_rad" for i in range(1, 7))), dataset["kind"],
                              dataset["group"], dataset.stack("dir_x", "dir_y", "dir_z"), dataset["speed_m_s"],
                              float(dataset.meta["cycle_s"]))
    r_s, r_tool = dataset.meta["stylus_radius_m"] * 1e3, dataset.meta["tool_radius_m"] * 1e3
    side = np.isin(data.kind, ("side", "axial"))
    drawn_axis = np.asarray(dataset.meta["tool_axis_drawn"])
    start = fitting.coarse(data.rotation, data.position_mm, data.kind, data.group, data.approach, r_s,
                           r_tool + r_s, drawn_axis)
    rows = []

    result, seconds = cpu(lambda: cls.solve(dataset, cell, options), args.repeats)
    f = result.tool_frame
    rows.append({"method": "cellcal tcp-stylus (whole solve)", "unknowns": len(result.extra["fitted"]),
                 "cpu_s": seconds, "fitness_rms_mm": result.residual_rms_mm, "iterations": None, "at_box_edge": None,
                 **score(f[:3] * 1e3, se3.rotvec_to_matrix(f[3:])[:, 2], f[:3] * 1e3, truth)})
    setup = fitting.Setup(start.line, r_s, r_tool + r_s, False, options.end_shape)
    contacts = fitting.Contacts(data.rotation[side], data.position_mm[side], np.zeros(int(side.sum()), int))
    fit, seconds = cpu(lambda: fitting.fit(contacts, setup, start.stylus_mm), args.repeats)
    rows.append({"method": "cellcal fit, side contacts, seed's unknowns", "unknowns": len(fit.names), "cpu_s": seconds,
                 "fitness_rms_mm": float(np.sqrt(np.mean(fit.residuals_mm ** 2))), "iterations": None,
                 "at_box_edge": None, **score(fit.line.point_mm, fit.line.direction, None, truth)})
    cfg = replace(PSOConfig(), iterations=args.iterations, seed=args.seed)
    rows.append(run_swarm("seed PSO: tool 6 + stylus 3", model, data, side, start, r_tool + r_s, truth, cfg, False))
    if args.dh:
        rows.append(run_swarm("seed PSO: DH 20 + tool 6 + stylus 3", model, data, side, start, r_tool + r_s, truth,
                              cfg, True))
    ours = rows[0]["cpu_s"]
    for row in rows:
        row["cpu_vs_cellcal"] = row["cpu_s"] / ours
    print(f"\n{len(dataset)} contacts ({int(side.sum())} on the mantle) of {cell.path}; the seed reports "
          f"{SEED_MINUTES[0]:g}-{SEED_MINUTES[1]:g} min for 200 contacts\n")
    print(f"{'method':<44} {'unkn':>4} {'CPU s':>8} {'x cellcal':>9} {'fit RMS mm':>10} {'axis mm':>8} "
          f"{'axis deg':>8} {'TCP mm':>7}")
    for r in rows:
        tcp = "-" if r["tcp_mm"] is None else f"{r['tcp_mm']:.4f}"
        print(f"{r['method']:<44} {r['unknowns']:>4} {r['cpu_s']:>8.3f} {r['cpu_vs_cellcal']:>9.1f} "
              f"{r['fitness_rms_mm']:>10.4f} {r['axis_line_mm']:>8.4f} {r['axis_deg']:>8.4f} {tcp:>7}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps({"rows": rows, "contacts": len(dataset), "side_contacts": int(side.sum()),
                                   "dataset": dataset.path, "pso": asdict(cfg), "seed_minutes": SEED_MINUTES,
                                   "python": platform.python_version(), "cpus": os.cpu_count(),
                                   "load_average": os.getloadavg()}, indent=1))
    say(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
