"""Fixture bench (issue 21, section 3): a two-socket plate against a tracker campaign of as many poses.

A UR10e with the usual hidden geometric errors (up to 0.5 mm and 0.05 deg, ``SimulatedArm``),
repeatability 0.03 mm, seats its target (about 100 mm off the flange) in both sockets of a plate
at ``--placements`` positions around it (``tests/support/point_data.py``). Each socket offers a pool of
``--pool`` random orientations (tilt up to ``--tilt`` from straight down, on each wrist branch of
``--wrists``); of those, ``--per-socket`` are taken at random, and as many by the seat design the
``kinematic-fixture`` routine uses (``solvers/fixtures/fixture_design.py``: D-optimal, points eliminated).
``identify_points`` calibrates on each, with the plate's distance known to ``--sd`` mm, for every
socket spacing of ``--spacing`` (the arm's scale is fixed only by that distance). The same arm is
then calibrated from a tracker campaign of as many poses (D-optimal from the full workspace,
AT960 noise, ``identify``).

Each result is scored against the hidden geometry at 500 random poses over the workspace:
the fixture calibration relative to the plates (its frame put on the true one through the
fitted sockets) and in the best-fitting frame; the tracker calibration and the nominal arm in
their best-fitting frames (their base frames, too, are conventions where the data cannot see
them). Mean distance, mm; the table to stdout, every number to bench/results/fixture-*.json.

    python -m bench.fixture_bench [--seeds 1,2,3,4,5] [--placements 4] [--per-socket 12] [--pool 48]
                                  [--spacing 50,200] [--sd 0.01] [--tilt 45] [--wrists normal,flipped]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if __package__ in (None, ""):
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the plate data generator of the tests
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from support.point_data import plate_placements, seat, workspace_errors  # noqa: E402

from cellcal.config.robot_files import load_robot  # noqa: E402
from cellcal.sims.physics.kinematic_arm import SimulatedArm  # noqa: E402
from cellcal.sims.physics.workspace import full_workspace  # noqa: E402
from cellcal.solvers.fixtures.fixture_design import select_seats  # noqa: E402
from cellcal.solvers.fixtures.fixture_identify import identify_points  # noqa: E402
from cellcal.solvers.fixtures.point_problem import FixtureOptions, PointData  # noqa: E402
from cellcal.solvers.identification.identify import IdentifyOptions, identify  # noqa: E402
from cellcal.solvers.identification.pose_design import select_poses  # noqa: E402


def _fit(model, arm, plate, rows, spacing, sd, poses) -> dict:
    q = plate.q[rows]
    setup, point_id = [plate.setup[i] for i in rows], [plate.point[i] for i in rows]
    keys = list(dict.fromkeys(zip(setup, point_id)))
    index = {k: i for i, k in enumerate(keys)}
    point = np.array([index[k] for k in zip(setup, point_id)])
    true = np.array([plate.true_points[k] for k in keys])
    distances = tuple((index[(s, "hole_0")], index[(s, "hole_1")], spacing, sd) for s in dict.fromkeys(setup))
    data = PointData(q, np.zeros(len(q), int), ("tcp",), point, tuple(keys), np.full((len(q), 3), np.nan), distances)
    res = identify_points(model, data, FixtureOptions(seating_sd_mm=0.03))
    return {"relative_to_plate_mm": float(workspace_errors(arm, res.k, res.offsets[0], poses, res.point_positions,
                                                           true).mean()),
            "best_frame_mm": float(workspace_errors(arm, res.k, res.offsets[0], poses).mean()),
            "held": list(res.held_at_nominal), "noise_rank": res.noise_rank, "structural_rank": res.structural_rank,
            "seconds": res.seconds, "offset": res.offsets[0].tolist()}


def one(seed: int, args) -> dict:
    model = load_robot("ur10e")
    rng = np.random.default_rng(seed)
    arm = SimulatedArm(model, rng, repeatability_mm=0.03, target_offsets=[[0.0, 0.0, 100.0]])
    placements = plate_placements(rng, args.placements)
    poses = full_workspace(model, 500, np.random.default_rng(10_000 + seed))
    row = {"seed": seed, "rows": args.placements * 2 * args.per_socket}
    for spacing in args.spacing:
        plate = seat(arm, placements, args.pool, np.random.default_rng(seed), max_tilt_deg=args.tilt,
                     wrists=tuple(args.wrists), spacing_mm=spacing)
        group = np.array([f"{s}/{p}" for s, p in zip(plate.setup, plate.point)])
        random_rows = np.concatenate([rng.choice(np.flatnonzero(group == g), args.per_socket, replace=False)
                                      for g in dict.fromkeys(group)])
        design = select_seats(model, plate.q, group, args.per_socket, compare={"random": random_rows})
        row[f"spacing{spacing:g}"] = {
            "random": _fit(model, arm, plate, random_rows, spacing, args.sd, poses),
            "design": _fit(model, arm, plate, design.chosen, spacing, args.sd, poses),
            "log_det": {"design": design.log_det, "random": design.log_det_of["random"]}}
        # the nominal arm with the target offset the fixture calibration found (the tool known, the arm not)
        row["nominal_mm"] = float(workspace_errors(arm, model.nominal, row[f"spacing{spacing:g}"]["design"]["offset"],
                                                   poses).mean())
    candidates = full_workspace(model, 600, rng)
    obs = arm.measure(candidates[select_poses(model, candidates, row["rows"]).chosen])
    tracker = identify(model, obs, IdentifyOptions())
    lay = tracker.layout
    tracker_errors = workspace_errors(arm, tracker.x[: lay.n_kin], tracker.x[lay.target(0)], poses)
    row["tracker"] = {"best_frame_mm": float(tracker_errors.mean()), "held": list(tracker.held_at_nominal)}
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="1,2,3,4,5")
    p.add_argument("--placements", type=int, default=4)
    p.add_argument("--per-socket", type=int, default=12)
    p.add_argument("--pool", type=int, default=48, help="candidate orientations per socket the seats are taken from")
    p.add_argument("--spacing", default="50,200", help="the plate's socket spacings to try, mm")
    p.add_argument("--sd", type=float, default=0.01, help="standard deviation of the plate's distance, mm")
    p.add_argument("--tilt", type=float, default=45.0, help="the tool's tilt from straight down, at most (deg)")
    p.add_argument("--wrists", default="normal,flipped", help="wrist branches the seats may use")
    args = p.parse_args(argv)
    args.spacing = [float(s) for s in args.spacing.split(",")]
    args.wrists = args.wrists.split(",")
    rows = []
    for s in args.seeds.split(","):
        rows.append(one(int(s), args))
        print(f"seed {s} done", file=sys.stderr, flush=True)
    print(f"UR10e, two-socket plate at {args.placements} placements x 2 sockets x {args.per_socket} seats "
          f"(of {args.pool} per socket, tilt up to {args.tilt:g} deg, wrists {'+'.join(args.wrists)}); mean error at "
          "500 random workspace poses against the hidden geometry, mm, relative to the plates "
          "(random seats / designed seats)")
    head = f"{'seed':>5}{'rows':>6}{'nominal':>9}" + "".join(f"{f'{sp:g} mm plate':>18}" for sp in args.spacing) \
        + f"{'tracker':>9}{'ratio':>7}"
    print(head)
    for r in rows:
        cells = "".join(f"{r[f'spacing{sp:g}']['random']['relative_to_plate_mm']:>11.3f} /"
                        f"{r[f'spacing{sp:g}']['design']['relative_to_plate_mm']:6.3f}" for sp in args.spacing)
        last = r[f"spacing{args.spacing[-1]:g}"]["design"]["relative_to_plate_mm"]
        print(f"{r['seed']:>5}{r['rows']:>6}{r['nominal_mm']:>9.3f}{cells}{r['tracker']['best_frame_mm']:>9.3f}"
              f"{last / r['tracker']['best_frame_mm']:>7.1f}")
    means = {sp: (np.mean([r[f"spacing{sp:g}"]["random"]["relative_to_plate_mm"] for r in rows]),
                  np.mean([r[f"spacing{sp:g}"]["design"]["relative_to_plate_mm"] for r in rows]))
             for sp in args.spacing}
    tracker = np.mean([r["tracker"]["best_frame_mm"] for r in rows])
    print(f"{'mean':>5}{'':>6}{np.mean([r['nominal_mm'] for r in rows]):>9.3f}"
          + "".join(f"{means[sp][0]:>11.3f} /{means[sp][1]:6.3f}" for sp in args.spacing)
          + f"{tracker:>9.3f}{means[args.spacing[-1]][1] / tracker:>7.1f}")
    last = rows[0][f"spacing{args.spacing[-1]:g}"]["design"]
    print("held (plate, designed seats, seed 1):", ", ".join(last["held"]))
    print("held (tracker):", ", ".join(rows[0]["tracker"]["held"]))
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    name = f"fixture-{args.placements}x{args.per_socket}-tilt{args.tilt:g}-{'+'.join(args.wrists)}.json"
    (out / name).write_text(json.dumps({"args": vars(args), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
