"""Bench: the experiment that breaks a tie, against as many random poses, over 10 + 10 seeds.

    python -m bench.discriminate_bench [--seeds 10] [--poses 12]

A heavy arm (ABB IRB4600) measured one joint at a time (tests/hidden_cases.sweep_case)
hides compliance at the elbow in one set of seeds and a first-order cyclic error there in
the other. For each: does the first analysis report the pair as indistinguishable; how
many poses the design says suffice; and does the analysis of the sweeps plus the proposed
poses, measured on the same simulated arm, name the hidden cause at the elbow. The
baseline, in the same run: the sweeps plus as many random configurations over the
workspace (what a campaign without a design would add). Where the design itself says
more poses are needed (up to MAX_FOLLOWED), the analysis also runs with that many
designed poses: whether its count is worth following.
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
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.analysis.analyze import analyze
from cellcal.solvers.analysis.discriminate import design
from cellcal.solvers.analysis.effects import Context, approach_directions
from cellcal.solvers.identification.measurement_model import Observations

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.hidden_cases import SWEEP_ROBOT, elbow_pair, sweep_case  # noqa: E402  (a test fixture, not part of the package)

CAUSES = ("joint_compliance", "cyclic_joint_error")
ELBOW = 3  # 1-based, as the finding says it
MAX_FOLLOWED = 40  # poses measured when following the design's own count beyond --poses


def _with(first: Observations, second: Observations) -> tuple[Observations, Context]:
    q = np.concatenate([first.q, second.q])
    obs = Observations(q, np.concatenate([first.xyz_mm, second.xyz_mm]),
                       np.concatenate([first.target, second.target]), first.target_names)
    return obs, Context(approach_directions(q))


def _names(finding, cause: str) -> bool:
    return finding.cause == cause and finding.where.get("joint") == ELBOW


def one(model, cause: str, seed: int, n_poses: int) -> dict:
    arm, q = sweep_case(model, cause, seed)
    first = arm.campaign(q)
    started = time.perf_counter()
    finding = analyze(model, first.obs, first.ctx)
    analysis_s = time.perf_counter() - started
    tied = sorted(t.label for t in finding.indistinguishable)
    pair = elbow_pair([t.json() for t in finding.indistinguishable])
    row = {"cause": cause, "seed": seed, "first_cause": finding.cause, "tied": tied, "pair_tied": pair,
           "analysis_s": analysis_s}
    if len(finding.indistinguishable) < 2:
        return row
    started = time.perf_counter()
    plan = design(finding, first.ctx, n_poses, np.random.default_rng(seed))
    row["design_s"] = time.perf_counter() - started
    row["needed"] = plan.needed
    trials = [("designed", plan.q_rad), ("random", full_workspace(model, n_poses, np.random.default_rng(1000 + seed)))]
    if plan.needed is not None and n_poses < plan.needed <= MAX_FOLLOWED:  # as many as the design says suffice
        trials.append(("followed", design(finding, first.ctx, plan.needed, np.random.default_rng(seed)).q_rad))
    for name, q_new in trials:
        obs, ctx = _with(first.obs, arm.campaign(q_new).obs)
        again = analyze(model, obs, ctx)
        row[name] = {"cause": again.cause, "where": again.where, "named": _names(again, cause),
                     "margin_pct": 100.0 * again.margin, "poses": len(q_new)}
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--poses", type=int, default=12)
    args = ap.parse_args(argv)
    model = load_robot(SWEEP_ROBOT)
    rows = []
    with threadpool_limits(1):
        for cause in CAUSES:
            for seed in range(args.seeds):
                r = one(model, cause, seed, args.poses)
                rows.append(r)
                after = {k: (r[k]["cause"], r[k]["where"].get("joint")) for k in ("designed", "random") if k in r}
                print(f"{cause:20s} seed {seed}: first {r['first_cause']}, tied {r['tied']}, "
                      f"needed {r.get('needed')}, after: {after}", flush=True)
    print(f"\n{model.name}, one-joint-at-a-time sweeps ({len(rows) // len(CAUSES)} seeds per cause), "
          f"{args.poses} new poses:")
    print(f"{'hidden at the elbow':22s} {'tie reported':>12s} {'named (designed)':>17s} {'named (random)':>15s} "
          f"{'poses needed (median, max)':>27s} {'named, count followed':>21s}")
    summary = {}
    for cause in CAUSES:
        mine = [r for r in rows if r["cause"] == cause]
        needed = [r["needed"] for r in mine if r.get("needed") is not None]
        counts = {k: sum(1 for r in mine if r.get(k, {}).get("named")) for k in ("designed", "random")}
        # the design's own count followed where it asked for more than --poses, else the designed poses
        followed = sum(1 for r in mine if r.get("followed", r.get("designed", {})).get("named"))
        tied = sum(r["pair_tied"] for r in mine)
        summary[cause] = {"seeds": len(mine), "pair_tied": tied, **{f"named_{k}": v for k, v in counts.items()},
                          "needed": needed, "named_count_followed": followed}
        spread = f"{int(np.median(needed))}, {max(needed)}" if needed else "-"
        print(f"{cause:22s} {tied:>9d}/{len(mine)} {counts['designed']:>14d}/{len(mine)} "
              f"{counts['random']:>12d}/{len(mine)} {spread:>27s} {followed:>18d}/{len(mine)}")
    times = [r["analysis_s"] for r in rows]
    design_times = [r["design_s"] for r in rows if "design_s" in r]
    print(f"analysis of the sweeps {np.median(times):.2f} s median; design {np.median(design_times):.2f} s median"
          if design_times else "")
    out = Path(__file__).resolve().parent / "results" / "discriminate.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"summary": summary, "rows": rows}, indent=1, default=float))
    print(f"results: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
