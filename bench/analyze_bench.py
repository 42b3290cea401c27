"""Bench: discrepancy analysis of 500 poses with every candidate, time per candidate.

    python -m bench.analyze_bench [--poses 500] [--seed 0] [--justin-only]

For each robot, one data set with a hidden effect (compliance at the elbow, 4x the
noise): total analysis time, the number of candidates scored, seconds per candidate,
and the naive alternative measured in the same run: every candidate refitted with
nonlinear least squares in every cross-validation fold (what the linearised scoring
replaces), extrapolated from a timed sample of candidates. Then the Agile Justin data, the
elastic mount's pivot shift off (the baseline) and on, CPU seconds and held-out mean of each.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from cellcal.config.robot_files import load_robot
from cellcal.sims.physics.physical_arm import HiddenEffect
from cellcal.solvers.estimation import crossval
from cellcal.solvers.analysis.analyze import NEIGHBOUR_RAD, AnalyzeOptions, analyze
from cellcal.solvers.analysis.extended_model import fit_extended

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.hidden_cases import make_case  # noqa: E402  (a test fixture, not part of the package)

ROBOTS = ("ur10e", "abb-irb4600", "elite-ec66")


def naive_seconds_per_candidate(model, case, finding, sample=3):
    """Refit geometry + term nonlinearly in each of 5 folds for a few candidates."""
    obs = case.campaign.obs
    folds = crossval.fold_ids(obs.q, 5, 0, NEIGHBOUR_RAD)
    geo = finding.baseline
    from cellcal.solvers.identification.identify import IdentifyOptions, identify

    base = identify(model, obs, IdentifyOptions(regularize="none"))
    terms = [c.terms[0] for c in finding.candidates if c.terms and c.terms[0].model is None][:sample]
    t0 = time.perf_counter()
    for term in terms:
        for f in range(5):
            rows = np.flatnonzero(folds != f)
            sub = obs.subset(rows)
            sub_term = term.__class__(**{**term.__dict__,
                                         "joint_basis": None if term.joint_basis is None else term.joint_basis[rows],
                                         "cart_basis": None if term.cart_basis is None else term.cart_basis[rows],
                                         "param_basis": None if not term.param_basis else
                                         {p: b[rows] for p, b in term.param_basis.items()}})
            fit_extended(base.layout, sub, geo.x, base.free, (sub_term,), prior_mm=1.0)
    return (time.perf_counter() - t0) / max(len(terms), 1)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--justin-only", action="store_true", help="only the Agile Justin data")
    args = parser.parse_args(argv)
    rows = []
    with threadpool_limits(limits=1, user_api="blas"):
        for i, robot in enumerate(() if args.justin_only else ROBOTS):
            model = load_robot(robot)
            case = make_case(model, [HiddenEffect("joint_compliance", 2)], [4.0], n=args.poses, seed=args.seed + i)
            t0 = time.perf_counter()
            finding = analyze(model, case.campaign.obs, case.campaign.ctx, AnalyzeOptions())
            total = time.perf_counter() - t0
            n = len(finding.candidates)
            naive = naive_seconds_per_candidate(model, case, finding)
            rows.append({"robot": model.name, "poses": args.poses, "candidates": n, "seconds": total,
                         "seconds_per_candidate": total / n, "naive_seconds_per_candidate": naive,
                         "speedup_per_candidate": naive / (total / n), "finding": finding.cause,
                         "where": finding.where, "gain_pct": finding.gain_pct})
            print(f"{model.name:22s} {n:3d} candidates  {total:6.2f} s  {1000 * total / n:7.1f} ms/candidate  "
                  f"naive {1000 * naive:8.1f} ms/candidate ({naive / (total / n):5.1f}x)  "
                  f"-> {finding.cause} {finding.where}", file=sys.stderr)
        justin = Path(__file__).resolve().parents[2] / "shared" / "data" / "dlr-agile-justin" / "measurements.csv"
        if justin.exists():  # the real data set: 500 poses x 2 markers on a tree
            from cellcal.measurements.importers import dlr_justin
            from cellcal.solvers.analysis.effects import Context, approach_directions
            from cellcal.solvers.identification.measurement_model import Observations

            fields = dlr_justin(justin)
            obs = Observations(fields["q_rad"], fields["xyz_mm"], fields["target"], fields["target_names"])
            model = load_robot("agile-justin")
            # baseline in the same run: the geometric calibration alone, the first step of the analysis
            from cellcal.solvers.identification.identify import IdentifyOptions, identify

            c0 = time.process_time()
            identify(model, obs, IdentifyOptions(regularize="cv"))
            geometric_cpu = time.process_time() - c0
            # the elastic mount's pivot shift off (the baseline, as before it was offered) and on, same run
            from cellcal.solvers.analysis.effects import elastic_mount

            for shift in (False, True):
                elastic_mount.PIVOT_SHIFT = shift
                t0, c0 = time.perf_counter(), time.process_time()
                finding = analyze(model, obs, Context(approach_directions(obs.q)))
                total, cpu = time.perf_counter() - t0, time.process_time() - c0
                n = len(finding.candidates)
                name = f"{model.name} ({'with' if shift else 'without'} pivot shift)"
                rows.append({"robot": name, "poses": len(obs) // 2, "candidates": n, "seconds": total,
                             "cpu_seconds": cpu, "geometric_cpu_seconds": geometric_cpu,
                             "seconds_per_candidate": total / n, "naive_seconds_per_candidate": float("nan"),
                             "speedup_per_candidate": float("nan"), "finding": finding.cause,
                             "where": finding.where, "gain_pct": finding.gain_pct,
                             "heldout_mean_mm": [finding.baseline.heldout_mean_mm,
                                                 finding.extended.heldout_mean_mm]})
                print(f"{name:22s} {n:3d} candidates  {total:6.2f} s ({cpu:.2f} s CPU, budget 10 s; geometric "
                      f"calibration alone {geometric_cpu:.2f} s CPU, {cpu / geometric_cpu:.1f}x)  held-out "
                      f"{finding.baseline.heldout_mean_mm:.3f} -> {finding.extended.heldout_mean_mm:.3f} mm",
                      file=sys.stderr)
            elastic_mount.PIVOT_SHIFT = True
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    name = "analyze_justin.json" if args.justin_only else "analyze.json"
    (out / name).write_text(json.dumps(rows, indent=1) + "\n")
    print(f"{'robot':22s} {'poses':>5s} {'cand.':>5s} {'total s':>8s} {'ms/cand':>8s} {'naive ms':>9s} {'ratio':>6s}")
    for r in rows:
        print(f"{r['robot']:22s} {r['poses']:5d} {r['candidates']:5d} {r['seconds']:8.2f} "
              f"{1000 * r['seconds_per_candidate']:8.1f} {1000 * r['naive_seconds_per_candidate']:9.1f} "
              f"{r['speedup_per_candidate']:6.1f}")
    if not rows:
        return 0
    worst = max(rows, key=lambda r: r["seconds"])
    print(f"slowest analysis: {worst['robot']}, {worst['poses']} poses, {worst['seconds']:.1f} s "
          f"(budget 30 s for 500 poses)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
