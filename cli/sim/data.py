"""``cellcal sim-data``: a measurement CSV from the simulated arm with physical effects of hidden
size switched on (data for ``cellcal analyze``). Their true sizes go to a separate truth file,
never into the CSV."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cellcal.cli.common import SEED, UsageError, counted, number, print_progress, whole, writable_file
from cellcal.config.robot_files import load_robot
from cellcal.measurements.writer import write_measurements
from cellcal.sims.physics.physical_arm import CAUSE_IDS, HiddenEffect, PhysicalArm
from cellcal.sims.physics.workspace import full_workspace

# trigger latency needs joint velocities at the triggers, which a static pose campaign has not
MAX_POSES = 100_000  # a campaign 100x larger than any measured (about 2 s to simulate)
SIM_DATA_CAUSES = tuple(c for c in CAUSE_IDS if c != "trigger_latency")


def add_parser(sub) -> None:
    p = sub.add_parser("sim-data", help="write a measurement CSV from the simulated cell, with hidden effects",
                       description="Measure random poses with the simulated arm and tracker, with physical "
                                   "effects of hidden size switched on, and write the measurement CSV "
                                   "(rows in measured order, approach directions implied). The effect's "
                                   "true size goes to a separate truth file, never into the CSV.")
    p.add_argument("--robot", default="ur10e", help="robot model file or shipped name (default ur10e)")
    p.add_argument("--poses", type=whole(1, MAX_POSES), default=300,
                   help=f"random poses to measure, 1 .. {MAX_POSES} (default 300)")
    p.add_argument("--effect", action="append", default=[], metavar="CAUSE[:JOINT]",
                   help="hidden effect, e.g. joint_compliance:2 or thermal_drift (joint 1-based); repeatable; "
                        f"causes: {', '.join(SIM_DATA_CAUSES)}")
    p.add_argument("--rms-mm", type=number(0.0, 100.0, above=True, unit="mm"), default=0.3,
                   help="TCP displacement of each effect, rms, above 0 and at most 100 (default 0.3)")
    p.add_argument("--seed", type=SEED, default=1,
                   help=f"seed of the hidden sizes, poses and noise, 0 .. {SEED.high} (default 1)")
    p.add_argument("-o", "--out", required=True, metavar="OUT.csv",
                   help="measurement CSV to write; the hidden truth goes beside it, to OUT.csv.truth.json")
    p.set_defaults(func=run)


def _hidden_effect(spec: str, rms_mm: float, n_joints: int) -> HiddenEffect:
    """--effect CAUSE[:JOINT], joint 1-based."""
    cause, _, joint = spec.partition(":")
    if cause not in SIM_DATA_CAUSES:
        raise UsageError(f"--effect {spec}: cause must be one of {', '.join(SIM_DATA_CAUSES)}")
    if cause == "thermal_drift":
        if joint:
            raise UsageError(f"--effect {spec}: thermal_drift acts on the whole arm; give no joint")
        return HiddenEffect(cause, None, rms_mm=rms_mm)
    if not joint.isdigit() or not 1 <= int(joint) <= n_joints:
        raise UsageError(f"--effect {spec}: give the joint from 1 to {n_joints}, e.g. {cause}:2")
    return HiddenEffect(cause, int(joint) - 1, rms_mm=rms_mm)


def run(args) -> int:
    writable_file(args.out, "-o")
    writable_file(str(args.out) + ".truth.json", "-o (its truth file)")
    model = load_robot(args.robot)
    effects = [_hidden_effect(spec, args.rms_mm, model.n_joints) for spec in args.effect]
    rng = np.random.default_rng(args.seed)
    arm = PhysicalArm(model, rng, effects)
    campaign = arm.campaign(full_workspace(model, args.poses, rng))
    write_measurements(args.out, q_rad=campaign.obs.q, xyz_mm=campaign.obs.xyz_mm, t_s=campaign.ctx.t_s,
                       temp_c=campaign.ctx.temp_c, comment=f"{model.name}, simulated, seed {args.seed}")
    truth = {e.cause: {"joint": None if e.joint is None else e.joint + 1, "size": arm.hidden_size(e)}
             for e in effects}
    Path(str(args.out) + ".truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    print_progress(f"wrote {args.out} ({counted(args.poses, 'row')}); hidden truth in {args.out}.truth.json")
    return 0
