"""pybotics calibration on a data file: runs inside the bench-only pybotics venv.

Usage: ``python pybotics_baseline.py DATA.npz RESULT.json [--variants default,lm]``

This script imports only numpy, scipy and pybotics (which pins numpy<2), never
cellcal: ``pybotics_runner.py`` writes the data file in cellcal's environment and
starts this script with the venv's interpreter.

The calibration is pybotics' own: an ``OptimizationHandler`` over the robot's MDH
kinematic chain, tool and world frame with masks, ``optimize_accuracy`` as the
residual (one position error per pose) and ``scipy.optimize.least_squares``, as
pybotics' test of its optimisation module drives it. Variants:

* ``default``: least_squares' defaults (trf), as in pybotics' own test. Its relative
  ``xtol`` compares the step with the norm of the whole vector, which the world
  translation (metres, in mm) dominates, so it can stop while entries in radians are
  still moving;
* ``lm``: ``method="lm"`` (MINPACK), otherwise the same: pybotics' residual, driven
  to convergence, the form a careful pybotics user would end up with.

Data file keys (mm, rad):
    q_cal, xyz_cal, q_val, xyz_val   joints (N, dof) and measured positions (N, 3)
    mdh                              (dof, 4) rows [alpha, a, theta, d], pybotics' order
    kc_mask                          (4 dof,) bool, MDH parameters to optimise
    tool, world                      (4, 4) start tool (flange -> TCP) and world (instrument -> base)
    tool_mask, world_mask            (6,) bool over [x, y, z, Euler ZYX a, b, c]
    check_xyz                        (N, 3) cellcal's prediction at the start, to verify the mapping
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from importlib import metadata

import numpy as np
import scipy
import scipy.optimize
from pybotics.geometry import matrix_2_vector
from pybotics.kinematic_chain import MDHKinematicChain
from pybotics.optimization import OptimizationHandler, compute_absolute_errors, optimize_accuracy
from pybotics.robot import Robot
from pybotics.tool import Tool


def _stats(errors: np.ndarray) -> dict:
    return {"mean_mm": float(errors.mean()), "rms_mm": float(np.sqrt(np.mean(errors**2))),
            "max_mm": float(errors.max())}


VARIANTS = {"default": {}, "lm": {"method": "lm"}}


def _solve(robot: Robot, data, options: dict) -> dict:
    q_cal, xyz_cal = data["q_cal"], data["xyz_cal"]
    t0, c0 = time.perf_counter(), time.process_time()
    # the handler deep-copies the robot, so every variant starts from the same model
    handler = OptimizationHandler(robot=robot,
                                  kinematic_chain_mask=[bool(b) for b in data["kc_mask"]],
                                  tool_mask=[bool(b) for b in data["tool_mask"]],
                                  world_mask=[bool(b) for b in data["world_mask"]])
    x0 = handler.generate_optimization_vector()
    sol = scipy.optimize.least_squares(fun=optimize_accuracy, x0=x0,
                                       args=(handler, q_cal, xyz_cal), **options)
    # leave the handler's robot at the solution, not at the last probe of the solver
    handler.apply_optimization_vector(sol.x)
    seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
    cal = compute_absolute_errors(qs=q_cal, positions=xyz_cal, robot=handler.robot)
    val = compute_absolute_errors(qs=data["q_val"], positions=data["xyz_val"], robot=handler.robot)
    world = matrix_2_vector(handler.robot.world_frame)
    return {
        "options": options,
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "nfev": int(sol.nfev),
        "unknowns": int(len(x0)),
        "solver_status": int(sol.status),
        "solver_message": str(sol.message),
        "calibration": _stats(cal),
        "validation": _stats(val),
        "validation_errors_mm": val.tolist(),
        "world_euler_zyx_deg": np.rad2deg(world[3:]).tolist(),
    }


def calibrate(data, variants: list[str]) -> dict:
    robot = Robot(kinematic_chain=MDHKinematicChain(np.asarray(data["mdh"], dtype=float)),
                  tool=Tool(matrix=np.asarray(data["tool"], dtype=float)),
                  world_frame=np.asarray(data["world"], dtype=float))
    q_cal, xyz_cal = data["q_cal"], data["xyz_cal"]
    # the DH -> MDH mapping is exact, so pybotics must reproduce cellcal's start prediction
    start = np.array([robot.fk(q)[:3, 3] for q in q_cal])
    before = compute_absolute_errors(qs=q_cal, positions=xyz_cal, robot=robot)
    return {
        "status": "ok",
        "mapping_check_max_mm": float(np.abs(start - data["check_xyz"]).max()),
        "calibration_before": _stats(before),
        "variants": {name: _solve(robot, data, VARIANTS[name]) for name in variants},
        "versions": {"python": sys.version.split()[0], "numpy": np.__version__,
                     "scipy": scipy.__version__, "pybotics": metadata.version("pybotics")},
    }


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description="pybotics calibration on a cellcal data file")
    parser.add_argument("data", help=".npz written by pybotics_runner.py")
    parser.add_argument("result", help="JSON to write")
    parser.add_argument("--variants", default="default,lm",
                        help=f"comma-separated, of {', '.join(VARIANTS)} (default: %(default)s)")
    args = parser.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        parser.error(f"unknown variant(s) {', '.join(unknown)}")
    with np.load(args.data) as data:
        result = calibrate({k: data[k] for k in data.files}, variants)
    with open(args.result, "w", encoding="utf-8") as fh:
        json.dump(result, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
