"""Fixture bench (issue 21, section 3): a two-socket plate against a tracker campaign of as many poses.

A UR10e with the usual hidden geometric errors (up to 0.5 mm and 0.05 deg, ``SimulatedArm``),
repeatability 0.03 mm, seats its target (about 100 mm off the flange) in both sockets of a plate
(50 mm apart) at ``--placements`` positions around it, ``--per-socket`` orientations each
(``tests/point_data.py``). ``identify_points`` calibrates on them with the plate's distance
known to ``--sd`` mm (each value given is a run). The same arm is then calibrated from a tracker
campaign of as many poses (D-optimal from the full workspace, AT960 noise, ``identify``).

Each result is scored against the hidden geometry at 500 random poses over the workspace:
the fixture calibration relative to the plates (its frame put on the true one through the
fitted sockets) and in the best-fitting frame; the tracker calibration and the nominal arm in
their best-fitting frames (their base frames, too, are conventions where the data cannot see
them). Mean distance, mm; the table to stdout, every number to bench/results/fixture-*.json.

    python -m bench.fixture_bench [--seeds 1,2,3] [--placements 4] [--per-socket 12] [--sd 0.1,0.01] [--tilt 35]
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

from point_data import plate_placements, seat, workspace_errors  # noqa: E402

from cellcal.config.robot_files import load_robot  # noqa: E402
from cellcal.sims.physics.kinematic_arm import SimulatedArm  # noqa: E402
from cellcal.sims.physics.workspace import full_workspace  # noqa: E402
from cellcal.solvers.fixture_identify import FixtureOptions, PointData, identify_points  # noqa: E402
from cellcal.solvers.identify import IdentifyOptions, identify  # noqa: E402
from cellcal.solvers.pose_design import select_poses  # noqa: E402


def one(seed: int, placements: int, per_socket: int, sds, tilt_deg: float) -> dict:
    model = load_robot("ur10e")
    rng = np.random.default_rng(seed)
    arm = SimulatedArm(model, rng, repeatability_mm=0.03, target_offsets=[[0.0, 0.0, 100.0]])
    plate = seat(arm, plate_placements(rng, placements), per_socket, rng, max_tilt_deg=tilt_deg)
    keys = list(dict.fromkeys(zip(plate.setup, plate.point)))
    index = {k: i for i, k in enumerate(keys)}
    point = np.array([index[k] for k in zip(plate.setup, plate.point)])
    true = np.array([plate.true_points[k] for k in keys])
    poses = full_workspace(model, 500, np.random.default_rng(10_000 + seed))
    row = {"seed": seed, "rows": len(plate.q)}
    for sd in sds:
        setups = list(dict.fromkeys(plate.setup))
        distances = tuple((index[(s, "hole_0")], index[(s, "hole_1")], 50.0, sd) for s in setups)
        data = PointData(plate.q, np.zeros(len(plate.q), int), ("tcp",), point, tuple(keys),
                         np.full((len(plate.q), 3), np.nan), distances)
        res = identify_points(model, data, FixtureOptions(seating_sd_mm=0.03))
        row[f"fixture_sd{sd}"] = {
            "relative_to_plate_mm": float(workspace_errors(arm, res.k, res.offsets[0], poses, res.point_positions,
                                                           true).mean()),
            "best_frame_mm": float(workspace_errors(arm, res.k, res.offsets[0], poses).mean()),
            "held": list(res.held_at_nominal), "seconds": res.seconds}
        row["nominal_mm"] = float(workspace_errors(arm, model.nominal, res.offsets[0], poses).mean())
    candidates = full_workspace(model, 600, rng)
    obs = arm.measure(candidates[select_poses(model, candidates, len(plate.q)).chosen])
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
    p.add_argument("--sd", default="0.1,0.01", help="standard deviations of the plate's distance, mm")
    p.add_argument("--tilt", type=float, default=35.0, help="the tool's tilt from straight down, at most (deg)")
    args = p.parse_args(argv)
    sds = [float(s) for s in args.sd.split(",")]
    rows = [one(int(s), args.placements, args.per_socket, sds, args.tilt) for s in args.seeds.split(",")]
    head = f"{'seed':>5}{'rows':>6}{'nominal':>9}" + "".join(f"{'plate sd ' + str(sd):>22}" for sd in sds) \
        + f"{'tracker':>9}{'ratio':>7}"
    print(f"UR10e, two-socket plate at {args.placements} placements x 2 sockets x {args.per_socket} (tilt up to "
          f"{args.tilt:g} deg); mean error at "
          "500 random workspace poses, mm (plate: relative to the plates / best frame)")
    print(head)
    for r in rows:
        cells = "".join(f"{r[f'fixture_sd{sd}']['relative_to_plate_mm']:>13.3f} /"
                        f"{r[f'fixture_sd{sd}']['best_frame_mm']:6.3f}" for sd in sds)
        ratio = r[f"fixture_sd{sds[-1]}"]["relative_to_plate_mm"] / r["tracker"]["best_frame_mm"]
        print(f"{r['seed']:>5}{r['rows']:>6}{r['nominal_mm']:>9.3f}{cells}{r['tracker']['best_frame_mm']:>9.3f}"
              f"{ratio:>7.1f}")
    print("held (plate):", ", ".join(rows[0][f"fixture_sd{sds[-1]}"]["held"]))
    print("held (tracker):", ", ".join(rows[0]["tracker"]["held"]))
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    name = f"fixture-{args.placements}x{args.per_socket}-tilt{args.tilt:g}.json"
    (out / name).write_text(json.dumps({"args": vars(args), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
