"""``cellcal analyze``: explanations the data cannot tell apart, and ``--discriminate N -o POSES.csv``.

The poses file is what a measurement campaign reads: one row per configuration,
joint columns as the measurement CSV has them (``q1_rad … qN_rad``), most telling
first, each configuration to be measured at every target the data had. Measured,
its rows are appended to the data and the analysis run again.
"""
from __future__ import annotations

import csv

import numpy as np

from cellcal.solvers.analysis.analyze import Finding
from cellcal.measurements.table import MAX_PAYLOAD_KG
from cellcal.solvers.analysis.discriminate import Experiment, ExperimentError, design
from cellcal.cli.common import UsageError, number, print_progress, whole, writable_file

MAX_POSES = 1000  # an experiment to tell two explanations apart is a few dozen poses; 1000 is a long day's measuring


def add_arguments(p) -> None:
    p.add_argument("--discriminate", type=whole(1, MAX_POSES), metavar="N",
                   help="when the data cannot tell causes apart, propose N new configurations (within the "
                        "robot file's joint limits) that would, and say how many should suffice (N at most "
                        f"{MAX_POSES}); needs -o")
    p.add_argument("-o", "--output", metavar="POSES.csv",
                   help="with --discriminate: write the configurations here, one row each, columns "
                        "q1_rad .. qN_rad as in the measurement CSV, most telling first; measure each at every "
                        "target, append the rows to the data and analyse again")
    p.add_argument("--payload-kg", type=number(0.0, MAX_PAYLOAD_KG, above=True, unit="kg"), metavar="KG",
                   help="with --discriminate: a payload the cell can mount; each configuration is also offered "
                        "with it, and POSES.csv gets a payload_kg column saying which poses to measure with it "
                        f"(above 0, at most {MAX_PAYLOAD_KG:g})")


def check_arguments(args) -> None:
    """Before any computation: --discriminate and -o together, -o writable (N and the payload are
    bounded where they are parsed)."""
    if args.discriminate is None:
        if args.output is not None or args.payload_kg is not None:
            raise UsageError("-o/--output and --payload-kg belong to --discriminate N; give -o with it, "
                             "or none of them")
        return
    if args.output is None:
        raise UsageError("--discriminate N needs -o POSES.csv: the file to write the configurations to")
    writable_file(args.output, "-o")


def tie_lines(f: Finding) -> list[str]:
    """The text of a tie: the explanations, why each cannot be told apart, and what was named on what grounds."""
    if not f.indistinguishable:
        return []
    lines = ["", "indistinguishable -- these data cannot tell these explanations apart:"]
    for t in f.indistinguishable:
        lines.append(f"  {t.scored.heldout_mean_mm:8.4f}  {t.label}: {t.why}")
        if t.size:
            verdict = {True: "plausible", False: "implausible", None: "not judged"}[t.plausible]
            sizes = ", ".join(f"{k} {v:.3g}" for k, v in t.size.items()
                              if isinstance(v, (int, float)) and k != "effect_beyond_geometry_rms_mm")
            lines.append(f"            size it would need: {sizes} ({verdict})")
    if f.grounds:
        lines.append(f"  {f.grounds}")
    else:
        lines.append("  none is named: only a different experiment can decide "
                     "(--discriminate N -o POSES.csv proposes one)")
    return lines


def tie_json(f: Finding) -> dict:
    out = {"indistinguishable": [t.json() for t in f.indistinguishable]}
    if f.grounds:
        out["grounds"] = f.grounds
    return out


def run_design(args, finding: Finding, ctx, model) -> dict | None:
    """The experiment of --discriminate, written to -o; its summary for the JSON (None when not asked).
    A finding with nothing to tell apart writes no file and says so."""
    if args.discriminate is None:
        return None
    try:
        d = design(finding, ctx, args.discriminate, np.random.default_rng(0), payload_kg=args.payload_kg)
    except ExperimentError as exc:
        print_progress(f"--discriminate: {exc}; no poses written")
        return {"poses": 0, "file": None, "reason": str(exc)}
    write_poses(args.output, d, model)
    print_progress(d.summary())
    print_progress(f"poses written to {args.output}")
    return {"poses": len(d.q_rad), "file": str(args.output), "needed": d.needed, "models": list(d.models),
            "targets": list(d.target_names), "sigma_mm": d.sigma_mm,
            "separation_sigma": float(np.sqrt(d.lambda_cum[-1])), "miss_mm": d.miss_mm.tolist(),
            "payload_kg": None if d.payload_kg is None else d.payload_kg.tolist(), "summary": d.summary()}


def write_poses(path, d: Experiment, model) -> None:
    lines = [f"cellcal analyze --discriminate: {model.name}", d.summary(),
             f"measure each configuration at every target: {', '.join(d.target_names)}",
             "within the robot file's joint limits, the arm above its mounting plane; check reach, collisions and "
             "line of sight in the cell before measuring"]
    with open(path, "w", encoding="utf-8", newline="") as f:
        for text in lines:
            f.write(f"# {text}\n")
        out = csv.writer(f, lineterminator="\n")
        out.writerow([f"q{j}_rad" for j in range(1, model.n_joints + 1)]
                     + ([] if d.payload_kg is None else ["payload_kg"]))
        rows = d.q_rad if d.payload_kg is None else np.column_stack([d.q_rad, d.payload_kg])
        out.writerows([[repr(float(v)) for v in row] for row in rows])
