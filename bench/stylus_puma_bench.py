"""The stylus paper's scenario on a PUMA 560: cellcal's fixture calibration against the paper's swarm.

Chang et al., "A Stylus-Based Calibration Method for Robotic Belt Grinding Tools" (2025) fit 20 DH
errors, the tool and the stylus from contacts alone, by a particle swarm, on a simulated PUMA 560
and report an RMSE below 0.1 mm. Here (issue 21, section 3, second bullet), per seed:

* the arm: ``load_robot("puma560")`` with the usual hidden geometric errors (``SimulatedArm``: up
  to 0.5 mm and 0.05 deg on every DH parameter), a point tool at the paper's ideal tool position
  (125, 7, 41) mm on the flange (a few mm off, as drawn tools are);
* the stylus: a ball of ``--radius`` mm at ``--balls`` positions around the arm (the issue's
  "several stylus positions") plus one more the calibration never sees. Each ball is placed
  where the true tool is at a reference pose (spread in azimuth, wrist clear of its singularity);
  every contact touches a random spot of the ball's upper half with the flange turned up to
  ``--tilt`` deg about each axis from that pose (the paper's +-20 deg), at the joints the true
  arm needs; the tool lands within the repeatability ``--noise`` mm per axis of the spot;
* the data: ``--contacts`` per position, of which ``--holdout`` per fitted position are kept out of
  the fit. With ``--pair MM`` every position holds a second ball MM from the first (a two-ball bar,
  distance known to ``--pair-sd``), the contacts shared between the two: the paper has no known
  distance, and without one the arm's scale is seen only through the ball radius.

On the fitted rows, two methods over the same objective (the contact residual |p - c| - r, the
paper's fitness with a point tool touching a ball instead of a wheel touching a needle):

1. cellcal: ``identify_points`` (rank analysis, least squares, trust gates) on kinematics, tool
   and every ball position (and the pairs' distances); its structural and above-noise rank, what it
   holds, CPU s;
2. the paper's swarm (``bench.stylus_bench.swarm``: Algorithm 1 with Table 3's settings, 200
   particles, w 0.8, c1 = c2 = 1.49, ``--iterations`` (500), stop at 1e-6) minimising the RMS of
   the residual in Table 2's box around the coarse start: the paper's 20 DH errors (+-5 mm,
   +-2 deg), the tool position (+-10 mm: a point tool has no orientation) and each ball (+-5 mm).
   The paper's parameters are Craig's modified DH, (theta_i, d_i, a_(i-1), alpha_(i-1)) of links
   2-6; in the classic DH of ``config/robots/puma560.yaml`` the same 20 are theta2-6, d2-6, a1-5 and
   alpha1-5 (Rx(alpha) Tx(a) commute, so a_(i-1), alpha_(i-1) ride on the previous classic link).
   The coarse start, the box centre, is cellcal's fit of tool and balls with nominal kinematics.

Both are scored alike: the fit RMS (the quantity the paper reports as RMSE), the error on the
held-out contacts of the fitted balls, the mean error on the new ball after refitting only its
position (``refit_points``: kinematics and tool kept, as ``identify --validate``), and the mean
error at ``--poses`` random workspace poses against the hidden geometry, relative to the balls
(the calibrated frame put on the true one through the fitted balls) and in the best-fitting frame.

    python -m bench.stylus_puma_bench [--seeds 1] [--balls 4] [--contacts 50] [--holdout 10]
                                      [--radius 4] [--noise 0.03] [--tilt 20] [--iterations 500]
                                      [--particles 200] [--poses 500] [--pair 0] [--pair-sd 0.01]

Progress to stderr, the table to stdout, every number to bench/results/stylus-puma.json
(stylus-puma-pairMM.json with ``--pair``).
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

ROOT = Path(__file__).resolve().parent.parent
if __package__ in (None, ""):  # run as a file: make the repository root importable
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the workspace scorer of the tests
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one BLAS thread, as the other benches

import numpy as np  # noqa: E402

from support.point_data import workspace_errors  # noqa: E402

from bench.pso import PSOConfig  # noqa: E402
from bench.stylus_bench import swarm  # noqa: E402
from cellcal.config.robot_files import load_robot  # noqa: E402
from cellcal.sims.physics.kinematic_arm import SimulatedArm  # noqa: E402
from cellcal.sims.physics.workspace import full_workspace  # noqa: E402
from cellcal.solvers.geometry import se3  # noqa: E402
from cellcal.solvers.geometry.chain import forward  # noqa: E402
from cellcal.solvers.fixtures.fixture_identify import identify_points, refit_points  # noqa: E402
from cellcal.solvers.fixtures.fixture_predict import predict_seats  # noqa: E402
from cellcal.solvers.fixtures.point_problem import FixtureOptions, PointData  # noqa: E402
from cellcal.solvers.geometry.inverse import inverse_many  # noqa: E402

RESULTS = ROOT / "bench" / "results" / "stylus-puma.json"
PAPER_TOOL_MM = (125.0, 7.0, 41.0)  # the paper's ideal tool translation (Section 3)
PAPER_RMSE_MM = 0.0952  # Tables 10-11 (experiment): RMS contact residual over the calibration contacts
# the paper's 20: (theta_i, d_i, a_(i-1), alpha_(i-1)) of links 2-6, in classic DH names
PAPER_DH = tuple(f"{p}{i}" for i in range(2, 7) for p in ("theta", "d")) + tuple(
    f"{p}{i}" for i in range(1, 6) for p in ("a", "alpha"))


def say(msg: str) -> None:
    print(f"[stylus-puma] {msg}", file=sys.stderr, flush=True)


def _euler(rng, n, tilt_deg):
    """n rotations Rz Ry Rx with each angle uniform in +-tilt_deg (the paper's perturbation)."""
    a = np.deg2rad(rng.uniform(-tilt_deg, tilt_deg, (n, 3)))
    rz = se3.rotvec_to_matrix(np.c_[np.zeros(n), np.zeros(n), a[:, 0]])
    ry = se3.rotvec_to_matrix(np.c_[np.zeros(n), a[:, 1], np.zeros(n)])
    rx = se3.rotvec_to_matrix(np.c_[a[:, 2], np.zeros(n), np.zeros(n)])
    return rz @ ry @ rx


def reference_poses(model, rng, n):
    """n joint rows spread in azimuth, tool in front of the arm, wrist clear of its singularity
    (|q5| 25-80 deg), the tool 300-750 mm from the base axis and within 350 mm of the shoulder's height."""
    lim = model.joint_limits
    chain = model.chains[model.default_chain]
    out = []
    for k in range(n):
        while True:
            q = rng.uniform(lim[:, 0] + 0.1, lim[:, 1] - 0.1, (400, model.n_joints))
            q[:, 0] = np.clip(-np.pi + 2 * np.pi * (k + 0.5) / n + rng.uniform(-0.3, 0.3, 400),
                              lim[0, 0] + 0.3, lim[0, 1] - 0.3)
            q[:, 4] = np.deg2rad(rng.uniform(25, 80, 400)) * rng.choice([-1, 1], 400)
            rot, org = forward(chain, model.nominal, q)
            tip = org + rot @ np.array(PAPER_TOOL_MM)
            radial = np.linalg.norm(tip[:, :2], axis=1)
            ok = (radial > 300) & (radial < 750) & (np.abs(tip[:, 2]) < 350)
            # margins so that +-tilt about each axis stays inside the joint limits
            ok &= np.all((q[:, 1:] > lim[1:, 0] + 0.5) & (q[:, 1:] < lim[1:, 1] - 0.5), axis=1)
            if ok.any():
                out.append(q[np.flatnonzero(ok)[0]])
                break
    return np.array(out)


def _touch(true_model, tool_m, centre, n, q_seed, rot_ref, rng, radius_mm, noise_mm, tilt_deg):
    """n joint rows of the true arm whose tool touches a random spot of the upper half of the ball at
    centre (plus the repeatability, per axis), the flange turned up to tilt_deg about each axis from
    rot_ref, on q_seed's wrist branch and within the joint limits."""
    lim = true_model.joint_limits
    got = np.empty((0, true_model.n_joints))
    for _ in range(20):
        m = 2 * n
        normal = rng.normal(size=(m, 3))
        normal[:, 2] = np.abs(normal[:, 2])
        spot = centre + radius_mm * normal / np.linalg.norm(normal, axis=1)[:, None]
        goal = spot + rng.normal(scale=noise_mm, size=(m, 3))
        goal_rot = rot_ref @ _euler(rng, m, tilt_deg)
        q = inverse_many(true_model, np.c_[goal / 1000.0, se3.matrix_to_rotvec(goal_rot)], q_seed, tool_m)
        ok = np.isfinite(q).all(axis=1)
        ok[ok] &= np.all((q[ok] >= lim[:, 0]) & (q[ok] <= lim[:, 1]), axis=1)
        ok[ok] &= np.sign(q[ok, 4]) == np.sign(q_seed[4])  # the reference's wrist branch
        got = np.concatenate([got, q[ok]])[:n]
        if len(got) == n:
            return got
    raise RuntimeError(f"ball at {np.round(centre, 1)}: only {len(got)} of {n} contacts reachable")


def contacts(arm, q_ref, per_position, rng, radius_mm, noise_mm, tilt_deg, pair_mm=0.0):
    """Contacts of the true arm's tool with the stylus at each reference pose. The (first) ball's
    centre lies radius_mm below where the true tool is at the reference; with pair_mm a second ball
    sits pair_mm from it, horizontally in a random direction (a two-ball bar), and the position's
    contacts are shared between the two. Returns (q (R, nj), ball index (R,), position index (R,),
    true ball centres (positions x balls per position, 3)), balls numbered position-major."""
    model, lay = arm.model, arm.truth.layout
    true_model = replace(model, nominal=arm.truth.x[: lay.n_kin])  # the hidden geometry: simulation only
    tool_m = np.r_[arm.truth.x[lay.target(0)] / 1000.0, 0.0, 0.0, 0.0]
    rot, org = forward(model.chains[model.default_chain], true_model.nominal, q_ref)
    first = org + rot @ arm.truth.x[lay.target(0)] - [0.0, 0.0, radius_mm]
    per = 2 if pair_mm else 1
    qs, ball, position, centres = [], [], [], []
    for b in range(len(q_ref)):
        for j in range(per):
            n = per_position * (j + 1) // per - per_position * j // per
            for attempt in range(10 if j else 1):  # the second ball: another direction if out of reach
                turn = rng.uniform(0, 2 * np.pi)
                c = first[b] + j * pair_mm * np.array([np.cos(turn), np.sin(turn), 0.0])
                try:
                    got = _touch(true_model, tool_m, c, n, q_ref[b], rot[b], rng, radius_mm, noise_mm, tilt_deg)
                    break
                except RuntimeError:
                    if attempt == (9 if j else 0):
                        raise
            qs.append(got)
            ball += [len(centres)] * n
            position += [b] * n
            centres.append(c)
    return np.concatenate(qs), np.array(ball), np.array(position), np.array(centres)


def point_data(q, ball, per, pair_mm, pair_sd):
    """PointData of contact rows: each stylus position its own setup with its one or two balls (and,
    with two, their distance pair_mm +- pair_sd)."""
    used = sorted(set(ball.tolist()))
    index = {g: i for i, g in enumerate(used)}
    names = tuple((f"stylus_{g // per}", f"ball_{g % per}") for g in used)
    distances = tuple((index[g], index[g + 1], pair_mm, pair_sd) for g in used if g % per == 0 and g + 1 in index) \
        if per == 2 else ()
    return PointData(q, np.zeros(len(q), int), ("tcp",), np.array([index[g] for g in ball]), names,
                     np.full((len(q), 3), np.nan), distances)


def residuals(model, k, tool, balls, q, ball_index, radius_mm):
    """Contact residuals |p - c| - r (mm) of one model."""
    rot, org = forward(model.chains[model.default_chain], np.asarray(k), q)
    return np.linalg.norm(org + rot @ tool - balls[ball_index], axis=1) - radius_mm


def score(model, arm, k, tool, balls, sets, options, poses, true_balls, pair) -> dict:
    """The same scores for any calibration (kinematics k, tool, fitted ball centres)."""
    fit_q, fit_b, out_q, out_b, new_q, new_b = sets
    r = options.stylus_radius_mm
    train = residuals(model, k, tool, balls, fit_q, fit_b, r)
    held = residuals(model, k, tool, balls, out_q, out_b, r)
    new_err, _ = refit_points(model, k, tool[None], None, point_data(new_q, new_b, *pair), {}, options)
    return {"fit_rms_mm": float(np.sqrt(np.mean(train ** 2))),
            "heldout_contacts_rms_mm": float(np.sqrt(np.mean(held ** 2))),
            "heldout_contacts_mean_mm": float(np.mean(np.abs(held))),
            "new_ball_mean_mm": float(np.mean(new_err)),
            "workspace_rel_balls_mm": float(workspace_errors(arm, k, tool, poses, balls, true_balls).mean()),
            "workspace_best_frame_mm": float(workspace_errors(arm, k, tool, poses).mean())}


def paper_swarm(model, start_k, start_tool, start_balls, q, ball_index, radius_mm, cfg, distances=(), weight=1.0):
    """The paper's swarm over its 20 DH errors, the tool position and each ball, in Table 2's box
    around the coarse start; with distances (a, b, mm) between balls, their misfits (times weight, as
    identify_points weighs them) join the contact residuals in the RMS. Returns (k, tool, balls,
    fitness, iterations, at_box_edge)."""
    chain = model.chains[model.default_chain]
    dh = np.array([model.index(n) for n in PAPER_DH])
    nb = len(start_balls)
    half = np.r_[np.where(model.param_is_angle[dh], np.deg2rad(cfg.angle_deg), cfg.length_mm),
                 [cfg.target_mm] * 3, [cfg.base_mm] * 3 * nb]
    pairs = np.array([(a, b) for a, b, *_ in distances], int).reshape(-1, 2)
    lengths = np.array([mm for _, _, mm, *_ in distances])

    def decode(z):
        k = np.tile(start_k, (len(z), 1))
        k[:, dh] += z[:, : len(dh)]
        tool = start_tool + z[:, len(dh): len(dh) + 3]
        balls = start_balls + z[:, len(dh) + 3:].reshape(len(z), nb, 3)
        return k, tool, balls

    def fitness(z):
        k, tool, balls = decode(z)
        rot, org = forward(chain, k, q)  # (M, N, 3, 3), (M, N, 3)
        p = org + np.einsum("mnij,mj->mni", rot, tool)
        d = np.linalg.norm(p - balls[:, ball_index], axis=2) - radius_mm
        sq = np.sum(d ** 2, axis=1)
        if len(pairs):
            dd = weight * (np.linalg.norm(balls[:, pairs[:, 0]] - balls[:, pairs[:, 1]], axis=2) - lengths)
            sq = sq + np.sum(dd ** 2, axis=1)
        return np.sqrt(sq / (len(q) + len(pairs)))

    best, f, iterations = swarm(fitness, -half, half, np.zeros(len(half)), cfg)
    k, tool, balls = decode(best[None])
    at_edge = int(np.sum(np.abs(np.abs(best) - half) < 1e-3 * half))
    return k[0], tool[0], balls[0], f, iterations, at_edge


def one(seed: int, args) -> dict:
    model = load_robot("puma560")
    rng = np.random.default_rng(seed)
    arm = SimulatedArm(model, rng, repeatability_mm=args.noise, target_offsets=[PAPER_TOOL_MM])
    q_ref = reference_poses(model, rng, args.balls + 1)
    q, ball, position, true_centres = contacts(arm, q_ref, args.contacts, rng, args.radius, args.noise, args.tilt,
                                               args.pair)
    per = 2 if args.pair else 1
    pair = (per, args.pair, args.pair_sd)
    nb = args.balls  # the last position is the one the calibration never sees
    held = np.zeros(len(q), bool)
    for b in range(nb):
        held[rng.choice(np.flatnonzero(position == b), args.holdout, replace=False)] = True
    new = position == nb
    fit, out = ~held & ~new, held
    sets = (q[fit], ball[fit], q[out], ball[out], q[new], ball[new])
    options = FixtureOptions(seating_sd_mm=args.noise, stylus_radius_mm=args.radius)
    poses = full_workspace(model, args.poses, np.random.default_rng(10_000 + seed))
    true_balls = true_centres[: nb * per]
    row = {"seed": seed, "fit_rows": int(fit.sum()), "heldout_rows": int(out.sum()),
           "new_position_rows": int(new.sum()), "ball_centres_mm": true_centres.round(1).tolist()}

    data = point_data(q[fit], ball[fit], *pair)
    c0 = time.process_time()
    res = identify_points(model, data, options)
    cpu_cellcal = time.process_time() - c0
    u = res.unknowns
    start_tool = res.z_nominal[u.target(0)]
    start_balls = res.z_nominal[u.points_slice].reshape(-1, 3)
    row["nominal"] = score(model, arm, model.nominal, start_tool, start_balls, sets, options, poses, true_balls, pair)
    row["cellcal"] = {"cpu_s": cpu_cellcal, "unknowns": int(res.free.sum()),
                      "candidates": model.n_params, "structural_rank": res.structural_rank,
                      "noise_rank": res.noise_rank, "held": list(res.held_at_nominal), "absorbed": list(res.absorbed),
                      "conventions": list(res.conventions), "noise_mm": res.noise_mm,
                      # what cellcal itself expects at those poses from these contacts (no truth involved)
                      "predicted_ws_1sigma_mm": predict_seats(model, data, options, poses, args.noise).mean_error_mm,
                      **score(model, arm, res.k, res.offsets[0], res.point_positions, sets, options, poses,
                              true_balls, pair)}
    say(f"seed {seed}: cellcal {cpu_cellcal:.2f} CPU s, rank {res.structural_rank} structural / {res.noise_rank} "
        f"above noise of {model.n_params}; swarm: {len(PAPER_DH) + 3 + 3 * nb * per} unknowns, {args.particles} "
        f"particles, up to {args.iterations} iterations")
    cfg = replace(cfg_of(args), seed=seed)
    c0 = time.process_time()
    k, tool, balls, f, iterations, at_edge = paper_swarm(model, model.nominal, start_tool, start_balls, q[fit],
                                                         data.point, args.radius, cfg, data.distances,
                                                         args.noise / args.pair_sd)
    cpu_swarm = time.process_time() - c0
    row["swarm"] = {"cpu_s": cpu_swarm, "unknowns": len(PAPER_DH) + 3 + 3 * nb * per, "iterations": iterations,
                    "fitness_mm": f, "at_box_edge": at_edge,
                    **score(model, arm, k, tool, balls, sets, options, poses, true_balls, pair)}
    say(f"seed {seed}: swarm {cpu_swarm:.1f} CPU s, fitness {f:.4f} mm")
    return row


COLUMNS = (("fit_rms_mm", "fit RMS"), ("heldout_contacts_rms_mm", "held-out RMS"),
           ("new_ball_mean_mm", "new ball"), ("workspace_rel_balls_mm", "ws/balls"),
           ("workspace_best_frame_mm", "ws/best"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1", help="comma-separated seeds (one simulated arm and data set each)")
    ap.add_argument("--balls", type=int, default=4, help="stylus positions in the fit (one more is held out)")
    ap.add_argument("--contacts", type=int, default=50, help="contacts per stylus position")
    ap.add_argument("--holdout", type=int, default=10, help="contacts per fitted position kept out of the fit")
    ap.add_argument("--radius", type=float, default=4.0, help="stylus ball radius (+ tool tip radius), mm")
    ap.add_argument("--noise", type=float, default=0.03, help="contact repeatability per axis, mm (1 sigma)")
    ap.add_argument("--tilt", type=float, default=20.0, help="flange turn about each axis, at most (deg)")
    ap.add_argument("--iterations", type=int, default=PSOConfig.iterations)
    ap.add_argument("--particles", type=int, default=PSOConfig.particles)
    ap.add_argument("--poses", type=int, default=500, help="random workspace poses for the hidden-truth score")
    ap.add_argument("--pair", type=float, default=0.0,
                    help="mm: a second ball this far from the first at every position, distance known (default 0: "
                         "one ball, as the paper's one needle)")
    ap.add_argument("--pair-sd", type=float, default=0.01, help="standard deviation of --pair, mm")
    args = ap.parse_args(argv)
    per = 2 if args.pair else 1
    if not 0 <= args.holdout <= args.contacts - 3 * per:
        ap.error("--holdout must leave at least 3 contacts per ball in the fit")
    rows = [one(int(s), args) for s in args.seeds.split(",")]
    fit = args.balls * (args.contacts - args.holdout)
    stylus = f"two balls {args.pair:g} +- {args.pair_sd:g} mm apart" if args.pair else "one ball"
    print(f"\nPUMA 560, hidden errors up to 0.5 mm / 0.05 deg, tool {PAPER_TOOL_MM} mm, stylus: {stylus}, r = "
          f"{args.radius:g} mm, at {args.balls} positions x {args.contacts - args.holdout} contacts in the fit "
          f"({fit} rows), {args.holdout} per position held out, 1 new position x {args.contacts}; flange "
          f"+-{args.tilt:g} deg per axis, noise {args.noise:g} mm per axis; swarm {args.particles} particles, "
          f"up to {args.iterations} iterations.\nErrors in mm: fit RMS and held-out RMS of the contact residual, "
          f"new ball = mean after refitting its position only, ws = mean at {args.poses} random workspace poses "
          "against the hidden geometry (relative to the balls / best frame).\n")
    print(f"{'seed':>4} {'method':<16} {'unkn':>4} {'rank':>7} {'CPU s':>8}" + "".join(f" {h:>12}" for _, h in COLUMNS))
    for r in rows:
        for name in ("nominal", "cellcal", "swarm"):
            m = r[name]
            rank = f"{m['structural_rank']}/{m['noise_rank']}" if name == "cellcal" else "-"
            unkn = m.get("unknowns", "-")
            cpu = f"{m['cpu_s']:.2f}" if "cpu_s" in m else "-"
            print(f"{r['seed']:>4} {name:<16} {unkn:>4} {rank:>7} {cpu:>8}"
                  + "".join(f" {m[key]:>12.4f}" for key, _ in COLUMNS))
        print(f"{'':>4} {'swarm / cellcal':<16} {'':>4} {'':>7} {r['swarm']['cpu_s'] / r['cellcal']['cpu_s']:>8.0f}"
              + "".join(f" {r['swarm'][key] / r['cellcal'][key]:>12.1f}" for key, _ in COLUMNS))
    if len(rows) > 1:
        for name in ("nominal", "cellcal", "swarm"):
            mean = {key: np.mean([r[name][key] for r in rows]) for key, _ in COLUMNS}
            cpu = f"{np.mean([r[name]['cpu_s'] for r in rows]):.2f}" if name != "nominal" else "-"
            print(f"{'mean':>4} {name:<16} {'':>4} {'':>7} {cpu:>8}"
                  + "".join(f" {mean[key]:>12.4f}" for key, _ in COLUMNS))
    print("cellcal's own 1-sigma prediction of its workspace error from the contacts (predict_seats): "
          + ", ".join(f"{r['cellcal']['predicted_ws_1sigma_mm']:.3f}" for r in rows) + " mm")
    c = rows[0]["cellcal"]
    print(f"\nrank: {c['structural_rank']} of {c['candidates']} DH parameters structurally, {c['noise_rank']} above "
          f"the noise (seed {rows[0]['seed']}); held at nominal: {', '.join(c['held'])}")
    for conv in c["conventions"]:
        print(f"convention: {conv}")
    print(f"the paper reports RMSE {PAPER_RMSE_MM} mm (< 0.1 mm): the RMS contact residual over its own calibration "
          "contacts, the 'fit RMS' column, not an error on poses outside the fit")
    results = RESULTS.with_name(f"stylus-puma-pair{args.pair:g}.json") if args.pair else RESULTS
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text(json.dumps({"args": vars(args), "rows": rows, "pso": asdict(cfg_of(args)),
                                   "paper_dh": PAPER_DH, "paper_rmse_mm": PAPER_RMSE_MM,
                                   "python": platform.python_version(), "cpus": os.cpu_count(),
                                   "load_average": os.getloadavg()}, indent=1))
    say(f"wrote {results}")
    return 0


def cfg_of(args) -> PSOConfig:
    return replace(PSOConfig(), iterations=args.iterations, particles=args.particles)


if __name__ == "__main__":
    sys.exit(main())
