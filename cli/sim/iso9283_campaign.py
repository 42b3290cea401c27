"""``cellcal sim-campaign --iso9283``: an ISO 9283 test before calibration, after, and after compensation.

On the simulated cell (hidden geometric errors and a hidden joint-2 compliance), end to end
through files as a cell integrator would work:

1. a tracker calibration campaign (``cal.csv``) and ``cellcal analyze`` on it, written as
   ``calibrated.yaml``; the nominal geometry with its own fitted instrument frame and
   target offset as ``nominal.yaml`` (what a cell knows before calibration);
2. the ISO cube (clause 6.8) in front of the robot, tool pointing down, P1 .. P5 visited in
   order for ``--cycles`` cycles: driven with the controller's nominal inverse
   (``iso_nominal.csv``), and driven with joints from ``compensate`` (``iso_compensated.csv``);
3. the three cases side by side: before calibration (nominal data, nominal model), after
   calibration (the same data read through the calibrated model: what it says the robot
   reaches), after compensation (compensated data, calibrated model: the points asked for).

The simulation's objects come in as arguments (only ``sim_campaign`` builds them), so this
module stays clear of ``sims``.
"""
from __future__ import annotations

import json
import time

import numpy as np

from cellcal.config.model_files import write_calibrated
from cellcal.measurements.reader import read_measurements
from cellcal.measurements.writer import write_measurements
from cellcal.solvers.geometry import se3
from cellcal.solvers.analysis.analyze import AnalyzeOptions, analyze
from cellcal.solvers.compensation.calibrated_model import from_fit
from cellcal.solvers.compensation.compensate import OK, compensate
from cellcal.solvers.analysis.effects import approach_directions
from cellcal.solvers.identification.identify import IdentifyOptions, identify
from cellcal.solvers.identification.iso9283 import POSES, cube_points
from cellcal.cli import iso9283 as iso9283_cmd
from cellcal.cli.common import UsageError, print_progress
from cellcal.reports.iso9283 import write_report

CAUSES = ("joint_compliance", "backlash", "cyclic_joint_error", "parallel_axis_tilt")
DOWN = np.diag([1.0, -1.0, -1.0])  # tool axis along -z of the base


def run(args, arm, workspace, out) -> int:
    """arm: a PhysicalArm with the hidden effects; workspace(n, rng) -> n configurations."""
    t0 = time.perf_counter()
    model, rng = arm.model, arm.rng
    data = arm.campaign(workspace(args.poses, rng))
    write_measurements(out / "cal.csv", q_rad=data.obs.q, xyz_mm=data.obs.xyz_mm,
                       comment=f"{model.name}, simulated tracker campaign for ISO 9283, seed {args.seed}")
    table = read_measurements(out / "cal.csv", model.n_joints)
    obs = table.observations()
    finding = analyze(model, obs, type(data.ctx)(direction=approach_directions(obs.q)),
                      AnalyzeOptions(causes=CAUSES), progress=print_progress)
    scored = finding.both if finding.both is not None else finding.extended
    calibrated = from_fit(model, obs.target_names, scored.x, scored.terms, scored.theta, obs.q)
    nominal = from_fit(model, obs.target_names, identify(model, obs, IdentifyOptions(regularize="none")).x_nominal)
    record = {"written_by": "cellcal sim-campaign --iso9283", "command": "analyze"}
    write_calibrated(out / "calibrated.yaml", calibrated, args.robot, record, None)
    write_calibrated(out / "nominal.yaml", nominal, args.robot, {**record, "command": "identify (nominal)"})
    print_progress(f"calibrated: {finding.cause} {finding.where}; wrote {out / 'calibrated.yaml'} and "
                   f"{out / 'nominal.yaml'}")

    points, seed = _cube(nominal, workspace, rng)
    instrument = _to_instrument(nominal, points)  # the one physical cube, in the instrument frame
    cases = {}
    for name, cal in (("nominal", nominal), ("compensated", calibrated)):
        q = _joints(model, cal, _to_base(cal, instrument), seed)
        order = np.tile(np.arange(5), args.cycles)
        run_ = arm.campaign(q[order])
        write_measurements(out / f"iso_{name}.csv", q_rad=run_.obs.q, xyz_mm=run_.obs.xyz_mm,
                           extra={"pose": [POSES[i] for i in order], "cycle": list(np.repeat(np.arange(1, args.cycles + 1), 5))},
                           comment=f"{model.name}, ISO 9283 cube, {args.cycles} cycles, driven {name}")
        cases[name] = out / f"iso_{name}.csv"
    runs = [("before calibration", out / "nominal.yaml", cases["nominal"]),
            ("after calibration", out / "calibrated.yaml", cases["nominal"]),
            ("after compensation", out / "calibrated.yaml", cases["compensated"])]
    results, texts, summary = [], [], {}
    for label, robot, path in runs:
        _, pose, _, commanded, attained, poses, distance = iso9283_cmd.evaluate(robot, path)
        results.append((label, pose, commanded, attained, poses, distance))
        texts.append(iso9283_cmd.as_text(f"{label}: --robot {robot.name} --data {path.name}", poses, distance))
        summary[label] = iso9283_cmd.as_json(poses, distance)
    text = "\n\n".join(texts)
    page = write_report(out / "report", results, text)
    if args.json:
        print(json.dumps({"robot": model.name, "seed": args.seed, "cycles": args.cycles, "cause": finding.cause,
                          "cases": summary, "report": str(page), "seconds": time.perf_counter() - t0}))
    else:
        print(text)
        print(f"\n{'':22s}{'AP max mm':>12s}{'RP max mm':>12s}")
        for label, s in summary.items():
            print(f"{label:22s}{s['AP_max_mm']:12.4f}{s['RP_max_mm']:12.4f}")
        print(f"\nreport: {page}")
    return 0


def _to_base(cal, p_instrument):
    return (p_instrument - cal.base[:3]) @ se3.rotvec_to_matrix(cal.base[3:])


def _to_instrument(cal, p_base):
    return p_base @ se3.rotvec_to_matrix(cal.base[3:]).T + cal.base[:3]


def _cube(nominal, workspace, rng):
    """The test cube (robot base frame of ``nominal``) and a configuration on its branch: centre at
    half the reach in front of the robot, side a third of the reach, every point reachable with
    the tool pointing down on one branch."""
    q = workspace(400, rng)
    reach = float(np.linalg.norm(nominal.end_frames(q, nominal.offsets[0])[1][:, :2], axis=1).max())
    for scale in (1.0, 0.8, 0.6, 0.45):
        points = cube_points([0.5 * reach, 0.0, 0.25 * reach], scale * reach / 3.0)
        for start in q[:80]:
            seed = np.tile(start, (5, 1))
            out = compensate(nominal.model, nominal, points, np.repeat(DOWN[None], 5, 0), seed,
                             offset_mm=nominal.offsets[0])
            if np.all(out.status == OK):
                return points, out.q_nominal
    raise UsageError(f"{nominal.model.name}: no cube of the ISO 9283 test fits the workspace with the tool down")


def _joints(model, cal, points_base, seed):
    """Joints for the cube points: the controller's nominal inverse for the nominal case, compensated
    joints for the calibrated one (the calibrated model's inverse started from the nominal one)."""
    out = compensate(model, cal, points_base, np.repeat(DOWN[None], len(points_base), 0), seed,
                     offset_mm=cal.offsets[0])
    if not np.all(out.status == OK):
        raise RuntimeError(f"ISO 9283 cube: poses {', '.join(np.array(POSES)[out.status != OK])} not reachable")
    return out.q
