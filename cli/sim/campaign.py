"""A simulated tracker campaign: ``cellcal sim-campaign``.

``sim-campaign`` runs a laser-tracker calibration campaign end to end: plan poses
on the nominal model (D-optimal choice from random candidates), measure them with
the simulated arm and tracker, write the datasets to disk (the seam every solver is
re-run from), identify from the file as ``cellcal identify`` would, validate on
fresh poses, and score the result against the simulation's hidden truth — which
only this report reads, after the solver has finished.
"""
from __future__ import annotations

import json
import time

import numpy as np

from cellcal.config.robot_files import load_robot
from cellcal.measurements.reader import read_measurements
from cellcal.measurements.writer import write_measurements
from cellcal.sims.physics.kinematic_arm import SimulatedArm
from cellcal.sims.physics.physical_arm import HiddenEffect, PhysicalArm
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.identification.identify import REGULARIZE, IdentifyOptions, identify
from cellcal.solvers.identification.measurement_model import Observations, predict
from cellcal.solvers.identification.pose_design import select_poses
from cellcal.cli.sim import iso9283_campaign
from cellcal.cli.common import SEED, UsageError, print_progress, whole, writable_folder
from cellcal.reports.identification import error_stats
from cellcal.solvers.identification.iso9283 import MIN_CYCLES, STANDARD_CYCLES

MAX_POSES = 10_000  # ten times the largest calibration campaign measured in practice
MAX_CANDIDATES = 100_000  # the D-optimal choice holds a Jacobian per candidate


