"""Kinematic identification bench: cellcal against a PSO baseline and pybotics.

One simulated campaign (ABB IRB4600, hidden errors +-0.5 mm / +-0.05 deg, AT960
tracker noise plus 0.05 mm repeatability: the ``SimulatedArm`` defaults; 150
full-workspace calibration poses, 300 validation poses) is solved by

* cellcal's ``identify`` with ``regularize="none"`` and ``"cv"``,
* the seed-000 particle swarm (``bench/pso.py``),
* pybotics' calibration in its own venv (``bench/pybotics_runner.py``),

each scored by the mean position error on the validation poses against the
oracle floor (the true model's error on the same measurements). Then cellcal's
time is measured on 150, 1 000 and 10 000 poses to show how it grows.

    python -m bench.identify_bench [--quick] [--seed N]

Progress goes to stderr, the table to stdout, the numbers to bench/results/identify.json.
Every method runs with one BLAS thread unless OPENBLAS_NUM_THREADS etc. say otherwise.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import asdict
from pathlib import Path

if __package__ in (None, ""):  # run as a file: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

# One BLAS thread for every method (pybotics' subprocess inherits it), set before numpy
# loads. On 2-core machines OpenBLAS' threads on these tall, narrow problems made
# identify() 3-10x slower at times and scattered its times 2x from run to run, so the
# comparison would measure thread scheduling, not the methods. One thread is steady.
BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
for _var in BLAS_THREAD_VARS:
    os.environ.setdefault(_var, "1")

import numpy as np
import scipy

from bench.pso import PSOConfig, run_pso, structural_mask
from bench.pybotics_runner import PyboticsUnavailable, run_pybotics
from cellcal.config.robot_files import load_robot
from cellcal.sims.physics.kinematic_arm import SimulatedArm
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.identification.identify import IdentifyOptions, identify, initial_base_and_targets
from cellcal.solvers.identification.measurement_model import Layout, Observations, predict

ROBOT = "abb-irb4600"
RESULTS = Path(__file__).resolve().parent / "results" / "identify.json"


def say(msg: str) -> None:
    print(f"[identify-bench] {msg}", file=sys.stderr, flush=True)


def stats(errors: np.ndarray) -> dict:
    return {"mean_mm": float(errors.mean()), "rms_mm": float(np.sqrt(np.mean(errors**2))),
            "max_mm": float(errors.max())}


def campaign(model, seed: int, n_cal: int, n_val: int):
    """The simulated arm and its calibration and validation measurements."""
    rng = np.random.default_rng(seed)
    arm = SimulatedArm(model, rng)
    q_cal = full_workspace(model, n_cal, rng)
    q_val = full_workspace(model, n_val, rng)
    return arm, arm.measure(q_cal), arm.measure(q_val)


def run_ours(model, cal: Observations, val: Observations, regularize: str, repeats: int = 1) -> dict:
    """identify() timed end to end (start, analysis, fits); median of `repeats` runs.

    The runs are deterministic, so repeating only steadies the clock for the
    sub-second cases.
    """
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        res = identify(model, cal, IdentifyOptions(regularize=regularize))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {"seconds": float(np.median(times)), "cpu_seconds": float(np.median(cpu)),
            "seconds_runs": times, "cpu_seconds_runs": cpu,
            "validation": stats(res.errors(val)),
            "calibration": stats(np.linalg.norm(res.residuals_mm, axis=1)),
            "lambda": res.lam, "kinematic_estimated": int(res.free[: res.layout.n_kin].sum()),
            "held_at_nominal": list(res.held_at_nominal)}


def run_swarm(layout: Layout, cal: Observations, val: Observations, cfg: PSOConfig) -> dict:
    say(f"PSO: {cfg.particles} particles x {cfg.iterations} iterations")
    res = run_pso(layout, cal, cfg, progress=say)
    errors = np.linalg.norm(predict(layout, res.x, val) - val.xyz_mm, axis=1)
    fitted = np.linalg.norm(predict(layout, res.x, cal) - cal.xyz_mm, axis=1)
    return {"seconds": res.seconds, "cpu_seconds": res.cpu_seconds,
            "validation": stats(errors), "calibration": stats(fitted),
            "iterations": res.iterations, "evaluations": res.evaluations,
            "dimensions": len(res.searched), "searched": list(res.searched),
            "best_at_box_edge": res.at_bound, "config": asdict(cfg),
            "history_every_10": res.history[::10].tolist() + [float(res.history[-1])]}


def run_pyb(layout: Layout, cal: Observations, val: Observations) -> dict:
    x_start = initial_base_and_targets(layout, cal)
    try:
        res = run_pybotics(layout, cal, val, x_start, structural_mask(layout, cal, x_start), say=say)
    except PyboticsUnavailable as exc:
        say(f"pybotics failed: {exc}")
        return {"status": "failed", "error": str(exc)}
    for variant in res["variants"].values():
        variant.pop("validation_errors_mm", None)  # the statistics are kept; the file stays small
    return res


def scaling(model, arm: SimulatedArm, val: Observations, sizes, modes, seed: int,
            repeats: int) -> list[dict]:
    """identify() time on growing campaigns from the same arm (median of `repeats` runs)."""
    rows = []
    for n in sizes:
        # a stream of its own, so the main comparison does not depend on the sizes asked for
        q = full_workspace(model, n, np.random.default_rng([seed, 1, n]))
        obs = arm.measure(q)
        for mode in modes:
            say(f"scaling: {n} poses, regularize={mode}")
            r = run_ours(model, obs, val, mode, repeats)
            rows.append({"poses": n, "regularize": mode, "seconds": r["seconds"],
                         "cpu_seconds": r["cpu_seconds"], "cpu_seconds_runs": r["cpu_seconds_runs"],
                         "cpu_seconds_per_pose": r["cpu_seconds"] / n,
                         "validation_mean_mm": r["validation"]["mean_mm"]})
    for mode in modes:
        mine = [r for r in rows if r["regularize"] == mode]
        for prev, r in zip([mine[0]] + mine[:-1], mine):
            # growth from the previous size: linear where the two ratios agree
            r["cpu_time_ratio"] = r["cpu_seconds"] / prev["cpu_seconds"]
            r["pose_ratio"] = r["poses"] / prev["poses"]
    return rows


def print_table(results: dict) -> None:
    floor = results["oracle_floor"]["mean_mm"]
    m = results["methods"]
    rows = [("cellcal regularize=none", m["ours_none"]), ("cellcal regularize=cv", m["ours_cv"]),
            (f"PSO {m['pso']['config']['particles']}x{m['pso']['iterations']}", m["pso"])]
    pyb = m["pybotics"]
    if pyb.get("status") == "ok":
        rows += [(f"pybotics ({name})", v) for name, v in pyb["variants"].items()]
    # ratios use CPU time: on a shared machine the wall clock also counts other people's work
    t_none, t_cv = m["ours_none"]["cpu_seconds"], m["ours_cv"]["cpu_seconds"]
    print(f"\nIRB4600, {results['config']['calibration_poses']} calibration / "
          f"{results['config']['validation_poses']} validation poses, seed {results['config']['seed']}")
    # cal rms: the fit on its own data, which shows whether a method's optimiser converged
    print(f"{'method':<26}{'wall s':>9}{'cpu s':>9}{'cal rms':>9}{'val mean':>10}{'val rms':>9}"
          f"{'val max':>9}{'/floor':>8}{'cpu/none':>10}{'cpu/cv':>9}")
    print(f"{'oracle floor':<26}{'':>9}{'':>9}{'':>9}{floor:>10.4f}{results['oracle_floor']['rms_mm']:>9.4f}"
          f"{results['oracle_floor']['max_mm']:>9.4f}{1.0:>8.3f}")
    for name, r in rows:
        v = r["validation"]
        print(f"{name:<26}{r['seconds']:>9.3f}{r['cpu_seconds']:>9.3f}{r['calibration']['rms_mm']:>9.4f}"
              f"{v['mean_mm']:>10.4f}{v['rms_mm']:>9.4f}{v['max_mm']:>9.4f}{v['mean_mm'] / floor:>8.3f}"
              f"{r['cpu_seconds'] / t_none:>10.1f}{r['cpu_seconds'] / t_cv:>9.1f}")
    if pyb.get("status") != "ok":
        print(f"pybotics: {pyb.get('status')}" + (f": {pyb['error']}" if "error" in pyb else ""))
    if results["scaling"]:
        print(f"\n{'poses':>7}{'regularize':>12}{'wall s':>9}{'cpu s':>9}{'cpu ms/pose':>13}{'x cpu':>8}"
              f"{'x poses':>9}{'val mean':>10}   (x: against the previous size)")
        for r in results["scaling"]:
            print(f"{r['poses']:>7}{r['regularize']:>12}{r['seconds']:>9.3f}{r['cpu_seconds']:>9.3f}"
                  f"{1000 * r['cpu_seconds_per_pose']:>13.3f}{r['cpu_time_ratio']:>8.2f}"
                  f"{r['pose_ratio']:>9.1f}{r['validation_mean_mm']:>10.4f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Kinematic identification bench (IRB4600)")
    p.add_argument("--seed", type=int, default=0, help="campaign and swarm seed (default 0)")
    p.add_argument("--quick", action="store_true",
                   help="smoke run: 20 PSO iterations, no pybotics, scaling on 150 and 1000 poses")
    p.add_argument("--cal", type=int, default=150, help="calibration poses (default 150)")
    p.add_argument("--val", type=int, default=300, help="validation poses (default 300)")
    p.add_argument("--pso-iterations", type=int, help="override Table 3's 500 iterations")
    p.add_argument("--no-pybotics", action="store_true", help="skip pybotics")
    p.add_argument("--scaling", default=None, help="pose counts for the scaling run, e.g. 150,1000,10000; "
                   "empty to skip (default 150,1000,10000; 150,1000 with --quick)")
    p.add_argument("--no-cv-scaling", action="store_true", help="scale regularize=none only")
    p.add_argument("--repeats", type=int, default=3, help="timed runs of each cellcal case (median)")
    p.add_argument("--out", type=Path, default=RESULTS, help=f"JSON output (default {RESULTS})")
    args = p.parse_args(argv)
    iterations = args.pso_iterations or (20 if args.quick else 500)
    sizes_text = args.scaling if args.scaling is not None else ("150,1000" if args.quick else "150,1000,10000")
    sizes = [int(s) for s in sizes_text.split(",") if s.strip()]

    load_start = os.getloadavg()  # other work on the machine skews every time below
    model = load_robot(ROBOT)
    arm, cal, val = campaign(model, args.seed, args.cal, args.val)
    layout = Layout(model, cal.target_names)
    floor = arm.oracle_errors(val)
    say(f"{model.name}: {len(cal)} calibration, {len(val)} validation poses; "
        f"oracle floor {floor.mean():.4f} mm")
    methods = {}
    for mode in ("none", "cv"):
        say(f"cellcal identify, regularize={mode}")
        methods[f"ours_{mode}"] = run_ours(model, cal, val, mode, args.repeats)
    methods["pso"] = run_swarm(layout, cal, val, PSOConfig(iterations=iterations, seed=args.seed))
    if args.quick or args.no_pybotics:
        methods["pybotics"] = {"status": "skipped"}
    else:
        methods["pybotics"] = run_pyb(layout, cal, val)

    floor_mean = float(floor.mean())
    timed = {k: v for k, v in methods.items() if "seconds" in v}
    if methods["pybotics"].get("status") == "ok":
        timed.update({f"pybotics_{k}": v for k, v in methods["pybotics"]["variants"].items()})
    ratios = {name: {"error_vs_floor": r["validation"]["mean_mm"] / floor_mean,
                     "cpu_time_vs_ours_none": r["cpu_seconds"] / methods["ours_none"]["cpu_seconds"],
                     "cpu_time_vs_ours_cv": r["cpu_seconds"] / methods["ours_cv"]["cpu_seconds"],
                     "wall_time_vs_ours_none": r["seconds"] / methods["ours_none"]["seconds"],
                     "wall_time_vs_ours_cv": r["seconds"] / methods["ours_cv"]["seconds"]}
              for name, r in timed.items()}
    modes = ("none",) if args.no_cv_scaling else ("none", "cv")
    results = {
        "config": {"robot": model.name, "seed": args.seed, "calibration_poses": len(cal),
                   "validation_poses": len(val), "quick": args.quick,
                   "true_errors": "+-0.5 mm lengths, +-0.05 deg angles (uniform)",
                   "noise": "AT960 0.015 mm + 6 um/m per axis (1 sigma) + 0.05 mm repeatability"},
        "oracle_floor": stats(floor),
        "methods": methods,
        "ratios": ratios,
        "scaling": scaling(model, arm, val, sizes, modes, args.seed, args.repeats) if sizes else [],
        "environment": {"python": platform.python_version(), "numpy": np.__version__,
                        "scipy": scipy.__version__, "machine": platform.machine(),
                        "cpus": os.cpu_count(), "command": " ".join(sys.argv),
                        "blas_threads": {v: os.environ.get(v) for v in BLAS_THREAD_VARS},
                        "load_average_1_5_15_min": {"start": load_start, "end": os.getloadavg()}},
    }
    print_table(results)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1), encoding="utf-8")
    say(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