def add_parser(sub):
    p = sub.add_parser("sim-campaign", help="simulated tracker campaign: plan, measure, identify, validate",
                       description="Plan poses on the nominal model (D-optimal choice from random candidates), "
                                   "measure them with the simulated arm and tracker, write the datasets to disk "
                                   "(the seam every solver is re-run from), identify from the file as "
                                   "cellcal identify would, validate on fresh poses, and score the result "
                                   "against the simulation's hidden truth — which only this report reads, "
                                   "after the solver has finished.")
    p.add_argument("--robot", default="ur10e", help="robot model file or shipped name (default ur10e)")
    p.add_argument("--poses", type=whole(10, MAX_POSES), default=60,
                   help=f"calibration poses to measure, 10 .. {MAX_POSES} (default 60)")
    p.add_argument("--candidates", type=whole(10, MAX_CANDIDATES), default=600,
                   help=f"random candidate configurations the poses are chosen from, at least --poses, at most "
                        f"{MAX_CANDIDATES} (default 600)")
    p.add_argument("--validate-poses", type=whole(1, MAX_POSES), default=300,
                   help=f"fresh validation poses, 1 .. {MAX_POSES} (default 300)")
    p.add_argument("--regularize", choices=REGULARIZE, default="cv",
                   help="as for cellcal identify (default cv)")
    p.add_argument("--seed", type=SEED, default=1,
                   help=f"seed of the simulated cell's hidden errors and noise, 0 .. {SEED.high} (default 1)")
    p.add_argument("--out", default="out/sim-campaign", help="folder for cal.csv and val.csv")
    p.add_argument("--iso9283", action="store_true",
                   help="instead: hidden geometric errors and joint-2 compliance, calibrate with analyze, then an "
                        "ISO 9283 cube test before calibration, after, and after compensation, with a report in "
                        "OUT/report")
    p.add_argument("--cycles", type=whole(MIN_CYCLES, 1000), default=STANDARD_CYCLES,
                   help=f"--iso9283: cycles over P1 .. P5, {MIN_CYCLES} .. 1000 (default {STANDARD_CYCLES}, "
                        "as the standard asks)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=run)


def _iso9283(args, out) -> int:
    """The ISO 9283 campaign (``iso9283_campaign``) on an arm with a hidden compliance."""
    model = load_robot(args.robot)
    rng = np.random.default_rng(args.seed)
    arm = PhysicalArm(model, rng, [HiddenEffect("joint_compliance", 1, rms_mm=0.4)], target_offsets=[[0.0, 0.0, 100.0]])
    print_progress(f"simulated {model.name}: hidden geometric errors and joint-2 compliance (0.4 mm rms)")
    return iso9283_campaign.run(args, arm, lambda n, r: full_workspace(model, n, r), out)


def _truth_error(arm: SimulatedArm, layout, x, obs: Observations) -> np.ndarray:
    """Distance of the model's prediction from the true (noise-free) target position."""
    return np.linalg.norm(predict(layout, x, obs) - arm.true_positions(obs.q, obs.target), axis=1)


def run(args) -> int:
    if args.candidates < args.poses:
        raise UsageError(f"--candidates {args.candidates}: fewer than --poses {args.poses}; the poses are chosen "
                         "from the candidates")
    out = writable_folder(args.out, "--out")
    if args.iso9283:
        return _iso9283(args, out)
    t0 = time.perf_counter()
    model = load_robot(args.robot)
    rng = np.random.default_rng(args.seed)
    arm = SimulatedArm(model, rng, target_offsets=[[0.0, 0.0, 100.0]])
    print_progress(f"simulated {model.name}: hidden errors up to 0.5 mm / 0.05 deg, tracker 15 um + 6 um/m, "
                   f"repeatability {arm.repeatability_mm} mm")

    candidates = full_workspace(model, args.candidates, rng)
    design = select_poses(model, candidates, args.poses)
    print_progress(f"planned {args.poses} of {args.candidates} candidate poses (D-optimal, nominal model)")
    cal = arm.measure(candidates[design.chosen])
    val = arm.measure(full_workspace(model, args.validate_poses, rng))

    for name, obs in (("cal.csv", cal), ("val.csv", val)):
        write_measurements(out / name, q_rad=obs.q, xyz_mm=obs.xyz_mm,
                           comment=f"{model.name}, simulated tracker campaign, seed {args.seed}")
    print_progress(f"wrote {out / 'cal.csv'} and {out / 'val.csv'}")

    cal_obs = read_measurements(out / "cal.csv", model.n_joints).observations()
    val_obs = read_measurements(out / "val.csv", model.n_joints).observations()
    result = identify(model, cal_obs, IdentifyOptions(regularize=args.regularize), progress=print_progress)

    floor = arm.oracle_errors(val_obs)
    rows = {
        "validation_measured": {"before": error_stats(result.errors(val_obs, nominal=True)),
                                "after": error_stats(result.errors(val_obs)),
                                "true_model": error_stats(floor)},
        "validation_vs_truth": {"before": error_stats(_truth_error(arm, result.layout, result.x_nominal, val_obs)),
                                "after": error_stats(_truth_error(arm, result.layout, result.x, val_obs))},
    }
    summary = {
        "robot": model.name, "seed": args.seed, "poses": args.poses, "regularize": args.regularize,
        "unidentifiable": list(result.unidentifiable), "held_at_nominal": list(result.held_at_nominal),
        "lambda": result.lam,
        "identify_seconds": result.seconds, "seconds": time.perf_counter() - t0,
        "after_over_floor": rows["validation_measured"]["after"]["mean_mm"] / float(floor.mean()),
        "sim_truth": rows,
        "files": {"cal": str(out / "cal.csv"), "val": str(out / "val.csv")},
    }
    if args.json:
        print(json.dumps(summary))
        return 0
    vm, vt = rows["validation_measured"], rows["validation_vs_truth"]
    print(f"\nSimulated campaign: {model.name}, {args.poses} calibration poses, {args.validate_poses} fresh "
          f"validation poses (seed {args.seed})\n")
    print(f"{'validation, mean / max mm':40s}{'before':>16s}{'after':>16s}")
    print(f"{'  against measured positions':40s}{vm['before']['mean_mm']:8.3f} /{vm['before']['max_mm']:6.3f}"
          f"{vm['after']['mean_mm']:8.3f} /{vm['after']['max_mm']:6.3f}")
    print(f"{'  against hidden true positions':40s}{vt['before']['mean_mm']:8.3f} /{vt['before']['max_mm']:6.3f}"
          f"{vt['after']['mean_mm']:8.3f} /{vt['after']['max_mm']:6.3f}")
    print(f"{'  floor: true model vs measured':40s}{'':16s}{vm['true_model']['mean_mm']:8.3f} /"
          f"{vm['true_model']['max_mm']:6.3f}")
    print(f"\nafter / floor = {summary['after_over_floor']:.3f}; identification took {result.seconds:.2f} s; "
          f"held at nominal (not identifiable, or not trustworthy): {', '.join(result.held_at_nominal) or 'none'}")
    print(f"datasets: {out / 'cal.csv'}, {out / 'val.csv'} -- re-run offline with\n"
          f"  cellcal identify --robot {args.robot} --data {out / 'cal.csv'} --validate {out / 'val.csv'}")
    return 0
